"""The station's protocol core in virtual time: advertising, connecting with retries,
heartbeats, heartbeat loss -> disconnect -> reconnect (also against the real agent-side
core, swarm.core.agent.gslink, over a lossy fake channel), command acks, retries, dedupe and
refusals, the leader, trails, and the passive (replay) mode."""

from __future__ import annotations

import json
import random
from typing import Any

import pytest

from swarm.core.agent.gslink import GsConfig, GsLink
from swarm.core.station.commands import NO_ANSWER, CommandRefused, CommandSpec, parse_command
from swarm.core.station.core import StationCore
from swarm.core.station.model import StationConfig, StOut
from swarm.core.wire.codes import FLAG_ARMED, FLAG_FC_OK, mode_code
from swarm.core.wire.message_types import (
    AckResult,
    AgentState,
    Command,
    CommandAck,
    CommandKind,
    GSAdvertize,
    GSConnect,
    GSConnectAck,
    GSHeartbeat,
    Phase,
    Pose,
    PoseReport,
    Telemetry,
)
from swarm.core.wire.messages import decode, encode

POSE = Pose(47.397, 8.545, 488.0, 90.0)


def msgs(outs: list[StOut], cls: type) -> list[StOut]:
    return [o for o in outs if isinstance(o.msg, cls)]


def tm(
    sender: int,
    *,
    pose: Pose = POSE,
    phase: Phase = Phase.IDLE,
    leader: int = 0,
    flags: int = 0,
    battery: int = 255,
) -> Telemetry:
    return Telemetry(sender, pose, mode_code("POSCTL"), flags, phase, leader, battery, 180, 170, 2.5)


def connect(core: StationCore, agent: int, now: float, hb_ms: int = 500) -> None:
    out = core.handle(GSAdvertize(agent, f"agent{agent}"), now)
    (c,) = msgs(out, GSConnect)
    core.handle(GSConnectAck(agent, c.msg.seq, hb_ms), now)
    assert core.agents[agent].connected


def test_station_advertises_every_second_and_ignores_stations() -> None:
    core = StationCore("gcs", 255)
    times = [t / 10 for t in range(0, 35) if msgs(core.tick(t / 10), GSAdvertize)]
    assert times == [0.0, 1.0, 2.0, 3.0]
    ad = msgs(core.tick(4.0), GSAdvertize)[0]
    assert ad.to == 0 and ad.msg == GSAdvertize(255, "gcs")
    assert core.handle(GSAdvertize(255, "gcs"), 4.0) == []  # our own echo
    assert core.handle(GSAdvertize(252, "other"), 4.0) == []  # another station
    assert core.agents == {}
    with pytest.raises(ValueError):
        StationCore("gcs", 7)  # not a station id


def test_connect_retries_with_the_same_seq_until_acked_then_heartbeats() -> None:
    core = StationCore()
    core.tick(0.0)
    out = core.handle(GSAdvertize(3, "agent3"), 0.5)
    (c,) = msgs(out, GSConnect)
    assert (c.to, c.name) == (3, "agent3") and c.msg.sender == 255
    retries = []
    t = 0.6
    while t < 3.05:
        retries += [(round(t, 1), o.msg.seq) for o in msgs(core.tick(t), GSConnect)]
        t += 0.1
    assert retries == [(1.5, c.msg.seq), (2.5, c.msg.seq)]
    # an ack with another seq (a stale attempt) does not connect
    core.handle(GSConnectAck(3, c.msg.seq + 7, 500), 2.6)
    assert not core.agents[3].connected and core.counters.stale_connect_acks == 1
    core.handle(GSConnectAck(3, c.msg.seq, 500), 2.7)
    a = core.agents[3]
    assert a.connected and a.hb_interval == 0.5
    assert [e.kind for e in core.take_events()] == ["connect"]
    hbs = []
    t = 2.7
    while t < 6.0:
        out = core.tick(t)
        assert not msgs(out, GSConnect), "no connect once connected"
        hbs += [o.msg.seq for o in msgs(out, GSHeartbeat) if o.to == 3]
        core.handle(tm(3), t)  # the agent's Telemetry keeps the connection
        t += 0.1
    assert hbs == [1, 2, 3]  # one per second, in the rounds at 3, 4 and 5 s


