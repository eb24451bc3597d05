"""What a command did on the vehicle, after the agent said yes: results that mean what they say.

Theory of operation
-------------------
An agent's ACCEPTED says that it took the command, not that its vehicle did what was
asked: after an autopilot failsafe a vehicle sits in its autopilot's loiter and a Go
it accepted moves it 0 m; "take-off: accepted (already flying)" changes nothing. So
the station follows each command the agent took (:data:`FOLLOWED`) on the agent's
Telemetry, and says how it ended: ``DONE`` (with what showed it), ``DID_NOT_HAPPEN``
(with why: the autopilot has control, the vehicle disarmed, it has not moved toward
the target for :data:`STALL_S`...), or ``REPLACED`` (a newer command to the same agent
took over). Until then it is ``IN_PROGRESS`` with what is left ("45 m to go").

One :class:`Followup` per agent (the newest command it took). The rules, per kind
(:func:`judge`; heights are above home: the agent's own report, else the station's):

* ARM, DISARM: done when the vehicle is armed (disarmed); did not happen when it is
  not within :data:`SWITCH_S`; SET_MODE likewise with the mode asked;
* STOP: done when the agent holds; did not happen when it does not within SWITCH_S;
* TAKEOFF: done when airborne within :data:`ALT_TOL_M` of the height asked (or above:
  an already flying vehicle asked to take off to lower is left where it is by the
  agents, which says so); in progress while it climbs;
* GOTO: done within :data:`ARRIVE_M` of the target (and ALT_TOL_M of its height when
  known); in progress while the distance falls (by 1 m within STALL_S);
* LAND, RETURN: done once on the ground (not airborne) or disarmed; in progress
  while the autopilot is in its landing (return) mode or the vehicle descends;
* for all: did not happen when the autopilot has control (the agent's
  ``control_lost``: a failsafe, RC) for :data:`LOST_S` (LAND and RETURN: when the
  vehicle is in another mode than theirs for LOST_S, SWITCH_S after the command),
  when the vehicle disarms in flight, or when it made no progress for STALL_S (LAND,
  RETURN: :data:`LAND_STALL_S`); and after :data:`GIVE_UP_S` in all.

Pure: fed with the station's :class:`~swarm.core.station.model.AgentView` and ``now``;
no I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from swarm.core.station.model import AgentView
from swarm.core.station.rows import DoingRow
from swarm.core.wire.message_types import CommandKind

ARRIVE_M = 3.0
ALT_TOL_M = 2.0
SWITCH_S = 10.0
LOST_S = 5.0
STALL_S = 15.0
LAND_STALL_S = 30.0
GIVE_UP_S = 600.0
PROGRESS_M = 1.0  # closer by this much is progress

FOLLOWED = (
    CommandKind.ARM,
    CommandKind.DISARM,
    CommandKind.STOP,
    CommandKind.TAKEOFF,
    CommandKind.GOTO,
    CommandKind.LAND,
    CommandKind.RETURN,
    CommandKind.SET_MODE,
)
IN_PROGRESS, DONE, DID_NOT_HAPPEN, REPLACED = "IN_PROGRESS", "DONE", "DID_NOT_HAPPEN", "REPLACED"
_LAND_MODES = ("AUTO.LAND", "LAND")
_RETURN_MODES = ("AUTO.RTL", "RTL", "SMART_RTL")


@dataclass
class Followup:
    """One command an agent took, followed on its vehicle."""

    agent: int
    kind: CommandKind
    label: str  # "GOTO -> agent3 (3)"
    request: int
    started: float
    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0  # metres above home (TAKEOFF, GOTO)
    best: float = math.inf  # the least left to go so far
    moved_at: float = 0.0  # when it last came closer
    lost_since: float | None = None  # the autopilot has had control since
    state: str = IN_PROGRESS
    text: str = ""
    changed: float = 0.0
    mode: str = ""  # SET_MODE: the mode asked

    def as_dict(self, wall_offset: float) -> DoingRow:
        return {
            "kind": self.kind.name.lower(),
            "request": self.request,
            "state": self.state,
            "text": self.text,
            "since": round(self.started + wall_offset, 3),
        }

    @property
    def line(self) -> str:
        """Its line in the station's log (the page reads ``KIND -> who: STATE``)."""
        return f"{self.label}: {self.state}" + (f" ({self.text})" if self.text else "")


def height(a: AgentView) -> float | None:
    """Metres above home: the agent's own report, else from the home the station saw."""
    if a.rel_alt is not None:
        return a.rel_alt
    if a.pose is not None and a.home is not None:
        return a.pose.alt - a.home[2]
    return None


def ground_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    k = math.pi / 180.0
    x = (lon2 - lon1) * k * math.cos((lat1 + lat2) * k / 2)
    return 6_371_000.0 * math.hypot(x, (lat2 - lat1) * k)


def left_to_go(f: Followup, a: AgentView) -> float | None:
    """How far the vehicle still is from what ``f`` asks (None: unknown)."""
    h = height(a)
    if f.kind == CommandKind.GOTO:
        if a.pose is None:
            return None
        d = ground_m(a.pose.lat, a.pose.lon, f.lat, f.lon)
        return d if h is None else math.hypot(d, h - f.alt)
    if f.kind == CommandKind.TAKEOFF:
        return None if h is None else max(0.0, f.alt - h)
    if f.kind in (CommandKind.LAND, CommandKind.RETURN):
        return h
    return None


