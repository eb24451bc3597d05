"""The station's state is typed (swarm.core.station.rows): the rows the core, the
fleet and the federation really build have exactly the keys their TypedDicts name.
The type checker holds the code to the types; these tests hold the types to the
data (a key added in one place and not the other fails here)."""

from __future__ import annotations

import json
from typing import Any

from test_gcs_station import POSE, connect, tm

from swarm.core.flight.geofence import Geofence
from swarm.core.station.core import StationCore
from swarm.core.station.federation import clean_agent, clean_state
from swarm.core.station.fleet import merge_channels, merge_stations
from swarm.core.station.model import StationConfig
from swarm.core.station.rows import AgentRow, AlertRow, EventRow, Snapshot, StationState, SwarmRow
from swarm.core.wire.codes import FLAG_AIRBORNE, FLAG_ARMED, FLAG_FC_OK
from swarm.core.wire.message_types import Phase


def keys_fit(row: Any, typed: Any, where: str) -> None:
    assert isinstance(row, dict), where
    assert typed.__required_keys__ <= row.keys(), f"{where} lacks {typed.__required_keys__ - row.keys()}"
    extra = row.keys() - typed.__required_keys__ - typed.__optional_keys__
    assert not extra, f"{where} has keys its type does not name: {extra}"


def a_station() -> StationCore:
    core = StationCore(config=StationConfig(fence=Geofence()))
    now = 0.0
    for k in (1, 2, 3):
        connect(core, k, now)
    flags = FLAG_ARMED | FLAG_AIRBORNE | FLAG_FC_OK
    core.handle(tm(1, phase=Phase.LEADER, leader=1, flags=flags, battery=9), 1.0)
    core.handle(tm(2, phase=Phase.MEMBER, leader=1, flags=flags), 1.0)
    core.handle(tm(3, phase=Phase.MEMBER, leader=1), 1.0)
    return core


def test_the_cores_snapshot_rows_are_its_types() -> None:
    snap = a_station().snapshot(2.0)
    keys_fit(snap, Snapshot, "snapshot")
    assert snap["agents"] and snap["events"] and snap["alerts"]  # the low battery: an alert
    for a in snap["agents"]:
        keys_fit(a, AgentRow, f"agent {a['id']}")
    for e in snap["events"]:
        keys_fit(e, EventRow, "event")
    for al in snap["alerts"]:
        keys_fit(al, AlertRow, "alert")
    for s in snap["swarms"]:
        keys_fit(s, SwarmRow, "swarm")
    assert json.loads(json.dumps(snap)) == snap  # plain JSON, as sent


def test_a_fleets_and_another_stations_rows_are_the_same_types() -> None:
    snap = a_station().snapshot(2.0)
    mine = merge_channels("gcs", [("north", snap), ("south", snap)])
    published = mine.as_state()
    keys_fit(published, StationState, "published state")
    theirs = clean_state(json.loads(json.dumps(published)))  # what another station keeps
    keys_fit(theirs, StationState, "cleaned state")
    for a in theirs["agents"]:
        keys_fit(a, AgentRow, "a remote agent")
    for al in theirs["alerts"]:
        keys_fit(al, AlertRow, "a remote alert")
    for s in theirs["swarms"]:
        keys_fit(s, SwarmRow, "a remote swarm")
    there = merge_stations(set(), [("east", True, theirs)])
    for a in there.agents:
        keys_fit(a, AgentRow, "a merged remote agent")


def test_a_remote_agents_failsafe_state_crosses_and_every_field_keeps_its_type() -> None:
    """An autopilot's failsafe on another station's agent (``control_lost``) was dropped
    by the cleaning (the field was not among those it rebuilt); a number that is not
    one of its kind is unknown."""
    row = dict(a_station().snapshot(2.0)["agents"][0])
    row.update(control_lost=True, battery=55.5, rssi="strong", hb_s=0.5)
    a = clean_agent(json.loads(json.dumps(row)))
    assert a["control_lost"] is True
    assert a["battery"] is None and a["rssi"] is None and a["hb_s"] == 0.5
    assert a["lat"] == round(POSE.lat, 7) and a["armed"] is True
