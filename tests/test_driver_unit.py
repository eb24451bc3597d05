"""Unit tests of the flight-controller driver: no simulator, only tiny pymavlink fakes."""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest
from net_helpers import free_port
from pymavlink import mavutil

from firmware_bridge import driver as drv
from firmware_bridge.errors import (
    CommandRejected,
    CommandTimeout,
    ConnectError,
    HeartbeatTimeout,
    SetpointError,
)
from firmware_bridge.modes import (
    UnknownMode,
    canonical_mode,
    custom_mode_of,
    decode_mode,
    encode_mode,
)

mavlink: Any = mavutil.mavlink


def free_udp_port() -> int:
    return free_port("udp")


class FakeAutopilot:
    """Sends HEARTBEATs to the driver's udpin port and answers commands with ``ack``
    (None = never answer); records every message it receives."""

    def __init__(
        self,
        port: int,
        *,
        autopilot: int = 12,
        sysid: int = 1,
        custom_mode: int = 0,
        ack: Callable[[Any], int | None] | None = None,
        text: str = "",
        gcs_first: bool = False,
        signing_key: bytes | None = None,
    ) -> None:
        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=sysid, source_component=1
        )
        if signing_key is not None:
            self.conn.setup_signing(signing_key, sign_outgoing=True)
        self.autopilot, self.custom_mode, self.ack, self.text = autopilot, custom_mode, ack, text
        self.gcs_first = gcs_first
        self.received: list[Any] = []
        self.heartbeats = True
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb and self.heartbeats:
                if self.gcs_first:  # a GCS on the same link: must be ignored
                    gcs = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3)
                    gcs.pack(self.conn.mav)
                    self.conn.mav.srcSystem, keep = 255, self.conn.mav.srcSystem
                    self.conn.mav.send(gcs)
                    self.conn.mav.srcSystem = keep
                self.conn.mav.heartbeat_send(2, self.autopilot, 1, self.custom_mode, 3)
                next_hb = now + 0.1
            self.conn.select(0.02)
            while (m := self.conn.recv_msg()) is not None:
                if m.get_type() == "BAD_DATA":
                    continue
                self.received.append(m)
                if m.get_type() == "COMMAND_LONG" and self.ack is not None:
                    result = self.ack(m)
                    if result is None:
                        continue
                    if result != 0 and self.text:
                        self.conn.mav.statustext_send(3, self.text.encode())
                    self.conn.mav.command_ack_send(
                        m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()
                    )

    def of_type(self, name: str) -> list[Any]:
        return [m for m in list(self.received) if m.get_type() == name]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.conn.close()


@pytest.fixture
def fake_factory():
    made: list[FakeAutopilot] = []

    def make(port: int, **kw: Any) -> FakeAutopilot:
        f = FakeAutopilot(port, **kw)
        made.append(f)
        return f

    yield make
    for f in made:
        f.close()


# --- connection strings ---------------------------------------------------------------
@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("serial:/dev/ttyAMA0:921600", drv.Endpoint("serial", device="/dev/ttyAMA0", baud=921600)),
        ("serial:/dev/ttyUSB0", drv.Endpoint("serial", device="/dev/ttyUSB0", baud=57600)),
        ("/dev/ttyACM0:115200", drv.Endpoint("serial", device="/dev/ttyACM0", baud=115200)),
        ("udp:127.0.0.1:14540", drv.Endpoint("udpin", host="127.0.0.1", port=14540)),
        ("udpin:0.0.0.0:14541", drv.Endpoint("udpin", host="0.0.0.0", port=14541)),
        ("udp://:14540", drv.Endpoint("udpin", host="0.0.0.0", port=14540)),
        ("udpout:10.0.0.2:14550", drv.Endpoint("udpout", host="10.0.0.2", port=14550)),
        ("tcp:127.0.0.1:5760", drv.Endpoint("tcp", host="127.0.0.1", port=5760)),
        # the radio links' serial form: one string names a serial port for both
        ("/dev/ttyAMA0?baud=921600", drv.Endpoint("serial", device="/dev/ttyAMA0", baud=921600)),
        ("serial:/dev/ttyS1?baud=115200", drv.Endpoint("serial", device="/dev/ttyS1", baud=115200)),
        ("/dev/ttyUSB1?", drv.Endpoint("serial", device="/dev/ttyUSB1", baud=57600)),
    ],
)
def test_parse_url(url: str, expected: drv.Endpoint) -> None:
    assert drv.parse_url(url) == expected


