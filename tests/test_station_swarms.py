"""Several swarms at the station (swarm.core.station.swarms, issue 16): the state's
``swarms`` (leader, members, a stable colour), commands to one swarm or to all, and
the hostile sender: a ``swarm`` field of any JSON value, a swarm that is not or no
longer there, a flood of leaders in AgentStates and Heartbeats. Pure core, virtual time.
"""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from swarm.core.station.commands import CommandRefused, CommandSpec, parse_command
from swarm.core.station.core import StationCore
from swarm.core.station.delta import apply, build
from swarm.core.station.model import StOut
from swarm.core.wire.codes import FLAG_FC_OK, mode_code
from swarm.core.wire.message_types import (
    AckResult,
    AgentState,
    Command,
    CommandAck,
    CommandKind,
    GSAdvertize,
    GSConnect,
    GSConnectAck,
    Heartbeat,
    Phase,
    Pose,
    Telemetry,
)

POSE = Pose(47.397, 8.545, 488.0, 90.0)
#: two swarms: agent 3 leads 1 and 2, agent 6 leads 4 and 5
TWO = {1: 3, 2: 3, 3: 3, 4: 6, 5: 6, 6: 6}


def tm(sender: int, leader: int = 0) -> Telemetry:
    phase = Phase.LEADER if leader == sender else Phase.MEMBER if leader else Phase.IDLE
    return Telemetry(sender, POSE, mode_code("POSCTL"), FLAG_FC_OK, phase, leader, 80, 180, 170, 0.0)


def station(leaders: dict[int, int]) -> StationCore:
    """Connected agents, each following ``leaders[id]`` (0: none)."""
    core = StationCore()
    for i, lead in leaders.items():
        out = core.handle(GSAdvertize(i, f"agent{i}"), 0.0)
        (c,) = [o.msg for o in out if isinstance(o.msg, GSConnect)]
        core.handle(GSConnectAck(i, c.seq, 1000), 0.0)
        core.handle(tm(i, lead), 0.0)
    core.take_events()
    return core


def cmds(out: list[StOut]) -> list[Command]:
    return [o.msg for o in out if isinstance(o.msg, Command)]


def sent(out: list[StOut]) -> list[tuple[int, int]]:
    """(to, Command.target) of each Command sent."""
    return [(o.to, o.msg.target) for o in out if isinstance(o.msg, Command)]


def refusal(body: Any) -> tuple[int, str]:
    with pytest.raises(CommandRefused) as exc:
        parse_command(body)
    return exc.value.status, exc.value.reason


def submit_refused(core: StationCore, spec: CommandSpec) -> tuple[int, str]:
    with pytest.raises(CommandRefused) as exc:
        core.submit(spec, 1.0)
    return exc.value.status, exc.value.reason


# -- the state ---------------------------------------------------------------------------
def test_two_swarms_in_the_state_with_their_members_and_colours() -> None:
    core = station(TWO)
    snap = core.snapshot(1.0)
    assert snap["swarms"] == [
        {"leader": 3, "members": [1, 2, 3], "colour": 0},
        {"leader": 6, "members": [4, 5, 6], "colour": 1},
    ]
    assert snap["leader"] == 6  # the largest swarm's (a tie: the highest id, as ever)
    assert json.loads(core.snapshot_json(1.0, {})) == {**snap, "station": {}}


def test_one_swarm_reads_as_before() -> None:
    core = station({1: 2, 2: 2, 3: 2})
    snap = core.snapshot(1.0)
    assert snap["leader"] == 2
    assert snap["swarms"] == [{"leader": 2, "members": [1, 2, 3], "colour": 0}]
    assert snap["swarm_tasks"] == {} and snap["swarm_slots"] == {}


def test_a_re_election_keeps_the_swarms_colour_and_a_new_swarm_takes_a_free_one() -> None:
    core = station(TWO)
    for i in (4, 5, 6):  # swarm 6 elects 5
        core.handle(tm(i, 5), 1.0)
    swarms = {s["leader"]: s for s in core.snapshot(1.0)["swarms"]}
    assert swarms[5] == {"leader": 5, "members": [4, 5, 6], "colour": 1}
    assert swarms[3]["colour"] == 0
    core.handle(tm(2, 2), 2.0)  # agent 2 leaves 3 and leads alone
    swarms = {s["leader"]: s for s in core.snapshot(2.0)["swarms"]}
    assert swarms[2]["colour"] == 2 and swarms[3]["members"] == [1, 3]


