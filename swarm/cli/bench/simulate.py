"""Figures of the deterministic simulator for the election targets (virtual time; the
tdm profile's election in TDM rounds, issue 16's target), and
its own speed: CPU seconds per 1,000 N=10 runs and per N=50 run (issue 15's targets).
The sub-swarm targets (a size cap, several channels) are ``swarm bench scale``'s
(:mod:`swarm.cli.bench.scale`).

Speed is measured on serial runs in this process (``time.process_time``); the N=50
campaign runs over all cores (``--jobs``: identical figures) and its CPU is this
process's plus its reaped workers'.

``core_floor`` is the part of the N=10 CPU that is the protocol itself: the share of a
run's time spent inside the agents' cores (``Core.start``, ``handle``, ``tick``,
``next_deadline``) and the message codec (``encode``, ``decode``), timed in a separate
pass of the same runs (:func:`core_share`; the timing adds a little to both sides).
The simulator runs the agents' own cores, so however fast the rest became, a run
cannot cost less than that: ``cpu_s_per_1000_runs_floor`` is the share times the
measured CPU.
"""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Callable
from typing import Any

import swarm.sim.simulate as simulate
from swarm.sim.faultsim import make_sim
from swarm.sim.parallel import sweep
from swarm.sim.scenario import RunResult
from swarm.sim.simulate import Scenario

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
    res = sweep(sc, runs, 0, jobs=jobs)
    return res, cpu_s() - t0


class _Timer:
    """Time spent inside the wrapped callables (an outermost call counts once: a tick
    that ticks again, or start calling tick, is not counted twice)."""

    def __init__(self) -> None:
        self.s = 0.0
        self._depth = 0

    def wrap(self, f: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._depth:
                return f(*args, **kwargs)
            self._depth = 1
            t0 = time.perf_counter()
            try:
                return f(*args, **kwargs)
            finally:
                self.s += time.perf_counter() - t0
                self._depth = 0

        return timed


def core_share(sc: Scenario, runs: int) -> tuple[float, list[RunResult]]:
    """``(share, results)``: the share of ``runs`` seeded runs' time spent in the
    protocol cores and the codec (see the module docstring), and the runs' results
    (the same as without the timing: it wraps, it changes nothing)."""
    timer = _Timer()
    saved = simulate.encode, simulate.decode
    simulate.encode, simulate.decode = timer.wrap(simulate.encode), timer.wrap(simulate.decode)
    results = []
    t0 = time.perf_counter()
    try:
        for seed in range(runs):
            sim = make_sim(sc, seed)
            for c in sim.cores:  # instance attributes shadow the class's methods
                for name in ("start", "handle", "tick", "next_deadline"):
                    setattr(c, name, timer.wrap(getattr(c, name)))
            results.append(sim.run())
    finally:
        simulate.encode, simulate.decode = saved
    return timer.s / (time.perf_counter() - t0), results


def _floor(sc: Scenario, runs: int, cpu_per_1000: float) -> dict[str, Any]:
    share, _ = core_share(sc, runs)
    return {"core_share": round(share, 3), "cpu_s_per_1000_runs_floor": round(share * cpu_per_1000, 1)}


def run(quick: bool = False) -> dict[str, Any]:
    k = 20 if quick else 500
    jobs = os.cpu_count() or 1
    out: dict[str, Any] = {}
    n10 = {
        "paper_n10_loss10": Scenario(agents=10, loss=0.1),
        "fast_n10_loss10": Scenario(agents=10, loss=0.1, profile="fast"),
    }
    per_1000: dict[str, Any] = {}
    for name, sc in n10.items():
        out[name], cpu = _timed(sc, k)
        per_1000[name] = round(1000 * cpu / k, 1)
    out["cpu_s_per_1000_runs"] = {**per_1000, "target": TARGET_CPU_S_PER_1000_RUNS}
    n_floor = 10 if quick else 100
    out["core_floor"] = {name: _floor(sc, n_floor, per_1000[name]) for name, sc in n10.items()}
    # the tdm profile (issue 16): election p95 within TARGET_TDM_P95_ROUNDS TDM rounds
    out["tdm_n10_loss10"] = sweep(Scenario(agents=10, loss=0.1, profile="tdm"), k, jobs=jobs)
    out["tdm_n10_loss10"]["target_p95_rounds"] = TARGET_TDM_P95_ROUNDS
    out["paper_n20_64kbps"] = sweep(Scenario(agents=20, loss=0.1), 5 if quick else 30, jobs=jobs)
    out["fast_n20_64kbps"] = sweep(
        Scenario(agents=20, loss=0.1, profile="fast"), 5 if quick else 30, jobs=jobs
    )
    out["paper_n5_leader_crash"] = sweep(
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