def judge(f: Followup, a: AgentView, now: float) -> tuple[str, str]:
    """(state, text) of ``f`` now (module docstring)."""
    k = f.kind
    mode = a.mode or "unknown"
    if k == CommandKind.ARM:
        if a.armed is True:
            return DONE, "armed"
        return (
            (DID_NOT_HAPPEN, "the vehicle is not armed") if now - f.started >= SWITCH_S else (IN_PROGRESS, "")
        )
    if k == CommandKind.DISARM:
        if a.armed is False:
            return DONE, "disarmed"
        if now - f.started >= SWITCH_S:
            return DID_NOT_HAPPEN, "the vehicle is still armed"
        return IN_PROGRESS, ""
    if k == CommandKind.SET_MODE:
        if a.mode == f.mode:
            return DONE, f"in {f.mode}"
        if now - f.started >= SWITCH_S:
            return DID_NOT_HAPPEN, f"the vehicle is in {mode}, not {f.mode}"
        return IN_PROGRESS, ""
    if k == CommandKind.STOP:
        if a.holding is True:
            return DONE, "holding"
        return (
            (DID_NOT_HAPPEN, "the agent is not holding") if now - f.started >= SWITCH_S else (IN_PROGRESS, "")
        )
    landing = k in (CommandKind.LAND, CommandKind.RETURN)
    if landing and (a.airborne is False or a.armed is False):
        return DONE, "on the ground" if a.airborne is False else "disarmed"
    if a.armed is False and now - f.started >= SWITCH_S:
        return DID_NOT_HAPPEN, "the vehicle disarmed"
    left = left_to_go(f, a)
    if not landing and a.control_lost is True:  # not done while the autopilot has control
        if f.lost_since is not None and now - f.lost_since >= LOST_S:
            return DID_NOT_HAPPEN, f"the autopilot has control (mode {mode}): take control back first"
        return IN_PROGRESS, f"the autopilot has control (mode {mode})"
    if (
        k == CommandKind.GOTO
        and left is not None
        and left <= ARRIVE_M + (ALT_TOL_M if height(a) is not None else 0)
    ):
        return DONE, f"arrived, {left:.1f} m from the target"
    if k == CommandKind.TAKEOFF and a.airborne is True and left is not None and left <= ALT_TOL_M:
        h = height(a)
        return DONE, f"airborne at {h:.1f} m above home" if h is not None else "airborne"
    if f.lost_since is not None and now - f.lost_since >= LOST_S:
        if landing:
            what = "landing" if k == CommandKind.LAND else "its return"
            return DID_NOT_HAPPEN, f"the vehicle left {what} (mode {mode})"
        return DID_NOT_HAPPEN, f"the autopilot has control (mode {mode}): take control back first"
    stall = LAND_STALL_S if landing else STALL_S
    if now - f.moved_at >= stall:
        more = f"{left:.0f} m to go, " if left is not None else ""
        return DID_NOT_HAPPEN, f"the vehicle has not moved toward it in {stall:.0f} s ({more}mode {mode})"
    if now - f.started >= GIVE_UP_S:
        return DID_NOT_HAPPEN, f"not done after {GIVE_UP_S / 60:.0f} min"
    return IN_PROGRESS, f"{left:.0f} m to go" if left is not None else ""


class Followups:
    """The command each agent last took, followed (module docstring)."""

    def __init__(self) -> None:
        self.by_agent: dict[int, Followup] = {}

    def start(self, f: Followup, a: AgentView | None, now: float) -> Followup | None:
        """Follow ``f`` (its agent's view ``a``); the one it replaced, if still going."""
        old = self.by_agent.get(f.agent)
        f.moved_at = f.changed = now
        if a is not None:
            self._observe(f, a, now)
        self.by_agent[f.agent] = f
        if old is not None and old.state == IN_PROGRESS:
            old.state, old.text, old.changed = REPLACED, f"by {f.kind.name}", now
            return old
        return None

    def observe(self, a: AgentView, now: float) -> Followup | None:
        """The agent's new Telemetry: its follow-up, if this ended it."""
        f = self.by_agent.get(a.id)
        if f is None or f.state != IN_PROGRESS:
            return None
        return f if self._observe(f, a, now) else None

    def tick(self, agents: dict[int, AgentView], now: float) -> list[Followup]:
        """Time passes (an agent silent, a vehicle that does not move): those that ended."""
        out = []
        for f in self.by_agent.values():
            a = agents.get(f.agent)
            if f.state == IN_PROGRESS and a is not None and self._judge(f, a, now):
                out.append(f)
        return out

    def _observe(self, f: Followup, a: AgentView, now: float) -> bool:
        left = left_to_go(f, a)
        if left is not None and left < f.best - PROGRESS_M:
            f.best, f.moved_at = left, now
        elif left is not None and f.best == math.inf:
            f.best = left
        if f.kind in (CommandKind.LAND, CommandKind.RETURN):  # its own mode, not a setpoint mode
            # a return ends in a landing (PX4: AUTO.RTL, then AUTO.LAND)
            expected = _LAND_MODES if f.kind == CommandKind.LAND else _RETURN_MODES + _LAND_MODES
            off = bool(a.mode) and a.mode not in expected and now - f.started >= SWITCH_S
        else:
            off = a.control_lost is True
        if off:
            f.lost_since = now if f.lost_since is None else f.lost_since
        else:
            f.lost_since = None
        return self._judge(f, a, now)

    def _judge(self, f: Followup, a: AgentView, now: float) -> bool:
        state, text = judge(f, a, now)
        f.text = text
        if state != IN_PROGRESS:
            f.state, f.changed = state, now
            return True
        return False


__all__ = [
    "ALT_TOL_M",
    "ARRIVE_M",
    "DID_NOT_HAPPEN",
    "DONE",
    "FOLLOWED",
    "GIVE_UP_S",
    "IN_PROGRESS",
    "LOST_S",
    "REPLACED",
    "STALL_S",
    "Followup",
    "Followups",
    "judge",
]