@pytest.mark.parametrize(
    "url",
    [
        "",
        "   ",
        "nonsense",
        "ftp:host:21",
        "udp:127.0.0.1",
        "udp:127.0.0.1:port",
        "udp:127.0.0.1:0",
        "udp:127.0.0.1:70000",
        "tcp::5760",
        "tcp:127.0.0.1",
        "serial:",
        "serial:/dev/ttyS0:fast",
        "serial:/dev/ttyS0:-5",
        "udpout::14550",
        "/dev/ttyS0?baud=fast",
        "/dev/ttyS0?baud=0",
        "/dev/ttyS0?baud=57600&rtscts=maybe",
        "flight.tlog?speed=2",
        "virtual://bus?loss=0",
        "/dev/tty\x00S0?baud=57600",
    ],
)
def test_parse_url_rejects(url: str) -> None:
    with pytest.raises(ConnectError):
        drv.parse_url(url)


def test_connect_errors_are_clear() -> None:
    with pytest.raises(ConnectError, match="does not exist"):
        drv.connect("serial:/dev/does-not-exist-xyz:57600", timeout=1)
    with pytest.raises(ConnectError, match="unknown scheme"):
        drv.connect("bogus:1:2", timeout=1)
    with pytest.raises(ConnectError, match="resolve"):
        drv.connect("udpout:no-such-host.invalid:14550", timeout=1)
    # a TCP port nobody listens on: refused at once, not retried forever
    port = free_port("tcp")
    t0 = time.monotonic()
    with pytest.raises(ConnectError):
        drv.connect(f"tcp:127.0.0.1:{port}", timeout=2)
    assert time.monotonic() - t0 < 5
    with pytest.raises(ConnectError, match="32 bytes"):
        drv.connect("udpin:127.0.0.1:14999", signing_key=b"short")


def test_silent_udp_port_times_out() -> None:
    t0 = time.monotonic()
    with pytest.raises(HeartbeatTimeout):
        drv.connect(f"udpin:127.0.0.1:{free_udp_port()}", timeout=1.0)
    assert time.monotonic() - t0 < 3.0


def test_silent_tcp_server_times_out() -> None:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    accepted: list[socket.socket] = []
    th = threading.Thread(target=lambda: accepted.append(srv.accept()[0]), daemon=True)
    th.start()
    try:
        t0 = time.monotonic()
        with pytest.raises(HeartbeatTimeout) as info:
            drv.connect(f"tcp:127.0.0.1:{srv.getsockname()[1]}", timeout=1.0)
        assert isinstance(info.value, TimeoutError)
        assert time.monotonic() - t0 < 3.0
    finally:
        for c in accepted:
            c.close()
        srv.close()


def test_tcp_autopilot_that_opens_its_port_late_is_found_within_the_timeout() -> None:
    """A script started together with its SITL or ``swarm sim``: the port is refused
    for a moment, then listens and talks; connect() finds it within its timeout."""
    port = free_port("tcp")  # outside the ephemeral range: no retry can connect to itself
    done = threading.Event()
    conns: list[socket.socket] = []

    def autopilot() -> None:
        time.sleep(1.2)  # refused until then
        srv = socket.create_server(("127.0.0.1", port))
        c = srv.accept()[0]
        conns.append(c)
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        hb = mav.heartbeat_encode(2, 3, 81, 0, 3).pack(mav)  # quad, ArduPilot, standby
        while not done.wait(0.2):
            c.sendall(hb)
        c.close()
        srv.close()

    th = threading.Thread(target=autopilot, daemon=True)
    th.start()
    try:
        with drv.connect(f"tcp:127.0.0.1:{port}", timeout=8, request_telemetry=False) as v:
            assert v.autopilot == "ardupilot"
    finally:
        done.set()
        th.join(5)


