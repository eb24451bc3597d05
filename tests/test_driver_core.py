"""The driver's pure cores without a socket, a thread or a sleep: telemetry folding,
link watching, stream re-requests and the command/ACK/retry machine, fed real MAVLink 2
bytes built in memory (packed by one pymavlink MAVLink object, parsed by another) and
times from a manual clock."""

from __future__ import annotations

import math
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega

from firmware_bridge.commands import (
    Accepted,
    CommandExchange,
    Rejected,
    TimedOut,
    command_long,
)
from firmware_bridge.errors import CommandRejected, CommandTimeout, SetpointError
from firmware_bridge.modes import custom_mode_of
from firmware_bridge.setpoints import validate_takeoff_altitude
from firmware_bridge.telemetry import (
    HOME_REQUEST,
    CommandAck,
    Heard,
    LinkWatch,
    StatusText,
    StreamRequests,
    TelemetryFolder,
    VehicleState,
)

mavlink: Any = ardupilotmega

OUR_SYSID = 1  # the companion shares the vehicle's system id, as connect() does by default
ARMED = 1 | 128  # CUSTOM_MODE_ENABLED | SAFETY_ARMED


class Clock:
    """A manual clock: the test moves it, nothing else does."""

    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        self.t += dt
        return self.t


class Wire:
    """Builds messages as a MAVLink sender with ``sysid``/``compid`` puts them on the
    wire, and parses them back as the driver's link would: real bytes, no socket."""

    def __init__(self, sysid: int = 1, compid: int = 1) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.rx = mavlink.MAVLink(None)

    def __call__(self, msg: Any) -> Any:
        got = self.rx.parse_buffer(msg.pack(self.mav))
        assert got is not None and len(got) == 1
        return got[0]

    def heartbeat(self, custom_mode: int = 0, base_mode: int = 1, autopilot: int = 12, type_: int = 2) -> Any:
        return self(mavlink.MAVLink_heartbeat_message(type_, autopilot, base_mode, custom_mode, 4, 3))

    def ack(self, command: int, result: int, target_system: int = OUR_SYSID) -> Any:
        return self(mavlink.MAVLink_command_ack_message(command, result, 0, 0, target_system, 191))

    def text(self, text: str, severity: int = 3) -> Any:
        return self(mavlink.MAVLink_statustext_message(severity, text.encode()))


def folder(autopilot: str = "px4") -> TelemetryFolder:
    return TelemetryFolder(autopilot, target_system=1, target_component=1, own_system=OUR_SYSID)


# --- telemetry folding ------------------------------------------------------------------
def test_heartbeat_gives_mode_armed_and_times() -> None:
    f, ap = folder(), Wire()
    f.fold(ap.heartbeat(custom_mode_of("px4", "OFFBOARD"), ARMED), 5.0)
    s = f.state
    assert (s.mode, s.armed, s.last_heartbeat_time, s.last_message_time) == ("OFFBOARD", True, 5.0, 5.0)
    assert (s.autopilot, s.system_id, s.component_id) == ("px4", 1, 1)
    f.fold(ap.heartbeat(custom_mode_of("px4", "AUTO.LOITER"), 1), 6.0)
    assert (f.state.mode, f.state.armed) == ("AUTO.LOITER", False)
    ardu = folder("ardupilot")
    ardu.fold(Wire().heartbeat(4, 1, autopilot=3), 1.0)
    assert ardu.state.mode == "GUIDED"


