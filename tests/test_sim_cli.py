"""``swarm sim`` as a user runs it: readiness lines, a plain pymavlink client, signals, bad input."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import net_helpers
import pytest
from pymavlink import mavutil

pytestmark = pytest.mark.processes  # swarm sim processes


def run(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "swarm.cli", "sim", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def free_port(kind: int) -> int:
    return net_helpers.free_port("udp" if kind == socket.SOCK_DGRAM else "tcp")


@pytest.mark.timing  # exit within 5 s of SIGTERM
def test_ready_lines_client_and_sigterm() -> None:
    base = free_port(socket.SOCK_STREAM)
    p = run("--vehicles", "2", "--profile", "ardupilot", "--base-port", str(base), "--speedup", "2")
    try:
        assert p.stdout is not None
        lines = [p.stdout.readline() for _ in range(2)]
        assert lines[0].startswith("vehicle 1 sysid=1 ardupilot tcp -> tcp:127.0.0.1:")
        assert "home=" in lines[0]
        assert f"tcp:127.0.0.1:{base + 10}" in lines[1]
        c = mavutil.mavlink_connection(f"tcp:127.0.0.1:{base + 10}", source_system=255)
        hb = c.wait_heartbeat(timeout=10)
        assert hb is not None and hb.get_srcSystem() == 2 and hb.autopilot == 3
        c.close()
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=10) == 0
        assert time.monotonic() - t0 < 5.0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_sigint_px4() -> None:
    p = run("--vehicles", "1", "--base-port", str(free_port(socket.SOCK_DGRAM)))
    assert p.stdout is not None
    assert "px4 udp -> udpin:127.0.0.1:" in p.stdout.readline()
    p.send_signal(signal.SIGINT)
    assert p.wait(timeout=10) == 130  # interrupted (issue 18: one exit-code rule)


def test_bad_input_exit_2_without_traceback() -> None:
    base = free_port(socket.SOCK_STREAM)
    held = socket.socket()
    held.bind(("127.0.0.1", base))
    held.listen(1)
    try:
        for args in (
            ["--vehicles", "2", "--home", "91,8,400"],
            ["--vehicles", "2", "--home", "nope"],
            ["--vehicles", "0"],
            ["--vehicles", "1", "--speedup", "0"],
            ["--vehicles", "1", "--profile", "ardupilot", "--base-port", str(base)],
        ):
            p = run(*args)
            _, err = p.communicate(timeout=20)
            assert p.returncode == 2, (args, err)
            assert "Traceback" not in err and err.startswith("swarm sim: error:"), err
            assert len(err.strip().splitlines()) == 1
    finally:
        held.close()


def test_home_accepts_a_negative_latitude_as_written() -> None:
    """``--home -35.36,149.16,584`` (southern hemisphere) parses as a value, not as an option."""
    from swarm.cli.commands.sim import build_parser, join_negative_values

    for argv in (
        ["--vehicles", "1", "--home", "-35.363261,149.16523,584"],
        ["--vehicles", "2", "--home", "-35.36,-149.1,-5"],
    ):
        args = build_parser().parse_args(join_negative_values(argv))
        assert args.home == argv[argv.index("--home") + 1]
    # a value that is not a number stays an option (argparse reports it as usual)
    assert join_negative_values(["--home", "--vehicles", "1"]) == ["--home", "--vehicles", "1"]


@pytest.mark.processes
def test_home_negative_latitude_prints_the_southern_home() -> None:
    p = run(
        "--vehicles",
        "1",
        "--profile",
        "ardupilot",
        "--base-port",
        str(free_port(socket.SOCK_STREAM)),
        "--home",
        "-35.363261,149.16523,584",
    )
    try:
        assert p.stdout is not None
        assert "home=-35.3632610,149.1652300,584.0" in p.stdout.readline()
    finally:
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=10) == 130
