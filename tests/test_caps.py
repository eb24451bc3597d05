"""Sub-swarms with a size cap (issue 16): the cap's rules in the pure core (manual clock),
the Advertize's size byte on the wire (hostile bytes included), capped simulations over
the SiK air model (virtual time), and the agent's and the simulator's settings. No test
sleeps or starts a process."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from swarm.cli.commands import agent as agent_cmd
from swarm.cli.commands import simulate as simulate_cmd
from swarm.core.election import caps
from swarm.core.election.outbox import ADVERTIZE, FLAG_LEADER
from swarm.core.election.profiles import PAPER
from swarm.core.election.protocol import Core
from swarm.core.wire.message_types import (
    ADV_SIZE,
    ADV_SWARM,
    Advertize,
    Heartbeat,
    Phase,
    PoolStatus,
    StartPool,
    StartPoolAck,
    SyncPool,
    SyncPoolAck,
    swarm_tag,
)
from swarm.core.wire.messages import decode, encode
from swarm.errors import DecodeError, MessageError
from swarm.runtime.options import AgentConfig
from swarm.sim.simulate import Scenario, Sim
from swarm.sim.subswarms import capped_agreement, split_pairs


def _pool(core: Core, *others: int, now: float = 0.0) -> Core:
    """``core`` started and founding a pool with ``others`` (they asked it in turn)."""
    core.start(now)
    for o in others:
        core.handle(StartPool(o), now)
    return core


def _leader(me: int, members: set[int], cap: int) -> Core:
    c = Core(me, cap=cap)
    c.start(0.0)
    c.become_leader(0.0, members)
    return c


def _adverts(out: list) -> list[Advertize]:
    return [o.msg for o in out if o.to == ADVERTIZE and isinstance(o.msg, Advertize)]


# -- no cap: today's behaviour and bytes ----------------------------------------------


def test_without_a_cap_the_advertize_carries_no_size_and_a_pool_grows_past_any_number() -> None:
    c = _pool(Core(1), *range(2, 30))
    assert len(c.pool) == 29
    ad = _adverts(c.tick(1.0))[0]
    assert ad.size == 0 and not ad.flags & ADV_SIZE
    assert encode(ad) == encode(Advertize(1, "agent1", 0))


@pytest.mark.parametrize("bad", [1, -1, 251, 2.5, True, "10"])
def test_a_cap_out_of_range_is_refused_where_the_core_is_built(bad: object) -> None:
    with pytest.raises(ValueError, match=r"0 \(no cap\) or 2\.\.250"):
        Core(1, cap=bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        AgentConfig(swarm_cap=bad)  # type: ignore[arg-type]


# -- admission ------------------------------------------------------------------------


def test_a_full_pool_refuses_with_full_and_its_members() -> None:
    c = _pool(Core(1, cap=3), 2, 3)
    assert c.pool == {1, 2, 3} and c.capped.founder
    out = c.handle(StartPool(4), 0.2)
    assert c.pool == {1, 2, 3}
    assert out[0].to == 4 and out[0].msg == StartPoolAck(1, PoolStatus.FULL, False, frozenset({1, 2, 3}))
    # one already in the pool is answered as before
    out = c.handle(StartPool(2), 0.3)
    assert out[0].msg.status == PoolStatus.ALREADY_IN_POOL


def test_only_the_founder_admits_into_a_capped_pool() -> None:
    joiner = Core(5, cap=4)
    joiner.start(0.0)
    joiner.handle(StartPoolAck(1, PoolStatus.SUCCESS, False, frozenset({1, 5})), 0.1)
    assert joiner.phase == Phase.POOLING and not joiner.capped.founder
    out = joiner.handle(StartPool(6), 0.2)
    assert out[0].msg.status == PoolStatus.FULL and joiner.pool == {1, 5}
    assert not _adverts(joiner.tick(0.3)), "a pool member that does not admit does not advertise"


def test_a_full_leader_refuses_a_late_joiner_and_one_with_room_adopts_it() -> None:
    full = _leader(1, {2, 3}, cap=3)
    out = full.handle(StartPool(9), 1.0)
    assert out[0].msg.status == PoolStatus.FULL and out[0].msg.locked and 9 not in full.members
    roomy = _leader(1, {2}, cap=3)
    out = roomy.handle(StartPool(9), 1.0)
    assert out[0].msg.status == PoolStatus.ALREADY_IN_POOL and 9 in roomy.members


def test_a_full_swarm_advertises_its_size_and_a_free_agent_does_not_ask_it() -> None:
    lead = _leader(1, {2, 3}, cap=3)
    ad = _adverts(lead.tick(0.0))[0]
    assert ad.flags & FLAG_LEADER and ad.flags & ADV_SIZE and ad.size == 3
    free = Core(7, cap=3)
    free.start(0.0)
    for k in range(20):  # a full leader heard for ever: never asked, never "not alone"
        assert free.handle(ad, 1.0 + k) == []
    assert free.idle_since == 0.0
    out = free.tick(PAPER.alone_timeout + 0.1)
    assert free.phase == Phase.LEADER and free.members == {}, "it leads a swarm of one instead"
    assert _adverts(out)


def test_a_refused_agent_stops_asking_until_the_swarm_shrinks() -> None:
    """A leader configured with a smaller cap than ours refuses although its size leaves
    room by our cap: the asker does not ask it at every Advertize."""
    free = Core(7, cap=5)
    free.start(0.0)
    ad = Advertize(1, "agent1", FLAG_LEADER | ADV_SIZE, 2)
    assert [o.msg for o in free.handle(ad, 1.0)] == [StartPool(7)]
    free.handle(StartPoolAck(1, PoolStatus.FULL, True, frozenset({1, 2})), 1.5)
    assert 1 not in free.asked
    for k in range(2):
        assert free.handle(ad, 2.5 + k) == [], "refused at size 2: not asked again soon"
    smaller = Advertize(1, "agent1", FLAG_LEADER | ADV_SIZE, 1)
    assert [o.msg for o in free.handle(smaller, 4.0)] == [StartPool(7)]
    free.handle(StartPoolAck(1, PoolStatus.FULL, True, frozenset({1, 2})), 4.5)
    later = 4.5 + caps.REFUSAL_RETRIES * PAPER.startpool_retry
    assert [o.msg for o in free.handle(ad, later)] == [StartPool(7)], "and again after a while"


def test_free_agents_ask_only_lower_ids_of_their_block_first() -> None:
    c = Core(13, cap=10)  # block 11..20
    c.start(0.0)
    assert c.handle(Advertize(12, "agent12"), 0.5) != []
    assert c.handle(Advertize(14, "agent14"), 0.5) == [], "a higher id asks us"
    assert c.handle(Advertize(3, "agent3"), 0.5) == [], "another block"
    late = PAPER.advertize_interval * caps.FALLBACK_INTERVALS
    assert c.handle(Advertize(3, "agent3"), late + 0.1) != [], "late: anyone with room"


def test_a_capped_pooling_agent_does_not_ask_other_pools() -> None:
    c = _pool(Core(1, cap=10), 2)
    assert c.handle(Advertize(3, "agent3", ADV_SIZE, 4), 0.5) == []


# -- merges ------------------------------------------------------------------------------


def test_pools_merge_while_the_union_fits() -> None:
    c = _pool(Core(1, cap=5), 2)
    c.handle(SyncPool(2, 0, False, frozenset({1, 2, 3, 4})), 0.5)
    assert c.pool == {1, 2, 3, 4}


def test_an_overfull_union_keeps_the_caps_lowest_ids_on_every_side() -> None:
    """The split is a function of the union alone: both sides decide the same."""
    union = {1, 2, 3, 4, 5, 6}
    kept = {1, 2, 3, 4}
    low = _pool(Core(2, cap=4), 1, 3)
    low.handle(SyncPool(5, 0, False, frozenset({2, 4, 5, 6})), 0.5)
    assert low.pool == kept and low.counters.refused == 1
    other = _pool(Core(4, cap=4), 5, 6)
    other.handle(SyncPool(2, 0, False, frozenset(union - {5})), 0.5)
    assert other.pool == kept
    left_out = _pool(Core(6, cap=4), 5, 4)
    left_out.handle(SyncPoolAck(4, False, False, frozenset({1, 2, 3, 4})), 0.5)
    assert left_out.phase == Phase.IDLE and left_out.pool == set(), "beyond the cap: free again"


def test_leaders_merge_only_when_both_swarms_fit() -> None:
    big = _leader(1, {2, 3}, cap=5)
    small = Heartbeat(9, 0, 1, frozenset({8}))
    big.handle(small, 1.0)
    assert set(big.members) == {2, 3, 8, 9}, "3 + 2 <= 5: the larger absorbs the smaller"
    full = _leader(1, {2, 3, 4}, cap=5)
    full.handle(small, 1.0)
    assert set(full.members) == {2, 3, 4} and full.counters.refused == 1
    # the smaller side decides the same: it is never listed, so it stays a leader
    lone = _leader(9, {8}, cap=5)
    lone.handle(Heartbeat(1, 0, 1, frozenset({2, 3, 4})), 1.0)
    assert lone.phase == Phase.LEADER


def test_a_leader_does_not_court_a_leader_whose_swarm_would_not_fit() -> None:
    lead = _leader(1, {2, 3}, cap=5)
    assert lead.handle(Advertize(9, "agent9", FLAG_LEADER | ADV_SIZE, 3), 1.0) == []
    out = lead.handle(Advertize(9, "agent9", FLAG_LEADER | ADV_SIZE, 2), 1.0)
    assert [type(o.msg) for o in out] == [Heartbeat]


def _periodic_heartbeat(core: Core, now: float) -> set[int]:
    """Who the leader's next periodic Heartbeat goes to (one frame, these addressees)."""
    out = core.tick(now)
    return {o.to for o in out if isinstance(o.msg, Heartbeat)}


