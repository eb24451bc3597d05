"""``swarm doctor`` on a bench: emulated SiK radios on real ptys, the vehicle simulator
on real UDP, real key files; a healthy set-up, then one planted fault at a time.

The bench: two emulated radios (radio0 on NETID 25, radio1 on NETID 77, both at
57600 baud) and one simulated PX4 vehicle. Each fault test asserts that exactly the
check it plants fails. The emulator's ptys ignore the baud rate a host sets (a pty has
no line speed), so an emulated radio answers AT at any baud: the wrong-baud test
checks what the doctor reads (SERIAL_SPEED against the agent's ``?baud=``); on real
hardware the radio would not answer at all, which a radio on a pty that hears its host
only at its own line speed stands in for (``UartRadio``; ``UartAutopilot`` likewise).
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import select
import socket
import subprocess
import sys
import termios
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from emu_helpers import running_emulator
from net_helpers import free_port
from sik_pty_radio import PtyRadio, make_engine

from firmware_bridge.sim import SimConfig, VehicleSim
from swarm.cli.commands import doctor
from swarm.core.doctor import Check, text_line
from swarm.core.doctor.radio import RadioPlan
from swarm.core.doctor.vehicle import vehicle_checks
from swarm.runtime.doctor import Setup, examine
from swarm.runtime.doctor.vehicle import vehicle_facts

pytestmark = pytest.mark.processes

PARAMS = "NETID=25,AIR_SPEED=64,SERIAL_SPEED=57,MAVLINK=1"
EXPECTED = {"NETID": 25, "AIR_SPEED": 64, "SERIAL_SPEED": 57, "MAVLINK": 1}


def failed(checks: list[Check]) -> list[str]:
    return [c.name for c in checks if c.status == "fail"]


def by_name(checks: list[Check]) -> dict[str, Check]:
    return {c.name: c for c in checks}


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    d = tmp_path_factory.mktemp("doctor-bench")
    port = free_port("udp")
    sim = VehicleSim(SimConfig(vehicles=1, profile="px4", seed=0, base_port=port))
    (fc,) = sim.start()
    key = d / "swarm.key"
    key.write_bytes(os.urandom(32))
    key.chmod(0o600)
    try:
        with running_emulator(d, 2, netids=[25, 77]) as emu:
            yield {"radios": emu.paths, "fc": fc, "key": str(key), "sim": sim, "dir": d}
    finally:
        sim.stop()


def bench_setup(bench: dict[str, Any], **change: Any) -> Setup:
    base: dict[str, Any] = {
        "radio": bench["radios"][0],
        "fc": bench["fc"],
        "key": bench["key"],
        "plan": RadioPlan(expected=EXPECTED),
    }
    base.update(change)
    return Setup(**base)


def test_healthy_bench_passes(bench: dict[str, Any]) -> None:
    """The command line, as a user runs it: exit 0, one JSON report, nothing failed."""
    argv = [sys.executable, "-m", "swarm.cli", "doctor", "--name", "a1", "--id", "1", "--json"]
    argv += [
        "--radio",
        bench["radios"][0],
        "--radio-params",
        PARAMS,
        "--fc",
        bench["fc"],
        "--key",
        bench["key"],
    ]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    report = json.loads(done.stdout)
    assert report["ok"] is True
    status = {c["name"]: c["status"] for c in report["checks"]}
    for name in ("radio device", "radio NETID", "radio AIR_SPEED", "radio baud", "fc", "fc GPS", "fc home"):
        assert status[name] == "pass", report
    assert status["key"] == status["key mode"] == status["clock"] == "pass"
    assert "fail" not in status.values()


def test_wrong_netid(bench: dict[str, Any]) -> None:
    checks = examine(bench_setup(bench, radio=bench["radios"][1]), now=time.time())
    assert failed(checks) == ["radio NETID"]
    assert by_name(checks)["radio NETID"].seen == "77 (expected 25)"


def test_world_readable_key(bench: dict[str, Any]) -> None:
    key = Path(bench["dir"]) / "open.key"
    key.write_bytes(os.urandom(32))
    key.chmod(0o644)
    checks = examine(bench_setup(bench, key=str(key), radio=None), now=time.time())
    assert failed(checks) == ["key mode"]
    assert by_name(checks)["key mode"].fix == f"chmod 600 {key}"


def test_wrong_baud(bench: dict[str, Any]) -> None:
    """The radio runs 57600 baud; the agent's --radio asks for 115200."""
    radio = bench["radios"][0] + "?baud=115200"
    checks = examine(bench_setup(bench, radio=radio, plan=RadioPlan()), now=time.time())
    assert failed(checks) == ["radio baud"]
    assert "?baud=57600" in by_name(checks)["radio baud"].fix


def test_no_gps_fix(bench: dict[str, Any]) -> None:
    sim = bench["sim"].vehicle(0)
    sim.fail_gps(True)
    try:
        checks = examine(bench_setup(bench, radio=None), now=time.time())
    finally:
        sim.fail_gps(False)
    assert failed(checks) == ["fc GPS"]
    assert by_name(checks)["fc GPS"].seen.startswith("no GPS")


