"""The fault campaign as a benchmark: ``swarm bench campaign [--quick] --json``.

Runs the campaign of :mod:`swarm.sim.campaign` (seed 0) over all cores and prints
how many scenarios ran, the violations, the failing scenarios (shrunk, with their
replay commands), wall and CPU seconds (this process's and its reaped workers'),
scenarios per CPU second and the scenarios and failures by fault kind. The full
campaign is FULL scenarios (issue 15's target: 0 violations within 1,800 s of wall
time on a 2-core machine); ``--quick`` (CI) runs QUICK with at most QUICK_AGENTS
agents (the same draws otherwise: about a minute of CPU).
"""

from __future__ import annotations

import os
import resource
import time
from typing import Any

from swarm.sim.campaign import run_campaign

FULL = 10_000
QUICK = 300
QUICK_AGENTS = 12


def _cpu_s() -> float:
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def run(quick: bool = False, scenarios: int | None = None, seed: int = 0) -> dict[str, Any]:
    k = scenarios if scenarios is not None else QUICK if quick else FULL
    cpu0, wall0 = _cpu_s(), time.monotonic()
    res = run_campaign(k, seed, jobs=os.cpu_count() or 1, max_agents=QUICK_AGENTS if quick else 50)
    cpu, wall = _cpu_s() - cpu0, time.monotonic() - wall0
    return {
        "scenarios": res["scenarios"],
        "violations": res["violations"],
        "failing": res["failing"],
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "scenarios_per_cpu_s": round(k / cpu, 2) if cpu > 0 else None,
        "virtual_s": res["virtual_s"],
        "agents_max": res["agents_max"],
        # the full campaign's wall time at this rate (the quick one's agents are capped)
        "full_estimate_wall_s": None if quick or not k else round(wall * FULL / k),
        "seed": seed,
        "by_kind": res["by_kind"],
    }
