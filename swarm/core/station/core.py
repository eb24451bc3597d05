"""The ground station's side of the connection protocol, and its runtime.

Theory of operation
-------------------
The protocol is the one :mod:`swarm.core.agent.gslink` describes (it is the agent side); the
station's part:

1. Every ``advertize_interval`` the station publishes GSAdvertize(its id, its name)
   on ``swarm/GSAdvertize`` so agents (and their radio bridges) learn its name.
   GSAdvertize whose sender is a station id is ignored.
2. An agent (id 1..250) announcing itself there while not connected gets
   GSConnect(station id, seq) in its inbox ``swarm/<agent>``, again every
   ``connect_retry`` with the same seq until it answers GSConnectAck (then it is
   connected, with the heartbeat interval the ack names), or until nothing was
   heard from it for ``connect_give_up``. Telemetry from a known agent that is not
   connected starts the same exchange (the station restarted; a drop was brief).
3. Connected agents get GSHeartbeat every ``heartbeat_interval`` (one seq for all
   agents in a round, so a radio bridge sends one multicast frame); an agent without
   Telemetry for ``max(min_timeout, 3 * hb_interval)`` is disconnected (an event)
   and reconnected when it advertises again; once its link has a record, for as
   long as that record says a silence is no chance (up to 10 heartbeats: a lossy
   link does not flap, :mod:`swarm.core.station.alerts`).
4. Telemetry, ``swarm/<name>/state`` (AgentState) and ``swarm/<name>/pose``
   (PoseReport) fill each agent's view: position, a trail (the last ``trail_s``,
   at most ``trail_points`` points), mode, flags, battery, radio, election state.
   The leaders and their swarms are :mod:`swarm.core.station.swarms`'s (``swarms``;
   ``leader``: the one most connected agents follow). An agent whose
   Telemetry had FLAG_FC_OK and loses it has lost its flight controller: a
   ``vehicle`` event ("vehicle link lost"), ``vehicle_link: false`` and its mode,
   arming and airborne state unknown until the flag is back ("vehicle link back").
5. Commands: :meth:`StationCore.submit` refuses them in a replay (409) and hands
   them to its :class:`~swarm.core.station.delivery.CommandDelivery` (checks
   against what the station knows, sending with retries to the agents or the
   leader seen at each try, answers matched by seq); a CommandAck goes there too,
   and so does each change of leader and each Telemetry (evidence of a command
   carried out). What a command is, parses to and ends with is
   :mod:`swarm.core.station.commands`.
6. Alerts (battery, link, vehicle link, the agents' notices, refused commands,
   separation holds) are :class:`~swarm.core.station.watch.AlertWatch`'s, kept in
   an :class:`~swarm.core.station.alerts.AlertBook` (``alerts`` in the state;
   :meth:`StationCore.ack_alert` acknowledges one). AgentNotice lines go to the log.
   The station radio's RADIO_STATUS (:meth:`StationCore.observe_radio`) gives the
   state's ``radio``: RSSI, noise and their margins, local and remote.
7. The views and settings (:class:`AgentView`, :class:`Event`, :class:`StOut`,
   :class:`StationConfig`) are :mod:`swarm.core.station.model`'s; import them from there.
8. The plan (:mod:`swarm.core.station.plan`): each agent's ``route`` (GOTO, WAYPOINT, any
   station's) until "arrived"; the leader's Heartbeat task (``task``, ``slots``).

:class:`StationCore` does no I/O, starts no thread and reads no clock:
``handle(msg, now)``, ``submit(spec, now)`` and ``tick(now)`` return the
:class:`StOut` to send; ``next_deadline()`` says when to tick next. ``now`` is any
monotonic clock in seconds; events carry ``now + wall_offset`` (Unix time).

With ``passive=True`` (replay) the core sends nothing and an agent counts as
connected while anything from it was heard in the last ``passive_timeout``.

The runtime that drives it over Zenoh or a radio is :mod:`swarm.runtime.station.live`.
"""

from __future__ import annotations

import itertools
import json
import math
from collections import deque
from typing import Any

