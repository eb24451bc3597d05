"""Leader selection in virtual time: the pure core alone (manual clock), and N cores
over the SiK air model (swarm.sim.simulate) in the scenarios the issue names. No test
sleeps: time is a number the test advances."""

from __future__ import annotations

import random

import pytest

from swarm.core.election.outbox import ADVERTIZE
from swarm.core.election.profiles import PAPER, fast_profile, paper_profile
from swarm.core.election.protocol import Core
from swarm.core.wire.message_types import (
    Advertize,
    Heartbeat,
    HeartbeatAck,
    Phase,
    PoolStatus,
    Pose,
    Selection,
    StartPool,
    StartPoolAck,
    SyncPool,
    pool_digest,
)
from swarm.sim.parallel import sweep
from swarm.sim.simulate import Scenario, Sim

POSE = Pose(47.4, 8.5, 500.0)


class FixedVote:
    def __init__(self, w: int) -> None:
        self.w = w

    def weight(self, rng: random.Random) -> int:
        return self.w


# -- the core alone -------------------------------------------------------------


def test_idle_agent_advertises_and_answers_start_pool_with_success() -> None:
    c = Core(1, "a1")
    out = c.start(0.0)
    assert [o.to for o in out] == [ADVERTIZE] and isinstance(out[0].msg, Advertize)
    out = c.handle(StartPool(2), 0.1)
    assert c.phase == Phase.POOLING and c.pool == {1, 2}
    ack = out[0].msg
    assert isinstance(ack, StartPoolAck) and ack.status == PoolStatus.SUCCESS and out[0].to == 2


def test_agent_in_open_pool_answers_already_in_pool_and_adds_sender() -> None:
    c = Core(1)
    c.start(0.0)
    c.handle(StartPool(2), 0.1)
    out = c.handle(StartPool(3), 0.2)
    assert c.pool == {1, 2, 3}
    assert out[0].msg == StartPoolAck(1, PoolStatus.ALREADY_IN_POOL, False, frozenset({1, 2, 3}))


def test_locked_agent_ignores_start_pool() -> None:
    c = Core(1)
    c.start(0.0)
    c.handle(StartPool(2), 0.0)
    c.tick(PAPER.lock_window + 0.01)
    assert c.locked and c.phase == Phase.LOCKED
    assert c.handle(StartPool(3), 2.1) == []
    assert c.counters.ignored_phase >= 1 and 3 not in c.pool


def test_pool_locks_after_the_window_and_elects_after_two_more() -> None:
    a = Core(1, policy=FixedVote(10))
    a.start(0.0)
    a.handle(StartPool(2), 0.0)
    a.tick(1.0)
    assert a.phase == Phase.POOLING
    a.tick(2.0)
    assert a.phase == Phase.LOCKED
    a.tick(4.0)
    assert a.phase == Phase.ELECTING and a.vote == (10, 1)
    # a heavier vote from the pool is adopted
    a.handle(Selection(2, 2, 99, a.epoch), 4.5)
    assert a.vote == (99, 2)
    a.tick(6.4)
    assert a.phase == Phase.ELECTING  # unchanged for 1.9 s only
    a.tick(6.6)
    assert a.phase == Phase.MEMBER and a.leader == 2


def test_votes_from_another_election_or_outside_the_pool_are_ignored() -> None:
    a = Core(1, policy=FixedVote(10))
    a.start(0.0)
    a.handle(StartPool(2), 0.0)
    a.tick(2.0)
    a.tick(4.0)
    a.handle(Selection(2, 2, 99, (a.epoch + 1) & 0xFFFF), 4.1)
    a.handle(Selection(7, 7, 99, a.epoch), 4.2)
    assert a.vote == (10, 1)
    assert a.counters.ignored_stale == 1 and a.counters.ignored_foreign == 1


def test_identical_weights_break_ties_towards_the_higher_id() -> None:
    a = Core(1, policy=FixedVote(5))
    a.start(0.0)
    a.handle(StartPool(2), 0.0)
    a.tick(2.0)
    a.tick(4.0)
    a.handle(Selection(2, 2, 5, a.epoch), 4.1)
    assert a.vote == (5, 2)


