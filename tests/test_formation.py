"""V-formation geometry, the pilot's rules, and whole flights in virtual time (protocol
cores, pilots and PX4-like dynamics over the air model): the V forms and holds
through a route; it re-forms after a member is lost and after the leader is lost."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from swarm.core.flight.formation import (
    AgeEstimator,
    FormationConfig,
    Route,
    arms,
    assign,
    carried_motion,
    chain_of,
    chain_position,
    estimate_accel,
    follow_target,
    ne_between,
    offset,
    reconcile,
    slot_error,
    slot_offset,
)
from swarm.core.flight.pilot import Mode, Pilot, PilotConfig, Role
from swarm.core.wire.message_types import (
    AckResult,
    Assignment,
    Command,
    CommandKind,
    Phase,
    Pose,
    Side,
    Task,
    TaskKind,
)
from swarm.sim.flightsim import FlightScenario, FlightSim

HOME = Pose(47.397742, 8.545594, 508.0)


def at(n: float, e: float, *, alt: float = 508.0, vn: float = 0.0, ve: float = 0.0, t: float = 0.0) -> Pose:
    lat, lon = offset(HOME.lat, HOME.lon, n, e)
    return Pose(lat, lon, alt, 0.0, vn, ve, t % 2.56)


# -- geometry -------------------------------------------------------------------------


def test_slot_offsets_are_behind_and_to_the_side() -> None:
    assert slot_offset(0.0, Side.RIGHT, 10, 5) == pytest.approx((-10.0, 5.0))
    assert slot_offset(0.0, Side.LEFT, 10, 5) == pytest.approx((-10.0, -5.0))
    # facing east: behind is west, left is north
    assert slot_offset(90.0, Side.LEFT, 10, 5) == pytest.approx((5.0, -10.0))
    assert slot_offset(180.0, Side.RIGHT, 10, 5) == pytest.approx((10.0, -5.0))


@pytest.mark.parametrize("n", range(2, 11))
def test_assignments_make_two_balanced_chains(n: int) -> None:
    leader = 7
    members = [m for m in range(1, n + 1) if m != leader] if n >= 7 else list(range(1, n))
    if leader not in range(1, n + 1):
        leader = n
        members = list(range(1, n))
    a = assign(leader, members, 0.0)
    assert sorted(x.member for x in a) == sorted(members)  # everyone once, never the leader
    chains = arms(a, leader)
    left, right = chains[Side.LEFT], chains[Side.RIGHT]
    assert abs(len(left) - len(right)) <= 1 and len(right) >= len(left)
    for chain, side in ((left, Side.LEFT), (right, Side.RIGHT)):
        prev = leader
        for m in chain:
            x = next(y for y in a if y.member == m)
            assert x.follows == prev and x.side == side
            prev = m
    task = Task(TaskKind.FOLLOW, 0.0, 10, 5, a)
    assert max(chain_position(task, m) for m in members) == math.ceil(len(members) / 2)


def test_assignment_follows_where_members_are() -> None:
    # leader at the origin heading north; 2 and 4 are west of it, 3 and 5 east; 4 and 5 further back
    poses = {2: at(-5, -8), 4: at(-20, -15), 3: at(-5, 8), 5: at(-20, 15)}
    a = assign(1, poses, 0.0, poses, at(0, 0))
    chains = arms(a, 1)
    assert chains[Side.LEFT] == [2, 4] and chains[Side.RIGHT] == [3, 5]
    # facing south, the same agents are on the other sides
    b = arms(assign(1, poses, 180.0, poses, at(0, 0)), 1)
    assert set(b[Side.LEFT]) == {3, 5} and set(b[Side.RIGHT]) == {2, 4}


def test_reconcile_closes_the_chain_adds_newcomers_and_reassigns_for_a_new_leader() -> None:
    task = Task(TaskKind.FOLLOW, 0.0, 10, 5, assign(1, [2, 3, 4, 5, 6], 0.0))
    right = arms(task.assignments, 1)[Side.RIGHT]  # [2, 4, 6]
    gone = right[1]
    t2 = reconcile(task, 1, {2, 3, 4, 5, 6} - {gone})
    a = {x.member: x for x in t2.assignments}
    assert gone not in a and a[right[2]].follows == right[0]  # the chain closed up
    assert reconcile(t2, 1, {2, 3, 4, 5, 6} - {gone}) is t2  # nothing changed: same task
    t3 = reconcile(t2, 1, {2, 3, 4, 5, 6, 9} - {gone})
    assert arms(t3.assignments, 1)[Side.RIGHT][-1] == 9  # the shorter arm got the newcomer
    t4 = reconcile(t3, 5, {1, 2, 3, 4, 6, 9} - {gone})  # agent 5 leads now
    heads = {x.follows for x in t4.assignments} - {x.member for x in t4.assignments}
    assert heads == {5} and 5 not in {x.member for x in t4.assignments}
    assert reconcile(Task(TaskKind.HOLD), 1, {2}) == Task(TaskKind.HOLD)


def test_route_rounds_the_corner_and_is_continuous() -> None:
    r = Route([(0, 0), (100, 0), (100, 100)], turn_radius_m=20)
    assert r.length == pytest.approx(200 - 2 * 20 + 20 * math.pi / 2, abs=1e-6)
    prev = r.at(0)
    assert prev.heading_deg == pytest.approx(0.0)
    s = 0.0
    while s < r.length:
        s += 0.5
        p = r.at(s)
        assert math.hypot(p.n - prev.n, p.e - prev.e) <= 0.5 + 1e-6
        prev = p
    assert (prev.n, prev.e) == pytest.approx((100, 100)) and prev.heading_deg == pytest.approx(90.0)
    mid = r.at(80 + 5 * math.pi)  # half-way round the corner (a quarter circle of 20 m)
    assert mid.heading_deg == pytest.approx(45.0, abs=0.01)
    with pytest.raises(ValueError):
        Route([(0, 0), (0, 0)])


def test_follow_law_predicts_and_feeds_forward() -> None:
    cfg = FormationConfig(lead_s=0.0)
    lead = at(0, 0, vn=5.0)
    sp = follow_target(lead, 0.4, 0.0, Side.RIGHT, cfg)
    n, e = ne_between(HOME.lat, HOME.lon, sp.lat, sp.lon)
    assert (n, e) == pytest.approx((-10.0 + 2.0, 5.0), abs=0.01)  # 0.4 s at 5 m/s
    assert (sp.vn, sp.ve) == (5.0, 0.0) and sp.yaw_deg == 0.0
    # turning right at 10 deg/s: a right-side slot behind swings west-to-north... its velocity
    turning = follow_target(at(0, 0), 0.0, 0.0, Side.RIGHT, cfg, turn_rate_dps=10.0)
    w = math.radians(10.0)
    # w x r, led by the centripetal -w^2 r over the velocity loop's lag (accel_lead_s)
    c = w * w * cfg.accel_lead_s
    assert (turning.vn, turning.ve) == pytest.approx((-w * 5.0 + c * 10.0, w * -10.0 - c * 5.0))
    # the setpoint's own delay is predicted too
    later = follow_target(lead, 0.4, 0.0, Side.RIGHT, FormationConfig(lead_s=0.1))
    assert ne_between(HOME.lat, HOME.lon, later.lat, later.lon)[0] == pytest.approx(-7.5, abs=0.01)
    assert slot_error(at(-10, 5), at(0, 0), 0.0, Side.RIGHT, 10, 5) == pytest.approx(0.0, abs=1e-6)
    assert slot_error(at(-10, 8), at(0, 0), 0.0, Side.RIGHT, 10, 5) == pytest.approx(3.0, abs=1e-3)


def test_pose_age_from_wrapped_sample_times() -> None:
    est = AgeEstimator()
    clock_offset = 1000.37  # the sender's clock is far from ours
    for k, delay in enumerate([0.05, 0.30, 0.05, 0.55, 0.12]):
        sample = 10.0 + k * 0.25
        age = est.age(4, (sample + clock_offset) % 2.56, sample + delay)
        assert age == pytest.approx(delay - 0.05 if k else 0.0, abs=1e-6)


@pytest.mark.parametrize("offset_s", [k * 0.16 + 0.03 for k in range(16)])
def test_pose_age_whatever_the_two_clocks_are_modulo_the_wrap(offset_s: float) -> None:
    # two drones' clocks differ by anything modulo 2.56 s: the delays seen then straddle
    # the wrap for some offsets (2.45, then 0.14...); the ages must not depend on it
    # (they were 0 or 0.3 s short for a fifth of the offsets: metres at 5 m/s)
    est = AgeEstimator()
    delays = [0.05, 0.30, 0.05, 0.55, 0.12, 0.80, 0.40]
    for k, delay in enumerate(delays):
        sample = 10.0 + k * 0.25
        age = est.age(4, (sample + 1000.0 + offset_s) % 2.56, sample + delay)
        assert age == pytest.approx(delay - 0.05 if k else 0.0, abs=1e-6), (offset_s, k)


# -- the pilot's rules -----------------------------------------------------------------


def flying(me: int, n: float = 0.0, e: float = 0.0) -> Pilot:
    p = Pilot(me, PilotConfig())
    p.set_own(at(n, e, alt=528.0), True)
    p.hold("test")
    return p


def test_follow_is_refused_without_a_leader_by_a_member_and_with_a_bad_heading() -> None:
    p = flying(2)
    cmd = Command(255, 1, 0, CommandKind.FOLLOW, heading=90.0)
    assert p.command(cmd, Role(Phase.IDLE), 0.0)[:2] == (AckResult.NO_LEADER, "no leader elected yet")
    res, why, _ = p.command(cmd, Role(Phase.MEMBER, leader=1), 0.0)
    assert res == AckResult.REJECTED and "agent 1" in why
    lead = flying(1)
    bad = Command(255, 2, 0, CommandKind.FOLLOW, heading=400.0)
    assert lead.command(bad, Role(Phase.LEADER, 1, frozenset({2})), 0.0)[0] == AckResult.BAD_ARGUMENT
    res, _, _ = lead.command(cmd, Role(Phase.LEADER, 1, frozenset({2, 3})), 0.0)
    assert res == AckResult.ACCEPTED and lead.task.kind == TaskKind.FOLLOW and lead.task.heading == 90.0
    assert {a.member for a in lead.task.assignments} == {2, 3}
    on_ground = Pilot(3)
    assert (
        on_ground.command(Command(255, 3, 3, CommandKind.GOTO, 47.4, 8.5, 20.0), Role(Phase.MEMBER, 1), 0.0)[
            0
        ]
        == AckResult.REJECTED
    )
    assert (
        on_ground.command(Command(255, 4, 3, CommandKind.TAKEOFF, alt=500.0), Role(Phase.MEMBER, 1), 0.0)[0]
        == AckResult.BAD_ARGUMENT
    )


def member_following(me: int = 2) -> Pilot:
    p = flying(me, -10, 5)
    task = Task(TaskKind.FOLLOW, 0.0, 10, 5, (Assignment(me, 1, Side.RIGHT),), gen=1)
    p.on_task(task, 0.0)
    p.on_pose(1, at(0, 0, alt=528.0, t=0.0), 0.0)
    return p


def test_member_follows_then_holds_on_a_stale_pose_and_resumes() -> None:
    p = member_following()
    role = Role(Phase.MEMBER, 1)
    sp, _ = p.step(0.1, role)
    assert p.mode == Mode.FOLLOW and sp is not None
    assert ne_between(HOME.lat, HOME.lon, sp.lat, sp.lon) == pytest.approx((-10.0, 5.0), abs=0.05)
    p.set_own(at(-9, 5, alt=528.0), True)
    sp, _ = p.step(2.5, role)  # the leader's pose is 2.5 s old
    assert p.holding and "no fresh pose of agent 1" in " ".join(p.take_events())
    assert sp is not None
    assert ne_between(HOME.lat, HOME.lon, sp.lat, sp.lon) == pytest.approx((-9, 5), abs=0.05)
    p.on_pose(1, at(3, 0, alt=528.0, t=2.6), 2.6)
    sp, _ = p.step(2.7, role)
    assert not p.holding and sp is not None
    assert ne_between(HOME.lat, HOME.lon, sp.lat, sp.lon) == pytest.approx((-7.0, 5.0), abs=0.05)


def test_too_close_agents_both_hold_and_report_it() -> None:
    a, b = member_following(2), member_following(3)
    a.set_own(at(-10, 5, alt=528.0), True)
    b.set_own(at(-10, 6.5, alt=528.0), True)  # 1.5 m apart
    a.on_pose(3, b.own, 0.0)  # type: ignore[arg-type]
    b.on_pose(2, a.own, 0.0)  # type: ignore[arg-type]
    for p in (a, b):
        p.step(0.1, Role(Phase.MEMBER, 1))
        assert p.holding and p.too_close
        assert any("too close" in e for e in p.take_events())
    # an individual stop from the operator clears it (the operator is resolving it)
    stop = Command(255, 9, 2, CommandKind.STOP)
    assert a.command(stop, Role(Phase.MEMBER, 1), 0.2)[0] == AckResult.ACCEPTED
    assert not a.too_close and a.mode == Mode.HOLD


def test_two_agents_at_one_point_do_not_hold_each_other_for_ever() -> None:
    """Two copters started at one point (a real SITL pair: no sensor noise) used to hold
    each other for good: a setpoint may lead only away from a too-close agent, and at
    0 m no direction is away. There the higher id goes; the lower one too, unless it
    would follow the other's motion."""
    role = Role(Phase.MEMBER, 1)
    # the follower on its leader's very spot, its slot 10 m behind and 5 m to the side
    m = member_following(2)
    m.set_own(at(0, 0, alt=528.0), True)
    sp, _ = m.step(0.1, role)
    assert m.too_close and sp is not None
    assert ne_between(HOME.lat, HOME.lon, sp.lat, sp.lon) == pytest.approx((-10.0, 5.0), abs=0.05)
    # two members on one spot, each with a slot elsewhere
    a, b = member_following(2), member_following(3)
    for p in (a, b):
        p.set_own(at(-10, 5, alt=528.0), True)
    b.on_task(Task(TaskKind.FOLLOW, 0.0, 10, 5, (Assignment(3, 1, Side.LEFT),), gen=1), 0.0)
    a.on_pose(3, b.own, 0.0)  # type: ignore[arg-type]
    b.on_pose(2, a.own, 0.0)  # type: ignore[arg-type]
    sp_b, _ = b.step(0.1, role)
    assert sp_b is not None and ne_between(HOME.lat, HOME.lon, sp_b.lat, sp_b.lon) == pytest.approx(
        (-10.0, -5.0), abs=0.05
    )  # the higher id goes to its slot
    sp_a, _ = a.step(0.1, role)
    assert sp_a is not None and ne_between(HOME.lat, HOME.lon, sp_a.lat, sp_a.lon) == pytest.approx(
        (-10.0, 5.0), abs=0.05
    )  # the other is still: going anywhere parts them
    # the lower id does not follow the other's own way out (it would stay beside it)
    c = member_following(2)  # its slot 5 m east of here
    c.set_own(at(-10, 0, alt=528.0), True)
    c.on_pose(3, at(-10, 0.2, alt=528.0, ve=2.0, t=0.2), 0.2)  # agent 3, leaving east
    sp_c, _ = c.step(0.3, role)
    assert c.too_close and sp_c is not None
    assert ne_between(HOME.lat, HOME.lon, sp_c.lat, sp_c.lon) == pytest.approx((-10.0, 0.0), abs=0.05)


