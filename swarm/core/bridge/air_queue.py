"""What the radio bridge sends next: three priority queues with air-time budgets.

Theory of operation
-------------------
Each item the bridge will put on air waits in the queue of its class: protocol >
pose > telemetry (:class:`Klass`). A full queue drops its oldest item (the stalest).
:meth:`AirQueue.next_item` picks the next item to send at ``now``, in class order:

* each class has a token bucket of air bytes per second (``rates``) and a burst
  (``bursts``), so one agent cannot flood the channel; an item waits until its
  class's bucket holds its frame's size (:meth:`AirQueue.frame_size`, signature
  included);
* **RADIO_STATUS** back-off (:class:`swarm.core.bridge.radio_guard.RadioStatusGuard`):
  below 50% free transmit buffer telemetry waits (counted in ``throttled``); poses
  are thinned by at most 15% (``poses_thinned``), never held; protocol always goes;
* **Multicast**: a P2P protocol item waits ``coalesce_s`` for identical payloads to
  other peers (a leader's heartbeat to its members); they leave as one MULTI item
  listing the addressees (``multicast_merged``), as many as one frame holds.

It returns the item with how long to wait when nothing can go yet. The caller
(:class:`swarm.runtime.bridge.radio_bridge.RadioBridge`) holds its lock around every call, packs
the item only when it goes (so sequence numbers and signing timestamps follow air
order), and reads its clock for ``now``: nothing here does I/O or reads a clock.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import IntEnum
from typing import Protocol

from swarm.core.bridge.radio_guard import RadioStatusGuard
from swarm.core.wire.tunnel import Kind, fits_multicast


class Klass(IntEnum):
    PROTOCOL = 0
    POSE = 1
    TELEMETRY = 2


@dataclass
class AirItem:
    klass: Klass
    kind: Kind
    targets: list[int]
    payload: bytes
    raw_frame: bytes | None = None
    t: float = 0.0  # when queued


@dataclass
class Bucket:
    rate: float
    burst: float
    tokens: float
    t: float

    def refill(self, now: float) -> None:
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
        self.t = now

    def wait_for(self, n: int) -> float:
        return max(0.0, (min(n, self.burst) - self.tokens) / self.rate) if self.rate > 0 else 1.0


class QueueCounters(Protocol):
    """The counters :class:`AirQueue` keeps (the bridge's stats)."""

    queue_drops: int
    throttled: int
    poses_thinned: int
    multicast_merged: int


class AirQueue:
    """The bridge's three queues and their budgets. See the module docstring."""

    def __init__(
        self,
        *,
        rates: tuple[float, float, float],
        bursts: tuple[float, float, float],
        sizes: tuple[int, int, int],
        coalesce_s: float,
        signed: bool,
        guard: RadioStatusGuard,
        stats: QueueCounters,
        now: float,
    ) -> None:
        self.sizes = sizes
        self.coalesce_s = coalesce_s
        self.signed = signed
        self.guard = guard
        self.stats = stats
        self.queues: list[deque[AirItem]] = [deque() for _ in Klass]
        self.buckets = [Bucket(r, b, b, now) for r, b in zip(rates, bursts, strict=True)]

    def put(self, item: AirItem, now: float) -> None:
        """Queue ``item`` (stamped ``now``); a full queue drops its oldest."""
        q = self.queues[item.klass]
        if len(q) >= self.sizes[item.klass]:
            q.popleft()  # the oldest is the stalest
            self.stats.queue_drops += 1
        item.t = now
        q.append(item)

    def clear(self) -> int:
        """Drop everything queued (the radio went away); how many items were dropped."""
        n = sum(len(q) for q in self.queues)
        for q in self.queues:
            q.clear()
        return n

    def next_item(self, now: float) -> tuple[AirItem | None, float]:
        """The next item to send, or None and how long to wait (0.0: ask again now)."""
        wait = 0.25
        allowed = self._allowed_classes(now)
        for klass in Klass:
            q = self.queues[klass]
            if not q:
                continue
            if klass not in allowed:
                self.stats.throttled += 1
                continue
            bucket = self.buckets[klass]
            bucket.refill(now)
            item = q[0]
            if item.raw_frame is None and item.kind == Kind.P2P:
                hold = item.t + self.coalesce_s - now
                if hold > 0:
                    wait = min(wait, hold)
                    continue
                self._merge_multicast(q, item)
            size = self.frame_size(item)
            if bucket.tokens < min(size, bucket.burst):
                wait = min(wait, bucket.wait_for(size))
                continue
            q.popleft()
            if klass == Klass.POSE and not self.guard.take_pose(now):
                self.stats.poses_thinned += 1  # bounded txbuf back-off: skip this one
                return None, 0.0
            bucket.tokens -= size
            return item, 0.0
        return None, wait

    def frame_size(self, item: AirItem) -> int:
        """Bytes on air of ``item``'s frame."""
        if item.raw_frame is not None:
            return len(item.raw_frame)
        extra = 1 + len(set(item.targets)) if item.kind == Kind.MULTI else 0
        return 12 + 5 + len(item.payload) + extra + (13 if self.signed else 0)

    def _allowed_classes(self, now: float) -> tuple[Klass, ...]:
        # protocol and poses always go (poses may be thinned, see next_item)
        if self.guard.telemetry_allowed(now):
            return tuple(Klass)
        return (Klass.PROTOCOL, Klass.POSE)

    def _merge_multicast(self, q: deque[AirItem], item: AirItem) -> None:
        same = [
            o
            for o in q
            if o is not item and o.kind == Kind.P2P and o.raw_frame is None and o.payload == item.payload
        ]
        if not same or not fits_multicast(len(item.payload), len(item.targets) + len(same)):
            return
        for o in same:
            item.targets.extend(o.targets)
            q.remove(o)
        item.kind = Kind.MULTI
        self.stats.multicast_merged += len(same)
