"""The fault campaign: K scenarios drawn from a seeded distribution, run strict, shrunk when they fail.

Theory of operation
-------------------
Scenario ``k`` of the campaign seeded ``S`` is drawn by :func:`draw` from its own
generator (``random.Random("campaign:S:k")``), so it depends on nothing but ``S``
and ``k``: the same scenarios run, and the same results come back in the same
order, whatever the number of jobs (:func:`swarm.sim.parallel.run_jobs`).

The distribution: N from 2 to 50, weighted to small swarms (three in four have 2-8
agents, one in thirty more than 20: a swarm of 50 costs about as much CPU as two
hundred of 5); the paper and fast profiles, and one scenario in three the tdm
profile (or one profile for all, ``profile``); one in five of four agents or more
with a swarm size cap of 2 to N-1 (sub-swarms: kind ``cap``, the agreement is every
agent in a led swarm of at most the cap); and, each with its own chance, uniform loss (0-30 %),
bursty loss (bad 2-14 % of the time, over at most 15 % uniform loss), partitions
that heal, crashes of the leader (several leader changes in one run), members
leaving (they stop without a word: the protocol has no goodbye), restarts without
state and pauses with it (:mod:`swarm.sim.faultsim`), late joiners, asymmetric
links (more loss one way, up to 35 % with the uniform loss), one-way links for a
while (an agent that hears the others but is not heard), and clock drift per agent.
The tdm and cap draws come from a stream of their own (``campaign:S:k:swarm``), so
a scenario's other draws are those it had before they were added.
Faults fall in a horizon of 30 s to 30 virtual minutes (mostly short); a run's cost
is bounded: the horizon is cut to COST_BUDGET agent-seconds, and the run lasts the
horizon (or to the end of its last fault, if later) plus a tail long enough for the
swarm to settle (:meth:`Scenario.settle_tail_s`; it stops as soon as it has settled
after the last fault).

Every scenario runs ``strict`` (the continuous invariants of
:class:`swarm.sim.faultsim.FaultSim`). Each failing scenario is shrunk
(:func:`swarm.sim.shrink.shrink`) and reported with the ``swarm simulate`` command
that replays it, before and after shrinking.
"""

from __future__ import annotations

import random
from collections import defaultdict
from collections.abc import Callable
from typing import Any

from swarm.sim.parallel import run_jobs
from swarm.sim.scenario import RunResult, Scenario
from swarm.sim.shrink import shrink

#: a scenario's horizon is cut so that agents x seconds stays under this
COST_BUDGET = 3000.0
#: failing scenarios shrunk per campaign (each costs up to SHRINK_RUNS runs)
SHRINK_MAX = 3
KINDS = (
    "loss",
    "burst",
    "partition",
    "leader_crash",
    "leave",
    "restart",
    "pause",
    "late",
    "asymmetric",
    "one_way",
    "drift",
    "cap",
)
#: the share of scenarios (of four agents or more) whose agents have a swarm size cap
CAP_CHANCE = 0.2


def _agents(rng: random.Random) -> int:
    r = rng.random()
    if r < 0.75:
        return rng.randint(2, 8)
    if r < 0.967:
        return rng.randint(9, 20)
    return rng.randint(21, 50)


def _horizon(rng: random.Random, n: int) -> float:
    r = rng.random()
    h = rng.uniform(30, 150) if r < 0.8 else rng.uniform(150, 600) if r < 0.95 else rng.uniform(600, 1800)
    return round(max(30.0, min(h, COST_BUDGET / n)), 1)


def _t(rng: random.Random, a: float, b: float) -> float:
    return round(rng.uniform(a, b), 1)


def _partition(rng: random.Random, n: int, h: float) -> str:
    ids = list(range(1, n + 1))
    rng.shuffle(ids)
    cut = rng.randint(1, n - 1)
    t0 = _t(rng, 5, h)
    t1 = round(t0 + rng.uniform(5, 60), 1)
    a, b = sorted(ids[:cut]), sorted(ids[cut:])
    return f"{t0}-{t1}:{','.join(map(str, a))}|{','.join(map(str, b))}"


def _pair(rng: random.Random, n: int) -> tuple[int, int]:
    a, b = rng.sample(range(1, n + 1), 2)
    return a, b


