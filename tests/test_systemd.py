"""Running as a systemd service: the notify client, the watchdog, the units and
``swarm service print|install``.

The notify tests use a real AF_UNIX datagram socket as the service manager's end
(:class:`notify_sink.NotifySink`). The process tests run ``swarm agent`` over Zenoh
with a simulated autopilot on a pseudo terminal (``swarm sim --serial pty``) and
``swarm gcs`` under a fake ``NOTIFY_SOCKET`` with a one-second watchdog: READY=1
arrives once they serve, WATCHDOG=1 keeps arriving, and stops while one loop hangs.
The hang is a real one: the autopilot's serial port stops taking bytes (its output
suspended, as a USB-serial adapter or a hung autopilot does), so the agent's
flight-controller housekeeper blocks in a write while the process and its other
loops live on. The units pass ``systemd-analyze verify``.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import termios
import time
import urllib.request
import uuid
from pathlib import Path

import pytest
from net_helpers import free_port, wait_until
from notify_sink import NotifySink

from swarm.cli.commands import service
from swarm.cli.procs import Child
from swarm.cli.util import UsageError
from swarm.runtime.notify import (
    Notifier,
    Service,
    Watchdog,
    socket_address,
    stale_loops,
    watchdog_interval,
)

WATCHDOG_USEC = 1_000_000  # one second: pets every half second


def abstract_name() -> str:
    return f"@uav-swarm-test-{uuid.uuid4().hex}"


# -- the notify client ---------------------------------------------------------------


def test_notifier_sends_each_message_to_a_path_socket(tmp_path: Path) -> None:
    with NotifySink(str(tmp_path / "notify")) as sink:
        n = Notifier.from_environ(sink.env())
        assert n.enabled
        assert n.ready("agent a1 ready") and n.watchdog() and n.status("busy") and n.stopping()
        wait_until(lambda: len(sink.raw) == 4, "four datagrams", 10)
        assert sink.raw == [
            b"READY=1\nSTATUS=agent a1 ready\n",
            b"WATCHDOG=1\n",
            b"STATUS=busy\n",
            b"STOPPING=1\nSTATUS=stopping\n",
        ]
        n.close()
        n.close()  # safe twice


def test_notifier_reaches_an_abstract_socket() -> None:
    with NotifySink(abstract_name()) as sink:
        n = Notifier.from_environ(sink.env())
        assert n.watchdog()
        wait_until(lambda: sink.count("WATCHDOG", "1") == 1, "WATCHDOG=1", 10)
        n.close()


def test_a_status_text_cannot_forge_another_assignment(tmp_path: Path) -> None:
    """A status line carries text from elsewhere (a name, a path): a newline in it would
    be a second KEY=VALUE to the manager (READY=1 before the service serves)."""
    with NotifySink(str(tmp_path / "notify")) as sink:
        n = Notifier.from_environ(sink.env())
        n.status("radio /dev/x\nREADY=1\r\nMAINPID=1")
        wait_until(lambda: sink.raw, "the datagram", 10)
        assert sink.raw == [b"STATUS=radio /dev/x READY=1 MAINPID=1\n"]
        n.close()


def test_without_notify_socket_nothing_happens() -> None:
    n = Notifier.from_environ({})
    assert not n.enabled
    assert not n.ready("x") and not n.watchdog() and not n.stopping()
    svc = Service(dict, env={"WATCHDOG_USEC": "1000000"})
    svc.ready("ready")
    assert svc.watchdog is None
    svc.stopping()


@pytest.mark.parametrize(
    "value",
    ["relative/notify", "notify", "@", "/" + "x" * 200, "@" + "y" * 120, "/run/a\0b", " /run/notify"],
)
def test_a_notify_socket_that_cannot_be_one_turns_notify_off(
    value: str, caplog: pytest.LogCaptureFixture
) -> None:
    with pytest.raises(ValueError):
        socket_address(value)
    n = Notifier.from_environ({"NOTIFY_SOCKET": value})
    assert not n.enabled and not n.ready("x")
    assert len([r for r in caplog.records if "service notify off" in r.getMessage()]) == 1


def test_a_manager_gone_loses_datagrams_without_an_error(tmp_path: Path) -> None:
    path = tmp_path / "notify"
    sink = NotifySink(str(path))
    sink.close()  # unlinked: the manager went away
    n = Notifier.from_environ({"NOTIFY_SOCKET": str(path)})
    assert n.enabled
    assert not n.watchdog() and not n.watchdog()
    assert n.failed == 2 and n.sent == 0
    n.close()


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        ({}, None),
        ({"WATCHDOG_USEC": "1000000"}, 1.0),
        ({"WATCHDOG_USEC": "250000", "WATCHDOG_PID": "4242"}, 0.25),
        ({"WATCHDOG_USEC": "250000", "WATCHDOG_PID": "4243"}, None),  # another process's
    ],
)
def test_watchdog_interval(env: dict[str, str], expected: float | None) -> None:
    assert watchdog_interval(env, 4242) == expected


@pytest.mark.parametrize(
    "env",
    [
        {"WATCHDOG_USEC": "0"},
        {"WATCHDOG_USEC": "-5"},
        {"WATCHDOG_USEC": "1e6"},
        {"WATCHDOG_USEC": ""},
        {"WATCHDOG_USEC": "\u0661\u0660\u0660"},  # digits, but not ASCII ones
        {"WATCHDOG_USEC": "\u00b2"},
        {"WATCHDOG_USEC": "9" * 400},  # more than a float holds
        {"WATCHDOG_USEC": "1000", "WATCHDOG_PID": "me"},
    ],
)
def test_a_bad_watchdog_setting_is_refused_in_one_line(env: dict[str, str], tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        watchdog_interval(env, 4242)
    with NotifySink(str(tmp_path / "notify")) as sink:
        svc = Service(dict, env={**sink.env(), **env})
        svc.ready("ready")  # READY still goes; no watchdog is started
        assert svc.watchdog is None
        svc.stopping()
        wait_until(lambda: sink.count("STOPPING") == 1, "STOPPING=1", 10)
        assert sink.count("READY", "1") == 1


def test_stale_loops() -> None:
    beats = {"protocol": (100.0, 1.0), "pose": (98.0, 4.0), "radio-send": (101.0, 1.0)}
    assert stale_loops(beats, 101.9, 1.0) == []
    assert stale_loops(beats, 102.1, 1.0) == ["protocol"]
    assert stale_loops(beats, 102.1, 10.0) == []
    assert stale_loops(beats, 200.0, 1.0) == ["pose", "protocol", "radio-send"]
    assert stale_loops({"x": (float("nan"), 1.0)}, 0.0, 1.0) == ["x"]


def test_the_watchdog_pets_only_while_every_loop_goes_round(tmp_path: Path) -> None:
    beats = {"protocol": (100.0, 1.0), "fc-housekeeping": (100.0, 0.1)}
    with NotifySink(str(tmp_path / "notify")) as sink:
        n = Notifier.from_environ(sink.env())
        dog = Watchdog(n, lambda: beats, interval=1.0)
        assert dog.check(100.5)
        assert not dog.check(101.2)  # the housekeeper: 1.2 s > 0.1 + 1
        assert not dog.check(101.4)
        beats["fc-housekeeping"] = (101.5, 0.1)
        assert dog.check(101.6)
        wait_until(lambda: len(sink.raw) == 4, "four datagrams", 10)
        assert sink.raw == [
            b"WATCHDOG=1\n",
            b"STATUS=stuck: fc-housekeeping (watchdog not petted)\n",  # said once
            b"STATUS=running (every loop runs again)\n",
            b"WATCHDOG=1\n",
        ]
        n.close()


def test_a_probe_that_fails_stops_the_petting(tmp_path: Path) -> None:
    def probe() -> dict[str, tuple[float, float]]:
        raise RuntimeError("a bug")

    with NotifySink(str(tmp_path / "notify")) as sink:
        n = Notifier.from_environ(sink.env())
        assert not Watchdog(n, probe, interval=1.0).check(0.0)
        wait_until(lambda: sink.raw, "the status", 10)
        assert sink.count("WATCHDOG") == 0 and sink.statuses() == ["stuck: probe (watchdog not petted)"]
        n.close()


def test_the_watchdog_thread_pets_at_half_the_interval(tmp_path: Path) -> None:
    with NotifySink(str(tmp_path / "notify")) as sink:
        now = time.monotonic
        svc = Service(lambda: {"loop": (now(), 0.0)}, env=sink.env(watchdog_usec=200_000))
        svc.ready("ready")
        wait_until(lambda: sink.count("WATCHDOG", "1") >= 5, "five WATCHDOG=1", 20)
        svc.stopping()
        assert svc.watchdog is not None and svc.watchdog.interval == 0.2
        wait_until(lambda: sink.count("STOPPING", "1") == 1, "STOPPING=1", 10)


# -- swarm service print|install -------------------------------------------------------


def run_service(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = service.main(argv)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("kind", ["agent", "gcs"])
def test_print_shows_the_unit_with_this_installation(kind: str, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_service(["print", kind], capsys)
    assert code == 0
    lines = out.splitlines()
    config = "/etc/uav-swarm/%i.toml" if kind == "agent" else "/etc/uav-swarm/gcs.toml"
    assert f"ExecStart={sys.executable} -m swarm.cli {kind} --config {config}" in lines
    for line in (
        "Type=notify",
        "WatchdogSec=10",
        "Restart=on-failure",
        "User=uav-swarm",
        "SupplementaryGroups=dialout",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "StateDirectory=uav-swarm",
        "WorkingDirectory=/var/lib/uav-swarm",
        "WantedBy=multi-user.target",
    ):
        assert line in lines
    assert "@SWARM@" not in out and not any(x.startswith("ReadWritePaths") for x in lines)


@pytest.mark.parametrize(
    ("path", "word"),
    [
        ("/opt/uav-swarm/bin/python", "/opt/uav-swarm/bin/python"),
        ("/opt/uav swarm/bin/python", '"/opt/uav swarm/bin/python"'),
        ("/opt/100%/bin/python", "/opt/100%%/bin/python"),
        ("/opt/$HOME/python", "/opt/$$HOME/python"),
        ('/opt/a"b\\c/python', '"/opt/a\\"b\\\\c/python"'),
    ],
)
def test_the_executable_is_quoted_for_systemd(path: str, word: str) -> None:
    assert service.swarm_command(path) == f"{word} -m swarm.cli"


@pytest.mark.parametrize("path", ["/opt/a\nExecStartPre=/bin/rm/python", "/opt/\x1b[2J", "python", ""])
def test_an_executable_path_that_cannot_go_in_a_unit_is_refused(path: str) -> None:
    with pytest.raises(UsageError):
        service.swarm_command(path)


def test_install_writes_keeps_and_replaces_only_with_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    unit = tmp_path / "swarm-agent@.service"
    code, out, _ = run_service(["install", "agent", "--dir", str(tmp_path)], capsys)
    assert code == 0 and f"wrote {unit}" in out
    assert unit.read_text() == service.unit_text("agent")
    assert unit.stat().st_mode & 0o777 == 0o644
    for step in ("useradd", "dialout", "systemctl daemon-reload", "enable --now swarm-agent@NAME"):
        assert step in out
    assert run_service(["install", "agent", "--dir", str(tmp_path)], capsys)[1].startswith(
        f"{unit}: unchanged"
    )

    unit.write_text("# the operator's own unit\n")
    code, out, err = run_service(["install", "agent", "--dir", str(tmp_path)], capsys)
    assert code == 1 and out == ""
    assert err == f"swarm service: error: {unit} exists with other content: kept (--force replaces it)\n"
    assert unit.read_text() == "# the operator's own unit\n"

    assert run_service(["install", "agent", "--dir", str(tmp_path), "--force"], capsys)[0] == 0
    assert unit.read_text() == service.unit_text("agent")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["swarm-agent@.service"]  # no temporary left


def test_install_never_writes_through_a_symlink(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A masked unit is a symlink to /dev/null; any symlink there points somewhere the
    operator chose. It is kept without --force; --force replaces the link, never its target."""
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    units = tmp_path / "units"
    units.mkdir()
    link = units / "swarm-gcs.service"
    link.symlink_to(victim)
    code, _, err = run_service(["install", "gcs", "--dir", str(units)], capsys)
    assert code == 1 and "is a symlink" in err and err.count("\n") == 1
    assert link.is_symlink()
    assert run_service(["install", "gcs", "--dir", str(units), "--force"], capsys)[0] == 0
    assert not link.is_symlink() and link.read_text() == service.unit_text("gcs")
    assert victim.read_text() == "precious\n"