def test_a_failsafe_is_reported_and_a_command_takes_control_back_or_says_why_not() -> None:
    """After PX4's setpoint-loss failsafe the vehicle sat in AUTO.LOITER: a go-to was
    reported accepted and it moved 0 m, a take-off said "already flying". Now the
    pilot says the autopilot let go, and a go-to, stop or take-off takes control back
    first (a vehicle call, so the station hears the vehicle's result, not "accepted")."""
    role = Role(Phase.IDLE)
    p = flying(2, 0, 0)
    p.set_own(at(0, 0, alt=528.0), True, (HOME.lat, HOME.lon, 508.0))
    p.set_control(True, "OFFBOARD")
    assert p.control_lost == "" and not p.take_events()
    p.set_control(False, "AUTO.LOITER")  # the failsafe: one report may predate a switch just made
    assert p.control_lost == "" and not p.take_events()
    p.set_control(False, "AUTO.LOITER")
    assert p.control_lost == "AUTO.LOITER"
    said = " ".join(p.take_events())
    assert "left setpoint control by itself (now AUTO.LOITER)" in said and "takes control back" in said
    p.set_control(False, "AUTO.LOITER")
    assert not p.take_events()  # said once
    assert p.status()["control_lost"] == "AUTO.LOITER"
    goto = Command(255, 5, 2, CommandKind.GOTO, lat=HOME.lat + 2e-4, lon=HOME.lon, alt=20.0)
    res, why, calls = p.command(goto, role, 1.0)
    assert res == AckResult.ACCEPTED and [c.kind for c in calls] == ["control"] and "AUTO.LOITER" in why
    assert p.mode == Mode.GOTO  # the route is set; it flies once control is back
    p.call_done(calls[0], False, "mode OFFBOARD refused")
    assert p.control_lost == "AUTO.LOITER" and "failed" in " ".join(p.take_events())
    # a take-off in the air takes control back too, instead of "already flying"
    res, why, calls = p.command(Command(255, 6, 2, CommandKind.TAKEOFF, alt=10.0), role, 2.0)
    assert res == AckResult.ACCEPTED and [c.kind for c in calls] == ["control"], why
    p.call_done(calls[0], True)
    p.set_control(True, "OFFBOARD")
    assert p.control_lost == "" and "back under setpoint control" in " ".join(p.take_events())
    res, _, calls = p.command(goto, role, 3.0)
    assert res == AckResult.ACCEPTED and calls == []  # under control: nothing to take back
    # the failsafe lands it: on the ground there is nothing left to take back
    p.set_control(False, "AUTO.LOITER")
    p.set_control(False, "AUTO.LAND")
    assert p.control_lost == "AUTO.LAND"
    p.set_own(at(0, 0, alt=508.0), False)
    p.set_control(False, "AUTO.LAND")
    assert p.control_lost == "" and "landed under the autopilot's control" in " ".join(p.take_events())
    # a landing asked for, or a take-off under way, is not a failsafe
    q = flying(3, 0, 0)
    q.set_control(True, "OFFBOARD")
    q.command(Command(255, 7, 3, CommandKind.LAND), role, 4.0)
    q.set_control(False, "AUTO.LAND")
    q.set_control(False, "AUTO.LAND")
    assert q.control_lost == "" and "left setpoint control" not in " ".join(q.take_events())
    # on the ground there is nothing to take back: a take-off is a take-off
    g = Pilot(4)
    g.set_own(at(0, 0), False)
    g.set_control(False, "AUTO.LOITER")
    g.set_control(False, "AUTO.LOITER")
    assert g.control_lost == ""
    assert [c.kind for c in g.command(Command(255, 8, 4, CommandKind.TAKEOFF, alt=10.0), role, 5.0)[2]] == [
        "takeoff"
    ]