def test_a_smaller_leader_courts_the_larger_with_every_heartbeat_until_listed() -> None:
    # the attack-free fault: the larger leader's frames reach the smaller one rarely
    # (one Advertize in ten s), so the merge may not wait for a reply to that one
    small = _leader(6, {4, 11}, cap=0)
    small.handle(Heartbeat(3, 0, 1, frozenset({1, 2, 5})), 1.0)  # larger: 4 > 3
    assert small.phase == Phase.LEADER
    hb = small.profile.heartbeat_interval
    for k in (1, 2):  # each periodic Heartbeat, not only the one reply
        assert _periodic_heartbeat(small, 1.0 + k * hb) == {3, 4, 11}
    large = _leader(3, {1, 2, 5}, cap=0)
    ours = next(o.msg for o in small.tick(1.0 + 3 * hb) if isinstance(o.msg, Heartbeat))
    large.handle(ours, 1.0 + 3 * hb)
    assert set(large.members) == {1, 2, 4, 5, 6, 11}, "the larger absorbs on any one of them"
    assert caps.courted(large, 1.0 + 3 * hb) == [], "nobody courts a smaller leader"
    small.handle(Heartbeat(3, 0, 2, frozenset(large.members)), 1.0 + 4 * hb)
    assert small.phase == Phase.MEMBER and small.leader == 3