def test_install_into_a_folder_that_is_not_one_is_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = tmp_path / "file"
    f.write_text("")
    for where in (str(f), str(tmp_path / "missing")):
        code, out, err = run_service(["install", "gcs", "--dir", where], capsys)
        assert code == 2 and out == "" and err == f"swarm service: error: --dir {where}: not a directory\n"
    with pytest.raises(SystemExit) as stop:  # argparse's own usage error
        service.main(["install", "robot"])
    assert stop.value.code == 2 and "invalid choice: 'robot'" in capsys.readouterr().err


# -- real processes --------------------------------------------------------------------


NOBODY = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]


def check_nobody_can_run_the_checkout() -> None:
    """Fail in one clear line when user nobody cannot run this checkout's interpreter
    and package (a clone under a private 0700 folder): what the test needs, not a bug."""
    probe = subprocess.run(
        [*NOBODY, sys.executable, "-c", "import swarm.cli.commands.service"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd="/",
    )
    if probe.returncode != 0:
        last = (probe.stderr.strip().splitlines() or ["no output"])[-1]
        pytest.fail(
            f"user nobody cannot run {sys.executable} with this checkout ({last}): a folder on the "
            "way is private (mode 0700?); this test runs `swarm service install` as nobody: make the "
            "folders traversable (chmod o+x) or clone where other users may read",
            pytrace=False,
        )


@pytest.mark.processes
def test_install_into_etc_needs_root_in_one_line(tmp_path: Path) -> None:
    """As a user without root (nobody): one line, exit 1, nothing written."""
    check_nobody_can_run_the_checkout()
    proc = subprocess.run(
        [*NOBODY, sys.executable, "-m", "swarm.cli", "service", "install", "agent"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout == ""
    assert proc.stderr.startswith(
        "swarm service: error: installing into /etc/systemd/system needs root: "
        "run it with sudo, or give --dir"
    )
    assert proc.stderr.count("\n") == 1


SYSTEMD_ANALYZE = shutil.which("systemd-analyze")


@pytest.mark.processes
def test_systemd_analyze_verifies_both_units(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``systemd-analyze verify`` on the installed units, the agent's as an instance (it
    checks that ExecStart's program exists: this interpreter). make setup installs it."""
    assert SYSTEMD_ANALYZE is not None, "systemd-analyze missing: make setup installs Debian's systemd"
    for kind in ("agent", "gcs"):
        assert run_service(["install", kind, "--dir", str(tmp_path)], capsys)[0] == 0
    instance = tmp_path / "swarm-agent@field1.service"
    shutil.copy(tmp_path / "swarm-agent@.service", instance)
    units = [str(instance), str(tmp_path / "swarm-gcs.service"), str(tmp_path / "swarm-agent@.service")]
    proc = subprocess.run(
        [SYSTEMD_ANALYZE, "verify", "--man=no", *units], capture_output=True, text=True, timeout=120
    )
    # the service user need not exist on the machine that verifies (systemd 252 does not
    # look it up; a newer one may say so): any other line is a finding
    findings = [line for line in (proc.stdout + proc.stderr).splitlines() if "uav-swarm" not in line.split()]
    assert proc.returncode == 0 and findings == [], proc.stdout + proc.stderr


def start_child(argv: list[str], name: str, env: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> Child:
    with monkeypatch.context() as m:
        for k, v in env.items():
            m.setenv(k, v)
        return Child(argv, name=name)


def suspend_output(tty: str, suspended: bool) -> None:
    """Stop (or restart) what a serial port passes on, as a USB-serial adapter whose far
    end stops taking bytes: a write to it blocks (the port's output is suspended)."""
    fd = os.open(tty, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        termios.tcflow(fd, termios.TCOOFF if suspended else termios.TCOON)
    finally:
        os.close(fd)


@pytest.mark.processes
def test_agent_ready_watchdog_and_a_stuck_flight_controller_write(monkeypatch: pytest.MonkeyPatch) -> None:
    sim = Child(["sim", "--vehicles", "1", "--serial", "pty"], name="sim")
    agent = None
    tty = ""
    try:
        first = sim.wait_lines(1, 60)[0]
        tty = first.split(" -> ")[1].split()[0]
        assert tty.startswith("/dev/"), first
        with NotifySink(abstract_name()) as sink:
            port = free_port()
            argv = ["agent", "--name", "a1", "--id", "1", "--zenoh-listen", f"tcp/127.0.0.1:{port}"]
            agent = start_child(
                [*argv, "--fc", tty, "--json"], "agent", sink.env(watchdog_usec=WATCHDOG_USEC), monkeypatch
            )
            ready = wait_until(lambda: sink.having("READY", "1"), "READY=1", 60, children=[agent])
            # READY once the flight controller is open and the agent advertises: its
            # ready line is out before
            assert json.loads(agent.lines[0])["event"] == "ready"
            assert ready[0][1]["STATUS"] == f"agent a1 id=1 zenoh listen=tcp/127.0.0.1:{port} ready"
            wait_until(
                lambda: sink.count("WATCHDOG", "1") >= 4, "WATCHDOG=1 four times", 30, children=[agent]
            )

            suspend_output(tty, True)  # the housekeeper's next HEARTBEAT write blocks
            # (only the housekeeper: a loop starved of CPU on a busy machine may show too)
            wait_until(
                lambda: "stuck: fc-housekeeping (watchdog not petted)" in sink.statuses(),
                "STATUS=stuck: fc-housekeeping",
                30,
                children=[agent],
            )
            pets = sink.count("WATCHDOG")
            t_stuck = time.monotonic()
            # three watchdog intervals without a pet (the manager would have killed it),
            # while the process and its other loops live on
            wait_until(lambda: time.monotonic() - t_stuck > 3.0, "three intervals", 10)
            assert sink.count("WATCHDOG") == pets and agent.proc.poll() is None

            suspend_output(tty, False)  # the port takes bytes again: the loop goes round
            wait_until(lambda: sink.count("WATCHDOG") >= pets + 2, "WATCHDOG=1 again", 30, children=[agent])
            assert "running (every loop runs again)" in sink.statuses()

            agent.proc.send_signal(signal.SIGTERM)
            assert agent.proc.wait(30) == 0
            assert sink.count("STOPPING", "1") == 1
    finally:
        if tty:
            suspend_output(tty, False)
        if agent is not None:
            agent.stop()
        sim.stop()


@pytest.mark.processes
def test_gcs_ready_once_its_server_answers(monkeypatch: pytest.MonkeyPatch) -> None:
    with NotifySink(abstract_name()) as sink:
        argv = ["gcs", "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}", "--http", "127.0.0.1:0", "--json"]
        gcs = start_child(argv, "gcs", sink.env(watchdog_usec=WATCHDOG_USEC), monkeypatch)
        try:
            wait_until(lambda: sink.having("READY", "1"), "READY=1", 60, children=[gcs])
            url = json.loads(gcs.lines[0])["url"]
            with urllib.request.urlopen(f"{url}api/state", timeout=30) as r:
                assert r.status == 200
            wait_until(lambda: sink.count("WATCHDOG", "1") >= 3, "WATCHDOG=1 three times", 30, children=[gcs])
            gcs.proc.send_signal(signal.SIGTERM)
            assert gcs.proc.wait(30) == 0
            assert sink.count("STOPPING", "1") == 1 and sink.statuses()[-1] == "stopping"
        finally:
            gcs.stop()


@pytest.mark.processes
def test_an_agent_and_a_station_on_a_radio_report_every_loop_alive() -> None:
    """The watchdog's probe over a radio (a ``virtual://`` bus): the protocol loop and the
    bridge's two threads, all fresh. A probe that raised would stop the petting for good."""
    from swarm.runtime.agent.live import Agent
    from swarm.runtime.options import NodeOptions
    from swarm.runtime.station.live import Station

    bus = f"virtual://notify-{uuid.uuid4().hex}"
    with Agent("a1", 1, NodeOptions(radio=bus)) as agent, Station(radio=bus) as station:
        for what, probe in (("agent", agent.loop_beats), ("station", station.loop_beats)):
            beats = probe()
            assert set(beats) == {"protocol", "radio-send", "radio-receive"}, what
            # every loop goes round within its own longest wait (plus a scheduling margin)
            wait_until(
                lambda probe=probe: stale_loops(probe(), time.monotonic(), 0.5) == [],
                f"every {what} loop fresh",
                30,
            )
            loop_beat, _ = beats["protocol"]
            wait_until(lambda probe=probe, b=loop_beat: probe()["protocol"][0] > b, f"{what} beats", 30)
