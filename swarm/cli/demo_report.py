"""What ``swarm demo`` tells a person and a program at the end: the targets it judged the
run on, and its summary as text.

Theory of operation
-------------------
:func:`targets` checks the formation figures of a demo's summary (computed by
:func:`swarm.sim.tracks.analyse` from the capture) against the run's limits and returns
one entry per target missed: which figure, what was measured, the limit, and a sentence
naming the figure's legs and interval (:data:`swarm.sim.tracks.INTERVAL`). A step that did
not happen (no leader agreed, a process that exited) is put in the same list by
:func:`swarm.cli.demo.run_demo`. :func:`summary_lines` renders the summary for people:
the figures with their definitions, every target missed, where the capture, plot and
working folder are (or that they were removed with the folder), and where the ground
station was (it stops with the demo). Pure: no I/O.
"""

from __future__ import annotations

from typing import Any

from swarm.sim.tracks import INTERVAL, LEGS, fmt


def targets(summary: dict[str, Any], max_rms_m: float, max_turn_m: float) -> list[dict[str, Any]]:
    """The targets the figures in ``summary`` missed (each: ``target``, ``measured``, ``limit``,
    ``text``, naming the figure's legs and interval); empty when every one was met."""
    missed: list[dict[str, Any]] = []

    def check(key: str, name: str, limit: float, where: str) -> None:
        v = summary.get(key)
        if v is None:
            text = f"{name}: nothing measured ({where})"
        elif v > limit:
            text = f"{name} {v:g} m > {limit:g} m ({where})"
        else:
            return
        missed.append({"target": key, "measured": v, "limit": limit, "text": text})

    if summary.get("formation_rms_m") is not None or summary.get("route_rms_m") is None:
        check("formation_rms_m", "formation RMS", max_rms_m, f"straight legs, {INTERVAL}")
    else:  # a route too short for straight legs: judged whole
        check("route_rms_m", "route RMS", max_rms_m, f"whole route, turns included, {INTERVAL}")
    if summary.get("turn_max_m") is not None:
        check("turn_max_m", "largest error in the turn", max_turn_m, f"turns, {INTERVAL}")
    return missed


def summary_lines(s: dict[str, Any]) -> list[str]:
    """The summary for people, one line each."""
    lines = ["== summary", f"   leader: agent{s.get('leader')}, elected in {fmt(s.get('elect_s'), ' s')}"]
    if "route_rms_m" in s:  # measured (not a run that stopped before the route)
        dur = fmt((s.get("interval") or {}).get("duration_s"), " s")
        lines.append(f"   slot error {INTERVAL}: {dur}")
        lines += [f"     {key}: {fmt(s[key])} ({LEGS[key]})" for key in LEGS]
    if s.get("heading_error_after_turn_deg") is not None:
        lines.append(f"   heading_error_after_turn_deg: {s['heading_error_after_turn_deg']}")
    if s.get("autopilot_cpu_pct"):  # real autopilots: what each kind used of one core
        cpu = ", ".join(f"{k} {fmt(v, ' %')}" for k, v in sorted(s["autopilot_cpu_pct"].items()))
        lines.append(f"   autopilots: {' '.join(s.get('autopilots', []))}; CPU each (of one core): {cpu}")
        if s.get("boot_s") is not None:
            lines.append(
                f"   take-off accepted by every autopilot {fmt(s['boot_s'], ' s')} after the agents started"
            )
    util = s.get("air_utilisation")
    lines.append(f"   air_utilisation: {'n/a' if util is None else f'{util:.0%}'} (during the route)")
    gone = "removed with the working folder (--keep keeps it)"
    kept = s.get("workdir_kept")
    lines.append(f"   capture: {s.get('capture') or gone}")
    lines.append(f"   plot: {s.get('plot') or ('none' if kept else gone)}")
    lines.append(f"   working folder: {s.get('workdir')}" + ("" if kept else " (removed)"))
    if s.get("gcs"):
        up = "still running" if s.get("gcs_running") else "stopped with the demo"
        lines.append(f"   ground station: was at {s['gcs']} ({up})")
    lines.append(f"   wall_s: {fmt(s.get('wall_s'), ' s')}")
    for m in s.get("missed", []):
        lines.append(f"   MISSED: {m['text']}")
    lines.append(f"   ok: {str(bool(s.get('ok'))).lower()}")
    return lines


__all__ = ["summary_lines", "targets"]
