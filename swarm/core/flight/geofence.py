"""The geofence: where a command may send a vehicle, checked where sent and where carried out.

Theory of operation
-------------------
Every altitude an operator types, the API takes and a Command carries is in metres
*above the vehicle's home* (QGroundControl's default; MAVLink's GLOBAL_RELATIVE_ALT
frame), so the station need not know each home and 20 means 20 m above the ground
the vehicle took off from, whatever that ground's height above sea level.

A :class:`Geofence` holds three limits: a ``floor_m`` and a ``ceiling_m`` above home
and a ``radius_m`` around home. :meth:`Geofence.refusal` answers a target (a
take-off's altitude, or a go-to's position and altitude) with None (inside) or one
short line saying which limit it breaks; it knows nothing of who asks. The agent's
pilot (:mod:`swarm.core.flight.pilot`) checks every command against its own fence and the
vehicle's home, the last word; the ground station
(:meth:`swarm.core.station.delivery.CommandDelivery.submit`) checks its own fence
before sending anything, and the radius only when it knows the agent's home (the
position it last saw the agent on the ground): otherwise it leaves the radius to the
agent. Pure: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from swarm.core.flight.formation import ne_between

#: the highest ceiling and the widest radius a fence takes (a Command's altitude
#: field tops out at 5553 m; a go-to travels at most 5 km)
MAX_CEILING_M = 5000.0
MAX_RADIUS_M = 50_000.0


def _finite(v: object) -> bool:
    """A finite float, or an int a float holds (a 400-digit integer is no altitude)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    return abs(v) < 10**15 if isinstance(v, int) else math.isfinite(v)


def _show(v: object) -> str:
    text = repr(v)
    return text if len(text) <= 24 else text[:20] + "..."


@dataclass(frozen=True)
class Geofence:
    """Limits around home: a target below ``floor_m`` or above ``ceiling_m`` (metres
    above home) or farther than ``radius_m`` from home is refused.

    Raises:
        ValueError: (one line) a limit that is not a finite number, a negative floor,
            a ceiling not above the floor or above :data:`MAX_CEILING_M`, a radius not
            positive or above :data:`MAX_RADIUS_M`.
    """

    floor_m: float = 2.0
    ceiling_m: float = 120.0
    radius_m: float = 1000.0

    def __post_init__(self) -> None:
        for k in ("floor_m", "ceiling_m", "radius_m"):
            v = getattr(self, k)
            if not _finite(v):
                raise ValueError(f"geofence {k[:-2]} {_show(v)}: a finite number of metres")
        if self.floor_m < 0:
            raise ValueError(f"geofence floor {self.floor_m:g} m: 0 or more (metres above home)")
        if not self.floor_m < self.ceiling_m <= MAX_CEILING_M:
            raise ValueError(
                f"geofence ceiling {self.ceiling_m:g} m: above the floor ({self.floor_m:g} m)"
                f" and at most {MAX_CEILING_M:g} m"
            )
        if not 0 < self.radius_m <= MAX_RADIUS_M:
            raise ValueError(f"geofence radius {self.radius_m:g} m: more than 0, at most {MAX_RADIUS_M:g}")

    def alt_refusal(self, alt: float) -> str | None:
        """Why ``alt`` (metres above home) is refused, or None."""
        if not _finite(alt):
            return f"altitude {_show(alt)} is not a finite number"
        if alt < self.floor_m:
            return f"altitude {alt:g} m above home is below the floor ({self.floor_m:g} m above home)"
        if alt > self.ceiling_m:
            return f"altitude {alt:g} m above home is above the ceiling ({self.ceiling_m:g} m)"
        return None

    def refusal(self, lat: float, lon: float, alt: float, home: tuple[float, float] | None) -> str | None:
        """Why a target at ``lat``, ``lon``, ``alt`` metres above home is refused, or
        None. ``home``: (lat, lon), or None when unknown: then the radius is not
        checked here (the caller says who does)."""
        if not (_finite(lat) and _finite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
            return "position out of range"
        why = self.alt_refusal(alt)
        if why is not None or home is None:
            return why
        d = math.hypot(*ne_between(home[0], home[1], lat, lon))
        if d > self.radius_m:
            return f"target {d:.0f} m from home, beyond the radius ({self.radius_m:g} m)"
        return None


__all__ = ["MAX_CEILING_M", "MAX_RADIUS_M", "Geofence"]
