"""Wind, gusts and GPS noise for the flight simulator's vehicles, in virtual time, seeded.

Theory of operation
-------------------
:class:`Weather` says what the air and the satellites do; :class:`Environment` runs it
for N vehicles, one fixed step ``dt`` at a time, from its own seeded random generator
(the same seed gives the same gusts and the same GPS errors). Nothing reads a clock.

* **Wind**: a steady wind of ``wind_mps`` blowing from ``wind_from_deg`` (the
  meteorological convention: 270 is a west wind, blowing east), plus gusts, one
  first-order Gauss-Markov process per horizontal axis (standard deviation
  ``gust_mps``, correlation time ``gust_tau_s``), the same for every vehicle (they
  fly within a few tens of metres of each other).
* **What wind does to a multicopter**: a drag acceleration ``drag_per_s`` times the
  air-relative velocity (wind minus ground velocity). The autopilot's velocity loop
  has an integrator that learns a steady push; it is modelled as an estimate of the
  push that follows it with time constant ``integrator_tau_s``, and only the part it
  has not learnt yet moves the vehicle (:meth:`Environment.push`). A steady wind
  therefore costs a transient when the vehicle's speed or the wind changes; gusts
  cost what the integrator cannot follow.
* **GPS noise**: each vehicle's position estimate is off its true position by its
  own Gauss-Markov error (horizontal RMS ``gps_noise_m``, correlation time
  ``gps_tau_s``): the autopilot flies its *estimate* to the setpoint and the agent
  reports its estimate on the air, while the formation metrics use the true
  positions. The errors of different vehicles are independent, which is the worst
  case: receivers side by side share most of theirs.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass


@dataclass(frozen=True)
class Weather:
    wind_mps: float = 0.0
    wind_from_deg: float = 270.0
    gust_mps: float = 0.0
    gust_tau_s: float = 2.0
    gps_noise_m: float = 0.0
    gps_tau_s: float = 5.0
    drag_per_s: float = 0.3
    integrator_tau_s: float = 1.5

    def __post_init__(self) -> None:
        limits = {
            "wind_mps": (0.0, 30.0),
            "wind_from_deg": (0.0, 360.0),
            "gust_mps": (0.0, 15.0),
            "gust_tau_s": (0.1, 60.0),
            "gps_noise_m": (0.0, 20.0),
            "gps_tau_s": (0.1, 600.0),
            "drag_per_s": (0.0, 5.0),
            "integrator_tau_s": (0.05, 60.0),
        }
        for k, (lo, hi) in limits.items():
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"weather {k}={v!r}: {lo:g}..{hi:g}")

    @property
    def calm(self) -> bool:
        return self.wind_mps == 0.0 and self.gust_mps == 0.0 and self.gps_noise_m == 0.0

    def describe(self) -> dict[str, float]:
        return {"wind_mps": self.wind_mps, "gust_mps": self.gust_mps, "gps_noise_m": self.gps_noise_m}


def _markov(x: float, sigma: float, tau: float, dt: float, rng: random.Random) -> float:
    """One step of a first-order Gauss-Markov process (stationary standard deviation ``sigma``)."""
    if sigma == 0.0:
        return 0.0
    return x - x * dt / tau + sigma * math.sqrt(2.0 * dt / tau) * rng.gauss(0.0, 1.0)


class Environment:
    """The weather of N vehicles (see the module docstring)."""

    def __init__(self, weather: Weather, vehicles: int, seed: int) -> None:
        self.w = weather
        self.rng = random.Random(seed)
        frm = math.radians(weather.wind_from_deg)
        # blowing from wind_from_deg: toward the opposite direction (north, east)
        self.steady = (-weather.wind_mps * math.cos(frm), -weather.wind_mps * math.sin(frm))
        g = weather.gust_mps
        self.gust = [self.rng.gauss(0.0, g) if g else 0.0 for _ in range(2)]
        s = weather.gps_noise_m / math.sqrt(2.0)  # per axis
        self.gps = [[self.rng.gauss(0.0, s) if s else 0.0 for _ in range(2)] for _ in range(vehicles)]
        # the autopilots have been hovering in the steady wind: their integrators know it
        d = weather.drag_per_s
        self.learnt = [[d * self.steady[0], d * self.steady[1]] for _ in range(vehicles)]

    @property
    def wind(self) -> tuple[float, float]:
        """The wind now (north, east m/s)."""
        return self.steady[0] + self.gust[0], self.steady[1] + self.gust[1]

    def step(self, dt: float) -> None:
        """Advance the gusts and the GPS errors by ``dt``."""
        w, rng = self.w, self.rng
        self.gust = [_markov(x, w.gust_mps, w.gust_tau_s, dt, rng) for x in self.gust]
        s = w.gps_noise_m / math.sqrt(2.0)
        self.gps = [[_markov(x, s, w.gps_tau_s, dt, rng) for x in e] for e in self.gps]

    def push(self, i: int, vel: list[float], dt: float) -> tuple[float, float]:
        """The velocity change (north, east) over ``dt`` that vehicle ``i``'s autopilot has
        not cancelled yet, for its ground velocity ``vel`` (NED); updates what it learnt."""
        wn, we = self.wind
        d = self.w.drag_per_s
        an, ae = d * (wn - vel[0]), d * (we - vel[1])
        lr = self.learnt[i]
        out = ((an - lr[0]) * dt, (ae - lr[1]) * dt)
        k = min(1.0, dt / self.w.integrator_tau_s)
        lr[0] += (an - lr[0]) * k
        lr[1] += (ae - lr[1]) * k
        return out

    def gps_error(self, i: int) -> tuple[float, float]:
        """Vehicle ``i``'s position estimate minus its true position (north, east m)."""
        e = self.gps[i]
        return e[0], e[1]


__all__ = ["Environment", "Weather"]
