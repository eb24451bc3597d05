"""The ground station's side of the connection protocol, and its runtime.

Theory of operation
-------------------
The protocol is the one :mod:`swarm.core.gslink` describes (it is the agent side); the
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
   and reconnected when it advertises again.
4. Telemetry, ``swarm/<name>/state`` (AgentState) and ``swarm/<name>/pose``
   (PoseReport) fill each agent's view: position, a trail (the last ``trail_s``,
   at most ``trail_points`` points), mode, flags, battery, radio, election state.
   The swarm's leader is the one most connected agents follow. An agent whose
   Telemetry had FLAG_FC_OK and loses it has lost its flight controller: a
   ``vehicle`` event ("vehicle link lost"), ``vehicle_link: false`` and its mode,
   arming and airborne state unknown until the flag is back ("vehicle link back").
5. Commands: :meth:`StationCore.submit` checks a :class:`CommandSpec` against what
   the station knows (unknown agent, not connected, no leader: refused with a
   reason and an HTTP-like status, nothing sent) and returns a :class:`Request`
   holding one :class:`Command` per addressee. Each is re-sent with the same seq
   after ``command_backoff`` gaps (0.5, 1, 2, 3, 4 s, then 4 s) until its
   CommandAck arrives or ``command_give_up`` (12 s) has passed since the first
   send. Answers are matched by seq and by the agents the command went to
   (duplicates and late answers are counted and dropped). Swarm FOLLOW and STOP
   go to the leader as Command(target=0), and every retry goes to the leader the
   station sees *then*: a command sent just before an election reaches the new
   leader. A "not the leader" or "no leader" answer to a swarm command is not
   final while time remains (the agent does not remember it, so the new leader
   answers for itself). Swarm STOP also goes to every connected agent; swarm
   ARM/DISARM/TAKEOFF/LAND/RETURN go to every connected agent.
6. Results (:data:`RESULTS`): the agent's answer (``ACCEPTED``, or a refusal:
   ``REJECTED``, ``FAILED``, ``BAD_ARGUMENT``, ``NO_LEADER``, ``UNKNOWN_AGENT``...,
   with its reason); at give-up without an answer, ``CARRIED_OUT`` when the
   agent's Telemetry since the first send shows the command's effect
   (:func:`evidence`: ARM armed, DISARM disarmed, TAKEOFF airborne or a take-off
   mode, LAND and RETURN their modes; each a change from what it was when the
   command was first sent), else ``NO_ANSWER``.

:class:`StationCore` does no I/O, starts no thread and reads no clock:
``handle(msg, now)``, ``submit(spec, now)`` and ``tick(now)`` return the
:class:`StOut` to send; ``next_deadline()`` says when to tick next. ``now`` is any
monotonic clock in seconds; events carry ``now + wall_offset`` (Unix time).

With ``passive=True`` (replay) the core sends nothing and an agent counts as
connected while anything from it was heard in the last ``passive_timeout``.

The runtime that drives it over Zenoh or a radio is :mod:`swarm.runtime.station`.
"""

from __future__ import annotations

import itertools
import json
import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

from swarm.core.gslink import FLAG_AIRBORNE, FLAG_ARMED, FLAG_FC_OK, FLAG_HOLDING, is_station, mode_name
from swarm.core.messages import (
    GCS_ID,
    AckResult,
    AgentState,
    Command,
    CommandAck,
    CommandKind,
    GSAdvertize,
    GSConnect,
    GSConnectAck,
    GSHeartbeat,
    Message,
    Phase,
    Pose,
    PoseReport,
    Telemetry,
    check_name,
)
from swarm.core.pilot import MAX_TAKEOFF_M
from swarm.errors import SwarmError