def test_silent_udpout_peer_times_out() -> None:
    t0 = time.monotonic()
    with pytest.raises(HeartbeatTimeout):
        drv.connect(f"udpout:127.0.0.1:{free_udp_port()}", timeout=1.0)
    assert time.monotonic() - t0 < 3.0


# --- modes ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "custom"),
    [
        ("OFFBOARD", 393216),
        ("POSCTL", 196608),
        ("AUTO.TAKEOFF", 33816576),
        ("AUTO.LOITER", 50593792),
        ("AUTO.MISSION", 67371008),
        ("AUTO.RTL", 84148224),
        ("AUTO.LAND", 100925440),
    ],
)
def test_px4_modes(name: str, custom: int) -> None:
    assert custom_mode_of("px4", name) == custom
    assert decode_mode("px4", custom, 1 | 128) == name
    p1, p2, p3 = encode_mode("px4", name)
    assert p1 == 1 and (int(p2) << 16 | int(p3) << 24) == custom and p2 < 256


@pytest.mark.parametrize(
    ("name", "number"),
    [
        ("STABILIZE", 0),
        ("ALT_HOLD", 2),
        ("AUTO", 3),
        ("GUIDED", 4),
        ("LOITER", 5),
        ("RTL", 6),
        ("LAND", 9),
        ("POSHOLD", 16),
        ("SMART_RTL", 21),
        ("FOLLOW", 23),
    ],
)
def test_ardupilot_modes(name: str, number: int) -> None:
    assert custom_mode_of("ardupilot", name) == number
    assert decode_mode("ardupilot", number, 1) == name
    assert encode_mode("ardupilot", name) == (1.0, float(number), 0.0)


def test_mode_aliases_and_unknown() -> None:
    assert canonical_mode("px4", "hold") == "AUTO.LOITER"
    assert canonical_mode("px4", "land") == "AUTO.LAND"
    assert canonical_mode("px4", "rtl") == "AUTO.RTL"
    assert canonical_mode("ardupilot", "hold") == "LOITER"
    assert canonical_mode("ardupilot", "guided") == "GUIDED"
    with pytest.raises(UnknownMode):
        encode_mode("px4", "GUIDED")
    with pytest.raises(UnknownMode):
        encode_mode("ardupilot", "OFFBOARD")
    assert decode_mode("ardupilot", 99).startswith("UNKNOWN")
    assert decode_mode("px4", 99 << 16, 1).startswith("UNKNOWN")


# --- setpoints ----------------------------------------------------------------------------
BAD_LOCAL = [
    (math.nan, 0, -5, 0),
    (0, math.inf, -5, 0),
    (0, 0, -math.inf, 0),
    (0, 0, -5, math.nan),
    (10_001, 0, -5, 0),
    (0, -10_001, -5, 0),
    (0, 0, -20_000, 0),
    (0, 0, 5_000, 0),
    ("x", 0, 0, 0),
]
BAD_GLOBAL = [
    (math.nan, 8.5, 10, 0),
    (47.3, math.inf, 10, 0),
    (91, 8.5, 10, 0),
    (47.3, -181, 10, 0),
    (47.3, 8.5, 50_000, 0),
    (47.3, 8.5, -5_000, 0),
    (47.3, 8.5, 10, math.inf),
]


@pytest.mark.parametrize("args", BAD_LOCAL)
def test_validate_local_rejects(args: tuple[Any, ...]) -> None:
    with pytest.raises(SetpointError):
        drv.validate_local(*args)


@pytest.mark.parametrize("args", BAD_GLOBAL)
def test_validate_global_rejects(args: tuple[Any, ...]) -> None:
    with pytest.raises(SetpointError):
        drv.validate_global(*args)


def test_yaw_is_wrapped() -> None:
    t = drv.validate_local(1, 2, -3, 3 * math.pi)
    assert math.isclose(abs(t.yaw), math.pi)
    assert -math.pi <= drv.validate_global(47, 8, 10, -7.0).yaw <= math.pi


def _roundtrip(msg: Any) -> Any:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    buf = msg.pack(mav)
    return mav.parse_char(buf)


