"""Seeded runs spread over processes: ``swarm simulate --jobs N``.

Theory of operation
-------------------
A run (:class:`swarm.sim.simulate.Sim`) depends on nothing but its scenario and its
seed, so seeds can run anywhere in any order: :func:`run_seeds` starts ``jobs``
worker processes, each with a pipe of its own, hands each one seed at a time (the
next one as soon as it answers, so a slow seed holds up nobody) and puts the results
back in seed order, so a campaign's figures and its JSON are the same whatever the
number of jobs. Workers are started with ``spawn`` (a fresh interpreter: nothing of
the parent's state is shared, and it works the same on every platform); the function
they run is a top-level one. No queue or lock is shared between processes (a pool's
shared queue can deadlock its own terminate when a worker dies holding the queue's
lock), so stopping is always possible: the parent terminates its workers and waits
for each of them.

Workers ignore SIGINT from their start (the parent blocks it while it spawns them,
they inherit that, and ignore it before they unblock it): a Ctrl-C reaches the whole
process group, and only the parent decides. When the parent is interrupted (KeyboardInterrupt, which the CLI
also raises for SIGTERM) it terminates every worker (SIGTERM, then SIGKILL) and
waits for them before passing the interruption on, so no worker outlives it. A
worker that dies on its own ends the run with :class:`WorkerDied`.
"""

from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from typing import Any

from swarm.errors import SwarmError
from swarm.sim.faultsim import make_sim
from swarm.sim.relay import RelaySim
from swarm.sim.simulate import RunResult, Scenario, Sim, pct, pct2

STOP_GRACE_S = 5.0  # after SIGTERM, before SIGKILL


class WorkerDied(SwarmError):
    """A worker process ended without answering (killed, out of memory)."""


def run_one(job: tuple[Scenario, int]) -> RunResult:
    sc, seed = job
    if sc.command_at is not None:  # a station on the channel (swarm.sim.relay)
        return RelaySim(sc, seed).run()
    return make_sim(sc, seed).run()


def _serve(conn: Connection) -> None:
    """A worker: runs each ``(index, scenario, seed)`` it receives, answers ``(index, result)``,
    ends on ``None`` or when the parent's end closes. It ignores SIGINT (it started
    blocked, and a Ctrl-C that came while it started is dropped here) and takes SIGTERM
    as it comes, also one that came while it started."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        while True:
            job = conn.recv()
            if job is None:
                return
            index, sc, seed = job
            conn.send((index, run_one((sc, seed))))
    except (EOFError, OSError):  # the parent went away
        return


def run_seeds(
    sc: Scenario, seeds: int, seed0: int, jobs: int, on_done: Callable[[], None] = lambda: None
) -> list[RunResult]:
    """The results of seeds ``seed0 .. seed0 + seeds - 1``, in that order, computed by
    ``jobs`` worker processes (in this process when ``jobs`` is 1 or there is one seed);
    ``on_done`` is called as each seed's result arrives (a progress display).

    Raises:
        WorkerDied: a worker ended without answering.
    """
    return run_jobs([(sc, seed0 + k) for k in range(seeds)], jobs, on_done)


def run_jobs(
    work: list[tuple[Scenario, int]], jobs: int, on_done: Callable[[], None] = lambda: None
) -> list[RunResult]:
    """The results of runs ``(scenario, seed)``, in that order, computed by ``jobs``
    worker processes (in this process when ``jobs`` is 1 or there is one run).

    Raises:
        WorkerDied: a worker ended without answering.
    """
    if jobs <= 1 or len(work) <= 1:
        return [_done(run_one(job), on_done) for job in work]
    procs: list[BaseProcess] = []
    try:
        conns = _start(min(jobs, len(work)), procs)
        results = _hand_out(work, conns, on_done)
        for c in conns:
            c.send(None)
    finally:
        _stop(procs)
    return [results[k] for k in range(len(work))]


def _start(jobs: int, procs: list[BaseProcess]) -> list[Connection]:
    """Spawn the workers (appended to ``procs`` as they start); their pipes.

    Workers are spawned with SIGINT and SIGTERM blocked: a blocked signal stays blocked
    across exec, so no worker prints a Ctrl-C traceback while it is still importing
    (each drops a Ctrl-C and takes a SIGTERM once it serves). The parent's signals
    wait too, and stop the run as soon as the workers have started: spawning takes
    seconds on a busy machine, and a Ctrl-C then must not be lost (it once was: the
    parent ignored SIGINT while it spawned, and the run went on to its end)."""
    ctx = multiprocessing.get_context("spawn")
    conns: list[Connection] = []
    # the mask as it was, read before anything changes it: a Ctrl-C raised right after
    # the block below, before the ``try``, must not leave the signals blocked for good
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    try:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        for _ in range(jobs):
            ours, theirs = ctx.Pipe()
            p = ctx.Process(target=_serve, args=(theirs,), daemon=True)
            p.start()
            procs.append(p)
            theirs.close()
            conns.append(ours)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)  # a Ctrl-C or SIGTERM that waited acts here
    return conns


def _done(result: RunResult, on_done: Callable[[], None]) -> RunResult:
    on_done()
    return result


def _hand_out(
    work: list[tuple[Scenario, int]], conns: list[Connection], on_done: Callable[[], None]
) -> dict[int, RunResult]:
    """One run at a time to each worker, the next as soon as it answers; results by
    the run's index in ``work``."""
    todo: Iterator[tuple[int, Scenario, int]] = ((k, sc, seed) for k, (sc, seed) in enumerate(work))
    results: dict[int, RunResult] = {}
    busy: list[Connection] = []
    for c in conns:
        job = next(todo, None)
        if job is not None:
            c.send(job)
            busy.append(c)
    while busy:
        for ready in wait(busy):
            c = busy[busy.index(ready)]  # type: ignore[arg-type]  # one of ours
            try:
                index, result = c.recv()
            except (EOFError, OSError):
                raise WorkerDied("a simulation worker died without answering") from None
            results[index] = _done(result, on_done)
            nxt = next(todo, None)
            if nxt is None:
                busy.remove(c)
            else:
                c.send(nxt)
    return results


