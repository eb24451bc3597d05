"""What differs between the simulated PX4 and ArduCopter: the :class:`Flavour` interface.

Theory of operation. :class:`~firmware_bridge.sim.autopilot.Autopilot` holds the logic
both autopilots share (time steps, physics, arming and disarming, the hold, take-off,
land and return modes, streams, command dispatch and acks). Wherever the two differ it
asks its flavour, one object per vehicle: :class:`~firmware_bridge.sim.px4.Px4` or
:class:`~firmware_bridge.sim.ardupilot.ArduPilot`. A flavour holds

* data: mode names, controller limits, default streams, the MAV_RESULT of a refusal,
  landing and take-off speeds, STATUSTEXT wordings, the SITL link it imitates;
* rules, as methods given the autopilot: heartbeat fields, mode numbers, arming
  checks, mode-change checks, take-off and reposition commands, setpoint parsing;
* its own external-control mode and that mode's state: PX4 OFFBOARD (the setpoint
  stream and its loss failsafe), ArduCopter GUIDED (sub-mode, target, GUID_TIMEOUT).

Like the autopilot it does no I/O and reads no clock. This module also holds the
MAVLink constants and the setpoint field helpers both flavours use.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar

import pymap3d

from firmware_bridge.sim.dynamics import NAN, Limits, Target

if TYPE_CHECKING:
    from firmware_bridge.sim.autopilot import Autopilot

Msg = Any  # a pymavlink MAVLink_message
Reply = tuple[int, str | None]  # (MAV_RESULT, STATUSTEXT or None) of a command

# MAV_RESULT
ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = 0, 1, 2, 3, 4
# MAV_LANDED_STATE
ON_GROUND, IN_AIR, TAKEOFF, LANDING = 1, 2, 3, 4

PRE_TAKEOFF_DISARM = 10.0  # COM_DISARM_PRFLT / DISARM_DELAY, s


def finite(x: float) -> bool:
    return math.isfinite(x)


def rotate(v: list[float], yaw: float) -> list[float]:
    """Rotate the horizontal part of ``v`` by ``yaw`` (body frame to NED)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return [v[0] * c - v[1] * s, v[0] * s + v[1] * c, v[2]]


def setpoint_fields(
    msg: Msg, xyz: tuple[float, float, float]
) -> tuple[list[float], list[float], list[float]]:
    """Position, velocity and acceleration of a SET_POSITION_TARGET_*; ignored fields NaN."""
    mask = msg.type_mask
    pos = [NAN if mask & bit else v for bit, v in zip((1, 2, 4), xyz, strict=True)]
    vel = [NAN if mask & bit else v for bit, v in zip((8, 16, 32), (msg.vx, msg.vy, msg.vz), strict=True)]
    acc = [
        NAN if mask & bit else v for bit, v in zip((64, 128, 256), (msg.afx, msg.afy, msg.afz), strict=True)
    ]
    return pos, vel, acc


def global_setpoint_ned(ap: Autopilot, msg: Msg) -> tuple[float, float, float]:
    """SET_POSITION_TARGET_GLOBAL_INT's position in the local NED frame (flat terrain)."""
    n, e, _ = pymap3d.geodetic2ned(msg.lat_int / 1e7, msg.lon_int / 1e7, ap.origin[2], *ap.origin)
    frame = msg.coordinate_frame
    if frame in (0, 5):
        d = -(msg.alt - ap.origin[2])
    elif frame in (3, 6):
        d = ap.home[2] - msg.alt
    else:
        d = -msg.alt  # flat terrain at the origin's altitude
    return float(n), float(e), float(d)


