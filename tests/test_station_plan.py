"""What the station keeps of the plan (swarm.core.station.plan, through StationCore):
routes and go-to targets set by GOTO, extended by WAYPOINT, replaced, cleared on
"arrived", on STOP and on a refusal; other stations' commands heard; the leader's
task and slots from its Heartbeat; home positions; hostile commands ignored."""

from __future__ import annotations

import json

from test_gcs_station import station_with, tm

from swarm.core.station.commands import CommandSpec
from swarm.core.station.core import StationCore
from swarm.core.station.delta import apply, build
from swarm.core.station.plan import ROUTE_MAX, PlanBook
from swarm.core.wire.message_types import (
    AckResult,
    AgentNotice,
    Assignment,
    Command,
    CommandAck,
    CommandKind,
    Heartbeat,
    NoticeSource,
    Phase,
    Pose,
    Side,
    Task,
    TaskKind,
)


def goto(
    core: StationCore, agent: int, lat: float, lon: float, alt: float = 20.0, now: float = 1.0
) -> Command:
    _, out = core.submit(CommandSpec(agent, CommandKind.GOTO, lat=lat, lon=lon, alt=alt), now)
    (o,) = out
    assert isinstance(o.msg, Command)
    return o.msg


def route(core: StationCore, agent: int) -> object:
    return core.snapshot(5.0)["agents"][[a.id for a in core.agents.values()].index(agent)].get("route")


def arrived(agent: int) -> AgentNotice:
    return AgentNotice(agent, NoticeSource.AGENT, 6, "arrived: holding")


def test_goto_sets_the_target_waypoints_extend_and_arrival_clears() -> None:
    core = station_with(3, 4)
    goto(core, 3, 47.398, 8.546)
    assert route(core, 3) == [[47.398, 8.546, 20.0]]
    assert route(core, 4) is None
    core.submit(CommandSpec(3, CommandKind.WAYPOINT, lat=47.399, lon=8.547, alt=25.0), 1.5)
    assert route(core, 3) == [[47.398, 8.546, 20.0], [47.399, 8.547, 25.0]]
    # a new GOTO replaces the route
    goto(core, 3, 47.3975, 8.5455, 30.0, now=2.0)
    assert route(core, 3) == [[47.3975, 8.5455, 30.0]]
    # an autopilot's "arrived"-like text is not the agent's own notice
    core.handle(AgentNotice(3, NoticeSource.AUTOPILOT, 4, "arrived somewhere"), 3.0)
    assert route(core, 3) is not None
    core.handle(arrived(4), 3.0)  # another agent's arrival
    assert route(core, 3) is not None
    core.handle(arrived(3), 3.1)
    assert route(core, 3) is None
    assert json.loads(json.dumps(core.snapshot(5.0))) == core.snapshot(5.0)


def test_stop_ends_routes_and_a_refused_goto_is_not_drawn() -> None:
    core = station_with(3, 4, leader=3)
    goto(core, 3, 47.398, 8.546)
    goto(core, 4, 47.399, 8.546)
    core.submit(CommandSpec(4, CommandKind.STOP), 1.2)
    assert route(core, 4) is None and route(core, 3) is not None
    core.submit(CommandSpec(None, CommandKind.STOP), 1.3)  # the swarm's STOP: every route
    assert route(core, 3) is None
    cmd = goto(core, 4, 47.3985, 8.546, now=2.0)
    core.handle(CommandAck(4, cmd.seq, AckResult.REJECTED, "outside the fence"), 2.2)
    core.take_finished()
    assert route(core, 4) is None
    # refused waypoint: only its point goes
    goto(core, 4, 47.3985, 8.546, now=3.0)
    _, out = core.submit(CommandSpec(4, CommandKind.WAYPOINT, lat=47.3986, lon=8.546, alt=20.0), 3.1)
    core.handle(CommandAck(4, out[0].msg.seq, AckResult.BAD_ARGUMENT, "no"), 3.2)
    core.take_finished()
    assert route(core, 4) == [[47.3985, 8.546, 20.0]]