def test_heartbeat_loss_disconnects_and_advertising_reconnects() -> None:
    core = StationCore()
    connect(core, 3, 0.0, hb_ms=500)  # timeout max(2, 1.5) = 2 s
    connect(core, 4, 0.0, hb_ms=1000)  # timeout 3 s
    core.take_events()
    t, dropped = 0.0, {}
    while t < 10.0:
        if t < 1.0:
            core.handle(tm(3), t)
            core.handle(tm(4), t)
        core.tick(t)
        for e in core.take_events():
            assert e.kind == "disconnect"
            dropped[e.text.split()[0]] = t
        t = round(t + 0.05, 2)
    assert set(dropped) == {"agent3", "agent4"}
    assert 2.9 < dropped["agent3"] <= 3.05  # last Telemetry at 0.95 + 2 s
    assert 3.9 < dropped["agent4"] <= 4.05  # + 3 s
    assert not core.agents[3].connected and core.agents[3].pose == POSE  # kept for the map
    # advertising again starts a new connection (new seq)
    (c,) = msgs(core.handle(GSAdvertize(3, "agent3"), 10.0), GSConnect)
    core.handle(GSConnectAck(3, c.msg.seq, 500), 10.1)
    assert core.agents[3].connected
    assert [e.text for e in core.take_events()] == ["agent3 (3) connected again"]


def test_telemetry_from_a_known_unconnected_agent_reconnects_it() -> None:
    core = StationCore()
    assert core.handle(tm(9), 0.0) == []  # no name yet: nothing to answer to
    assert core.counters.unknown_agent == 1
    connect(core, 3, 0.0)
    core.tick(5.0)  # silent: dropped
    assert not core.agents[3].connected
    assert [o.msg.sender for o in msgs(core.handle(tm(3), 5.1), GSConnect)] == [255]


def test_connect_attempts_stop_when_the_agent_is_gone() -> None:
    core = StationCore(config=StationConfig(connect_give_up=3.0))
    core.handle(GSAdvertize(3, "agent3"), 0.0)
    sent = [t / 10 for t in range(1, 100) if msgs(core.tick(t / 10), GSConnect)]
    assert sent == [1.0, 2.0, 3.0]  # then nothing heard for 3 s: gives up
    assert msgs(core.handle(GSAdvertize(3, "agent3"), 10.0), GSConnect)


class Channel:
    """Station core <-> agent cores (swarm.core.agent.gslink) with seeded loss, in virtual time."""

    def __init__(self, core: StationCore, agents: list[GsLink], loss: float, seed: int) -> None:
        self.core = core
        self.agents = {g.me: g for g in agents}
        self.loss = loss
        self.rng = random.Random(seed)
        self.up = dict.fromkeys(self.agents, True)

    def lost(self) -> bool:
        return self.rng.random() < self.loss

    def step(self, now: float) -> None:
        for o in self.core.tick(now):
            targets = list(self.agents) if o.to == 0 else [o.to]
            for aid in targets:
                if self.up[aid] and not self.lost():
                    for back in self.agents[aid].handle(decode(encode(o.msg)), now):
                        self.deliver(back.msg, now)
        for aid, g in self.agents.items():
            if not self.up[aid]:
                continue
            for o in g.tick(now, lambda aid=aid: tm(aid)):  # type: ignore[misc]
                self.deliver(o.msg, now)

    def deliver(self, msg: Any, now: float) -> None:
        if not self.lost():
            for o in self.core.handle(decode(encode(msg)), now):
                g = self.agents[o.to]
                if self.up[o.to] and not self.lost():
                    for back in g.handle(o.msg, now):
                        self.deliver(back.msg, now)