def test_local_setpoint_message() -> None:
    msg = drv.setpoint_message(
        drv.validate_local(20, -3, -10, 1.0), time_boot_ms=1234, target_system=1, target_component=1
    )
    got = _roundtrip(msg)
    assert got.get_type() == "SET_POSITION_TARGET_LOCAL_NED"
    assert got.coordinate_frame == 1 and got.type_mask == 2552
    assert (got.x, got.y, got.z) == (20, -3, -10)
    assert math.isclose(got.yaw, 1.0, rel_tol=1e-6) and got.yaw_rate == 0
    assert got.target_system == 1 and got.target_component == 1 and got.time_boot_ms == 1234


def test_global_setpoint_message() -> None:
    msg = drv.setpoint_message(
        drv.validate_global(47.397742, 8.545594, 10, -0.5),
        time_boot_ms=2**32 + 5,
        target_system=3,
        target_component=1,
    )
    got = _roundtrip(msg)
    assert got.get_type() == "SET_POSITION_TARGET_GLOBAL_INT"
    assert got.coordinate_frame == 6 and got.type_mask == 2552
    assert (got.lat_int, got.lon_int) == (473977420, 85455940)
    assert math.isclose(got.alt, 10) and math.isclose(got.yaw, -0.5, rel_tol=1e-6)
    assert got.time_boot_ms == 5 and got.target_system == 3


# --- against a tiny fake autopilot -------------------------------------------------------
def test_connect_ignores_gcs_and_takes_ids(fake_factory) -> None:
    port = free_udp_port()
    fake = fake_factory(port, sysid=7, gcs_first=True, custom_mode=custom_mode_of("px4", "AUTO.LOITER"))
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5) as v:
        assert (v.target_system, v.target_component, v.autopilot) == (7, 1, "px4")
        assert v.state.mode == "AUTO.LOITER"
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not fake.of_type("HEARTBEAT"):
            time.sleep(0.05)
        hb = fake.of_type("HEARTBEAT")[0]
        assert (hb.get_srcSystem(), hb.get_srcComponent(), hb.type, hb.autopilot) == (7, 191, 18, 8)
        # telemetry was requested (ArduPilot streams nothing by default)
        asked = {int(m.param1) for m in fake.of_type("COMMAND_LONG") if m.command == 511}
        assert {30, 32, 33, 242, 245, 1} <= asked
    v.close()  # twice is fine


def test_ardupilot_detected(fake_factory) -> None:
    port = free_udp_port()
    fake_factory(port, autopilot=3, custom_mode=4)
    with drv.connect(f"udp:127.0.0.1:{port}", timeout=5) as v:
        assert v.autopilot == "ardupilot" and v.state.mode == "GUIDED"


def test_command_never_acknowledged(fake_factory) -> None:
    port = free_udp_port()
    fake = fake_factory(port, ack=lambda m: None)
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5, command_retries=3, command_timeout=0.3) as v:
        t0 = time.monotonic()
        with pytest.raises(CommandTimeout) as info:
            v.arm()
        assert isinstance(info.value, TimeoutError)
        assert 0.8 < time.monotonic() - t0 < 3.0
        tries = [m for m in fake.of_type("COMMAND_LONG") if m.command == 400]
        assert [m.confirmation for m in tries] == [0, 1, 2]
        assert all(m.target_system == 1 and m.target_component == 1 for m in tries)


def test_command_rejected_carries_text(fake_factory) -> None:
    port = free_udp_port()
    fake_factory(port, ack=lambda m: 1 if m.command == 400 else 0, text="Arming denied: no GPS fix")
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5) as v, pytest.raises(CommandRejected) as info:
        v.arm()
    assert info.value.result == 1 and info.value.command == 400
    assert "no GPS fix" in info.value.text and "no GPS fix" in str(info.value)


