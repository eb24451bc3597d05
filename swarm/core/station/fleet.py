"""Several channels' and stations' states merged into one view: pure functions.

Theory of operation
-------------------
A station with several radios (one channel per NETID) and other stations joined over
Zenoh shows one fleet (the runtime's :class:`~swarm.runtime.station.fleet.Fleet`
takes the snapshots and hands them here). The rules of the merge:

* an agent id is one aircraft across a deployment: heard on two channels it is shown
  once (the first channel's), and another station's agent that is also held here is
  hidden; each such collision is a note (the fleet says each note once);
* every agent carries ``net`` (its channel) or ``station`` (who hears it); another
  station's agents carry ``station_alive``, and are shown disconnected while their
  station is silent;
* a channel's swarms are its core's own list (a ``colour`` made unique across the
  channels: ``colour * channels + index``), or one per leader its agents name; only a
  live station's swarms are shown;
* alert ids are made unique the same way (``id * channels + index``), so an
  acknowledgement reaches the channel that raised it.

The rows are the station's snapshot rows (``StationCore.snapshot``); each merge
returns new rows and leaves its inputs alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from swarm.core.station.rows import AgentRow, AlertRow, EventRow, Snapshot, StationState, SwarmRow


@dataclass
class Merged:
    """Agents, events, swarms and alerts of several channels or stations, and the
    collisions found on the way (one line each)."""

    agents: list[AgentRow] = field(default_factory=list)
    events: list[EventRow] = field(default_factory=list)
    swarms: list[SwarmRow] = field(default_factory=list)
    alerts: list[AlertRow] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def as_state(self) -> StationState:
        """What a station publishes to the others (the notes stay here)."""
        return {"agents": self.agents, "events": self.events, "swarms": self.swarms, "alerts": self.alerts}


def channel_swarms(snap: Snapshot, net: str, station: str, index: tuple[int, int]) -> list[SwarmRow]:
    """A channel's swarms: its core's own list (a ``colour`` made unique across the
    ``index[1]`` channels, as alert ids are), or one per leader its agents name."""
    if isinstance(snap.get("swarms"), list):
        i, n = index
        out: list[SwarmRow] = [{**s, "net": net, "station": station} for s in snap["swarms"]]
        for s in out:
            c = s.get("colour")
            if isinstance(c, int):
                s["colour"] = c * n + i
        return out
    lead = [a["leader"] for a in snap["agents"] if a.get("leader")]
    swarms: list[SwarmRow] = []
    for leader in sorted(set(lead)):
        members = sorted(a["id"] for a in snap["agents"] if a.get("leader") == leader)
        swarms.append({"leader": leader, "members": members, "net": net, "station": station})
    return swarms


def merge_channels(station: str, channels: Sequence[tuple[str, Snapshot]]) -> Merged:
    """This station's channels (``(net, snapshot)`` in order) as one state."""
    out = Merged()
    held: dict[int, AgentRow] = {}
    n = len(channels)
    for i, (net, snap) in enumerate(channels):
        for a in snap["agents"]:
            if a["id"] in held:
                out.notes.append(f"agent id {a['id']} heard on {held[a['id']]['net']} and {net}")
                continue
            held[a["id"]] = {**a, "net": net, "station": station}
        out.events += [{**e, "net": net} for e in snap["events"]]
        out.swarms += channel_swarms(snap, net, station, (i, n))
        out.alerts += [{**al, "id": al["id"] * n + i, "net": net} for al in snap["alerts"]]
    out.agents = list(held.values())
    return out


def merge_stations(held: set[int], remotes: Sequence[tuple[str, bool, StationState]]) -> Merged:
    """The other stations' states (``(name, alive, state)``) beside the agent ids
    ``held`` here, each row tagged with its ``station``. ``held`` is left alone."""
    out = Merged()
    seen = set(held)
    for name, alive, state in remotes:
        for a in state["agents"]:
            if a["id"] in seen:
                out.notes.append(f"agent id {a['id']} of station {name} is also held here: hidden")
                continue
            seen.add(a["id"])
            row: AgentRow = {**a, "station": name, "station_alive": alive}
            if not alive:
                row["connected"] = False
            out.agents.append(row)
        out.events += [{**e, "station": name} for e in state["events"]]
        if alive:
            out.swarms += [{**s, "station": name} for s in state["swarms"]]
        out.alerts += [{**al, "station": name, "station_alive": alive} for al in state.get("alerts", [])]
    return out


__all__ = ["Merged", "channel_swarms", "merge_channels", "merge_stations"]
