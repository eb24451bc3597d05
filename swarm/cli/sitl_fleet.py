"""Real autopilots for the bench: N ArduCopter / PX4 SITL processes in a row.

:class:`SitlFleet` starts one real autopilot per kind given (:mod:`firmware_bridge.sitl`:
each its own instance, hence its own ports and system id, and its own working folder),
vehicle K ``spacing`` metres east of vehicle K-1 from ``home``, and gives their
flight-controller URLs in order. PX4's system id is its instance + 1; an ArduCopter
gets 100 + K, so a mixed fleet never shares one. :meth:`SitlFleet.cpu` is what each used of one core,
on average since it started (from ``/proc/PID/stat``: the autopilot is the process
started). :meth:`SitlFleet.stop` stops them all (SIGTERM, then SIGKILL), safe twice.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pymap3d

from firmware_bridge import sitl
from swarm.errors import SwarmError

_TICK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float | None:
    """User + system seconds of process ``pid`` (its threads included), None when gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / _TICK  # utime, stime (fields 14, 15)


class SitlFleet:
    """Real autopilots of ``kinds`` (``ardupilot`` / ``px4``), one per agent."""

    def __init__(
        self, kinds: list[str], workdir: str, home: tuple[float, float, float], spacing: float
    ) -> None:
        self.kinds, self.workdir, self.home, self.spacing = kinds, Path(workdir), home, spacing
        self.running: list[sitl.Sitl] = []
        self._t0: list[tuple[float, float]] = []  # (wall, cpu s) at start, per autopilot

    def start(self) -> list[str]:
        """Start them all; their URLs in order.

        Raises:
            SwarmError: one could not start (all started are stopped again).
        """
        lat0, lon0, alt0 = self.home
        try:
            for k, kind in enumerate(self.kinds):
                lat, lon, _ = pymap3d.ned2geodetic(0.0, self.spacing * k, 0.0, lat0, lon0, alt0)
                home = (
                    (float(lat), float(lon), alt0, 0.0)
                    if kind == "ardupilot"
                    else (float(lat), float(lon), alt0)
                )
                sysid = 100 + k + 1 if kind == "ardupilot" else None
                s = sitl.start(kind, self.workdir / f"{k + 1}-{kind}", home=home, sysid=sysid)  # type: ignore[arg-type]
                self.running.append(s)
                self._t0.append((time.monotonic(), _cpu_s(s.proc.pid) or 0.0))
        except sitl.SitlError as exc:
            self.stop()
            raise SwarmError(f"real autopilot {len(self.running) + 1}: {exc}") from None
        return [s.url for s in self.running]

    def describe(self) -> str:
        """``3 ArduCopter + 2 PX4 (SITL instances 1, 2...)``."""
        names = {"ardupilot": "ArduCopter", "px4": "PX4"}
        counts = [f"{self.kinds.count(k)} {names[k]}" for k in ("ardupilot", "px4") if k in self.kinds]
        return " + ".join(counts) + " SITL (system ids " + ", ".join(str(s.sysid) for s in self.running) + ")"

    def cpu(self) -> dict[str, float | None]:
        """Percent of one core each autopilot used since it started, averaged per kind."""
        per: dict[str, list[float]] = {}
        for s, (t0, c0) in zip(self.running, self._t0, strict=True):
            c1 = _cpu_s(s.proc.pid)
            if c1 is not None and time.monotonic() > t0:
                per.setdefault(s.kind, []).append(100.0 * (c1 - c0) / (time.monotonic() - t0))
        return {k: round(sum(v) / len(v), 1) if v else None for k, v in per.items()}

    def stop(self) -> None:
        for s in reversed(self.running):
            try:
                s.stop()
            except OSError:
                pass
        self.running = []