def _stop(procs: list[BaseProcess]) -> None:
    """Every worker ended and waited for: SIGTERM, then SIGKILL after STOP_GRACE_S."""
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(STOP_GRACE_S)
        if p.is_alive():
            p.kill()
            p.join()


def sweep(
    sc: Scenario, seeds: int, seed0: int = 0, jobs: int = 1, on_done: Callable[[], None] = lambda: None
) -> dict[str, Any]:
    """Seeds ``seed0 ..`` run (over ``jobs`` processes) and summarised; the summary is
    the same for any number of jobs. ``on_done`` is called once per finished seed."""
    results = run_seeds(sc, seeds, seed0, jobs, on_done)
    elect = [r.elect_s for r in results if r.elect_s is not None]
    fail = [r.failover_s for r in results if r.failover_s is not None]
    bad = [r for r in results if r.violations]
    round_s = Sim(sc, seed0).round_s
    out: dict[str, Any] = {
        "agents": sc.agents,
        "profile": sc.profile,
        "loss": sc.loss,
        "runs": len(results),
        "converged": sum(r.elect_s is not None or r.failover_s is not None for r in results),
        "stable_at_end": sum(r.stable_at_end for r in results),
        "violations": sum(len(r.violations) for r in results),
        "elect_s": {"p50": pct(elect, 0.5), "p95": pct(elect, 0.95), "max": pct(elect, 1.0)},
        "air_utilisation": {
            "p50": pct([r.air_utilisation for r in results], 0.5),
            "max": pct([r.air_utilisation for r in results], 1.0),
        },
        "messages_per_agent": {"p50": pct([r.messages_per_agent for r in results], 0.5)},
        "round_s": round(round_s, 4),
        "election_rounds": {k: None if v is None else round(v / round_s, 2) for k, v in pct2(elect).items()},
    }
    if sc.crashes:
        out["failover_s"] = {"p50": pct(fail, 0.5), "p95": pct(fail, 0.95)}
    out["failing"] = [
        {"seed": r.seed, "violations": r.violations or ["did not converge"], "replay": sc.command(r.seed)}
        for r in bad[:10]
    ]
    return out


__all__ = ["WorkerDied", "run_jobs", "run_seeds", "sweep"]
