"""What a ground station's command is: its parsing, its outcomes and their evidence.

Theory of operation
-------------------
The API's command object (``{"target": id | "swarm", "kind": ..., args}``, and with
target ``"swarm"`` an optional ``"swarm"``: the leader id of one swarm, or ``"all"``)
becomes a :class:`CommandSpec` in :func:`parse_command`, or is refused with a
:class:`CommandRefused` holding a short reason and an HTTP-like status; nothing about
the swarm is known here (that check is
:meth:`swarm.core.station.delivery.CommandDelivery.submit`'s, and so is the
geofence; which swarms a swarm command reaches is
:func:`swarm.core.station.swarms.swarm_plan`'s). Altitudes are metres above the
vehicle's home (``alt``); a go-to may give ``alt_amsl`` instead, which submit
converts with the home the station knows.

A submitted command is a :class:`Request` holding one :class:`Pending` per addressee:
its :class:`~swarm.core.wire.message_types.Command` (one seq each), the tries made, the agents
it went to, and what the station saw of each agent's vehicle at its first send
(:class:`Seen`). Results (:data:`RESULTS`): the agent's answer (``ACCEPTED``, or a
refusal: ``REJECTED``, ``FAILED``, ``BAD_ARGUMENT``, ``NO_LEADER``,
``UNKNOWN_AGENT``..., with its reason: for a command carried out on the vehicle,
ARM, DISARM, TAKEOFF, LAND, RETURN, the agent answers with what the vehicle did and
the autopilot's own words); ``IN_PROGRESS`` when the vehicle was still at it when
the station's retry window ended (not done: the station keeps asking and logs the
result when it comes, see :mod:`swarm.core.station.delivery`); at give-up without an answer,
``CARRIED_OUT`` when the agent's Telemetry since the first send shows the command's
effect (:func:`evidence`: ARM armed, DISARM disarmed, TAKEOFF airborne or a take-off
mode, LAND and RETURN their modes; each a change from what it was when the command
was first sent), else ``NO_ANSWER``. A request is done when every addressee has a
result; :func:`outcome` is its (status, body) for the API.

Sending, retrying and matching answers is :mod:`swarm.core.station.delivery`'s. Pure:
no I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from swarm.core.wire.codes import SELECTABLE_MODES
from swarm.core.wire.message_types import LEGACY_KINDS, AckResult, Command, CommandKind
from swarm.errors import SwarmError

NO_ANSWER = "NO_ANSWER"
#: no answer, but the agent's Telemetry shows the command's effect (see :func:`evidence`)
CARRIED_OUT = "CARRIED_OUT"
#: every result a command can end with: the agents' answers, then the station's two
RESULTS = (*(r.name for r in AckResult), CARRIED_OUT, NO_ANSWER)
#: results that mean the command was carried out
DONE_RESULTS = (AckResult.ACCEPTED.name, CARRIED_OUT)
KINDS: dict[str, CommandKind] = {k.name.lower(): k for k in CommandKind if k not in LEGACY_KINDS}
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
    CommandKind.SET_MODE,
}
ALT_RANGE = (-1000.0, 5553.0)  # what a Command can carry (decimetres, offset 1000 m)
ALT_AMSL = (-1000.0, 10000.0)  # an ``alt_amsl`` the API takes (converted with the agent's home)


class CommandRefused(SwarmError):
    """A command the station will not send; ``status`` is the HTTP-like code
    (400 bad request, 404 unknown agent, 409 not connected / no leader / replay)."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


@dataclass(frozen=True)
class CommandSpec:
    """A validated command request: ``target`` an agent id or None for the swarm."""

    target: int | None
    kind: CommandKind
    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0  # metres above the vehicle's home
    heading: float = 0.0
    #: GOTO/WAYPOINT given as ``alt_amsl`` (metres above sea level): submit converts it
    #: to ``alt`` with the home the station knows for the agent, or refuses it
    alt_amsl: float | None = None
    #: a swarm command (``target`` None) for the one swarm led by this agent; None: every
    #: swarm. Set with :meth:`for_swarm` (not an argument: callers that pass ``**floats``
    #: for the position and heading keep their types; ``dataclasses.replace`` drops it)
    swarm: int | None = field(default=None, init=False)
    #: SET_MODE: the mode's name (one of SELECTABLE_MODES)
    mode: str = ""

    def for_swarm(self, leader: int | None) -> CommandSpec:
        """This command for the swarm led by ``leader`` (None: every swarm)."""
        spec = replace(self)
        object.__setattr__(spec, "swarm", leader)
        return spec


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
    spec = _args(body, target, kind)
    return spec.for_swarm(_swarm(body, target)) if "swarm" in body else spec


def _args(body: dict[str, Any], target: int | None, kind: CommandKind) -> CommandSpec:
    what = kind.name.lower()
    if kind == CommandKind.TAKEOFF:  # metres above home; the geofence is submit's (and the pilot's)
        return CommandSpec(target, kind, alt=_number(body, "alt", 0.0, ALT_RANGE[1], what))
    if kind in (CommandKind.GOTO, CommandKind.WAYPOINT):
        return _position(body, target, kind)
    if kind == CommandKind.FOLLOW:
        return CommandSpec(target, kind, heading=_number(body, "heading", 0.0, 360.0, what) % 360.0)
    if kind == CommandKind.SET_MODE:
        return CommandSpec(target, kind, mode=_mode(body))
    return CommandSpec(target, kind)


