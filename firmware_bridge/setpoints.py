"""Position setpoints: validation and the SET_POSITION_TARGET_* messages.

Theory of operation. A setpoint is checked before anything is sent: every value
must be a finite number, positions within 10 km of the origin, altitudes within
-1 km..10 km, speeds at most 30 m/s; a bad one raises :class:`SetpointError` and
the caller's current target stays. A good one becomes an immutable
:class:`LocalTarget` (NED metres from the EKF origin) or :class:`GlobalTarget`
(degrees, metres above home), yaw wrapped to -pi..pi. :func:`setpoint_message`
turns a target into SET_POSITION_TARGET_LOCAL_NED (frame 1) or _GLOBAL_INT
(frame 6) with the type mask position + yaw (2552), or position + velocity
feed-forward + yaw (2496). Pure: no I/O, no clock (the caller gives the boot time).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega

from firmware_bridge.errors import SetpointError

mavlink: Any = ardupilotmega

__all__ = [
    "GlobalTarget",
    "LocalTarget",
    "finite",
    "setpoint_message",
    "validate_global",
    "validate_local",
    "validate_takeoff_altitude",
    "wrap_yaw",
]

FRAME_LOCAL_NED = 1
FRAME_GLOBAL_RELATIVE_ALT_INT = 6
MASK_POS_YAW = 2552  # ignore velocity, acceleration, force and yaw rate
MASK_POS_VEL_YAW = 2496  # position + velocity feed-forward + yaw
MAX_VELOCITY_MS = 30.0

# setpoint sanity limits
MAX_LOCAL_M = 10_000.0
MAX_ALT_M = 10_000.0
MIN_ALT_M = -1_000.0
MIN_TAKEOFF_M = 0.5


@dataclass(frozen=True)
class LocalTarget:
    """Position in the autopilot's local NED frame (EKF origin), yaw in radians."""

    north: float
    east: float
    down: float
    yaw: float
    velocity: tuple[float, float, float] | None = None  # NED m/s feed-forward


@dataclass(frozen=True)
class GlobalTarget:
    """Latitude/longitude in degrees, altitude in metres above home."""

    lat: float
    lon: float
    rel_alt: float
    yaw: float
    velocity: tuple[float, float, float] | None = None  # NED m/s feed-forward


def wrap_yaw(yaw: float) -> float:
    """``yaw`` in radians wrapped to -pi..pi."""
    return math.atan2(math.sin(yaw), math.cos(yaw))


def finite(name: str, value: float) -> float:
    """``value`` as a finite float.

    Raises:
        SetpointError: not a number, NaN or infinite (``name`` says which value).
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SetpointError(f"{name} {value!r} is not a number") from None
    if not math.isfinite(v):
        raise SetpointError(f"{name} is {v}: setpoints must be finite")
    return v


def _velocity(v: Sequence[float] | None) -> tuple[float, float, float] | None:
    if v is None:
        return None
    if len(v) != 3:
        raise SetpointError(f"velocity {v!r}: three components (north, east, down) in m/s")
    out = (finite("velocity north", v[0]), finite("velocity east", v[1]), finite("velocity down", v[2]))
    if any(abs(x) > MAX_VELOCITY_MS for x in out):
        raise SetpointError(f"velocity {out} above {MAX_VELOCITY_MS:g} m/s")
    return out


def validate_local(
    north: float, east: float, down: float, yaw: float, velocity: Sequence[float] | None = None
) -> LocalTarget:
    """Check a local NED setpoint.

    Raises:
        SetpointError: NaN/inf, |north| or |east| > 10 km, altitude out of range.
    """
    n, e, d = finite("north", north), finite("east", east), finite("down", down)
    y = finite("yaw", yaw)
    for name, v in (("north", n), ("east", e)):
        if abs(v) > MAX_LOCAL_M:
            raise SetpointError(f"{name} {v:g} m is more than {MAX_LOCAL_M:g} m from the origin")
    if not MIN_ALT_M <= -d <= MAX_ALT_M:
        raise SetpointError(f"down {d:g} m is outside {-MAX_ALT_M:g}..{-MIN_ALT_M:g} m")
    return LocalTarget(n, e, d, wrap_yaw(y), _velocity(velocity))


def validate_global(
    lat: float, lon: float, rel_alt: float, yaw: float, velocity: Sequence[float] | None = None
) -> GlobalTarget:
    """Check a global setpoint (altitude relative to home).

    Raises:
        SetpointError: NaN/inf, latitude/longitude out of range, altitude out of range.
    """
    la, lo, a = finite("lat", lat), finite("lon", lon), finite("rel_alt", rel_alt)
    y = finite("yaw", yaw)
    if not -90.0 <= la <= 90.0:
        raise SetpointError(f"latitude {la:g} outside -90..90")
    if not -180.0 <= lo <= 180.0:
        raise SetpointError(f"longitude {lo:g} outside -180..180")
    if not MIN_ALT_M <= a <= MAX_ALT_M:
        raise SetpointError(f"relative altitude {a:g} m outside {MIN_ALT_M:g}..{MAX_ALT_M:g} m")
    return GlobalTarget(la, lo, a, wrap_yaw(y), _velocity(velocity))


def validate_takeoff_altitude(rel_alt: float) -> float:
    """Check a takeoff altitude above home.

    Raises:
        SetpointError: not finite, or outside 0.5..10 km.
    """
    alt = finite("takeoff altitude", rel_alt)
    if not MIN_TAKEOFF_M <= alt <= MAX_ALT_M:
        raise SetpointError(f"takeoff altitude {alt:g} m outside {MIN_TAKEOFF_M:g}..{MAX_ALT_M:g} m")
    return alt


def setpoint_message(
    target: LocalTarget | GlobalTarget, *, time_boot_ms: int, target_system: int, target_component: int
) -> Any:
    """The SET_POSITION_TARGET_* message for ``target``: LOCAL_NED (frame 1) or
    GLOBAL_INT (frame 6, relative altitude), type mask position + yaw (2552), or
    position + velocity feed-forward + yaw (2496) when the target has a velocity."""
    t = time_boot_ms & 0xFFFFFFFF
    vel = target.velocity
    mask = MASK_POS_YAW if vel is None else MASK_POS_VEL_YAW
    vn, ve, vd = vel if vel is not None else (0.0, 0.0, 0.0)
    tail = (vn, ve, vd, 0, 0, 0, target.yaw, 0)  # velocity, acceleration (unused), yaw, yaw rate
    if isinstance(target, LocalTarget):
        return mavlink.MAVLink_set_position_target_local_ned_message(
            t, target_system, target_component, FRAME_LOCAL_NED, mask,
            target.north, target.east, target.down, *tail,
        )  # fmt: skip
    return mavlink.MAVLink_set_position_target_global_int_message(
        t, target_system, target_component, FRAME_GLOBAL_RELATIVE_ALT_INT, mask,
        round(target.lat * 1e7), round(target.lon * 1e7), target.rel_alt, *tail,
    )  # fmt: skip