def test_no_flight_controller_fails_within_5_s(tmp_path: Path) -> None:
    """Nothing listens: the command line's own deadline (5 s), exit 1, one FAIL line."""
    key = tmp_path / "k"
    key.write_bytes(os.urandom(32))
    key.chmod(0o600)
    argv = [sys.executable, "-m", "swarm.cli", "doctor", "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"]
    argv += ["--fc", f"udpin:127.0.0.1:{free_port('udp')}", "--key", str(key)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1, done.stdout + done.stderr
    fails = [line for line in done.stdout.splitlines() if line.startswith("FAIL")]
    assert len(fails) == 1 and fails[0].startswith("FAIL fc ")
    assert "no autopilot heartbeat within 5 s" in fails[0]
    assert done.stderr == ""
    refused = examine(
        Setup(fc=f"tcp:127.0.0.1:{free_port()}", zenoh_connect=("tcp/127.0.0.1:7447",)), now=time.time()
    )
    assert failed(refused) == ["fc"]


def test_a_radio_held_by_another_program_is_not_touched(bench: dict[str, Any]) -> None:
    """A running agent holds its radio without a lock: the doctor must see it and keep
    its +++ out of the agent's traffic."""
    with open(bench["radios"][0], "rb") as held:
        holder = subprocess.Popen(["sleep", "60"], stdin=held)
    try:
        checks = examine(bench_setup(bench, fc=None), now=time.time())
    finally:
        holder.kill()
        holder.wait()
    c = by_name(checks)
    assert failed(checks) == ["radio device"]
    assert "in use by another program" in c["radio device"].seen
    assert "radio firmware" not in c  # not probed


def test_multipoint_radios_see_each_others_node_ids(tmp_path: Path) -> None:
    """Three multipoint radios: the doctor on node 1 hears nodes 0 and 2 answer RTI."""
    with running_emulator(tmp_path, 3) as emu:
        emu.wait_locked(0, 1, 2)
        checks = examine(Setup(radio=emu.paths[1], key=None), now=time.time())
    c = by_name(checks)
    assert c["radio NODEID"].seen == "NODEID 1 < NODECOUNT 3"
    assert c["radio NODEID unique"].status == "pass", c["radio NODEID unique"]
    assert "nodes 0, 2 answered" in c["radio NODEID unique"].seen
    assert c["radio peers"].status == "pass"


class UartRadio:
    """A SiK radio (the AT engine) on a pty that, like one on a real UART, understands
    its host only at its own serial speed: at any other rate the pty's line is set to,
    what the host writes is noise to it and it answers nothing."""

    def __init__(self, baud: int) -> None:
        self.speed = getattr(termios, f"B{baud}")
        self.engine = make_engine()
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        os.close(slave)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while not self.stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.02)
            with contextlib.suppress(OSError):  # no host has the slave open
                data = os.read(self.master, 4096) if ready else b""
                heard = termios.tcgetattr(self.master)[5] == self.speed
                out = (
                    self.engine.feed(data, time.monotonic())
                    if heard and data
                    else self.engine.poll(time.monotonic())
                )
                if heard and out.to_host:
                    os.write(self.master, out.to_host)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        os.close(self.master)


def test_a_radio_at_another_serial_speed_is_found() -> None:
    """What a radio at another serial speed does on real hardware: nothing, at the
    agent's rate (115200). The doctor finds the rate it answers at (57600)."""
    radio = UartRadio(57600)
    try:
        checks = examine(Setup(radio=f"{radio.path}?baud=115200"), now=time.time())
    finally:
        radio.close()
    c = by_name(checks)["radio"]
    assert c.status == "fail" and "no answer to +++" in c.seen
    assert "the radio answers at 57600 baud" in c.seen
    assert f"--radio {radio.path}?baud=57600" in c.fix and "--set SERIAL_SPEED=115" in c.fix


def test_a_hostile_radio_banner_is_escaped(capsys: pytest.CaptureFixture[str]) -> None:
    engine = make_engine()
    engine.version = "2.2\x1b]0;owned\x07\x1b[2J"
    with PtyRadio(engine, peer=make_engine()) as radio:
        code = doctor.main(["--radio", radio.path])
    out = capsys.readouterr().out
    assert code == 0
    assert "\x1b" not in out and "\x07" not in out
    firmware = next(line for line in out.splitlines() if line.startswith("INFO radio firmware"))
    assert "\\x1b" in firmware


def test_a_radio_answering_a_number_of_5000_digits_fails_one_line() -> None:
    """``int()`` refuses more than 4300 digits: the radio's answer is garbage, not a crash
    (the strict register reader takes at most 10 digits: such a line is no register)."""
    engine = make_engine()
    info = engine._info  # noqa: SLF001 (white box: a radio that answers too much)
    engine._info = lambda arg: ["S3:NETID=" + "9" * 5000] if arg[:1] == "5" else info(arg)  # type: ignore[method-assign]  # noqa: SLF001 (white box: a radio that answers too much)
    with PtyRadio(engine) as radio:
        checks = examine(Setup(radio=radio.path), now=time.time())
    c = by_name(checks)["radio"]
    assert c.status == "fail" and "is not a standard SiK register line" in c.seen
    assert len(text_line(c)) < 1000