def test_only_the_autopilot_is_folded() -> None:
    f = folder()
    f.fold(Wire().heartbeat(custom_mode_of("px4", "POSCTL")), 1.0)
    before = f.state
    # another system, another component of ours, a GCS and a companion on the same link
    assert f.fold(Wire(sysid=2).heartbeat(custom_mode_of("px4", "OFFBOARD"), ARMED), 2.0) == Heard()
    assert f.fold(Wire(compid=154).heartbeat(custom_mode_of("px4", "OFFBOARD"), ARMED), 2.0) == Heard()
    f.fold(Wire().heartbeat(0, 0, autopilot=8, type_=6), 2.0)  # a GCS heartbeat with our ids
    f.fold(Wire().heartbeat(0, 0, autopilot=8, type_=18), 2.0)  # a companion's
    f.fold(Wire(sysid=2).ack(400, 0), 2.0)
    assert f.state == before
    assert f.fold(mavlink.MAVLink_bad_data(b"\xfd\x00", "garbage"), 3.0) == Heard()
    assert f.state == before


def test_positions_attitude_and_their_fallbacks() -> None:
    f, ap = folder(), Wire()
    gpi = mavlink.MAVLink_global_position_int_message(
        1234, 473977420, 85455940, 498_000, 10_500, 150, -20, 5, 9000
    )
    f.fold(ap(gpi), 10.0)
    s = f.state
    assert (s.lat, s.lon) == pytest.approx((47.397742, 8.545594))
    assert (s.alt_amsl, s.rel_alt, s.time_boot_ms, s.position_time) == pytest.approx(
        (498.0, 10.5, 1234, 10.0)
    )
    assert s.velocity == pytest.approx((1.5, -0.2, 0.05))  # no LOCAL_POSITION_NED yet: from here
    assert s.yaw == pytest.approx(math.pi / 2)  # no ATTITUDE yet: the heading
    f.fold(ap(mavlink.MAVLink_local_position_ned_message(1, 3.0, 4.0, -10.0, 0.5, 0.25, 0.0)), 10.1)
    f.fold(ap(mavlink.MAVLink_attitude_message(1, 0.0, 0.0, 3 * math.pi / 2, 0, 0, 0)), 10.1)
    assert f.state.ned == (3.0, 4.0, -10.0) and f.state.velocity == (0.5, 0.25, 0.0)
    assert f.state.yaw == pytest.approx(-math.pi / 2)  # wrapped to -pi..pi
    f.fold(ap(gpi), 10.5)  # the better sources are fresh: kept
    assert f.state.velocity == (0.5, 0.25, 0.0) and f.state.yaw == pytest.approx(-math.pi / 2)
    f.fold(ap(gpi), 11.2)  # ... and stale after a second: the fallbacks again
    assert f.state.velocity == pytest.approx((1.5, -0.2, 0.05)) and f.state.yaw == pytest.approx(math.pi / 2)


def test_hostile_values_are_not_folded() -> None:
    f, ap = folder(), Wire()
    f.fold(ap(mavlink.MAVLink_local_position_ned_message(1, 3.0, 4.0, -10.0, 0, 0, 0)), 1.0)
    f.fold(ap(mavlink.MAVLink_attitude_message(1, 0.0, 0.0, 0.5, 0, 0, 0)), 1.0)
    for bad in (math.nan, math.inf):
        f.fold(ap(mavlink.MAVLink_local_position_ned_message(2, bad, 0.0, 0.0, 0, 0, 0)), 5.0)
        f.fold(ap(mavlink.MAVLink_attitude_message(2, 0.0, 0.0, bad, 0, 0, 0)), 5.0)
    assert f.state.ned == (3.0, 4.0, -10.0) and f.state.yaw == pytest.approx(0.5)
    assert f.state.last_message_time == 5.0  # heard, though: the link is alive
    # an unknown heading (65535) keeps the yaw even when ATTITUDE is stale
    f.fold(ap(mavlink.MAVLink_global_position_int_message(1, 0, 0, 0, 0, 0, 0, 0, 65535)), 9.0)
    assert f.state.yaw == pytest.approx(0.5)


