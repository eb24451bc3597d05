"""A member's own acknowledgement timer (swarm.core.liveness): the rule in the core
alone (virtual time: the test moves ``now``), and the fault campaign's three heavy-loss
replays that never settled before it (issue 15)."""

from __future__ import annotations

import pytest

from swarm.core import liveness
from swarm.core.liveness import OWN_ACK_SLACK
from swarm.core.messages import Heartbeat, HeartbeatAck, Phase, Task
from swarm.core.protocol import Core, paper_profile
from swarm.sim.faultsim import make_sim
from swarm.sim.scenario import Scenario


def member_of(leader: int, now: float) -> Core:
    c = Core(2, "a2", paper_profile())
    c.start(0.0)
    c.handle(Heartbeat(leader, 7, 41, frozenset({2}), Task()), now)
    assert c.phase == Phase.MEMBER and c.leader == leader
    return c


def acks(out: list) -> list[HeartbeatAck]:
    return [o.msg for o in out if isinstance(o.msg, HeartbeatAck)]


def test_a_member_that_hears_every_heartbeat_acks_only_in_answer() -> None:
    c = member_of(1, 10.0)
    hb = c.profile.heartbeat_interval
    for k in range(1, 20):
        now = 10.0 + k * hb
        assert (c.next_deadline() or 0.0) > now - 1e-9  # nothing due before the Heartbeat
        out = c.handle(Heartbeat(1, 7, 41 + k, frozenset({2}), Task()), now)
        assert [(a.sender, a.seq) for a in acks(out)] == [(2, (41 + k) & 0xFF)]
        assert acks(c.tick(now)) == []


def test_a_member_missing_heartbeats_acks_on_its_own_timer_until_one_comes() -> None:
    c = member_of(1, 10.0)
    hb = c.profile.heartbeat_interval
    first = 10.0 + OWN_ACK_SLACK * hb
    assert c.next_deadline() == pytest.approx(first)
    assert acks(c.tick(first - 0.01)) == []  # not yet overdue
    sent = []
    now = first
    while now < 10.0 + c.profile.leader_timeout - 1e-6:
        out = c.tick(now)
        sent += [(now, a) for a in acks(out)]
        now = c.next_deadline() or now + hb
    # one ack per heartbeat interval after the slack, to the leader, with the last seq heard
    assert [t for t, _ in sent] == pytest.approx([first + k * hb for k in range(len(sent))])
    assert len(sent) >= 3 and all(a.sender == 2 and a.seq == 41 for _, a in sent)
    # a Heartbeat restarts the timer; the paper's rule to leave is unchanged
    out = c.handle(Heartbeat(1, 7, 60, frozenset({2}), Task()), now)
    assert [a.seq for a in acks(out)] == [60] and c.next_deadline() == pytest.approx(now + OWN_ACK_SLACK * hb)
    c.tick(now + c.profile.leader_timeout + 0.01)
    assert c.phase == Phase.IDLE


def run_lossy_swarm(until: float) -> tuple[Core, Core]:
    """A leader and member 2 in virtual time: 2 hears one Heartbeat in five (one each
    2.5 s: within its leader timeout, 3 s) and every ack it sends in answer is lost;
    what it sends on its own timer arrives. Returns (leader, member)."""
    lead, m2 = Core(1, "a1", paper_profile()), member_of(1, 0.0)
    lead.start(0.0)
    lead._become_leader(0.0, {2})
    now, beats = 0.0, 0
    while now < until and 2 in lead.members:
        for o in lead.tick(now):
            if isinstance(o.msg, Heartbeat) and o.to == 2:
                beats += 1
                if beats % 5 == 0:
                    m2.handle(o.msg, now)  # its answer is lost
        for o in m2.tick(now):
            lead.handle(o.msg, now)
        now += 0.05
    return lead, m2


def test_a_member_whose_answers_are_lost_stays_in_the_swarm_by_its_own_acks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    lead, m2 = run_lossy_swarm(30.0)
    assert set(lead.members) == {2} and m2.phase == Phase.MEMBER and lead.counters.expelled == 0
    # the paper's rule alone (no own acks): the leader hears nothing and expels it
    monkeypatch.setattr(liveness, "OWN_ACK_SLACK", 1e9)
    lead, m2 = run_lossy_swarm(30.0)
    assert lead.counters.expelled == 1 and 2 not in lead.members


REPLAYS = {
    "17 agents, 29 % loss, two late joiners": dict(
        agents=17, loss=0.29, late=["17@64.9", "7@64.0"], duration=94.3, seed=843359523
    ),
    "36 agents, 27 % loss, a restart": dict(
        agents=36, loss=0.27, restarts=["19@22.2-42.6"], duration=269.2, seed=214428412
    ),
    "16 agents, 26 % loss with bursts, a partition": dict(
        agents=16,
        loss=0.26,
        burst_loss="0.034,0.37",
        partitions=["79.1-111.9:11,15|1,2,3,4,5,6,7,8,9,10,12,13,14,16"],
        duration=225.9,
        seed=1522498602,
    ),
}


@pytest.mark.parametrize("name", sorted(REPLAYS))
def test_the_campaigns_heavy_loss_replays_settle(name: str) -> None:
    spec = dict(REPLAYS[name])
    seed = int(spec.pop("seed"))  # type: ignore[call-overload]
    sc = Scenario(profile="paper", strict=True, **spec)  # type: ignore[arg-type]
    r = make_sim(sc, seed).run()
    assert r.violations == [] and r.converged and r.stable_at_end, (sc.command(seed), r.violations)