def test_swarm_stop_holds_everyone_and_a_new_follow_brings_members_back() -> None:
    lead = flying(1)
    role = Role(Phase.LEADER, 1, frozenset({2}))
    lead.command(Command(255, 1, 0, CommandKind.FOLLOW, heading=0.0), role, 0.0)
    m = member_following()
    m.on_task(lead.task, 0.5)
    m.step(0.6, Role(Phase.MEMBER, 1))
    assert m.mode == Mode.FOLLOW
    assert lead.command(Command(255, 2, 0, CommandKind.STOP), role, 1.0)[0] == AckResult.ACCEPTED
    assert lead.task.kind == TaskKind.HOLD and lead.mode == Mode.HOLD
    m.on_task(lead.task, 1.5)
    m.step(1.6, Role(Phase.MEMBER, 1))
    assert m.mode == Mode.HOLD and m.hold_reason == "swarm stop"
    lead.command(Command(255, 3, 0, CommandKind.FOLLOW, heading=0.0), role, 2.0)
    m.on_task(lead.task, 2.5)
    m.step(2.6, Role(Phase.MEMBER, 1))
    assert m.mode == Mode.FOLLOW


# -- flights in virtual time -------------------------------------------------------------


def test_five_agents_form_a_v_and_hold_it_through_the_route() -> None:
    sim = FlightSim(FlightScenario(agents=5, loss=0.1, pose_hz=4.0, leg_m=100.0), seed=11)
    r = sim.run_flight()
    assert r.ok, r.why
    assert r.rms_straight_m is not None and r.rms_straight_m < 1.5
    assert r.max_turn_m is not None and r.max_turn_m < 8.0
    assert len(r.per_member) == 4 and 0.0 < r.air_utilisation < 1.0