def test_battery_gps_and_home() -> None:
    f, ap = folder(), Wire()
    gps_bit = 32

    def sys_status(healthy: bool, voltage_mv: int) -> Any:
        health = gps_bit if healthy else 0
        return ap(
            mavlink.MAVLink_sys_status_message(
                gps_bit, gps_bit, health, 0, voltage_mv, -1, 76, 0, 0, 0, 0, 0, 0
            )
        )

    f.fold(sys_status(True, 65535), 1.0)
    assert (f.state.battery_remaining, f.state.voltage, f.state.gps_ok) == (76, None, True)
    f.fold(sys_status(False, 12_600), 2.0)
    assert f.state.voltage == pytest.approx(12.6) and not f.state.gps_ok
    # once GPS_RAW_INT speaks, it decides (SYS_STATUS no longer does)
    f.fold(ap(mavlink.MAVLink_gps_raw_int_message(0, 3, 0, 0, 0, 100, 100, 0, 0, 9)), 3.0)
    assert f.state.gps_ok
    f.fold(sys_status(False, 12_600), 4.0)
    assert f.state.gps_ok
    f.fold(ap(mavlink.MAVLink_gps_raw_int_message(0, 1, 0, 0, 0, 100, 100, 0, 0, 0)), 5.0)
    assert not f.state.gps_ok
    home = mavlink.MAVLink_home_position_message(473977420, 85455940, 488_000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0)
    f.fold(ap(home), 6.0)
    assert f.state.home == pytest.approx((47.397742, 8.545594, 488.0))


def test_in_air_from_landed_state_or_altitude() -> None:
    f, ap = folder(), Wire()
    assert not f.state.in_air
    f.fold(ap.heartbeat(0, ARMED), 1.0)
    f.fold(ap(mavlink.MAVLink_global_position_int_message(1, 0, 0, 0, 2_000, 0, 0, 0, 0)), 1.0)
    assert f.state.in_air  # armed and above 0.5 m, no EXTENDED_SYS_STATE
    f.fold(ap(mavlink.MAVLink_extended_sys_state_message(0, 1)), 2.0)  # ON_GROUND says otherwise
    assert not f.state.in_air
    f.fold(ap(mavlink.MAVLink_extended_sys_state_message(0, 4)), 3.0)  # LANDING is in the air
    assert f.state.in_air
    assert not VehicleState(armed=True, rel_alt=0.4).in_air


def test_statustexts_and_acks_are_heard() -> None:
    f, ap = folder(), Wire()
    heard = f.fold(ap.text("Arming denied: no GPS fix"), 7.0)
    assert heard == Heard(text=StatusText(7.0, 3, "Arming denied: no GPS fix"))
    # a text from another component of the vehicle (a camera) is kept, its state is not touched
    heard = f.fold(Wire(compid=100).text("camera ready", 6), 7.5)
    assert heard.text is not None and heard.text.text == "camera ready"
    assert f.texts_since(7.2) == ["camera ready"] and len(f.texts_since(0)) == 2
    assert f.fold(ap.ack(400, 4), 8.0) == Heard(ack=CommandAck(400, 4, 8.0))
    assert f.fold(ap.ack(400, 0, target_system=0), 8.0).ack == CommandAck(400, 0, 8.0)  # broadcast
    assert f.fold(ap.ack(400, 0, target_system=9), 8.0) == Heard()  # someone else's
    assert f.state.last_message_time == 8.0


def test_a_long_statustext_in_chunks_is_joined() -> None:
    """MAVLink 2 cuts a text longer than 50 characters into chunks of one ``id``,
    numbered by ``chunk_seq``; the last is shorter than 50 (ArduPilot's long PreArm
    texts). Each chunk used to be a text of its own: the reason arrived cut."""
    f, ap = folder(), Wire()
    whole = "PreArm: Compass not healthy; " + "x" * 60 + " and the end"
    parts = [whole[i : i + 50] for i in range(0, len(whole), 50)]
    assert len(parts) == 3

    def chunk(seq: int, id_: int = 7, severity: int = 2) -> Any:
        return ap(mavlink.MAVLink_statustext_message(severity, parts[seq].encode(), id_, seq))

    assert f.fold(chunk(0), 1.0).text is None and f.fold(chunk(1), 1.01).text is None
    heard = f.fold(chunk(2), 1.02)
    assert heard.text == StatusText(1.02, 2, whole) and f.texts_since(0) == [whole]
    # a chunk lost: what came is kept, said to be cut, once the rest is overdue
    f.fold(chunk(0, id_=8), 2.0)
    f.fold(ap.heartbeat(), 4.0)
    assert f.texts_since(2.0) == [parts[0] + " [cut]"]
    # an id of 0 is a whole text, as before
    assert f.fold(ap.text("short"), 5.0).text == StatusText(5.0, 3, "short")


