"""The simulator's profiles against what the real autopilots were recorded doing
(PX4 v1.15.4 and ArduCopter 4.7 SITL, see firmware_bridge.sim.px4_boot and .boot):
PX4's boot (UNINIT, refusals TEMPORARILY_REJECTED with an EVENT and no STATUSTEXT, no
GLOBAL_POSITION_INT before its estimate, arming check reports), its land detector, the
mode it goes back to after a landing; ArduPilot's EKF_STATUS_REPORT, its STABILIZE
arming during the boot, each boot text said once. Pure core, real MAVLink bytes, no
sockets, simulated time."""

from __future__ import annotations

import math

from test_sim_flavours import ACCEPTED, HOME, POS_MASK, TEMPORARILY_REJECTED, Pilot

from firmware_bridge.sim import REALISTIC_BOOTS, px4_boot
from firmware_bridge.sim.ardupilot import EKF_NO_GPS, EKF_UNINITIALISED, EKF_USING_GPS
from firmware_bridge.sim.boot import RECORDED_TOTAL
from firmware_bridge.sim.flavour import LANDING, ON_GROUND
from firmware_bridge.sim.px4 import COM_DISARM_LAND, LAND_DETECT_S


def test_px4_boots_as_recorded_uninit_refusals_in_events_and_no_position() -> None:
    p = Pilot("px4", boot_time=REALISTIC_BOOTS["px4"])
    assert p.command(400, 1).result == TEMPORARILY_REJECTED  # an early arm
    p.run(2.0)
    said = [e for e, _a in p.events()]
    # the refusal is an EVENT, the failing checks a report; no STATUSTEXT at all
    assert said[0] == px4_boot.ARMING_DENIED[0] and p.texts() == []
    assert px4_boot.NO_ATTITUDE[0] in said and px4_boot.NO_GLOBAL_POSITION[0] in said
    assert p.heartbeat().system_status == 0  # UNINIT while a check fails
    types = {m.get_type() for m in p.heard}
    assert "GLOBAL_POSITION_INT" not in types and "GPS_RAW_INT" in types  # fix, no estimate
    p.run(32.5 - p.t)
    assert p.command(400, 1).result == TEMPORARILY_REJECTED  # position valid, not yet armable
    assert any(m.get_type() == "GLOBAL_POSITION_INT" for m in p.heard)
    p.run(px4_boot.RECORDED_TOTAL + 0.1 - p.t)
    assert p.heartbeat().system_status == 3  # STANDBY: armable
    assert p.command(400, 1).result == ACCEPTED
    assert (px4_boot.ARMED_BY_COMMAND[0], px4_boot.ARMED_BY_COMMAND[2]) in p.events()


def test_px4_arming_checks_report_only_when_they_change() -> None:
    p = Pilot("px4", boot_time=REALISTIC_BOOTS["px4"])
    p.run(10.0)
    reports = [e for e, _a in p.events()].count(px4_boot.CHECK_SUMMARY)
    assert reports == 1  # one report for the whole first phase
    p.run(px4_boot.RECORDED_TOTAL + 1.0 - p.t)
    assert [e for e, _a in p.events()].count(px4_boot.CHECK_SUMMARY) == 3  # attitude, then ready


def test_px4_landing_is_detected_late_and_it_disarms_back_into_offboard() -> None:
    p = Pilot("px4")
    assert p.command(400, 1).result == ACCEPTED
    assert p.command(22, 0, 0, 0, 0, 0, 0, HOME[2] + 5).result == ACCEPTED
    p.run(15.0)
    assert p.ap.mode == "AUTO.LOITER" and abs(p.ap.snapshot().position[2] + 5.0) < 0.3

    def stream() -> None:
        p.send(
            p.cl.set_position_target_local_ned_encode(0, 1, 1, 1, POS_MASK, 0, 0, -5, 0, 0, 0, 0, 0, 0, 0, 0)
        )

    p.run(0.5, stream)
    assert p.command(176, 1, 6, 0).result == ACCEPTED  # OFFBOARD
    p.run(1.0, stream)
    assert p.command(21).result == ACCEPTED  # NAV_LAND
    touchdown = None
    while p.t < 60.0 and p.ap.armed:
        p.run(0.05)
        if touchdown is None and p.ap.body.on_ground:
            touchdown = p.t
            assert p.ap.landed_state == LANDING  # the land detector has not decided yet
    assert touchdown is not None and not p.ap.armed
    assert p.t - touchdown >= LAND_DETECT_S + COM_DISARM_LAND - 0.1  # detected, then the disarm delay
    assert p.ap.landed_state == ON_GROUND and p.ap.mode == "OFFBOARD"  # PX4's user intention
    assert p.heartbeat().system_status == 0  # OFFBOARD with no signal: a check fails


def test_px4_descends_as_mpc_land_alt_says() -> None:
    p = Pilot("px4")
    fl = p.ap.flavour
    speeds = [fl.descent_speed(p.ap, a) for a in (12.0, 10.0, 7.5, 5.0, 2.0, 0.5)]
    assert speeds[0] == 1.5 and math.isclose(speeds[2], 1.1) and speeds[3:5] == [0.7, 0.7]
    assert speeds[5] == 0.3 and speeds == sorted(speeds, reverse=True)


def test_ardupilot_ekf_status_follows_its_boot_and_stabilize_arms_early() -> None:
    p = Pilot("ardupilot", boot_time=RECORDED_TOTAL)
    assert p.command(511, 193, 1e6).result == ACCEPTED  # streamed, as the real one does

    def flags() -> list[int]:
        return [m.flags for m in p.heard if m.get_type() == "EKF_STATUS_REPORT"]

    p.run(3.0)
    assert set(flags()) == {EKF_UNINITIALISED}
    p.heard.clear()
    p.run(10.0)
    assert flags()[-1] == EKF_NO_GPS  # no absolute horizontal position (bit 16)
    assert not EKF_NO_GPS & 16 and EKF_USING_GPS & 16
    # STABILIZE needs no position: armed once the gyros agree (recorded: accepted at 22 s)
    assert p.command(400, 1).result == 4
    p.run(23.5 - p.t)
    assert p.command(400, 1).result == ACCEPTED
    assert p.command(400, 0).result == ACCEPTED
    # GUIDED still needs the position estimate
    assert p.command(176, 1, 4).result == ACCEPTED
    assert p.command(400, 1).result == 4
    p.heard.clear()
    p.run(RECORDED_TOTAL + 2.0 - p.t)
    assert flags()[-1] == EKF_USING_GPS
    assert p.texts().count("EKF3 IMU0 is using GPS") == 1  # each boot text once
    assert p.command(400, 1).result == ACCEPTED


def test_px4_refuses_ekf_status_report_as_px4_does() -> None:
    p = Pilot("px4")
    assert p.command(511, 193, 1e6).result == 4  # FAILED: not a PX4 message