class FakeAutopilot:
    """A PX4 autopilot (system 1, component 1) that sends only heartbeats, and an
    intruder on the same link (system 9, and a second component of system 1) that
    sends everything the doctor asks for, and garbage: none of it may count."""

    def __init__(self, port: int, clock_ahead_s: float = 0.0) -> None:
        from pymavlink.dialects.v20 import common

        self.port = port
        self.clock_ahead_s = clock_ahead_s
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.stop = threading.Event()
        self.mav = [common.MAVLink(None, srcSystem=s, srcComponent=c) for s, c in ((1, 1), (9, 1), (1, 42))]
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def send(self, msg: Any, mav: Any) -> None:
        self.sock.sendto(msg.pack(mav), ("127.0.0.1", self.port))

    def run(self) -> None:
        ap, intruders = self.mav[0], self.mav[1:]
        rng = random.Random(7)
        while not self.stop.wait(0.2):
            self.send(ap.heartbeat_encode(2, 12, 0, 0, 3, 3), ap)
            self.send(ap.system_time_encode(int((time.time() + self.clock_ahead_s) * 1e6), 0), ap)
            hb = ap.heartbeat_encode(2, 12, 0, 0, 3, 3).pack(ap)
            for junk in (rng.randbytes(300), b"\xfd" + rng.randbytes(40), hb[:7], b"\xfd\xff" + bytes(300)):
                self.sock.sendto(junk, ("127.0.0.1", self.port))
            for m in intruders:
                self.send(m.gps_raw_int_encode(0, 6, 1, 1, 1, 1, 1, 1, 0, 20), m)
                self.send(m.home_position_encode(1, 1, 1, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0), m)
                self.send(m.gps_global_origin_encode(1, 1, 1), m)
                self.send(m.system_time_encode(0, 0), m)
                self.send(
                    m.autopilot_version_encode(0, 1 << 24, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0), m
                )

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        self.sock.close()


def test_messages_from_another_system_do_not_count() -> None:
    port = free_port("udp")
    fake = FakeAutopilot(port)
    try:
        facts = vehicle_facts(f"udpin:127.0.0.1:{port}", timeout=5.0, listen=1.5)
    finally:
        fake.close()
    assert facts.answered and facts.sysid == 1 and facts.autopilot == 12
    assert facts.gps_fix is None and facts.version is None
    assert not facts.home and not facts.origin
    assert facts.clock_offset_s is not None and abs(facts.clock_offset_s) < 5.0  # the intruder's 0 ignored


def test_a_clock_an_hour_behind_the_autopilots_gps_time_fails() -> None:
    port = free_port("udp")
    fake = FakeAutopilot(port, clock_ahead_s=3600.0)
    try:
        facts = vehicle_facts(f"udpin:127.0.0.1:{port}", timeout=5.0, listen=1.0)
    finally:
        fake.close()
    c = by_name(vehicle_checks(facts))["fc clock"]
    assert c.status == "fail" and "s behind the autopilot's GPS time" in c.seen
    assert facts.clock_offset_s is not None and 3590 < facts.clock_offset_s < 3610


class UartAutopilot:
    """An autopilot on a pty that, like one on a real UART, is heard only at its own
    baud rate: at any other rate the host set on its side, what it sends is noise."""

    def __init__(self, baud: int) -> None:
        from pymavlink.dialects.v20 import common

        self.speed = getattr(termios, f"B{baud}")
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        os.close(slave)
        os.set_blocking(self.master, False)
        self.mav = common.MAVLink(None, srcSystem=1, srcComponent=1)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        rng = random.Random(3)
        while not self.stop.wait(0.2):
            with contextlib.suppress(OSError):  # nobody has the slave open, or its buffer is full
                os.read(self.master, 4096)
                same = termios.tcgetattr(self.master)[5] == self.speed
                data = (
                    self.mav.heartbeat_encode(2, 12, 0, 0, 3, 3).pack(self.mav) if same else rng.randbytes(40)
                )
                os.write(self.master, data)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        os.close(self.master)


def test_flight_controller_at_another_baud_rate_is_found() -> None:
    """The agent opens the autopilot's UART at 57600; it runs at 921600."""
    fc = UartAutopilot(921600)
    try:
        facts = vehicle_facts(f"{fc.path}:57600", timeout=1.0, scan=1.0)
        assert vehicle_facts(f"{fc.path}:921600", timeout=3.0, listen=0.5).answered
    finally:
        fc.close()
    assert not facts.answered and facts.found_baud == 921600
    (c,) = vehicle_checks(facts)
    assert c.status == "fail" and "the autopilot answers at 921600 baud" in c.seen
    assert "--fc with :921600" in c.fix