def test_the_leaders_heartbeat_list_adds_agents_that_name_no_other_leader() -> None:
    core = station({**TWO, 7: 0})
    core.handle(Heartbeat(3, 1, 1, frozenset({1, 2, 4, 7})), 1.0)  # 4 follows 6: its own word wins
    swarms = {s["leader"]: s["members"] for s in core.snapshot(1.0)["swarms"]}
    assert swarms == {3: [1, 2, 3, 7], 6: [4, 5, 6]}


def test_the_other_swarms_task_travels_apart_from_its_members() -> None:
    from swarm.core.wire.message_types import Assignment, Side, Task, TaskKind

    core = station(TWO)
    task = Task(TaskKind.FOLLOW, heading=90.0, assignments=(Assignment(1, 3, Side.LEFT),))
    core.handle(Heartbeat(3, 1, 1, frozenset({1, 2}), task), 1.0)
    old = core.snapshot(1.0)
    assert old["swarm_tasks"]["3"]["heading"] == 90.0 and old["swarm_slots"]["3"] == [[1, 3, -1]]
    core.handle(
        Heartbeat(3, 1, 2, frozenset({1, 2}), Task(TaskKind.FOLLOW, 92.0, assignments=task.assignments)), 1.1
    )
    new = core.snapshot(1.1)
    d = build(old, new)
    assert set(d["set"]) == {"time", "swarm_tasks"}  # a turn: the task, not the members
    assert apply(old, d) == new


# -- hostile senders -------------------------------------------------------------------
def test_a_flood_of_leaders_in_agent_states_is_bounded_by_the_connected_agents() -> None:
    core = station({1: 0, 2: 0})
    for i in range(1, 251):  # every id names another (or no such) leader
        core.handle(AgentState(i, Phase.MEMBER, leader=(i % 250) + 1), 1.0, f"x{i}")
        core.handle(AgentState(i, Phase.MEMBER, leader=10**6 + i), 1.0, f"x{i}")
    core.handle(Heartbeat(2, 1, 1, frozenset(range(-5, 400))), 1.0)
    snap = core.snapshot(1.0)
    # only agents 1 and 2 are connected: no swarm is led by an agent the station does not see
    assert len(snap["agents"]) == 250 and snap["swarms"] == []
    for i in (1, 2):  # now both lead themselves and list everyone
        core.handle(tm(i, i), 2.0)
        core.handle(Heartbeat(i, 1, 1, frozenset(range(-5, 400))), 2.0)
    swarms = core.snapshot(2.0)["swarms"]
    assert [s["leader"] for s in swarms] == [1, 2]
    listed = [m for s in swarms for m in s["members"]]
    assert len(listed) == len(set(listed)) and set(listed) <= set(range(1, 251))  # no agent twice


# -- the API's "swarm" field -----------------------------------------------------------------
@pytest.mark.parametrize(
    ("value", "shown"),
    [
        ("x" * 5000, "'xxxxxxxxxxxxxxxxxxxxxxxx'..."),
        (True, "True"),
        (None, "None"),
        (1.5, "of type float"),
        (float("nan"), "of type float"),
        (10**400, "a number of more than 15 digits"),
        (-1, "-1"),
        (0, "0"),
        (251, "251"),
        ([3], "of type list"),
        ({"leader": 3}, "of type dict"),
    ],
)
def test_a_swarm_that_is_no_leader_id_is_refused_in_one_line(value: Any, shown: str) -> None:
    status, reason = refusal({"target": "swarm", "kind": "land", "swarm": value})
    assert status == 400 and "\n" not in reason and len(reason) < 120
    assert reason == f'swarm {shown}: its leader\'s agent id (1..250) or "all"'


