"""One view of several channels (swarm.runtime.station.fleet.Fleet), in one process: two real
stations (each its own Zenoh session, standing in for a radio's channel) with scripted
agents that speak the real connection protocol. Agents tagged with their channel, one
agent id heard on both shown once and reported, alert ids unique across channels and
acknowledged on the right one, commands routed to the channel that holds the agent,
swarm commands to both with their results gathered, events tagged."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from net_helpers import free_port, wait_until
from test_gcs_api import ScriptedAgent

from swarm.core.flight.geofence import Geofence
from swarm.core.station.commands import CommandRefused, parse_command
from swarm.core.station.fleet import channel_swarms, merge_channels, merge_stations
from swarm.core.wire.message_types import Phase, Telemetry
from swarm.runtime.station.fleet import Fleet
from swarm.runtime.station.live import Station

DEADLINE = 30.0


class LowBattery(ScriptedAgent):
    """A scripted agent at 10 % battery (a critical alert at its station)."""

    def telemetry(self) -> Telemetry:
        t = super().telemetry()
        return Telemetry(
            t.sender, t.pose, t.mode, t.flags, t.phase, t.leader, 10, t.rssi, t.remrssi, t.groundspeed
        )


@pytest.fixture
def fleet() -> Iterator[tuple[Fleet, list[ScriptedAgent]]]:
    eps = [f"tcp/127.0.0.1:{free_port()}" for _ in range(2)]
    channels = [
        (net, Station("gcs", zenoh_listen=[ep])) for net, ep in zip(("north", "south"), eps, strict=True)
    ]
    f = Fleet("gcs", 255, channels, Geofence()).start()
    agents: list[ScriptedAgent] = []
    try:
        agents += [LowBattery(eps[0], 1, phase=Phase.LEADER, leader=1), ScriptedAgent(eps[0], 3, leader=1)]
        agents += [LowBattery(eps[1], 2, phase=Phase.LEADER, leader=2), ScriptedAgent(eps[1], 3, leader=2)]
        yield f, agents
    finally:
        for a in agents:
            a.close()
        f.stop()


@pytest.mark.processes
def test_channels_merge_into_one_view(fleet: tuple[Fleet, list[ScriptedAgent]]) -> None:
    f, _agents = fleet
    seen: list[dict[str, Any]] = []
    f.add_listener(seen.append)

    def connected() -> dict[int, str]:
        return {a["id"]: a["net"] for a in f.snapshot()["agents"] if a["connected"]}

    wait_until(lambda: connected() == {1: "north", 2: "south", 3: "north"}, "both channels' agents", DEADLINE)
    s = f.snapshot()
    assert all(a["station"] == "gcs" for a in s["agents"])
    assert any("agent id 3 heard on north and south" in e["text"] for e in s["events"])
    assert [n["name"] for n in s["nets"]] == ["north", "south"]
    assert {(w["leader"], w["net"]) for w in s["swarms"]} == {(1, "north"), (2, "south")}

    # one battery alert per channel, each with a local id of its own: unique here
    def battery() -> list[dict[str, Any]]:
        return [a for a in f.snapshot()["alerts"] if a["kind"] == "battery"]

    alerts = wait_until(
        lambda: len(battery()) == 2 and battery(), "a battery alert on each channel", DEADLINE
    )
    assert len({a["id"] for a in alerts}) == 2 and {a["net"] for a in alerts} == {"north", "south"}
    south = next(a for a in alerts if a["net"] == "south")
    assert f.ack_alert(south["id"])["acked"] is True
    acked = {a["net"]: a["acked"] for a in battery()}
    assert acked == {"north": False, "south": True}
    # to one agent: the channel that holds it answers; to the swarm: both, gathered
    status, body = f.submit(parse_command({"target": 2, "kind": "land"})).result(20)
    assert status == 200 and [r["agent"] for r in body["results"]] == [2]
    status, body = f.submit(parse_command({"target": "swarm", "kind": "land"})).result(20)
    assert status == 200 and body["ok"] is True
    assert {(r["agent"], r["net"]) for r in body["results"]} >= {(1, "north"), (3, "north"), (2, "south")}
    # a route to every swarm: each channel holds one, together two that would meet: refused
    with pytest.raises(CommandRefused) as refused:
        f.submit(parse_command({"target": "swarm", "kind": "follow", "heading": 90}))
    assert refused.value.status == 409 and "led by 1, 2" in str(refused.value)
    status, body = f.submit(
        parse_command({"target": "swarm", "swarm": 2, "kind": "follow", "heading": 90})
    ).result(20)
    assert status == 200 and [(r["agent"], r["net"]) for r in body["results"]] == [(2, "south")]
    wait_until(
        lambda: {e.get("net") for e in seen} >= {"north", "south"}, "events tagged by channel", DEADLINE
    )


def test_a_cores_own_swarms_are_tagged_and_their_colours_made_unique() -> None:
    snap = {
        "agents": [],
        "swarms": [{"leader": 4, "members": [4, 5], "colour": 0}, {"leader": 9, "members": [9]}],
    }
    got = [channel_swarms(snap, net, "gcs", (i, 2)) for i, net in enumerate(("north", "south"))]
    assert [[(s["leader"], s.get("colour"), s["net"]) for s in g] for g in got] == [
        [(4, 0, "north"), (9, None, "north")],
        [(4, 1, "south"), (9, None, "south")],
    ]
    # without the cores' list: one swarm per leader the agents name
    snap = {"agents": [{"id": 1, "leader": 2}, {"id": 2, "leader": 2}, {"id": 3, "leader": 0}]}
    assert channel_swarms(snap, "n", "gcs", (0, 1)) == [
        {"leader": 2, "members": [1, 2], "net": "n", "station": "gcs"}
    ]


def test_an_id_is_one_aircraft_across_channels_and_stations() -> None:
    """The fleet merge (pure): an id heard on two channels is shown once (the first
    channel's) and said; another station's agent also held here is hidden and said;
    a silent station's agents are shown disconnected and its swarms left out; alert ids
    are made unique per channel; the inputs are left alone."""
    north = {
        "agents": [{"id": 1, "leader": 1}, {"id": 3, "leader": 1}],
        "events": [{"t": 1.0, "text": "a"}],
        "alerts": [{"id": 0}],
    }
    south = {"agents": [{"id": 3, "leader": 2}, {"id": 2, "leader": 2}], "events": [], "alerts": [{"id": 0}]}
    mine = merge_channels("gcs", [("north", north), ("south", south)])
    assert [(a["id"], a["net"], a["station"]) for a in mine.agents] == [
        (1, "north", "gcs"),
        (3, "north", "gcs"),
        (2, "south", "gcs"),
    ]
    assert mine.notes == ["agent id 3 heard on north and south"]
    assert [a["id"] for a in mine.alerts] == [0, 1] and [a["net"] for a in mine.alerts] == ["north", "south"]
    assert north["agents"][1] == {"id": 3, "leader": 1}  # inputs untouched
    assert mine.as_state().keys() == {"agents", "events", "swarms", "alerts"}

    held = {a["id"] for a in mine.agents}
    remote = {"agents": [{"id": 2}, {"id": 7, "connected": True}], "events": [], "swarms": [{"leader": 7}]}
    live = merge_stations(held, [("east", True, remote)])
    assert [a["id"] for a in live.agents] == [7] and live.swarms == [{"leader": 7, "station": "east"}]
    assert live.notes == ["agent id 2 of station east is also held here: hidden"]
    silent = merge_stations(held, [("east", False, remote)])
    assert silent.agents == [{"id": 7, "connected": False, "station": "east", "station_alive": False}]
    assert silent.swarms == [] and held == {1, 2, 3}