def test_leader_expels_a_silent_member_and_member_leaves_a_silent_leader() -> None:
    lead = Core(1, policy=FixedVote(99))
    lead.start(0.0)
    lead.handle(StartPool(2), 0.0)
    lead.handle(StartPool(3), 0.0)
    out = []
    for t in (2.0, 4.0, 6.1, 6.2):
        out += lead.tick(t)
    assert lead.phase == Phase.LEADER and set(lead.members) == {2, 3}
    assert {o.to for o in out if isinstance(o.msg, Heartbeat)} == {2, 3}
    lead.handle(HeartbeatAck(2, 1, POSE), 7.0)
    lead.tick(6.1 + PAPER.ack_timeout + 0.5)
    assert set(lead.members) == {2} and lead.counters.expelled == 1

    m = Core(2)
    m.start(0.0)
    out = m.handle(Heartbeat(1, 0, 1, frozenset({2})), 1.0)
    assert m.phase == Phase.MEMBER and m.leader == 1
    assert any(isinstance(o.msg, HeartbeatAck) and o.to == 1 for o in out)
    m.tick(1.0 + PAPER.leader_timeout + 0.1)
    assert m.phase == Phase.IDLE and m.counters.left == 1


def test_member_not_listed_by_its_leader_leaves() -> None:
    m = Core(2)
    m.start(0.0)
    m.handle(Heartbeat(1, 0, 1, frozenset({2, 3})), 1.0)
    m.handle(Heartbeat(1, 0, 2, frozenset({3})), 1.5)
    assert m.phase == Phase.IDLE


def test_member_expelled_while_deaf_leaves_although_it_hears_the_leaders_poses() -> None:
    """Found by the fault bench: a member whose radio was flooded was expelled; its leader's
    Heartbeats then went to the other members only (multicast), but the leader's pose stream
    kept the expelled member's leader timeout from firing, so it stayed a member of a swarm
    that did not have it, for good. Poses keep a member only so long without a Heartbeat."""
    m = Core(2)
    m.start(0.0)
    m.handle(Heartbeat(1, 0, 1, frozenset({2, 3})), 1.0)
    t = 1.0
    limit = 1.0 + PAPER.leader_timeout * 3
    while t + 0.25 < limit:  # poses only: the expelled member is no longer addressed
        t += 0.25
        m.note_pose(1, POSE, t)
        m.tick(t)
        assert m.phase == Phase.MEMBER  # a lost Heartbeat or two is not an expulsion
    for _ in range(4):
        t += 0.25
        m.note_pose(1, POSE, t)
        m.tick(t)
    assert m.phase != Phase.MEMBER and m.counters.left == 1
    assert m.next_deadline() is not None


def test_an_agent_that_hears_a_leader_is_not_alone() -> None:
    """Found by the fault bench: a member whose radio was flooded for three minutes could
    hear the swarm but not be heard; expelled, it formed a swarm of one after the alone
    timeout, and the swarm had two leaders for the rest of the flood. An agent that hears
    a leader's Advertize keeps asking to join it instead."""
    from swarm.core.election.outbox import FLAG_LEADER

    a = Core(4)
    a.start(0.0)
    t = 0.0
    asked = 0
    while t < 3 * PAPER.alone_timeout:
        t += 1.0
        out = a.handle(Advertize(1, "agent1", FLAG_LEADER), t) + a.tick(t)
        asked += sum(isinstance(o.msg, StartPool) and o.to == 1 for o in out)
        assert a.phase == Phase.IDLE  # not a second leader
    assert asked >= 3  # it keeps asking the leader it hears
    quiet = t
    while a.phase == Phase.IDLE and t < quiet + 2 * PAPER.alone_timeout:
        t += 0.25
        a.tick(t)
    assert a.phase == Phase.LEADER and t >= quiet + PAPER.alone_timeout  # alone now: a swarm of one


def test_time_without_a_radio_is_not_time_alone() -> None:
    """Found by the fault bench (issue 27): a member whose radio a flood of garbage kept
    from sending was expelled; IDLE, it heard the leader's Advertizes, but its radio was
    re-checked every few seconds (the radio guard borrows the port), and a check that
    covered the gap between two Advertizes made it a swarm of one beside the real leader
    for the rest of the flood (two leaders for 144 s of a 1 MiB flood). While the radio
    is away the election core's time stands still."""
    from swarm.core.agent.node import AgentNode, RadioAway, RadioBack
    from swarm.core.election.outbox import FLAG_LEADER

    node = AgentNode(4, "agent4", PAPER)
    node.start(0.0)
    a = node.core
    a.handle(Advertize(1, "agent1", FLAG_LEADER), 1.0)  # the leader heard at 1 s
    away = 2.0
    node.handle(RadioAway(), away)
    t = away
    while t < away + 3 * PAPER.alone_timeout:  # a long unplug: deaf, not alone
        t += 0.5
        node.tick(t)
        assert a.phase == Phase.IDLE, t
    back = t
    node.handle(RadioBack(), back)
    heard_quiet = away - 1.0  # quiet before the radio went away
    while a.phase == Phase.IDLE and t < back + 2 * PAPER.alone_timeout:
        t += 0.25
        node.tick(t)
        if a.phase == Phase.IDLE:
            assert t < back + PAPER.alone_timeout - heard_quiet, t
    # alone only after a whole alone timeout of listening, the time before the radio went counted
    assert a.phase == Phase.LEADER and t >= back + PAPER.alone_timeout - heard_quiet - 0.25