@pytest.mark.parametrize("seed", range(5))
def test_against_the_agent_side_core_with_loss_crash_and_restart(seed: int) -> None:
    core = StationCore()
    agents = [GsLink(i, f"agent{i}", GsConfig(hb_interval=0.5)) for i in (1, 2, 3)]
    ch = Channel(core, agents, loss=0.2, seed=seed)
    t = 0.0

    def run_until(pred: Any, limit: float) -> None:
        nonlocal t
        end = t + limit
        while not pred():
            assert t < end, f"not reached by t={t:.1f}: {[e.text for e in core.events]}"
            ch.step(t)
            t = round(t + 0.05, 2)

    run_until(lambda: all(a.connected for a in core.agents.values()) and len(core.agents) == 3, 15)
    ch.up[2] = False  # agent 2 dies
    run_until(lambda: not core.agents[2].connected, 5)
    assert core.agents[1].connected and core.agents[3].connected
    agents[1] = fresh = GsLink(2, "agent2", GsConfig(hb_interval=0.5))  # restarted process
    ch.agents[2] = fresh
    ch.up[2] = True
    run_until(lambda: core.agents[2].connected, 15)
    kinds = [(e.kind, e.text) for e in core.events if "agent2" in e.text]
    assert kinds == [
        ("connect", "agent2 (2) connected"),
        ("disconnect", kinds[1][1]),
        ("connect", "agent2 (2) connected again"),
    ]


# -- commands ------------------------------------------------------------------------


def station_with(*ids: int, leader: int = 0) -> StationCore:
    core = StationCore()
    for i in ids:
        connect(core, i, 0.0)
        if leader:
            core.handle(tm(i, phase=Phase.LEADER if i == leader else Phase.MEMBER, leader=leader), 0.0)
    core.take_events()
    return core


def test_command_is_acked_and_a_duplicate_ack_is_dropped() -> None:
    core = station_with(3)
    req, out = core.submit(CommandSpec(3, CommandKind.TAKEOFF, alt=10.0), 1.0)
    (o,) = out
    assert o.to == 3 and o.name == "agent3"
    assert o.msg == Command(255, o.msg.seq, 3, CommandKind.TAKEOFF, alt=10.0)
    assert decode(encode(o.msg)) == o.msg
    assert not req.done
    core.handle(CommandAck(3, o.msg.seq, AckResult.ACCEPTED), 1.2)
    assert req.done and req.status == 200
    assert req.body() == {
        "ok": True,
        "request": req.id,
        "results": [{"agent": 3, "result": "ACCEPTED", "reason": ""}],
    }
    assert core.take_finished() == [req]
    core.handle(CommandAck(3, o.msg.seq, AckResult.ACCEPTED), 1.3)  # answer to a retry
    assert core.counters.duplicate_acks == 1
    assert [e.text for e in core.take_events()] == [f"TAKEOFF -> agent3 (3): ACCEPTED [seq {o.msg.seq}]"]
    assert core.take_finished() == []
    assert not msgs(core.tick(5.0), Command)  # nothing more to send


def test_command_retries_with_the_same_seq_then_no_answer() -> None:
    core = station_with(3)
    req, out = core.submit(CommandSpec(3, CommandKind.ARM), 1.0)
    seq = out[0].msg.seq
    sent = []
    t = 1.0
    while not req.done:
        core.handle(tm(3), t)  # still connected, just not answering commands
        sent += [(round(t, 1), o.msg.seq) for o in msgs(core.tick(t), Command)]
        t = round(t + 0.1, 1)
        assert t < 20
    # 0.5, 1, 2, 3 and 4 s apart: 6 tries in all, then given up 12 s after the first
    assert sent == [(1.5, seq), (2.5, seq), (4.5, seq), (7.5, seq), (11.5, seq)]
    assert round(t - 0.1, 1) == 13.0
    assert req.status == 504 and req.body()["results"][0]["result"] == NO_ANSWER
    assert "error" in req.body()
    core.handle(CommandAck(3, seq, AckResult.ACCEPTED), t)  # too late
    assert core.counters.duplicate_acks == 1 and req.body()["results"][0]["result"] == NO_ANSWER