def test_texts_are_bounded() -> None:
    f, ap = folder(), Wire()
    for i in range(100):
        f.fold(ap.text(f"t{i}"), float(i))
    assert len(f.texts) == 32 and f.texts[-1].text == "t99"


# --- link watch and stream requests -------------------------------------------------------
def test_link_lost_once_and_restored_once() -> None:
    w = LinkWatch(2.0)
    assert w.check(10.0, 11.9) is None and w.ok
    assert w.check(10.0, 12.0) is None  # exactly the timeout: not yet
    assert w.check(10.0, 12.1) == "lost" and not w.ok
    assert w.check(10.0, 30.0) is None  # said once
    assert w.check(30.5, 31.0) == "restored" and w.ok
    assert w.check(31.0, 31.5) is None


def test_silent_streams_are_asked_for_again() -> None:
    r, clock = StreamRequests(), Clock(0.0)
    r.asked(33, 10.0, clock())
    r.asked(1, 0.25, clock())  # slow: 3 periods are 12 s
    seen: dict[int, float] = {}  # never heard
    assert r.due(seen, clock.advance(3.0)) == []  # asked 3 s ago: not more than 3 s
    assert r.due(seen, clock.advance(0.1)) == [(33, 10.0)]
    r.asked(33, 10.0, clock())
    assert r.due(seen, clock.advance(1.0)) == []  # asked again a moment ago
    seen[33] = clock()
    assert r.due(seen, clock.advance(2.5)) == []  # heard 2.5 s ago: fine
    assert r.due(seen, clock.t + 9.0) == [(33, 10.0), (1, 0.25)]  # 15.6 s since the start
    assert r.due(seen, 12.0) == [(33, 10.0)]  # message 1: not yet 3 periods of 4 s


def test_home_is_asked_for_until_known() -> None:
    r = StreamRequests()
    assert r.home_due(False, 10.0) and r.last_asked[HOME_REQUEST] == 10.0
    assert not r.home_due(False, 12.0)
    assert r.home_due(False, 13.5)
    assert not r.home_due(True, 30.0)


# --- the command exchange --------------------------------------------------------------------
def exchange(clock: Clock, *, tries: int = 3, per_try: float = 1.0, **kw: Any) -> CommandExchange:
    return CommandExchange(
        400, (1, 0), clock(), target_system=1, target_component=1, tries=tries, per_try=per_try, **kw
    )


def feed(ex: CommandExchange, f: TelemetryFolder, msg: Any, now: float) -> None:
    """As the driver does: fold the message, hand what it means to the exchange."""
    heard = f.fold(msg, now)
    for event in (heard.ack, heard.text):
        if event is not None:
            ex.handle(event, now)


def test_accepted_on_the_first_try() -> None:
    clock, f, ap = Clock(), folder(), Wire()
    ex = exchange(clock)
    first = Wire(sysid=OUR_SYSID, compid=191)(ex.start())  # real bytes, as the autopilot reads them
    assert first.get_type() == "COMMAND_LONG"
    assert (first.command, first.confirmation, first.param1, first.param7) == (400, 0, 1.0, 0.0)
    assert (first.target_system, first.target_component) == (1, 1)
    assert ex.next_deadline() == clock.t + 1.0
    assert ex.tick(clock.advance(0.5)) == []
    feed(ex, f, ap.ack(176, 0), clock())  # another command's ACK is not this one's
    assert ex.outcome is None
    feed(ex, f, ap.ack(400, 0), clock.advance(0.1))
    assert ex.outcome == Accepted() and ex.next_deadline() is None and ex.error("px4") is None
    assert ex.tick(clock.advance(10.0)) == []  # done: nothing more goes out