def test_leader_adopts_a_late_joiner() -> None:
    lead = Core(1)
    lead.start(0.0)
    lead.tick(PAPER.alone_timeout + 0.1)  # alone: a swarm of one
    assert lead.phase == Phase.LEADER
    out = lead.handle(StartPool(5), 20.0)
    assert 5 in lead.members
    assert out[0].msg == StartPoolAck(1, PoolStatus.ALREADY_IN_POOL, True, frozenset({1, 5}))


def test_larger_swarm_absorbs_smaller_when_leaders_meet() -> None:
    big = Core(9)
    big.start(0.0)
    big.tick(PAPER.alone_timeout + 0.1)
    big.handle(StartPool(5), 10.0)
    big.handle(StartPool(6), 10.0)
    small = Core(3)
    small.start(0.0)
    small.tick(PAPER.alone_timeout + 0.1)
    small.handle(StartPool(4), 10.0)
    # each hears the other's advertize -> sends its heartbeat
    out = big.handle(Advertize(3, "agent3", 0x02), 11.0)
    hb_big = next(o.msg for o in out if isinstance(o.msg, Heartbeat))
    out = small.handle(Advertize(9, "agent9", 0x02), 11.0)
    hb_small = next(o.msg for o in out if isinstance(o.msg, Heartbeat))
    big.handle(hb_small, 11.1)  # the bigger absorbs the smaller leader and its member
    assert {3, 4} <= set(big.members)
    small.handle(Heartbeat(9, big.epoch, 1, frozenset(big.members)), 11.6)
    assert small.phase == Phase.MEMBER and small.leader == 9
    assert hb_big.sender == 9


def test_sync_pool_merges_and_spreads_the_lock() -> None:
    a = Core(1)
    a.start(0.0)
    a.handle(StartPool(2), 0.0)
    out = a.handle(SyncPool(2, pool_digest({1, 2, 3}), False, frozenset({1, 2, 3})), 0.5)
    assert a.pool == {1, 2, 3}
    assert out == []  # same pool, same lock state: silence means agreement
    out = a.handle(SyncPool(2, pool_digest({1, 9}), False), 0.6)
    assert [type(o.msg).__name__ for o in out] == ["SyncPoolAck"] and out[0].msg.members == {1, 2, 3}
    a.handle(SyncPool(2, pool_digest({1, 2, 3}), True), 1.0)
    assert a.locked


def test_garbage_and_out_of_order_messages_never_raise() -> None:
    rng = random.Random(7)
    c = Core(1)
    c.start(0.0)
    msgs = [
        StartPool(2),
        StartPoolAck(3, PoolStatus.SUCCESS, True, frozenset({3, 9})),
        SyncPool(4, 123, True, None),
        Selection(5, 77, 3, 9),
        Heartbeat(6, 1, 2, frozenset()),
        HeartbeatAck(7, 3, POSE),
        Advertize(1, "me"),
    ]
    t = 0.0
    for _ in range(500):
        t += rng.random()
        c.handle(rng.choice(msgs), t)
        c.tick(t)
    assert c.phase in set(Phase)


def test_profiles_stretch_with_the_radio_round() -> None:
    assert paper_profile(0.24) == paper_profile(0.0)  # fast radios: the paper's values
    slow = paper_profile(2.4)
    assert slow.vote_window == pytest.approx(3.6) and slow.ack_timeout == pytest.approx(12.0)
    f = fast_profile(0.24)
    assert f.vote_window < PAPER.vote_window


# -- N cores over the air model --------------------------------------------------


@pytest.mark.parametrize("n", [2, 3, 5, 10, 20])
def test_swarm_converges_for_n_agents(n: int) -> None:
    seeds = 2 if n >= 10 else 3
    r = sweep(Scenario(agents=n, loss=0.1 if n > 2 else 0.0), seeds, 100)
    assert r["violations"] == 0, r["failing"]
    assert r["converged"] == seeds