def test_a_leader_courts_only_leaders_that_would_absorb_it_and_not_for_ever() -> None:
    lead = _leader(6, {4, 11}, cap=0)
    lead.handle(Heartbeat(9, 0, 1, frozenset({7, 8, 10, 12})), 1.0)  # larger: 5 > 3
    lead.handle(Heartbeat(2, 0, 1, frozenset({1})), 1.0)  # smaller (2 < 3): it absorbs that one
    hb = lead.profile.heartbeat_interval
    assert _periodic_heartbeat(lead, 1.0 + hb) == {1, 2, 4, 11, 9}, "(5, 9) > (5, 6)"
    quiet = 1.0 + lead.profile.leader_timeout + 2 * hb  # 9 not heard for a leader timeout
    assert 9 not in _periodic_heartbeat(lead, quiet)
    capped = _leader(6, {4, 11}, cap=5)
    capped.handle(Heartbeat(9, 0, 1, frozenset({7, 8, 10})), 1.0)  # 3 + 4 > 5: no merge
    assert 9 not in _periodic_heartbeat(capped, 1.0 + hb)
    named = Core(6, swarm_name="red")
    named.start(0.0)
    named.become_leader(0.0, {4})
    named.handle(Advertize(9, "agent9", FLAG_LEADER | ADV_SWARM, 0, swarm_tag("blue")), 1.0)
    assert 9 not in _periodic_heartbeat(named, 1.0 + hb), "another name's leader is never courted"


