"""The ``tdm`` election profile in virtual time: the pure core alone (time is a number
the test passes), and N cores over the SiK air model. No processes, no sleeps."""

from __future__ import annotations

import json
import random

import pytest

from swarm.cli.commands.simulate import main as simulate_main
from swarm.core.election.outbox import Out
from swarm.core.election.profiles import (
    PROFILE_NAMES,
    fast_profile,
    paper_profile,
    profile_by_name,
    tdm_profile,
)
from swarm.core.election.protocol import Core
from swarm.core.wire.message_types import Phase, Selection, StartPool, StartPoolAck, SyncPool, pool_digest
from swarm.sim.campaign import draw, run_campaign
from swarm.sim.parallel import sweep
from swarm.sim.simulate import Scenario, Sim

ROUND = 1.0


class FixedVote:
    def __init__(self, w: int) -> None:
        self.w = w

    def weight(self, rng: random.Random) -> int:
        return self.w


def pooled(me: int, pool: set[int], weight: int, t: float = 0.0) -> Core:
    """A tdm core that joined ``pool`` at ``t`` (a SyncPool listing it, the answer to its
    StartPool), and sent its first SyncPool and vote."""
    c = Core(me, profile=tdm_profile(ROUND), policy=FixedVote(weight))
    c.start(t)
    other = min(pool - {me})
    c.handle(SyncPool(other, pool_digest(pool), False, frozenset(pool)), t)
    c.tick(t)
    return c


def locked(me: int, pool: set[int], weight: int) -> tuple[Core, float]:
    """A tdm core whose pool has just locked (ELECTING) with no vote heard yet."""
    c = pooled(me, pool, weight)
    t = tdm_profile(ROUND).lock_window
    c.tick(t)
    assert c.phase == Phase.ELECTING and c.locked
    return c, t


# -- the profile ---------------------------------------------------------------------


def test_tdm_is_chosen_by_name_and_derives_its_windows_from_the_round() -> None:
    assert PROFILE_NAMES == ("paper", "fast", "tdm")
    p = profile_by_name("tdm", 1.2)
    assert p.name == "tdm" and p.tdm
    assert p.sync_interval == p.vote_interval == p.heartbeat_interval == pytest.approx(1.2)
    assert p.lock_window == pytest.approx(1.25 * 1.2) and p.vote_window == pytest.approx(1.5 * 1.2)
    assert not paper_profile(1.2).tdm and not fast_profile(1.2).tdm  # their rules are the paper's
    with pytest.raises(ValueError, match="paper, fast or tdm"):
        profile_by_name("slow", 1.0)


# -- the core alone ------------------------------------------------------------------


def test_a_startpool_is_answered_by_one_syncpool_with_the_vote_beside_it() -> None:
    c = Core(1, profile=tdm_profile(ROUND), policy=FixedVote(7))
    c.start(0.0)
    out = c.handle(StartPool(2), 0.1)
    assert c.phase == Phase.POOLING and c.pool == {1, 2}
    assert not any(isinstance(o.msg, StartPoolAck) for o in out)  # no ack: the SyncPool answers
    out = c.handle(StartPool(3), 0.2) + c.tick(0.2)
    syncs = [o for o in out if isinstance(o.msg, SyncPool)]
    votes = [o for o in out if isinstance(o.msg, Selection)]
    assert {o.to for o in syncs} == {o.to for o in votes} == {2, 3}
    assert len({id(o.msg) for o in syncs}) == 1  # one message for all: one multicast frame
    assert syncs[0].msg.members == frozenset({1, 2, 3})
    assert (votes[0].msg.candidate, votes[0].msg.weight) == (1, 7)


def test_an_idle_agent_listed_in_a_syncpool_joins_that_pool() -> None:
    c = pooled(2, {1, 2, 3}, 5)
    assert c.phase == Phase.POOLING and c.pool == {1, 2, 3}


def test_votes_are_exchanged_while_pooling_and_the_heavier_is_adopted() -> None:
    c = pooled(1, {1, 2, 3}, 5)
    c.handle(Selection(2, 3, 9, 0), 0.2)  # relayed: agent 3's vote, heard through agent 2
    assert c.phase == Phase.POOLING and c.vote == (9, 3)
    c.handle(Selection(3, 3, 4, 0), 0.3)  # lighter: kept
    assert c.vote == (9, 3)


def test_every_vote_heard_ends_the_election_at_once() -> None:
    c, t = locked(1, {1, 2, 3}, 5)
    c.handle(Selection(2, 2, 3, 0), t + 0.1)
    assert c.phase == Phase.ELECTING  # agent 3 not heard yet: it may be heavier
    c.handle(Selection(3, 3, 9, 0), t + 0.2)
    assert c.phase == Phase.MEMBER and c.leader == 3  # long before the vote window


def test_the_heaviest_that_heard_everyone_leads_at_once() -> None:
    c, t = locked(1, {1, 2, 3}, 50)
    c.handle(Selection(2, 2, 3, 0), t + 0.1)
    c.handle(Selection(3, 2, 3, 0), t + 0.2)
    assert c.phase == Phase.LEADER and set(c.members) == {2, 3}