NO_ANSWER = "NO_ANSWER"
#: no answer, but the agent's Telemetry shows the command's effect (see :func:`evidence`)
CARRIED_OUT = "CARRIED_OUT"
#: every result a command can end with: the agents' answers, then the station's two
RESULTS = (*(r.name for r in AckResult), CARRIED_OUT, NO_ANSWER)
#: results that mean the command was carried out
DONE_RESULTS = (AckResult.ACCEPTED.name, CARRIED_OUT)
KINDS: dict[str, CommandKind] = {k.name.lower(): k for k in CommandKind}
#: kinds a swarm target accepts (FOLLOW and STOP through the leader; the rest fanned out)
SWARM_KINDS = {
    CommandKind.ARM,
    CommandKind.DISARM,
    CommandKind.TAKEOFF,
    CommandKind.LAND,
    CommandKind.RETURN,
    CommandKind.FOLLOW,
    CommandKind.STOP,
}
AGENT_KINDS = {
    CommandKind.ARM,
    CommandKind.DISARM,
    CommandKind.TAKEOFF,
    CommandKind.LAND,
    CommandKind.RETURN,
    CommandKind.GOTO,
    CommandKind.WAYPOINT,
    CommandKind.STOP,
}
ALT_AMSL = (-1000.0, 5553.0)  # what a Command can carry (decimetres, offset 1000 m)


class CommandRefused(SwarmError):
    """A command the station will not send; ``status`` is the HTTP-like code
    (400 bad request, 404 unknown agent, 409 not connected / no leader / replay)."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


@dataclass(frozen=True)
class StationConfig:
    advertize_interval: float = 1.0
    connect_retry: float = 1.0
    connect_give_up: float = 15.0
    heartbeat_interval: float = 1.0
    min_timeout: float = 2.0
    timeout_heartbeats: float = 3.0
    #: gaps between a command's tries (the last one repeats), and how long it is tried
    command_backoff: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0, 4.0)
    command_give_up: float = 12.0
    trail_s: float = 60.0
    trail_points: int = 120
    events: int = 200
    passive_timeout: float = 5.0

    def __post_init__(self) -> None:
        for k in (
            "advertize_interval",
            "connect_retry",
            "connect_give_up",
            "heartbeat_interval",
            "min_timeout",
            "timeout_heartbeats",
            "command_give_up",
            "trail_s",
            "passive_timeout",
        ):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{k} {v!r}: a positive number of seconds")
        b = self.command_backoff
        if not (
            isinstance(b, tuple)
            and b
            and all(isinstance(x, (int, float)) and math.isfinite(x) and x > 0 for x in b)
        ):
            raise ValueError(f"command_backoff {b!r}: a tuple of positive numbers of seconds")
        for k in ("trail_points", "events"):
            v = getattr(self, k)
            if not (isinstance(v, int) and v > 0):
                raise ValueError(f"{k} {v!r}: a positive integer")


@dataclass(frozen=True)
class StOut:
    """A message to send: ``to`` an agent id (its inbox ``swarm/<name>``), or 0 for
    ``swarm/GSAdvertize``."""

    to: int
    name: str
    msg: Message


@dataclass(frozen=True)
class Event:
    t: float  # Unix time
    kind: str  # connect | disconnect | leader | command | info
    text: str

    def as_dict(self) -> dict[str, Any]:
        return {"t": round(self.t, 3), "kind": self.kind, "text": self.text}


# -- commands --------------------------------------------------------------------


@dataclass(frozen=True)
class CommandSpec:
    """A validated command request: ``target`` an agent id or None for the swarm."""

    target: int | None
    kind: CommandKind
    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0
    heading: float = 0.0


def _number(body: dict[str, Any], key: str, lo: float, hi: float, what: str) -> float:
    """``body[key]`` as a float in ``lo..hi``. Any JSON value is refused with a short
    reason: NaN and infinities, and integers of any size (compared exactly, never
    converted first: a 400-digit integer overflows a float).

    Raises:
        CommandRefused: (400) missing, not a number, not finite, out of range.
    """
    if key not in body:
        raise CommandRefused(400, f"{what} needs {key!r}")
    v = body[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        names = {str: "a string", list: "a list", dict: "an object", type(None): "null", bool: "true/false"}
        raise CommandRefused(400, f"{key!r} must be a number, not {names.get(type(v), type(v).__name__)}")
    if isinstance(v, float) and not math.isfinite(v):
        shown = "NaN" if math.isnan(v) else ("Infinity" if v > 0 else "-Infinity")
        raise CommandRefused(400, f"{key!r} must be a number, not {shown}")
    if not lo <= v <= hi:
        shown = str(v) if isinstance(v, float) or abs(v) < 10**15 else "a number of more than 15 digits"
        raise CommandRefused(400, f"{key!r} {shown} outside {lo:g}..{hi:g}")
    return float(v)


def parse_command(body: Any) -> CommandSpec:
    """The API's command object (``{"target": id | "swarm", "kind": ..., args}``) as a
    :class:`CommandSpec`.

    Raises:
        CommandRefused: (400) not an object, unknown kind or target form, a kind the
            target does not take, a missing or out-of-range argument.
    """
    if not isinstance(body, dict):
        raise CommandRefused(400, "a command is a JSON object")
    kind_s = body.get("kind")
    if not isinstance(kind_s, str) or kind_s.lower() not in KINDS:
        # a short reason whatever was sent (a 60 KB string, a nested list)
        shown = (
            repr(kind_s[:24]) + ("..." if len(kind_s) > 24 else "")
            if isinstance(kind_s, str)
            else f"of type {type(kind_s).__name__}"
            if isinstance(kind_s, (list, dict, int))
            else repr(kind_s)
        )
        raise CommandRefused(400, f"unknown command kind {shown}: one of {', '.join(KINDS)}")
    kind = KINDS[kind_s.lower()]
    if "target" not in body:
        raise CommandRefused(400, "a command needs a 'target': an agent id or \"swarm\"")
    t = body["target"]
    target: int | None
    if t == "swarm":
        target = None
        if kind not in SWARM_KINDS:
            raise CommandRefused(400, f"{kind.name.lower()} is for one agent, not the swarm")
    elif isinstance(t, int) and not isinstance(t, bool):
        if not 1 <= t <= 250:
            shown = str(t) if abs(t) < 10**15 else "a number of more than 15 digits"
            raise CommandRefused(400, f"target {shown} is not an agent id (1..250)")
        target = t
        if kind not in AGENT_KINDS:
            raise CommandRefused(400, f'{kind.name.lower()} is a swarm command: target "swarm"')
    else:
        shown = (
            repr(t[:24]) + ("..." if len(t) > 24 else "")
            if isinstance(t, str)
            else f"of type {type(t).__name__}"
            if isinstance(t, (list, dict))
            else repr(t)
        )
        raise CommandRefused(400, f'target {shown}: an agent id (1..250) or "swarm"')
    what = kind.name.lower()
    if kind == CommandKind.TAKEOFF:  # the pilot's range (swarm.core.pilot): refused here, not in the air
        return CommandSpec(target, kind, alt=_number(body, "alt", 1.0, MAX_TAKEOFF_M, what))
    if kind in (CommandKind.GOTO, CommandKind.WAYPOINT):
        return CommandSpec(
            target,
            kind,
            lat=_number(body, "lat", -90.0, 90.0, what),
            lon=_number(body, "lon", -180.0, 180.0, what),
            alt=_number(body, "alt", *ALT_AMSL, what),
        )
    if kind == CommandKind.FOLLOW:
        return CommandSpec(target, kind, heading=_number(body, "heading", 0.0, 360.0, what) % 360.0)
    return CommandSpec(target, kind)


@dataclass(frozen=True)
class _Seen:
    """What the station saw of an agent's vehicle when a command was first sent."""

    mode: str
    armed: bool | None
    airborne: bool | None
    holding: bool | None


