"""Figures of the deterministic simulator for the election targets (virtual time; the
tdm profile's election in TDM rounds, issue 16's target), and
its own speed: CPU seconds per 1,000 N=10 runs and per N=50 run (issue 15's targets).
The sub-swarm targets (a size cap, several channels) are ``swarm bench scale``'s
(:mod:`swarm.cli.bench.scale`).

Speed is measured on serial runs in this process (``time.process_time``); the N=50
campaign runs over all cores (``--jobs``: identical figures) and its CPU is this
process's plus its reaped workers'.
"""

from __future__ import annotations

import os
import resource
import time
from typing import Any

from swarm.sim.simulate import Scenario, campaign

#: issue 15's targets, CPU seconds
TARGET_CPU_S_PER_1000_RUNS = 10.0
TARGET_CPU_S_PER_RUN_N50 = 2.5
#: issue 16's target: N=10, 10 % loss, the best profile's election p95 in TDM rounds
TARGET_TDM_P95_ROUNDS = 3.5


def cpu_s() -> float:
    """CPU of this process and of its finished children (the pool's workers)."""
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def _timed(sc: Scenario, runs: int, jobs: int = 1) -> tuple[dict[str, Any], float]:
    t0 = cpu_s()
    res = campaign(sc, runs, 0, jobs=jobs)
    return res, cpu_s() - t0


def run(quick: bool = False) -> dict[str, Any]:
    k = 20 if quick else 500
    jobs = os.cpu_count() or 1
    out: dict[str, Any] = {}
    out["paper_n10_loss10"], cpu_paper = _timed(Scenario(agents=10, loss=0.1), k)
    out["fast_n10_loss10"], cpu_fast = _timed(Scenario(agents=10, loss=0.1, profile="fast"), k)
    out["cpu_s_per_1000_runs"] = {
        "paper_n10_loss10": round(1000 * cpu_paper / k, 1),
        "fast_n10_loss10": round(1000 * cpu_fast / k, 1),
        "target": TARGET_CPU_S_PER_1000_RUNS,
    }
    # the tdm profile (issue 16): election p95 within TARGET_TDM_P95_ROUNDS TDM rounds
    out["tdm_n10_loss10"] = campaign(Scenario(agents=10, loss=0.1, profile="tdm"), k, jobs=jobs)
    out["tdm_n10_loss10"]["target_p95_rounds"] = TARGET_TDM_P95_ROUNDS
    out["paper_n20_64kbps"] = campaign(Scenario(agents=20, loss=0.1), 5 if quick else 30, jobs=jobs)
    out["fast_n20_64kbps"] = campaign(
        Scenario(agents=20, loss=0.1, profile="fast"), 5 if quick else 30, jobs=jobs
    )
    out["paper_n5_leader_crash"] = campaign(
        Scenario(agents=5, crashes=["leader@15"], duration=80), 10 if quick else 100, jobs=jobs
    )
    n50 = 1 if quick else 20
    out["paper_n50_loss10"], cpu_n50 = _timed(Scenario(agents=50, loss=0.1), n50, jobs=jobs)
    out["cpu_s_per_run_n50"] = round(cpu_n50 / n50, 2)
    out["cpu_s_per_run_n50_target"] = TARGET_CPU_S_PER_RUN_N50
    for v in out.values():
        if isinstance(v, dict) and "failing" in v and not v["failing"]:
            v.pop("failing")
    return out
