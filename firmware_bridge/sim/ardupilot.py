"""The ArduCopter flavour of the simulated autopilot: its rules and its GUIDED mode.

Theory of operation. :class:`ArduPilot` answers the questions
:class:`~firmware_bridge.sim.autopilot.Autopilot` asks its flavour (see
:mod:`firmware_bridge.sim.flavour`) the way ArduCopter 4.x does: the custom_mode is the
mode number, a refusal is FAILED, nothing streams until REQUEST_DATA_STREAM or
SET_MESSAGE_INTERVAL asks, arming runs pre-arm checks (force arm 2989 skips them).
GUIDED is a small machine of sub-modes: ``idle`` (landed), ``takeoff`` (NAV_TAKEOFF,
metres above home, climbing), ``pos`` (a position target, held for good), ``vel`` (a
velocity or acceleration target, stopped after GUID_TIMEOUT) and ``hold`` (that stop).
Setpoints are used only in GUIDED and only in the air; one it cannot follow (FORCE,
NaN, a frame or field combination it does not take) holds the current position. With
both yaw fields ignored it faces where it goes (auto yaw). "(I)" in comments marks
inferred behaviour.

As recorded from a real ArduCopter 4.7 SITL: it boots along a
:class:`~firmware_bridge.sim.boot.BootTimeline` (BOOT status, zero positions, late home
and origin, arming refused with the real reasons until the EKF uses GPS; a mode set
during BOOT reverts to STABILIZE at "ArduPilot Ready"); it sends TIMESYNC every 10 s,
PARAM_VALUE at boot and at disarm, GPS_GLOBAL_ORIGIN when the origin is set and at each
arm, one more HEARTBEAT with each ACK that changes the mode; SYS_STATUS carries the
pre-arm check bit (healthy once the boot allows arming) and GPS health from the
detected GPS; base_mode has GUIDED (8)
whenever the position controller runs (GUIDED, AUTO, LAND, armed in any position mode,
and during BOOT); NAV_TAKEOFF while disarmed fails without a text; AUTO without a
mission is accepted while disarmed; the motors spool up for ``SPOOL_UP`` s before a
take-off climbs.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

from firmware_bridge.sim import modes, telemetry
from firmware_bridge.sim.boot import (
    BOOT_PARAMS,
    ORIGIN_SET,
    READY,
    TIMESYNC_FIRST,
    TIMESYNC_PERIOD,
    BootTimeline,
)
from firmware_bridge.sim.dynamics import NAN, Limits, Target, wrap_pi
from firmware_bridge.sim.flavour import (
    ACCEPTED,
    DENIED,
    FAILED,
    PRE_TAKEOFF_DISARM,
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

GUID_TIMEOUT = 3.0  # guided velocity/accel target timeout, s
EKF_UNINITIALISED, EKF_NO_GPS, EKF_USING_GPS = 1024, 167, 831  # EKF_STATUS_REPORT.flags, recorded
AP_FORCE_ARM = 2989  # arm param 2: skip the pre-arm checks
SPOOL_UP = 3.1  # s from an accepted NAV_TAKEOFF to the climb (recorded lift-off 3.1 s)
#: modes whose position controller runs while disarmed (HEARTBEAT base_mode bit 8)
POSITION_CONTROL = frozenset({"GUIDED", "AUTO", "LAND"})
#: REQUEST_DATA_STREAM groups -> message ids (I: which group holds what)
GROUPS: dict[int, tuple[int, ...]] = {
    2: (1, 24, 85, 245),  # EXTENDED_STATUS
    6: (33, 32),  # POSITION
    10: (30,),  # EXTRA1
    11: (74,),  # EXTRA2 (VFR_HUD)
    12: (147,),  # EXTRA3
}


class ArduPilot(Flavour):
    """ArduCopter multicopter, with the state of its GUIDED mode."""

    name = "ardupilot"
    sitl_link = "tcp"
    sitl_base_port = 5760
    sitl_port_step = 10
    initial_mode = "STABILIZE"
    land_mode = "LAND"
    rtl_mode = "RTL"
    # WPNAV speeds; kp_z, a_z and v_xy fitted to the recorded take-off and 20 m step
    # and the yaw rate ATC_SLEW_YAW allows (6000 cdeg/s: a 90 degree turn in 1.7 s on the real one)
    limits: ClassVar[Limits] = Limits(
        v_xy=6.0, v_up=2.5, v_down=1.5, a_xy=2.5, kp_z=0.8, a_z=1.0, yaw_rate_max=math.radians(60.0)
    )
    default_streams: ClassVar[dict[int, float]] = {}  # SRn_* rates default to 0
    refusal = FAILED
    takeoff_speed = 2.5
    land_speed_low = 0.5  # LAND_SPEED
    rtl_loiter = 5.0  # RTL_LOIT_TIME: s over home before the descent
    version = 4 << 24 | 6 << 16
    set_mode_ack = 11
    reposition_by_long = False  # ArduCopter: COMMAND_INT only
    text_gps_lost = "GPS 1: lost fix"
    text_gps_failsafe = "EKF Failsafe: changed to LAND Mode"
    text_preflight_disarm = "Disarming motors"
    text_landed_disarm = "Disarming motors"
    text_disarm_denied = "Disarm: vehicle is flying"
    text_armed = "Arming motors"
    text_disarmed = "Disarming motors"
    text_battery_low = "Battery 1 is low"
    text_battery_critical = "Battery 1 is critical"
    params = (  # ArduCopter 4.7 SITL's names, types and defaults (GUID_TIMEOUT is read by GUIDED)
        ("FORMAT_VERSION", 120, 4),
        ("PILOT_TKOFF_ALT", 0.0, 9),
        ("RTL_ALT", 1500, 6),
        ("FS_GCS_ENABLE", 0, 2),
        ("LAND_SPEED", 50, 4),
        ("ARMING_CHECK", 1, 6),
        ("DISARM_DELAY", 10, 2),
        ("WPNAV_SPEED", 1000.0, 9),
        ("WPNAV_SPEED_UP", 250.0, 9),
        ("WPNAV_SPEED_DN", 150.0, 9),
        ("MOT_THST_HOVER", 0.39, 9),
        ("GUID_TIMEOUT", GUID_TIMEOUT, 9),
        ("MAV_SYSID", 1, 4),
    )
    refusal_severity = 2
    heartbeat_on_mode_change = True
    gps_fix_type = 6  # as SITL reports

    def __init__(self, boot_time: float = 0.0) -> None:
        self.boot = BootTimeline(boot_time)
        self.home_wanted = False  # a REQUEST_MESSAGE HOME_POSITION waits for home
        self.last_t = 0.0  # the time of the previous boot step
        self.takeoff_time = 0.0
        self.sub = "idle"  # GUIDED sub-mode: idle | takeoff | pos | vel | hold
        self.target = Target()
        self.target_time = 0.0  # when the last velocity/acceleration target arrived
        self.auto_yaw = False

    # ---------------------------------------------------------------- status
    def heartbeat(self, ap: Autopilot) -> Msg:
        custom = modes.AP_MODES[ap.mode]
        base = 1 | 16 | 64 | (128 if ap.armed else 0)
        booting = self.boot.booting(ap.t)
        if booting or ap.mode in POSITION_CONTROL or (ap.armed and ap.mode in modes.NEEDS_POSITION):
            base |= 8
        # ACTIVE from lift-off until disarmed, touchdown included (as recorded)
        status = 5 if (ap.failsafe and ap.armed) else (4 if ap.armed and ap.took_off else 3)
        return ap.mav.heartbeat_encode(2, 3, base, custom, 1 if booting else status)

    # ------------------------------------------------------------------ boot
    def position_valid(self, ap: Autopilot) -> bool:
        return self.boot.position_valid(ap.t)

    def local_valid(self, ap: Autopilot) -> bool:
        return self.boot.using_gps(ap.t)

    def home_set(self, ap: Autopilot) -> bool:
        return self.boot.origin_set(ap.t)

    def prearm_ok(self, ap: Autopilot) -> bool | None:
        return ap.gps_ok and not self.boot.arm_refusal(ap.t)

    def defer_request(self, ap: Autopilot, mid: int) -> bool:
        if mid == 242 and not self.home_set(ap):
            self.home_wanted = True
            return True
        return False

    def unknown_stream(self, mid: int) -> Reply:
        return DENIED, f"No ap_message for mavlink id ({mid})"

    def ekf_flags(self, ap: Autopilot) -> int | None:
        """As recorded: 1024 (uninitialised) until the EKF starts, 167 (attitude,
        velocities, vertical position, constant position mode) until it uses GPS, then
        831 (with the absolute horizontal position the driver waits for); GPS lost: 167."""
        if not self.boot.ekf_started(ap.t):
            return EKF_UNINITIALISED
        return EKF_USING_GPS if self.boot.using_gps(ap.t) and ap.gps_ok else EKF_NO_GPS

    def on_arm(self, ap: Autopilot) -> None:
        self._send(ap, 49)  # GPS_GLOBAL_ORIGIN at each arm

    def _send(self, ap: Autopilot, mid: int) -> None:
        m = telemetry.message(ap, mid)
        if m is not None:
            ap.out(m)

    def _param(self, ap: Autopilot, name: str, value: float) -> None:
        ap.out(ap.mav.param_value_encode(name.encode(), value, 9, 1000, 65535))

    def _boot_events(self, ap: Autopilot) -> None:
        """What the boot timeline, TIMESYNC and the parameters announce in the last step."""
        t0, t1, bt = self.last_t, ap.t, self.boot
        self.last_t = t1  # the previous step's own time: a moment falls in exactly one step
        for sev, text in bt.texts_between(t0, t1, ap.origin[2]):
            ap.text(sev, text)
        if bt.crossed(0.11, t0, t1):
            for name in BOOT_PARAMS:
                self._param(ap, name, 0.0)
        if bt.total > 0.0 and bt.crossed(READY, t0, t1) and ap.mode != self.initial_mode:
            ap.enter_mode(self.initial_mode)  # a mode set during BOOT does not survive it
        if bt.total > 0.0 and bt.crossed(ORIGIN_SET, t0, t1):
            self._send(ap, 49)
            if self.home_wanted:
                self.home_wanted = False
                self._send(ap, 242)
        k = (t1 - TIMESYNC_FIRST) / TIMESYNC_PERIOD
        if k >= 0.0 and (t0 - TIMESYNC_FIRST) / TIMESYNC_PERIOD < float(int(k)) <= k:
            ap.out(ap.mav.timesync_encode(0, round(t1 * 1e9)))

    def touchdown_disarm_delay(self, kind: str) -> float:
        return 2.0 if kind in ("land", "rtl") else PRE_TAKEOFF_DISARM  # recorded 2.07 s

    def echo_mask(self, ap: Autopilot) -> int | None:
        return 1024 | 2048 if ap.mode == "GUIDED" else None  # echoed in GUIDED only, yaw ignored

    # ----------------------------------------------------------------- modes
    def set_mode_numbers(self, ap: Autopilot, p2: float, p3: float) -> Reply:
        return self.set_custom_mode(ap, int(p2))

    def set_custom_mode(self, ap: Autopilot, custom_mode: int) -> Reply:
        name = modes.AP_BY_NUMBER.get(custom_mode)
        if name is None:
            return FAILED, f"Unknown mode {custom_mode}"
        return ap.change_mode(name)

    def change_mode(self, ap: Autopilot, name: str) -> Reply:
        if name in modes.NEEDS_POSITION and not ap.gps_ok:
            return FAILED, f"Mode change to {name} failed: requires position"
        if name == "AUTO" and ap.armed:
            return FAILED, "Mode change to AUTO failed: no mission"
        ap.enter_mode(name)
        return ACCEPTED, None

    def arm_refusal(self, ap: Autopilot, p: tuple[float, ...]) -> tuple[str, ...]:
        if int(p[1]) == AP_FORCE_ARM:
            return ()
        booting = self.boot.arm_refusal(ap.t)
        if ap.mode not in modes.NEEDS_POSITION:  # STABILIZE, ALT_HOLD...: no position needed
            booting = tuple(r for r in booting if r != "Arm: Need Position Estimate")
        if booting:
            return booting
        if not ap.gps_ok and ap.mode in modes.NEEDS_POSITION:
            return ("Arm: Need Position Estimate",)
        if ap.mode in modes.AP_NOT_ARMABLE:
            return (f"Arm: {ap.mode} mode not armable",)
        if ap.battery < 5.0:
            return ("Arm: Battery low",)
        return ()

    def on_request_data_stream(self, ap: Autopilot, msg: Msg) -> None:
        groups = list(GROUPS) if msg.req_stream_id == 0 else [msg.req_stream_id]
        rate = msg.req_message_rate if msg.start_stop else 0
        for g in groups:
            for mid in GROUPS.get(g, ()):
                ap.set_stream(mid, 1.0 / rate if rate > 0 else 0.0)

    # -------------------------------------------------------------- commands
    def takeoff(self, ap: Autopilot, p: tuple[float, ...], frame: int | None) -> Reply:
        b = ap.body
        if frame is not None and frame not in (3, 6):
            return FAILED, "Takeoff failed: frame must be GLOBAL_RELATIVE_ALT"
        if not ap.armed:
            return FAILED, None  # as recorded: no text
        if ap.mode != "GUIDED":
            return FAILED, f"Takeoff failed: {ap.mode} does not support takeoff"
        if not b.on_ground:
            return FAILED, "Takeoff failed: already flying"
        alt = p[6]
        if not finite(alt) or alt <= 0.0:
            return FAILED, "Takeoff failed: altitude below current"
        self.sub = "takeoff"
        self.takeoff_time = ap.t
        ap.hold_point = (b.pos[0], b.pos[1], b.pos[2])
        ap.hold_yaw = b.yaw
        ap.takeoff_z = ap.home[2] - alt
        return ACCEPTED, None

    def reposition(self, ap: Autopilot, p: tuple[float, ...], ned: tuple[float, float, float]) -> Reply:
        if ap.mode != "GUIDED":
            if not int(p[1]) & 1:
                return FAILED, "Reposition failed: not in GUIDED"
            ap.enter_mode("GUIDED")
        self.sub = "pos"
        self.target = Target(pos=ned, yaw=ap.body.yaw)
        self.auto_yaw = True
        return ACCEPTED, None

    def on_local_setpoint(self, ap: Autopilot, msg: Msg) -> None:
        if ap.mode != "GUIDED":
            return  # ignored outside GUIDED
        frame = msg.coordinate_frame
        pos, vel, acc = setpoint_fields(msg, (msg.x, msg.y, msg.z))
        b = ap.body
        yaw_off = 0.0
        if frame in (7, 8, 9):
            rot = b.yaw if frame in (8, 9) else 0.0
            off = rotate(pos, rot)
            pos = [b.pos[i] + off[i] for i in range(3)]
            if frame in (8, 9):
                vel = rotate(vel, rot)
                acc = rotate(acc, rot)
                yaw_off = b.yaw
        elif frame != 1:
            self._hold(ap)
            return
        self._set_target(ap, msg, pos, vel, acc, yaw_off, terrain=False)

    def on_global_setpoint(self, ap: Autopilot, msg: Msg) -> None:
        frame = msg.coordinate_frame
        if ap.mode != "GUIDED":
            return
        if frame not in (0, 5, 3, 6, 10, 11):
            self._hold(ap)
            return
        pos, vel, acc = setpoint_fields(msg, global_setpoint_ned(ap, msg))
        self._set_target(ap, msg, pos, vel, acc, 0.0, terrain=frame in (10, 11))

    # ---------------------------------------------------------------- GUIDED
    def _hold(self, ap: Autopilot) -> None:
        b = ap.body
        if b.on_ground:
            return
        self.sub = "pos"
        self.target = Target(pos=(b.pos[0], b.pos[1], b.pos[2]), yaw=b.yaw)
        self.auto_yaw = False

    def _set_target(
        self,
        ap: Autopilot,
        msg: Msg,
        pos: list[float],
        vel: list[float],
        acc: list[float],
        yaw_off: float,
        *,
        terrain: bool,
    ) -> None:
        if ap.body.on_ground and self.sub != "takeoff":
            return  # landed: guided targets don't spin up motors
        mask = msg.type_mask
        pos_i, vel_i, acc_i = (mask & 7) == 7, (mask & 56) == 56, (mask & 448) == 448
        if not _usable(msg, pos, vel, acc, terrain):
            self._hold(ap)
            return
        yaw_set = not mask & 1024 and finite(msg.yaw)
        rate_set = not mask & 2048 and finite(msg.yaw_rate)
        self.auto_yaw = bool(mask & 1024 and mask & 2048)
        self.target = Target(
            pos=(NAN, NAN, NAN) if pos_i else (pos[0], pos[1], pos[2]),
            vel=(NAN, NAN, NAN) if vel_i else (vel[0], vel[1], vel[2]),
            acc=(NAN, NAN, NAN) if acc_i else (acc[0], acc[1], acc[2]),
            yaw=wrap_pi(msg.yaw + yaw_off)
            if yaw_set
            else (NAN if rate_set or self.auto_yaw else ap.body.yaw),
            yaw_rate=msg.yaw_rate if rate_set and not yaw_set else NAN,
        )
        self.sub = "pos" if not pos_i else "vel"
        self.target_time = ap.t

    def check_timeouts(self, ap: Autopilot) -> None:
        timeout = ap.params.get("GUID_TIMEOUT", GUID_TIMEOUT)
        if ap.mode == "GUIDED" and self.sub == "vel" and ap.t - self.target_time > timeout:
            # velocity / acceleration target timed out: decelerate to a stop
            self.sub = "hold"
            self.target = Target(vel=(0.0, 0.0, 0.0), yaw=ap.body.yaw)

    def own_target(self, ap: Autopilot) -> Target:
        b = ap.body
        if self.sub == "idle" or (b.on_ground and self.sub != "takeoff"):
            return ap.hold_target() if b.on_ground else Target(pos=(b.pos[0], b.pos[1], b.pos[2]))
        if self.sub == "takeoff":
            if ap.t - self.takeoff_time < SPOOL_UP:
                return ap.hold_target()  # motors spooling up
            return ap.climb_target(self.takeoff_speed)
        tg = self.target
        if not self.auto_yaw:
            return tg
        yaw = b.yaw
        if all(finite(x) for x in tg.pos[:2]):
            dn, de = tg.pos[0] - b.pos[0], tg.pos[1] - b.pos[1]
            if math.hypot(dn, de) > 2.0:
                yaw = math.atan2(de, dn)
        elif all(finite(x) for x in tg.vel[:2]) and math.hypot(tg.vel[0], tg.vel[1]) > 0.5:
            yaw = math.atan2(tg.vel[1], tg.vel[0])
        return Target(pos=tg.pos, vel=tg.vel, acc=tg.acc, yaw=yaw)

    def after_step(self, ap: Autopilot, kind: str) -> None:
        self._boot_events(ap)
        b = ap.body
        if kind == "guided" and self.sub == "takeoff" and b.pos[2] <= ap.takeoff_z + 0.1:
            self.sub = "pos"
            self.target = Target(pos=(b.pos[0], b.pos[1], ap.takeoff_z), yaw=b.yaw)

    def taking_off(self, ap: Autopilot, kind: str) -> bool:
        return kind == "guided" and self.sub == "takeoff"

    def on_enter_mode(self, ap: Autopilot, kind: str) -> None:
        if kind != "guided":
            return
        b = ap.body
        if b.on_ground:
            self.sub = "idle"
        else:
            self.sub = "pos"
            self.target = Target(pos=ap.hold_point, yaw=b.yaw)
            self.auto_yaw = False

    def on_disarm(self, ap: Autopilot, kind: str) -> None:
        if ap.mode == "GUIDED":
            self.sub = "idle"
        self._param(ap, "MOT_THST_HOVER", 0.35)


def _usable(msg: Msg, pos: list[float], vel: list[float], acc: list[float], terrain: bool) -> bool:
    """Whether GUIDED can follow this setpoint; it holds position otherwise."""
    mask = msg.type_mask
    pos_i, vel_i, acc_i = (mask & 7) == 7, (mask & 56) == 56, (mask & 448) == 448
    used = ([] if pos_i else pos) + ([] if vel_i else vel) + ([] if acc_i else acc)
    if (mask & 512) or any(not finite(v) for v in used) or any(abs(v) > 1000 for v in vel if not vel_i):
        return False  # FORCE, NaN or an absurd velocity
    if not pos_i and vel_i and not acc_i:
        return False  # pos + acc without vel
    if pos_i and vel_i and acc_i:
        return False  # nothing set
    return not (terrain and not pos_i and not vel_i)
