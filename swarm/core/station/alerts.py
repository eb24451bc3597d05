"""The ground station's alerts and its judgement of each agent's link.

Theory of operation
-------------------
**Link health** (:class:`LinkHealth`, one per agent). Telemetry is the agent's
heartbeat at a rate the station knows (the interval its GSConnectAck named), so the
arrivals tell the loss: over the last ``window_s`` *up to the last arrival*, loss =
1 - arrivals / expected. Measuring up to the last arrival keeps the silence being
judged out of the estimate it is judged by.

Connection loss is judged with that measure. A silence of ``n`` missed heartbeats on
a link that loses a fraction ``p`` of them happens by chance with probability
``p**n``; the station declares an agent lost only after ``n`` heartbeats such that
this chance is below ``false_alarm`` (1e-6 a heartbeat), with ``p`` an upper estimate
((lost + 1) / (expected + 1): a short or clean record does not make it bold), and
``n`` between the station's ``timeout_heartbeats`` (3) and ``max_silence_heartbeats``
(10). With a full record (``window_s``, 120 s) a clean link is declared lost after 3
missed heartbeats, as before; one losing 20 % after 8 or 9 (0.2**8: a chance flap
about once in 100 hours at 1 Hz); a silent agent is lost within 10 whatever its
record. Before 5 heartbeats' worth of record the station's base timeout applies.
The link alert has its own hysteresis: raised at ``loss_alert`` percent, cleared
below ``loss_clear``.

**Alerts** (:class:`AlertBook`): battery warning and critical (thresholds in
percent), link loss (measured, and silence: the agent disconnected), vehicle link
loss (FLAG_FC_OK gone), the autopilot's STATUSTEXTs the agents forward, commands
refused or unanswered, separation holds. Each has an id, a kind, the agent, a level
(``warning`` or ``critical``), its text, when it was raised (and cleared: a
condition that ended; a one-off such as a STATUSTEXT is cleared when raised) and
whether an operator acknowledged it. A condition raised again while its alert is
still open updates it (a battery going from warning to critical is unacknowledged
again); a one-off raised again while unacknowledged counts (``count``) instead of
piling up. At most ``keep`` alerts are kept: acknowledged ones go first; the state
shows the unacknowledged ones and the last 10 acknowledged (:meth:`AlertBook.as_list`).

Pure: fed with ``now`` (the station core's monotonic seconds; times shown are
``now + wall_offset``), no I/O, no clock.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from swarm.core.station.rows import AlertRow

LEVELS = ("warning", "critical")
KINDS = ("battery", "link", "vehicle_link", "statustext", "command", "separation")


@dataclass(frozen=True)
class AlertConfig:
    battery_warning: int = 30  # percent
    battery_critical: int = 15
    loss_alert: float = 50.0  # percent of Telemetry lost: raised at, cleared below loss_clear
    loss_clear: float = 30.0
    window_s: float = 120.0
    false_alarm: float = 1e-6
    max_silence_heartbeats: float = 10.0
    keep: int = 100

    def __post_init__(self) -> None:
        w, c = self.battery_warning, self.battery_critical
        if not (isinstance(w, int) and isinstance(c, int) and 0 <= c < w <= 100):
            raise ValueError(
                f"battery thresholds {w!r}/{c!r}: whole percents, 0 <= critical < warning <= 100"
            )
        a, cl = self.loss_alert, self.loss_clear
        if not (_num(a) and _num(cl) and 0 < cl < a <= 100):
            raise ValueError(f"link loss thresholds {a!r}/{cl!r}: percents, 0 < clear < alert <= 100")
        if not (_num(self.window_s) and self.window_s >= 5):
            raise ValueError(f"window_s {self.window_s!r}: at least 5 s")
        if not (_num(self.false_alarm) and 0 < self.false_alarm < 1):
            raise ValueError(f"false_alarm {self.false_alarm!r}: between 0 and 1")
        if not (_num(self.max_silence_heartbeats) and self.max_silence_heartbeats >= 1):
            raise ValueError(f"max_silence_heartbeats {self.max_silence_heartbeats!r}: at least 1")
        if not (isinstance(self.keep, int) and self.keep > 0):
            raise ValueError(f"keep {self.keep!r}: a positive integer")


def _num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


@dataclass
class LinkHealth:
    """One agent's Telemetry arrivals (see the module docstring); :meth:`arrival`
    updates ``loss`` (0..1, None before 5 heartbeats' worth of record) and
    ``silence_s`` (how long a silence means the agent is lost; None: the station's
    base timeout)."""

    arrivals: deque[float] = field(default_factory=deque)
    since: float = math.inf  # the first arrival of this connection
    loss: float | None = None
    silence_s: float | None = None
    lossy: bool = False  # the link alert's state (hysteresis)

    def arrival(self, now: float, hb_interval: float, cfg: AlertConfig, min_heartbeats: float) -> None:
        if not self.arrivals:
            self.since = now
        self.arrivals.append(now)
        while now - self.arrivals[0] > cfg.window_s:
            self.arrivals.popleft()
        span = min(cfg.window_s, now - self.since)
        expected = span / hb_interval
        # within the first window, its first arrival only opens it
        got = len(self.arrivals) - (1 if now - self.since <= cfg.window_s else 0)
        if expected < 5:
            self.loss = self.silence_s = None
            return
        self.loss = max(0.0, min(1.0, 1.0 - got / expected))
        p = min(1.0, max(1.0, expected - got + 1) / (expected + 1))  # an upper estimate
        n = cfg.max_silence_heartbeats
        if p < 1.0:
            n = min(n, math.ceil(math.log(cfg.false_alarm) / math.log(p)))
        self.silence_s = max(min_heartbeats, n) * hb_interval

    def reset(self) -> None:
        self.arrivals.clear()
        self.since = math.inf
        self.loss = self.silence_s = None
        self.lossy = False


@dataclass
class Alert:
    id: int
    kind: str
    agent: int
    level: str
    text: str
    raised: float  # Unix time
    cleared: float | None = None
    acked: bool = False
    count: int = 1

    def as_dict(self) -> AlertRow:
        return {
            "id": self.id,
            "kind": self.kind,
            "agent": self.agent,
            "level": self.level,
            "text": self.text,
            "raised": round(self.raised, 3),
            "cleared": None if self.cleared is None else round(self.cleared, 3),
            "acked": self.acked,
            "count": self.count,
        }


class AlertBook:
    """The station's alerts (module docstring). ``wall_offset`` turns ``now`` into Unix time."""

    def __init__(self, keep: int = 100, wall_offset: float = 0.0) -> None:
        self.keep = keep
        self.wall_offset = wall_offset
        self.alerts: dict[int, Alert] = {}
        self._open: dict[tuple[str, int], int] = {}  # (kind, agent) -> id of its open condition
        self._next_id = 1
        self.dropped = 0

    def raise_(self, kind: str, agent: int, level: str, text: str, now: float) -> tuple[Alert, bool]:
        """A condition that holds until :meth:`clear` (battery, link, vehicle link,
        separation); with whether it is new or worse than it was."""
        key = (kind, agent)
        a = self.alerts.get(self._open.get(key, 0))
        if a is not None and a.cleared is None:
            worse = LEVELS.index(level) > LEVELS.index(a.level)
            if worse:
                a.acked = False  # worse than what was acknowledged
            a.level, a.text = level, text
            return a, worse
        a = self._add(kind, agent, level, text, now)
        self._open[key] = a.id
        return a, True

    def clear(self, kind: str, agent: int, now: float) -> Alert | None:
        """The condition ended (the alert stays until acknowledged)."""
        a = self.alerts.get(self._open.pop((kind, agent), 0))
        if a is not None and a.cleared is None:
            a.cleared = now + self.wall_offset
            return a
        return None

    def is_open(self, kind: str, agent: int) -> bool:
        a = self.alerts.get(self._open.get((kind, agent), 0))
        return a is not None and a.cleared is None

    def once(self, kind: str, agent: int, level: str, text: str, now: float, count: int = 1) -> Alert:
        """A one-off (a STATUSTEXT, a refused command): the same text of the same agent
        while still unacknowledged counts instead of making a new alert."""
        for a in reversed(self.alerts.values()):
            if a.kind == kind and a.agent == agent and a.text == text and not a.acked:
                a.count = min(a.count + count, 1_000_000)
                a.cleared = now + self.wall_offset
                return a
        a = self._add(kind, agent, level, text, now)
        a.cleared, a.count = a.raised, max(1, count)
        return a

    def ack(self, alert_id: int) -> Alert | None:
        a = self.alerts.get(alert_id)
        if a is not None:
            a.acked = True
        return a

    def as_list(self, acked: int = 10) -> list[AlertRow]:
        """Every unacknowledged alert and the last ``acked`` acknowledged ones, oldest
        first (what a page needs, without resending what is settled at every push)."""
        done = [i for i, a in self.alerts.items() if a.acked]
        keep = set(done[-acked:]) if acked > 0 else set()
        return [a.as_dict() for i, a in self.alerts.items() if not a.acked or i in keep]

    def _add(self, kind: str, agent: int, level: str, text: str, now: float) -> Alert:
        a = Alert(self._next_id, kind, agent, level, text, now + self.wall_offset)
        self._next_id += 1
        self.alerts[a.id] = a
        while len(self.alerts) > self.keep:
            old = next((x for x in self.alerts.values() if x.acked), None)
            if old is None:
                old = next(iter(self.alerts.values()))
            del self.alerts[old.id]
            self.dropped += 1
        return a


def battery_level(pct: int | None, cfg: AlertConfig) -> str | None:
    """``critical``, ``warning`` or None for a battery at ``pct`` percent (None: unknown)."""
    if pct is None:
        return None
    if pct <= cfg.battery_critical:
        return "critical"
    if pct <= cfg.battery_warning:
        return "warning"
    return None


__all__ = [
    "KINDS",
    "LEVELS",
    "Alert",
    "AlertBook",
    "AlertConfig",
    "LinkHealth",
    "battery_level",
]
