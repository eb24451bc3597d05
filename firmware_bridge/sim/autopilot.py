"""The simulated autopilot of one vehicle: a MAVLink state machine with no I/O.

Theory of operation. :class:`Autopilot` owns the vehicle's whole state (arming, mode,
landed state, hold point, take-off altitude, battery, telemetry schedule) and a
point-mass :class:`~firmware_bridge.sim.dynamics.Body`. It never reads a clock or a
socket:

* ``handle(msg, now)`` takes one decoded MAVLink message received at simulated time
  ``now`` (seconds) and returns the messages to send back (acks, STATUSTEXT, replies);
* ``tick(now)`` advances physics in fixed steps of ``dt`` up to ``now`` and returns the
  telemetry that fell due (heartbeat, streams, failsafe texts);
* ``next_deadline()`` is the simulated time at which ``tick`` has work again.

Both first advance to ``now``, so messages take effect at the next physics step
boundary. The same inputs at the same simulated times give the same outputs: the only
randomness is a seeded ``random.Random`` (telemetry position noise).

This module holds what PX4 and ArduCopter share: the time step, arming and the
auto-disarms, GPS loss, the hold, take-off, land and return controllers, streams and
the command dispatch with its COMMAND_ACK. Whatever differs (mode numbers, heartbeat,
arming and mode rules, take-off and reposition, setpoints, OFFBOARD or GUIDED) it asks
its flavour, :class:`~firmware_bridge.sim.px4.Px4` or
:class:`~firmware_bridge.sim.ardupilot.ArduPilot` (see :mod:`firmware_bridge.sim.flavour`);
it never tests which one it is. :mod:`firmware_bridge.sim.telemetry` encodes the
streamed messages.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

import pymap3d
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.sim import modes, telemetry
from firmware_bridge.sim.ardupilot import ArduPilot
from firmware_bridge.sim.dynamics import NAN, Body, Target
from firmware_bridge.sim.flavour import (
    ACCEPTED,
    DENIED,
    IN_AIR,
    LANDING,
    ON_GROUND,
    PRE_TAKEOFF_DISARM,
    TAKEOFF,
    UNSUPPORTED,
    Flavour,
    Msg,
    Reply,
    finite,
)
from firmware_bridge.sim.params import ParamTable
from firmware_bridge.sim.px4 import MIS_TAKEOFF_ALT, Px4

FORCE_MAGIC = 21196  # arm param 2: force (disarm in the air)
#: battery percentages below which the autopilot warns once (PX4 BAT_LOW_THR, BAT_CRIT_THR)
BATTERY_LOW = 15.0
BATTERY_CRITICAL = 7.0
RTL_ALT = 15.0  # return altitude above home, m (AP RTL_ALT; PX4 shortened (I))
MAX_STREAM_HZ = 50.0
#: the flavour class of each profile (its class data: SITL link and ports)
FLAVOURS: dict[str, type[Flavour]] = {cls.name: cls for cls in (Px4, ArduPilot)}


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


LOSS_ACTIONS = ("position", "hold", "land", "rtl")  # PX4 COM_OBL_RC_ACT 0, 5, 4, 3


def make_flavour(profile: str, offboard_loss_action: str = "position", boot_time: float = 0.0) -> Flavour:
    """The flavour object of one vehicle. Raises ValueError for an unknown value.

    ``boot_time``: the autopilot's recorded boot scaled to these seconds (0: booted; see
    :mod:`firmware_bridge.sim.boot` and :mod:`firmware_bridge.sim.px4_boot`)."""
    if profile not in FLAVOURS:
        raise ValueError(f"unknown profile {profile!r} (px4 or ardupilot)")
    if offboard_loss_action not in LOSS_ACTIONS:
        raise ValueError(f"unknown offboard_loss_action {offboard_loss_action!r} ({', '.join(LOSS_ACTIONS)})")
    return Px4(offboard_loss_action, boot_time) if profile == "px4" else ArduPilot(boot_time)


class Autopilot:
    """One simulated PX4 or ArduCopter vehicle. See the module docstring."""

    def __init__(
        self,
        profile: str,
        sysid: int,
        origin: tuple[float, float, float],
        *,
        rng: random.Random | None = None,
        offboard_loss_action: str = "position",
        dt: float = 0.02,
        noise: float = 0.01,
        boot_time: float = 0.0,
        battery_drain: float = 0.0,
    ) -> None:
        if not (math.isfinite(battery_drain) and 0.0 <= battery_drain <= 6000.0):
            raise ValueError(f"battery_drain {battery_drain!r}: 0..6000 percent per minute")
        self.flavour = make_flavour(profile, offboard_loss_action, boot_time)
        fl = self.flavour
        self.params = ParamTable(
            tuple((n, sysid if n in ("MAV_SYS_ID", "MAV_SYSID") else v, t) for n, v, t in fl.params),
            bytewise=fl.param_bytewise,
            read_index=fl.param_read_index,
            hash_first=fl.param_hash_first,
        )
        self.profile = profile
        self.sysid = sysid
        self.origin = origin
        self.rng = rng if rng is not None else random.Random(0)
        self.dt = dt
        self.noise = noise
        self.mav = mavlink.MAVLink(None, sysid, 1)  # encoder only, never writes
        self.lim = self.flavour.limits
        self.body = Body()
        self.t = 0.0  # physics time
        self._steps = 0
        self.armed = False
        self.mode = self.flavour.initial_mode
        self.failsafe = False
        self.gps_ok = True
        self.battery = 100.0
        #: percent per simulated minute drawn at all times, armed or not (tests: a battery
        #: that runs low in seconds), on top of what flying draws
        self.battery_drain = battery_drain
        self._battery_warned = 0  # 1: low told, 2: critical told
        self.home = (0.0, 0.0, 0.0)
        self.arm_time = 0.0
        self.took_off = False
        self.touchdown_time: float | None = None
        self.hold_point = (0.0, 0.0, 0.0)
        self.hold_yaw = 0.0
        self.target: Target | None = None  # what the controller tracks now
        self.takeoff_z = -MIS_TAKEOFF_ALT  # take-off altitude (NED z) of a climb
        self.rtl_phase = "climb"  # climb | return | loiter (over home) | land
        self.rtl_home_time = 0.0  # when the return reached home
        self.streams: dict[int, list[float]] = {}  # msg id -> [interval, next due]
        for mid, iv in self.flavour.default_streams.items():
            self.set_stream(mid, iv)
        self.next_hb = 0.0
        self._out: list[Msg] = []
        self.landed_state = ON_GROUND

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
        elif t in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET"):
            if self._for_me(msg):
                self._on_param(t, msg)
        elif t in ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT", "REQUEST_DATA_STREAM"):
            if self._for_me(msg):
                self._on_flavour_message(t, msg)
        return self._flush()

    def _on_param(self, t: str, msg: Msg) -> None:
        """The parameter protocol (:mod:`.params`): PARAM_VALUE for a read, a set or a
        list; nothing for a name it does not have, as the real autopilots."""
        if t == "PARAM_REQUEST_LIST":
            answers = self.params.listing()
        else:
            raw = msg.param_id
            name = (raw.decode("ascii", "replace") if isinstance(raw, bytes) else str(raw)).split("\x00")[0]
            if t == "PARAM_SET":
                one = self.params.set(name, msg.param_value, msg.param_type)
            else:
                one = self.params.read(name, msg.param_index)
            answers = [] if one is None else [one]
        for a in answers:
            self.out(self.mav.param_value_encode(a.name.encode(), a.value, a.type, a.count, a.index))

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
            landed_state=self.landed_state,
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
            self.text(2, self.flavour.text_gps_lost)
            if self.armed and not self.body.on_ground and self.mode in modes.NEEDS_POSITION:
                self.enter_mode(self.flavour.land_mode)
                self.failsafe = True
                self.text(2, self.flavour.text_gps_failsafe)

    # ------------------------------------------------ for the flavour objects
    def enter_mode(self, mode: str) -> None:
        """Enter ``mode`` (no checks): hold here, restart the mode's controller."""
        b = self.body
        self.mode = mode
        self.failsafe = False
        self.hold_point = (b.pos[0], b.pos[1], b.pos[2])
        self.hold_yaw = b.yaw
        kind = modes.behaviour(mode)
        if kind == "rtl":
            self.rtl_phase = "climb"
        self.flavour.on_enter_mode(self, kind)

    def change_mode(self, name: str) -> Reply:
        """Enter ``name`` if the flavour's rules allow it now."""
        return self.flavour.change_mode(self, name)

    def hold_target(self) -> Target:
        return Target(pos=self.hold_point, yaw=self.hold_yaw)

    def climb_target(self, speed: float) -> Target:
        """Climb above the hold point to ``takeoff_z`` at ``speed`` m/s."""
        return Target(
            pos=(self.hold_point[0], self.hold_point[1], self.takeoff_z), yaw=self.hold_yaw, v_up=speed
        )

    def geo(self, n: float, e: float, d: float) -> tuple[float, float, float]:
        lat, lon, alt = pymap3d.ned2geodetic(n, e, d, *self.origin)
        return float(lat), float(lon), float(alt)

    def out(self, msg: Msg) -> None:
        """Send ``msg`` with the next output (for the flavours' unrequested messages)."""
        self._out.append(msg)

    def text(self, severity: int, text: str) -> None:
        """Say ``text``: a STATUSTEXT, or what the flavour says it with (PX4: an EVENT)."""
        ev = self.flavour.event_for(severity, text)
        if ev is not None:
            self.flavour.event(self, ev)
            return
        self._out.append(self.mav.statustext_encode(severity, text.encode("ascii", "replace")[:50]))

    def set_stream(self, mid: int, interval: float) -> None:
        """Send ``mid`` every ``interval`` simulated s from now on (<= 0: stop)."""
        if interval <= 0:
            self.streams.pop(mid, None)
            return
        interval = max(interval, 1.0 / MAX_STREAM_HZ)
        nxt = math.floor(self.t / interval + 1e-9) * interval + interval
        self.streams[mid] = [interval, nxt]

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
        self.flavour.check_timeouts(self)
        target = self._compute_target()
        self.target = target
        b.step(target, self.lim, self.dt, powered=self.armed)
        if self.armed and not b.on_ground:
            if not self.took_off:
                self.flavour.on_lift_off(self)
            self.took_off = True
            self.touchdown_time = None
        elif self.armed and b.on_ground and not was_ground:
            self.touchdown_time = self.t
        landed = self._compute_landed()
        if landed == ON_GROUND and self.landed_state in (IN_AIR, LANDING) and self.armed:
            self.flavour.on_landing_detected(self)
        self.landed_state = landed
        self._after_step()
        self._drain()

    def _compute_landed(self) -> int:
        if self.body.on_ground:
            detecting = (
                self.touchdown_time is not None
                and self.t - self.touchdown_time < self.flavour.land_detect_delay
            )
            if not (self.armed and detecting):
                return ON_GROUND
            return self.landed_state  # the land detector has not decided yet
        kind = modes.behaviour(self.mode)
        if kind == "takeoff" or self.flavour.taking_off(self, kind):
            return TAKEOFF
        if kind == "land" or (kind == "rtl" and self.rtl_phase == "land"):
            return LANDING
        return IN_AIR

    def _after_step(self) -> None:
        b = self.body
        kind = modes.behaviour(self.mode)
        self.flavour.after_step(self, kind)
        if kind == "rtl":
            hx, hy = self.home[0], self.home[1]
            if self.rtl_phase == "climb" and b.pos[2] <= self._rtl_z() + 0.3:
                self.rtl_phase = "return"
            elif self.rtl_phase == "return" and math.hypot(b.pos[0] - hx, b.pos[1] - hy) < 0.5:
                self.rtl_phase, self.rtl_home_time = "loiter", self.t
            elif self.rtl_phase == "loiter" and self.t - self.rtl_home_time >= self.flavour.rtl_loiter:
                self.rtl_phase = "land"
        if not self.armed:
            return
        spooling = self.flavour.taking_off(self, kind)  # a take-off spooling up is not idle
        if (
            b.on_ground
            and not self.took_off
            and not spooling
            and self.t - self.arm_time >= PRE_TAKEOFF_DISARM
        ):
            self._disarm(self.flavour.text_preflight_disarm)
        elif b.on_ground and self.took_off and self.touchdown_time is not None:
            if self.t - self.touchdown_time >= self.flavour.touchdown_disarm_delay(kind):
                self._disarm(self.flavour.text_landed_disarm)

    def _drain(self) -> None:
        rate = self.battery_drain / 60.0
        if self.armed and self.body.on_ground:
            rate += 0.02
        elif self.armed:
            a = self.body.acc
            rate += 0.08 + 0.004 * math.sqrt(a[0] ** 2 + a[1] ** 2 + a[2] ** 2)
        if rate <= 0.0:
            return
        self.battery = max(0.0, self.battery - rate * self.dt)
        if self.battery < BATTERY_CRITICAL and self._battery_warned < 2:
            self._battery_warned = 2
            self.text(2, self.flavour.text_battery_critical)
        elif self.battery < BATTERY_LOW and self._battery_warned < 1:
            self._battery_warned = 1
            self.text(4, self.flavour.text_battery_low)

    def _emit_due(self) -> None:
        t = self.t + 1e-9
        if t >= self.next_hb:
            self._out.append(self.flavour.heartbeat(self))
            self.next_hb += 1.0
            if self.next_hb <= t:
                self.next_hb = math.floor(t) + 1.0
        for mid, entry in self.streams.items():
            if t >= entry[1]:
                m = telemetry.message(self, mid)
                if m is not None:
                    self._out.append(m)
                entry[1] += entry[0]
                if entry[1] <= t:
                    entry[1] = t + entry[0]

    # ---------------------------------------------------------------- targets
    def _rtl_z(self) -> float:
        return min(self.body.pos[2], self.home[2] - RTL_ALT)

    def _compute_target(self) -> Target | None:
        kind = modes.behaviour(self.mode)
        if kind in ("offboard", "guided"):
            return self.flavour.own_target(self)
        if kind == "takeoff":
            return self.flavour.takeoff_target(self)
        if kind == "land":
            return self._descent_target(self.hold_point[0], self.hold_point[1], self.hold_yaw)
        if kind == "rtl":
            return self._rtl_target()
        return self.hold_target()

    def _descent_target(self, n: float, e: float, yaw: float) -> Target:
        v = self.flavour.descent_speed(self, self.home[2] - self.body.pos[2])
        return Target(pos=(n, e, NAN), vel=(NAN, NAN, v), yaw=yaw, v_down=v)

    def _rtl_target(self) -> Target | None:
        b = self.body
        hx, hy, _ = self.home
        if b.on_ground and self.rtl_phase != "land":
            return self.hold_target() if not self.took_off else None
        if self.rtl_phase == "climb":
            return Target(pos=(self.hold_point[0], self.hold_point[1], self._rtl_z()), yaw=b.yaw)
        if self.rtl_phase == "loiter":
            return Target(pos=(hx, hy, self._rtl_z()), yaw=b.yaw)
        if self.rtl_phase == "return":
            far = math.hypot(hx - b.pos[0], hy - b.pos[1]) > 2.0
            return Target(
                pos=(hx, hy, self._rtl_z()), yaw=math.atan2(hy - b.pos[1], hx - b.pos[0]) if far else b.yaw
            )
        return self._descent_target(hx, hy, b.yaw)

    # -------------------------------------------------------------- outputs
    def _flush(self) -> list[Msg]:
        out, self._out = self._out, []
        return out

    def _for_me(self, msg: Msg) -> bool:
        return msg.target_system in (0, self.sysid) and msg.target_component in (0, 1)

    # -------------------------------------------------------------- commands
    def _on_flavour_message(self, msg_type: str, msg: Msg) -> None:
        if msg_type == "SET_POSITION_TARGET_LOCAL_NED":
            self.flavour.on_local_setpoint(self, msg)
        elif msg_type == "SET_POSITION_TARGET_GLOBAL_INT":
            self.flavour.on_global_setpoint(self, msg)
        else:
            self.flavour.on_request_data_stream(self, msg)

    def _on_command(self, msg: Msg, src: tuple[int, int]) -> None:
        if not self._for_me(msg):
            return
        cmd = msg.command
        if msg.get_type() == "COMMAND_INT":
            local = msg.frame in (1, 7, 8, 9)
            x, y = (float(msg.x), float(msg.y)) if local else (msg.x / 1e7, msg.y / 1e7)
            params = (msg.param1, msg.param2, msg.param3, msg.param4, x, y, msg.z)
            frame: int | None = msg.frame
        else:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
            frame = None
        before = self.mode
        self._ack(cmd, src, self._command(cmd, params, frame))
        self._mode_beat(before)

    def _ack(self, cmd: int, src: tuple[int, int], reply: Reply) -> None:
        result, text = reply
        if text:
            self.text(4 if result else 6, text)
        self._out.append(self.mav.command_ack_encode(cmd, result, 0, 0, src[0], src[1]))

    def _mode_beat(self, before: str) -> None:
        """The extra HEARTBEAT some autopilots send with the ACK of a mode change."""
        if self.mode != before and self.flavour.heartbeat_on_mode_change:
            self._out.append(self.flavour.heartbeat(self))

    def _reject(self, text: str) -> tuple[int, str]:
        return self.flavour.refusal, text

    def _command(self, cmd: int, p: tuple[float, ...], frame: int | None) -> Reply:
        if cmd == 400:
            return self._arm_cmd(p)
        if cmd == 176:
            if not int(p[0]) & 1:
                return DENIED, "Mode change denied: custom mode flag not set"
            return self.flavour.set_mode_numbers(self, p[1], p[2])
        if cmd == 22:
            return (
                self._reject("Takeoff denied: no position")
                if not self.gps_ok
                else self.flavour.takeoff(self, p, frame)
            )
        if cmd == 21:
            return self.change_mode(self.flavour.land_mode)
        if cmd == 20:
            return self.change_mode(self.flavour.rtl_mode)
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

    def _set_interval(self, mid: int, us: float) -> Reply:
        if mid == 0:
            return ACCEPTED, None
        if mid not in telemetry.STREAMABLE or not self.flavour.can_stream(mid):
            return self.flavour.unknown_stream(mid)
        if us == 0:
            self.set_stream(mid, self.flavour.default_streams.get(mid, 0.0))
        elif us < 0:
            self.set_stream(mid, 0.0)
        else:
            self.set_stream(mid, us / 1e6)
        return ACCEPTED, None

    def _request_message(self, mid: int) -> Reply:
        if mid not in telemetry.REQUESTABLE:
            return UNSUPPORTED, None
        m = telemetry.message(self, mid)
        if m is None:
            return (ACCEPTED, None) if self.flavour.defer_request(self, mid) else (self.flavour.refusal, None)
        self._out.append(m)
        return ACCEPTED, None

    def _on_set_mode_msg(self, msg: Msg, src: tuple[int, int]) -> None:
        if msg.target_system != self.sysid:
            return
        before = self.mode
        self._ack(self.flavour.set_mode_ack, src, self.flavour.set_custom_mode(self, msg.custom_mode))
        self._mode_beat(before)

    # ------------------------------------------------------- arming, reposition
    def _arm_cmd(self, p: tuple[float, ...]) -> Reply:
        if p[0] >= 0.5:
            if self.armed:
                return ACCEPTED, None
            refusals = self.flavour.arm_refusal(self, p)
            if refusals:
                for text in refusals:  # each reason its own STATUSTEXT, then the ACK
                    self.text(self.flavour.refusal_severity, text)
                return self.flavour.refusal, None
            self._arm()
            self.flavour.on_arm(self)
            return ACCEPTED, self.flavour.text_armed
        if not self.armed:
            return ACCEPTED, None
        if not self.body.on_ground and int(p[1]) != FORCE_MAGIC:
            return self._reject(self.flavour.text_disarm_denied)
        self._disarm(None)
        return ACCEPTED, self.flavour.text_disarmed

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
        self.flavour.on_disarm(self, modes.behaviour(self.mode))
        if text:
            self.text(6, text)

    def _reposition(self, p: tuple[float, ...], frame: int | None) -> Reply:
        b = self.body
        if frame is None and not self.flavour.reposition_by_long:
            return UNSUPPORTED, None
        if not self.gps_ok or not self.armed or b.on_ground:
            return self._reject("Reposition denied: not flying")
        lat, lon, alt = p[4], p[5], p[6]
        n, e, d = b.pos
        if finite(lat) and finite(lon) and (lat != 0.0 or lon != 0.0):
            n, e, _ = pymap3d.geodetic2ned(lat, lon, self.origin[2], *self.origin)
        if finite(alt):
            d = (self.home[2] - alt) if frame in (3, 6) else -(alt - self.origin[2])
        return self.flavour.reposition(self, p, (float(n), float(e), float(d)))