_TAKEOFF_MODES = ("AUTO.TAKEOFF",)
_LAND_MODES = ("AUTO.LAND", "LAND")
_RETURN_MODES = ("AUTO.RTL", "RTL")


def evidence(kind: CommandKind, before: _Seen, now: _Seen) -> str | None:
    """Why the agent's Telemetry shows ``kind`` carried out, or None.

    Only a change since the command was first sent counts (an agent armed before
    ARM proves nothing). FOLLOW, STOP, GOTO and WAYPOINT leave no mark that only they
    leave (holding also comes from a stale pose or a neighbour too close): without an
    answer they are ``NO_ANSWER``.
    """
    if kind == CommandKind.ARM and now.armed is True and before.armed is not True:
        return "armed"
    if kind == CommandKind.DISARM and now.armed is False and before.armed is not False:
        return "disarmed"
    if kind == CommandKind.TAKEOFF:
        if now.airborne is True and before.airborne is not True:
            return "airborne"
        if now.mode in _TAKEOFF_MODES and before.mode not in _TAKEOFF_MODES:
            return f"mode {now.mode}"
    for k, modes in ((CommandKind.LAND, _LAND_MODES), (CommandKind.RETURN, _RETURN_MODES)):
        if kind == k and now.mode in modes and before.mode not in modes:
            return f"mode {now.mode}"
    return None