from swarm.core.station.alerts import SHELVE_MAX_S, AlertBook
from swarm.core.station.commands import (
    DONE_RESULTS,
    NO_ANSWER,
    CommandRefused,
    CommandSpec,
    Pending,
    Request,
)
from swarm.core.station.delivery import CommandDelivery
from swarm.core.station.followup import DID_NOT_HAPPEN, FOLLOWED, IN_PROGRESS, Followup, Followups
from swarm.core.station.model import AgentView, Event, StationConfig, StationCounters, StOut, has_position
from swarm.core.station.plan import PlanBook
from swarm.core.station.rows import AlertRow, RadioRow, Snapshot, StationInfo
from swarm.core.station.swarms import SwarmBook
from swarm.core.station.watch import AlertWatch
from swarm.core.wire.codes import (
    FLAG_AIRBORNE,
    FLAG_ARMED,
    FLAG_CONTROL_LOST,
    FLAG_FC_OK,
    FLAG_HOLDING,
    FLAG_READY,
    FLAG_READY_KNOWN,
    is_station,
    mode_name,
    short_reason,
)
from swarm.core.wire.message_types import (
    GCS_ID,
    AgentNotice,
    AgentState,
    Command,
    CommandAck,
    GSAdvertize,
    GSConnect,
    GSConnectAck,
    GSHeartbeat,
    Heartbeat,
    Message,
    NoticeSource,
    Phase,
    Pose,
    PoseReport,
    Telemetry,
    check_name,
)
from swarm.errors import SwarmError

#: how long a finished follow-up stays in its agent's row (then the log has it)
SHOW_ENDED_S = 60.0

#: a RADIO_STATUS older than this is not shown (ArduPilot's reports go stale after 5 s too)
RADIO_STALE_S = 5.0