def test_forged_leader_adverts_cannot_make_a_leader_flood_the_air_with_heartbeats() -> None:
    # a hostile radio (unsigned swarm) advertises 200 "leaders": courting each would
    # add 200 addressees, more than a TUNNEL frame holds, and the heartbeat would go as
    # one P2P frame per addressee every interval (an amplifier). It courts COURT_MAX.
    lead = _leader(6, {4, 11}, cap=0)
    for fake in range(20, 220):
        lead.handle(Advertize(fake, f"agent{fake}", FLAG_LEADER), 1.0)
    lead.handle(Heartbeat(3, 0, 1, frozenset({1, 2, 5, 7})), 1.0)  # the real, larger one
    to = _periodic_heartbeat(lead, 1.0 + lead.profile.heartbeat_interval)
    assert {3, 4, 11} <= to and len(to) <= 2 + caps.COURT_MAX, "known larger first, then few"


def test_a_member_stays_with_its_leader_and_the_other_lets_it_go() -> None:
    m = Core(5, cap=10)
    m.start(0.0)
    m.handle(Heartbeat(1, 0, 1, frozenset({5})), 1.0)
    assert m.phase == Phase.MEMBER and m.leader == 1
    out = m.handle(Heartbeat(7, 0, 1, frozenset({5, 6})), 1.5)
    assert m.leader == 1
    assert [(o.to, o.msg) for o in out] == [(7, SyncPoolAck(5, False, True, frozenset({1, 5})))]
    other = _leader(7, {5, 6}, cap=10)
    other.handle(out[0].msg, 2.0)
    assert set(other.members) == {6}, "released at once, not after the ack timeout"
    # the merge: a Heartbeat that lists our leader too takes us along
    m.handle(Heartbeat(7, 0, 2, frozenset({1, 5, 6})), 3.0)
    assert m.leader == 7


def test_a_member_by_vote_that_no_heartbeat_lists_leaves_and_asks_a_leader_with_room() -> None:
    c = _pool(Core(3, cap=10), 2)
    c.locked, c.phase = True, Phase.LOCKED
    out: list = []
    c.start_election(1.0, out)
    c.vote = (2**31, 9)  # the pool voted for 9, which never leads
    out = c.tick(1.0 + PAPER.vote_window)
    assert c.phase == Phase.MEMBER and c.leader == 9 and StartPool(3) in [o.msg for o in out]
    deadline = c.next_deadline()
    assert deadline is not None and deadline <= c.last_hb + caps.CONFIRM_INTERVALS * PAPER.heartbeat_interval
    c.handle(Advertize(2, "agent2", FLAG_LEADER | ADV_SIZE, 4), deadline - 0.5)  # a leader with room
    out = c.tick(deadline)
    assert c.phase == Phase.IDLE and (2, StartPool(3)) in [(o.to, o.msg) for o in out]


def test_a_member_by_vote_also_asks_its_blocks_leader_and_follows_the_first_that_lists_it() -> None:
    c = _pool(Core(3, cap=10), 2)
    c.locked, c.phase = True, Phase.LOCKED
    out: list = []
    c.start_election(1.0, out)
    c.vote = (2**31, 9)
    c.handle(Advertize(4, "agent4", FLAG_LEADER | ADV_SIZE, 6), 2.0)  # block 1..10, room
    c.handle(Advertize(14, "agent14", FLAG_LEADER | ADV_SIZE, 2), 2.0)  # another block
    out = c.tick(1.0 + PAPER.vote_window)
    assert sorted((o.to, o.msg) for o in out if isinstance(o.msg, StartPool)) == [
        (4, StartPool(3)),
        (9, StartPool(3)),
    ]
    c.handle(Heartbeat(4, 0, 1, frozenset({3, 5})), 3.5)
    assert c.leader == 4 and not c.capped.unconfirmed, "the first leader to list it"
    out = c.handle(Heartbeat(9, 0, 1, frozenset({3})), 4.0)
    assert c.leader == 4 and [o.to for o in out] == [9], "the candidate is told it follows another"


def test_the_leader_table_keeps_sizes_and_forgets_the_silent() -> None:
    c = Core(1, cap=10)
    c.start(0.0)
    c.handle(Advertize(4, "agent4", FLAG_LEADER | ADV_SIZE, 6), 1.0)
    c.handle(Heartbeat(8, 0, 1, frozenset({7})), 2.0)
    table = c.other_leaders.current(2.0, caps.forget_s(c))
    assert {k: v.size for k, v in table.items()} == {4: 6, 8: 2}
    c.handle(Advertize(4, "agent4", 0), 3.0)  # no longer a leader
    later = 3.0 + caps.forget_s(c) + 1
    c.handle(Advertize(9, "agent9", FLAG_LEADER), later)
    assert list(c.other_leaders.current(later, caps.forget_s(c))) == [9]