def test_a_missing_vote_holds_the_decision_for_the_window() -> None:
    # the split-vote guard: agent 3 may hold a heavier vote that did not reach us
    c, t = locked(1, {1, 2, 3}, 50)
    c.handle(Selection(2, 2, 3, 0), t + 0.1)
    end = c.changed_at + tdm_profile(ROUND).vote_window  # the window runs from the pool's last change
    assert end > t + 0.1
    c.tick(end - 0.01)
    assert c.phase == Phase.ELECTING
    assert c.next_deadline() == pytest.approx(end)
    c.tick(end)
    assert c.phase == Phase.LEADER  # agent 3 silent a whole window: presumed gone


def test_a_leader_adopts_the_agents_an_electing_members_syncpool_names() -> None:
    # the leader locked {1, 2, 3} without agent 4 (its StartPool lost); agent 2, still
    # electing, knows 4, which elects the same leader: the leader lists it
    c, t = locked(1, {1, 2, 3}, 50)
    c.handle(Selection(2, 2, 3, 0), t + 0.1)
    c.handle(Selection(3, 3, 4, 0), t + 0.1)
    assert c.phase == Phase.LEADER
    big = frozenset({1, 2, 3, 4})
    c.handle(SyncPool(2, pool_digest(big), False, big), t + 0.2)
    assert set(c.members) == {2, 3, 4}
    stranger = frozenset({1, 9, 10})
    c.handle(SyncPool(9, pool_digest(stranger), False, stranger), t + 0.3)  # not a member
    assert set(c.members) == {2, 3, 4}


def test_hostile_votes_are_counted_and_dropped() -> None:
    c = pooled(1, {1, 2, 3}, 5)
    before = c.counters.ignored_foreign
    c.handle(Selection(9, 9, 2**32 - 1, 0), 0.2)  # a stranger naming itself
    assert c.counters.ignored_foreign == before + 1
    c.handle(Selection(2, 77, 2**32 - 1, 0), 0.3)  # a member naming a stranger
    c.handle(Selection(2, 1, 2**32 - 1, 0), 0.3)  # a member naming us: our own weight is ours
    assert c.vote[1] in (1,) and 77 not in c.heard
    c.handle(Selection(1, 1, 2**32 - 1, 0), 0.4)  # our own id from elsewhere
    assert c.counters.impossible >= 1


def test_a_locked_peer_locks_us_and_the_election_starts() -> None:
    c = pooled(1, {1, 2, 3}, 5)
    pool = frozenset({1, 2, 3})
    out: list[Out] = c.handle(SyncPool(2, pool_digest(pool), True, pool), 0.4)
    out += c.tick(0.4)
    assert c.phase == Phase.ELECTING and c.locked


# -- N cores over the air model ---------------------------------------------------------


@pytest.mark.parametrize("loss", [0.0, 0.1])
@pytest.mark.parametrize("n", [2, 3, 5, 8, 13, 20])
def test_tdm_converges(n: int, loss: float) -> None:
    sim = Sim(Scenario(agents=n, loss=loss, profile="tdm"), 3)
    r = sim.run()
    assert r.violations == [] and r.elect_s is not None and r.stable_at_end
    assert sum(c.phase == Phase.LEADER for c in sim.cores) == 1


def test_a_vote_split_by_a_partition_ends_with_one_leader() -> None:
    # the partition cuts the pool while it votes: each side may elect its own leader
    # (two connected groups); once healed the two leaders hear each other and merge
    sc = Scenario(agents=6, profile="tdm", partitions=["1.5-8:1,2,3|4,5,6"], duration=60)
    sim = Sim(sc, 1)
    r = sim.run()
    assert r.violations == [] and r.stable_at_end
    assert sum(c.phase == Phase.LEADER for c in sim.cores) == 1


def test_a_vote_lost_one_way_cannot_leave_two_leaders() -> None:
    # agent 1 never hears agent 6 during the election: it cannot hear every vote, so it
    # waits out the window; whatever it decides, one leader remains
    sc = Scenario(agents=6, profile="tdm", links=["6>1:1.0@0-10"], duration=60)
    for seed in range(3):
        sim = Sim(sc, seed)
        r = sim.run()
        assert r.violations == [] and r.stable_at_end
        assert sum(c.phase == Phase.LEADER for c in sim.cores) == 1


def test_a_bounded_tdm_campaign_keeps_the_invariants() -> None:
    for k in range(10):
        sc, s, _ = draw(1, k, 6, "tdm")
        plain, s2, _ = draw(1, k, 6)
        assert sc.profile == "tdm" and s == s2 and sc.agents == plain.agents  # the same draws
    res = run_campaign(10, 1, jobs=1, max_agents=6, profile="tdm")
    assert res["violations"] == 0, res["failing"]


def test_the_rounds_figure_is_the_election_time_over_the_round() -> None:
    res = sweep(Scenario(agents=5, loss=0.1, profile="tdm"), 4)
    e, r, rounds = res["elect_s"], res["round_s"], res["election_rounds"]
    assert rounds["p50"] == pytest.approx(e["p50"] / r, abs=0.01)
    assert rounds["p95"] == pytest.approx(e["p95"] / r, abs=0.01)


def test_swarm_simulate_prints_the_rounds(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--agents", "4", "--seeds", "2", "--profile", "tdm", "--jobs", "1"]
    assert simulate_main([*argv, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["profile"] == "tdm" and set(out["election_rounds"]) == {"p50", "p95"}
    assert simulate_main(argv) == 0
    assert "election in rounds" in capsys.readouterr().out