class Flavour(ABC):
    """One autopilot's rules. Subclasses set all the data below and implement every rule."""

    name: ClassVar[str]  # the profile: "px4" or "ardupilot"
    #: the SITL link imitated: "udp" (vehicle i sends to base+i) or "tcp" (listens on base+10i)
    sitl_link: ClassVar[str]
    sitl_base_port: ClassVar[int]
    sitl_port_step: ClassVar[int]
    initial_mode: ClassVar[str]
    land_mode: ClassVar[str]
    rtl_mode: ClassVar[str]
    limits: ClassVar[Limits]
    #: streams at boot, and the interval SET_MESSAGE_INTERVAL 0 restores (msg id -> s)
    default_streams: ClassVar[dict[int, float]]
    refusal: ClassVar[int]  # MAV_RESULT of a refused command, or a message not available
    takeoff_speed: ClassVar[float]  # m/s
    land_speed_low: ClassVar[float]  # m/s below 10 m (1.5 m/s above)
    version: ClassVar[int]  # AUTOPILOT_VERSION flight_sw_version
    set_mode_ack: ClassVar[int]  # the command a SET_MODE message is acked as
    reposition_by_long: ClassVar[bool]  # DO_REPOSITION accepted in COMMAND_LONG
    # STATUSTEXT wordings
    text_gps_lost: ClassVar[str]
    text_gps_failsafe: ClassVar[str]
    text_preflight_disarm: ClassVar[str]
    text_landed_disarm: ClassVar[str]
    text_disarm_denied: ClassVar[str]
    text_armed: ClassVar[str | None]  # after an accepted arm command
    text_disarmed: ClassVar[str | None]  # after an accepted disarm command
    text_battery_low: ClassVar[str]  # WARNING, when the battery falls below BATTERY_LOW
    text_battery_critical: ClassVar[str]  # CRITICAL, below BATTERY_CRITICAL
    refusal_severity: ClassVar[int] = 4  # STATUSTEXT severity of a refused arm's reasons
    heartbeat_on_mode_change: ClassVar[bool] = False  # one more HEARTBEAT with the ACK
    gps_fix_type: ClassVar[int] = 3  # GPS_RAW_INT fix_type with a fix
    rtl_loiter: ClassVar[float] = 0.0  # s a return hovers over home before it lands
    #: the parameters it answers the MAVLink parameter protocol with: (name, default,
    #: MAV_PARAM_TYPE), the real autopilot's names and defaults (:mod:`.params`)
    params: ClassVar[tuple[tuple[str, float, int], ...]] = ()
    param_bytewise: ClassVar[bool] = False  # integers as their bits in the float (PX4)
    param_read_index: ClassVar[bool] = False  # a read by name reports the index (PX4), else 65535
    param_hash_first: ClassVar[bool] = False  # a list starts with _HASH_CHECK (PX4)
    #: s from touchdown until the land detector says so (landed state ON_GROUND)
    land_detect_delay: ClassVar[float] = 0.0
    #: before its fix, GLOBAL_POSITION_INT is sent with zeros (ArduPilot); else not at all
    zero_position_before_fix: ClassVar[bool] = True

    # ------------------------------------------- boot (default: none, booted)
    def position_valid(self, ap: Autopilot) -> bool:
        """GLOBAL_POSITION_INT and GPS_RAW_INT carry a position (else zeros, no fix)."""
        return True

    def local_valid(self, ap: Autopilot) -> bool:
        """LOCAL_POSITION_NED is sent."""
        return True

    def home_set(self, ap: Autopilot) -> bool:
        """HOME_POSITION can be answered."""
        return True

    def gps_detected(self, ap: Autopilot) -> bool:
        """GPS_RAW_INT has a fix (and SYS_STATUS a healthy GPS)."""
        return self.position_valid(ap)

    def prearm_ok(self, ap: Autopilot) -> bool | None:
        """SYS_STATUS's pre-arm check bit (None: this autopilot does not report it)."""
        return None

    def defer_request(self, ap: Autopilot, mid: int) -> bool:
        """True: REQUEST_MESSAGE ``mid`` that has no answer yet is accepted, answered later."""
        return False

    def ekf_flags(self, ap: Autopilot) -> int | None:
        """EKF_STATUS_REPORT.flags now (None: not sent)."""
        return None

    def can_stream(self, mid: int) -> bool:
        """This autopilot sends message ``mid`` when asked (among those the simulator encodes)."""
        return True

    def event_for(self, severity: int, text: str) -> Any:
        """What the autopilot sends instead of a STATUSTEXT ``text`` (PX4: an EVENT), or None."""
        return None

    def event(self, ap: Autopilot, ev: Any) -> None:
        """Send ``ev``, a value :meth:`event_for` returned."""
        return None

    def takeoff_target(self, ap: Autopilot) -> Target:
        """The controller's target in the take-off mode."""
        return ap.climb_target(self.takeoff_speed)

    def descent_speed(self, ap: Autopilot, alt: float) -> float:
        """A landing's descent speed at ``alt`` m above home."""
        return 1.5 if alt > 10.0 else self.land_speed_low

    def on_lift_off(self, ap: Autopilot) -> None:
        """The land detector saw the vehicle leave the ground."""
        return None

    def on_landing_detected(self, ap: Autopilot) -> None:
        """The land detector says the vehicle is on the ground (after ``land_detect_delay``)."""
        return None

    def unknown_stream(self, mid: int) -> Reply:
        """The reply to SET_MESSAGE_INTERVAL for a message this autopilot cannot stream."""
        return UNSUPPORTED, None

    def on_arm(self, ap: Autopilot) -> None:
        """After an accepted arm (before its STATUSTEXT)."""
        return None

    # ---------------------------------------------------------------- status
    @abstractmethod
    def heartbeat(self, ap: Autopilot) -> Msg:
        """The HEARTBEAT this autopilot sends now."""

    @abstractmethod
    def touchdown_disarm_delay(self, kind: str) -> float:
        """Seconds on the ground after a flight before auto-disarm, in a mode of ``kind``."""

    @abstractmethod
    def echo_mask(self, ap: Autopilot) -> int | None:
        """Extra ignore bits of POSITION_TARGET_LOCAL_NED, or None when not echoed now."""

    # ----------------------------------------------------------------- modes
    @abstractmethod
    def set_mode_numbers(self, ap: Autopilot, p2: float, p3: float) -> Reply:
        """DO_SET_MODE with the custom-mode flag: params 2 and 3 name the mode."""

    @abstractmethod
    def set_custom_mode(self, ap: Autopilot, custom_mode: int) -> Reply:
        """A SET_MODE message's custom_mode."""

    @abstractmethod
    def change_mode(self, ap: Autopilot, name: str) -> Reply:
        """Check and enter mode ``name`` (a name of this flavour's table)."""

    @abstractmethod
    def arm_refusal(self, ap: Autopilot, p: tuple[float, ...]) -> tuple[str, ...]:
        """Why an arm command with params ``p`` is refused (one STATUSTEXT each); () to arm."""

    # -------------------------------------------------------------- commands
    @abstractmethod
    def takeoff(self, ap: Autopilot, p: tuple[float, ...], frame: int | None) -> Reply:
        """NAV_TAKEOFF once the position check passed; ``frame`` None for COMMAND_LONG."""

    @abstractmethod
    def reposition(self, ap: Autopilot, p: tuple[float, ...], ned: tuple[float, float, float]) -> Reply:
        """DO_REPOSITION to ``ned`` once the flying checks passed."""

    @abstractmethod
    def on_local_setpoint(self, ap: Autopilot, msg: Msg) -> None:
        """A SET_POSITION_TARGET_LOCAL_NED addressed to this vehicle."""

    @abstractmethod
    def on_global_setpoint(self, ap: Autopilot, msg: Msg) -> None:
        """A SET_POSITION_TARGET_GLOBAL_INT addressed to this vehicle."""

    @abstractmethod
    def on_request_data_stream(self, ap: Autopilot, msg: Msg) -> None:
        """A REQUEST_DATA_STREAM addressed to this vehicle."""

    # ----------------------------------------- the flavour's own control mode
    @abstractmethod
    def check_timeouts(self, ap: Autopilot) -> None:
        """Before each physics step: the external-control timeouts and failsafes."""

    @abstractmethod
    def own_target(self, ap: Autopilot) -> Target:
        """The controller's target in the external-control mode (OFFBOARD / GUIDED)."""

    @abstractmethod
    def after_step(self, ap: Autopilot, kind: str) -> None:
        """After each physics step (before auto-disarm): mode transitions of its own."""

    @abstractmethod
    def taking_off(self, ap: Autopilot, kind: str) -> bool:
        """True while the external-control mode climbs to a take-off altitude."""

    @abstractmethod
    def on_enter_mode(self, ap: Autopilot, kind: str) -> None:
        """After the autopilot entered a mode (hold point and yaw already set)."""

    @abstractmethod
    def on_disarm(self, ap: Autopilot, kind: str) -> None:
        """After the autopilot disarmed (before its STATUSTEXT)."""