@pytest.mark.parametrize("victim", ["member", "leader"])
def test_the_v_re_forms_after_losing_a_member_or_the_leader(victim: str) -> None:
    fs = FlightScenario(agents=5, loss=0.1, pose_hz=4.0, leg_m=80.0, crash=(victim, 6.0), settle_s=25.0)
    sim = FlightSim(fs, seed=5)
    r = sim.run_flight()
    assert r.ok, r.why
    dead = sim.crashed
    lead = sim.cores[sim.leader - 1]
    assert sim.alive[sim.leader - 1] and lead.phase == Phase.LEADER and sim.leader != dead
    members = {a.member for a in lead.task.assignments}
    assert members == {k for k in range(1, 6) if k not in (dead, sim.leader)}
    heads = {a.follows for a in lead.task.assignments} - members
    assert heads == {sim.leader}
    # every survivor ends the flight in its slot
    tail = [e for t, _m, e, _h in sim.samples if t > r.end_s - 3.0]
    assert tail and max(tail) < 2.0


def test_take_off_holds_the_asked_altitude_not_where_the_take_off_returned() -> None:
    # the driver's take-off returns at 95 % of the height (9.5 m of 10): the hold that
    # follows must climb the last half metre, not keep the height it returned at
    p = Pilot(1)
    p.set_own(at(0, 0, alt=508.0), False)  # on the ground, 508 m AMSL
    res, _, calls = p.command(Command(255, 1, 1, CommandKind.TAKEOFF, alt=10.0), Role(Phase.IDLE), 0.0)
    assert res == AckResult.ACCEPTED and [c.kind for c in calls] == ["takeoff"]
    p.set_own(at(0.3, -0.2, alt=517.5), True)
    p.call_done(calls[0], True)
    sp, _ = p.step(0.1, Role(Phase.IDLE))
    assert p.mode == Mode.HOLD and sp is not None
    assert sp.alt == pytest.approx(518.0)
    assert ne_between(HOME.lat, HOME.lon, sp.lat, sp.lon) == pytest.approx((0.3, -0.2), abs=0.01)