# -- the wire: the Advertize's size byte -----------------------------------------------


def test_the_size_byte_round_trips_and_costs_one_byte() -> None:
    plain = encode(Advertize(3, "agent3", FLAG_LEADER))
    sized = encode(Advertize(3, "agent3", FLAG_LEADER | ADV_SIZE, 7))
    assert sized == bytes([plain[0]]) + plain[1:-1] + bytes([plain[-1] | ADV_SIZE, 7])
    assert decode(sized) == Advertize(3, "agent3", FLAG_LEADER | ADV_SIZE, 7)


@pytest.mark.parametrize(
    "what,raw",
    [
        ("flag without the byte", lambda p: p[:-1] + bytes([p[-1] | ADV_SIZE])),
        ("byte without the flag", lambda p: p + b"\x05"),
        ("size 0", lambda p: p[:-1] + bytes([p[-1] | ADV_SIZE, 0])),
        ("size 251", lambda p: p[:-1] + bytes([p[-1] | ADV_SIZE, 251])),
        ("size 255", lambda p: p[:-1] + bytes([p[-1] | ADV_SIZE, 255])),
        ("two size bytes", lambda p: p[:-1] + bytes([p[-1] | ADV_SIZE, 5, 5])),
    ],
)
def test_hostile_size_bytes_are_one_decode_error(what: str, raw: object) -> None:
    plain = encode(Advertize(3, "agent3", FLAG_LEADER))
    with pytest.raises(DecodeError):
        decode(raw(plain))  # type: ignore[operator]


def test_every_cut_and_every_byte_value_of_a_sized_advertize_decodes_canonically() -> None:
    sized = encode(Advertize(3, "agent3", FLAG_LEADER | ADV_SIZE, 7))
    for cut in range(len(sized)):
        with pytest.raises(DecodeError):
            decode(sized[:cut])
    for at in range(len(sized)):
        for v in range(256):
            raw = sized[:at] + bytes([v]) + sized[at + 1 :]
            try:
                got = decode(raw)
            except DecodeError:
                continue
            assert encode(got) == raw


@pytest.mark.parametrize("flags,size", [(ADV_SIZE, 0), (0, 4), (0, 300), (ADV_SIZE, -1)])
def test_an_inconsistent_advertize_is_our_own_misuse(flags: int, size: int) -> None:
    with pytest.raises(MessageError):
        Advertize(3, "agent3", flags, size)


def test_a_full_status_round_trips() -> None:
    ack = StartPoolAck(1, PoolStatus.FULL, True, frozenset({1, 2, 3}))
    assert decode(encode(ack)) == ack


# -- simulations over the air model (virtual time) ---------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
def test_25_capped_agents_converge_into_swarms_of_at_most_the_cap(seed: int) -> None:
    sim = Sim(Scenario(agents=25, loss=0.1, cap=10), seed)
    res = sim.run()
    assert res.violations == [] and res.elect_s is not None
    leaders = [c for c in sim.cores if c.phase == Phase.LEADER]
    assert len(leaders) >= 3
    listed = [m for c in leaders for m in c.members]
    assert len(listed) == len(set(listed)) == 25 - len(leaders), "every agent in exactly one swarm"
    assert all(len(c.members) + 1 <= 10 for c in leaders)
    for c in sim.cores:
        if c.phase == Phase.MEMBER:
            assert c.me in sim.cores[c.leader - 1].members


def test_a_capped_run_replays_exactly() -> None:
    a = Sim(Scenario(agents=12, loss=0.1, cap=5, profile="fast"), 3).run()
    b = Sim(Scenario(agents=12, loss=0.1, cap=5, profile="fast"), 3).run()
    assert a == b and a.elect_s is not None