def test_a_swarm_field_on_an_agents_command_is_refused() -> None:
    assert refusal({"target": 3, "kind": "land", "swarm": 3}) == (
        400,
        "'swarm' goes with target \"swarm\", not with one agent",
    )


def test_all_is_every_swarm_and_a_leader_id_one_swarm() -> None:
    assert parse_command({"target": "swarm", "kind": "land", "swarm": "all"}).swarm is None
    assert parse_command({"target": "swarm", "kind": "land", "swarm": 6}) == CommandSpec(
        None, CommandKind.LAND
    ).for_swarm(6)


def test_a_swarm_that_is_not_one_or_vanished_is_refused_before_anything_is_sent() -> None:
    core = station(TWO)
    assert submit_refused(core, CommandSpec(None, CommandKind.LAND).for_swarm(2)) == (
        400,
        "no swarm led by agent 2 now (2 swarms led by 3, 6)",
    )
    core.tick(20.0)  # every agent silent: disconnected, no swarm left
    assert submit_refused(core, CommandSpec(None, CommandKind.STOP).for_swarm(6)) == (
        400,
        "no swarm led by agent 6 now (no swarm)",
    )


# -- commands to one swarm or to all ---------------------------------------------------------
def test_follow_to_every_swarm_is_refused_and_to_one_goes_to_its_leader() -> None:
    core = station(TWO)
    status, reason = submit_refused(core, CommandSpec(None, CommandKind.FOLLOW, heading=90.0))
    assert status == 409 and reason.startswith("follow goes to one swarm (2 swarms led by 3, 6)")
    _, out = core.submit(CommandSpec(None, CommandKind.FOLLOW, heading=90.0).for_swarm(6), 1.0)
    assert sent(out) == [(6, 0)]


def test_land_to_one_swarm_reaches_only_its_members_with_results_per_swarm() -> None:
    core = station(TWO)
    req, out = core.submit(CommandSpec(None, CommandKind.LAND).for_swarm(3), 1.0)
    assert sent(out) == [(1, 1), (2, 2), (3, 3)]
    for c in cmds(out):
        core.handle(CommandAck(c.target, c.seq, AckResult.ACCEPTED), 1.2)
    body = req.body()
    assert body["ok"] and body["swarms"] == [{"swarm": 3, "ok": True, "agents": [1, 2, 3]}]
    assert {r["of_swarm"] for r in body["results"]} == {3}


def test_stop_to_every_swarm_goes_to_each_leader_and_every_agent() -> None:
    core = station({**TWO, 7: 0})
    req, out = core.submit(CommandSpec(None, CommandKind.STOP), 1.0)
    assert sent(out) == [(3, 0), (6, 0)] + [(i, i) for i in range(1, 8)]
    for o in out:
        if isinstance(o.msg, Command) and o.to != 5:
            core.handle(CommandAck(o.to, o.msg.seq, AckResult.ACCEPTED), 1.2)
    core.tick(14.0)  # agent 5 never answers
    body = req.body()
    assert body["swarms"] == [
        {"swarm": 0, "ok": True, "agents": [7]},  # in no swarm
        {"swarm": 3, "ok": True, "agents": [1, 2, 3]},
        {"swarm": 6, "ok": False, "agents": [4, 5, 6]},
    ]


def test_a_swarm_command_follows_its_members_new_leader() -> None:
    core = station(TWO)
    req, out = core.submit(CommandSpec(None, CommandKind.FOLLOW, heading=45.0).for_swarm(6), 1.0)
    (seq,) = [c.seq for c in cmds(out)]
    for i in (4, 5, 6):  # swarm 6 elects 5; swarm 3 is untouched
        core.handle(tm(i, 5), 1.2)
    retry = core.tick(1.3)
    assert [(o.to, o.msg.seq, o.msg.target) for o in retry if isinstance(o.msg, Command)] == [(5, seq, 0)]
    core.handle(CommandAck(5, seq, AckResult.ACCEPTED), 1.4)
    assert req.body()["results"] == [
        {"agent": 5, "result": "ACCEPTED", "reason": "", "swarm": True, "of_swarm": 6}
    ]