def test_take_off_with_no_ground_altitude_known_holds_where_it_is() -> None:
    # an agent started in the air never saw its ground: it cannot know the height asked
    # for in AMSL, so it keeps the height it has (what it did before) rather than guess
    p = flying(1)
    p.command(Command(255, 1, 1, CommandKind.LAND), Role(Phase.IDLE), 0.0)
    _, _, calls = p.command(Command(255, 2, 1, CommandKind.TAKEOFF, alt=10.0), Role(Phase.IDLE), 1.0)
    p.call_done(calls[0], True)
    assert p.hold_at is not None and p.hold_at.alt == pytest.approx(p.own.alt)  # type: ignore[union-attr]


def test_the_swarm_heading_converges_to_the_routes_after_the_turn() -> None:
    # north 100 m, then east: after the turn the V must face east (90), not stop where
    # the leader arrived (73.7 degrees before the fix, 3.2 m off the slots)
    sim = FlightSim(FlightScenario(agents=5, loss=0.1, pose_hz=4.0, leg_m=100.0), seed=11)
    r = sim.run_flight()
    assert r.ok, r.why
    task = sim.cores[sim.leader - 1].task
    assert abs((task.heading - 90.0 + 180.0) % 360.0 - 180.0) <= 2.0, task.heading
    poses = {i + 1: sim.pose_of(i, r.end_s) for i in range(5)}
    for a in task.assignments:  # each member in its slot for the route's own heading
        err = slot_error(poses[a.member], poses[a.follows], 90.0, a.side, task.back_m, task.side_m)
        assert err < 1.5, (a, err)