def test_retries_then_times_out() -> None:
    clock = Clock()
    ex = exchange(clock, tries=3, per_try=0.3)
    sent = [ex.start()]
    while (deadline := ex.next_deadline()) is not None:
        clock.t = deadline
        sent += ex.tick(clock())
    assert [m.confirmation for m in sent] == [0, 1, 2]
    assert all((m.command, m.target_system, m.target_component) == (400, 1, 1) for m in sent)
    assert clock.t == pytest.approx(100.9)
    assert ex.outcome == TimedOut(3, 0.3)
    err = ex.error("px4")
    assert isinstance(err, CommandTimeout) and isinstance(err, TimeoutError)
    assert str(err) == "COMPONENT_ARM_DISARM: no COMMAND_ACK from px4 after 3 tries of 0.3 s"


def test_a_late_ack_of_an_earlier_try_still_counts() -> None:
    clock, f, ap = Clock(), folder(), Wire()
    ex = exchange(clock)
    ex.start()
    assert len(ex.tick(clock.advance(1.0))) == 1  # the second try went out
    feed(ex, f, ap.ack(400, 0), clock.advance(0.2))
    assert ex.outcome == Accepted()


def test_rejection_carries_the_text_heard_just_before() -> None:
    clock, f, ap = Clock(), folder(), Wire()
    f.fold(ap.text("old news"), clock.t - 2.0)  # long before: not about this command
    f.fold(ap.text("Arming denied: no GPS fix"), clock.t - 0.2)
    ex = exchange(clock, texts=f.texts)
    ex.start()
    feed(ex, f, ap.ack(400, 1), clock.advance(0.1))
    assert ex.outcome == Rejected(1, "Arming denied: no GPS fix")
    err = ex.error("px4")
    assert isinstance(err, CommandRejected)
    assert (err.command, err.result, err.text) == (400, 1, "Arming denied: no GPS fix")
    assert (
        str(err) == "COMPONENT_ARM_DISARM rejected by px4: TEMPORARILY_REJECTED (Arming denied: no GPS fix)"
    )


def test_rejection_waits_a_moment_for_its_text() -> None:
    clock, f, ap = Clock(), folder(), Wire()
    ex = exchange(clock)
    ex.start()
    feed(ex, f, ap.ack(400, 4), clock.advance(0.1))
    assert ex.outcome is None and ex.next_deadline() == pytest.approx(clock.t + 0.3)
    feed(ex, f, ap.text("PreArm: Battery below minimum"), clock.advance(0.1))
    assert ex.outcome == Rejected(4, "PreArm: Battery below minimum")
    # without a text the refusal is reported after the grace, with no reason
    ex2 = exchange(clock)
    ex2.start()
    feed(ex2, f, Wire().ack(400, 2), clock.advance(0.1))
    assert ex2.tick(clock.advance(0.29)) == [] and ex2.outcome is None
    ex2.tick(clock.advance(0.01))
    assert ex2.outcome == Rejected(2, "")
    assert str(ex2.error("ardupilot")) == "COMPONENT_ARM_DISARM rejected by ardupilot: DENIED"
    feed(ex2, f, ap.ack(400, 0), clock.advance(0.1))  # too late to change its mind
    assert ex2.outcome == Rejected(2, "")


