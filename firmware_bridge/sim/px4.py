"""The PX4 flavour of the simulated autopilot: its rules and its OFFBOARD mode.

Theory of operation. :class:`Px4` answers the questions
:class:`~firmware_bridge.sim.autopilot.Autopilot` asks its flavour (see
:mod:`firmware_bridge.sim.flavour`) the way PX4 v1.15 does: modes are numbered
``main << 16 | sub << 24``, a refusal is TEMPORARILY_REJECTED, NAV_TAKEOFF enters
AUTO.TAKEOFF with an AMSL altitude (NaN: MIS_TAKEOFF_ALT), ramps its motors up for
MPC_TKO_RAMP_T, climbs at MPC_TKO_SPEED and completes into AUTO.LOITER. OFFBOARD
follows the setpoint stream: any valid setpoint, in any mode, is proof of life and
becomes the offboard setpoint; arming in OFFBOARD and switching to it while armed need
a setpoint younger than COM_OF_LOSS_T; a stream older than that while armed in
OFFBOARD is the loss failsafe (COM_OBL_RC_ACT: Position mode by default, or hold, land
or return; land without GPS). A landing descends at 1.5 m/s above MPC_LAND_ALT1, slows
to MPC_LAND_SPEED at MPC_LAND_ALT2 and crawls the last metre; the land detector takes
LAND_DETECT_S to say so and the vehicle disarms COM_DISARM_LAND later, going back to
the last mode it was put in that allows arming (PX4's "user intention": OFFBOARD when
the landing came from OFFBOARD).

As recorded from a real PX4 v1.15.4 SITL (:mod:`firmware_bridge.sim.px4_boot`): it
boots for about 34 s (HEARTBEAT UNINIT while any arming check fails, no
GLOBAL_POSITION_INT until the estimate is valid), reports its arming checks as EVENT
messages when they change, and says everything it says (arming, refusals, take-off
and landing detected, failsafes) in EVENTs, never STATUSTEXT. "(I)" in comments marks
inferred behaviour.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

from firmware_bridge.sim import modes, px4_boot, telemetry
from firmware_bridge.sim.dynamics import NAN, Limits, Target
from firmware_bridge.sim.flavour import (
    ACCEPTED,
    DENIED,
    FAILED,
    TEMPORARILY_REJECTED,
    Flavour,
    Msg,
    Reply,
    finite,
    global_setpoint_ned,
    rotate,
    setpoint_fields,
)

if TYPE_CHECKING:
    from firmware_bridge.sim.autopilot import Autopilot

COM_OF_LOSS_T = 0.5  # offboard stream timeout, s (PX4 v1.15 default, read from its SITL)
MIS_TAKEOFF_ALT = 2.5  # default take-off altitude above home, m
TKO_RAMP_S = 2.5  # s from an accepted take-off to lift-off (recorded about 3 s; MPC_TKO_RAMP_T is 3)
NAV_MC_ALT_RAD = 0.8  # m: a take-off within this of its altitude is done (AUTO.LOITER)
LAND_ALT1, LAND_ALT2, LAND_ALT3 = 10.0, 5.0, 1.0  # MPC_LAND_ALT1/2/3, m above home
LAND_CRAWL = 0.3  # MPC_LAND_CRWL, m/s below LAND_ALT3
LAND_DETECT_S = 2.3  # s from touchdown to "Landing detected" (recorded 2.2-2.5 s)
COM_DISARM_LAND = 2.0  # s from "Landing detected" to the disarm (recorded 2.06 s)

STREAMS: dict[int, float] = {  # msg id -> interval (simulated s), onboard link (reduced)
    33: 0.1,  # GLOBAL_POSITION_INT 10 Hz
    32: 0.1,  # LOCAL_POSITION_NED 10 Hz
    30: 0.1,  # ATTITUDE 10 Hz
    85: 0.1,  # POSITION_TARGET_LOCAL_NED 10 Hz
    1: 1.0,  # SYS_STATUS 1 Hz
    245: 1.0,  # EXTENDED_SYS_STATE 1 Hz
    24: 1.0,  # GPS_RAW_INT 1 Hz
    147: 1.0,  # BATTERY_STATUS 1 Hz
    242: 2.0,  # HOME_POSITION 0.5 Hz
}
#: COM_OBL_RC_ACT: offboard_loss_action -> mode (position: 0, PX4's default)
LOSS_MODES = {"position": "POSCTL", "hold": "AUTO.LOITER", "land": "AUTO.LAND", "rtl": "AUTO.RTL"}
#: modes PX4 cannot arm in: a disarm never goes back to them
NOT_ARMABLE = frozenset({"AUTO.LAND", "AUTO.RTL"})


class Px4(Flavour):
    """PX4 multicopter; ``loss_action`` is COM_OBL_RC_ACT (hold, land or rtl)."""

    name = "px4"
    sitl_link = "udp"
    sitl_base_port = 14540
    sitl_port_step = 1
    initial_mode = "AUTO.LOITER"
    land_mode = "AUTO.LAND"
    rtl_mode = "AUTO.RTL"
    # fitted to PX4 v1.15 SIH: a 20 m offboard step (its track; within 0.5 m in 4.1-4.9 s),
    # a 5 m climb in 5.4-7.0 s (two runs), a 90 degree turn in 1.1 s
    limits: ClassVar[Limits] = Limits(
        kp_xy=0.6, a_xy=7.0, tau=0.6, kp_z=0.4, a_z=1.0, yaw_rate_max=math.radians(120.0)
    )
    default_streams = STREAMS
    refusal = TEMPORARILY_REJECTED
    takeoff_speed = 1.5  # MPC_TKO_SPEED
    land_speed_low = 0.7  # MPC_LAND_SPEED
    version = 1 << 24 | 14 << 16
    set_mode_ack = 176  # (I) PX4 acks SET_MODE as DO_SET_MODE
    reposition_by_long = True
    land_detect_delay = LAND_DETECT_S
    zero_position_before_fix = False  # PX4 sends no GLOBAL_POSITION_INT before its estimate
    text_gps_lost = "GPS lost: no position"
    text_gps_failsafe = "Failsafe activated: no position, landing"
    text_preflight_disarm = "Disarmed by auto preflight disarming"
    text_landed_disarm = "Disarmed by landing"
    text_disarm_denied = "Disarming denied: not landed"
    text_armed = "Armed by external command"
    text_disarmed = "Disarmed by external command"
    text_battery_low = "Low battery level! Return advised"
    text_battery_critical = "Critical battery level! Land now"
    params = (  # v1.15 SITL's names, types and defaults (COM_OF_LOSS_T is read by the loss rule)
        ("COM_DISARM_LAND", 2.0, 9),
        ("COM_OBL_RC_ACT", 0, 6),
        ("COM_DISARM_PRFLT", 10.0, 9),
        ("COM_OF_LOSS_T", COM_OF_LOSS_T, 9),
        ("COM_RC_IN_MODE", 1, 6),
        ("MAV_SYS_ID", 1, 6),
        ("MIS_TAKEOFF_ALT", 2.5, 9),
        ("MPC_LAND_SPEED", 0.7, 9),
        ("MPC_TKO_SPEED", 1.5, 9),
        ("MPC_XY_CRUISE", 5.0, 9),
        ("MPC_XY_VEL_MAX", 12.0, 9),
        ("MPC_Z_VEL_MAX_UP", 3.0, 9),
        ("NAV_RCL_ACT", 2, 6),
        ("SYS_AUTOSTART", 10040, 6),
    )
    param_bytewise = True
    param_read_index = True
    param_hash_first = True

    def __init__(self, loss_action: str = "position", boot_time: float = 0.0) -> None:
        self.loss_action = loss_action
        self.boot = px4_boot.Px4Boot(boot_time)
        self.setpoint: Target | None = None  # the offboard setpoint
        self.setpoint_time = -math.inf  # when the last valid setpoint arrived
        self.takeoff_time = -math.inf  # when the last take-off was accepted
        self.after_disarm = self.initial_mode  # the last mode set that allows arming
        self.event_seq = 0
        self.reported: list[px4_boot.Ev] | None = None  # the last arming check report
        self.origin_sent = False  # GPS_GLOBAL_ORIGIN goes out once, early

    def stream_fresh(self, ap: Autopilot) -> bool:
        return ap.t - self.setpoint_time <= ap.params.get("COM_OF_LOSS_T", COM_OF_LOSS_T)

    # ------------------------------------------------------------------ boot
    def position_valid(self, ap: Autopilot) -> bool:
        return self.boot.position_valid(ap.t)

    def gps_detected(self, ap: Autopilot) -> bool:
        return True  # GPS_RAW_INT has its fix from the first second

    def checks(self, ap: Autopilot) -> list[px4_boot.Ev]:
        """The arming check report of the vehicle now (the EVENTs PX4 sends for it)."""
        return px4_boot.failing_checks(
            attitude=self.boot.attitude_valid(ap.t),
            position=ap.gps_ok and self.boot.position_valid(ap.t),
            booted=self.boot.booted(ap.t),
            offboard_signal=self.stream_fresh(ap),
        )

    def _blocked(self, ap: Autopilot) -> bool:
        """An arming check keeps it on the ground (no offboard signal: only in OFFBOARD)."""
        checks = self.checks(ap)
        if ap.mode != "OFFBOARD":
            checks = [c for c in checks if c != px4_boot.NO_OFFBOARD_SIGNAL]
        return px4_boot.blocking(checks)

    def event(self, ap: Autopilot, ev: px4_boot.Ev) -> None:
        """Send one EVENT (to everyone), numbered as PX4 numbers its events."""
        ev_id, levels, args = ev
        ap.out(px4_boot.EventMsg(ev_id, levels, args, self.event_seq, round(ap.t * 1000.0)))
        self.event_seq = (self.event_seq + 1) & 0xFFFF

    def event_for(self, severity: int, text: str) -> px4_boot.Ev | None:
        return EVENT_TEXTS.get(text)

    # ---------------------------------------------------------------- status
    def heartbeat(self, ap: Autopilot) -> Msg:
        custom = modes.px4_custom_mode(ap.mode)
        base = 1 | modes.px4_base_flags(ap.mode) | (128 if ap.armed else 0)
        if ap.armed:
            status = 5 if ap.failsafe else 4
        else:
            status = 0 if self._blocked(ap) else 3  # UNINIT while a check fails, as PX4
        return ap.mav.heartbeat_encode(2, 12, base, custom, status)

    def touchdown_disarm_delay(self, kind: str) -> float:
        return LAND_DETECT_S + COM_DISARM_LAND

    def unknown_stream(self, mid: int) -> Reply:
        return FAILED, None

    def can_stream(self, mid: int) -> bool:
        return mid != 193  # EKF_STATUS_REPORT is ArduPilot's

    def takeoff_target(self, ap: Autopilot) -> Target:
        if ap.t - self.takeoff_time < TKO_RAMP_S:
            return ap.hold_target()  # the motors ramp up: still on the ground
        return ap.climb_target(self.takeoff_speed)

    def descent_speed(self, ap: Autopilot, alt: float) -> float:
        """MPC_LAND_ALT1..3: 1.5 m/s above ALT1, down to MPC_LAND_SPEED at ALT2, crawling below ALT3."""
        if alt > LAND_ALT1:
            return 1.5
        if alt > LAND_ALT2:
            return self.land_speed_low + (1.5 - self.land_speed_low) * (alt - LAND_ALT2) / (
                LAND_ALT1 - LAND_ALT2
            )
        return self.land_speed_low if alt > LAND_ALT3 else LAND_CRAWL

    def echo_mask(self, ap: Autopilot) -> int | None:
        return 0  # the controller's setpoint, in every mode

    # ----------------------------------------------------------------- modes
    def set_mode_numbers(self, ap: Autopilot, p2: float, p3: float) -> Reply:
        main, sub = int(p2) & 0xFF, int(p3) & 0xFF  # PX4 casts to uint8
        if main == 0:
            return ACCEPTED, None  # accepted no-op, as PX4 does
        return self._mode_by_number(ap, main, sub)

    def set_custom_mode(self, ap: Autopilot, custom_mode: int) -> Reply:
        return self._mode_by_number(ap, (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)

    def _mode_by_number(self, ap: Autopilot, main: int, sub: int) -> Reply:
        if main != 4:
            sub = 0
        name = modes.PX4_BY_NUMBER.get((main, sub))
        if name is None:
            return DENIED, f"Mode change denied: unsupported mode {main}/{sub}"
        return ap.change_mode(name)

    def change_mode(self, ap: Autopilot, name: str) -> Reply:
        if ap.armed:
            if name in modes.NEEDS_POSITION and not ap.gps_ok:
                return TEMPORARILY_REJECTED, f"Switching to {name} is not available: no position"
            if name == "OFFBOARD" and not self.stream_fresh(ap):
                return TEMPORARILY_REJECTED, "Switching to Offboard is currently not available"
        if name == "AUTO.TAKEOFF":
            ap.takeoff_z = ap.home[2] - MIS_TAKEOFF_ALT if ap.armed else -MIS_TAKEOFF_ALT
            self.takeoff_time = ap.t
        self._intend(name)
        ap.enter_mode(name)
        return ACCEPTED, None

    def _intend(self, name: str) -> None:
        if name not in NOT_ARMABLE:
            self.after_disarm = name

    def arm_refusal(self, ap: Autopilot, p: tuple[float, ...]) -> tuple[str, ...]:
        if int(p[1]) == 21196:
            return ()  # forced
        if self._blocked(ap):
            return (ARMING_DENIED,)  # the failing checks are in the last report
        return ()

    # -------------------------------------------------------------- commands
    def takeoff(self, ap: Autopilot, p: tuple[float, ...], frame: int | None) -> Reply:
        home_amsl = ap.geo(*ap.home)[2]
        alt = p[6]
        rel = alt - home_amsl if finite(alt) else MIS_TAKEOFF_ALT
        if rel <= 0.0:
            rel = MIS_TAKEOFF_ALT
        self._intend("AUTO.TAKEOFF")
        ap.enter_mode("AUTO.TAKEOFF")
        ap.takeoff_z = ap.home[2] - rel
        self.takeoff_time = ap.t
        return ACCEPTED, None

    def reposition(self, ap: Autopilot, p: tuple[float, ...], ned: tuple[float, float, float]) -> Reply:
        self._intend("AUTO.LOITER")
        ap.enter_mode("AUTO.LOITER")
        ap.hold_point = ned
        return ACCEPTED, None

    def on_local_setpoint(self, ap: Autopilot, msg: Msg) -> None:
        frame = msg.coordinate_frame
        if frame not in (1, 8):
            ap.text(4, f"LOCAL_NED coordinate frame {frame} unsupported")
            return
        pos, vel, acc = setpoint_fields(msg, (msg.x, msg.y, msg.z))
        if frame == 8:
            pos = [NAN, NAN, NAN]
            vel = rotate(vel, ap.body.yaw)
            acc = rotate(acc, ap.body.yaw)
        self._accept(ap, msg, pos, vel, acc)

    def on_global_setpoint(self, ap: Autopilot, msg: Msg) -> None:
        frame = msg.coordinate_frame
        if frame not in (5, 6, 11):
            ap.text(4, f"GLOBAL_INT coordinate frame {frame} unsupported")
            return
        if not ap.gps_ok:
            return  # no global reference: dropped silently
        pos, vel, acc = setpoint_fields(msg, global_setpoint_ned(ap, msg))
        self._accept(ap, msg, pos, vel, acc)

    def on_request_data_stream(self, ap: Autopilot, msg: Msg) -> None:
        pass  # PX4 takes SET_MESSAGE_INTERVAL only

    def _accept(self, ap: Autopilot, msg: Msg, pos: list[float], vel: list[float], acc: list[float]) -> None:
        mask = msg.type_mask
        if any(math.isinf(v) for v in (*pos, *vel, *acc)):
            return
        has_acc = (mask & 448) != 448
        if (mask & 512) and has_acc:
            return  # FORCE with acceleration: rejected
        if (mask & 7) == 7 and (mask & 56) == 56 and not has_acc:
            return  # nothing set: invalid
        yaw = NAN if mask & 1024 else msg.yaw
        yaw_rate = NAN if mask & 2048 else msg.yaw_rate
        self.setpoint = Target(
            pos=(pos[0], pos[1], pos[2]),
            vel=(vel[0], vel[1], vel[2]),
            acc=(acc[0], acc[1], acc[2]),
            yaw=yaw if finite(yaw) else NAN,
            yaw_rate=yaw_rate if finite(yaw_rate) else NAN,
        )
        self.setpoint_time = ap.t  # proof of life, in any mode

    # ------------------------------------------------------- OFFBOARD and take-off
    def check_timeouts(self, ap: Autopilot) -> None:
        if ap.mode != "OFFBOARD" or not ap.armed or self.stream_fresh(ap):
            return
        action = LOSS_MODES[self.loss_action]
        if action not in ("AUTO.LOITER", "POSCTL") and not ap.gps_ok:
            action = "AUTO.LAND"
        ap.enter_mode(action)
        ap.failsafe = True
        self.event(ap, px4_boot.failsafe_event(action))

    def own_target(self, ap: Autopilot) -> Target:
        return self.setpoint if self.setpoint is not None else ap.hold_target()

    def after_step(self, ap: Autopilot, kind: str) -> None:
        if kind == "takeoff" and ap.armed and ap.body.pos[2] <= ap.takeoff_z + NAV_MC_ALT_RAD:
            self._intend("AUTO.LOITER")
            ap.enter_mode("AUTO.LOITER")
            ap.hold_point = (ap.hold_point[0], ap.hold_point[1], ap.takeoff_z)  # goes on to the altitude
        if not self.origin_sent and ap.t >= self.boot.at(px4_boot.ORIGIN_SENT):
            self.origin_sent = True
            m = telemetry.message(ap, 49)
            if m is not None:
                ap.out(m)
        if self.boot.reporting(ap.t):
            checks = self.checks(ap)
            if checks != self.reported:  # a report when the checks change
                self.reported = checks
                for ev in (*checks, *px4_boot.summary(checks)):
                    self.event(ap, ev)

    def on_lift_off(self, ap: Autopilot) -> None:
        self.event(ap, px4_boot.TAKEOFF_DETECTED)

    def on_landing_detected(self, ap: Autopilot) -> None:
        self.event(ap, px4_boot.LANDING_DETECTED)

    def taking_off(self, ap: Autopilot, kind: str) -> bool:
        return False  # AUTO.TAKEOFF is a mode of its own

    def on_enter_mode(self, ap: Autopilot, kind: str) -> None:
        pass  # OFFBOARD keeps its setpoint across mode changes

    def on_disarm(self, ap: Autopilot, kind: str) -> None:
        if ap.mode != self.after_disarm:
            ap.enter_mode(self.after_disarm)  # back to the mode last set that allows arming


ARMING_DENIED = "Arming denied: Resolve system health failures first"
#: what the simulator's PX4 says, as the EVENT PX4 v1.15 sends for it (recorded)
EVENT_TEXTS: dict[str, px4_boot.Ev] = {
    ARMING_DENIED: px4_boot.ARMING_DENIED,
    Px4.text_armed: px4_boot.ARMED_BY_COMMAND,
    Px4.text_disarmed: px4_boot.DISARMED_BY_COMMAND,
    Px4.text_landed_disarm: px4_boot.DISARMED_AUTO_LAND,
    Px4.text_preflight_disarm: px4_boot.DISARMED_AUTO_PREFLIGHT,
    Px4.text_disarm_denied: px4_boot.DISARM_DENIED,
}