def test_take_off_after_a_ground_pose_before_the_fix_holds_where_it_is() -> None:
    # real ArduPilot reports lat = lon = alt = 0 for seconds after boot: a ground altitude of
    # 0 m would make the hold after take-off dive for the sea; it is not trusted
    p = Pilot(1)
    p.set_own(Pose(0.0, 0.0, 0.0), False)
    _, _, calls = p.command(Command(255, 1, 1, CommandKind.TAKEOFF, alt=10.0), Role(Phase.IDLE), 0.0)
    p.set_own(at(0, 0, alt=517.5), True)
    p.call_done(calls[0], True)
    assert p.hold_at is not None and p.hold_at.alt == pytest.approx(517.5)


def test_acceleration_is_estimated_from_quantised_pose_velocities_and_wild_ones_are_not_believed() -> None:
    # speeding up north at 1 m/s^2, poses at 4 Hz with velocities in steps of 0.25 m/s
    hist = [(k * 0.25, math.floor(k * 0.25 * 4) / 4, 0.0) for k in range(9)]
    an, ae = estimate_accel(hist)
    assert an == pytest.approx(1.0, abs=0.3) and ae == 0.0
    assert estimate_accel(hist[:3]) == (0.0, 0.0)  # less than a second of poses
    assert estimate_accel([(0.0, 5.0, 0.0), (1.0, 5.0, 0.0)]) == (0.0, 0.0)  # steady
    assert estimate_accel([(0.0, 0.0, 0.0), (1.0, 20.0, 0.0)]) == (0.0, 0.0)  # 20 m/s^2: not believed


