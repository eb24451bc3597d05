"""Stations joined over Zenoh: the sealed envelope, its replay guard, and what may cross.

Theory of operation
-------------------
Ground stations on different machines meet on a Zenoh network (through Zenoh
routers) under a key space of their own, beside the agents' ``swarm/...``:

=============================  =================================================
``gcs/<station>/state``        the station's agents (each with ``net``), events,
                               swarms, alerts: whole, about twice a second
``gcs/<station>/command``      a queryable: a command for one of its agents; the
                               reply is the result
=============================  =================================================

Anyone who can reach a router can publish there, so every payload is an
*envelope* (:func:`seal`, :meth:`Gate.open`)::

    b"SWG1" | kind (1) | flags (1) | time (8, µs since 1970) | instance (4)
           | sender length (1) | sender | body | HMAC-SHA256 (32, when signed)

The MAC (with a key derived from the swarm key for this use only, :func:`fed_key`)
covers everything before it. A state's body is deflated (flag :data:`FLAG_DEFLATE`,
zlib: a state of 200 agents in flight is 0.28 MB of JSON, twice a second); the MAC
covers the deflated bytes, so a signed envelope is checked before anything is
inflated, and inflating stops at :data:`MAX_ENVELOPE` (a bomb is refused as too large).
 A :class:`Gate` keeps, per sender, the newest state's
time it accepted (a state not strictly newer is a replay) and the times of the
commands and results it took in the last :data:`WINDOW_S` (one seen again is a
replay; these may arrive out of order); a signed envelope, and any command or
result, more than :data:`WINDOW_S` from the receiver's clock is refused (a recording
played later). A state stamped more than :data:`FUTURE_S` ahead of the receiver's
clock is refused, signed or not: it would become the sender's newest and every real
state after it would be "not newer" (one forged unsigned state stamped in 2100 froze
a station's view for good). A gate with a key refuses unsigned envelopes; without a
key it accepts unsigned states, and commands only when told so
(``accept_unsigned_commands``). A result names the request it answers (its sender
and time), so an old result cannot answer a new request.

A gate's record crosses a restart of its station (:meth:`Gate.records`,
:meth:`Gate.restore`: the runtime keeps it in the station's state folder), so a
command overheard on the router and replayed to the restarted station is still one
seen before. What is restored is checked as hostile input, and a sender's newest
state time more than :data:`FUTURE_S` ahead of the clock at restore is dropped (a
clock set back across the restart would otherwise freeze that sender).

What crosses is checked as hostile input: a state is JSON of at most
:data:`MAX_ENVELOPE` bytes, its agents, events, swarms and alerts are re-built from
known fields with their types, their counts and texts bounded (:func:`clean_state`;
an alert's kind and level one of the known ones, at most :data:`MAX_ALERTS`);
anything else is dropped. A command for another
station's agent is checked here against this station's geofence
(:func:`check_remote`) before it is sent, and again by the station that carries it
out. Everything here is pure: times are given, nothing is read or sent.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import struct
import zlib
from dataclasses import dataclass, replace
from typing import Any

from swarm.core.flight.geofence import Geofence
from swarm.core.station.alerts import KINDS as ALERT_KINDS
from swarm.core.station.alerts import LEVELS as ALERT_LEVELS
from swarm.core.station.alerts import QUIET as ALERT_QUIET
from swarm.core.station.commands import CommandRefused, CommandSpec
from swarm.core.station.rows import AgentRow, AlertRow, EventRow, StationState, SwarmRow
from swarm.core.wire.message_types import NAME_RE, CommandKind
from swarm.errors import SwarmError

PREFIX = "gcs"
MAGIC = b"SWG1"
KIND_STATE, KIND_COMMAND, KIND_RESULT = b"S", b"C", b"R"
KINDS = (KIND_STATE, KIND_COMMAND, KIND_RESULT)
FLAG_SIGNED = 1
FLAG_DEFLATE = 2  # the body is zlib-deflated (states)
FLAGS = FLAG_SIGNED | FLAG_DEFLATE
MAC_LEN = 32
HEADER = struct.Struct(">4scBQIB")
MAX_ENVELOPE = 1024 * 1024  # a state of 250 agents with trails is well under this
WINDOW_S = 30.0  # a signed envelope this far from our clock is refused
#: a state stamped this far ahead of our clock is refused (stations' clocks in a field
#: without internet: a laptop synchronised a few days before drifts a second or two a
#: day; one forged state may hold a station's view still for at most this long)
FUTURE_S = 10.0
MAX_AGENTS = 250
MAX_EVENTS = 50
MAX_ALERTS = 100  # a station keeps 100 (AlertBook) and shows the open ones and 10 acknowledged
MAX_TRAIL = 600
#: the trail points a station sends of each agent: the newest, as many as a page draws
#: (static/app.js's TRAIL_POINTS); a station keeps 120, and they were 80 % of the bytes
TRAIL_SENT = 40
MAX_TEXT = 200
MAX_SENDERS = 256  # senders a gate remembers (beyond: the one heard longest ago is forgotten)
MAX_ONCE = 4096  # command or result times a gate remembers within the window
_KEY_LABEL = b"uav-swarm station federation v1"


class FederationRefused(SwarmError):
    """An envelope or a body refused (``reason``: one line, for a counter or a log)."""


def state_key(station: str) -> str:
    return f"{PREFIX}/{station}/state"


def command_key(station: str) -> str:
    return f"{PREFIX}/{station}/command"


def fed_key(swarm_key: bytes) -> bytes:
    """The key for station envelopes, derived from the swarm key (never the radio's own)."""
    return hmac.new(swarm_key, _KEY_LABEL, hashlib.sha256).digest()


@dataclass(frozen=True)
class Envelope:
    kind: bytes
    signed: bool
    t_us: int
    instance: int
    sender: str
    body: bytes


def seal(
    kind: bytes,
    sender: str,
    instance: int,
    t_us: int,
    body: bytes,
    key: bytes | None,
    *,
    deflate: bool = False,
) -> bytes:
    """The envelope of ``body`` (signed with ``key``, a :func:`fed_key`, when given;
    deflated when told: states)."""
    name = sender.encode()
    flags = (FLAG_SIGNED if key else 0) | (FLAG_DEFLATE if deflate else 0)
    if deflate:
        body = zlib.compress(body, 6)
    head = HEADER.pack(MAGIC, kind, flags, t_us, instance, len(name)) + name
    data = head + body
    return data + hmac.new(key, data, hashlib.sha256).digest() if key else data


class Stamp:
    """A sender's envelope times: the wall clock in µs, strictly increasing."""

    def __init__(self) -> None:
        self.last = 0

    def next(self, wall_s: float) -> int:
        self.last = max(int(wall_s * 1e6), self.last + 1)
        return self.last


class Gate:
    """Opens envelopes: size, form, signature, replay. Counts what it refuses.

    States (``kind`` :data:`KIND_STATE`) must be strictly newer than the sender's last:
    a late one is dropped, the next comes half a second later. Commands and results
    may cross on the way (two sent at once), so for them each time is taken once:
    the gate remembers the times it took within :data:`WINDOW_S` (at most
    :data:`MAX_ONCE`; a command's or result's time must be inside the window, signed or
    not) and refuses one seen again.
    """

    @property
    def remembered(self) -> int:
        """How many senders' newest stamps the gate keeps (at most ``MAX_SENDERS``)."""
        return len(self._newest)

    def __init__(self, key: bytes | None, *, accept_unsigned_commands: bool = False) -> None:
        self.key = key
        self.accept_unsigned_commands = accept_unsigned_commands
        self._newest: dict[tuple[str, bytes], int] = {}
        self._once: dict[tuple[str, bytes, int], float] = {}  # (sender, kind, time) -> when taken
        self.refused: dict[str, int] = {}
        self.taken = 0  # envelopes accepted: the record changed (what a keeper saves)

    def open(self, data: bytes, wall_s: float, kind: bytes) -> Envelope:
        """The envelope in ``data`` if it is a ``kind`` envelope this gate accepts.

        Raises:
            FederationRefused: too large, malformed, another kind, unsigned or badly
                signed where a signature is needed, replayed or out of the window.
        """
        try:
            env = self._open(data, wall_s, kind)
            if kind == KIND_STATE:
                self._newest[(env.sender, env.kind)] = env.t_us
                if len(self._newest) > MAX_SENDERS:  # names made up by the thousand (without a key)
                    del self._newest[min(self._newest, key=self._newest.__getitem__)]
            else:
                self._take_once(env, wall_s)
        except FederationRefused as exc:
            why = str(exc).split(":")[0]
            self.refused[why] = self.refused.get(why, 0) + 1
            raise
        self.taken += 1
        return env

    def records(self, wall_s: float) -> dict[str, Any]:
        """What this gate must remember across a restart, as JSON values: each sender's
        newest state time, and the commands and results taken in the last two windows."""
        return {
            "states": [[sender, k.decode(), t] for (sender, k), t in self._newest.items()],
            "taken": [
                [sender, k.decode(), t, round(at, 3)]
                for (sender, k, t), at in self._once.items()
                if at >= wall_s - 2 * WINDOW_S
            ],
        }

    def restore(self, records: Any, wall_s: float) -> int:
        """Take back :meth:`records` (from a file: hostile input) at ``wall_s``; the
        entries kept. Malformed entries are skipped; a newest state time more than
        :data:`FUTURE_S` ahead is dropped; taken times older than two windows too.

        Raises:
            FederationRefused: not a record at all (malformed).
        """
        if not isinstance(records, dict):
            raise FederationRefused("malformed: a gate's record is an object")
        states, taken = records.get("states"), records.get("taken")
        if not isinstance(states, list) or not isinstance(taken, list):
            raise FederationRefused("malformed: a gate's record has 'states' and 'taken' lists")
        kept = 0
        horizon = int((wall_s + FUTURE_S) * 1e6)
        for e in states[:MAX_SENDERS]:
            if _entry(e, 3) and e[2] <= horizon and len(self._newest) < MAX_SENDERS:
                key = (e[0], e[1].encode())
                self._newest[key] = max(e[2], self._newest.get(key, 0))
                kept += 1
        for e in taken[:MAX_ONCE]:
            if _entry(e, 4) and _num(e[3]) is not None and wall_s - 2 * WINDOW_S <= e[3] <= wall_s + WINDOW_S:
                if len(self._once) < MAX_ONCE:
                    self._once[(e[0], e[1].encode(), e[2])] = float(e[3])
                    kept += 1
        return kept

    def _take_once(self, env: Envelope, wall_s: float) -> None:
        if abs(env.t_us / 1e6 - wall_s) > WINDOW_S:
            raise FederationRefused(f"out of window: from {env.sender}, {env.t_us / 1e6 - wall_s:+.0f} s")
        for k in [k for k, t in self._once.items() if t < wall_s - 2 * WINDOW_S]:
            del self._once[k]
        tag = (env.sender, env.kind, env.t_us)
        if tag in self._once:
            raise FederationRefused(f"replayed: from {env.sender}")
        if len(self._once) >= MAX_ONCE:
            raise FederationRefused(f"busy: from {env.sender}, {MAX_ONCE} taken in {WINDOW_S:g} s")
        self._once[tag] = wall_s

    def _open(self, data: bytes, wall_s: float, kind: bytes) -> Envelope:
        if len(data) > MAX_ENVELOPE:
            raise FederationRefused(f"too large: {len(data)} bytes (at most {MAX_ENVELOPE})")
        if len(data) < HEADER.size:
            raise FederationRefused("malformed: shorter than a header")
        magic, k, flags, t_us, instance, n = HEADER.unpack_from(data)
        end = HEADER.size + n
        sender = data[HEADER.size : end].decode("ascii", "replace")
        if magic != MAGIC or k != kind or flags & ~FLAGS or not NAME_RE.match(sender):
            raise FederationRefused("malformed: not a station envelope of this kind")
        signed = bool(flags & FLAG_SIGNED)
        body = data[end:]
        if self.key is not None:
            if not signed or len(body) < MAC_LEN:
                raise FederationRefused(f"unsigned: from {sender} (this station has a key)")
            body, mac = body[:-MAC_LEN], body[-MAC_LEN:]
            good = hmac.new(self.key, data[:-MAC_LEN], hashlib.sha256).digest()
            if not hmac.compare_digest(mac, good):
                raise FederationRefused(f"bad signature: from {sender}")
            if abs(t_us / 1e6 - wall_s) > WINDOW_S:
                raise FederationRefused(f"out of window: from {sender}, {t_us / 1e6 - wall_s:+.0f} s")
        elif signed:
            body = body[:-MAC_LEN]  # no key to check it with: taken as unsigned
            signed = False
        if kind == KIND_COMMAND and not signed and not self.accept_unsigned_commands:
            raise FederationRefused(f"unsigned command: from {sender} (give the swarm key, --key)")
        if kind == KIND_STATE and t_us / 1e6 - wall_s > FUTURE_S:
            raise FederationRefused(f"from the future: from {sender}, {t_us / 1e6 - wall_s:+.0f} s")
        if kind == KIND_STATE and t_us <= self._newest.get((sender, kind), 0):
            raise FederationRefused(f"replayed: from {sender}")
        if flags & FLAG_DEFLATE:
            body = inflate(body)
        return Envelope(kind, signed, t_us, instance, sender, body)


def _entry(e: Any, size: int) -> bool:
    """A record's entry: ``[sender, kind, time_us, ...]`` of ``size`` items, each of its type."""
    return (
        isinstance(e, list)
        and len(e) == size
        and isinstance(e[0], str)
        and bool(NAME_RE.match(e[0]))
        and e[1] in ("S", "C", "R")
        and _int(e[2], 1, 2**63 - 1) is not None
    )


def inflate(data: bytes) -> bytes:
    """A deflated body, at most :data:`MAX_ENVELOPE` bytes once inflated.

    Raises:
        FederationRefused: not zlib data (malformed), more than that (too large).
    """
    d = zlib.decompressobj()
    try:
        out = d.decompress(data, MAX_ENVELOPE)
    except zlib.error:
        raise FederationRefused("malformed: the body is not deflated data") from None
    if d.unconsumed_tail:
        raise FederationRefused(f"too large: more than {MAX_ENVELOPE} bytes inflated")
    if not d.eof:
        raise FederationRefused("malformed: the deflated body is cut short")
    return out


def load_body(body: bytes) -> Any:
    """JSON from an envelope's body. Raises FederationRefused."""
    try:
        return json.loads(body.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise FederationRefused("malformed: the body is not JSON") from None


# -- what a state may carry -------------------------------------------------------------


def _num(v: Any) -> float | int | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    if isinstance(v, int):
        return v if abs(v) < 10**15 else None
    return v if math.isfinite(v) else None


def text(v: Any, limit: int = MAX_TEXT) -> str | None:
    """A printable one-line string of at most ``limit`` characters, or None."""
    if not isinstance(v, str):
        return None
    return "".join(c if c.isprintable() else "?" for c in v[:limit])


def _ids(v: Any) -> list[int]:
    if not isinstance(v, list):
        return []
    return sorted(
        {i for i in v[:MAX_AGENTS] if isinstance(i, int) and not isinstance(i, bool) and 1 <= i <= 250}
    )


def _point(v: Any) -> list[float] | None:
    if isinstance(v, list) and len(v) == 2:
        lat, lon = _num(v[0]), _num(v[1])
        if lat is not None and lon is not None and -90 <= lat <= 90 and -180 <= lon <= 180:
            return [lat, lon]
    return None


def _bool(v: Any) -> bool | None:
    return v if isinstance(v, bool) else None


def clean_agent(d: Any) -> AgentRow:
    """A remote agent re-built from the fields a station sends, each of its type.

    Raises:
        FederationRefused: not an object, no valid ``id`` (1..250) or ``name``.
    """
    if not isinstance(d, dict):
        raise FederationRefused("malformed: an agent is an object")
    aid, name = d.get("id"), d.get("name")
    if isinstance(aid, bool) or not isinstance(aid, int) or not 1 <= aid <= 250:
        raise FederationRefused("malformed: an agent id is 1..250")
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise FederationRefused(f"malformed: agent {aid}'s name")
    battery, rssi, remrssi = (_int(d.get(k), -(10**15), 10**15) for k in ("battery", "rssi", "remrssi"))
    leader = d.get("leader")
    if isinstance(leader, bool) or not isinstance(leader, int) or not 0 <= leader <= 250:
        leader = 0
    trail = d.get("trail")
    pts = [_point(p) for p in trail[-MAX_TRAIL:]] if isinstance(trail, list) else []
    net = d.get("net")
    out: AgentRow = {
        "id": aid,
        "name": name,
        "connected": d.get("connected") is True,
        "last_seen_s": _num(d.get("last_seen_s")),
        "hb_s": _num(d.get("hb_s")),
        "lat": _num(d.get("lat")),
        "lon": _num(d.get("lon")),
        "alt": _num(d.get("alt")),
        "home_alt": _num(d.get("home_alt")),
        "rel_alt": _num(d.get("rel_alt")),
        "climb": _num(d.get("climb")),
        "gps_fix": _int(d.get("gps_fix"), 0, 8),
        "satellites": _int(d.get("satellites"), 0, 254),
        "home_dist": _num(d.get("home_dist")),
        "ready": _bool(d.get("ready")),
        "heading": _num(d.get("heading")),
        "groundspeed": _num(d.get("groundspeed")),
        "mode": text(d.get("mode"), 32),
        "armed": _bool(d.get("armed")),
        "airborne": _bool(d.get("airborne")),
        "holding": _bool(d.get("holding")),
        "control_lost": _bool(d.get("control_lost")),
        "vehicle_link": _bool(d.get("vehicle_link")),
        "battery": battery,
        "rssi": rssi,
        "remrssi": remrssi,
        "loss_pct": _num(d.get("loss_pct")),
        "phase": text(d.get("phase"), 32),
        "leader": leader,
        "pool": _ids(d.get("pool")),
        "members": _ids(d.get("members")),
        "locked": d.get("locked") is True,
        "trail": [p for p in pts if p is not None],
        "net": net if isinstance(net, str) and NAME_RE.match(net) else None,
    }
    home = _point(d.get("home"))
    if home is not None:
        out["home"] = home
    return out


def clean_events(v: Any) -> list[EventRow]:
    out: list[EventRow] = []
    for e in v[-MAX_EVENTS:] if isinstance(v, list) else []:
        if isinstance(e, dict) and _num(e.get("t")) is not None:
            out.append(
                {"t": e["t"], "kind": text(e.get("kind"), 16) or "", "text": text(e.get("text")) or ""}
            )
    return out


def clean_swarms(v: Any) -> list[SwarmRow]:
    """The ``swarms`` list (each ``{leader, members, ...}``) with its ids checked."""
    out: list[SwarmRow] = []
    for s in v[:MAX_AGENTS] if isinstance(v, list) else []:
        if isinstance(s, dict) and _ids([s.get("leader")]):
            net = s.get("net")
            net = net if isinstance(net, str) and NAME_RE.match(net) else None
            d: SwarmRow = {"leader": s["leader"], "members": _ids(s.get("members")), "net": net}
            colour = s.get("colour")  # the page's palette index (issue 16's groups)
            if isinstance(colour, int) and not isinstance(colour, bool) and 0 <= colour < 10_000:
                d["colour"] = colour
            out.append(d)
    return out


def _int(v: Any, lo: int, hi: int) -> int | None:
    return v if isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi else None


def clean_alert(a: Any) -> AlertRow | None:
    """One remote alert re-built from the fields a station's alerts have
    (:meth:`swarm.core.station.alerts.Alert.as_dict`, with ``net``), each of its type;
    None (dropped) without an ``id`` (0..2**53), a ``raised`` time or a ``text``."""
    if not isinstance(a, dict):
        return None
    aid, raised, words = _int(a.get("id"), 0, 2**53), _num(a.get("raised")), text(a.get("text"))
    if aid is None or raised is None or words is None:
        return None
    kind, level, net, quiet = a.get("kind"), a.get("level"), a.get("net"), a.get("quiet")
    return {
        "id": aid,
        "kind": kind if kind in ALERT_KINDS else "other",
        "agent": _int(a.get("agent"), 0, 250) or 0,
        "level": level if level in ALERT_LEVELS else "warning",
        "text": words,
        "raised": raised,
        "last": _num(a.get("last")) or raised,
        "cleared": _num(a.get("cleared")),
        "acked": a.get("acked") is True,
        "count": _int(a.get("count"), 1, 1_000_000) or 1,
        # a station before alarm management announced every alert
        "announced": _num(a.get("announced")) if "announced" in a else raised,
        "quiet": quiet if quiet in ALERT_QUIET else None,
        "shelved_until": _num(a.get("shelved_until")),
        "net": net if isinstance(net, str) and NAME_RE.match(net) else None,
    }


def clean_alerts(v: Any) -> list[AlertRow]:
    """The ``alerts`` list: the last :data:`MAX_ALERTS` of those :func:`clean_alert`
    keeps, one per id (the last)."""
    out: dict[int, AlertRow] = {}
    for a in v[-MAX_ALERTS:] if isinstance(v, list) else []:
        c = clean_alert(a)
        if c is not None:
            out.pop(c["id"], None)
            out[c["id"]] = c
    return list(out.values())


def clean_state(body: Any) -> StationState:
    """A remote station's state: ``agents`` (each :func:`clean_agent`, ids unique),
    ``events``, ``swarms``, ``alerts``. Raises FederationRefused (the whole state is
    dropped)."""
    if not isinstance(body, dict) or not isinstance(body.get("agents"), list):
        raise FederationRefused("malformed: a state is an object with 'agents'")
    if len(body["agents"]) > MAX_AGENTS:
        raise FederationRefused(f"too large: more than {MAX_AGENTS} agents")
    agents: dict[int, AgentRow] = {}
    for d in body["agents"]:
        a = clean_agent(d)
        agents[a["id"]] = a
    return {
        "agents": [agents[i] for i in sorted(agents)],
        "events": clean_events(body.get("events")),
        "swarms": clean_swarms(body.get("swarms")),
        "alerts": clean_alerts(body.get("alerts")),
    }


def thin(body: StationState, points: int = 10) -> StationState:
    """``body`` (a state to publish) with each agent's trail cut to its last ``points``:
    every state is sent with :data:`TRAIL_SENT`, and one still too large for
    :data:`MAX_ENVELOPE` with 10 rather than refused."""
    agents: list[AgentRow] = [{**a, "trail": a.get("trail", [])[-points:]} for a in body.get("agents", [])]
    return {**body, "agents": agents}


# -- commands across stations ----------------------------------------------------------


def spec_body(spec: CommandSpec) -> dict[str, Any]:
    """The API's command object for ``spec`` (what the carrying station parses again)."""
    body: dict[str, Any] = {"target": "swarm" if spec.target is None else spec.target}
    body["kind"] = spec.kind.name.lower()
    if spec.swarm is not None:  # one swarm, by its leader
        body["swarm"] = spec.swarm
    if spec.kind in (CommandKind.GOTO, CommandKind.WAYPOINT):
        body.update(lat=spec.lat, lon=spec.lon, alt=spec.alt)
    elif spec.kind == CommandKind.TAKEOFF:
        body["alt"] = spec.alt
    elif spec.kind == CommandKind.FOLLOW:
        body["heading"] = spec.heading
    return body


def check_remote(spec: CommandSpec, fence: Geofence, agent: AgentRow | None) -> CommandSpec:
    """``spec`` for another station's ``agent`` (its cleaned dict; None: the swarm)
    inside this station's geofence, an ``alt_amsl`` made metres above the home that
    station reported.

    Raises:
        CommandRefused: 400 outside the fence; 409 the agent is not connected there,
            or an ``alt_amsl`` without a reported home.
    """
    what = spec.kind.name.lower()
    if agent is not None and not agent.get("connected"):
        raise CommandRefused(409, f"{agent['name']} ({agent['id']}) is not connected")
    why = None
    if spec.kind == CommandKind.TAKEOFF:
        why = fence.alt_refusal(spec.alt) or (None if spec.alt >= 1.0 else "a take-off climbs 1 m at least")
    elif spec.kind in (CommandKind.GOTO, CommandKind.WAYPOINT) and agent is not None:
        if spec.alt_amsl is not None:
            home_alt = agent.get("home_alt")
            if home_alt is None:
                raise CommandRefused(
                    409, f"{agent['name']}'s home is unknown here: give 'alt' (metres above home)"
                )
            spec = replace(spec, alt=round(spec.alt_amsl - home_alt, 1), alt_amsl=None)
        home = agent.get("home")
        why = fence.refusal(spec.lat, spec.lon, spec.alt, None if home is None else (home[0], home[1]))
    if why is not None:
        raise CommandRefused(400, f"{what} refused by the station's geofence: {why}")
    return spec


def ack_any(view: Any, alert_id: Any, station: Any) -> dict[str, Any]:
    """An acknowledgement from the page or the API: alert ``alert_id`` of ``station``
    (None or this station's name: one of its own) at ``view`` (a station or a fleet).

    Raises:
        CommandRefused: what the station refuses; 404 another station where there is
            no federation.
    """
    if station is None or station == getattr(view, "name", None):
        return dict(view.ack_alert(alert_id))
    remote = getattr(view, "ack_remote_alert", None)
    if remote is None or not isinstance(station, str):
        shown = text(station, 32) if isinstance(station, str) else type(station).__name__
        raise CommandRefused(404, f"no station {shown!r} here")
    return dict(remote(alert_id, station))


def shelve_any(view: Any, alert_id: Any, seconds: Any, station: Any) -> dict[str, Any]:
    """A shelving from the page or the API: alarm ``alert_id`` of this station (another
    station's alarms are shelved there, by its own operator).

    Raises:
        CommandRefused: what the station refuses; 409 another station's alarm.
    """
    if station is None or station == getattr(view, "name", None):
        return dict(view.shelve_alert(alert_id, seconds))
    shown = text(station, 32) if isinstance(station, str) else type(station).__name__
    raise CommandRefused(409, f"alarms of station {shown!r} are shelved there, by its operator")


def clean_result(body: Any, request_sender: str, request_t: int) -> tuple[int, dict[str, Any]]:
    """(status, body) of a command result, if it answers the request (``sender``,
    ``t``) this station made. Raises FederationRefused."""
    if not isinstance(body, dict) or body.get("to") != request_sender or body.get("req") != request_t:
        raise FederationRefused("malformed: a result for another request")
    status, out = body.get("status"), body.get("body")
    if isinstance(status, bool) or not isinstance(status, int) or not 100 <= status <= 599:
        raise FederationRefused("malformed: a result's status")
    return status, tame(out) if isinstance(out, dict) else {}


def tame(v: Any, depth: int = 0) -> Any:
    """A JSON value with strings cut, lists shortened, numbers finite, depth at most 4."""
    if isinstance(v, dict):
        return {str(k)[:32]: tame(x, depth + 1) for k, x in list(v.items())[:32]} if depth < 4 else {}
    if isinstance(v, list):
        return [tame(x, depth + 1) for x in v[:64]] if depth < 4 else []
    if isinstance(v, str):
        return text(v)
    if isinstance(v, bool) or v is None:
        return v
    return _num(v)


__all__ = [
    "FLAG_DEFLATE",
    "FUTURE_S",
    "KIND_COMMAND",
    "KIND_RESULT",
    "KIND_STATE",
    "MAX_ALERTS",
    "MAX_ENVELOPE",
    "MAX_ONCE",
    "MAX_SENDERS",
    "PREFIX",
    "TRAIL_SENT",
    "WINDOW_S",
    "Envelope",
    "FederationRefused",
    "Gate",
    "Stamp",
    "ack_any",
    "check_remote",
    "clean_agent",
    "clean_alert",
    "clean_alerts",
    "clean_result",
    "clean_state",
    "command_key",
    "fed_key",
    "inflate",
    "load_body",
    "seal",
    "shelve_any",
    "spec_body",
    "state_key",
    "tame",
    "thin",
]
