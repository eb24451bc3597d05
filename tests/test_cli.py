"""The plumbing every ``swarm`` subcommand shares: the one guard that turns the three
packages' errors into one line and an exit code, the node options declared and
checked once, and the global log options (``-v``, ``--log-level``).

The log test runs real agents as processes over real Zenoh on loopback and waits
for outcomes (their output lines) with generous deadlines.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable

import pytest
from net_helpers import free_port, wait_until

from firmware_bridge.errors import BridgeError, CommandTimeout, ConnectError, HeartbeatTimeout, SetpointError
from radios.errors import ATError, ConfigError, LinkClosedError, LinkOpenError, LinkTimeoutError, RadioError
from swarm.cli import main as swarm_main
from swarm.cli.demo import DemoError
from swarm.cli.procs import Child, ChildError
from swarm.cli.util import UsageError, add_node_arguments, guarded, node_options
from swarm.errors import DecodeError, MessageError, SwarmError, TransportError
from swarm.runtime.options import AgentConfig, NodeOptions


def _raising(exc: BaseException) -> Callable[[list[str] | None], int]:
    @guarded("swarm test")
    def main(argv: list[str] | None = None) -> int:
        raise exc

    return main


@pytest.mark.parametrize(
    "exc, code",
    [
        # bad input: exit 2
        (UsageError("--id 0: agent ids are 1..250"), 2),
        (ConfigError("AIR_SPEED=7 is not a valid value"), 2),
        (LinkOpenError("/dev/ttyUSB9: no such device"), 2),
        (ConnectError("udpin:bad: not a flight-controller URL"), 2),
        (TransportError("bad Zenoh endpoint configuration"), 2),
        # failures: exit 1 (a timeout is never the user's input, even a ConnectError)
        (HeartbeatTimeout("no heartbeat in 10 s"), 1),
        (LinkTimeoutError("write timed out"), 1),
        (LinkClosedError("the radio went away"), 1),
        (ATError("the radio answered ERROR"), 1),
        (RadioError("radio"), 1),
        (BridgeError("the autopilot link is lost"), 1),
        (CommandTimeout("no COMMAND_ACK"), 1),
        (SetpointError("NaN latitude"), 1),
        (SwarmError("swarm"), 1),
        (DecodeError("not a swarm message"), 1),
        (MessageError("bad field"), 1),
        (ChildError("agent1 exited with 1"), 1),
        (DemoError("timed out waiting for a leader"), 1),
    ],
)
def test_one_guard_knows_every_package_root(
    exc: Exception, code: int, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before the guard knew only RadioError, a BridgeError or a SwarmError reached the
    user as a traceback (and ChildError/DemoError had to pretend to be radio errors)."""
    assert _raising(exc)([]) == code
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"swarm test: error: {exc}"] and captured.out == ""


def test_the_demo_and_child_errors_are_swarm_errors() -> None:
    assert issubclass(DemoError, SwarmError) and issubclass(ChildError, SwarmError)
    assert not issubclass(DemoError, RadioError) and not issubclass(ChildError, RadioError)
    assert issubclass(UsageError, SwarmError)


def test_a_bug_is_not_hidden() -> None:
    """Only the errors raised on purpose are one line: anything else is a bug."""
    with pytest.raises(ZeroDivisionError):
        _raising(ZeroDivisionError("a bug"))([])


def test_interrupt_and_closed_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    assert _raising(KeyboardInterrupt())([]) == 130
    assert _raising(BrokenPipeError())([]) == 1
    assert capsys.readouterr().err == ""


# -- the node options, declared and checked once ------------------------------------


