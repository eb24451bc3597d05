"""The ``tdm`` election with a size cap (issue 16's sub-swarms): tdm's rules and the cap's
together in the pure core (time is a number the test passes), capped tdm runs over the
SiK air model and strict fault scenarios with a cap (virtual time). No processes, no sleeps."""

from __future__ import annotations

import random

from swarm.core.election import caps
from swarm.core.election.outbox import Out
from swarm.core.election.profiles import tdm_profile
from swarm.core.election.protocol import Core
from swarm.core.wire.message_types import (
    Phase,
    PoolStatus,
    Selection,
    StartPool,
    StartPoolAck,
    SyncPool,
    pool_digest,
)
from swarm.sim.campaign import draw
from swarm.sim.faultsim import FaultSim, make_sim
from swarm.sim.simulate import Scenario, Sim

ROUND = 1.0
TDM = tdm_profile(ROUND)


class FixedVote:
    def __init__(self, w: int) -> None:
        self.w = w

    def weight(self, rng: random.Random) -> int:
        return self.w


def joined(me: int, pool: set[int], weight: int, cap: int) -> Core:
    """A capped tdm core listed in the SyncPool of ``min(pool)`` at 0 (the answer to its
    StartPool), having sent its first SyncPool and vote."""
    c = Core(me, profile=TDM, policy=FixedVote(weight), cap=cap)
    c.start(0.0)
    first = min(pool - {me})
    c.handle(SyncPool(first, pool_digest(pool), False, frozenset(pool)), 0.0)
    c.tick(0.0)
    assert c.phase == Phase.POOLING and c.pool == pool
    return c


def _msgs(out: list[Out], kind: type) -> list[tuple[int, object]]:
    return sorted(((o.to, o.msg) for o in out if isinstance(o.msg, kind)), key=lambda x: x[0])


# -- admission: tdm's answers, the cap's limits -------------------------------------------


def test_a_capped_tdm_core_admits_by_syncpool_until_full_then_refuses() -> None:
    c = Core(1, profile=TDM, cap=3)
    assert c.tdm, "the cap no longer switches tdm's rules off"
    c.start(0.0)
    assert c.handle(StartPool(2), 0.1) == [] and c.pool == {1, 2} and c.capped.founder
    c.handle(StartPool(3), 0.2)
    assert c.pool == {1, 2, 3}
    out = c.handle(StartPool(4), 0.3)
    full = StartPoolAck(1, PoolStatus.FULL, False, frozenset({1, 2, 3}))
    assert [(o.to, o.msg) for o in out] == [(4, full)]
    assert c.pool == {1, 2, 3}


def test_a_capped_tdm_pool_member_that_did_not_found_it_refuses() -> None:
    c = joined(5, {1, 5}, 10, cap=4)
    assert not c.capped.founder
    out = c.handle(StartPool(6), 0.2)
    assert out[0].msg.status == PoolStatus.FULL and c.pool == {1, 5}, "one admitter per pool"


def test_a_named_tdm_agent_takes_no_stranger_into_its_pool() -> None:
    c = Core(1, profile=TDM, swarm_name="red")
    c.start(0.0)
    c.handle(StartPool(2), 0.1)  # agent 2 never advertised "red"
    assert c.phase == Phase.IDLE and c.counters.ignored_foreign == 1


def test_a_capped_leader_adopts_from_a_members_syncpool_only_while_there_is_room() -> None:
    lead = Core(1, profile=TDM, cap=4)
    lead.start(0.0)
    lead.become_leader(0.0, {2, 3})
    big = frozenset({1, 2, 3, 4, 5})
    lead.handle(SyncPool(2, pool_digest(big), False, big), 0.5)
    assert set(lead.members) == {2, 3, 4}, "the lowest id while the cap leaves room"
    assert lead.counters.refused == 1


# -- a full pool that heard every vote decides at once --------------------------------------


def test_a_full_pool_that_heard_every_vote_decides_before_its_lock_window() -> None:
    c = joined(2, {1, 2, 3}, 50, cap=3)
    c.handle(Selection(1, 1, 10, 0), 0.2)
    assert c.phase == Phase.POOLING, "agent 3's vote not heard yet"
    out = c.handle(Selection(3, 3, 99, 0), 0.3)
    assert TDM.lock_window > 0.3
    assert c.phase == Phase.MEMBER and c.leader == 3
    # the vote goes once more (a member that missed it would wait for it) and, capped,
    # the member asks its candidate to list it (swarm.core.election.caps: "A member by its vote")
    sel = Selection(2, 3, 99, pool_digest({1, 2, 3}) & 0xFFFF)
    assert _msgs(out, Selection) == [(1, sel), (3, sel)]
    assert (3, StartPool(2)) in _msgs(out, StartPool)