def test_follow_law_feeds_the_followed_acceleration_forward() -> None:
    cfg = FormationConfig()
    lead = at(0, 0, alt=528.0, vn=2.0)
    plain = follow_target(lead, 0.4, 0.0, Side.RIGHT, cfg)
    sp = follow_target(lead, 0.4, 0.0, Side.RIGHT, cfg, accel=(1.0, 0.0))
    dt = 0.4 + cfg.lead_s
    assert sp.vn == pytest.approx(2.0 + 1.0 * (dt + cfg.accel_lead_s))
    dn, _ = ne_between(plain.lat, plain.lon, sp.lat, sp.lon)
    assert dn == pytest.approx(0.5 * dt * dt, abs=0.01)


def test_a_member_down_an_arm_feeds_forward_the_leaders_motion_not_the_one_aheads() -> None:
    # chain 1 <- 3 <- 5 on the right arm: 5 follows 3's position but feeds forward the
    # leader's velocity carried to 3's place in the V, so 3's corrections are not passed on
    task = Task(
        TaskKind.FOLLOW, 0.0, 10, 5, (Assignment(3, 1, Side.RIGHT), Assignment(5, 3, Side.RIGHT)), gen=1
    )
    assert chain_of(task, 5) == (1, 2) and chain_of(task, 3) == (1, 1) and chain_of(task, 1) == (1, 0)
    p = flying(5, -20, 10)
    p.on_task(task, 0.0)
    p.on_pose(1, at(0, 0, alt=528.0, vn=5.0, t=0.0), 0.0)
    p.on_pose(3, at(-10, 5, alt=528.0, vn=8.5, t=0.0), 0.0)  # overshooting its own slot's speed
    sp, _ = p.step(0.0, Role(Phase.MEMBER, 1))
    assert sp is not None and (sp.vn, sp.ve) == pytest.approx((5.0, 0.0))
    # its position is still its slot behind 3 (3's position predicted at the leader's pace)
    lead_s = FormationConfig().lead_s
    n, e = ne_between(HOME.lat, HOME.lon, sp.lat, sp.lon)
    assert (n, e) == pytest.approx((-20.0 + 5.0 * lead_s, 10.0), abs=0.02)
    # the leader's pose stale: the one ahead's own motion, as before
    q = flying(5, -20, 10)
    q.on_task(task, 0.0)
    q.on_pose(1, at(0, 0, alt=528.0, vn=5.0, t=0.0), 0.0)
    q.on_pose(3, at(-10, 5, alt=528.0, vn=8.5, t=2.5), 2.5)
    sp, _ = q.step(2.5, Role(Phase.MEMBER, 1))
    assert sp is not None and sp.vn == pytest.approx(8.5)
    # the first of an arm follows the leader itself: unchanged
    m = flying(3, -10, 5)
    m.on_task(task, 0.0)
    m.on_pose(1, at(0, 0, alt=528.0, vn=5.0, t=0.0), 0.0)
    sp, _ = m.step(0.0, Role(Phase.MEMBER, 1))
    assert sp is not None and sp.vn == pytest.approx(5.0)