@dataclass
class _Pending:
    request: Request
    agent: int  # the addressee (for a swarm command: the leader it was last sent to)
    swarm: bool  # Command(target=0) to the leader
    msg: Command
    first_sent: float = 0.0
    tries: int = 0
    next_try: float = 0.0
    sent_to: set[int] = field(default_factory=set)
    before: dict[int, _Seen] = field(default_factory=dict)  # by agent, at its first send
    shown: str | None = None  # evidence seen in Telemetry (agent: what)
    refusal: tuple[int, str, str] | None = None  # a swarm "not here" answer: agent, result, reason
    result: str | None = None
    reason: str = ""

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"agent": self.agent, "result": self.result, "reason": self.reason}
        if self.swarm:
            d["swarm"] = True
        return d


@dataclass
class Request:
    """One submitted command and its per-agent outcomes."""

    id: int
    spec: CommandSpec
    pending: list[_Pending] = field(default_factory=list)

    @property
    def done(self) -> bool:
        return all(p.result is not None for p in self.pending)

    @property
    def status(self) -> int:
        """200, or 504 when no addressee answered at all."""
        if self.pending and all(p.result == NO_ANSWER for p in self.pending):
            return 504
        return 200

    def body(self) -> dict[str, Any]:
        ok = bool(self.pending) and all(p.result in DONE_RESULTS for p in self.pending)
        out: dict[str, Any] = {"ok": ok, "results": [p.as_dict() for p in self.pending]}
        if self.status == 504:
            out["error"] = "no answer after retries"
        return out


# -- agents ----------------------------------------------------------------------


@dataclass
class AgentView:
    """What the station knows of one agent."""

    id: int
    name: str
    connected: bool = False
    ever_connected: bool = False
    connect_seq: int | None = None  # a GSConnect awaiting its ack
    next_connect: float = 0.0
    last_heard: float = -math.inf
    last_telemetry: float = -math.inf
    hb_interval: float = 1.0
    pose: Pose | None = None
    mode: str = ""
    armed: bool | None = None
    airborne: bool | None = None
    holding: bool | None = None
    #: the agent's link to its flight controller: None until one was seen, then
    #: whether Telemetry says it is up (FLAG_FC_OK)
    vehicle_link: bool | None = None
    battery: int | None = None
    rssi: int | None = None
    remrssi: int | None = None
    groundspeed: float | None = None
    phase: Phase | None = None
    leader: int = 0
    pool: frozenset[int] = frozenset()
    members: frozenset[int] = frozenset()
    locked: bool = False
    #: (t, lat, lon, the point as JSON text): formatted once when stored, because
    #: formatting 50 agents' trails at every push cost more than the messages
    trail: deque[tuple[float, float, float, str]] = field(default_factory=deque)

    def as_dict(self, now: float) -> dict[str, Any]:
        d = self._fields(now)
        d["trail"] = [[p[1], p[2]] for p in self.trail]
        return d

    def as_json(self, now: float) -> str:
        """``json.dumps(self.as_dict(now))``, with the trail's cached point texts."""
        return (
            json.dumps(self._fields(now))[:-1] + ', "trail": [' + ", ".join(p[3] for p in self.trail) + "]}"
        )

    def _fields(self, now: float) -> dict[str, Any]:
        p = self.pose
        return {
            "id": self.id,
            "name": self.name,
            "connected": self.connected,
            "last_seen_s": round(now - self.last_heard, 1) if math.isfinite(self.last_heard) else None,
            "lat": round(p.lat, 7) if p else None,
            "lon": round(p.lon, 7) if p else None,
            "alt": round(p.alt, 1) if p else None,
            "heading": round(p.heading, 1) if p else None,
            "groundspeed": None if self.groundspeed is None else round(self.groundspeed, 2),
            "mode": self.mode or None,
            "armed": self.armed,
            "airborne": self.airborne,
            "holding": self.holding,
            "vehicle_link": self.vehicle_link,
            "battery": self.battery,
            "rssi": self.rssi,
            "remrssi": self.remrssi,
            "phase": self.phase.name if self.phase is not None else None,
            "leader": self.leader,
            "pool": sorted(self.pool),
            "members": sorted(self.members),
            "locked": self.locked,
        }


