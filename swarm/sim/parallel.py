"""Seeded runs spread over processes: ``swarm simulate --jobs N``.

Theory of operation
-------------------
A run (:class:`swarm.sim.simulate.Sim`) depends on nothing but its scenario and its
seed, so seeds can run anywhere in any order: :func:`run_seeds` hands them in
chunks to a pool of worker processes and puts the results back in seed order, so a
campaign's figures and its JSON are the same whatever the number of jobs. Workers
are started with ``spawn`` (a fresh interpreter: nothing of the parent's state is
shared, and it works the same on every platform); the function they run is a
top-level one. Workers ignore SIGINT from their start (the parent ignores it while
it spawns them, and they inherit that): a Ctrl-C reaches the whole process group,
and only the parent decides. When the parent is interrupted (KeyboardInterrupt,
which the CLI also raises for SIGTERM) it terminates the pool and waits for every
worker before passing the interruption on, so no worker outlives it.
"""

from __future__ import annotations

import multiprocessing
import signal

from swarm.sim.faultsim import make_sim
from swarm.sim.simulate import RunResult, Scenario


def _worker_start() -> None:
    """A worker ignores SIGINT (it started so: see :func:`run_seeds`) and takes SIGTERM
    (:meth:`Pool.terminate`) as it comes, also one that came while it started."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})


def _run_one(job: tuple[Scenario, int]) -> RunResult:
    sc, seed = job
    return make_sim(sc, seed).run()


def run_seeds(sc: Scenario, seeds: int, seed0: int, jobs: int) -> list[RunResult]:
    """The results of seeds ``seed0 .. seed0 + seeds - 1``, in that order, computed by
    ``jobs`` worker processes (in this process when ``jobs`` is 1 or there is one seed)."""
    return run_jobs([(sc, seed0 + k) for k in range(seeds)], jobs)


def run_jobs(work: list[tuple[Scenario, int]], jobs: int) -> list[RunResult]:
    """The results of runs (scenario, seed), in that order, computed by ``jobs``
    worker processes (in this process when ``jobs`` is 1 or there is one run)."""
    if jobs <= 1 or len(work) <= 1:
        return [_run_one(job) for job in work]
    jobs = min(jobs, len(work))
    chunk = max(1, len(work) // (jobs * 8))
    ctx = multiprocessing.get_context("spawn")
    # Workers are spawned with SIGINT ignored: an ignored signal stays ignored across
    # exec and Python then leaves it so, so no worker prints a Ctrl-C traceback while it
    # is still importing. (A Ctrl-C in those few milliseconds is lost for the parent
    # too; a SIGTERM waits, blocked, and stops the run once the pool has started.)
    old_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})

    def restore() -> None:
        signal.signal(signal.SIGINT, old_int)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)

    try:
        pool = ctx.Pool(jobs, initializer=_worker_start)
    except BaseException:
        restore()
        raise
    try:
        restore()  # a SIGTERM that waited is raised here: the pool is ended below
        results = pool.map(_run_one, work, chunksize=chunk)
    except BaseException:
        pool.terminate()
        pool.join()
        raise
    pool.close()
    pool.join()
    return results


__all__ = ["run_jobs", "run_seeds"]
