"""The simulator's ArduPilot profile, flown by plain pymavlink scripts over TCP.

Vehicle i listens on TCP base+10*i as ArduPilot SITL does; the simulator runs 5x
faster than wall time and every wait polls until a generous deadline.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator

import pytest
from mav_helpers import command, wait_msg
from net_helpers import free_port, free_port_range, wait_until
from pymavlink import mavutil

from firmware_bridge.sim import SimConfig, VehicleSim

pytestmark = pytest.mark.processes  # the vehicle simulator, in real time

SPEEDUP = 5.0
DEADLINE = 20.0
GUIDED = (1, 4)
POS_MASK = 3576


@pytest.fixture
def sim() -> Iterator[VehicleSim]:
    s = VehicleSim(
        SimConfig(
            vehicles=2,
            profile="ardupilot",
            speedup=SPEEDUP,
            home=(-35.363261, 149.165230, 584.0),
            base_port=free_port_range(2, "tcp", step=10),
        )
    )
    s.start()
    yield s
    s.stop()


@pytest.fixture
def conn(sim: VehicleSim) -> Iterator[mavutil.mavfile]:
    c = mavutil.mavlink_connection(sim.endpoints[0], source_system=255)
    assert c.wait_heartbeat(timeout=DEADLINE) is not None
    yield c
    c.close()


def wait_state(sim: VehicleSim, pred: Callable[[object], bool], what: str, timeout: float = DEADLINE) -> None:
    wait_until(lambda: pred(sim.vehicle(0).state), what, timeout, detail=lambda: sim.vehicle(0).state)


def settle(sim: VehicleSim, target: tuple[float, float, float], tol: float) -> None:
    deadline = time.monotonic() + DEADLINE * 2
    since = None
    while time.monotonic() < deadline:
        st = sim.vehicle(0).state
        if math.dist(st.position, target) < tol:
            since = st.time if since is None else since
            if st.time - since >= 2.0:
                return
        else:
            since = None
        time.sleep(0.02)
    raise AssertionError(f"never settled at {target}: {sim.vehicle(0).state}")


def take_off(sim: VehicleSim, c: mavutil.mavfile, alt: float = 10.0) -> None:
    assert command(c, 176, *GUIDED) == 0
    assert command(c, 400, 1) == 0
    assert command(c, 22, 0, 0, 0, 0, 0, 0, alt) == 0
    settle(sim, (0.0, 0.0, -alt), 0.3)


@pytest.mark.timing  # a count of positions in 2 s
def test_heartbeat_and_no_streams_until_requested(sim: VehicleSim, conn: mavutil.mavfile) -> None:
    hb = wait_msg(conn, "HEARTBEAT")
    assert hb.autopilot == 3 and hb.type == 2 and hb.custom_mode == 0  # STABILIZE
    assert hb.base_mode & 1 and hb.base_mode & 64 and hb.system_status == 3
    c2 = mavutil.mavlink_connection(sim.endpoints[1], source_system=255)
    assert c2.wait_heartbeat(timeout=DEADLINE).get_srcSystem() == 2
    c2.close()
    seen: set[str] = set()
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.0:  # 5 simulated s
        m = conn.recv_match(blocking=True, timeout=0.1)
        if m is not None:
            seen.add(m.get_type())
    assert seen <= {"HEARTBEAT"}, seen
    # 10 Hz simulated = 50 Hz wall
    assert command(conn, 511, 33, 100000) == 0
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < 2.0:
        if conn.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=0.1) is not None:
            n += 1
    assert 50 <= n <= 150, n
    assert command(conn, 511, 33, -1) == 0


def test_request_message_and_data_stream(sim: VehicleSim, conn: mavutil.mavfile) -> None:
    conn.mav.command_long_send(1, 1, 512, 0, 242, 0, 0, 0, 0, 0, 0)
    hp = wait_msg(conn, "HOME_POSITION")
    assert abs(hp.latitude / 1e7 + 35.363261) < 1e-6 and abs(hp.altitude - 584000) < 10
    wait_msg(conn, "COMMAND_ACK", lambda m: m.command == 512 and m.result == 0)
    assert command(conn, 512, 49) == 0  # GPS_GLOBAL_ORIGIN
    assert command(conn, 512, 148) == 0  # AUTOPILOT_VERSION
    conn.mav.request_data_stream_send(1, 1, 6, 4, 1)  # POSITION at 4 Hz
    lp = wait_msg(conn, "LOCAL_POSITION_NED")
    assert abs(lp.x) < 0.1 and lp.z == 0.0


def test_guided_takeoff_and_go_north(sim: VehicleSim, conn: mavutil.mavfile) -> None:
    take_off(sim, conn, 10.0)
    conn.mav.set_position_target_local_ned_send(0, 1, 1, 1, POS_MASK, 20, 0, -10, 0, 0, 0, 0, 0, 0, 0, 0)
    settle(sim, (20.0, 0.0, -10.0), 0.5)
    st = sim.vehicle(0).state
    assert abs(st.yaw) < 0.2  # auto-yaw faced the direction of travel (north)
    assert command(conn, 511, 85, 200000) == 0
    echo = wait_msg(conn, "POSITION_TARGET_LOCAL_NED")
    assert abs(echo.x - 20.0) < 1e-3 and echo.type_mask & 1024
    assert command(conn, 400, 0) == 4  # disarm in the air: FAILED
    assert command(conn, 21) == 0  # LAND
    wait_state(sim, lambda s: not s.armed, "disarmed after landing", timeout=DEADLINE * 2)


def test_setpoint_outside_guided_ignored(sim: VehicleSim, conn: mavutil.mavfile) -> None:
    take_off(sim, conn, 5.0)
    assert command(conn, 176, 1, 5) == 0  # LOITER
    for _ in range(10):
        conn.mav.set_position_target_local_ned_send(0, 1, 1, 1, POS_MASK, 20, 0, -5, 0, 0, 0, 0, 0, 0, 0, 0)
        time.sleep(0.05)
    t0 = sim.vehicle(0).state.time
    wait_state(sim, lambda s: s.time - t0 > 3.0, "3 s later")
    assert math.dist(sim.vehicle(0).state.position, (0, 0, -5)) < 0.3


def test_guided_velocity_times_out(sim: VehicleSim, conn: mavutil.mavfile) -> None:
    take_off(sim, conn, 5.0)
    conn.mav.set_position_target_local_ned_send(0, 1, 1, 1, 3527, 0, 0, 0, 2.0, 0, 0, 0, 0, 0, 0, 0)
    wait_state(sim, lambda s: s.velocity[0] > 1.5, "moving north")
    t0 = sim.vehicle(0).state.time
    wait_state(sim, lambda s: s.time - t0 > 6.0, "6 s later")
    st = sim.vehicle(0).state
    assert abs(st.velocity[0]) < 0.1 and 3.0 < st.position[0] < 10.0, st


def test_takeoff_refused_when_disarmed_and_outside_guided(sim: VehicleSim, conn: mavutil.mavfile) -> None:
    texts: list[str] = []
    assert command(conn, 22, 0, 0, 0, 0, 0, 0, 10, texts=texts) == 4
    assert command(conn, 400, 1) == 0  # armed in STABILIZE
    assert command(conn, 22, 0, 0, 0, 0, 0, 0, 10, texts=texts) == 4
    assert texts and all("Takeoff" in t for t in texts)
    # landed in GUIDED: targets do not spin up motors
    assert command(conn, 176, *GUIDED) == 0
    conn.mav.set_position_target_local_ned_send(0, 1, 1, 1, POS_MASK, 0, 0, -10, 0, 0, 0, 0, 0, 0, 0, 0)
    time.sleep(0.5)
    assert sim.vehicle(0).state.position[2] == 0.0


def test_arm_rejected_without_gps_and_guided_needs_position(sim: VehicleSim, conn: mavutil.mavfile) -> None:
    assert command(conn, 176, *GUIDED) == 0
    sim.vehicle(0).fail_gps(True)
    texts: list[str] = []
    assert command(conn, 400, 1, texts=texts) == 4
    assert any(t == "Arm: Need Position Estimate" for t in texts), texts
    # STABILIZE needs no position: real ArduCopter arms in it without one
    assert command(conn, 176, 1, 0) == 0
    assert command(conn, 400, 1) == 0
    assert command(conn, 400, 0) == 0
    assert command(conn, 176, *GUIDED, texts=texts) == 4
    conn.mav.set_mode_send(1, 1, 4)  # SET_MODE is acked as command 11
    ack = wait_msg(conn, "COMMAND_ACK", lambda m: m.command == 11)
    assert ack.result == 4
    sim.vehicle(0).fail_gps(False)
    conn.mav.set_mode_send(1, 1, 4)
    wait_msg(conn, "COMMAND_ACK", lambda m: m.command == 11 and m.result == 0)
    wait_msg(conn, "HEARTBEAT", lambda m: m.custom_mode == 4)


def test_auto_disarm_and_unknown_command(sim: VehicleSim, conn: mavutil.mavfile) -> None:
    assert command(conn, 31337) == 3
    assert command(conn, 176, *GUIDED) == 0
    assert command(conn, 400, 1) == 0
    t0 = sim.vehicle(0).state.time
    wait_msg(conn, "HEARTBEAT", lambda m: not m.base_mode & 128)
    assert sim.vehicle(0).state.time - t0 >= 9.5


@pytest.mark.parametrize("wait", [True, False], ids=["waits", "runs"])
def test_a_late_client_sees_the_boot_only_when_the_simulator_waits_for_it(wait: bool) -> None:
    """ArduPilot SITL waits for its SERIAL0 client before it runs; ``wait_for_client``
    does the same, so a client that connects late still sees the boot from its start.
    Without it the boot goes on with nobody listening (the default, as before)."""
    # a 60 s boot is BOOT for its first 3.4 simulated s: 0.68 s of wall time at speedup 5
    cfg = SimConfig(
        profile="ardupilot", speedup=5.0, boot_time=60.0, base_port=free_port("tcp"), wait_for_client=wait
    )
    with VehicleSim(cfg) as s:
        time.sleep(1.5)  # the client comes 7.5 simulated s late: BOOT is over unless waited for
        assert s.waiting is wait
        c = mavutil.mavlink_connection(s.endpoints[0], source_system=255)
        try:
            hb = c.wait_heartbeat(timeout=DEADLINE)
            assert hb is not None and not s.waiting
            assert (hb.system_status == 1) is wait, hb  # MAV_STATE_BOOT, else STANDBY
            wait_msg(c, "HEARTBEAT", lambda m: m.system_status == 3, timeout=DEADLINE)  # booted
        finally:
            c.close()
