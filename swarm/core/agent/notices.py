"""What an agent tells its ground stations in words: autopilot STATUSTEXTs and its own events.

Theory of operation
-------------------
An operator must see the autopilot's warnings ("PreArm: GPS not healthy", "Battery 1
is low") and what the agent itself did (took off, arrived, holding, too close to
another agent) without the channel filling with text. :class:`NoticeGate` sits
between those sources and the air:

* :meth:`NoticeGate.offer` takes one line: an autopilot STATUSTEXT (kept only at
  severity ``forward_severity`` (WARNING) or worse: MAVLink counts 0 emergency ..
  7 debug) or one of the agent's own events (:func:`agent_severity` rates it).
  The text is made one printable line, cut to :data:`NOTICE_MAX` bytes of UTF-8
  (:func:`one_line`): an autopilot's control characters, escapes and NULs never
  reach a station's page or log.
* A line already waiting is not queued twice: its ``repeats`` count grows. A line
  sent less than ``dedup_s`` ago waits until then (its copies counted), so a
  STATUSTEXT repeated ten times a second crosses the air once per ``dedup_s`` with
  the count of what it stood for.
* At most ``pending`` lines wait; a fuller queue drops the least severe (counted).
* :meth:`NoticeGate.take` hands out what may go now: a token bucket of ``burst``
  lines refilled one per ``interval_s`` (one notice every 4 s per agent in the long
  run: about 20 bytes/s of a SiK channel's 5-6 kB/s even for an agent that never
  stops talking), most severe first, oldest first among equals.

The node (:mod:`swarm.core.agent.node`) sends each line taken as an
:class:`~swarm.core.wire.message_types.AgentNotice` to every connected station. Pure: no I/O,
no clock (``now`` is given).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from swarm.core.wire.codes import DEBUG, INFO, NOTICE, SEPARATION_HOLD, WARNING, one_line
from swarm.core.wire.message_types import NoticeSource


def agent_severity(text: str) -> int:
    """How much one of the agent's own events matters to an operator."""
    if text.startswith(SEPARATION_HOLD) or " failed" in text or "advertises our id" in text:
        return WARNING
    if text.startswith(("holding", "waiting for position", "separation restored")):
        return NOTICE
    return INFO


@dataclass(frozen=True)
class NoticeConfig:
    forward_severity: int = WARNING
    interval_s: float = 4.0
    burst: int = 2
    dedup_s: float = 30.0
    pending: int = 8

    def __post_init__(self) -> None:
        if not (isinstance(self.forward_severity, int) and 0 <= self.forward_severity <= 7):
            raise ValueError(f"forward_severity {self.forward_severity!r}: 0..7")
        for k in ("interval_s", "dedup_s"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{k} {v!r}: a positive number of seconds")
        for k in ("burst", "pending"):
            v = getattr(self, k)
            if not (isinstance(v, int) and v > 0):
                raise ValueError(f"{k} {v!r}: a positive integer")


@dataclass
class Notice:
    """One line waiting (or handed out): ``repeats`` more copies of it came meanwhile."""

    source: NoticeSource
    severity: int
    text: str
    first: float
    not_before: float = 0.0
    repeats: int = 0


@dataclass
class NoticeCounters:
    offered: int = 0
    below_severity: int = 0
    merged: int = 0
    dropped: int = 0
    sent: int = 0


@dataclass
class NoticeGate:
    """Rate limit, deduplication and bounds for an agent's notices (module docstring)."""

    cfg: NoticeConfig = field(default_factory=NoticeConfig)
    counters: NoticeCounters = field(default_factory=NoticeCounters)

    def __post_init__(self) -> None:
        self._pending: dict[tuple[NoticeSource, str], Notice] = {}
        self._sent: dict[tuple[NoticeSource, str], float] = {}
        self._tokens = float(self.cfg.burst)
        self._t = -math.inf

    def offer(self, source: NoticeSource, severity: int, text: str | bytes, now: float) -> bool:
        """One line from ``source``; False when it is not forwarded (below the severity
        kept for autopilot texts, empty, or dropped for a fuller queue)."""
        c = self.counters
        c.offered += 1
        sev = severity if isinstance(severity, int) and 0 <= severity <= 7 else DEBUG
        if source == NoticeSource.AUTOPILOT and sev > self.cfg.forward_severity:
            c.below_severity += 1
            return False
        line = one_line(text)
        if not line:
            c.dropped += 1
            return False
        key = (source, line)
        n = self._pending.get(key)
        if n is not None:
            n.repeats = min(255, n.repeats + 1)
            n.severity = min(n.severity, sev)
            c.merged += 1
            return True
        last = self._sent.get(key)
        not_before = last + self.cfg.dedup_s if last is not None else now
        if len(self._pending) >= self.cfg.pending and not self._make_room(sev):
            c.dropped += 1
            return False
        self._pending[key] = Notice(source, sev, line, now, not_before)
        return True

    def _make_room(self, sev: int) -> bool:
        """Drop the least severe waiting line (the newest among equals) for one of
        severity ``sev``; False when none is less severe than it."""
        worst = max(self._pending.values(), key=lambda n: (n.severity, n.first))
        if worst.severity <= sev:
            return False
        del self._pending[(worst.source, worst.text)]
        self.counters.dropped += 1
        return True

    def take(self, now: float) -> list[Notice]:
        """The lines that may go now (most severe first)."""
        self._refill(now)
        out: list[Notice] = []
        while self._tokens >= 1.0:
            ready = [n for n in self._pending.values() if n.not_before <= now]
            if not ready:
                break
            n = min(ready, key=lambda x: (x.severity, x.first))
            key = (n.source, n.text)
            del self._pending[key]
            self._sent[key] = now
            self._tokens -= 1.0
            self.counters.sent += 1
            out.append(n)
        if len(self._sent) > 4 * self.cfg.pending:  # forget what can no longer hold a line back
            self._sent = {k: t for k, t in self._sent.items() if now - t < self.cfg.dedup_s}
        return out

    def _refill(self, now: float) -> None:
        if math.isfinite(self._t):
            self._tokens = min(float(self.cfg.burst), self._tokens + (now - self._t) / self.cfg.interval_s)
        self._t = now

    def next_deadline(self) -> float:
        """When :meth:`take` may hand something out (inf: nothing waits)."""
        if not self._pending:
            return math.inf
        ready = min(n.not_before for n in self._pending.values())
        token = self._t + max(0.0, 1.0 - self._tokens) * self.cfg.interval_s
        return max(ready, token)

    @property
    def waiting(self) -> int:
        return len(self._pending)


__all__ = ["Notice", "NoticeConfig", "NoticeCounters", "NoticeGate", "agent_severity"]
