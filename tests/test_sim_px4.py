"""The simulator's PX4 profile, flown by plain pymavlink scripts (and its I/O-free core).

The clients here are the kind of script PX4's docs show: ``mavlink_connection`` on
``udpin``, ``wait_heartbeat``, ``command_long_send``, ``set_position_target_local_ned_send``
and ``recv_match``. The simulator runs 5x faster than wall time; every wait polls
for the outcome until a generous deadline.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator

import pytest
from mav_helpers import EVENT, command, event_id, event_text, wait_msg
from net_helpers import free_port_range
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.sim import Autopilot, SimConfig, VehicleSim, px4_boot

pytestmark = pytest.mark.processes  # the vehicle simulator, in real time

SPEEDUP = 5.0
DEADLINE = 20.0  # wall seconds, only bounds a failing test
OFFBOARD = (1, 6, 0)  # DO_SET_MODE params 1-3
HOLD = (1, 4, 3)
POS_MASK = 3576
M = mavlink


@pytest.fixture
def sim() -> Iterator[VehicleSim]:
    s = VehicleSim(SimConfig(vehicles=2, profile="px4", speedup=SPEEDUP, base_port=free_port_range(2, "udp")))
    s.start()
    yield s
    s.stop()


@pytest.fixture
def slow_sim() -> Iterator[VehicleSim]:
    """2x only: the offboard stream must beat COM_OF_LOSS_T (0.5 s wall) on a busy machine."""
    s = VehicleSim(SimConfig(vehicles=1, profile="px4", speedup=2.0, base_port=free_port_range(1, "udp")))
    s.start()
    yield s
    s.stop()


def connect(endpoint: str) -> mavutil.mavfile:
    conn = mavutil.mavlink_connection(endpoint, source_system=255)
    assert conn.wait_heartbeat(timeout=DEADLINE) is not None
    return conn


class Streamer:
    """Sends a LOCAL_NED setpoint at ~20 Hz wall (4 Hz simulated) whenever ``tick`` runs."""

    def __init__(self, conn: mavutil.mavfile, x: float, y: float, z: float, frame: int = 1) -> None:
        self.conn, self.sp, self.frame, self.last = conn, (x, y, z), frame, 0.0
        self.on = True

    def tick(self) -> None:
        now = time.monotonic()
        if self.on and now - self.last >= 0.05:
            self.last = now
            x, y, z = self.sp
            self.conn.mav.set_position_target_local_ned_send(
                0, self.conn.target_system, 1, self.frame, POS_MASK & ~1024, x, y, z, 0, 0, 0, 0, 0, 0, 0.0, 0
            )


def settle(
    sim: VehicleSim,
    target: tuple[float, float, float],
    tol: float,
    tick: Callable[[], None] | None = None,
    conn: mavutil.mavfile | None = None,
) -> None:
    """Wait until the vehicle stays within ``tol`` of ``target`` for 2 simulated s."""
    v = sim.vehicle(0)
    deadline = time.monotonic() + DEADLINE * 2
    since = None
    while time.monotonic() < deadline:
        if tick is not None:
            tick()
        if conn is not None:
            conn.recv_match(blocking=True, timeout=0.02)
        else:
            time.sleep(0.02)
        st = v.state
        if math.dist(st.position, target) < tol:
            since = st.time if since is None else since
            if st.time - since >= 2.0:
                return
        else:
            since = None
    raise AssertionError(f"never settled at {target}: {v.state}")


def test_heartbeat_fields(sim: VehicleSim) -> None:
    conns = [connect(ep) for ep in sim.endpoints]
    for i, c in enumerate(conns):
        hb = wait_msg(c, "HEARTBEAT")
        assert hb.get_srcSystem() == i + 1 and hb.get_srcComponent() == 1
        assert hb.autopilot == 12 and hb.type == 2
        assert hb.custom_mode == 50593792  # AUTO.LOITER: 4<<16 | 3<<24
        assert hb.base_mode & 1 and not hb.base_mode & 128
        assert hb.system_status == 3
        assert c.mavlink20()
    # PX4 streams by default on the onboard link
    wait_msg(conns[0], "GLOBAL_POSITION_INT")
    wait_msg(conns[0], "EXTENDED_SYS_STATE", lambda m: m.landed_state == 1)
    hp = wait_msg(conns[0], "HOME_POSITION")
    assert abs(hp.latitude / 1e7 - 47.397742) < 1e-6


def test_arm_rejected_without_gps(sim: VehicleSim) -> None:
    c = connect(sim.endpoints[0])
    sim.vehicle(0).fail_gps(True)
    texts: list[str] = []
    assert command(c, 400, 1, texts=texts) == 1  # TEMPORARILY_REJECTED
    # as PX4 v1.15: no STATUSTEXT for the refusal, its EVENT (and the checks' report)
    assert event_text(px4_boot.ARMING_DENIED[0]) in texts, texts
    assert not sim.vehicle(0).state.armed
    sim.vehicle(0).fail_gps(False)
    assert command(c, 400, 1) == 0


def test_unknown_command_unsupported_and_other_sysid_ignored(sim: VehicleSim) -> None:
    c = connect(sim.endpoints[0])
    assert command(c, 31337, 1) == 3
    c.mav.command_long_send(7, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)  # not us
    assert c.recv_match(type="COMMAND_ACK", blocking=True, timeout=1.0) is None
    assert not sim.vehicle(0).state.armed


@pytest.mark.timing  # a 20 Hz setpoint stream never paused 0.5 s; the failsafe within 3 s
def test_offboard_rules_flight_and_failsafe(slow_sim: VehicleSim) -> None:
    sim = slow_sim
    c = connect(sim.endpoints[0])
    texts: list[str] = []
    # armed in Hold without a stream: OFFBOARD temporarily rejected
    assert command(c, 400, 1) == 0
    assert command(c, 176, *OFFBOARD, texts=texts) == 1
    assert any("Offboard" in t for t in texts)
    assert command(c, 400, 0) == 0
    # stream first, then OFFBOARD (accepted while disarmed), then arm: take off to 10 m
    s = Streamer(c, 0.0, 0.0, -10.0)
    for _ in range(10):
        s.tick()
        time.sleep(0.05)
    assert command(c, 176, *OFFBOARD, tick=s.tick) == 0
    assert command(c, 400, 1, tick=s.tick) == 0
    wait_msg(c, "HEARTBEAT", lambda m: m.custom_mode == 393216 and m.base_mode & 128, tick=s.tick)
    settle(sim, (0.0, 0.0, -10.0), 0.5, tick=s.tick, conn=c)
    wait_msg(c, "EXTENDED_SYS_STATE", lambda m: m.landed_state == 2, tick=s.tick)
    gpi = wait_msg(c, "GLOBAL_POSITION_INT", tick=s.tick)
    assert abs(gpi.relative_alt - 10000) < 600 and abs(gpi.alt - 498000) < 600
    echo = wait_msg(c, "POSITION_TARGET_LOCAL_NED", tick=s.tick)
    assert echo.coordinate_frame == 1 and abs(echo.z + 10.0) < 1e-3 and not echo.type_mask & 7
    # 20 m north
    s.sp = (20.0, 0.0, -10.0)
    settle(sim, (20.0, 0.0, -10.0), 0.5, tick=s.tick, conn=c)
    # stream stops: failsafe to Position mode (PX4's default) with its EVENT within
    # COM_OF_LOSS_T + margin
    s.on = False
    t0 = sim.vehicle(0).state.time
    wait_msg(c, EVENT, lambda m: event_id(m) == px4_boot.FAILSAFE_DISENGAGED)
    hb = wait_msg(c, "HEARTBEAT", lambda m: m.custom_mode == 3 << 16)
    assert hb.system_status == 5  # CRITICAL: armed + failsafe
    assert sim.vehicle(0).state.mode == "POSCTL"
    assert sim.vehicle(0).state.time - t0 < 1.0 + 2.0
    # disarm in the air refused without force
    assert command(c, 400, 0) == 1
    assert command(c, 400, 0, 21196) == 0


def test_frames_7_and_9_dropped_with_statustext(sim: VehicleSim) -> None:
    c = connect(sim.endpoints[0])
    s = Streamer(c, 0.0, 0.0, -5.0, frame=7)
    txt = wait_msg(c, "STATUSTEXT", lambda m: "unsupported" in m.text, tick=s.tick)
    assert "frame 7" in txt.text
    s.frame = 9
    wait_msg(c, "STATUSTEXT", lambda m: "frame 9" in m.text, tick=s.tick)
    # dropped: no proof of life, so arming in OFFBOARD is refused
    assert command(c, 176, *OFFBOARD, tick=s.tick) == 0
    texts: list[str] = []
    assert command(c, 400, 1, tick=s.tick, texts=texts) == 1
    assert event_text(px4_boot.ARMING_DENIED[0]) in texts, texts


def test_auto_disarm_without_takeoff(sim: VehicleSim) -> None:
    c = connect(sim.endpoints[0])
    assert command(c, 400, 1) == 0
    t_arm = sim.vehicle(0).state.time
    wait_msg(c, "HEARTBEAT", lambda m: not m.base_mode & 128, timeout=DEADLINE)
    assert sim.vehicle(0).state.time - t_arm >= 10.0 - 0.5


def test_nav_takeoff_amsl_then_land(sim: VehicleSim) -> None:
    c = connect(sim.endpoints[0])
    assert command(c, 400, 1) == 0
    assert command(c, 22, 0, 0, 0, math.nan, math.nan, math.nan, 488.0 + 6.0) == 0
    wait_msg(c, "HEARTBEAT", lambda m: m.custom_mode == 33816576)  # AUTO.TAKEOFF
    wait_msg(c, "HEARTBEAT", lambda m: m.custom_mode == 50593792)  # then AUTO.LOITER within 0.8 m
    assert abs(sim.vehicle(0).state.position[2] + 6.0) < 0.8
    assert command(c, 21) == 0
    wait_msg(c, "HEARTBEAT", lambda m: not m.base_mode & 128, timeout=DEADLINE * 2)
    assert sim.vehicle(0).state.landed_state == 1


@pytest.mark.timing  # heartbeats back within 0.8 s
def test_drop_link_silences_heartbeats(sim: VehicleSim) -> None:
    c = connect(sim.endpoints[0])
    wait_msg(c, "HEARTBEAT")
    sim.vehicle(0).drop_link(4.0)  # simulated s = 0.8 s wall
    t0 = time.monotonic()
    last = t0
    gap = 0.0
    while time.monotonic() - t0 < 2.5:
        m = c.recv_match(type="HEARTBEAT", blocking=True, timeout=0.05)
        if m is not None:
            now = time.monotonic()
            gap = max(gap, now - last)
            last = now
    assert gap >= 0.5, gap
    assert time.monotonic() - last < 0.8  # heartbeats came back


def test_latency_delays_replies(sim: VehicleSim) -> None:
    c = connect(sim.endpoints[0])
    sim.vehicle(0).set_latency(2.5)  # 0.5 s wall
    t0 = time.monotonic()
    assert command(c, 31337) == 3
    assert time.monotonic() - t0 >= 0.3


# ---------------------------------------------------------------- core (no I/O)
HOME = (47.397742, 8.545594, 488.0)


def _client() -> mavlink.MAVLink:
    return mavlink.MAVLink(None, 255, 0)


def _roundtrip(client: mavlink.MAVLink, msg: mavlink.MAVLink_message) -> mavlink.MAVLink_message:
    rx = mavlink.MAVLink(None, 0, 0)
    out = rx.parse_buffer(msg.pack(client))
    assert out
    return out[0]


def _fly_script(seed: int) -> tuple[list[tuple[float, ...]], list[bytes]]:
    import random

    ap = Autopilot("px4", 1, HOME, rng=random.Random(seed))
    cl = _client()
    enc = mavlink.MAVLink(None, 0, 0)
    samples: list[tuple[float, ...]] = []
    wire: list[bytes] = []
    t = 0.0

    def feed(msg: mavlink.MAVLink_message) -> None:
        for m in ap.handle(_roundtrip(cl, msg), t):
            wire.append(m.pack(enc))

    for step in range(600):  # 30 simulated s at 20 Hz
        t = step * 0.05
        sp = (0.0, 0.0, -10.0) if t < 12 else (20.0, 5.0, -10.0)
        feed(cl.set_position_target_local_ned_encode(0, 1, 1, 1, POS_MASK, *sp, 0, 0, 0, 0, 0, 0, 0, 0))
        if step == 20:
            feed(cl.command_long_encode(1, 1, 176, 0, *OFFBOARD, 0, 0, 0, 0))
        if step == 21:
            feed(cl.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
        for m in ap.tick(t):
            wire.append(m.pack(enc))
        st = ap.snapshot()
        samples.append((*st.position, *st.velocity, st.yaw))
    return samples, wire


def test_determinism_same_seed_same_trajectory_and_telemetry() -> None:
    a, wa = _fly_script(3)
    b, wb = _fly_script(3)
    assert a == b and wa == wb
    assert math.dist(a[-1][:3], (20.0, 5.0, -10.0)) < 0.5
    _, wc = _fly_script(4)
    assert wc != wa  # the seed drives the telemetry noise


def test_core_setpoint_parsing_px4() -> None:
    ap = Autopilot("px4", 1, HOME)
    cl = _client()
    # FORCE with acceleration: rejected, no proof of life
    ap.handle(
        _roundtrip(
            cl,
            cl.set_position_target_local_ned_encode(0, 1, 1, 1, 3135 | 512, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0),
        ),
        0.1,
    )
    assert ap.flavour.setpoint is None
    # nothing set: invalid
    ap.handle(
        _roundtrip(
            cl, cl.set_position_target_local_ned_encode(0, 1, 1, 1, 0xFFF, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
        ),
        0.2,
    )
    assert ap.flavour.setpoint is None
    # addressed to another system: ignored
    ap.handle(
        _roundtrip(
            cl,
            cl.set_position_target_local_ned_encode(0, 9, 1, 1, POS_MASK, 1, 2, -3, 0, 0, 0, 0, 0, 0, 0, 0),
        ),
        0.3,
    )
    assert ap.flavour.setpoint is None
    # BODY_NED velocity, position ignored
    ap.handle(
        _roundtrip(
            cl, cl.set_position_target_local_ned_encode(0, 1, 1, 8, 3520, 5, 5, 5, 1, 0, 0, 0, 0, 0, 0, 0)
        ),
        0.4,
    )
    assert ap.flavour.setpoint is not None and all(math.isnan(x) for x in ap.flavour.setpoint.pos)
    assert ap.flavour.setpoint.vel[0] == pytest.approx(1.0)
    # global relative-alt frame projected to local NED
    ap.handle(
        _roundtrip(
            cl,
            cl.set_position_target_global_int_encode(
                0, 1, 1, 6, POS_MASK, int(HOME[0] * 1e7), int(HOME[1] * 1e7), 7.0, 0, 0, 0, 0, 0, 0, 0, 0
            ),
        ),
        0.5,
    )
    assert ap.flavour.setpoint.pos[2] == pytest.approx(-7.0) and abs(ap.flavour.setpoint.pos[0]) < 0.02
    # the packed custom_mode in param2 is cast to uint8: accepted no-op (a PX4 pitfall)
    out = ap.handle(_roundtrip(cl, cl.command_long_encode(1, 1, 176, 0, 1, 393216, 0, 0, 0, 0, 0)), 0.6)
    assert [m.result for m in out if m.get_type() == "COMMAND_ACK"] == [0]
    assert ap.mode == "AUTO.LOITER"


def test_offboard_loss_action_land() -> None:
    ap = Autopilot("px4", 1, HOME, offboard_loss_action="land")
    cl = _client()
    t = 0.0
    for step in range(200):
        t = step * 0.05
        ap.handle(
            _roundtrip(
                cl,
                cl.set_position_target_local_ned_encode(
                    0, 1, 1, 1, POS_MASK, 0, 0, -5, 0, 0, 0, 0, 0, 0, 0, 0
                ),
            ),
            t,
        )
        if step == 2:
            ap.handle(_roundtrip(cl, cl.command_long_encode(1, 1, 176, 0, *OFFBOARD, 0, 0, 0, 0)), t)
            ap.handle(_roundtrip(cl, cl.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)), t)
    out = ap.tick(t + 1.5)
    assert ap.mode == "AUTO.LAND" and ap.failsafe
    failsafe = [m for m in out if m.get_type() == "EVENT" and m.id == px4_boot.FAILSAFE_DISENGAGED]
    assert [m.arguments[-1] for m in failsafe] == [px4_boot.FAILSAFE_ACTIONS["AUTO.LAND"]]
