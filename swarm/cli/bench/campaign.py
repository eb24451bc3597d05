"""The fault campaign as a benchmark: ``swarm bench campaign [--quick] --json``.

Runs the campaign of :mod:`swarm.sim.campaign` (seed 0) over all cores and prints
how many scenarios ran, the violations, the failing scenarios (shrunk, with their
replay commands), wall and CPU seconds (this process's and its reaped workers'),
scenarios per CPU second and the scenarios and failures by fault kind. The full
campaign is FULL scenarios (issue 15's target: 0 violations within 1,800 s of wall
time on a 2-core machine); ``--quick`` (CI) runs QUICK with at most QUICK_AGENTS
agents (the same draws otherwise: about a minute of CPU).

Machines differ and a shared one is slower on some days than on others, so the
bench also times a fixed piece of work on this machine (REFERENCE_RUNS N=10 paper
runs at 10 % loss, serial) before the campaign and again after it
(``reference_cpu_s_before_after``; a shared machine's speed drifts over half an hour:
one reference taken first once ran 27 % faster than the day before while the
campaign's own CPU was the same within 1 %), and gives the campaign's CPU in units of
their mean (``reference_cpu_s``, ``cpu_in_reference_units``): a figure that compares
across days and machines where ``wall_s`` does not. Neither reference counts in
``wall_s`` or ``cpu_s``.
"""

from __future__ import annotations

import os
import resource
import time
from typing import Any

from swarm.sim.campaign import run_campaign
from swarm.sim.parallel import sweep
from swarm.sim.simulate import Scenario

FULL = 10_000
QUICK = 300
QUICK_AGENTS = 12
#: the fixed work that measures this machine's speed (N=10 paper runs, serial)
REFERENCE_RUNS = 40


def _cpu_s() -> float:
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def reference_cpu_s() -> float:
    """CPU seconds of the fixed reference work (:data:`REFERENCE_RUNS`) here, now."""
    t0 = time.process_time()
    sweep(Scenario(agents=10, loss=0.1), REFERENCE_RUNS, 0, jobs=1)
    return time.process_time() - t0


def run(quick: bool = False, scenarios: int | None = None, seed: int = 0) -> dict[str, Any]:
    k = scenarios if scenarios is not None else QUICK if quick else FULL
    ref_before = reference_cpu_s()
    cpu0, wall0 = _cpu_s(), time.monotonic()
    res = run_campaign(k, seed, jobs=os.cpu_count() or 1, max_agents=QUICK_AGENTS if quick else 50)
    cpu, wall = _cpu_s() - cpu0, time.monotonic() - wall0
    ref_after = reference_cpu_s()
    ref = (ref_before + ref_after) / 2
    return {
        "scenarios": res["scenarios"],
        "violations": res["violations"],
        "failing": res["failing"],
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "scenarios_per_cpu_s": round(k / cpu, 2) if cpu > 0 else None,
        "reference_cpu_s": round(ref, 2),
        "reference_cpu_s_before_after": [round(ref_before, 2), round(ref_after, 2)],
        "cpu_in_reference_units": round(cpu / ref, 1) if ref > 0 else None,
        "virtual_s": res["virtual_s"],
        "agents_max": res["agents_max"],
        # the full campaign's wall time at this rate (the quick one's agents are capped)
        "full_estimate_wall_s": None if quick or not k else round(wall * FULL / k),
        "seed": seed,
        "by_kind": res["by_kind"],
    }
