"""Shrinking a failing scenario to the smallest that still fails.

Theory of operation
-------------------
:func:`shrink` is greedy, as property-based testing tools shrink: it tries smaller
variants of the scenario (:func:`candidates`: one fault fewer, no uniform or bursty
loss, fewer agents, a shorter run), with the same run seed, and keeps the first that
still violates an invariant of a kind the original violated (:func:`kinds`: a
variant that fails otherwise, say every agent crashed, shows another problem or
none); it starts again from that one until no variant fails or SHRINK_RUNS runs are
spent. Fewer agents drop the faults that name an agent no
longer there and the agent from partition groups. The result is a scenario that
fails (the original if nothing smaller does) and the result of its run; its
:meth:`Scenario.command` replays it.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator

from swarm.sim.faultsim import make_sim
from swarm.sim.scenario import Link, RunResult, Scenario

#: runs one shrink may spend
SHRINK_RUNS = 60
_NUMBER = re.compile(r"\d+(\.\d+)?")
_LISTS = ("crashes", "restarts", "pauses", "partitions", "links", "late", "drift")


def _names(field: str, spec: str) -> list[int]:
    """The agent ids a fault names."""
    if field == "links":
        k = Link.parse(spec)
        return [k.src, k.dst]
    if field == "partitions":
        return []  # groups are cut to the agents left instead
    who = spec.split(":" if field == "drift" else "@", 1)[0]
    return [int(who)] if who.isdigit() else []


def _cut_partition(spec: str, n: int) -> str | None:
    times, groups = spec.split(":", 1)
    kept = [",".join(x for x in g.split(",") if x and int(x) <= n) for g in groups.split("|")]
    kept = [g for g in kept if g]
    return f"{times}:{'|'.join(kept)}" if len(kept) > 1 else None


def fewer_agents(sc: Scenario, n: int) -> Scenario:
    """``sc`` with agents 1..n only."""
    out = dataclasses.replace(sc, agents=n)
    for f in _LISTS:
        kept: list[str] = []
        for spec in getattr(sc, f):
            if f == "partitions":
                cut = _cut_partition(spec, n)
                if cut is not None:
                    kept.append(cut)
            elif all(a <= n for a in _names(f, spec)):
                kept.append(spec)
        setattr(out, f, kept)
    return out


def candidates(sc: Scenario) -> Iterator[Scenario]:
    """Smaller variants of ``sc``, the likeliest to help first."""
    for n in sorted({2, sc.agents // 2, sc.agents - 1}):
        if 2 <= n < sc.agents:
            yield fewer_agents(sc, n)
    for f in _LISTS:
        items = getattr(sc, f)
        for k in range(len(items)):
            yield dataclasses.replace(sc, **{f: items[:k] + items[k + 1 :]})
    if sc.loss:
        yield dataclasses.replace(sc, loss=0.0)
    if sc.burst_loss:
        yield dataclasses.replace(sc, burst_loss=None)
    if sc.duration is not None and sc.duration > 60:
        yield dataclasses.replace(sc, duration=round(sc.duration * 0.7, 1))


def kinds(violations: list[str]) -> set[str]:
    """The kinds of ``violations``: their texts without numbers (times, ids, bounds)."""
    return {_NUMBER.sub("#", v) for v in violations}


def shrink(sc: Scenario, seed: int, runs: int = SHRINK_RUNS) -> tuple[Scenario, RunResult]:
    """The smallest variant of failing ``sc`` found that still fails the same way (a
    violation of a kind the original had), and its result."""
    best = make_sim(sc, seed).run()
    wanted = kinds(best.violations)
    spent = 1
    improved = True
    while improved and spent < runs:
        improved = False
        for cand in candidates(sc):
            if spent >= runs:
                break
            spent += 1
            res = make_sim(cand, seed).run()
            if kinds(res.violations) & wanted:
                sc, best, improved = cand, res, True
                break
    return sc, best


__all__ = ["SHRINK_RUNS", "candidates", "fewer_agents", "kinds", "shrink"]