def test_a_retried_command_answered_on_the_second_try_and_rejections() -> None:
    core = station_with(3, 4)
    req, out = core.submit(CommandSpec(3, CommandKind.GOTO, lat=47.4, lon=8.55, alt=20.0), 0.0)
    seq = out[0].msg.seq
    core.handle(CommandAck(4, seq, AckResult.ACCEPTED), 0.5)  # wrong agent: not its answer
    assert not req.done and core.counters.late_acks == 1
    assert msgs(core.tick(1.0), Command)[0].msg.seq == seq
    core.handle(CommandAck(3, seq, AckResult.REJECTED, "not armed"), 1.1)
    assert req.done and req.status == 200
    assert req.body() == {
        "ok": False,
        "request": req.id,
        "results": [{"agent": 3, "result": "REJECTED", "reason": "not armed"}],
    }


def test_refusals_send_nothing() -> None:
    core = station_with(3)
    core.handle(GSAdvertize(5, "agent5"), 0.0)  # known, never connected
    cases = [
        (CommandSpec(9, CommandKind.ARM), 404, "unknown agent 9"),
        (CommandSpec(5, CommandKind.ARM), 409, "agent5 (5) is not connected"),
        (CommandSpec(None, CommandKind.FOLLOW, heading=90.0), 409, "no leader elected yet"),
    ]
    for spec, status, reason in cases:
        with pytest.raises(CommandRefused) as ei:
            core.submit(spec, 1.0)
        assert (ei.value.status, ei.value.reason) == (status, reason)
    assert core.counters.commands_sent == 0
    empty = StationCore()
    with pytest.raises(CommandRefused) as ei:
        empty.submit(CommandSpec(None, CommandKind.LAND), 0.0)
    assert ei.value.status == 409 and ei.value.reason == "no connected agents"


def test_swarm_commands_go_to_the_leader_and_fan_out() -> None:
    core = station_with(1, 2, 3, leader=2)
    assert core.leader == 2
    _, out = core.submit(CommandSpec(None, CommandKind.FOLLOW, heading=45.0), 1.0)
    assert [(o.to, o.msg.target, o.msg.kind, o.msg.heading) for o in out] == [
        (2, 0, CommandKind.FOLLOW, 45.0)
    ]
    req, out = core.submit(CommandSpec(None, CommandKind.STOP), 1.0)
    assert [(o.to, o.msg.target) for o in out] == [(2, 0), (1, 1), (2, 2), (3, 3)]
    assert len({o.msg.seq for o in out}) == 4
    for o in out:
        core.handle(CommandAck(o.to, o.msg.seq, AckResult.ACCEPTED), 1.1)
    assert req.done and req.body()["ok"] is True
    assert [r.get("swarm", False) for r in req.body()["results"]] == [True, False, False, False]
    _, out = core.submit(CommandSpec(None, CommandKind.TAKEOFF, alt=15.0), 2.0)
    assert [(o.to, o.msg.target, o.msg.alt) for o in out] == [(1, 1, 15.0), (2, 2, 15.0), (3, 3, 15.0)]
    # a disconnected agent is left out of a fan-out
    t = 2.0
    while core.agents[3].connected:
        t += 0.5
        core.handle(tm(1, phase=Phase.MEMBER, leader=2), t)
        core.handle(tm(2, phase=Phase.LEADER, leader=2), t)
        core.tick(t)
    _, out = core.submit(CommandSpec(None, CommandKind.LAND), t)
    assert [o.to for o in out] == [1, 2]


def test_partial_answers_are_200_not_ok() -> None:
    core = station_with(1, 2)
    req, out = core.submit(CommandSpec(None, CommandKind.ARM), 0.0)
    core.handle(CommandAck(1, out[0].msg.seq, AckResult.ACCEPTED), 0.1)
    for k in range(1, 140):
        core.tick(k / 10)
    assert req.done and req.status == 200 and req.body()["ok"] is False
    assert [r["result"] for r in req.body()["results"]] == ["ACCEPTED", NO_ANSWER]