def test_the_capped_judge() -> None:
    lead = _leader(1, {2, 3}, cap=3)
    members = []
    for m in (2, 3):
        c = Core(m, cap=3)
        c.start(0.0)
        c.handle(Heartbeat(1, 0, 1, frozenset({2, 3})), 0.5)
        members.append(c)
    one = lambda a: 0  # noqa: E731  (one connected group)
    assert capped_agreement([lead, *members], 3, one) == (True, 1)
    assert capped_agreement([lead, *members], 2, one)[0] is False, "a swarm over the cap"
    idle = Core(4, cap=3)
    idle.start(0.0)
    assert capped_agreement([lead, *members, idle], 3, one)[0] is False, "an agent in no swarm"
    two = _leader(4, set(), cap=3)
    assert capped_agreement([lead, *members, two], 3, one) == (True, 1)
    assert not split_pairs([lead, *members, two], 3, one)
    assert split_pairs([_leader(5, {6}, cap=3), two], 3, one) == {(4, 5)}, "2 + 1 fit under 3"
    # the split check times each pair of leaders of one group (every pair without a cap)
    three = [_leader(7, set(), cap=0), _leader(8, {9}, cap=0), _leader(10, set(), cap=0)]
    assert split_pairs(three, 0, one) == {(7, 8), (7, 10), (8, 10)}
    assert split_pairs(three, 0, lambda a: a % 2) == {(8, 10)}, "7 is in another group"
    assert split_pairs(three, 2, one) == {(7, 10)}, "only two swarms of one fit under 2"


def test_the_replay_command_names_the_cap() -> None:
    assert "--cap 10" in Scenario(agents=50, cap=10).command(7)
    assert "--cap" not in Scenario(agents=50).command(7)


# -- settings: the agent's flag and config key, the simulator's flag ---------------------


@pytest.mark.parametrize("value", ["1", "251", "-3"])
def test_swarm_agent_refuses_a_bad_cap_in_one_line(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--name", "a1", "--id", "3", "--zenoh-listen", "tcp/127.0.0.1:0", "--swarm-cap", value]
    assert agent_cmd.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"swarm agent: error: --swarm-cap {value}: 0 (no cap) or 2..250 agents"]


