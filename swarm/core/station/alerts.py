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

**Alarms** (:class:`AlertBook`), managed after ISA-18.2 and EEMUA 191: battery
warning and critical, link loss (measured, and silence: the agent disconnected),
vehicle link loss (FLAG_FC_OK gone), the autopilot's STATUSTEXTs the agents forward,
separation holds, and commands refused or unanswered.

* **One alarm per condition.** A condition is ``(kind, agent)`` (a one-off such as
  a STATUSTEXT or a refused command: ``(kind, agent, text)``); it has one record,
  whatever it does: its ``count`` of occurrences, when it was first ``raised`` and
  ``last`` seen, ``cleared`` (the condition returned to normal; None: active). A
  condition that returns while its alarm is still unacknowledged is the same alarm
  (count + 1): a flapping link is one line, not one a flap.
* **Latched until acknowledged**: an alarm whose condition ended stays until an
  operator acknowledges it; one acknowledged comes back (the same record, unacknowledged
  again) when its condition does, or when it gets worse (a battery warning turned
  critical).
* **Priorities** (``level``): ``critical`` (act now), ``warning`` (act soon),
  ``advisory`` (to the list only: never in the banner, never a sound, not counted as
  an alarm: a refused or unanswered command, which its sender sees in its result,
  and the autopilot's reasons not to arm).
* **Announced** (``announced``: the Unix time of its last announcement): an alarm is
  announced (banner, sound for a critical) when it appears, comes back after its
  acknowledgement, or gets worse, unless it is quiet (``quiet``):
  ``"shelved"`` by an operator (:meth:`AlertBook.shelve`, ``shelved_until``: at most
  :data:`SHELVE_MAX_S`; it comes back by itself when the time is up),
  ``"chattering"`` (announced ``chatter_count`` times within ``chatter_window_s``: its
  occurrences are still counted, and it is announced again only when it comes back
  ``chatter_window_s`` after its last announcement, or gets worse), or ``"flood"`` (more than ``flood_limit``
  announcements in the last ``flood_window_s``: a warning is listed, not announced;
  a critical always is).
* **On-delay**: a separation hold is an alarm only when it lasts ``on_delay_s``
  (the formation's own safety check resolves most within seconds; those are lines in
  the log). The battery clears with a deadband (``battery_deadband`` above the warning)
  so that a reading that wobbles on the threshold is one alarm.
* **Rate**: :attr:`AlertBook.announced` holds the announcements' times; the state's
  ``alarm_rate`` says how many in the last ``flood_window_s`` and whether the station
  is in a flood.

At most ``keep`` alarms are kept (acknowledged and cleared ones go first); the state
shows every one still active or unacknowledged and the last 10 others
(:meth:`AlertBook.as_list`).

Pure: fed with ``now`` (the station core's monotonic seconds; times shown are
``now + wall_offset``), no I/O, no clock.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from swarm.core.station.rows import AlarmRate, AlertRow

LEVELS = ("advisory", "warning", "critical")  # priorities, lowest first
KINDS = ("battery", "link", "vehicle_link", "statustext", "command", "separation")
QUIET = ("shelved", "chattering", "flood")
#: one-off kinds: each text of an agent is its own condition, over as soon as raised
ONE_OFF = ("statustext", "command")
SHELVE_DEFAULT_S = 600.0
SHELVE_MAX_S = 3600.0


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
    battery_deadband: int = 3  # percent above the warning before a battery alarm clears
    on_delay_s: float = 5.0  # a separation hold is an alarm when it lasts this long
    chatter_count: int = 2  # announcements within chatter_window_s that make an alarm chattering
    chatter_window_s: float = 600.0
    flood_limit: int = 10  # announcements within flood_window_s beyond which warnings are held
    flood_window_s: float = 600.0

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
        for k in ("keep", "chatter_count", "flood_limit"):
            v = getattr(self, k)
            if not (isinstance(v, int) and not isinstance(v, bool) and v > 0):
                raise ValueError(f"{k} {v!r}: a positive integer")
        if not (isinstance(self.battery_deadband, int) and 0 <= self.battery_deadband <= 100 - w):
            raise ValueError(
                f"battery_deadband {self.battery_deadband!r}: whole percents, warning + it <= 100"
            )
        for k in ("on_delay_s", "chatter_window_s", "flood_window_s"):
            v = getattr(self, k)
            if not (_num(v) and 0 <= v <= 86400):
                raise ValueError(f"{k} {v!r}: seconds, 0..86400")


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
    """One alarm: one condition's record (module docstring). Times are Unix times."""

    id: int
    kind: str
    agent: int
    level: str
    text: str
    raised: float  # its first occurrence
    last: float = 0.0  # its last occurrence
    cleared: float | None = None  # returned to normal; None: active
    acked: bool = False
    count: int = 1
    announced: float | None = None  # its last announcement; None: never announced
    quiet: str | None = None  # "shelved", "chattering", "flood"; None: announced when due
    shelved_until: float | None = None
    #: its announcements' times (chatter is judged on them)
    announcements: deque[float] = field(default_factory=deque)

    def as_dict(self) -> AlertRow:
        return {
            "id": self.id,
            "kind": self.kind,
            "agent": self.agent,
            "level": self.level,
            "text": self.text,
            "raised": round(self.raised, 3),
            "last": round(self.last, 3),
            "cleared": None if self.cleared is None else round(self.cleared, 3),
            "acked": self.acked,
            "count": self.count,
            "announced": None if self.announced is None else round(self.announced, 3),
            "quiet": self.quiet,
            "shelved_until": None if self.shelved_until is None else round(self.shelved_until, 3),
        }

    @property
    def in_banner(self) -> bool:
        """What a banner shows: unacknowledged, announced, not quiet, not advisory."""
        return (
            not self.acked and self.quiet is None and self.level != "advisory" and self.announced is not None
        )


class Raised(NamedTuple):
    """What raising a condition did: its alarm (None: waiting for its on-delay), whether
    this was an occurrence (new, or back after it ended, or worse), and whether it was
    announced."""

    alert: Alert | None
    occurred: bool
    announced: bool


class AlertBook:
    """The station's alarms (module docstring). ``wall_offset`` turns ``now`` into Unix
    time; ``cfg`` sets chatter, flood and on-delay (:class:`AlertConfig`)."""

    def __init__(self, keep: int = 100, wall_offset: float = 0.0, cfg: AlertConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else AlertConfig(keep=keep)
        self.keep = keep
        self.wall_offset = wall_offset
        self.alerts: dict[int, Alert] = {}
        self._by_key: dict[tuple[str, int, str], int] = {}  # condition -> id of its alarm
        self._pending: dict[tuple[str, int, str], tuple[float, str, str]] = {}  # on-delay
        self._next_id = 1
        self.dropped = 0
        self.announced: deque[float] = deque()  # announcement times (now), for the rate
        self.filtered = 0  # conditions over before their on-delay
        self.held = 0  # announcements a flood held back

    # -- conditions ---------------------------------------------------------------------
    def raise_(
        self, kind: str, agent: int, level: str, text: str, now: float, *, delay: bool = False
    ) -> Raised:
        """A condition that holds until :meth:`clear`. ``delay``: with the on-delay
        (``on_delay_s``: no alarm until :meth:`tick` finds the condition held that long)."""
        key = (kind, agent, "")
        a = self._get(key)
        if delay and self.cfg.on_delay_s > 0 and (a is None or a.cleared is not None):
            since = self._pending.get(key, (now, level, text))[0]
            self._pending[key] = (since, level, text)
            if now - since < self.cfg.on_delay_s:
                return Raised(None, False, False)
            del self._pending[key]
        return self._occur(key, kind, agent, level, text, now)

    def clear(self, kind: str, agent: int, now: float) -> Alert | None:
        """The condition ended (its alarm stays until acknowledged)."""
        key = (kind, agent, "")
        if self._pending.pop(key, None) is not None:
            self.filtered += 1
        a = self._get(key)
        if a is not None and a.cleared is None:
            a.cleared = now + self.wall_offset
            return a
        return None

    def is_open(self, kind: str, agent: int) -> bool:
        a = self._get((kind, agent, ""))
        return a is not None and a.cleared is None

    def once(self, kind: str, agent: int, level: str, text: str, now: float, count: int = 1) -> Alert:
        """A one-off (a STATUSTEXT, a refused command): its text is the condition, over
        as soon as raised; the same text again is the same alarm, counted."""
        r = self._occur((kind, agent, text), kind, agent, level, text, now, count)
        assert r.alert is not None
        r.alert.cleared = now + self.wall_offset
        return r.alert

    def _get(self, key: tuple[str, int, str]) -> Alert | None:
        i = self._by_key.get(key)
        return None if i is None else self.alerts.get(i)

    def _occur(
        self,
        key: tuple[str, int, str],
        kind: str,
        agent: int,
        level: str,
        text: str,
        now: float,
        count: int = 1,
    ) -> Raised:
        t = now + self.wall_offset
        a = self._get(key)
        if a is None:
            a = self._add(kind, agent, level, text, t)
            a.count = max(1, count)
            self._by_key[key] = a.id
            return Raised(a, True, self._announce(a, now))
        worse = LEVELS.index(level) > LEVELS.index(a.level)
        back = a.cleared is not None  # a one-off's is always: it is over once raised
        if back:
            a.count = min(a.count + max(1, count), 1_000_000)
            a.cleared = None
        a.level, a.text, a.last = level, text, t
        win = a.announcements
        if back and a.quiet == "chattering" and (not win or now - win[-1] >= self.cfg.chatter_window_s):
            a.quiet = None  # not announced for a whole window: no longer chattering
        if (back and a.acked) or worse:
            a.acked = False
            return Raised(a, True, self._announce(a, now, worse=worse))
        return Raised(a, back, False)

    def _announce(self, a: Alert, now: float, *, worse: bool = False) -> bool:
        """Announce ``a`` unless advisory or quiet; True if it was."""
        cfg = self.cfg
        if a.level == "advisory":
            return False
        if a.quiet == "shelved":
            if not (worse and a.level == "critical"):
                return False
            a.shelved_until = None  # turned critical: the shelf ends
        elif a.quiet == "chattering" and not worse:
            return False
        win = a.announcements
        while win and now - win[0] > cfg.chatter_window_s:
            win.popleft()
        if len(win) >= cfg.chatter_count and not worse:
            a.quiet = "chattering"
            return False
        rate = self.announced
        while rate and now - rate[0] > cfg.flood_window_s:
            rate.popleft()
        if len(rate) >= cfg.flood_limit and a.level != "critical":
            if a.quiet != "flood":
                self.held += 1
            a.quiet = "flood"
            return False
        a.quiet = None
        win.append(now)
        rate.append(now)
        a.announced = now + self.wall_offset
        return True

    def tick(self, now: float) -> list[Raised]:
        """Time passes: on-delays that ran out become alarms, shelves that ran out end
        (an active alarm is announced again); what occurred or was announced."""
        out: list[Raised] = []
        for key, (since, level, text) in list(self._pending.items()):
            if now - since >= self.cfg.on_delay_s:
                del self._pending[key]
                r = self._occur(key, key[0], key[1], level, text, now)
                if r.alert is not None and r.occurred:
                    out.append(r)
        t = now + self.wall_offset
        for a in self.alerts.values():
            if a.quiet == "shelved" and a.shelved_until is not None and t >= a.shelved_until:
                a.quiet, a.shelved_until = None, None
                if a.cleared is None and not a.acked and self._announce(a, now):
                    out.append(Raised(a, False, True))
        return out

    def next_deadline(self) -> float:
        """When :meth:`tick` has something to do (``now`` seconds; inf: nothing)."""
        times = [since + self.cfg.on_delay_s for since, _, _ in self._pending.values()]
        times += [
            a.shelved_until - self.wall_offset for a in self.alerts.values() if a.shelved_until is not None
        ]
        return min(times, default=math.inf)

    # -- the operator -------------------------------------------------------------------
    def ack(self, alert_id: int) -> Alert | None:
        a = self.alerts.get(alert_id)
        if a is not None:
            a.acked = True
        return a

    def shelve(self, alert_id: int, seconds: float, now: float) -> Alert | None:
        """Shelve an alarm for ``seconds`` (0: unshelve), checked by the caller to be in
        0..:data:`SHELVE_MAX_S`; None: no such alarm."""
        a = self.alerts.get(alert_id)
        if a is None:
            return None
        if seconds <= 0:
            if a.quiet == "shelved":
                a.quiet, a.shelved_until = None, None
            return a
        a.quiet, a.shelved_until = "shelved", now + self.wall_offset + seconds
        return a

    def as_list(self, acked: int = 10) -> list[AlertRow]:
        """Every alarm still active or unacknowledged, and the last ``acked`` settled
        ones (acknowledged and over), oldest first: what a page needs, without resending
        what is settled."""
        settled = [i for i, a in self.alerts.items() if a.acked and a.cleared is not None]
        keep = set(settled[-acked:]) if acked > 0 else set()
        return [
            a.as_dict()
            for i, a in self.alerts.items()
            if not (a.acked and a.cleared is not None) or i in keep
        ]

    def rate(self, now: float) -> AlarmRate:
        """Announcements in the last ``flood_window_s``, and whether that is a flood."""
        rate = self.announced
        while rate and now - rate[0] > self.cfg.flood_window_s:
            rate.popleft()
        return {
            "announced": len(rate),
            "window_s": self.cfg.flood_window_s,
            "flood": len(rate) >= self.cfg.flood_limit,
            "held": self.held,
        }

    def _add(self, kind: str, agent: int, level: str, text: str, t: float) -> Alert:
        a = Alert(self._next_id, kind, agent, level, text, t, last=t)
        self._next_id += 1
        self.alerts[a.id] = a
        while len(self.alerts) > self.keep:
            old = next((x for x in self.alerts.values() if x.acked and x.cleared is not None), None)
            if old is None:
                old = next((x for x in self.alerts.values() if x.cleared is not None), None)
            if old is None:
                old = next(iter(self.alerts.values()))
            del self.alerts[old.id]
            self._by_key = {k: v for k, v in self._by_key.items() if v != old.id}
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
    "ONE_OFF",
    "QUIET",
    "SHELVE_DEFAULT_S",
    "SHELVE_MAX_S",
    "Alert",
    "AlertBook",
    "AlertConfig",
    "LinkHealth",
    "Raised",
    "battery_level",
]