def test_leader_follows_the_majority_and_changes_are_events() -> None:
    core = station_with(1, 2, 3)
    assert core.leader == 0
    for i in (1, 2, 3):
        core.handle(tm(i, phase=Phase.LEADER if i == 3 else Phase.MEMBER, leader=3), 1.0)
    assert core.leader == 3
    core.handle(
        AgentState(
            3, Phase.LEADER, leader=3, pool=frozenset({1, 2, 3}), members=frozenset({1, 2}), locked=True
        ),
        1.0,
        "agent3",
    )
    a = core.agents[3].as_dict(1.0)
    assert (a["phase"], a["leader"], a["pool"], a["members"], a["locked"]) == (
        "LEADER",
        3,
        [1, 2, 3],
        [1, 2],
        True,
    )
    events = [e for e in core.take_events() if e.kind == "leader"]
    assert [e.text for e in events] == ["agent3 (3) is the leader"]
    for i in (1, 2):
        core.handle(tm(i, phase=Phase.ELECTING), 2.0)
    core.handle(tm(3, phase=Phase.ELECTING), 2.0)
    assert core.leader == 0
    assert [e.text for e in core.take_events()] == ["no leader"]


def test_view_fields_trail_and_snapshot() -> None:
    core = StationCore(config=StationConfig(trail_s=60.0, trail_points=120), wall_offset=1000.0)
    connect(core, 3, 0.0)
    a = core.agents[3].as_dict(0.0)
    assert a["lat"] is None and a["battery"] is None and a["trail"] == []
    core.handle(tm(3), 0.0)  # no flight controller: arming and flight unknown
    a = core.agents[3].as_dict(0.0)
    assert (a["armed"], a["airborne"], a["mode"]) == (None, None, "POSCTL")
    t = 0.0
    while t < 100.0:
        p = Pose(47.0 + t * 1e-5, 8.0, 500.0, 10.0)
        if int(t * 10) % 2:
            core.handle(tm(3, pose=p, flags=FLAG_ARMED | FLAG_FC_OK, battery=77), t)
        else:
            core.handle(PoseReport(p), t, "agent3")
        t = round(t + 0.05, 2)
    d = core.agents[3].as_dict(t)
    assert d["connected"] and d["mode"] == "POSCTL" and d["armed"] is True and d["airborne"] is False
    assert (d["battery"], d["rssi"], d["remrssi"], d["groundspeed"]) == (77, 180, 170, 2.5)
    assert d["lat"] == pytest.approx(47.0 + 99.95e-5) and d["heading"] == 10.0
    assert 110 <= len(d["trail"]) <= 120
    assert d["trail"][0][0] >= 47.0 + 39.9e-5  # only the last 60 s
    assert d["trail"][-1] == [d["lat"], d["lon"]]
    snap = core.snapshot(t)
    assert snap["time"] == pytest.approx(1100.0) and snap["leader"] == 0
    station = {"name": "gcs", "id": 255, "link": "x"}
    assert json.loads(core.snapshot_json(t, station)) == {**snap, "station": station}
    assert snap["events"][0]["t"] == 1000.0 and snap["events"][0]["kind"] == "connect"
    # a pose from an agent with no fix yet (0, 0) is not a position
    core.handle(GSAdvertize(4, "agent4"), t)
    core.handle(PoseReport(Pose(0.0, 0.0, 0.0)), t, "agent4")
    assert core.agents[4].pose is None


def test_events_are_capped() -> None:
    core = StationCore(config=StationConfig(events=5))
    for i in range(1, 9):
        connect(core, i, float(i))
    assert len(core.events) == 5 and core.events[-1].text == "agent8 (8) connected"