def test_the_carried_motion_turns_with_the_v_about_the_leader() -> None:
    # heading north, turning right at 10 deg/s: the point two slots down the right arm
    # (20 m back, 10 m right) moves as the rigid V does about the leader
    w = math.radians(10.0)
    (vn, ve), (an, ae) = carried_motion(at(0, 0, vn=5.0), (0.5, 0.0), 0.0, 10.0, 0.0, Side.RIGHT, 10, 5, 2)
    assert (vn, ve) == pytest.approx((5.0 - w * 10.0, w * -20.0))
    assert (an, ae) == pytest.approx((0.5 + w * w * 20.0, -w * w * 10.0))  # centripetal, to the leader
    assert carried_motion(at(0, 0, vn=5.0), (0.0, 0.0), 0.0, 0.0, 0.0, Side.LEFT, 10, 5, 1) == (
        (5.0, 0.0),
        (0.0, 0.0),
    )
    # the turn slowing at 3 deg/s^2: the tail's swing slows too
    _v, (an, ae) = carried_motion(at(0, 0), (0.0, 0.0), 0.0, 0.0, -3.0, Side.RIGHT, 10, 5, 2)
    al = math.radians(-3.0)
    assert (an, ae) == pytest.approx((-al * 10.0, al * -20.0))


def test_a_member_feeds_forward_the_turn_starting_and_stopping() -> None:
    # Heartbeats 0.8 s apart with the turn rate slowing 12 -> 9.5 deg/s: the member leads
    # its slot's swing by the velocity loop's lag; at rate 0 nothing more is fed forward
    p = member_following()
    role = Role(Phase.MEMBER, 1)
    task = p.task
    p.on_task(replace(task, turn_rate=12.0), 1.0)
    p.on_task(replace(task, turn_rate=9.5), 1.8)
    assert p.turn_accel == pytest.approx(-2.5 / 0.8)
    p.on_pose(1, at(0, 0, alt=528.0, t=1.8), 1.8)
    sp, _ = p.step(1.8, role)
    cfg = FormationConfig()
    plain = follow_target(at(0, 0, alt=528.0), 0.0, 0.0, Side.RIGHT, cfg, 10, 5, 9.5)
    assert sp is not None and sp.vn != pytest.approx(plain.vn)
    led = follow_target(
        at(0, 0, alt=528.0), 0.0, 0.0, Side.RIGHT, cfg, 10, 5, 9.5, turn_accel_dps2=-2.5 / 0.8
    )
    assert (sp.vn, sp.ve) == pytest.approx((led.vn, led.ve))
    # a duplicate Heartbeat 0.1 s later does not make an acceleration of quantisation steps
    p.on_task(replace(task, turn_rate=9.0), 1.9)
    assert p.turn_accel == pytest.approx(-2.5 / 0.8)
    # the turn over: rate 0, nothing fed forward, and a slowing turn is never led past 0
    p.on_task(replace(task, turn_rate=0.0), 2.6)
    assert p.swarm_turn_accel(0.0) == 0.0
    p.turn_accel = -20.0
    assert p.swarm_turn_accel(1.0) == pytest.approx(-1.0 / cfg.accel_lead_s)


def test_members_keep_their_slots_while_the_leader_speeds_up_and_slows_down() -> None:
    # the demo's 100 m legs: the straight samples include the leader's speed ramps, where
    # members following with velocity alone lagged 1.5 m behind (0.91 m RMS here before)
    r = FlightSim(FlightScenario(agents=5, loss=0.1, pose_hz=4.0, leg_m=100.0), seed=11).run_flight()
    assert r.ok, r.why
    assert r.rms_straight_m is not None and r.rms_straight_m < 0.7
    assert r.max_turn_m is not None and r.max_turn_m < 3.0