def test_hostile_votes_cannot_settle_a_full_pool() -> None:
    c = joined(2, {1, 2, 3}, 50, cap=3)
    c.handle(Selection(1, 1, 10, 0), 0.2)
    c.handle(Selection(9, 9, 2**32 - 1, 0), 0.3)  # a stranger
    c.handle(Selection(3, 77, 2**32 - 1, 0), 0.3)  # a member naming a stranger
    c.handle(Selection(2, 2, 2**32 - 1, 0), 0.3)  # our own id from elsewhere
    assert c.phase == Phase.POOLING and c.heard == {1} and c.vote == (50, 2)


def test_a_pool_below_its_cap_waits_for_the_lock_window_though_every_vote_is_heard() -> None:
    c = joined(2, {1, 2, 3}, 50, cap=5)
    c.handle(Selection(1, 1, 10, 0), 0.2)
    c.handle(Selection(3, 3, 99, 0), 0.3)
    assert c.phase == Phase.POOLING, "another agent may still join"
    assert c.next_deadline() is not None
    c.tick(TDM.lock_window)
    assert c.phase == Phase.MEMBER and c.leader == 3


def test_an_uncapped_member_deciding_on_every_vote_sends_its_vote_once_more() -> None:
    c = Core(1, profile=TDM, policy=FixedVote(5))
    c.start(0.0)
    pool = frozenset({1, 2, 3})
    c.handle(SyncPool(2, pool_digest(pool), False, pool), 0.0)
    c.tick(0.0)
    c.tick(TDM.lock_window)
    assert c.phase == Phase.ELECTING
    c.handle(Selection(2, 2, 30, 0), 1.3)
    out = c.handle(Selection(3, 3, 40, 0), 1.4)
    assert c.phase == Phase.MEMBER and c.leader == 3
    assert [to for to, _ in _msgs(out, Selection)] == [2, 3]
    assert not _msgs(out, StartPool), "without a cap a member asks nobody"


def test_a_tdm_members_confirm_deadline_counts_its_candidates_vote_window() -> None:
    c = joined(2, {1, 2, 3}, 50, cap=3)
    c.handle(Selection(1, 1, 10, 0), 0.2)
    c.handle(Selection(3, 3, 99, 0), 0.3)
    assert c.capped.unconfirmed
    deadline = c.last_hb + caps.CONFIRM_INTERVALS * TDM.heartbeat_interval + TDM.vote_window
    assert caps.unconfirmed_deadline(c) == deadline
    c.tick(deadline - TDM.vote_window / 2)  # the candidate may still be electing
    assert c.phase == Phase.MEMBER
    c.tick(deadline)
    assert c.phase == Phase.IDLE, "no Heartbeat listed it: it leaves"


# -- over the air model (virtual time) ----------------------------------------------------------


def test_50_capped_tdm_agents_are_all_led_within_30_virtual_seconds() -> None:
    sim = Sim(Scenario(agents=50, loss=0.1, profile="tdm", cap=10), 1)
    res = sim.run()
    assert res.violations == [] and res.elect_s is not None and res.elect_s <= 30.0
    leaders = [c for c in sim.cores if c.phase == Phase.LEADER]
    listed = [m for c in leaders for m in c.members]
    assert len(listed) == len(set(listed)) == 50 - len(leaders), "every agent in exactly one swarm"
    assert all(len(c.members) + 1 <= 10 for c in leaders)


def test_the_strict_check_flags_a_pool_over_the_cap() -> None:
    sim = FaultSim(Scenario(agents=4, cap=2, strict=True), 0)
    sim.started = [True] * 4
    sim.cores[0].pool = {1, 2, 3}
    sim._continuous(1.0)  # noqa: SLF001 (white box: the strict checks now)
    assert any("more than the cap of 2" in v for v in sim.violations)


def test_strict_fault_scenarios_with_a_cap_keep_the_invariants_under_tdm() -> None:
    failing = []
    for k in range(8):
        sc, seed, _ = draw(5, k, 10, "tdm")
        sc.cap = 3 if sc.agents > 2 else 0
        res = make_sim(sc, seed).run()
        if res.violations:
            failing.append((sc.command(seed), res.violations))
    assert failing == []