def test_heavy_loss_with_bursts_still_converges() -> None:
    r = sweep(Scenario(agents=5, loss=0.3, burst_loss="0.02,0.5"), 3, 200)
    assert r["violations"] == 0, r["failing"]
    assert r["converged"] == 3


def test_late_joiner_joins_the_existing_swarm() -> None:
    s = Sim(Scenario(agents=5, late=["5@25"]), 1)
    r = s.run()
    assert not r.violations and r.stable_at_end
    lead = s.cores[r.leader - 1]
    assert 5 in lead.members and s.cores[4].leader == r.leader


def test_leader_crash_survivors_agree_on_a_new_leader() -> None:
    s = Sim(Scenario(agents=5, crashes=["leader@15"], duration=80), 2)
    r = s.run()
    assert not r.violations
    assert r.failover_s is not None
    p = s.cores[0].profile
    # within the leader timeout plus one election (pool, lock, vote windows) and a margin
    assert r.failover_s < p.leader_timeout + 3 * p.lock_window + 6
    dead = [i + 1 for i in range(5) if not s.alive[i]]
    assert r.leader not in dead


def test_member_crash_is_expelled() -> None:
    s = Sim(Scenario(agents=5, crashes=["2@15"], duration=40), 3)
    r = s.run()
    assert not r.violations
    lead = s.cores[r.leader - 1]
    assert 2 not in lead.members


def test_partition_then_heal_merges_into_one_swarm() -> None:
    s = Sim(Scenario(agents=6, partitions=["0-25:1,2,3|4,5,6"], duration=90), 4)
    r = s.run()
    assert not r.violations
    assert r.stable_at_end
    leaders = [c for c in s.cores if c.phase == Phase.LEADER]
    assert len(leaders) == 1 and len(leaders[0].members) == 5


def test_a_seed_replays_exactly() -> None:
    a = Sim(Scenario(agents=5, loss=0.2), 42).run()
    b = Sim(Scenario(agents=5, loss=0.2), 42).run()
    assert a == b


def test_campaign_paper_n10_loss10_bounded() -> None:
    """The bounded version CI runs (the target campaign is 500 seeds, below)."""
    r = sweep(Scenario(agents=10, loss=0.1), 60)
    assert r["converged"] == 60 and r["violations"] == 0, r["failing"]


@pytest.mark.slow
def test_campaign_paper_n10_loss10_500_seeds() -> None:
    r = sweep(Scenario(agents=10, loss=0.1), 500)
    assert r["converged"] == 500 and r["violations"] == 0, r["failing"]


# -- a leader that cannot fly hands over (issue 11, item 7) ------------------------------


def _leader_of(members: set[int], *, has_fc: bool = True) -> Core:
    lead = Core(1, policy=FixedVote(99), has_fc=has_fc)
    lead.start(0.0)
    for m in members:
        lead.handle(StartPool(m), 0.0)
    for t in (2.0, 4.0, 6.1):
        lead.tick(t)
    assert lead.phase == Phase.LEADER and set(lead.members) == members
    return lead


def test_a_leader_whose_vehicle_is_lost_hands_over_after_the_grace() -> None:
    lead = _leader_of({2, 3})
    g = lead.profile.vehicle_grace
    lead.set_vehicle_link(False, 7.0)
    assert lead.next_deadline() is not None and lead.next_deadline() <= 7.0 + g  # type: ignore[operator]
    for t in (7.0, 7.0 + g / 2):
        for m in (2, 3):
            lead.handle(HeartbeatAck(m, 1, POSE), t)
        lead.tick(t)
    assert lead.phase == Phase.LEADER  # a short loss changes nothing
    out = lead.tick(7.0 + g)
    assert lead.phase == Phase.IDLE and lead.counters.step_downs == 1
    last = [o for o in out if isinstance(o.msg, Heartbeat)]
    assert {o.to for o in last} == {2, 3} and all(o.msg.members == frozenset() for o in last)
    # a member hearing that last Heartbeat leaves at once (no leader_timeout to wait)
    m = Core(2)
    m.start(0.0)
    m.handle(Heartbeat(1, 0, 1, frozenset({2, 3})), 6.5)
    m.handle(last[0].msg, 7.0 + g)
    assert m.phase == Phase.IDLE
    # until its vehicle is back it does not form a swarm of one, and says it has none
    out = lead.tick(7.0 + g + 3 * lead.profile.alone_timeout)
    assert lead.phase == Phase.IDLE
    ads = [o.msg for o in out if isinstance(o.msg, Advertize)]
    assert ads and not ads[0].flags & 0x01
    nd = lead.next_deadline()
    assert nd is not None and nd > 7.0 + g + 3 * lead.profile.alone_timeout - 1  # no busy loop