def test_in_progress_keeps_waiting(fake_factory) -> None:
    port = free_udp_port()
    calls = {"n": 0}

    def ack(m: Any) -> int | None:
        if m.command != 400:
            return 0
        calls["n"] += 1
        return 5 if calls["n"] == 1 else None  # IN_PROGRESS, then silence

    fake = fake_factory(port, ack=ack)
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5, command_timeout=0.3) as v:

        def finish() -> None:
            time.sleep(0.6)  # longer than one try: still waiting thanks to IN_PROGRESS
            fake.conn.mav.command_ack_send(400, 0, 0, 0, v.target_system, 191)
            fake.conn.mav.heartbeat_send(2, 12, 1 | 128, 0, 4)

        threading.Thread(target=finish, daemon=True).start()
        v.arm()
        assert calls["n"] == 1


def test_bad_setpoints_are_never_sent(fake_factory) -> None:
    port = free_udp_port()
    fake = fake_factory(port, ack=lambda m: 0)
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5, setpoint_rate_hz=20) as v:
        for args in BAD_LOCAL:
            with pytest.raises(SetpointError):
                v.set_target_ned(*args)
        for args in BAD_GLOBAL:
            with pytest.raises(SetpointError):
                v.set_target_global(*args)
        with pytest.raises(SetpointError):
            v.takeoff(math.nan)
        time.sleep(0.3)
        assert not v.streaming
        assert not fake.of_type("SET_POSITION_TARGET_LOCAL_NED")
        assert not fake.of_type("SET_POSITION_TARGET_GLOBAL_INT")
        # a good one streams, yaw finite (current yaw when none is given)
        v.set_target_ned(5, 0, -10)
        time.sleep(0.6)
        sent = fake.of_type("SET_POSITION_TARGET_LOCAL_NED")
        assert len(sent) >= 5
        assert all(m.type_mask == 2552 and m.coordinate_frame == 1 and math.isfinite(m.yaw) for m in sent)
        # a bad update keeps the old target, still nothing bad on the wire
        with pytest.raises(SetpointError):
            v.set_target_ned(math.nan, 0, -10)
        v.stop_setpoints()
        assert not v.streaming
        time.sleep(0.2)  # let the last datagram in flight arrive
        n = len(fake.of_type("SET_POSITION_TARGET_LOCAL_NED"))
        time.sleep(0.3)
        assert len(fake.of_type("SET_POSITION_TARGET_LOCAL_NED")) == n
        assert all(m.x == 5 for m in fake.of_type("SET_POSITION_TARGET_LOCAL_NED"))
        assert len(v.setpoint_intervals()) >= 4


def test_link_lost_and_restored(fake_factory) -> None:
    port = free_udp_port()
    fake = fake_factory(port)
    lost, restored = threading.Event(), threading.Event()
    with drv.connect(
        f"udpin:127.0.0.1:{port}",
        timeout=5,
        link_timeout=0.5,
        on_link_lost=lost.set,
        on_link_restored=restored.set,
    ) as v:
        assert v.link_ok
        fake.heartbeats = False
        assert lost.wait(5) and not v.link_ok
        assert not restored.is_set()
        fake.heartbeats = True
        assert restored.wait(5) and v.link_ok


def test_signing(fake_factory) -> None:
    key = bytes(range(32))
    port = free_udp_port()
    fake = fake_factory(port, signing_key=key)
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5, signing_key=key) as v:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not fake.of_type("HEARTBEAT"):
            time.sleep(0.05)
        assert fake.of_type("HEARTBEAT")
        assert all(m._signed for m in fake.of_type("HEARTBEAT"))  # noqa: SLF001 (pymavlink's signed flag)
        assert v.state.last_heartbeat_time > 0


def test_signing_timestamps_follow_the_wall_clock(fake_factory, monkeypatch) -> None:
    """pymavlink stamps the first frame with the wall clock and adds 10 µs per frame after
    that, so a companion's stamps lagged by its uptime; an autopilot rebooted after a
    minute (its own clock from GPS) would refuse the stream as a replay."""
    key = bytes(range(32))
    port = free_udp_port()
    fake = fake_factory(port, signing_key=key)
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5, signing_key=key):
        later = time.time() + 90.0
        monkeypatch.setattr(time, "time", lambda: later)
        want = int((later - 1420070400) * 100_000)

        def newest() -> int:
            return max(fake.conn.mav.signing.stream_timestamps.values(), default=0)

        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and newest() < want:
            time.sleep(0.05)
        assert newest() >= want  # the companion heartbeat (1 Hz) carries the new time