def test_a_refusal_is_explained_by_the_autopilots_reason_not_by_chatter() -> None:
    """ArduCopter sends "Arm: ..." just after its COMMAND_ACK; texts heard just before
    the command (boot messages at INFO) used to be taken as the reason at once."""
    clock, f, ap = Clock(), folder("ardupilot"), Wire()
    f.fold(ap.text("ArduPilot Ready", 6), clock.t - 0.3)
    f.fold(ap.text("AHRS: DCM active", 6), clock.t - 0.1)
    ex = exchange(clock, texts=f.texts)
    ex.start()
    feed(ex, f, ap.ack(400, 4), clock.advance(0.1))
    assert ex.outcome is None  # chatter is no reason: it waits for one
    feed(ex, f, ap.text("EKF3 IMU0 initialised", 6), clock.advance(0.02))
    assert ex.outcome is None
    feed(ex, f, ap.text("Arm: Need Position Estimate", 2), clock.advance(0.05))
    assert ex.outcome == Rejected(4, "Arm: Need Position Estimate")
    # with no reason within the grace, the chatter is all there is: said as it was
    ex2 = exchange(clock, texts=[StatusText(clock.t, 6, "GPS 1: detected")])
    ex2.start()
    feed(ex2, f, ap.ack(400, 4), clock.advance(0.1))
    ex2.tick(clock.advance(0.3))
    assert ex2.outcome == Rejected(4, "GPS 1: detected")


def test_unknown_result_codes_are_refusals() -> None:
    clock, f, ap = Clock(), folder(), Wire()
    ex = exchange(clock, texts=[StatusText(clock.t, 3, "no")])
    ex.start()
    feed(ex, f, ap.ack(400, 250), clock())
    assert ex.outcome == Rejected(250, "no") and "rejected by px4: 250 (no)" in str(ex.error("px4"))


def test_in_progress_keeps_waiting_up_to_its_limit() -> None:
    clock, f, ap = Clock(), folder(), Wire()
    ex = exchange(clock, tries=2, per_try=0.3, in_progress_timeout=8.0)
    ex.start()
    feed(ex, f, ap.ack(400, 5), clock.advance(0.1))  # IN_PROGRESS: at least 5 s more
    assert ex.next_deadline() == pytest.approx(clock.t + 5.0)
    assert ex.tick(clock.advance(4.0)) == [] and ex.outcome is None
    feed(ex, f, ap.ack(400, 5), clock())  # again: but not past 8 s after the try was sent
    assert ex.next_deadline() == pytest.approx(108.0)
    feed(ex, f, ap.ack(400, 0), clock.advance(1.0))
    assert ex.outcome == Accepted()
    # silence after IN_PROGRESS ends the try at its limit, and the next try goes out
    ex2 = exchange(clock, tries=2, per_try=0.3, in_progress_timeout=2.0)
    ex2.start()
    feed(ex2, f, ap.ack(400, 5), clock())
    retry = ex2.tick(clock.advance(2.0))
    assert [m.confirmation for m in retry] == [1]
    ex2.tick(clock.advance(0.3))
    assert ex2.outcome == TimedOut(2, 0.3)


def test_at_least_one_try_and_many_confirmations() -> None:
    clock = Clock()
    ex = exchange(clock, tries=0)
    ex.start()
    assert ex.tick(clock.advance(1.0)) == [] and ex.outcome == TimedOut(1, 1.0)
    ex = exchange(clock, tries=300, per_try=0.1)
    sent = [ex.start()]
    while (deadline := ex.next_deadline()) is not None:
        sent += ex.tick(deadline)
    assert len(sent) == 300 and sent[-1].confirmation == 255  # the field is a uint8


def test_command_long_pads_the_parameters() -> None:
    msg = Wire()(command_long(511, (33, 1e5), 0, target_system=3, target_component=1))
    params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
    assert params == [33.0, 1e5, 0, 0, 0, 0, 0] and msg.target_system == 3


# --- setpoints ------------------------------------------------------------------------------
def test_takeoff_altitude() -> None:
    assert validate_takeoff_altitude(10) == 10.0
    for bad in (math.nan, math.inf, 0.4, -5, 10_001, "high"):
        with pytest.raises(SetpointError):
            validate_takeoff_altitude(bad)  # type: ignore[arg-type]