class StationCore:
    """The station's protocol and view of the swarm. See the module docstring."""

    def __init__(
        self,
        name: str = "gcs",
        station_id: int = GCS_ID,
        config: StationConfig | None = None,
        *,
        passive: bool = False,
        wall_offset: float = 0.0,
        first_seq: int = 1,
    ) -> None:
        check_name(name)
        if not is_station(station_id):
            raise ValueError(f"station id {station_id}: ground stations use 251..255")
        self.name = name
        self.id = station_id
        self.cfg = config or StationConfig()
        self.passive = passive
        self.wall_offset = wall_offset
        self.agents: dict[int, AgentView] = {}
        self._by_name: dict[str, int] = {}
        self.events: deque[Event] = deque(maxlen=self.cfg.events)
        self._new_events: list[Event] = []
        self.counters = StationCounters()
        self.leader = 0
        self._next_advertize = -math.inf
        self._next_hb = -math.inf
        self._hb_seq = 0
        self._connect_seq = itertools.count(1)
        # the runtime starts commands at a random seq (see CommandDelivery)
        self.swarms = SwarmBook()  # every leader and its members (swarm.core.station.swarms)
        self.commands = CommandDelivery(
            self.id, self.cfg, self.counters, self.agents, self._label, self._event, first_seq, self.swarms
        )
        self._leader_dirty = False  # a connection, phase or leader changed
        # alerts and link health (swarm.core.station.alerts, swarm.core.station.watch)
        self.alerts = AlertBook(self.cfg.alerts.keep, wall_offset, self.cfg.alerts)
        self.watch = AlertWatch(self.cfg.alerts, self.alerts, self._label, self._event)
        self._now = 0.0  # the latest now seen (finished commands are handed out without one)
        self._radio: tuple[float, int, int, int, int] | None = None  # when, rssi, noise, remrssi, remnoise
        self.followups = Followups()  # what each agent's last command did (swarm.core.station.followup)
        self.plan = PlanBook()  # routes, go-to targets, the leader's task (swarm.core.station.plan)

    # -- inputs -----------------------------------------------------------------
    def handle(self, msg: Message, now: float, name: str = "") -> list[StOut]:
        """One message heard. ``name`` is the agent name from the key of a pose or
        state sample (``swarm/<name>/pose``); unused for the other messages."""
        self.counters.received += 1
        self._now = max(self._now, now)
        out: list[StOut] = []
        if isinstance(msg, GSAdvertize):
            if is_station(msg.sender) or not 1 <= msg.sender <= 250:
                return out  # ourselves, or another station
            a = self._learn(msg.sender, msg.name, now)
            if not a.connected and a.connect_seq is None:
                out += self._start_connect(a, now)
        elif isinstance(msg, GSConnectAck):
            self._connect_ack(msg, now)
        elif isinstance(msg, Telemetry):
            out += self._telemetry(msg, now)
        elif isinstance(msg, CommandAck):
            self._command_ack(msg, now)
        elif isinstance(msg, AgentState):
            self._state(msg, name, now)
        elif isinstance(msg, PoseReport):
            aid = self._by_name.get(name)
            if aid is None:
                self.counters.unknown_agent += 1
            else:
                self.observe_pose(aid, msg.pose, now)
        elif isinstance(msg, AgentNotice):
            self._notice(msg, now)
        elif isinstance(msg, Heartbeat):
            self.plan.heartbeat(msg)
            self._leader_dirty |= self.swarms.heartbeat(msg)  # its member list
        elif isinstance(msg, Command) and is_station(msg.sender) and (self.passive or msg.sender != self.id):
            self._plan_command(msg)
            if self.passive:
                who = self._label(msg.target) if msg.target else "the swarm (leader)"
                what = f"station {msg.sender} sent {msg.kind.name} to {who} (seq {msg.seq})"
                self._event(now, "command", what)
        else:
            self.counters.ignored += 1
        self._update_leader(now)
        return out

    def _connect_ack(self, msg: GSConnectAck, now: float) -> None:
        a = self.agents.get(msg.sender)
        if a is None:
            self.counters.unknown_agent += 1
        elif self.passive or msg.seq == a.connect_seq or a.connected:
            a.hb_interval = max(0.001, msg.hb_interval_ms / 1000.0)
            a.connect_seq = None
            a.last_telemetry = max(a.last_telemetry, now)  # the timeout counts from here
            self._heard(a, now)
            if not a.connected:
                self._connected(a, now)
        else:
            self.counters.stale_connect_acks += 1

    def observe_pose(self, agent_id: int, pose: Pose, now: float) -> None:
        """A position for ``agent_id`` (pose stream, or a vehicle frame in a replay)."""
        a = self.agents.get(agent_id)
        if a is None:
            self.counters.unknown_agent += 1
            return
        self._heard(a, now)
        if has_position(pose):
            a.pose = pose
            if a.groundspeed is None or not math.isfinite(a.last_telemetry):
                a.groundspeed = math.hypot(pose.vn, pose.ve)
            a.add_trail(pose, now, self.cfg.trail_s, self.cfg.trail_points)

    def observe_vehicle(
        self, agent_id: int, now: float, *, mode: str | None = None, armed: bool | None = None
    ) -> None:
        """Mode and arming from a forwarded vehicle HEARTBEAT (replay)."""
        a = self.agents.get(agent_id)
        if a is None:
            self.counters.unknown_agent += 1
            return
        self._heard(a, now)
        if mode is not None:
            a.mode = mode
        if armed is not None:
            a.armed = armed

    def observe_radio(self, rssi: int, noise: int, remrssi: int, remnoise: int, now: float) -> None:
        """The station radio's RADIO_STATUS (accepted at ``now``): its margins go in the state."""
        self._radio = (now, rssi, noise, remrssi, remnoise)

    def radio_dict(self, now: float) -> RadioRow | None:
        """The station radio's RSSI, noise and margins (RSSI - noise, SiK units: about 1.9
        per dB), local and remote; None without a report in the last 5 s."""
        if self._radio is None or now - self._radio[0] > RADIO_STALE_S:
            return None
        _, rssi, noise, rem, remnoise = self._radio
        return {
            "rssi": rssi,
            "noise": noise,
            "margin": rssi - noise,
            "remrssi": rem,
            "remnoise": remnoise,
            "remmargin": rem - remnoise,
        }

    def learn(self, agent_id: int, name: str, now: float) -> AgentView:
        """Record an agent's name (Advertize seen in a replay)."""
        return self._learn(agent_id, name, now)

    # -- commands -----------------------------------------------------------------
    def submit(self, spec: CommandSpec, now: float) -> tuple[Request, list[StOut]]:
        """Start a command.

        Raises:
            CommandRefused: 404 unknown agent, 409 agent not connected, no leader
                (FOLLOW), nothing connected (a swarm fan-out), or a passive core.
        """
        if self.passive:
            raise CommandRefused(409, "replay: this station only plays a capture, it sends no commands")
        req, out = self.commands.submit(spec, now, self.leader)
        for p in req.pending:
            self._plan_command(p.msg)
        return req, out

    def _plan_command(self, cmd: Command | None) -> None:
        """A command for the plan (None: the plan changed): each agent's route as it has it."""
        if cmd is not None:
            self.plan.command(cmd)
        for a in self.agents.values():
            a.route = self.plan.route_list(a.id)

    def _command_ack(self, msg: CommandAck, now: float) -> None:
        a = self.agents.get(msg.sender)
        if a is not None:
            self._heard(a, now)
        if self.passive:  # a capture replayed: whatever it holds, one printable line
            why = short_reason(msg.reason)
            self._event(
                now,
                "command",
                f"{self._label(msg.sender)} answered seq {msg.seq}: {msg.result.name}"
                + (f" ({why})" if why else ""),
            )
            return
        self.commands.ack(msg, now, self.leader)

    # -- time -----------------------------------------------------------------------
    def tick(self, now: float) -> list[StOut]:
        self._now = max(self._now, now)
        out: list[StOut] = []
        if not self.passive and now + 1e-9 >= self._next_advertize:
            out.append(StOut(0, "", GSAdvertize(self.id, self.name)))
            self._next_advertize = now + self.cfg.advertize_interval
        for a in self.agents.values():
            if a.connected and now - self._last_alive(a) > self._timeout(a):
                a.connected = False
                self._leader_dirty = True
                self._event(
                    now,
                    "disconnect",
                    f"{self._label(a.id)} disconnected (silent for {now - self._last_alive(a):.1f} s)",
                )
                if not self.passive:
                    self.watch.disconnected(a, now - self._last_alive(a), now)
            if self.passive:
                continue
            if a.connect_seq is not None and now + 1e-9 >= a.next_connect:
                if now - a.last_heard > self.cfg.connect_give_up:
                    a.connect_seq = None  # gone: the next GSAdvertize starts again
                else:
                    out += self._connect_out(a, now)
        if not self.passive and now + 1e-9 >= self._next_hb:
            # one round, one seq: identical payloads, which the radio bridge sends as
            # one multicast frame instead of one frame per agent
            self._next_hb = now + self.cfg.heartbeat_interval
            round_ = [a for a in self.agents.values() if a.connected]
            if round_:
                self._hb_seq = (self._hb_seq + 1) & 0xFF
                for a in round_:
                    out.append(StOut(a.id, a.name, GSHeartbeat(self.id, self._hb_seq)))
                self.counters.heartbeats_sent += len(round_)
        out += self.commands.tick(now, self.leader)
        for f in self.followups.tick(self.agents, now):
            self._followed(f)
        for aid, f in list(self.followups.by_agent.items()):
            if f.state != IN_PROGRESS and now - f.changed > SHOW_ENDED_S:
                del self.followups.by_agent[aid]  # shown long enough: the log keeps it
            self._doing(aid)
        self.watch.tick(now)
        self._update_leader(now)
        return out

    def next_deadline(self) -> float:
        times = [self._next_advertize, self._next_hb] if not self.passive else []
        for a in self.agents.values():
            if a.connected:
                times.append(self._last_alive(a) + self._timeout(a))
            if a.connect_seq is not None and not self.passive:
                times.append(a.next_connect)
        times.extend(self.commands.deadlines())
        times.append(self.alerts.next_deadline())
        return min(times)

    # -- outputs for the runtime ---------------------------------------------------------
    def take_events(self) -> list[Event]:
        ev, self._new_events = self._new_events, []
        return ev

    def take_finished(self) -> list[Request]:
        done = self.commands.take_finished()
        for r in done:
            self.watch.finished(r, self._now)
            for p in r.pending:  # a refused go-to is not flown to
                if p.result not in (*DONE_RESULTS, NO_ANSWER, "IN_PROGRESS"):
                    self.plan.refused(p.agent, p.msg)
                    self._plan_command(None)
                elif p.result != NO_ANSWER and p.msg.kind in FOLLOWED:
                    self._follow(r, p)
        return done

    def _follow(self, r: Request, p: Pending) -> None:
        """Follow what the agent took on its vehicle (swarm.core.station.followup)."""
        m = p.msg
        targets = [p.agent] if not p.swarm else sorted(p.group or self.agents)
        for aid in targets:
            label = f"{m.kind.name} -> {self._label(aid)}"
            f = Followup(aid, m.kind, label, r.id, self._now, m.lat, m.lon, m.alt, mode=mode_name(m.mode))
            old = self.followups.start(f, self.agents.get(aid), self._now)
            if old is not None:
                self._event(self._now, "command", old.line)
            if f.state != IN_PROGRESS:
                self._followed(f)
            self._doing(aid)

    def _doing(self, agent_id: int) -> None:
        a = self.agents.get(agent_id)
        if a is not None:
            f = self.followups.by_agent.get(agent_id)
            a.doing = None if f is None else f.as_dict(self.wall_offset)

    def _followed(self, f: Followup) -> None:
        """A follow-up ended: its line; one that did not happen is also an alarm."""
        self._event(self._now, "command", f.line)
        if f.state == DID_NOT_HAPPEN:
            text = f"{self._label(f.agent)}: {f.kind.name.lower()} did not happen: {f.text}"
            self.alerts.once("command", f.agent, "warning", text, self._now)

    def ack_alert(self, alert_id: Any) -> AlertRow:
        """Acknowledge alert ``alert_id``: its row.

        Raises:
            CommandRefused: 400 not an alert id (an integer), 404 no such alert.
        """
        if isinstance(alert_id, bool) or not isinstance(alert_id, int):
            raise CommandRefused(400, "an alert id is an integer")
        a = self.alerts.ack(alert_id)
        if a is None:
            shown = alert_id if -(10**9) < alert_id < 10**9 else "out of range"
            raise CommandRefused(404, f"no alert {shown}")
        return a.as_dict()

    def shelve_alert(self, alert_id: Any, seconds: Any, now: float) -> AlertRow:
        """Shelve alarm ``alert_id`` for ``seconds`` (0: unshelve): its row.

        Raises:
            CommandRefused: 400 not an alert id or not 0..SHELVE_MAX_S seconds, 404 no
                such alert.
        """
        if isinstance(alert_id, bool) or not isinstance(alert_id, int):
            raise CommandRefused(400, "an alert id is an integer")
        if (
            isinstance(seconds, bool)
            or not isinstance(seconds, (int, float))
            or not math.isfinite(seconds)
            or not 0 <= seconds <= SHELVE_MAX_S
        ):
            raise CommandRefused(400, f"shelve for 0..{SHELVE_MAX_S:.0f} seconds")
        a = self.alerts.shelve(alert_id, float(seconds), now)
        if a is None:
            shown = alert_id if -(10**9) < alert_id < 10**9 else "out of range"
            raise CommandRefused(404, f"no alert {shown}")
        what = f"shelved for {seconds / 60:.0f} min" if seconds > 0 else "unshelved"
        self._event(now, "alert", f"alarm {a.id} {what}: {a.text}")
        return a.as_dict()

    def snapshot(self, now: float) -> Snapshot:
        """The API's state object (without the station's link description)."""
        return {
            "time": round(now + self.wall_offset, 3),
            "leader": self.leader,
            "agents": [self.agents[i].as_dict(now) for i in sorted(self.agents)],
            "events": [e.as_dict() for e in self.events],
            "alerts": self.alerts.as_list(),
            "alarm_rate": self.alerts.rate(now),
            "radio": self.radio_dict(now),
            "task": self.plan.task_dict(self.leader),
            "slots": self.plan.slots_list(self.leader),
            **self.swarms.state(self.plan),  # swarms, swarm_tasks, swarm_slots
        }

    def snapshot_json(self, now: float, station: StationInfo) -> str:
        """``json.dumps`` of :meth:`snapshot` with ``station`` added, built faster."""
        head = json.dumps({"time": round(now + self.wall_offset, 3), "leader": self.leader})
        agents = ", ".join(self.agents[i].as_json(now) for i in sorted(self.agents))
        events = json.dumps([e.as_dict() for e in self.events])
        return (
            head[:-1]
            + ', "agents": ['
            + agents
            + '], "events": '
            + events
            + ', "alerts": '
            + json.dumps(self.alerts.as_list())
            + ', "alarm_rate": '
            + json.dumps(self.alerts.rate(now))
            + ', "radio": '
            + json.dumps(self.radio_dict(now))
            + ', "task": '
            + json.dumps(self.plan.task_dict(self.leader))
            + ', "slots": '
            + json.dumps(self.plan.slots_list(self.leader))
            + ", "
            + json.dumps(self.swarms.state(self.plan))[1:-1]
            + ', "station": '
            + json.dumps(station)
            + "}"
        )

    # -- internals ---------------------------------------------------------------------
    def _label(self, agent_id: int) -> str:
        a = self.agents.get(agent_id)
        return f"{a.name} ({agent_id})" if a is not None else f"agent {agent_id}"

    def _event(self, now: float, kind: str, text: str) -> None:
        ev = Event(now + self.wall_offset, kind, text)
        self.events.append(ev)
        self._new_events.append(ev)

    def _learn(self, agent_id: int, name: str, now: float) -> AgentView:
        a = self.agents.get(agent_id)
        if a is None:
            a = self.agents[agent_id] = AgentView(agent_id, name)
        elif a.name != name:
            self._by_name.pop(a.name, None)
            a.name = name
        self._by_name[name] = agent_id
        self._heard(a, now)
        return a

    def _heard(self, a: AgentView, now: float) -> None:
        a.last_heard = max(a.last_heard, now)
        if self.passive and not a.connected:
            self._connected(a, now)

    def _connected(self, a: AgentView, now: float) -> None:
        a.connected = True
        self._leader_dirty = True
        again = " again" if a.ever_connected else ""
        a.ever_connected = True
        self._event(now, "connect", f"{self._label(a.id)} connected{again}")
        self.watch.connected(a, now)

    def _last_alive(self, a: AgentView) -> float:
        return a.last_heard if self.passive else a.last_telemetry

    def _timeout(self, a: AgentView) -> float:
        if self.passive:
            return self.cfg.passive_timeout
        base = max(self.cfg.min_timeout, self.cfg.timeout_heartbeats * a.hb_interval)
        return base if a.link.silence_s is None else max(base, a.link.silence_s)  # the link's record

    def _start_connect(self, a: AgentView, now: float) -> list[StOut]:
        a.connect_seq = next(self._connect_seq) & 0xFFFF or next(self._connect_seq)
        if self.passive:
            return []
        return self._connect_out(a, now)

    def _connect_out(self, a: AgentView, now: float) -> list[StOut]:
        assert a.connect_seq is not None
        a.next_connect = now + self.cfg.connect_retry
        self.counters.connect_sent += 1
        return [StOut(a.id, a.name, GSConnect(self.id, a.connect_seq))]

    def _telemetry(self, msg: Telemetry, now: float) -> list[StOut]:
        a = self.agents.get(msg.sender)
        if a is None:
            self.counters.unknown_agent += 1  # no name yet: its GSAdvertize will come
            return []
        self._heard(a, now)
        if a.connected:
            a.last_telemetry = now
        out: list[StOut] = []
        if not a.connected and a.connect_seq is None and not self.passive:
            out += self._start_connect(a, now)
        fc = bool(msg.flags & FLAG_FC_OK)  # without a flight controller these are unknown
        if has_position(msg.pose):
            a.pose = msg.pose
            a.add_trail(msg.pose, now, self.cfg.trail_s, self.cfg.trail_points)
            if fc and not msg.flags & FLAG_AIRBORNE:
                a.home = (msg.pose.lat, msg.pose.lon, msg.pose.alt)  # the geofence's home
        self._vehicle_link(a, fc, now)
        a.mode = mode_name(msg.mode) if fc or a.vehicle_link is None else ""
        a.armed = bool(msg.flags & FLAG_ARMED) if fc else None
        a.airborne = bool(msg.flags & FLAG_AIRBORNE) if fc else None
        a.holding = bool(msg.flags & FLAG_HOLDING)
        a.control_lost = bool(msg.flags & FLAG_CONTROL_LOST) if fc else None
        a.battery = None if msg.battery > 100 else msg.battery
        a.rssi, a.remrssi = msg.rssi, msg.remrssi
        a.groundspeed = msg.groundspeed if fc else a.groundspeed
        if fc:  # without its flight controller the agent knows none of these now
            a.rel_alt, a.climb, a.home_dist = msg.rel_alt, msg.climb, msg.home_dist
            a.gps_fix, a.satellites = msg.gps_fix, msg.satellites
            a.ready = bool(msg.flags & FLAG_READY) if msg.flags & FLAG_READY_KNOWN else None
        else:
            a.rel_alt = a.climb = a.home_dist = a.gps_fix = a.satellites = a.ready = None
        if a.connected:  # a replay shows the battery alerts as they were, not its own link's
            self.watch.telemetry(a, now, self.cfg.timeout_heartbeats, link=not self.passive)
        self._set_election(a, msg.phase, msg.leader)
        if self.commands.in_flight:
            self.commands.look_for_evidence(a)
        ended = self.followups.observe(a, now)
        if ended is not None:
            self._followed(ended)
        self._doing(a.id)
        return out

    def _vehicle_link(self, a: AgentView, up: bool, now: float) -> None:
        """FLAG_FC_OK: an agent that had a flight controller and lost it is an alert."""
        if up == a.vehicle_link or (not up and a.vehicle_link is None):
            return  # unchanged, or an agent without a flight controller
        if not up:
            self._event(
                now,
                "vehicle",
                f"{self._label(a.id)}: vehicle link lost (its flight controller is silent; mode unknown)",
            )
        elif a.vehicle_link is False:
            self._event(now, "vehicle", f"{self._label(a.id)}: vehicle link back")
        self.watch.vehicle_link(a, up, now)
        a.vehicle_link = up

    def _notice(self, msg: AgentNotice, now: float) -> None:
        a = self.agents.get(msg.sender)
        if a is not None:
            self._heard(a, now)
            if msg.source == NoticeSource.AGENT:
                self.plan.notice(a.id, msg.text)
                self._plan_command(None)
        self.watch.notice(msg, now)

    def _state(self, msg: AgentState, name: str, now: float) -> None:
        if not 1 <= msg.sender <= 250:
            self.counters.ignored += 1
            return
        a = self.agents.get(msg.sender)
        if a is None:
            try:
                check_name(name)
            except SwarmError:
                name = f"agent{msg.sender}"
            a = self._learn(msg.sender, name, now)
        else:
            self._heard(a, now)
        self._set_election(a, msg.phase, msg.leader)
        a.locked, a.pool, a.members = msg.locked, msg.pool, msg.members

    def _set_election(self, a: AgentView, phase: Phase, leader: int) -> None:
        if (phase, leader) != (a.phase, a.leader):
            a.phase, a.leader = phase, leader
            self._leader_dirty = True

    def _update_leader(self, now: float) -> None:
        if not self._leader_dirty:
            return
        self._leader_dirty = False
        if self.swarms.update(self.agents):  # a swarm command in flight follows its members' leader
            self.commands.leader_changed(self.swarms.leader, now)
        leader = self.swarms.leader
        if leader != self.leader:
            self.leader = leader
            self._event(now, "leader", f"{self._label(leader)} is the leader" if leader else "no leader")
        for text in self.swarms.take_news(self._label):  # several swarms: each change of their leaders
            self._event(now, "leader", text)


__all__ = ["StationCore"]