def test_signing_refuses_unsigned_vehicle(fake_factory) -> None:
    port = free_udp_port()
    fake_factory(port)  # unsigned heartbeats
    with pytest.raises(HeartbeatTimeout):
        drv.connect(f"udpin:127.0.0.1:{port}", timeout=1.0, signing_key=bytes(32 * [7]))


def test_setpoint_with_velocity_feed_forward() -> None:
    t = drv.validate_global(47.397742, 8.545594, 10, 0.0, velocity=(5.0, -1.0, 0.0))
    got = _roundtrip(drv.setpoint_message(t, time_boot_ms=1, target_system=1, target_component=1))
    assert got.type_mask == 2496  # position, velocity and yaw used
    assert (got.vx, got.vy, got.vz) == (5.0, -1.0, 0.0)
    loc = _roundtrip(
        drv.setpoint_message(
            drv.validate_local(1, 2, -3, 0.0, velocity=(0, 1, 0)),
            time_boot_ms=1,
            target_system=1,
            target_component=1,
        )
    )
    assert loc.type_mask == 2496 and loc.vy == 1.0
    for bad in ((math.nan, 0, 0), (0, 0), (40.0, 0, 0)):
        with pytest.raises(drv.SetpointError):
            drv.validate_global(47.0, 8.0, 10, 0.0, velocity=bad)


def test_udpin_locks_onto_one_autopilot_and_says_so_when_another_appears(
    fake_factory, caplog: pytest.LogCaptureFixture
) -> None:
    """``udpin:`` takes datagrams from every sender on its port. With a second vehicle
    sending there, the driver sent every command to both (pymavlink writes to every
    client it heard) and read the other's telemetry too; now it keeps to the
    autopilot whose heartbeat it took, and says once that another one is there."""
    port = free_udp_port()
    first = fake_factory(port, sysid=1, ack=lambda m: 0)
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5) as v:
        second = fake_factory(port, sysid=2, ack=lambda m: 0, custom_mode=custom_mode_of("px4", "AUTO.LAND"))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not any("another" in r.getMessage() for r in caplog.records):
            time.sleep(0.05)
        v.send_command_nowait(176, (1, 1, 0))  # a DO_SET_MODE: only the locked autopilot may get it
        v.command(512, (242,))  # REQUEST_MESSAGE, acknowledged
        time.sleep(0.5)
        assert v.target_system == 1 and v.state.system_id == 1
        assert first.of_type("COMMAND_LONG") and not second.of_type("COMMAND_LONG")
        assert not second.of_type("HEARTBEAT")  # not even the companion's heartbeat
    said = [r.getMessage() for r in caplog.records if "another" in r.getMessage()]
    assert len(said) == 1 and "system 2" in said[0] and "locked" in said[0], said


def test_udpin_follows_its_autopilot_restarted_from_a_new_port(fake_factory, caplog) -> None:
    """A simulator (or a UDP bridge) restarted sends from a new port: after a silence
    of the locked address, the same system id from elsewhere is the autopilot again
    (the lock above kept a restarted simulator out for good); another system id still
    is not."""
    port = free_udp_port()
    first = fake_factory(port, sysid=1, ack=lambda m: 0)
    with drv.connect(f"udpin:127.0.0.1:{port}", timeout=5, link_timeout=1.0) as v:
        first.close()  # killed
        time.sleep(4.0)  # longer than the silence that allows a new address
        stranger = fake_factory(port, sysid=2, ack=lambda m: 0)
        again = fake_factory(port, sysid=1, ack=lambda m: 0, custom_mode=custom_mode_of("px4", "AUTO.LAND"))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not (v.state.mode == "AUTO.LAND" and v.link_ok):
            time.sleep(0.05)  # the link is said back at the housekeeper's next look
        assert v.state.mode == "AUTO.LAND" and v.link_ok
        v.command(512, (242,))
        time.sleep(0.3)
        assert again.of_type("COMMAND_LONG") and not stranger.of_type("COMMAND_LONG")
    assert any("is now at" in r.getMessage() for r in caplog.records)