def test_a_vehicle_back_within_the_grace_keeps_the_leader() -> None:
    lead = _leader_of({2})
    lead.set_vehicle_link(False, 7.0)
    lead.set_vehicle_link(True, 8.0)
    lead.handle(HeartbeatAck(2, 1, POSE), 9.0)
    lead.tick(7.0 + lead.profile.vehicle_grace + 1)
    assert lead.phase == Phase.LEADER and lead.counters.step_downs == 0


def test_without_a_flight_controller_nothing_changes() -> None:
    lead = _leader_of({2}, has_fc=False)
    lead.set_vehicle_link(False, 7.0)  # meaningless without one
    lead.handle(HeartbeatAck(2, 1, POSE), 10.0)
    lead.tick(7.0 + lead.profile.vehicle_grace + 1)
    assert lead.phase == Phase.LEADER


def test_an_agent_without_its_vehicle_votes_with_weight_zero_and_loses() -> None:
    a = Core(3, policy=FixedVote(99), has_fc=True)  # would win: the heaviest and highest id
    a.set_vehicle_link(False, 0.0)
    a.start(0.0)
    a.handle(StartPool(2), 0.0)
    a.tick(2.0)
    a.tick(4.0)
    assert a.phase == Phase.ELECTING and a.vote == (0, 3)
    a.handle(Selection(2, 2, 1, a.epoch), 4.1)
    assert a.vote == (1, 2)
    a.tick(4.1 + a.profile.vote_window)
    assert a.phase == Phase.MEMBER and a.leader == 2


def test_a_member_without_its_vehicle_stays_a_member() -> None:
    m = Core(2, has_fc=True)
    m.start(0.0)
    m.handle(Heartbeat(1, 0, 1, frozenset({2})), 1.0)
    m.set_vehicle_link(False, 1.5)
    for k in range(20):
        m.handle(Heartbeat(1, 0, 2 + k, frozenset({2})), 2.0 + k * 0.5)
        m.tick(2.0 + k * 0.5)
    assert m.phase == Phase.MEMBER and m.leader == 1


def test_three_cores_hand_over_to_one_that_can_fly() -> None:
    """Three cores over an instant, lossless channel and a manual clock: the elected
    leader loses its vehicle; the other two elect one of them, and the old leader
    joins as a member; its vehicle back, nothing changes."""
    cores = {i: Core(i, policy=FixedVote(10 * i), has_fc=True, rng=random.Random(i)) for i in (1, 2, 3)}
    queue: list[tuple[int, object]] = []

    def send(outs: list, sender: int) -> None:  # type: ignore[type-arg]
        for o in outs:
            targets = [i for i in cores if i != sender] if o.to == ADVERTIZE else [o.to]
            queue.extend((to, o.msg) for to in targets)

    t = 0.0
    for i, c in cores.items():
        send(c.start(t), i)

    def run(until: float) -> None:
        nonlocal t
        while t < until:
            while queue:
                to, msg = queue.pop(0)
                send(cores[to].handle(msg, t), to)  # type: ignore[arg-type]
            for i, c in cores.items():
                send(c.tick(t), i)
            t = round(t + 0.05, 2)

    def agreed() -> int | None:
        leaders = {c.leader for c in cores.values() if c.phase in (Phase.LEADER, Phase.MEMBER)}
        phases = [c.phase for c in cores.values()]
        if len(leaders) == 1 and phases.count(Phase.LEADER) == 1 and phases.count(Phase.MEMBER) == 2:
            return leaders.pop()
        return None

    run(20.0)
    assert agreed() == 3
    cores[3].set_vehicle_link(False, t)
    run(t + 30.0)
    assert agreed() == 2, [(c.me, c.phase, c.leader) for c in cores.values()]
    assert cores[3].counters.step_downs == 1 and cores[3].phase == Phase.MEMBER
    cores[3].set_vehicle_link(True, t)
    run(t + 20.0)
    assert agreed() == 2 and sum(c.counters.step_downs for c in cores.values()) == 1
