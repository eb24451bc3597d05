"""The ground station's data: its settings, what it sends, its events, its view of each agent.

Theory of operation
-------------------
:class:`StationConfig` holds the station protocol's intervals and sizes (checked when
built: positive numbers of seconds, positive counts). :class:`StOut` is one message to send (to an
agent's inbox, or 0 for ``swarm/GSAdvertize``); :class:`Event` one line of the
station's log (connect, disconnect, leader, command, vehicle, info) in Unix time.
:class:`AgentView` is what the station knows of one agent (position and trail, mode,
flags, battery, radio, measured Telemetry loss, election state), as the API's dict or
JSON text; its trail's
points are formatted once when stored (:meth:`AgentView.add_trail`).
:class:`StationCounters` counts what the station received, ignored and sent.

Filled and read by :class:`swarm.core.station.core.StationCore`. Pure: no I/O, no clock.
"""

from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass, field

from swarm.core.flight.geofence import Geofence
from swarm.core.station.alerts import AlertConfig, LinkHealth
from swarm.core.station.rows import AgentRow, DoingRow, EventRow
from swarm.core.wire.message_types import Message, Phase, Pose


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
    #: a command the agent answers IN_PROGRESS (its vehicle still at it) is followed
    #: this long at most after its first send, for its result
    command_in_progress_limit: float = 150.0
    trail_s: float = 60.0
    trail_points: int = 120
    events: int = 200
    passive_timeout: float = 5.0
    #: what a command may ask (swarm.core.flight.geofence); submit refuses the rest
    fence: Geofence = field(default_factory=Geofence)
    #: battery and link-loss thresholds, the link's judgement (swarm.core.station.alerts)
    alerts: AlertConfig = field(default_factory=AlertConfig)

    def __post_init__(self) -> None:
        for k in (
            "advertize_interval",
            "connect_retry",
            "connect_give_up",
            "heartbeat_interval",
            "min_timeout",
            "timeout_heartbeats",
            "command_give_up",
            "command_in_progress_limit",
            "trail_s",
            "passive_timeout",
        ):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{k} {v!r}: a positive number of seconds")
        if not isinstance(self.alerts, AlertConfig):
            raise ValueError(f"alerts {self.alerts!r}: an AlertConfig")
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

    def as_dict(self) -> EventRow:
        return {"t": round(self.t, 3), "kind": self.kind, "text": self.text}


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
    #: the agent's autopilot left setpoint control by itself (a failsafe): a command takes it back
    control_lost: bool | None = None
    #: the agent's link to its flight controller: None until one was seen, then
    #: whether Telemetry says it is up (FLAG_FC_OK)
    vehicle_link: bool | None = None
    battery: int | None = None
    rssi: int | None = None
    remrssi: int | None = None
    groundspeed: float | None = None
    # the Telemetry's detail block (an agent that sends none: None, unknown)
    rel_alt: float | None = None  # above the autopilot's home
    climb: float | None = None
    gps_fix: int | None = None
    satellites: int | None = None
    home_dist: float | None = None
    ready: bool | None = None  # the autopilot's pre-arm checks pass
    phase: Phase | None = None
    leader: int = 0
    pool: frozenset[int] = frozenset()
    members: frozenset[int] = frozenset()
    locked: bool = False
    #: Telemetry arrivals: measured loss, the silence that means lost (swarm.core.station.alerts)
    link: LinkHealth = field(default_factory=LinkHealth)
    #: (t, lat, lon, the point as JSON text): formatted once when stored, because
    #: formatting 50 agents' trails at every push cost more than the messages
    trail: deque[tuple[float, float, float, str]] = field(default_factory=deque)
    #: where Telemetry last showed the vehicle on the ground (lat, lon, m AMSL): its
    #: home once it takes off from there; None until seen on the ground
    home: tuple[float, float, float] | None = None
    #: the route the station knows it flies (swarm.core.station.plan): [[lat, lon, alt above
    #: home]...], its go-to target last; None without one
    route: list[list[float]] | None = None
    #: what its last command is doing on the vehicle (swarm.core.station.followup):
    #: {"kind", "request", "state", "text", "since"}; None: nothing followed
    doing: DoingRow | None = None

    def as_dict(self, now: float) -> AgentRow:
        d = self._fields(now)
        d["trail"] = [[p[1], p[2]] for p in self.trail]
        return d

    def as_json(self, now: float) -> str:
        """``json.dumps(self.as_dict(now))``, with the trail's cached point texts."""
        return (
            json.dumps(self._fields(now))[:-1] + ', "trail": [' + ", ".join(p[3] for p in self.trail) + "]}"
        )

    def _fields(self, now: float) -> AgentRow:
        d = self._base_fields(now)
        # the plan's fields only when known: 50 agents' nulls would weigh on every full state
        if self.home:
            d["home"] = [round(self.home[0], 7), round(self.home[1], 7)]
        if self.route:
            d["route"] = self.route
        if self.doing is not None:
            d["doing"] = self.doing
        return d

    def _base_fields(self, now: float) -> AgentRow:
        p = self.pose
        return {
            "id": self.id,
            "name": self.name,
            "connected": self.connected,
            "last_seen_s": round(now - self.last_heard, 1) if math.isfinite(self.last_heard) else None,
            "hb_s": round(self.hb_interval, 3),  # its Telemetry interval: the page's measure of "silent"
            "lat": round(p.lat, 7) if p else None,
            "lon": round(p.lon, 7) if p else None,
            "alt": round(p.alt, 1) if p else None,
            "home_alt": self._home_alt(),
            "rel_alt": None if self.rel_alt is None else round(self.rel_alt, 1),
            "climb": None if self.climb is None else round(self.climb, 2),
            "gps_fix": self.gps_fix,
            "satellites": self.satellites,
            "home_dist": None if self.home_dist is None else round(self.home_dist),
            "ready": self.ready,
            "heading": round(p.heading, 1) if p else None,
            "groundspeed": None if self.groundspeed is None else round(self.groundspeed, 2),
            "mode": self.mode or None,
            "armed": self.armed,
            "airborne": self.airborne,
            "holding": self.holding,
            "control_lost": self.control_lost,
            "vehicle_link": self.vehicle_link,
            "battery": self.battery,
            "rssi": self.rssi,
            "remrssi": self.remrssi,
            "loss_pct": None if self.link.loss is None else round(100.0 * self.link.loss, 1),
            "phase": self.phase.name if self.phase is not None else None,
            "leader": self.leader,
            "pool": sorted(self.pool),
            "members": sorted(self.members),
            "locked": self.locked,
        }

    def _home_alt(self) -> float | None:
        """Home's height AMSL: the autopilot's (AMSL less its height above home) when the
        agent says, else where the station saw it on the ground; None: unknown. One
        reference, whenever the station started."""
        if self.rel_alt is not None and self.pose is not None:
            return round(self.pose.alt - self.rel_alt, 1)
        return round(self.home[2], 1) if self.home else None

    def add_trail(self, pose: Pose, now: float, trail_s: float, trail_points: int) -> None:
        """Keep ``pose`` in the trail: one point per ``trail_s / trail_points``, the
        newest replacing the head until then; points older than ``trail_s`` or beyond
        ``trail_points`` dropped."""
        tr = self.trail
        spacing = trail_s / trail_points
        lat, lon = round(pose.lat, 7), round(pose.lon, 7)
        text = f"[{lat!r}, {lon!r}]"
        if not tr or now - tr[-1][0] >= spacing:
            tr.append((now, lat, lon, text))
        else:
            tr[-1] = (tr[-1][0], lat, lon, text)  # keep the newest point at the head
        while tr and (now - tr[0][0] > trail_s or len(tr) > trail_points):
            tr.popleft()


def has_position(p: Pose) -> bool:
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