def _node_args(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_node_arguments(p)
    return p.parse_args(list(argv))


def test_node_options_from_the_command_line() -> None:
    n = node_options(_node_args("--radio", "/tmp/radios/radio0", "--key", "k.txt"), "an agent")
    assert n == NodeOptions(radio="/tmp/radios/radio0", key_file="k.txt")
    assert n.on_radio and not n.on_zenoh and n.describe() == "radio=/tmp/radios/radio0"
    z = node_options(
        _node_args("--zenoh-listen", "tcp/127.0.0.1:7447", "--zenoh-connect", "tcp/a:1", "tcp/b:2"),
        "an agent",
    )
    assert z.zenoh_connect == ("tcp/a:1", "tcp/b:2")
    assert z.describe() == "zenoh listen=tcp/127.0.0.1:7447 connect=tcp/a:1,tcp/b:2"


@pytest.mark.parametrize(
    "argv, match",
    [
        ((), "give one of --radio URL, --zenoh-listen/--zenoh-connect EP..."),
        (("--radio", "x", "--zenoh-listen", "tcp/127.0.0.1:1"), "give one of"),
        (("--radio", "x", "--zenoh-connect", "tcp/127.0.0.1:1"), "give one of"),
        (
            ("--zenoh-listen", "tcp/127.0.0.1:1", "--exit-on-radio-loss"),
            "--exit-on-radio-loss is for an agent on a radio",
        ),
    ],
)
def test_node_options_refused(argv: tuple[str, ...], match: str) -> None:
    with pytest.raises(UsageError, match=match):
        node_options(_node_args(*argv), "an agent")


def test_node_and_agent_options_are_checked_when_built() -> None:
    with pytest.raises(ValueError, match="not both"):
        NodeOptions(radio="x", link=object())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="either"):
        NodeOptions(radio="x", zenoh_connect=["tcp/127.0.0.1:1"])
    with pytest.raises(ValueError, match="at least one Zenoh endpoint"):
        NodeOptions()
    for bad, match in (
        ({"pose_hz": 0.0}, "pose_hz"),
        ({"pose_hz": float("nan")}, "pose_hz"),
        ({"pose_hz": 51.0}, "pose_hz"),
        ({"round_s": float("inf")}, "round_s"),
        ({"round_s": -1.0}, "round_s"),
        ({"vote": "loudest"}, "vote"),
        ({"profile": "slow"}, "profile"),
    ):
        with pytest.raises(ValueError, match=match):
            AgentConfig(**bad)  # type: ignore[arg-type]


# -- the global options: log levels ---------------------------------------------------


def test_global_options_refuse_bad_input(capsys: pytest.CaptureFixture[str]) -> None:
    assert swarm_main(["--log-level", "LOUD", "agent"]) == 2
    err = capsys.readouterr().err
    assert "swarm: error:" in err and "LOUD" in err and "Traceback" not in err
    assert swarm_main(["-v"]) == 2  # options but no command: the usage
    assert "usage: swarm" in capsys.readouterr().out
    assert swarm_main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "--log-level LEVEL" in out and "-v, -vv" in out


@pytest.mark.processes
def test_verbose_shows_the_agents_log_lines_and_the_default_stays_quiet() -> None:
    """Two agents, one started with ``swarm -v``; a third node advertises both their
    ids under another name. Both report it (a pilot event on stdout); only the one
    with ``-v`` also logs it on stderr, one line with time, logger name and level."""
    from swarm.core.wire.message_types import Advertize
    from swarm.runtime.keyspace.transport import Transport

    ep = f"tcp/127.0.0.1:{free_port()}"
    common = ["--zenoh-listen", ep, "--json"]
    loud = Child(["-v", "agent", "--name", "loud", "--id", "1", *common], name="loud")
    kids = [loud]
    try:
        loud.wait_lines(1, 60)  # listening: the quiet one finds a peer at once (no warning)
        argv = ["agent", "--name", "quiet", "--id", "2", "--zenoh-connect", ep, "--json"]
        quiet = Child(argv, name="quiet")
        kids.append(quiet)
        quiet.wait_lines(1, 60)
        with Transport.open("intruder", connect=[ep]) as tr:

            def reported() -> bool:
                for k in (1, 2):
                    tr.advertise(Advertize(k, "intruder"))
                return all(
                    any("'intruder' advertises our id" in json.loads(x).get("text", "") for x in ch.lines[1:])
                    for ch in (loud, quiet)
                )

            wait_until(reported, "both agents to report the intruder", 60, 0.5)
        wait_until(lambda: [x for x in loud.errors if "advertises our id 1" in x], "the log line", 30)
        lines = [x for x in loud.errors if "advertises our id 1" in x]
        assert len(lines) == 1 and " swarm.runtime.agent.live INFO: agent loud: " in lines[0]
        assert lines[0][:4].isdigit()  # the time first
    finally:
        for ch in kids:
            assert ch.stop() == 0
    assert quiet.errors == []  # without -v: nothing configured, INFO stays quiet


@pytest.mark.processes
def test_log_level_debug_shows_the_hidden_traceback_after_the_error_line() -> None:
    import subprocess
    import sys

    argv = [sys.executable, "-m", "swarm.cli", "--log-level", "debug", "agent", "--name", "a1", "--id", "1"]
    p = subprocess.run([*argv, "--radio", "/nonexistent/radio0"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    err = p.stderr.splitlines()
    assert err[0].startswith("swarm agent: error: ") and "/nonexistent/radio0" in err[0]
    assert " swarm.cli DEBUG: swarm agent: LinkOpenError" in err[1] and "Traceback" in p.stderr
    q = subprocess.run(
        [*argv[:3], *argv[5:], "--radio", "/nonexistent/radio0"], capture_output=True, text=True, timeout=60
    )
    assert q.returncode == 2 and len(q.stderr.splitlines()) == 1  # the default: one line