def test_passive_core_sends_nothing_and_counts_anything_heard() -> None:
    core = StationCore(passive=True)
    assert core.tick(0.0) == []
    assert core.handle(GSAdvertize(3, "agent3"), 0.0) == []
    assert core.agents[3].connected
    core.handle(Command(255, 4, 3, CommandKind.LAND), 1.0)
    core.handle(CommandAck(3, 4, AckResult.ACCEPTED), 1.1)
    assert [e.kind for e in core.take_events()] == ["connect", "command", "command"]
    core.tick(6.5)
    assert not core.agents[3].connected
    with pytest.raises(CommandRefused) as ei:
        core.submit(CommandSpec(3, CommandKind.LAND), 7.0)
    assert ei.value.status == 409


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        ([], "a command is a JSON object"),
        ({"target": 3}, "unknown command kind None"),
        ({"target": 3, "kind": "fly"}, "unknown command kind 'fly'"),
        ({"kind": "arm"}, "a command needs a 'target'"),
        ({"target": "all", "kind": "arm"}, "target 'all'"),
        ({"target": True, "kind": "arm"}, "target True"),
        ({"target": 0, "kind": "arm"}, "target 0 is not an agent id"),
        ({"target": 251, "kind": "arm"}, "target 251 is not an agent id"),
        ({"target": 3, "kind": "takeoff"}, "takeoff needs 'alt'"),
        ({"target": 3, "kind": "takeoff", "alt": -1}, "'alt' -1 outside 0..5553"),
        ({"target": 3, "kind": "takeoff", "alt": "10"}, "'alt' must be a number"),
        ({"target": 3, "kind": "takeoff", "alt": 6000}, "'alt' 6000 outside"),
        ({"target": "swarm", "kind": "waypoint", "lat": 47, "lon": 8, "alt": 5}, "waypoint is for one agent"),
        ({"target": 3, "kind": "goto", "lat": 47.0, "lon": 8.0}, "goto needs 'alt'"),
        ({"target": 3, "kind": "goto", "lat": 91, "lon": 8.0, "alt": 500}, "'lat' 91 outside"),
        ({"target": 3, "kind": "goto", "lat": 47, "lon": 8.0, "alt": float("nan")}, "must be a number"),
        ({"target": "swarm", "kind": "goto", "lat": 47, "lon": 8, "alt": 5}, "goto is for one agent"),
        ({"target": 3, "kind": "follow", "heading": 10}, "follow is a swarm command"),
        ({"target": "swarm", "kind": "follow"}, "follow needs 'heading'"),
        ({"target": "swarm", "kind": "follow", "heading": 361}, "'heading' 361 outside"),
    ],
)
def test_parse_command_rejects(body: Any, reason: str) -> None:
    with pytest.raises(CommandRefused) as ei:
        parse_command(body)
    assert ei.value.status == 400 and reason in ei.value.reason


def test_parse_command_accepts() -> None:
    assert parse_command({"target": "swarm", "kind": "FOLLOW", "heading": 360}) == CommandSpec(
        None, CommandKind.FOLLOW, heading=0.0
    )
    assert parse_command(
        {"target": 7, "kind": "goto", "lat": -33.5, "lon": 151, "alt": 40.5, "id": "x"}
    ) == CommandSpec(7, CommandKind.GOTO, lat=-33.5, lon=151.0, alt=40.5)
    assert parse_command({"target": "swarm", "kind": "takeoff", "alt": 12}).alt == 12.0
    assert parse_command({"target": 1, "kind": "stop"}) == CommandSpec(1, CommandKind.STOP)
    assert parse_command({"target": 2, "kind": "waypoint", "lat": 1, "lon": 2, "alt": 3}) == CommandSpec(
        2, CommandKind.WAYPOINT, lat=1.0, lon=2.0, alt=3.0
    )


def test_a_heartbeat_round_is_one_payload_for_every_agent() -> None:
    core = station_with(1, 2, 3)
    core.tick(0.0)
    out = msgs(core.tick(1.0), GSHeartbeat)
    assert sorted(o.to for o in out) == [1, 2, 3]
    assert len({encode(o.msg) for o in out}) == 1  # the radio bridge merges them into one frame
    assert not msgs(core.tick(1.5), GSHeartbeat)