def _faults(rng: random.Random, sc: Scenario, h: float) -> list[str]:
    """Adds the faults drawn for ``sc`` within horizon ``h``; returns their kinds."""
    n = sc.agents
    kinds: list[str] = []

    def maybe(kind: str, chance: float) -> int:
        """How many of ``kind`` (0 when not drawn; 1-3 when drawn)."""
        if rng.random() >= chance:
            return 0
        kinds.append(kind)
        return rng.randint(1, 3)

    if maybe("loss", 0.5):
        sc.loss = round(rng.uniform(0.0, 0.3), 2)
    if maybe("burst", 0.2 if sc.loss <= 0.15 else 0.0):  # bursts on top of 15 % at most
        sc.burst_loss = f"{round(rng.uniform(0.01, 0.05), 3)},{round(rng.uniform(0.3, 0.6), 2)}"
    sc.partitions += [_partition(rng, n, h) for _ in range(maybe("partition", 0.3 if n > 2 else 0.1))]
    sc.crashes += [f"leader@{_t(rng, 10, h)}" for _ in range(maybe("leader_crash", 0.3) if n > 3 else 0)]
    sc.crashes += [f"{rng.randint(1, n)}@{_t(rng, 5, h)}" for _ in range(maybe("leave", 0.2) if n > 3 else 0)]
    del sc.crashes[n - 2 :]  # two agents at least stay
    for _ in range(maybe("restart", 0.3)):
        t0 = _t(rng, 5, h)
        sc.restarts.append(f"{rng.randint(1, n)}@{t0}-{round(t0 + rng.uniform(0.5, 30), 1)}")
    for _ in range(maybe("pause", 0.2)):
        t0 = _t(rng, 5, h)
        sc.pauses.append(f"{rng.randint(1, n)}@{t0}-{round(t0 + rng.uniform(0.2, 10), 1)}")
    late = rng.sample(range(1, n + 1), min(n - 1, maybe("late", 0.3)))
    sc.late += [f"{i}@{_t(rng, 1, min(h, 120))}" for i in late]
    for _ in range(maybe("asymmetric", 0.3)):
        a, b = _pair(rng, n)
        sc.links.append(f"{a}>{b}:{round(rng.uniform(0.05, max(0.06, 0.35 - sc.loss)), 2)}")
    for _ in range(maybe("one_way", 0.2)):
        a, b = _pair(rng, n)
        t0 = _t(rng, 5, h)
        sc.links.append(f"{a}>{b}:1.0@{t0}-{round(t0 + rng.uniform(5, 60), 1)}")
    drifted = rng.sample(range(1, n + 1), min(n, maybe("drift", 0.3)))
    sc.drift += [f"{i}:{rng.randint(-1000, 1000)}" for i in drifted]
    return kinds


def _swarm_kind(rng: random.Random, sc: Scenario, profile: str | None) -> list[str]:
    """The draws added with the ``tdm`` profile and sub-swarms, from a stream of their
    own so that every other draw of a scenario is what it was before them: one
    scenario in three runs ``tdm`` (unless ``profile`` is given), and one in
    CAP_CHANCE of four agents or more gets a size cap of 2 to N-1 (kind ``cap``)."""
    if profile is None and rng.random() < 1 / 3:
        sc.profile = "tdm"
    if sc.agents >= 4 and rng.random() < CAP_CHANCE:
        sc.cap = rng.randint(2, sc.agents - 1)
        return ["cap"]
    return []


def draw(
    seed: int, k: int, max_agents: int = 50, profile: str | None = None
) -> tuple[Scenario, int, list[str]]:
    """Scenario ``k`` of the campaign seeded ``seed``: (scenario, run seed, kinds);
    ``max_agents`` caps N and ``profile`` replaces the drawn profile (paper, fast or
    tdm): the draws are the same otherwise."""
    rng = random.Random(f"campaign:{seed}:{k}")
    n = max(2, min(_agents(rng), max_agents))
    drawn = rng.choice(("paper", "fast"))
    sc = Scenario(agents=n, profile=profile or drawn, strict=True)
    h = _horizon(rng, n)
    kinds = _faults(rng, sc, h)
    kinds += _swarm_kind(random.Random(f"campaign:{seed}:{k}:swarm"), sc, profile)
    sc.duration = round(max(h, sc.last_fault_s()) + sc.settle_tail_s(), 1)
    return sc, rng.getrandbits(31), kinds


def run_campaign(
    scenarios: int,
    seed: int,
    jobs: int = 1,
    shrink_max: int = SHRINK_MAX,
    max_agents: int = 50,
    on_done: Callable[[], None] = lambda: None,
    profile: str | None = None,
) -> dict[str, Any]:
    """Runs the campaign; the result is the same for any number of jobs. ``on_done`` is
    called as each scenario's run ends (a progress display); ``profile`` runs every
    scenario with that profile (None: each draws paper, fast or tdm)."""
    drawn = [draw(seed, k, max_agents, profile) for k in range(scenarios)]
    results = run_jobs([(sc, s) for sc, s, _ in drawn], jobs, on_done)
    by_kind: dict[str, dict[str, int]] = defaultdict(lambda: {"scenarios": 0, "failing": 0})
    failing: list[dict[str, Any]] = []
    for k, ((sc, s, kinds), r) in enumerate(zip(drawn, results, strict=True)):
        for kind in kinds or ["none"]:
            by_kind[kind]["scenarios"] += 1
            by_kind[kind]["failing"] += bool(r.violations)
        if r.violations:
            failing.append(_failure(k, sc, s, kinds, r, len(failing) < shrink_max))
    return {
        "scenarios": scenarios,
        "seed": seed,
        "violations": sum(len(r.violations) for r in results),
        "failing": failing,
        "virtual_s": round(sum(r.end_s for r in results), 1),
        "agents_max": max((sc.agents for sc, _, _ in drawn), default=0),
        "by_kind": {k: by_kind[k] for k in sorted(by_kind)},
    }


def _failure(k: int, sc: Scenario, s: int, kinds: list[str], r: RunResult, do_shrink: bool) -> dict[str, Any]:
    out: dict[str, Any] = {
        "index": k,
        "kinds": kinds,
        "violations": r.violations,
        "replay": sc.command(s),
    }
    if do_shrink:
        small, res = shrink(sc, s)
        out["shrunk"] = {"agents": small.agents, "violations": res.violations, "replay": small.command(s)}
    return out


__all__ = ["COST_BUDGET", "KINDS", "draw", "run_campaign"]