def test_other_stations_commands_heard_and_hostile_ones_ignored() -> None:
    core = station_with(3)
    core.handle(Command(252, 9, 3, CommandKind.GOTO, 47.4, 8.55, 15.0), 1.0)
    assert route(core, 3) == [[47.4, 8.55, 15.0]]
    core.handle(Command(252, 10, 3, CommandKind.WAYPOINT, 47.401, 8.55, 15.0), 1.1)
    core.handle(Command(252, 10, 3, CommandKind.WAYPOINT, 47.401, 8.55, 15.0), 1.2)  # a retry heard
    assert route(core, 3) == [[47.4, 8.55, 15.0], [47.401, 8.55, 15.0]]
    before = route(core, 3)
    core.handle(Command(7, 11, 3, CommandKind.GOTO, 47.5, 8.6, 15.0), 1.3)  # an agent is no station
    core.handle(Command(255, 11, 3, CommandKind.GOTO, 47.5, 8.6, 15.0), 1.3)  # our own id: submit's
    core.handle(Command(252, 12, 3, CommandKind.GOTO_AMSL, 47.5, 8.6, 500.0), 1.3)  # refused kind
    core.handle(Command(252, 13, 3, CommandKind.GOTO, 0.0, 0.0, 15.0), 1.3)  # no position
    core.handle(Command(252, 14, 0, CommandKind.GOTO, 47.5, 8.6, 15.0), 1.3)  # no agent
    assert route(core, 3) == before
    book = PlanBook()
    for i in range(ROUTE_MAX + 10):
        book.command(Command(252, i, 9, CommandKind.WAYPOINT, 47.0 + i / 1e4, 8.0, 10.0))
    assert len(book.routes[9]) == ROUTE_MAX and book.routes[9][-1][0] == round(47.0 + 41 / 1e4, 7)
    book.command(Command(252, 1, 9, CommandKind.GOTO, float("nan"), 8.0, 10.0))
    assert len(book.routes[9]) == ROUTE_MAX


def test_the_leaders_task_and_slots_and_home() -> None:
    core = station_with(3, 4, 5, leader=3)
    task = Task(
        TaskKind.FOLLOW,
        heading=90.3,
        back_m=10.0,
        side_m=5.0,
        assignments=(Assignment(5, 3, Side.RIGHT), Assignment(4, 3, Side.LEFT)),
    )
    snap = core.snapshot(1.0)
    assert snap["task"] is None and snap["slots"] is None
    core.handle(Heartbeat(3, 1, 7, frozenset({4, 5}), task), 1.0)
    snap = core.snapshot(1.0)
    assert snap["task"] == {"leader": 3, "heading": 90.5, "back": 10.0, "side": 5.0}
    assert snap["slots"] == [[4, 3, -1], [5, 3, 1]]
    full = json.loads(core.snapshot_json(1.0, {}))
    assert full["task"] == snap["task"] and full["slots"] == snap["slots"]
    # another agent's Heartbeat (not the leader's) is kept but not shown
    core.handle(Heartbeat(4, 1, 7, frozenset(), Task(TaskKind.FOLLOW, heading=10.0)), 1.1)
    assert core.snapshot(1.1)["task"]["leader"] == 3
    core.handle(Heartbeat(3, 1, 8, frozenset({4, 5}), Task(TaskKind.HOLD)), 1.2)
    assert core.snapshot(1.2)["task"] is None and core.snapshot(1.2)["slots"] is None
    # home: where Telemetry shows the vehicle on the ground with its flight controller
    from swarm.core.wire.codes import FLAG_FC_OK

    core.handle(tm(4, pose=Pose(47.3971, 8.5451, 488.0), phase=Phase.MEMBER, leader=3, flags=FLAG_FC_OK), 1.3)
    a4 = next(a for a in core.snapshot(1.3)["agents"] if a["id"] == 4)
    assert a4["home"] == [47.3971, 8.5451] and a4["home_alt"] == 488.0


def test_plan_fields_travel_in_small_deltas() -> None:
    core = station_with(3, 4, leader=3)
    hb = Heartbeat(
        3,
        1,
        7,
        frozenset({4}),
        Task(TaskKind.FOLLOW, heading=90.0, assignments=(Assignment(4, 3, Side.LEFT),)),
    )
    core.handle(hb, 1.0)
    old = core.snapshot(1.0)
    core.handle(
        Heartbeat(
            3, 1, 8, frozenset({4}), Task(TaskKind.FOLLOW, heading=92.0, assignments=hb.task.assignments)
        ),
        1.1,
    )
    new = core.snapshot(1.0)
    d = build(old, new)
    assert d == {
        "set": {"task": {"leader": 3, "heading": 92.0, "back": 10.0, "side": 5.0}}
    }  # slots unchanged
    assert apply(old, d) == new
    goto(core, 4, 47.398, 8.546)
    d = build(new, core.snapshot(1.0))
    assert d["agents"] == {"4": {"route": [[47.398, 8.546, 20.0]]}}
    old = core.snapshot(1.0)
    core.handle(AgentNotice(4, NoticeSource.AGENT, 6, "arrived: holding"), 1.5)
    d = build(old, core.snapshot(1.0))
    assert d["agents"]["4"]["unset"] == ["route"]  # gone, not a null on every agent
    assert apply(old, d) == core.snapshot(1.0)