def _mode(body: dict[str, Any]) -> str:
    """A SET_MODE's ``mode``: one of :data:`SELECTABLE_MODES`. Raises CommandRefused (400)."""
    v = body.get("mode")
    if isinstance(v, str) and v.upper() in SELECTABLE_MODES:
        return v.upper()
    shown = repr(v[:24]) if isinstance(v, str) else f"of type {type(v).__name__}" if v is not None else "none"
    raise CommandRefused(400, f"set_mode 'mode' {shown}: one of {', '.join(SELECTABLE_MODES)}")


def _swarm(body: dict[str, Any], target: int | None) -> int | None:
    """A swarm command's ``"swarm"``: its leader's id (1..250), or ``"all"`` (None: every swarm).

    Raises:
        CommandRefused: (400) on an agent's command, or not a leader's id nor "all".
    """
    v = body["swarm"]
    if target is not None:
        raise CommandRefused(400, "'swarm' goes with target \"swarm\", not with one agent")
    if v == "all":
        return None
    if isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 250:
        return v
    shown = (
        (str(v) if abs(v) < 10**15 else "a number of more than 15 digits")
        if isinstance(v, int) and not isinstance(v, bool)
        else repr(v[:24]) + ("..." if len(v) > 24 else "")
        if isinstance(v, str)
        else f"of type {type(v).__name__}"
        if isinstance(v, (list, dict, float))
        else repr(v)
    )
    raise CommandRefused(400, f'swarm {shown}: its leader\'s agent id (1..250) or "all"')


def _position(body: dict[str, Any], target: int | None, kind: CommandKind) -> CommandSpec:
    """A GOTO's or WAYPOINT's ``lat``, ``lon`` and ``alt`` (metres above home) or
    ``alt_amsl``. Raises CommandRefused (400)."""
    what = kind.name.lower()
    lat = _number(body, "lat", -90.0, 90.0, what)
    lon = _number(body, "lon", -180.0, 180.0, what)
    if "alt_amsl" in body:
        if "alt" in body:
            raise CommandRefused(400, f"{what}: give 'alt' (metres above home) or 'alt_amsl', not both")
        return CommandSpec(target, kind, lat, lon, alt_amsl=_number(body, "alt_amsl", *ALT_AMSL, what))
    if "alt" not in body:
        raise CommandRefused(400, f"{what} needs 'alt' (metres above home)")
    return CommandSpec(target, kind, lat, lon, _number(body, "alt", *ALT_RANGE, what))


@dataclass(frozen=True)
class Seen:
    """What the station saw of an agent's vehicle when a command was first sent."""

    mode: str
    armed: bool | None
    airborne: bool | None
    holding: bool | None


_TAKEOFF_MODES = ("AUTO.TAKEOFF",)
_LAND_MODES = ("AUTO.LAND", "LAND")
_RETURN_MODES = ("AUTO.RTL", "RTL")


def evidence(kind: CommandKind, before: Seen, now: Seen) -> str | None:
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
class Pending:
    request: Request
    agent: int  # the addressee (for a swarm command: the leader it was last sent to)
    swarm: bool  # Command(target=0) to the leader
    msg: Command
    first_sent: float = 0.0
    tries: int = 0
    next_try: float = 0.0
    sent_to: set[int] = field(default_factory=set)
    before: dict[int, Seen] = field(default_factory=dict)  # by agent, at its first send
    shown: str | None = None  # evidence seen in Telemetry (agent: what)
    refusal: tuple[int, str, str] | None = None  # a swarm "not here" answer: agent, result, reason
    progress: str | None = None  # the agent's latest IN_PROGRESS reason (its vehicle is at it)
    progress_at: float = 0.0  # when it was heard
    result: str | None = None  # IN_PROGRESS while followed past the retry window, then the final one
    reason: str = ""
    #: a swarm command: the members of the swarm it goes to (whose leader it follows;
    #: empty: the station's one leader), and that swarm's leader when sent (0: none)
    group: frozenset[int] = frozenset()
    of_swarm: int | None = None

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"agent": self.agent, "result": self.result, "reason": self.reason}
        if self.swarm:
            d["swarm"] = True
        if self.of_swarm is not None:
            d["of_swarm"] = self.of_swarm
        return d


@dataclass
class Request:
    """One submitted command and its per-agent outcomes."""

    id: int
    spec: CommandSpec
    pending: list[Pending] = field(default_factory=list)
    reported: bool = False  # its outcome was handed out (the API answered)

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
        # ``request``: its id, which the agents' ``doing`` names while the station follows it
        out: dict[str, Any] = {"ok": ok, "request": self.id, "results": [p.as_dict() for p in self.pending]}
        if any(p.of_swarm is not None for p in self.pending):  # several swarms: one line per swarm
            by: dict[int, list[Pending]] = {}
            for p in self.pending:
                by.setdefault(p.of_swarm or 0, []).append(p)
            out["swarms"] = [
                {
                    "swarm": k,
                    "ok": all(p.result in DONE_RESULTS for p in v),
                    "agents": sorted({p.agent for p in v}),
                }
                for k, v in sorted(by.items())
            ]
        if self.status == 504:
            out["error"] = "no answer after retries"
        return out


def outcome(req: Request) -> tuple[int, dict[str, Any]]:
    """(HTTP-like status, body) of a finished request."""
    return req.status, req.body()
