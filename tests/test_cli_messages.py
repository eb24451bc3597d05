"""Library errors as one line a user understands, and the people's text of
``swarm simulate`` (issue 18). Real Zenoh, real files; no process is started
except where a command's own loop is what is tested."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import net_helpers
import pytest

from swarm.cli.commands.gcs import main as gcs_main
from swarm.cli.commands.replay import main as replay_main
from swarm.cli.commands.sim import main as sim_main
from swarm.cli.commands.simulate import main as simulate_main
from swarm.cli.commands.simulate import text_report
from swarm.cli.util import PeerWatch
from swarm.core.keyspace.zenoh_errors import zenoh_open_message
from swarm.errors import TransportError
from swarm.runtime.keyspace.transport import open_session, session_config

DEMO = Path(__file__).parent / "data" / "demo" / "demo.tlog"


def test_zenoh_port_in_use_is_one_plain_line() -> None:
    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    held.listen(1)
    port = held.getsockname()[1]
    try:
        with pytest.raises(TransportError) as caught:
            open_session(listen=[f"tcp/127.0.0.1:{port}"])
    finally:
        held.close()
    msg = str(caught.value)
    ep = f"tcp/127.0.0.1:{port}"
    assert msg == f"cannot listen on {ep}: port {port} in use (another program, or another swarm node?)"


def test_zenoh_other_errors_lose_their_rust_source_paths() -> None:
    raw = (
        "Can not create a new TCP listener bound to tcp/10.9.9.9:7447: [10.9.9.9:7447: Some new error "
        "(os error 77) at /root/.cargo/git/checkouts/zenoh-x/io/tcp.rs:61.]"
        " at /root/.cargo/git/z/unicast.rs:338."
    )
    msg = zenoh_open_message(raw, ["tcp/10.9.9.9:7447"], [])
    assert ".rs" not in msg and ".cargo" not in msg and "[" not in msg
    assert msg.endswith("Some new error (os error 77)")


def test_zenoh_bad_endpoint_is_its_own_sentence_without_rust_wrapping() -> None:
    with pytest.raises(TransportError) as caught:
        session_config(listen=["bogus"])
    msg = str(caught.value)
    assert msg.startswith("bad Zenoh endpoint: Endpoints must be of the form <protocol>/<address>")
    assert ".rs" not in msg and "Json5Err" not in msg and "location" not in msg
    assert msg.endswith(": bogus (for example tcp/127.0.0.1:7447)")


def test_gcs_http_port_in_use_is_one_plain_line(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        argv = ["--zenoh-listen", f"tcp/127.0.0.1:{net_helpers.free_port()}", "--http", f"127.0.0.1:{port}"]
        assert gcs_main(argv) == 2
    err = capsys.readouterr().err
    why = f"port {port} in use (another program, or another station?)"
    assert err == f"swarm gcs: error: cannot listen on 127.0.0.1:{port}: {why}\n"


def test_sim_serial_missing_device_says_errno_once(capsys: pytest.CaptureFixture[str]) -> None:
    assert sim_main(["--vehicles", "1", "--serial", "/nonexistent/tty"]) == 2
    err = capsys.readouterr().err
    assert (
        err == "swarm sim: error: cannot open serial device '/nonexistent/tty': No such file or directory\n"
    )


def test_truncated_capture_plot_says_no_samples_not_none(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(DEMO.read_bytes()[:20000])  # ends before the formation settles, mid-record
    assert replay_main([str(cut), "--plot", str(tmp_path / "p.png")]) == 2  # a damaged file: bad input
    out, err = capsys.readouterr()
    assert "None" not in out and "n/a, 0 samples" in out  # no figures, said so
    assert err.startswith("swarm replay: error: ") and "truncated" in err and len(err.splitlines()) == 1


def test_peer_watch_warns_once_then_says_connected() -> None:
    w = PeerWatch(["tcp/10.0.0.2:7447"], now=0.0, grace=3.0)
    assert [w.update(False, t) for t in (0.5, 2.9)] == [None, None]
    assert w.update(False, 3.0) == "warning: no Zenoh peer reachable at tcp/10.0.0.2:7447; still trying"
    assert w.update(False, 10.0) is None  # once
    assert w.update(True, 11.0) == "connected to a Zenoh peer (tcp/10.0.0.2:7447)"
    assert w.update(True, 12.0) is None
    assert w.update(False, 20.0) is None and w.update(False, 23.0) is not None  # lost: said again
    quiet = PeerWatch(["tcp/10.0.0.2:7447"], now=0.0)
    assert quiet.update(True, 0.5) is None  # reached at once: nothing to say


@pytest.mark.processes
def test_gcs_zenoh_connect_to_a_closed_port_says_so_then_connects(tmp_path: Path) -> None:
    port = net_helpers.free_port()  # nobody listens there (yet)
    argv = ["gcs", "--zenoh-connect", f"tcp/127.0.0.1:{port}", "--http", "127.0.0.1:0"]
    gcs = subprocess.Popen(
        [sys.executable, "-m", "swarm.cli", *argv],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    peer = None
    try:
        assert gcs.stderr is not None
        t0 = time.monotonic()
        line = gcs.stderr.readline()
        assert line == f"swarm gcs: warning: no Zenoh peer reachable at tcp/127.0.0.1:{port}; still trying\n"
        assert time.monotonic() - t0 < 30  # generous: said within seconds, not never
        peer = open_session(listen=[f"tcp/127.0.0.1:{port}"])
        assert gcs.stderr.readline() == f"swarm gcs: connected to a Zenoh peer (tcp/127.0.0.1:{port})\n"
    finally:
        gcs.terminate()
        gcs.communicate(timeout=30)
        if peer is not None:
            peer.close()


FAILING_RUN = {
    "agents": 3,
    "profile": "paper",
    "loss": 0.5,
    "runs": 3,
    "converged": 1,
    "stable_at_end": 3,
    "violations": 2,
    "elect_s": {"p50": 7.778, "p95": 7.782, "max": 7.782},
    "air_utilisation": {"p50": 0.073, "max": 0.079},
    "messages_per_agent": {"p50": 30.333},
    "round_s": 0.3552,
    "failing": [
        {"seed": 1, "violations": ["two leaders at 3.0 s"], "replay": "swarm simulate --seed 1"},
        {"seed": 2, "violations": ["never converged"], "replay": "swarm simulate --seed 2"},
    ],
}


def test_simulate_text_is_for_people() -> None:
    text = text_report(FAILING_RUN)
    assert "{" not in text and "'" not in text  # no Python dicts
    assert "converged             1 of 3 runs" in text and "stable at the end     3 of 3 runs" in text
    assert "election time         p50 7.778 s, p95 7.782 s, max 7.782 s" in text
    assert "air time used         p50 7.3 %, max 7.9 %" in text
    for seed in (1, 2):
        assert text.count(f"swarm simulate --seed {seed}") == 1


def test_simulate_lists_each_replay_command_once(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--agents", "3", "--seeds", "3", "--loss", "0.5", "--duration", "11", "--jobs", "1"]
    assert simulate_main(argv) == 1  # seed 2 does not converge within 11 s at this loss
    out, err = capsys.readouterr()
    replay = "swarm simulate --agents 3 --seeds 1 --seed 2"
    assert (out + err).count(replay) == 1 and "{" not in out
    assert err == ""  # not a terminal: no progress line either


def test_demo_on_a_busy_http_port_exits_2_before_it_flies(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``swarm demo --http`` on a port another program holds: exit 2 with one line,
    before anything starts (it once flew the whole demo without its station)."""
    from swarm.cli.commands.demo import main as demo_main

    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    held.listen(1)
    port = held.getsockname()[1]
    work = tmp_path / "demo"
    try:
        code = demo_main(["--agents", "2", "--headless", "--http", f"127.0.0.1:{port}", "--dir", str(work)])
    finally:
        held.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and f"port {port} in use" in err[0] and "--no-gcs" in err[0], err
    assert not work.exists() or not any(work.iterdir())  # refused first: nothing was started


def test_demo_on_an_address_not_of_this_machine_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    from swarm.cli.commands.demo import main as demo_main

    assert demo_main(["--agents", "2", "--headless", "--http", "192.0.2.1:8080"]) == 2  # TEST-NET-1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "192.0.2.1" in err[0] and "not an address of this machine" in err[0], err