def _has_position(p: Pose) -> bool:
    return not (p.lat == 0.0 and p.lon == 0.0)  # NO_POSE: an agent before its first fix


@dataclass
class StationCounters:
    received: int = 0
    ignored: int = 0
    unknown_agent: int = 0
    connect_sent: int = 0
    heartbeats_sent: int = 0
    stale_connect_acks: int = 0
    commands_sent: int = 0
    command_retries: int = 0
    duplicate_acks: int = 0
    late_acks: int = 0


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
        self._finished: list[Request] = []
        self.counters = StationCounters()
        self.leader = 0
        self._next_advertize = -math.inf
        self._next_hb = -math.inf
        self._hb_seq = 0
        # the runtime starts commands at a random seq: an agent remembers answers by
        # (station, seq), and a restarted station must not reuse the seqs it just used
        self._seq = itertools.count(first_seq)
        self._connect_seq = itertools.count(1)
        self._request_ids = itertools.count(1)
        self._pending: dict[int, _Pending] = {}  # by seq
        self._answered: deque[tuple[int, int]] = deque(maxlen=256)  # (agent, seq) completed
        self._leader_dirty = False  # a connection, phase or leader changed

    # -- inputs -----------------------------------------------------------------
    def handle(self, msg: Message, now: float, name: str = "") -> list[StOut]:
        """One message heard. ``name`` is the agent name from the key of a pose or
        state sample (``swarm/<name>/pose``); unused for the other messages."""
        self.counters.received += 1
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
            self._ack(msg, now)
        elif isinstance(msg, AgentState):
            self._state(msg, name, now)
        elif isinstance(msg, PoseReport):
            aid = self._by_name.get(name)
            if aid is None:
                self.counters.unknown_agent += 1
            else:
                self.observe_pose(aid, msg.pose, now)
        elif isinstance(msg, Command) and self.passive and is_station(msg.sender):
            who = self._label(msg.target) if msg.target else "the swarm (leader)"
            self._event(now, "command", f"station {msg.sender} sent {msg.kind.name} to {who} (seq {msg.seq})")
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
        if _has_position(pose):
            a.pose = pose
            if a.groundspeed is None or not math.isfinite(a.last_telemetry):
                a.groundspeed = math.hypot(pose.vn, pose.ve)
            self._trail(a, pose, now)

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
        kind = spec.kind
        args = {"lat": spec.lat, "lon": spec.lon, "alt": spec.alt, "heading": spec.heading}
        plan: list[tuple[int, int]] = []  # (agent, Command.target)
        if spec.target is not None:
            a = self.agents.get(spec.target)
            if a is None:
                raise CommandRefused(404, f"unknown agent {spec.target}")
            if not a.connected:
                raise CommandRefused(409, f"{self._label(a.id)} is not connected")
            plan.append((a.id, a.id))
        else:
            connected = sorted(i for i, a in self.agents.items() if a.connected)
            if kind in (CommandKind.FOLLOW, CommandKind.STOP):
                if self.leader:
                    plan.append((self.leader, 0))
                elif kind == CommandKind.FOLLOW:
                    raise CommandRefused(409, "no leader elected yet")
            if kind != CommandKind.FOLLOW:
                plan += [(i, i) for i in connected]
            if not plan:
                raise CommandRefused(409, "no connected agents")
        req = Request(next(self._request_ids), spec)
        out: list[StOut] = []
        for agent, target in plan:
            seq = self._next_seq()
            p = _Pending(req, agent, target == 0, Command(self.id, seq, target, kind, **args), first_sent=now)
            req.pending.append(p)
            self._pending[seq] = p
            out += self._send_command(p, now)
        return req, out

    def _next_seq(self) -> int:
        while True:
            seq = next(self._seq) & 0xFFFF
            if seq and seq not in self._pending:
                return seq

    def _send_command(self, p: _Pending, now: float) -> list[StOut]:
        if p.swarm and self.leader and self.leader in self.agents:
            p.agent = self.leader  # re-resolved at every try: elections happen
        if p.agent not in p.before:
            p.before[p.agent] = self._seen(self.agents[p.agent])
        p.sent_to.add(p.agent)
        p.tries += 1
        gaps = self.cfg.command_backoff
        p.next_try = now + gaps[min(p.tries, len(gaps)) - 1]
        if p.tries == 1:
            self.counters.commands_sent += 1
        else:
            self.counters.command_retries += 1
        return [StOut(p.agent, self.agents[p.agent].name, p.msg)]

    @staticmethod
    def _seen(a: AgentView) -> _Seen:
        return _Seen(a.mode, a.armed, a.airborne, a.holding)

    def _ack(self, msg: CommandAck, now: float) -> None:
        a = self.agents.get(msg.sender)
        if a is not None:
            self._heard(a, now)
        if self.passive:
            self._event(
                now,
                "command",
                f"{self._label(msg.sender)} answered seq {msg.seq}: "
                f"{msg.result.name}" + (f" ({msg.reason})" if msg.reason else ""),
            )
            return
        p = self._pending.get(msg.seq)
        if p is None or msg.sender not in p.sent_to:
            if (msg.sender, msg.seq) in self._answered:
                self.counters.duplicate_acks += 1
            else:
                self.counters.late_acks += 1
            return
        if p.swarm and msg.result in (AckResult.REJECTED, AckResult.NO_LEADER):
            # "not the leader" / "no leader": not final while there is time to find the
            # leader (the agent keeps no record of it, so it will answer again)
            p.refusal = (msg.sender, msg.result.name, msg.reason)
            if now - p.first_sent < self.cfg.command_give_up:
                if self.leader and msg.sender != self.leader:
                    p.next_try = min(p.next_try, now)  # it already sees another leader: go now
                return
        p.agent = msg.sender
        self._complete(p, msg.result.name, msg.reason, now)

    def _complete(self, p: _Pending, result: str, reason: str, now: float) -> None:
        p.result, p.reason = result, reason
        del self._pending[p.msg.seq]
        for agent in p.sent_to:
            self._answered.append((agent, p.msg.seq))
        what = p.msg.kind.name + (" (swarm)" if p.swarm else "")
        text = (
            f"{what} -> {self._label(p.agent)}: {result}"
            + (f" ({reason})" if reason else "")
            + f" [seq {p.msg.seq}]"
        )  # the agent's own log names the same seq
        self._event(now, "command", text)
        if p.request.done:
            self._finished.append(p.request)

    def _give_up(self, p: _Pending, now: float) -> None:
        tries = f"{p.tries} {'try' if p.tries == 1 else 'tries'} in {now - p.first_sent:.0f} s"
        if p.shown is not None:
            agent, _, what = p.shown.partition(":")
            p.agent = int(agent)
            self._complete(p, CARRIED_OUT, f"no answer after {tries}, but it shows {what}", now)
        elif p.refusal is not None:
            p.agent, result, reason = p.refusal
            self._complete(p, result, reason, now)
        else:
            self._complete(p, NO_ANSWER, f"no answer after {tries}", now)

    def _look_for_evidence(self, a: AgentView) -> None:
        """Telemetry from ``a``: does it show a pending command carried out?"""
        now_seen = None
        for p in self._pending.values():
            before = p.before.get(a.id)
            if before is None or p.shown is not None:
                continue
            now_seen = now_seen or self._seen(a)
            what = evidence(p.msg.kind, before, now_seen)
            if what is not None:
                p.shown = f"{a.id}:{what}"

    # -- time -----------------------------------------------------------------------
    def tick(self, now: float) -> list[StOut]:
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
        for p in list(self._pending.values()):
            if now + 1e-9 >= p.first_sent + self.cfg.command_give_up:
                self._give_up(p, now)
            elif now + 1e-9 >= p.next_try:
                out += self._send_command(p, now)
        self._update_leader(now)
        return out

    def next_deadline(self) -> float:
        times = [self._next_advertize, self._next_hb] if not self.passive else []
        for a in self.agents.values():
            if a.connected:
                times.append(self._last_alive(a) + self._timeout(a))
            if a.connect_seq is not None and not self.passive:
                times.append(a.next_connect)
        for p in self._pending.values():
            times.append(min(p.next_try, p.first_sent + self.cfg.command_give_up))
        return min(times) if times else math.inf

    # -- outputs for the runtime ---------------------------------------------------------
    def take_events(self) -> list[Event]:
        ev, self._new_events = self._new_events, []
        return ev

    def take_finished(self) -> list[Request]:
        done, self._finished = self._finished, []
        return done

    def snapshot(self, now: float) -> dict[str, Any]:
        """The API's state object (without the station's link description)."""
        return {
            "time": round(now + self.wall_offset, 3),
            "leader": self.leader,
            "agents": [self.agents[i].as_dict(now) for i in sorted(self.agents)],
            "events": [e.as_dict() for e in self.events],
        }

    def snapshot_json(self, now: float, station: dict[str, Any]) -> str:
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

    def _last_alive(self, a: AgentView) -> float:
        return a.last_heard if self.passive else a.last_telemetry

    def _timeout(self, a: AgentView) -> float:
        if self.passive:
            return self.cfg.passive_timeout
        return max(self.cfg.min_timeout, self.cfg.timeout_heartbeats * a.hb_interval)

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
        if _has_position(msg.pose):
            a.pose = msg.pose
            self._trail(a, msg.pose, now)
        fc = bool(msg.flags & FLAG_FC_OK)  # without a flight controller these are unknown
        self._vehicle_link(a, fc, now)
        a.mode = mode_name(msg.mode) if fc or a.vehicle_link is None else ""
        a.armed = bool(msg.flags & FLAG_ARMED) if fc else None
        a.airborne = bool(msg.flags & FLAG_AIRBORNE) if fc else None
        a.holding = bool(msg.flags & FLAG_HOLDING)
        a.battery = None if msg.battery > 100 else msg.battery
        a.rssi, a.remrssi = msg.rssi, msg.remrssi
        a.groundspeed = msg.groundspeed if fc else a.groundspeed
        self._set_election(a, msg.phase, msg.leader)
        if self._pending:
            self._look_for_evidence(a)
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
        a.vehicle_link = up

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

    def _trail(self, a: AgentView, pose: Pose, now: float) -> None:
        tr = a.trail
        spacing = self.cfg.trail_s / self.cfg.trail_points
        lat, lon = round(pose.lat, 7), round(pose.lon, 7)
        text = f"[{lat!r}, {lon!r}]"
        if not tr or now - tr[-1][0] >= spacing:
            tr.append((now, lat, lon, text))
        else:
            tr[-1] = (tr[-1][0], lat, lon, text)  # keep the newest point at the head
        while tr and (now - tr[0][0] > self.cfg.trail_s or len(tr) > self.cfg.trail_points):
            tr.popleft()

    def _update_leader(self, now: float) -> None:
        if not self._leader_dirty:
            return
        self._leader_dirty = False
        votes: Counter[int] = Counter()
        for a in self.agents.values():
            if a.connected and a.phase in (Phase.LEADER, Phase.MEMBER) and a.leader:
                votes[a.leader] += 1
        leader = 0
        if votes:
            best = max(votes.values())
            top = [i for i, n in votes.items() if n == best and i in self.agents and self.agents[i].connected]
            leader = max(top) if top else 0
        if leader != self.leader:
            self.leader = leader
            for p in self._pending.values():
                if p.swarm and leader and p.agent != leader:
                    p.next_try = min(p.next_try, now)  # to the new leader at the next tick
            if leader:
                self._event(now, "leader", f"{self._label(leader)} is the leader")
            else:
                self._event(now, "leader", "no leader")


def outcome(req: Request) -> tuple[int, dict[str, Any]]:
    """(HTTP-like status, body) of a finished request."""
    return req.status, req.body()


__all__ = [
    "CARRIED_OUT",
    "DONE_RESULTS",
    "KINDS",
    "NO_ANSWER",
    "RESULTS",
    "AgentView",
    "CommandRefused",
    "CommandSpec",
    "Event",
    "Request",
    "StOut",
    "StationConfig",
    "StationCore",
    "evidence",
    "parse_command",
]
