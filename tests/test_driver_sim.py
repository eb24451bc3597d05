"""The driver flying the vehicle simulator, in both profiles (issue 3 tests).

The simulator runs sped up (SPEEDUP x real time), so the driver streams setpoints
at 25 Hz to stay well inside PX4's COM_OF_LOSS_T (0.5 simulated second). Deadlines are
generous; nothing asserts tight timing.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from net_helpers import free_port

from firmware_bridge import driver as drv
from firmware_bridge.errors import CommandRejected

pytestmark = pytest.mark.processes  # the driver flying the vehicle simulator, in real time

sim_mod = pytest.importorskip("firmware_bridge.sim")

SPEEDUP = 4.0
PROFILES = ["px4", "ardupilot"]


@pytest.fixture
def make_sim() -> Iterator[Any]:
    started: list[Any] = []

    def make(profile: str, speedup: float = SPEEDUP) -> tuple[Any, str]:
        port = free_port("udp" if profile == "px4" else "tcp")
        sim = sim_mod.VehicleSim(
            sim_mod.SimConfig(vehicles=1, profile=profile, speedup=speedup, seed=0, base_port=port)
        )
        endpoints = sim.start()
        started.append(sim)
        return sim, endpoints[0]

    yield make
    for sim in started:
        sim.stop()


def _connect(endpoint: str, **kw: Any) -> drv.Vehicle:
    kw.setdefault("setpoint_rate_hz", 25.0)
    kw.setdefault("timeout", 15.0)
    return drv.connect(endpoint, **kw)


def _wait_telemetry(v: drv.Vehicle) -> drv.VehicleState:
    return v.wait_for(lambda s: s.ned is not None and s.rel_alt is not None and s.gps_ok, 15.0, "telemetry")


@pytest.mark.timing  # setpoint gaps under 0.25 s
@pytest.mark.parametrize("profile", PROFILES)
def test_takeoff_then_20m_north(make_sim: Any, profile: str) -> None:
    _, endpoint = make_sim(profile)
    with _connect(endpoint) as v:
        assert v.autopilot == profile
        s0 = _wait_telemetry(v)
        assert s0.ned is not None and not s0.armed
        v.takeoff(10.0, timeout=60)
        s = v.wait_altitude(10.0, tolerance=0.5, timeout=60)
        assert s.armed and s.in_air
        v.start_offboard(timeout=60)
        assert v.state.mode == ("OFFBOARD" if profile == "px4" else "GUIDED")
        n0, e0, _ = s0.ned
        v.set_target_ned(n0 + 20.0, e0, -10.0, yaw=0.0)
        v.wait_ned(n0 + 20.0, e0, -10.0, tolerance=0.5, timeout=60)
        # settled: a 1.5 s window (6 simulated s) spent within 0.5 m, overshoot allowed before
        deadline = time.monotonic() + 60
        inside_since: float | None = None
        while True:
            now = time.monotonic()
            assert now < deadline, f"did not settle within 0.5 m: {v.state.ned}"
            ned = v.state.ned
            assert ned is not None
            if math.hypot(ned[0] - n0 - 20.0, ned[1] - e0, ned[2] + 10.0) <= 0.5:
                inside_since = now if inside_since is None else inside_since
                if now - inside_since >= 1.5:
                    break
            else:
                inside_since = None
            time.sleep(0.02)
        assert v.state.mode == ("OFFBOARD" if profile == "px4" else "GUIDED")
        intervals = v.setpoint_intervals()
        assert intervals and max(intervals) < 1.0 / SPEEDUP  # never near the loss timeout
        v.land()
        v.wait_for(lambda s: not s.in_air, 120, "landed")


def test_px4_offboard_needs_a_stream(make_sim: Any) -> None:
    _, endpoint = make_sim("px4")
    with _connect(endpoint) as v:
        _wait_telemetry(v)
        # disarmed: PX4 >= 1.14 accepts OFFBOARD, then refuses to arm without a stream
        v.set_mode("OFFBOARD")
        with pytest.raises(CommandRejected) as info:
            v.arm()
        assert info.value.text
        assert not v.state.armed
        v.set_mode("AUTO.LOITER")
        # armed and flying: OFFBOARD is refused outright without a stream
        v.takeoff(5.0, timeout=60)
        with pytest.raises(CommandRejected) as info:
            v.set_mode("OFFBOARD")
        assert info.value.result == 1  # TEMPORARILY_REJECTED
        assert v.state.mode != "OFFBOARD"


def test_px4_failsafe_when_stream_stops(make_sim: Any) -> None:
    _, endpoint = make_sim("px4")
    with _connect(endpoint) as v:
        _wait_telemetry(v)
        v.start_offboard(takeoff_alt=5.0, timeout=60)
        assert v.state.mode == "OFFBOARD"
        v.stop_setpoints()
        s = v.wait_for(lambda s: s.mode != "OFFBOARD", 15, "offboard loss failsafe")
        assert s.mode == "POSCTL"  # PX4's default COM_OBL_RC_ACT: Position mode
        # PX4 says it in an EVENT at CRITICAL ("Failsafe activated: ..." with PX4's metadata)
        assert any(t.severity <= 2 for t in v.statustexts()), v.statustexts()


def test_ardupilot_needs_guided_and_takeoff(make_sim: Any) -> None:
    _, endpoint = make_sim("ardupilot")
    with _connect(endpoint) as v:
        _wait_telemetry(v)
        # NAV_TAKEOFF disarmed fails, with no text (as recorded on ArduCopter SITL)
        with pytest.raises(CommandRejected) as info:
            v.command(drv.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, 10.0))
        assert info.value.result == 4
        # armed in GUIDED, a target above does not spin the motors up without a takeoff
        v.set_mode("GUIDED")
        v.arm()
        v.set_target_ned(0.0, 0.0, -10.0)
        time.sleep(8.0 / SPEEDUP)
        assert v.state.rel_alt is not None and v.state.rel_alt < 0.5
        v.stop_setpoints()
        v.takeoff(10.0, timeout=60)
        assert v.state.mode == "GUIDED" and v.state.in_air


@pytest.mark.timing  # the refusal's texts are those that arrive within a window of the ACK
@pytest.mark.parametrize("profile", PROFILES)
def test_rejected_arm_carries_text(make_sim: Any, profile: str) -> None:
    sim, endpoint = make_sim(profile)
    with _connect(endpoint) as v:
        _wait_telemetry(v)
        if profile == "ardupilot":  # STABILIZE arms without a position: GUIDED does not
            v.set_mode("GUIDED")
        sim.vehicle(0).fail_gps(True)
        if profile == "ardupilot":
            v.wait_for(lambda s: not s.gps_ok, 10, "GPS failure")
        with pytest.raises(CommandRejected) as info:
            if profile == "ardupilot":
                v.command(drv.MAV_CMD_COMPONENT_ARM_DISARM, (1, 0))
            else:
                v.arm()
        assert info.value.text, "the autopilot's reason (STATUSTEXT, PX4's EVENT) must be attached"
        assert info.value.text in str(info.value)
        assert not v.state.armed


@pytest.mark.timing  # a 0.5 s link timeout
@pytest.mark.parametrize("profile", PROFILES)
def test_lost_link_detected(make_sim: Any, profile: str) -> None:
    sim, endpoint = make_sim(profile)
    lost, restored = threading.Event(), threading.Event()
    with _connect(endpoint, link_timeout=0.5, on_link_lost=lost.set, on_link_restored=restored.set) as v:
        _wait_telemetry(v)
        assert v.link_ok
        sim.vehicle(0).drop_link(3.0 * SPEEDUP)
        assert lost.wait(15), "on_link_lost not called"
        assert not v.link_ok
        assert restored.wait(30), "on_link_restored not called"
        assert v.link_ok
        v.wait_for(lambda s: time.monotonic() - s.last_message_time < 0.5, 10, "fresh telemetry")
