"""One exit-code rule for every ``swarm`` subcommand (issue 18): 0 ok, 1 failure,
2 bad usage or input, 130 interrupted.

Bad input runs each command in this process (quick). Interruption sends a real
SIGINT: to this process while a batch command (simulate, bench) computes, and to
a started node process (agent, gcs, radio-emu, sim) once it printed its ready
line; SIGTERM, a service manager's orderly stop, is 0 (the node tests check it).
"""

from __future__ import annotations

import importlib
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import net_helpers
import pytest

from swarm.cli import COMMANDS
from swarm.cli import main as swarm_main

TEXT = "a text file, not a capture\n" * 10

# command -> arguments that are bad input ("{text}": a text file, "{dir}": a fresh folder)
BAD_INPUT: dict[str, list[str]] = {
    "radio-emu": ["--nodes", "0", "--dir", "{dir}"],
    "radio-config": ["{dir}/no-such-tty", "--show"],
    "replay": ["{text}"],
    "sim": ["--vehicles", "0"],
    "agent": ["--name", "a1", "--id", "1"],  # no way in
    "simulate": ["--agents", "0"],
    "gcs": ["--replay", "{text}"],
    "router": ["--listen", "tcp/127.0.0.1:notaport"],
    "demo": ["--agents", "0"],
    "bench": ["no-such-area"],
    "config": ["example", "no-such-command"],
    "keygen": ["{dir}/no-such-folder/swarm.key"],
    "certs": ["node", "{dir}", "agent1", "--role", "agent"],  # no CA in that folder
    "service": ["print", "no-such-kind"],
    "doctor": ["--id", "0"],
    "tiles": [
        "fetch",
        "--url",
        "https://tile.openstreetmap.org/{{z}}/{{x}}/{{y}}.png",
        "--bounds",
        "1,1,2,2",
        "--zoom",
        "1",
        "--out",
        "{dir}/x.mbtiles",
        "--yes",
    ],
}


def test_every_command_has_a_bad_input_case() -> None:
    assert set(BAD_INPUT) == set(COMMANDS)


@pytest.mark.parametrize("command", sorted(BAD_INPUT))
def test_bad_input_exits_2_with_one_line(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = tmp_path / "notes.tlog"
    text.write_text(TEXT)
    argv = [x.format(text=text, dir=tmp_path) for x in BAD_INPUT[command]]
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        code = swarm_main([command, *argv])
    except SystemExit as exc:  # argparse's own usage errors leave as the process would
        code = exc.code
    assert code == 2
    # run in-process, a command leaves Ctrl-C as it found it (the router's stop flag
    # once kept SIGINT, and a later command in the same process could not be stopped)
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error" in err
    assert err.strip().splitlines()[-1].startswith(("swarm", "usage")), err


def _interrupt_soon(after: float) -> threading.Timer:
    timer = threading.Timer(after, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    return timer


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "--agents", "50", "--seeds", "100000", "--jobs", "1"],
        ["bench", "simulate", "--quick"],
    ],
    ids=["simulate", "bench"],
)
def test_sigint_in_a_batch_command_exits_130(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    module = importlib.import_module(f"swarm.cli.commands.{COMMANDS[argv[0]][0]}")
    before = signal.getsignal(signal.SIGINT)
    timer = _interrupt_soon(0.5)  # well inside the run: it takes minutes
    try:
        assert module.main(argv[1:]) == 130
    finally:
        timer.join()
        signal.signal(signal.SIGINT, before)
    assert "Traceback" not in capsys.readouterr().err


def _node_argv(command: str, tmp_path: Path) -> tuple[list[str], str]:
    """The command line of a node and the text its ready line holds."""
    port = net_helpers.free_port()
    if command == "agent":
        return ["agent", "--name", "a1", "--id", "1", "--zenoh-listen", f"tcp/127.0.0.1:{port}"], "ready"
    if command == "gcs":
        return ["gcs", "--zenoh-listen", f"tcp/127.0.0.1:{port}", "--http", "127.0.0.1:0"], "ready"
    if command == "radio-emu":
        return ["radio-emu", "--nodes", "2", "--dir", str(tmp_path)], "radio1 "
    return ["sim", "--vehicles", "1", "--base-port", str(net_helpers.free_port("udp"))], "ready:"


@pytest.mark.processes
@pytest.mark.parametrize("command", ["agent", "gcs", "radio-emu", "sim"])
def test_sigint_in_a_node_exits_130(command: str, tmp_path: Path) -> None:
    argv, ready = _node_argv(command, tmp_path)
    p = subprocess.Popen(
        [sys.executable, "-m", "swarm.cli", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert p.stdout is not None
        seen = []
        for line in p.stdout:  # the ready line: the command's handlers are in place
            seen.append(line)
            if ready in line:
                break
        assert any(ready in line for line in seen), seen
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=30)
        assert p.returncode == 130, err
        assert "Traceback" not in err
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