@pytest.mark.parametrize(
    "line,says",
    [
        ("swarm_cap = 300", "swarm_cap = 300: 0 (no cap) or 2..250 agents"),
        ('swarm_cap = "ten"', 'swarm_cap = "ten": a string, not an integer'),
        ("swarm_cap = true", "swarm_cap = true: true or false, not an integer"),
        ("swarm_cap = 1e400", "swarm_cap = inf"),
        ("swarm_cap = [10]", "swarm_cap = [10]"),
    ],
)
def test_a_hostile_swarm_cap_in_the_config_file_is_one_line_and_exit_2(
    line: str, says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "agent.toml"
    cfg.write_text(f'name = "a1"\nid = 3\nzenoh_listen = ["tcp/127.0.0.1:0"]\n{line}\n')
    assert agent_cmd.main(["--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err


@pytest.mark.parametrize("value", ["1", "300", "x"])
def test_swarm_simulate_refuses_a_bad_cap(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    try:
        code = simulate_cmd.main(["--cap", value])
    except SystemExit as exc:  # argparse's own: not a number
        code = exc.code
    assert code == 2
    assert "--cap" in capsys.readouterr().err


def test_swarm_simulate_runs_capped(capsys: pytest.CaptureFixture[str]) -> None:
    assert simulate_cmd.main(["--agents", "8", "--cap", "4", "--seeds", "1", "--loss", "0.05", "--json"]) == 0
    out = capsys.readouterr().out
    assert '"converged": 1' in out


def test_the_agent_config_carries_the_cap_to_its_core() -> None:
    from swarm.core.agent.node import AgentNode

    node = AgentNode(3, "a3", PAPER, rng=random.Random(1), cap=6)
    assert node.core.cap == 6
    assert AgentConfig(swarm_cap=6).swarm_cap == 6


# -- an explicit swarm name ----------------------------------------------------------------


def _named(me: int, name: str, cap: int = 0) -> Core:
    c = Core(me, swarm_name=name, cap=cap)
    c.start(0.0)
    return c


def test_a_named_agent_advertises_its_names_tag_and_an_unnamed_one_does_not() -> None:
    ad = _adverts(_named(3, "red").tick(1.0))[0]
    assert ad.flags & ADV_SWARM and ad.swarm == swarm_tag("red") != swarm_tag("blue")
    assert decode(encode(ad)) == ad
    assert not _adverts(Core(3).start(0.0))[0].flags & ADV_SWARM


def test_agents_of_different_names_never_pool() -> None:
    red, blue = _named(3, "red"), _named(4, "blue")
    red_ad, blue_ad = _adverts(red.tick(1.0))[0], _adverts(blue.tick(1.0))[0]
    assert red.handle(blue_ad, 0.1) == [] and blue.handle(red_ad, 0.1) == []
    assert red.handle(StartPool(4), 0.2) == [] and red.phase == Phase.IDLE, "a StartPool across names"
    unheard = _named(5, "red")
    assert unheard.handle(StartPool(9), 0.2) == [], "one not heard yet is not taken in"
    other_red = _named(6, "red")
    assert [o.msg for o in other_red.handle(red_ad, 0.3)] == [StartPool(6)]
    red.handle(_adverts(other_red.tick(1.0))[0], 0.3)
    out = red.handle(StartPool(6), 0.4)
    assert red.pool == {3, 6} and out[0].msg.status == PoolStatus.SUCCESS
    assert Core(7).handle(red_ad, 0.5) == [], "an unnamed agent does not ask a named one"


def test_leaders_of_different_names_never_merge_and_members_never_switch() -> None:
    red = _leader(1, {2}, cap=0)
    red.capped.tag = swarm_tag("red")
    red.handle(Advertize(9, "agent9", FLAG_LEADER | ADV_SWARM, 0, swarm_tag("blue")), 0.5)
    red.handle(Heartbeat(9, 0, 1, frozenset()), 1.0)
    assert set(red.members) == {2}, "a blue leader's swarm is not absorbed"
    m = _named(5, "red")
    m.handle(Advertize(1, "agent1", FLAG_LEADER | ADV_SWARM, 0, swarm_tag("red")), 0.1)
    m.handle(Advertize(9, "agent9", FLAG_LEADER | ADV_SWARM, 0, swarm_tag("blue")), 0.1)
    m.handle(Heartbeat(1, 0, 1, frozenset({5})), 1.0)
    m.handle(Heartbeat(9, 0, 1, frozenset({1, 5})), 1.5)
    assert m.leader == 1


def test_two_names_on_one_channel_form_two_swarms() -> None:
    sim = Sim(Scenario(agents=10, loss=0.05, cap=10), 2)
    for c in sim.cores:
        c.capped.tag = swarm_tag("red" if c.me % 2 else "blue")
    res = sim.run()
    assert res.violations == [] and res.elect_s is not None
    leaders = [c for c in sim.cores if c.phase == Phase.LEADER]
    assert len(leaders) == 2
    for lead in leaders:
        assert {m % 2 for m in lead.members} <= {lead.me % 2}, "one name per swarm"
        assert len(lead.members) == 4


@pytest.mark.parametrize(
    "what,raw",
    [
        ("flag without the tag", lambda p: p[:-1] + bytes([p[-1] | ADV_SWARM])),
        ("half a tag", lambda p: p[:-1] + bytes([p[-1] | ADV_SWARM, 7])),
        ("tag 0", lambda p: p[:-1] + bytes([p[-1] | ADV_SWARM, 0, 0])),
        ("a tag without the flag", lambda p: p + b"\x07\x00"),
        ("a tag and a byte more", lambda p: p[:-1] + bytes([p[-1] | ADV_SWARM, 7, 0, 1])),
    ],
)
def test_hostile_swarm_tags_are_one_decode_error(what: str, raw: object) -> None:
    plain = encode(Advertize(3, "agent3", FLAG_LEADER))
    with pytest.raises(DecodeError):
        decode(raw(plain))  # type: ignore[operator]


@pytest.mark.parametrize("name", ["a b", "x" * 17, "", "é"])
def test_a_bad_swarm_name_is_refused(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--name", "a1", "--id", "3", "--zenoh-listen", "tcp/127.0.0.1:0", "--swarm-name", name]
    assert agent_cmd.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--swarm-name" in err[0]
    with pytest.raises((ValueError, MessageError)):
        Core(3, swarm_name=name) if name else AgentConfig(swarm_name="a b")


def test_a_hostile_swarm_name_in_the_config_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "agent.toml"
    cfg.write_text('name = "a1"\nid = 3\nzenoh_listen = ["tcp/127.0.0.1:0"]\nswarm_name = "no/slash"\n')
    assert agent_cmd.main(["--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'swarm_name = "no/slash"' in err[0], err