def test_the_log_names_the_swarms_when_their_leaders_change() -> None:
    core = station({1: 3, 2: 3, 3: 3})
    assert [e.text for e in core.events if e.kind == "leader"] == ["agent3 (3) is the leader"]
    core = station(TWO)
    assert [e.text for e in core.events if e.kind == "leader"][-2:] == [
        "2 swarms: agent3 (3) with 3, agent6 (6) with 3",  # agent6 connects: its followers are a swarm
        "agent6 (6) is the leader",  # then it says it leads: 3 against 3, the higher id
    ]

    def news() -> list[str]:
        return [e.text for e in core.events if e.kind == "leader" and " swarm" in e.text]

    for i in (4, 5):
        core.handle(tm(i, 3), 1.0)  # swarm 6 joins 3; 6 leads alone: the same two leaders
    assert news() == ["2 swarms: agent3 (3) with 3, agent6 (6) with 3"]
    core.handle(tm(6, 3), 1.0)
    assert news()[-1] == "1 swarm: agent3 (3) with 6"


# -- one colour per swarm across stations (fleet_colours) ----------------------------------


def _swarms(spec: dict[str, list[int]]) -> list[dict[str, Any]]:
    """Each station's swarms with its own colours 0, 1, ... (leader ids made up)."""
    out = []
    for k, (station, colours) in enumerate(sorted(spec.items())):
        out += [{"station": station, "leader": 10 * k + c + 1, "colour": c} for c in colours]
    return out


def test_two_stations_own_colour_0_swarms_get_distinct_colours_the_same_on_every_page() -> None:
    from swarm.core.station.swarms import fleet_colours

    merged = _swarms({"gcsA": [0, 1], "gcsB": [0], "gcsC": [0, 1, 2]})
    got = {(s["station"], s["leader"]): s["colour"] for s in fleet_colours(merged)}
    assert len(set(got.values())) == len(merged)
    # every page: the same swarms in another order, the same colours
    for order in (merged[::-1], merged[2:] + merged[:2], sorted(merged, key=lambda s: -s["leader"])):
        assert {(s["station"], s["leader"]): s["colour"] for s in fleet_colours(order)} == got
    # a re-election (a new leader, the station's own colour kept): the same colour everywhere
    again = [{**s, "leader": 99} if s["leader"] == 1 else s for s in merged]
    assert {s["leader"]: s["colour"] for s in fleet_colours(again)}[99] == got[("gcsA", 1)]
    # the station's own colour stays beside the merged one; the input is not changed
    assert {s["station_colour"] for s in fleet_colours(merged)} == {0, 1, 2}
    assert "station_colour" not in merged[0]


def test_a_stations_swarm_keeps_its_colour_when_another_stations_swarm_appears() -> None:
    from swarm.core.station.swarms import PALETTE, fleet_colours

    alone = fleet_colours(_swarms({"gcsA": [0, 1]}))
    both = fleet_colours(_swarms({"gcsA": [0, 1], "gcsB": [0]}))
    # the first swarms choose first: A's colour-0 swarm keeps its colour beside B's
    assert alone[0]["colour"] == both[0]["colour"]
    assert all(0 <= s["colour"] < PALETTE for s in both)


@given(
    st.dictionaries(
        st.text("abcdefgh", min_size=1, max_size=6),
        st.lists(st.integers(0, 40), max_size=12, unique=True),
        max_size=6,
    )
)
def test_colours_are_always_distinct_beyond_the_palette_too(spec: dict[str, list[int]]) -> None:
    from swarm.core.station.swarms import PALETTE, fleet_colours

    merged = _swarms(spec)
    colours = [s["colour"] for s in fleet_colours(merged)]
    assert len(set(colours)) == len(colours) and all(c >= 0 for c in colours)
    assert all(c < PALETTE for c in colours) or len(colours) > PALETTE  # beyond only when full
    # swarms without a station colour (an older core: none) are numbered too
    bare = [{"station": s["station"], "leader": s["leader"]} for s in merged]
    colours = [s["colour"] for s in fleet_colours(bare)]
    assert len(set(colours)) == len(colours)
