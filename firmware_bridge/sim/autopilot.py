"""The simulated autopilot of one vehicle: a MAVLink state machine with no I/O.

Theory of operation. :class:`Autopilot` owns the vehicle's whole state (arming, mode,
landed state, setpoints, battery, telemetry schedule) and a point-mass
:class:`~firmware_bridge.sim.dynamics.Body`. It never reads a clock or a socket:

* ``handle(msg, now)`` takes one decoded MAVLink message received at simulated time
  ``now`` (seconds) and returns the messages to send back (acks, STATUSTEXT, replies);
* ``tick(now)`` advances physics in fixed steps of ``dt`` up to ``now`` and returns the
  telemetry that fell due (heartbeat, streams, failsafe texts);
* ``next_deadline()`` is the simulated time at which ``tick`` has work again.

Both first advance to ``now``, so messages take effect at the next physics step
boundary. The same inputs at the same simulated times give the same outputs: the only
randomness is a seeded ``random.Random`` (telemetry position noise). The rules follow
reference/autopilot.md sections 1-5 for the ``px4`` and ``ardupilot`` profiles; "(I)" in
comments marks inferred behaviour.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Any

import pymap3d
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.sim import modes
from firmware_bridge.sim.dynamics import NAN, Body, Limits, Target, wrap_pi

Msg = Any  # a pymavlink MAVLink_message

# MAV_RESULT
ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = 0, 1, 2, 3, 4
# MAV_LANDED_STATE
ON_GROUND, IN_AIR, TAKEOFF, LANDING = 1, 2, 3, 4
FORCE_MAGIC = 21196
AP_FORCE_ARM = 2989

COM_OF_LOSS_T = 1.0  # PX4 offboard stream timeout, s
PRE_TAKEOFF_DISARM = 10.0  # COM_DISARM_PRFLT / DISARM_DELAY, s
GUID_TIMEOUT = 3.0  # ArduCopter guided velocity/accel target timeout, s
MIS_TAKEOFF_ALT = 2.5  # PX4 default take-off altitude above home, m
RTL_ALT = 15.0  # return altitude above home, m (AP RTL_ALT; PX4 shortened (I))

PX4_STREAMS: dict[int, float] = {  # msg id -> interval (simulated s), onboard link (reduced)
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
#: ArduPilot REQUEST_DATA_STREAM groups -> message ids (I: which group holds what)
AP_GROUPS: dict[int, tuple[int, ...]] = {
    2: (1, 24, 85, 245),  # EXTENDED_STATUS
    6: (33, 32),  # POSITION
    10: (30,),  # EXTRA1
    11: (74,),  # EXTRA2 (VFR_HUD)
    12: (147,),  # EXTRA3
}
STREAMABLE = frozenset({1, 24, 30, 32, 33, 49, 74, 85, 147, 242, 245})
REQUESTABLE = STREAMABLE | {0, 148}
MAX_STREAM_HZ = 50.0


@dataclass(frozen=True)
class VehicleState:
    """A snapshot of one simulated vehicle (true state, not telemetry)."""

    sysid: int
    time: float  # simulated seconds since start
    position: tuple[float, float, float]  # NED m from the start point (EKF origin)
    velocity: tuple[float, float, float]  # NED m/s
    yaw: float  # rad
    armed: bool
    mode: str
    landed_state: int  # MAV_LANDED_STATE 1 ground .. 4 landing
    battery: float  # percent remaining
    home: tuple[float, float, float]  # NED m of home (arming point)
    gps_ok: bool
    failsafe: bool


def _f(x: float) -> bool:
    return math.isfinite(x)


class Autopilot:
    """One simulated PX4 or ArduCopter vehicle. See the module docstring."""

    def __init__(
        self,
        profile: str,
        sysid: int,
        origin: tuple[float, float, float],
        *,
        rng: random.Random | None = None,
        offboard_loss_action: str = "hold",
        dt: float = 0.02,
        noise: float = 0.01,
    ) -> None:
        if profile not in ("px4", "ardupilot"):
            raise ValueError(f"unknown profile {profile!r} (px4 or ardupilot)")
        if offboard_loss_action not in ("hold", "land", "rtl"):
            raise ValueError(f"unknown offboard_loss_action {offboard_loss_action!r} (hold, land, rtl)")
        self.px4 = profile == "px4"
        self.profile = profile
        self.sysid = sysid
        self.origin = origin
        self.rng = rng if rng is not None else random.Random(0)
        self.loss_action = offboard_loss_action
        self.dt = dt
        self.noise = noise
        self.mav = mavlink.MAVLink(None, sysid, 1)  # encoder only, never writes
        self.lim = Limits() if self.px4 else Limits(v_xy=10.0, v_up=2.5, v_down=1.5, a_xy=2.5)
        self.body = Body()
        self.t = 0.0  # physics time
        self._steps = 0
        self.armed = False
        self.mode = "AUTO.LOITER" if self.px4 else "STABILIZE"
        self.failsafe = False
        self.gps_ok = True
        self.battery = 100.0
        self.home = (0.0, 0.0, 0.0)
        self.arm_time = 0.0
        self.took_off = False
        self.touchdown_time: float | None = None
        self.hold_point = (0.0, 0.0, 0.0)
        self.hold_yaw = 0.0
        self.target: Target | None = None  # what the controller tracks now
        # PX4 offboard
        self.ob_sp: Target | None = None
        self.ob_time = -math.inf
        # PX4 AUTO.TAKEOFF / AP guided takeoff altitude (NED z) and xy
        self.takeoff_z = -MIS_TAKEOFF_ALT
        # AP guided: submode idle | takeoff | pos | vel | hold
        self.g_sub = "idle"
        self.g_target = Target()
        self.g_time = 0.0
        self.g_auto_yaw = False
        self.rtl_phase = "climb"
        self.streams: dict[int, list[float]] = {}
        for mid, iv in PX4_STREAMS.items() if self.px4 else ():
            self._set_stream(mid, iv, 0.0)
        self.next_hb = 0.0
        self._out: list[Msg] = []
        self._landed_state = ON_GROUND

    # ------------------------------------------------------------------ public
    def handle(self, msg: Msg, now: float) -> list[Msg]:
        """Process one received message at simulated time ``now``; return replies."""
        self._advance(now)
        t = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src == (self.sysid, 1):
            pass  # our own echo
        elif t in ("COMMAND_LONG", "COMMAND_INT"):
            self._on_command(msg, src)
        elif t == "SET_MODE":
            self._on_set_mode_msg(msg, src)
        elif t == "SET_POSITION_TARGET_LOCAL_NED":
            if self._for_me(msg):
                self._on_local_sp(msg)
        elif t == "SET_POSITION_TARGET_GLOBAL_INT":
            if self._for_me(msg):
                self._on_global_sp(msg)
        elif t == "REQUEST_DATA_STREAM" and not self.px4:
            if self._for_me(msg):
                self._on_request_data_stream(msg)
        return self._flush()

    def tick(self, now: float) -> list[Msg]:
        """Advance to simulated time ``now``; return the telemetry that fell due."""
        self._advance(now)
        return self._flush()

    def next_deadline(self) -> float:
        return (self._steps + 1) * self.dt

    def snapshot(self) -> VehicleState:
        b = self.body
        return VehicleState(
            sysid=self.sysid,
            time=self.t,
            position=(b.pos[0], b.pos[1], b.pos[2]),
            velocity=(b.vel[0], b.vel[1], b.vel[2]),
            yaw=b.yaw,
            armed=self.armed,
            mode=self.mode,
            landed_state=self._landed_state,
            battery=self.battery,
            home=self.home,
            gps_ok=self.gps_ok,
            failsafe=self.failsafe,
        )

    def set_gps(self, ok: bool) -> None:
        """Fault hook: a failed GPS gives no position, refuses arming and position modes."""
        if ok == self.gps_ok:
            return
        self.gps_ok = ok
        if not ok:
            self._text(2, "GPS lost: no position" if self.px4 else "GPS 1: lost fix")
            if self.armed and not self.body.on_ground and self.mode in modes.NEEDS_POSITION:
                self._enter_mode("AUTO.LAND" if self.px4 else "LAND")
                self.failsafe = True
                self._text(
                    2,
                    "Failsafe activated: no position, landing"
                    if self.px4
                    else "EKF Failsafe: changed to LAND Mode",
                )

    # --------------------------------------------------------------- time step
    def _advance(self, now: float) -> None:
        while (self._steps + 1) * self.dt <= now + 1e-9:
            self._steps += 1
            self.t = self._steps * self.dt
            self._physics_step()
            self._emit_due()

    def _physics_step(self) -> None:
        b = self.body
        was_ground = b.on_ground
        self._check_timeouts()
        target = self._compute_target()
        self.target = target
        b.step(target, self.lim, self.dt, powered=self.armed)
        if self.armed and not b.on_ground:
            self.took_off = True
            self.touchdown_time = None
        elif self.armed and b.on_ground and not was_ground:
            self.touchdown_time = self.t
        self._landed_state = self._compute_landed()
        self._after_step()
        self._drain()

    def _compute_landed(self) -> int:
        b = self.body
        if b.on_ground:
            return ON_GROUND
        kind = modes.behaviour(self.mode)
        if kind == "takeoff" or (kind == "guided" and self.g_sub == "takeoff"):
            return TAKEOFF
        if kind == "land" or (kind == "rtl" and self.rtl_phase == "land"):
            return LANDING
        return IN_AIR

    def _after_step(self) -> None:
        b = self.body
        kind = modes.behaviour(self.mode)
        if kind == "takeoff" and self.armed and b.pos[2] <= self.takeoff_z + 0.15:
            self._enter_mode("AUTO.LOITER")
        if kind == "guided" and self.g_sub == "takeoff" and b.pos[2] <= self.takeoff_z + 0.1:
            self.g_sub = "pos"
            self.g_target = Target(pos=(b.pos[0], b.pos[1], self.takeoff_z), yaw=b.yaw)
        if kind == "rtl":
            hx, hy = self.home[0], self.home[1]
            if self.rtl_phase == "climb" and b.pos[2] <= self._rtl_z() + 0.3:
                self.rtl_phase = "return"
            elif self.rtl_phase == "return" and math.hypot(b.pos[0] - hx, b.pos[1] - hy) < 0.5:
                self.rtl_phase = "land"
        if not self.armed:
            return
        if b.on_ground and not self.took_off and self.t - self.arm_time >= PRE_TAKEOFF_DISARM:
            self._disarm("Disarmed by auto preflight disarming" if self.px4 else "Disarming motors")
        elif b.on_ground and self.took_off and self.touchdown_time is not None:
            delay = 2.0 if self.px4 else (1.0 if kind in ("land", "rtl") else PRE_TAKEOFF_DISARM)
            if self.t - self.touchdown_time >= delay:
                self._disarm("Landing detected, disarmed" if self.px4 else "Disarming motors")

    def _drain(self) -> None:
        if not self.armed:
            return
        if self.body.on_ground:
            rate = 0.02
        else:
            a = self.body.acc
            rate = 0.08 + 0.004 * math.sqrt(a[0] ** 2 + a[1] ** 2 + a[2] ** 2)
        self.battery = max(0.0, self.battery - rate * self.dt)

    def _check_timeouts(self) -> None:
        if self.px4:
            if self.mode == "OFFBOARD" and self.armed and self.t - self.ob_time > COM_OF_LOSS_T:
                action = {"hold": "AUTO.LOITER", "land": "AUTO.LAND", "rtl": "AUTO.RTL"}[self.loss_action]
                if action != "AUTO.LOITER" and not self.gps_ok:
                    action = "AUTO.LAND"
                self._enter_mode(action)
                self.failsafe = True
                name = {"AUTO.LOITER": "Hold", "AUTO.LAND": "Land", "AUTO.RTL": "Return"}[action]
                self._text(2, f"Failsafe activated: no offboard signal, {name}")
        elif self.mode == "GUIDED" and self.g_sub == "vel" and self.t - self.g_time > GUID_TIMEOUT:
            # velocity / acceleration target timed out: decelerate to a stop
            self.g_sub = "hold"
            self.g_target = Target(vel=(0.0, 0.0, 0.0), yaw=self.body.yaw)

    # ---------------------------------------------------------------- targets
    def _hold_target(self) -> Target:
        return Target(pos=self.hold_point, yaw=self.hold_yaw)

    def _rtl_z(self) -> float:
        return min(self.body.pos[2], self.home[2] - RTL_ALT)

    def _compute_target(self) -> Target | None:
        b = self.body
        kind = modes.behaviour(self.mode)
        if kind == "offboard":
            return self.ob_sp if self.ob_sp is not None else self._hold_target()
        if kind == "takeoff":
            return Target(
                pos=(self.hold_point[0], self.hold_point[1], self.takeoff_z),
                yaw=self.hold_yaw,
                v_up=1.5 if self.px4 else 2.5,
            )
        if kind == "land":
            v = 1.5 if -b.pos[2] > 10.0 else (0.7 if self.px4 else 0.5)
            return Target(
                pos=(self.hold_point[0], self.hold_point[1], NAN),
                vel=(NAN, NAN, v),
                yaw=self.hold_yaw,
                v_down=v,
            )
        if kind == "rtl":
            hx, hy, _ = self.home
            if b.on_ground and self.rtl_phase != "land":
                return self._hold_target() if not self.took_off else None
            if self.rtl_phase == "climb":
                return Target(pos=(self.hold_point[0], self.hold_point[1], self._rtl_z()), yaw=b.yaw)
            if self.rtl_phase == "return":
                return Target(
                    pos=(hx, hy, self._rtl_z()),
                    yaw=math.atan2(hy - b.pos[1], hx - b.pos[0])
                    if math.hypot(hx - b.pos[0], hy - b.pos[1]) > 2.0
                    else b.yaw,
                )
            v = 1.5 if -b.pos[2] > 10.0 else (0.7 if self.px4 else 0.5)
            return Target(pos=(hx, hy, NAN), vel=(NAN, NAN, v), yaw=b.yaw, v_down=v)
        if kind == "guided":
            if self.g_sub == "idle" or (b.on_ground and self.g_sub != "takeoff"):
                return self._hold_target() if b.on_ground else Target(pos=(b.pos[0], b.pos[1], b.pos[2]))
            if self.g_sub == "takeoff":
                return Target(
                    pos=(self.hold_point[0], self.hold_point[1], self.takeoff_z), yaw=self.hold_yaw, v_up=2.5
                )
            tg = self.g_target
            if self.g_auto_yaw:
                yaw = b.yaw
                if all(_f(x) for x in tg.pos[:2]):
                    dn, de = tg.pos[0] - b.pos[0], tg.pos[1] - b.pos[1]
                    if math.hypot(dn, de) > 2.0:
                        yaw = math.atan2(de, dn)
                elif all(_f(x) for x in tg.vel[:2]) and math.hypot(tg.vel[0], tg.vel[1]) > 0.5:
                    yaw = math.atan2(tg.vel[1], tg.vel[0])
                return Target(pos=tg.pos, vel=tg.vel, acc=tg.acc, yaw=yaw)
            return tg
        return self._hold_target()

    # ------------------------------------------------------------------ modes
    def _enter_mode(self, mode: str) -> None:
        b = self.body
        self.mode = mode
        self.failsafe = False
        self.hold_point = (b.pos[0], b.pos[1], b.pos[2])
        self.hold_yaw = b.yaw
        kind = modes.behaviour(mode)
        if kind == "rtl":
            self.rtl_phase = "climb"
        if kind == "guided":
            if b.on_ground:
                self.g_sub = "idle"
            else:
                self.g_sub = "pos"
                self.g_target = Target(pos=self.hold_point, yaw=b.yaw)
                self.g_auto_yaw = False

    def _mode_name(self, mode: str) -> str:
        return mode

    def _heartbeat(self) -> Msg:
        b = self.body
        if self.px4:
            custom = modes.px4_custom_mode(self.mode)
            base = 1 | modes.px4_base_flags(self.mode) | (128 if self.armed else 0)
            status = (5 if self.failsafe else 4) if self.armed else 3
            return self.mav.heartbeat_encode(2, 12, base, custom, status)
        custom = modes.AP_MODES[self.mode]
        base = 1 | 16 | 64 | (128 if self.armed else 0)
        if self.armed and self.mode in modes.NEEDS_POSITION:
            base |= 8
        status = 5 if (self.failsafe and self.armed) else (3 if b.on_ground else 4)
        return self.mav.heartbeat_encode(2, 3, base, custom, status)

    # --------------------------------------------------------------- streams
    def _set_stream(self, mid: int, interval: float, now: float) -> None:
        if interval <= 0:
            self.streams.pop(mid, None)
            return
        interval = max(interval, 1.0 / MAX_STREAM_HZ)
        nxt = math.floor(now / interval + 1e-9) * interval + interval
        self.streams[mid] = [interval, nxt]

    def _emit_due(self) -> None:
        t = self.t + 1e-9
        if t >= self.next_hb:
            self._out.append(self._heartbeat())
            self.next_hb += 1.0
            if self.next_hb <= t:
                self.next_hb = math.floor(t) + 1.0
        for mid, entry in self.streams.items():
            if t >= entry[1]:
                m = self._message(mid)
                if m is not None:
                    self._out.append(m)
                entry[1] += entry[0]
                if entry[1] <= t:
                    entry[1] = t + entry[0]

    def _boot_ms(self) -> int:
        return round(self.t * 1000.0) & 0xFFFFFFFF

    def _geo(self, n: float, e: float, d: float) -> tuple[float, float, float]:
        lat, lon, alt = pymap3d.ned2geodetic(n, e, d, *self.origin)
        return float(lat), float(lon), float(alt)

    def _noisy_pos(self) -> tuple[float, float, float]:
        b = self.body
        s = self.noise
        if s <= 0:
            return b.pos[0], b.pos[1], b.pos[2]
        dz = 0.0 if b.on_ground else self.rng.gauss(0.0, s)
        return b.pos[0] + self.rng.gauss(0.0, s), b.pos[1] + self.rng.gauss(0.0, s), b.pos[2] + dz

    def _message(self, mid: int) -> Msg | None:
        b = self.body
        m = self.mav
        if mid == 0:
            return self._heartbeat()
        if mid == 33:
            if not self.gps_ok:
                return None
            n, e, d = self._noisy_pos()
            lat, lon, alt = self._geo(n, e, d)
            rel = alt - self._geo(*self.home)[2]
            hdg = round(math.degrees(b.yaw) * 100.0) % 36000
            return m.global_position_int_encode(
                self._boot_ms(),
                round(lat * 1e7),
                round(lon * 1e7),
                round(alt * 1000),
                round(rel * 1000),
                round(b.vel[0] * 100),
                round(b.vel[1] * 100),
                round(b.vel[2] * 100),
                hdg,
            )
        if mid == 32:
            if not self.gps_ok:
                return None
            n, e, d = self._noisy_pos()
            return m.local_position_ned_encode(self._boot_ms(), n, e, d, b.vel[0], b.vel[1], b.vel[2])
        if mid == 30:
            a = b.acc
            c, s = math.cos(b.yaw), math.sin(b.yaw)
            fwd, right = a[0] * c + a[1] * s, -a[0] * s + a[1] * c
            g = 9.80665
            return m.attitude_encode(
                self._boot_ms(), math.atan2(right, g), -math.atan2(fwd, g), b.yaw, 0.0, 0.0, b.yaw_rate
            )
        if mid == 85:
            return self._target_echo()
        if mid == 1:
            sensors = 32 | 1 | 2 | 4 | 8  # GPS, gyro, accel, mag, baro
            health = sensors if self.gps_ok else sensors & ~32
            volt, cur = self._battery_vi()
            return m.sys_status_encode(
                sensors,
                sensors,
                health,
                250,
                int(volt * 1000),
                int(cur * 100),
                int(self.battery),
                0,
                0,
                0,
                0,
                0,
                0,
            )
        if mid == 245:
            return m.extended_sys_state_encode(0, self._landed_state)
        if mid == 24:
            fix = 3 if self.gps_ok else 0
            lat, lon, alt = self._geo(b.pos[0], b.pos[1], b.pos[2]) if self.gps_ok else (0.0, 0.0, 0.0)
            return m.gps_raw_int_encode(
                int(self.t * 1e6),
                fix,
                round(lat * 1e7),
                round(lon * 1e7),
                round(alt * 1000),
                80 if fix else 9999,
                120 if fix else 9999,
                int(math.hypot(b.vel[0], b.vel[1]) * 100),
                0,
                12 if fix else 0,
            )
        if mid == 147:
            volt, cur = self._battery_vi()
            cells = [int(volt * 250)] * 4 + [65535] * 6
            return m.battery_status_encode(0, 1, 3, 32767, cells, int(cur * 100), -1, -1, int(self.battery))
        if mid == 242:
            return self._home_position()
        if mid == 49:
            lat, lon, alt = self.origin
            return m.gps_global_origin_encode(
                round(lat * 1e7), round(lon * 1e7), round(alt * 1000), int(self.t * 1e6)
            )
        if mid == 74:
            _, _, alt = self._geo(*b.pos)
            hdg = round(math.degrees(b.yaw)) % 360
            return m.vfr_hud_encode(
                0.0, math.hypot(b.vel[0], b.vel[1]), hdg, 0 if not self.armed else 50, alt, -b.vel[2]
            )
        if mid == 148:
            caps = 4 | 8 | 128 | 256 | 8192  # MISSION_INT, COMMAND_INT, SET_POS_TARGET_*, MAVLINK2
            ver = (1 << 24 | 14 << 16) if self.px4 else (4 << 24 | 6 << 16)
            return m.autopilot_version_encode(caps, ver, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.sysid)
        return None

    def _battery_vi(self) -> tuple[float, float]:
        volt = 14.0 + 2.8 * self.battery / 100.0
        if not self.armed:
            cur = 0.5
        elif self.body.on_ground:
            cur = 3.0
        else:
            cur = 18.0
        return volt, cur

    def _home_position(self) -> Msg | None:
        lat, lon, alt = self._geo(*self.home)
        h = self.home
        return self.mav.home_position_encode(
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt * 1000),
            h[0],
            h[1],
            h[2],
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
            int(self.t * 1e6),
        )

    def _target_echo(self) -> Msg | None:
        if not self.px4 and self.mode != "GUIDED":
            return None
        tg = self.target if self.target is not None else self._hold_target()
        fields = (*tg.pos, *tg.vel, *tg.acc, tg.yaw, tg.yaw_rate)
        bits = (1, 2, 4, 8, 16, 32, 64, 128, 256, 1024, 2048)
        mask = 0
        vals = []
        for bit, v in zip(bits, fields, strict=True):
            if not _f(v):
                mask |= bit
                vals.append(0.0)
            else:
                vals.append(v)
        if not self.px4:
            mask |= 1024 | 2048
        return self.mav.position_target_local_ned_encode(self._boot_ms(), 1, mask, *vals)

    # -------------------------------------------------------------- outputs
    def _text(self, severity: int, text: str) -> None:
        self._out.append(self.mav.statustext_encode(severity, text.encode("ascii", "replace")[:50]))

    def _flush(self) -> list[Msg]:
        out, self._out = self._out, []
        return out

    def _for_me(self, msg: Msg) -> bool:
        return msg.target_system in (0, self.sysid) and msg.target_component in (0, 1)

    # -------------------------------------------------------------- commands
    def _on_command(self, msg: Msg, src: tuple[int, int]) -> None:
        if not self._for_me(msg):
            return
        cmd = msg.command
        if msg.get_type() == "COMMAND_INT":
            params = (
                msg.param1,
                msg.param2,
                msg.param3,
                msg.param4,
                msg.x / 1e7 if msg.frame not in (1, 7, 8, 9) else float(msg.x),
                msg.y / 1e7 if msg.frame not in (1, 7, 8, 9) else float(msg.y),
                msg.z,
            )
            frame: int | None = msg.frame
        else:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
            frame = None
        result, text = self._command(cmd, params, frame)
        if text:
            self._text(4 if result else 6, text)
        self._out.append(self.mav.command_ack_encode(cmd, result, 0, 0, src[0], src[1]))

    def _reject(self, text: str) -> tuple[int, str]:
        return (TEMPORARILY_REJECTED if self.px4 else FAILED), text

    def _command(self, cmd: int, p: tuple[float, ...], frame: int | None) -> tuple[int, str | None]:
        if cmd == 400:
            return self._arm_cmd(p)
        if cmd == 176:
            return self._do_set_mode(p)
        if cmd == 22:
            return self._takeoff_cmd(p, frame)
        if cmd == 21:
            return self._change_mode("AUTO.LAND" if self.px4 else "LAND")
        if cmd == 20:
            return self._change_mode("AUTO.RTL" if self.px4 else "RTL")
        if cmd == 192:
            return self._reposition(p, frame)
        if cmd == 511:
            return self._set_interval(int(p[0]), p[1])
        if cmd == 512:
            return self._request_message(int(p[0]))
        if cmd == 520:
            return self._request_message(148)
        if cmd == 410:
            return self._request_message(242)
        return UNSUPPORTED, None

    def _set_interval(self, mid: int, us: float) -> tuple[int, str | None]:
        if mid == 0:
            return ACCEPTED, None
        if mid not in STREAMABLE:
            return UNSUPPORTED, None
        if us == 0:
            default = PX4_STREAMS.get(mid, 0.0) if self.px4 else 0.0
            self._set_stream(mid, default, self.t)
        elif us < 0:
            self._set_stream(mid, 0.0, self.t)
        else:
            self._set_stream(mid, us / 1e6, self.t)
        return ACCEPTED, None

    def _request_message(self, mid: int) -> tuple[int, str | None]:
        if mid not in REQUESTABLE:
            return UNSUPPORTED, None
        m = self._message(mid)
        if m is None:
            return (TEMPORARILY_REJECTED if self.px4 else FAILED), None
        self._out.append(m)
        return ACCEPTED, None

    def _on_request_data_stream(self, msg: Msg) -> None:
        groups = list(AP_GROUPS) if msg.req_stream_id == 0 else [msg.req_stream_id]
        rate = msg.req_message_rate if msg.start_stop else 0
        for g in groups:
            for mid in AP_GROUPS.get(g, ()):
                self._set_stream(mid, 1.0 / rate if rate > 0 else 0.0, self.t)

    def _arm_cmd(self, p: tuple[float, ...]) -> tuple[int, str | None]:
        force = int(p[1]) == FORCE_MAGIC
        if p[0] >= 0.5:
            if self.armed:
                return ACCEPTED, None
            skip = not self.px4 and int(p[1]) == AP_FORCE_ARM
            if not self.gps_ok and not skip:
                return self._reject(
                    "Arming denied: Preflight Fail: no global position"
                    if self.px4
                    else "PreArm: Need Position Estimate"
                )
            if self.px4 and self.mode == "OFFBOARD" and not self._stream_fresh():
                return self._reject("Arming denied: no offboard signal")
            if not self.px4 and self.mode in modes.AP_NOT_ARMABLE and not skip:
                return self._reject("Arm: Mode not armable")
            if not self.px4 and self.battery < 5.0 and not skip:
                return self._reject("PreArm: Battery low")
            self._arm()
            return ACCEPTED, ("Armed by external command" if self.px4 else None)
        if not self.armed:
            return ACCEPTED, None
        if not self.body.on_ground and not force:
            return self._reject("Disarming denied: not landed" if self.px4 else "Disarm: vehicle is flying")
        self._disarm(None)
        return ACCEPTED, ("Disarmed by external command" if self.px4 else None)

    def _arm(self) -> None:
        b = self.body
        self.armed = True
        self.arm_time = self.t
        self.took_off = not b.on_ground
        self.touchdown_time = None
        if b.on_ground:
            self.home = (b.pos[0], b.pos[1], b.pos[2])
        self.hold_point = (b.pos[0], b.pos[1], b.pos[2])
        self.hold_yaw = b.yaw

    def _disarm(self, text: str | None) -> None:
        self.armed = False
        self.took_off = False
        self.touchdown_time = None
        self.failsafe = False
        if self.mode == "GUIDED":
            self.g_sub = "idle"
        if modes.behaviour(self.mode) in ("takeoff",):
            self._enter_mode("AUTO.LOITER")
        if text:
            self._text(6, text)

    def _stream_fresh(self) -> bool:
        return self.t - self.ob_time <= COM_OF_LOSS_T

    def _do_set_mode(self, p: tuple[float, ...]) -> tuple[int, str | None]:
        if not int(p[0]) & 1:
            return DENIED, "Mode change denied: custom mode flag not set"
        if self.px4:
            main, sub = int(p[1]) & 0xFF, int(p[2]) & 0xFF  # PX4 casts to uint8
            if main == 0:
                return ACCEPTED, None  # accepted no-op, as PX4 does
            return self._px4_mode_by_number(main, sub)
        name = modes.AP_BY_NUMBER.get(int(p[1]))
        if name is None:
            return FAILED, f"Unknown mode {int(p[1])}"
        return self._change_mode(name)

    def _px4_mode_by_number(self, main: int, sub: int) -> tuple[int, str | None]:
        if main != 4:
            sub = 0
        name = modes.PX4_BY_NUMBER.get((main, sub))
        if name is None:
            return DENIED, f"Mode change denied: unsupported mode {main}/{sub}"
        return self._change_mode(name)

    def _on_set_mode_msg(self, msg: Msg, src: tuple[int, int]) -> None:
        if msg.target_system != self.sysid:
            return
        if self.px4:
            cm = msg.custom_mode
            result, text = self._px4_mode_by_number((cm >> 16) & 0xFF, (cm >> 24) & 0xFF)
            cmd = 176  # (I) PX4 acks as DO_SET_MODE
        else:
            name = modes.AP_BY_NUMBER.get(msg.custom_mode)
            result, text = (
                (FAILED, f"Unknown mode {msg.custom_mode}") if name is None else self._change_mode(name)
            )
            cmd = 11
        if text:
            self._text(4 if result else 6, text)
        self._out.append(self.mav.command_ack_encode(cmd, result, 0, 0, src[0], src[1]))

    def _change_mode(self, name: str) -> tuple[int, str | None]:
        if self.px4:
            if self.armed:
                if name in modes.NEEDS_POSITION and not self.gps_ok:
                    return TEMPORARILY_REJECTED, f"Switching to {name} is not available: no position"
                if name == "OFFBOARD" and not self._stream_fresh():
                    return TEMPORARILY_REJECTED, "Switching to Offboard is currently not available"
            if name == "AUTO.TAKEOFF":
                self.takeoff_z = self.home[2] - MIS_TAKEOFF_ALT if self.armed else -MIS_TAKEOFF_ALT
            self._enter_mode(name)
            return ACCEPTED, None
        if name in modes.NEEDS_POSITION and not self.gps_ok:
            return FAILED, f"Mode change to {name} failed: requires position"
        if name == "AUTO":
            return FAILED, "Mode change to AUTO failed: no mission"
        self._enter_mode(name)
        return ACCEPTED, None

    def _takeoff_cmd(self, p: tuple[float, ...], frame: int | None) -> tuple[int, str | None]:
        b = self.body
        if not self.gps_ok:
            return self._reject("Takeoff denied: no position")
        if self.px4:
            home_amsl = self._geo(*self.home)[2]
            alt = p[6]
            rel = alt - home_amsl if _f(alt) else MIS_TAKEOFF_ALT
            if rel <= 0.0:
                rel = MIS_TAKEOFF_ALT
            self._enter_mode("AUTO.TAKEOFF")
            self.takeoff_z = self.home[2] - rel
            return ACCEPTED, None
        if frame is not None and frame not in (3, 6):
            return FAILED, "Takeoff failed: frame must be GLOBAL_RELATIVE_ALT"
        if not self.armed:
            return FAILED, "Takeoff failed: not armed"
        if self.mode != "GUIDED":
            return FAILED, f"Takeoff failed: {self.mode} does not support takeoff"
        if not b.on_ground:
            return FAILED, "Takeoff failed: already flying"
        alt = p[6]
        if not _f(alt) or alt <= 0.0:
            return FAILED, "Takeoff failed: altitude below current"
        self.g_sub = "takeoff"
        self.hold_point = (b.pos[0], b.pos[1], b.pos[2])
        self.hold_yaw = b.yaw
        self.takeoff_z = self.home[2] - alt
        return ACCEPTED, None

    def _reposition(self, p: tuple[float, ...], frame: int | None) -> tuple[int, str | None]:
        b = self.body
        if not self.px4 and frame is None:
            return UNSUPPORTED, None  # ArduCopter: COMMAND_INT only
        if not self.gps_ok or not self.armed or b.on_ground:
            return self._reject("Reposition denied: not flying")
        lat, lon, alt = p[4], p[5], p[6]
        n, e, d = b.pos
        if _f(lat) and _f(lon) and (lat != 0.0 or lon != 0.0):
            n, e, _ = pymap3d.geodetic2ned(lat, lon, self.origin[2], *self.origin)
        if _f(alt):
            rel_frames = (3, 6)
            d = (self.home[2] - alt) if frame in rel_frames else -(alt - self.origin[2])
        if self.px4:
            self._enter_mode("AUTO.LOITER")
            self.hold_point = (float(n), float(e), float(d))
            return ACCEPTED, None
        if self.mode != "GUIDED":
            if not int(p[1]) & 1:
                return FAILED, "Reposition failed: not in GUIDED"
            self._enter_mode("GUIDED")
        self.g_sub = "pos"
        self.g_target = Target(pos=(float(n), float(e), float(d)), yaw=b.yaw)
        self.g_auto_yaw = True
        return ACCEPTED, None

    # ------------------------------------------------------------- setpoints
    @staticmethod
    def _fields(msg: Msg, xyz: tuple[float, float, float]) -> tuple[list[float], list[float], list[float]]:
        mask = msg.type_mask
        pos = [NAN if mask & bit else v for bit, v in zip((1, 2, 4), xyz, strict=True)]
        vel = [NAN if mask & bit else v for bit, v in zip((8, 16, 32), (msg.vx, msg.vy, msg.vz), strict=True)]
        acc = [
            NAN if mask & bit else v
            for bit, v in zip((64, 128, 256), (msg.afx, msg.afy, msg.afz), strict=True)
        ]
        return pos, vel, acc

    def _px4_accept(self, msg: Msg, pos: list[float], vel: list[float], acc: list[float]) -> None:
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
        self.ob_sp = Target(
            pos=(pos[0], pos[1], pos[2]),
            vel=(vel[0], vel[1], vel[2]),
            acc=(acc[0], acc[1], acc[2]),
            yaw=yaw if _f(yaw) else NAN,
            yaw_rate=yaw_rate if _f(yaw_rate) else NAN,
        )
        self.ob_time = self.t  # proof of life, in any mode

    def _on_local_sp(self, msg: Msg) -> None:
        frame = msg.coordinate_frame
        pos, vel, acc = self._fields(msg, (msg.x, msg.y, msg.z))
        if self.px4:
            if frame not in (1, 8):
                self._text(4, f"LOCAL_NED coordinate frame {frame} unsupported")
                return
            if frame == 8:
                pos = [NAN, NAN, NAN]
                vel = self._rotate(vel, self.body.yaw)
                acc = self._rotate(acc, self.body.yaw)
            self._px4_accept(msg, pos, vel, acc)
            return
        if self.mode != "GUIDED":
            return  # ArduCopter: ignored outside GUIDED
        b = self.body
        yaw_off = 0.0
        if frame in (7, 8, 9):
            rot = b.yaw if frame in (8, 9) else 0.0
            off = self._rotate(pos, rot)
            pos = [b.pos[i] + off[i] for i in range(3)]
            if frame in (8, 9):
                vel = self._rotate(vel, rot)
                acc = self._rotate(acc, rot)
                yaw_off = b.yaw
        elif frame != 1:
            self._ap_hold()
            return
        self._ap_target(msg, pos, vel, acc, yaw_off, terrain=False)

    def _on_global_sp(self, msg: Msg) -> None:
        frame = msg.coordinate_frame
        if self.px4:
            if frame not in (5, 6, 11):
                self._text(4, f"GLOBAL_INT coordinate frame {frame} unsupported")
                return
            if not self.gps_ok:
                return  # no global reference: dropped silently
        elif self.mode != "GUIDED":
            return
        elif frame not in (0, 5, 3, 6, 10, 11):
            self._ap_hold()
            return
        n, e, _ = pymap3d.geodetic2ned(msg.lat_int / 1e7, msg.lon_int / 1e7, self.origin[2], *self.origin)
        if frame in (0, 5):
            d = -(msg.alt - self.origin[2])
        elif frame in (3, 6):
            d = self.home[2] - msg.alt
        else:
            d = -msg.alt  # flat terrain at the origin's altitude
        pos, vel, acc = self._fields(msg, (float(n), float(e), float(d)))
        if self.px4:
            self._px4_accept(msg, pos, vel, acc)
        else:
            self._ap_target(msg, pos, vel, acc, 0.0, terrain=frame in (10, 11))

    @staticmethod
    def _rotate(v: list[float], yaw: float) -> list[float]:
        c, s = math.cos(yaw), math.sin(yaw)
        return [v[0] * c - v[1] * s, v[0] * s + v[1] * c, v[2]]

    def _ap_hold(self) -> None:
        if self.body.on_ground:
            return
        b = self.body
        self.g_sub = "pos"
        self.g_target = Target(pos=(b.pos[0], b.pos[1], b.pos[2]), yaw=b.yaw)
        self.g_auto_yaw = False

    def _ap_target(
        self, msg: Msg, pos: list[float], vel: list[float], acc: list[float], yaw_off: float, *, terrain: bool
    ) -> None:
        if self.body.on_ground and self.g_sub != "takeoff":
            return  # landed: guided targets don't spin up motors
        mask = msg.type_mask
        pos_i, vel_i, acc_i = (mask & 7) == 7, (mask & 56) == 56, (mask & 448) == 448
        used = ([] if pos_i else pos) + ([] if vel_i else vel) + ([] if acc_i else acc)
        if (mask & 512) or any(not _f(v) for v in used) or any(abs(v) > 1000 for v in vel if not vel_i):
            self._ap_hold()
            return
        if not pos_i and vel_i and not acc_i:
            self._ap_hold()  # pos + acc without vel
            return
        if pos_i and vel_i and acc_i:
            self._ap_hold()
            return
        if terrain and not pos_i and not vel_i:
            self._ap_hold()
            return
        yaw_set = not mask & 1024 and _f(msg.yaw)
        rate_set = not mask & 2048 and _f(msg.yaw_rate)
        self.g_auto_yaw = bool(mask & 1024 and mask & 2048)
        tg = Target(
            pos=(NAN, NAN, NAN) if pos_i else (pos[0], pos[1], pos[2]),
            vel=(NAN, NAN, NAN) if vel_i else (vel[0], vel[1], vel[2]),
            acc=(NAN, NAN, NAN) if acc_i else (acc[0], acc[1], acc[2]),
            yaw=wrap_pi(msg.yaw + yaw_off)
            if yaw_set
            else (NAN if rate_set or self.g_auto_yaw else self.body.yaw),
            yaw_rate=msg.yaw_rate if rate_set and not yaw_set else NAN,
        )
        self.g_target = tg
        self.g_sub = "pos" if not pos_i else "vel"
        self.g_time = self.t
