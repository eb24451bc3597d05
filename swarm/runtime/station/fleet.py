"""One view of several channels and stations: what the server reads when a station has
more than one radio, or joins other stations over Zenoh.

Theory of operation
-------------------
A :class:`Fleet` holds one :class:`~swarm.runtime.station.live.Station` per channel (one
radio per NETID, each with its own Zenoh session and radio bridge, as a
one-radio station) and, optionally, a :class:`~swarm.runtime.station.federation.Federation`
(the other stations' states and a way to command their agents). It gives the server
the same view as one station (``snapshot``, ``agent``, ``submit``, events,
alerts):

* ``agents``, ``swarms``: every channel's, then every other station's, merged by
  the pure functions of :mod:`swarm.core.station.fleet` (an id is one aircraft: shown
  once, each collision an event); each swarm's ``colour`` is the merged view's
  (:func:`swarm.core.station.swarms.fleet_colours`: the same swarm in the same colour
  on every page, all distinct), the station's own beside it (``station_colour``), and
  the state published to the others carries the station's own;
* ``leader``, ``radio``, ``task``, ``slots``: the first channel's, as before;
* ``events``: every channel's and station's, by time; ``alerts``: this station's
  channels', each id made unique (``id * channels + channel index``) so an
  acknowledgement reaches the channel that raised it, then every other station's
  (as it published them, cleaned: :func:`swarm.core.station.federation.clean_alerts`), each
  with the ``station`` that raised it (and whether it is alive). One of those is
  acknowledged at its station (:meth:`Fleet.ack_remote_alert`: a signed
  ``{"kind": "ack_alert", "id": N}`` over the federation, not awaited; the station's
  next state shows it acknowledged, a refusal is an event here);
* commands: to an agent, the channel that holds it, or the station that does (checked
  here against this station's geofence, :func:`swarm.core.station.federation.check_remote`,
  and there again when carried out); to one swarm (a ``swarm`` leader id on the
  command), the channel or station holding its leader; to every swarm, every channel
  and every station that is alive, their results gathered in one (status: the worst
  one's), but a FOLLOW to every swarm is refused while the channels and stations hold
  several swarms between them (each channel's core refuses it only for its own). A command
  from another station (:meth:`run_local`) is only ever carried out on this station's
  own channels, never passed on (an ``ack_alert`` too).
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future
from typing import Any

from swarm.core.flight.geofence import Geofence
from swarm.core.station.commands import CommandRefused, CommandSpec, parse_command
from swarm.core.station.federation import check_remote, spec_body, text
from swarm.core.station.fleet import Merged, merge_channels, merge_stations
from swarm.core.station.model import Event
from swarm.core.station.rows import AgentRow, AlertAck, AlertRow, EventRow, Snapshot, StationRow, StationState
from swarm.core.station.swarms import fleet_colours
from swarm.core.wire.message_types import CommandKind
from swarm.runtime.station.federation import Federation, Result
from swarm.runtime.station.live import Station
from swarm.runtime.station.served import Listener

MAX_EVENTS = 200
MAX_NOTES = 1000  # the fleet's own events (collisions) it says at most, each once


#: tries of another station's alert acknowledgement left unanswered (it is idempotent)
ACK_TRIES = 3


class Fleet:
    """Channels (``(net name, Station)``) and the other stations' agents as one station."""

    replay = None

    def __init__(self, name: str, station_id: int, channels: Sequence[tuple[str, Station]], fence: Geofence):
        if not channels:
            raise ValueError("a fleet has at least one channel")
        self.name = name
        self.id = station_id
        self.channels = list(channels)
        self.fence = fence
        self.federation: Federation | None = None
        self._lock = threading.Lock()
        self._listeners: dict[Listener, list[Listener]] = {}
        self._noted: set[str] = set()
        self._own_events: deque[EventRow] = deque(maxlen=MAX_EVENTS)

    # -- life cycle ---------------------------------------------------------------------
    def start(self) -> Fleet:
        """Start every channel (and the federation, if set). Raises what they raise."""
        try:
            for _net, st in self.channels:
                st.start()
            if self.federation is not None:
                self.federation.start()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        if self.federation is not None:
            self.federation.stop()
        for _net, st in self.channels:
            st.stop()

    @property
    def running(self) -> bool:
        fed_ok = self.federation is None or self.federation.alive
        return fed_ok and all(st.running for _n, st in self.channels)

    @property
    def session(self) -> Any:
        """The federation's Zenoh session (None without one): the CLI's peer watch."""
        return self.federation.session if self.federation is not None else None

    @property
    def bridge(self) -> Any:
        return self.channels[0][1].bridge

    def loop_beats(self) -> dict[str, tuple[float, float]]:
        beats: dict[str, tuple[float, float]] = {}
        for net, st in self.channels:
            beats.update({f"{net}:{k}": v for k, v in st.loop_beats().items()})
        return beats

    def describe(self) -> str:
        parts = [f"{net}:{st.describe()}" for net, st in self.channels]
        if self.federation is not None:
            parts.append(self.federation.describe())
        return " ".join(parts)

    # -- events ---------------------------------------------------------------------------
    def note(self, kind: str, text: str) -> None:
        """An event of the fleet's own (a collision), once per text."""
        with self._lock:
            if text in self._noted or len(self._noted) >= MAX_NOTES:
                return
            self._noted.add(text)
            ev = Event(time.time(), kind, text).as_dict()
            self._own_events.append(ev)
            listeners = [fns[0] for fns in self._listeners.values()]
        for fn in listeners:
            fn(ev)

    def add_listener(self, fn: Listener) -> None:
        wrappers = [fn]
        for net, st in self.channels:
            w = self._tagged(fn, net)
            wrappers.append(w)
            st.add_listener(w)
        with self._lock:
            self._listeners[fn] = wrappers

    def remove_listener(self, fn: Listener) -> None:
        with self._lock:
            wrappers = self._listeners.pop(fn, [fn])
        for (_net, st), w in zip(self.channels, wrappers[1:], strict=False):
            st.remove_listener(w)

    def _tagged(self, fn: Listener, net: str) -> Listener:
        return lambda ev: fn({**ev, "net": net, "station": self.name})

    # -- the view -------------------------------------------------------------------------
    def local_state(self, snaps: list[Snapshot] | None = None) -> StationState:
        """This station's channels only (their ``snaps``, taken now if not given): what
        it publishes to the others."""
        if snaps is None:
            snaps = [st.snapshot() for _net, st in self.channels]
        return self._merged_channels(snaps).as_state()

    def _merged_channels(self, snaps: list[Snapshot]) -> Merged:
        merged = merge_channels(
            self.name, [(net, s) for (net, _st), s in zip(self.channels, snaps, strict=True)]
        )
        for line in merged.notes:
            self.note("federation", line)
        return merged

    def _merged_stations(self, held: set[int]) -> Merged:
        """The other stations' agents, events, swarms (live stations') and alerts."""
        fed = self.federation
        remotes = [(r.name, alive, r.state) for r, alive in fed.remotes()] if fed is not None else []
        merged = merge_stations(held, remotes)
        for line in merged.notes:
            self.note("federation", line)
        return merged

    def snapshot(self) -> Snapshot:
        snaps = [st.snapshot() for _net, st in self.channels]
        first = snaps[0]
        mine = self._merged_channels(snaps)
        other = self._merged_stations({a["id"] for a in mine.agents})
        with self._lock:
            own = list(self._own_events)
        all_events = sorted(mine.events + other.events + own, key=lambda e: e["t"])[-MAX_EVENTS:]
        first["agents"] = sorted(mine.agents + other.agents, key=lambda a: a["id"])
        first["events"] = all_events
        alerts: list[AlertRow] = [{**al, "station": self.name} for al in mine.alerts]
        first["alerts"] = alerts + other.alerts
        rates = [r for s in snaps if (r := s.get("alarm_rate")) is not None]
        if rates:  # this station's operator: its own channels' announcements
            first["alarm_rate"] = {
                "announced": sum(r["announced"] for r in rates),
                "window_s": rates[0]["window_s"],
                "flood": any(r["flood"] for r in rates),
                "held": sum(r["held"] for r in rates),
            }
        first["swarms"] = fleet_colours(mine.swarms + other.swarms)
        first["nets"] = [
            {"name": net, "station": self.name, "link": st.describe()} for net, st in self.channels
        ]
        first["stations"] = self._stations()
        first["station"] = {"name": self.name, "id": self.id, "link": self.describe()}
        return first

    def _stations(self) -> list[StationRow]:
        out: list[StationRow] = [{"name": self.name, "alive": True, "here": True}]
        if self.federation is not None:
            out += [{"name": r.name, "alive": alive, "here": False} for r, alive in self.federation.remotes()]
        return out

    def snapshot_json(self) -> str:
        return json.dumps(self.snapshot())

    def agent(self, agent_id: int) -> AgentRow | None:
        for a in self.snapshot()["agents"]:
            if a["id"] == agent_id:
                return a.copy()
        return None

    def center(self) -> list[float] | None:
        for a in self.snapshot()["agents"]:
            lat, lon = a["lat"], a["lon"]
            if lat is not None and lon is not None:
                return [lat, lon]
        return None

    def ack_alert(self, alert_id: Any) -> AlertRow:
        if isinstance(alert_id, bool) or not isinstance(alert_id, int) or alert_id < 0:
            raise CommandRefused(400, "an alert id is an integer")
        n = len(self.channels)
        net, st = self.channels[alert_id % n]
        out = st.ack_alert(alert_id // n)
        return {**out, "id": alert_id, "net": net}

    def shelve_alert(self, alert_id: Any, seconds: Any) -> AlertRow:
        if isinstance(alert_id, bool) or not isinstance(alert_id, int) or alert_id < 0:
            raise CommandRefused(400, "an alert id is an integer")
        n = len(self.channels)
        net, st = self.channels[alert_id % n]
        out = st.shelve_alert(alert_id // n, seconds)
        return {**out, "id": alert_id, "net": net}

    def ack_remote_alert(self, alert_id: Any, station: str) -> AlertAck:
        """Acknowledge alert ``alert_id`` of another ``station`` there (not awaited).

        Raises:
            CommandRefused: 400 not an integer id; 404 no such station or alert; 409 the
                station is gone.
        """
        if isinstance(alert_id, bool) or not isinstance(alert_id, int) or alert_id < 0:
            raise CommandRefused(400, "an alert id is an integer")
        fed = self.federation
        for r, alive in fed.remotes() if fed is not None else []:
            if r.name != station:
                continue
            alert = next((a for a in r.state.get("alerts", []) if a["id"] == alert_id), None)
            if alert is None:
                raise CommandRefused(404, f"no alert {alert_id} of station {station}")
            if not alive:
                raise CommandRefused(409, f"station {station} is gone: acknowledge it there")
            assert fed is not None
            self._ack_there(fed, station, alert_id, 1)
            ack: AlertAck = {**alert, "station": station, "acked": True, "forwarded": True}
            return ack
        raise CommandRefused(404, f"no station {text(station, 32)!r} heard here")

    def _ack_there(self, fed: Federation, station: str, alert_id: int, attempt: int) -> None:
        """Ask ``station`` to acknowledge its alert; unanswered (an idempotent ack), ask
        again up to :data:`ACK_TRIES` times; refused or never answered: one log line."""

        def said(f: Future[Result]) -> None:
            status, body = f.result()
            if status in (503, 504) and attempt < ACK_TRIES:
                self._ack_there(fed, station, alert_id, attempt + 1)
            elif status != 200:
                why = body.get("error", status)
                self.note("federation", f"station {station} refused the ack of alert {alert_id}: {why}")

        fed.request(station, {"kind": "ack_alert", "id": alert_id}).add_done_callback(said)

    # -- commands -------------------------------------------------------------------------
    def _holder(self, agent_id: int) -> tuple[str, Station] | None:
        for net, st in self.channels:
            if st.agent(agent_id) is not None:
                return net, st
        return None

    def submit(self, spec: CommandSpec) -> Future[Result]:
        """:meth:`send` from this station's own page or API (may reach other stations)."""
        return self.send(spec, remote=True)

    def send(self, spec: CommandSpec, *, remote: bool) -> Future[Result]:
        """A command to an agent (here or at another station) or to every swarm.

        Raises:
            CommandRefused: 404 unknown agent, what the channel's core or
                :func:`~swarm.core.station.federation.check_remote` refuses, 409 nothing to
                command.
        """
        leader = spec.swarm  # a swarm by its leader's id
        if spec.target is None and leader is None and spec.kind == CommandKind.FOLLOW:
            self._one_swarm_to_follow(remote)
        if spec.target is None and leader is not None:
            here = self._holder(leader)
            if here is not None:
                return tagged(here[1].submit(spec), {"net": here[0], "station": self.name})
            if remote:
                return self._submit_remote(spec, leader)
            raise CommandRefused(404, f"no swarm led by {leader} at station {self.name}")
        if spec.target is not None:
            here = self._holder(spec.target)
            if here is not None:
                return tagged(here[1].submit(spec), {"net": here[0], "station": self.name})
            if remote:
                return self._submit_remote(spec, spec.target)
            raise CommandRefused(404, f"unknown agent {spec.target} at station {self.name}")
        parts: list[tuple[dict[str, Any], Future[Result]]] = []
        refusals: list[CommandRefused] = []
        fed = self.federation if remote else None
        body = (
            spec_body(check_remote(spec, self.fence, None)) if fed is not None else {}
        )  # before any is sent
        for net, st in self.channels:
            try:
                parts.append(({"net": net, "station": self.name}, st.submit(spec)))
            except CommandRefused as exc:
                refusals.append(exc)
        if fed is not None:
            for r, alive in fed.remotes():
                if alive and r.state["agents"]:
                    parts.append(({"station": r.name}, fed.request(r.name, body)))
        if not parts:
            raise refusals[0] if refusals else CommandRefused(409, "no connected agents")
        return gather(parts)

    def _one_swarm_to_follow(self, remote: bool) -> None:
        """A FOLLOW to every swarm is refused while this station's channels and the live
        stations (``remote``) hold several swarms, as one channel's core refuses it
        (:func:`swarm.core.station.swarms.swarm_plan`): each channel alone holding one
        swarm must not send them all one way from near each other.

        Raises:
            CommandRefused: 409 several swarms, none named.
        """
        leaders = [s["leader"] for _net, st in self.channels for s in st.snapshot().get("swarms") or []]
        if remote and self.federation is not None:
            leaders += [
                s["leader"] for r, alive in self.federation.remotes() if alive for s in r.state["swarms"]
            ]
        if len(leaders) > 1:
            raise CommandRefused(
                409,
                f"follow goes to one swarm (led by {', '.join(map(str, sorted(leaders)))}): name it with"
                ' "swarm": <leader id>; several swarms sent one way would meet',
            )

    def _submit_remote(self, spec: CommandSpec, agent_id: int) -> Future[Result]:
        """To the station that holds agent ``agent_id`` (the target, or a swarm's leader)."""
        if self.federation is not None:
            for r, alive in self.federation.remotes():
                for a in r.state["agents"]:
                    if a["id"] != agent_id:
                        continue
                    if not alive:
                        raise CommandRefused(409, f"station {r.name} is gone: {a['name']} cannot be reached")
                    checked = check_remote(spec, self.fence, a if spec.target is not None else None)
                    return tagged(self.federation.request(r.name, spec_body(checked)), {"station": r.name})
        raise CommandRefused(404, f"unknown agent {agent_id}")

    def run_local(self, body: Any) -> Future[Result]:
        """Another station's command object, for this station's own channels only.

        Raises:
            CommandRefused: what :func:`parse_command` and the channel refuse; 404 an
                agent not on this station's channels (or no such alert).
        """
        if isinstance(body, dict) and body.get("kind") == "ack_alert":  # from a page that shows ours
            done: Future[Result] = Future()
            done.set_result((200, {"ok": True, "alert": self.ack_alert(body.get("id"))}))
            return done
        return self.send(parse_command(body), remote=False)  # never passed on to a third station


def tagged(f: Future[Result], where: dict[str, Any]) -> Future[Result]:
    """``f``'s result with each of its results saying where it was carried out."""
    out: Future[Result] = Future()

    def done(_f: Future[Result]) -> None:
        status, body = f.result()
        results = [{**r, **where} if isinstance(r, dict) else r for r in body.get("results", [])]
        out.set_result((status, {**body, "results": results} if "results" in body else body))

    f.add_done_callback(done)
    return out


def gather(parts: list[tuple[dict[str, Any], Future[Result]]]) -> Future[Result]:
    """One result for several: every part's results, ``ok`` when all are, the worst status."""
    out: Future[Result] = Future()
    lock = threading.Lock()
    left = [len(parts)]

    def one(_f: Future[Result]) -> None:
        with lock:
            left[0] -= 1
            if left[0]:
                return
        statuses, results, errors = [], [], []
        for where, f in parts:
            status, part = f.result()
            statuses.append(status)
            results += [{**r, **where} for r in part.get("results", []) if isinstance(r, dict)]
            if part.get("error"):
                errors.append(f"{where.get('net') or where['station']}: {part['error']}")
        ok = all(s == 200 for s in statuses) and all(f.result()[1].get("ok") for _w, f in parts)
        body: dict[str, Any] = {"ok": ok, "results": results}
        if errors:
            body["error"] = "; ".join(errors)
        out.set_result((max(statuses), body))

    for _where, f in parts:
        f.add_done_callback(one)
    return out


__all__ = ["Fleet", "gather"]
