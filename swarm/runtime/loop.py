"""The queue-and-deadline loop every runtime runs its pure core on.

Theory of operation
-------------------
A pure core (:class:`swarm.core.agent.node.AgentNode`, :class:`swarm.core.station.core.StationCore`)
is driven from one thread: callbacks of other threads (Zenoh, the pose reader, the
vehicle caller, the HTTP server) only :meth:`EventLoop.put` what they have; the
loop waits on the queue until the core's next deadline, hands every queued item to
``handle(item, now)``, then calls ``tick(now)`` and ``after()``. ``min_tick_gap``
bounds how often a busy loop ticks (at hundreds of messages a second a tick after
every batch would cost more than the messages); a tick is never later than the
core's deadline. ``clock`` is the runtime's monotonic clock. :attr:`EventLoop.beat`
is ``time.monotonic()`` at the loop's last round or item (at least every ``max_wait``
seconds while it runs): the service watchdog's sign that the loop is not stuck
(:mod:`swarm.runtime.notify`).

A callback that raises is logged and counted in ``errors``: a bug must not
silence a drone (``on_error`` hears of it too). :meth:`stop` ends the loop (from any thread, also its own) and
waits for it.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

_STOP = object()
_WAKE = object()


class EventLoop:
    def __init__(
        self,
        name: str,
        *,
        handle: Callable[[object, float], None],
        tick: Callable[[float], None],
        next_deadline: Callable[[], float],
        after: Callable[[], None] | None = None,
        on_error: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        min_tick_gap: float = 0.0,
        max_wait: float = 1.0,
    ) -> None:
        self.name = name
        self._handle = handle
        self._tick = tick
        self._next_deadline = next_deadline
        self._after = after
        self._on_error = on_error
        self.clock = clock
        self.min_tick_gap = min_tick_gap
        self.max_wait = max_wait
        self.errors = 0
        self.beat = time.monotonic()  # the last round or item (liveness, real time)
        self._q: queue.Queue[object] = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def put(self, item: object) -> None:
        """Queue ``item`` for ``handle`` (any thread)."""
        self._q.put(item)

    def wake(self) -> None:
        """Make the loop look at its deadline again (it moved)."""
        self._q.put(_WAKE)

    def start(self) -> EventLoop:
        self._thread = threading.Thread(target=self.run, name=self.name, daemon=True)
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._q.put(_STOP)
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout)

    def run(self) -> None:
        deadline, last_tick = -math.inf, -math.inf
        while not self._stop.is_set():
            self.beat = time.monotonic()
            wait = min(self.max_wait, max(0.0, deadline - self.clock()))
            try:
                item: object = self._q.get(timeout=wait)
            except queue.Empty:
                item = None
            try:
                while item is not None:
                    if item is _STOP:
                        self._stop.set()
                        return
                    if item is not _WAKE:
                        self.beat = time.monotonic()
                        self._handle(item, self.clock())
                    try:
                        item = self._q.get_nowait()
                    except queue.Empty:
                        item = None
                now = self.clock()
                if now >= deadline or now - last_tick >= self.min_tick_gap:
                    self._tick(now)
                    last_tick = now
                deadline = self._next_deadline()
                if self._after is not None:
                    self._after()
            except Exception:  # a bug must not silence the node: log, count, go on
                self.errors += 1
                log.exception("%s: error", self.name)
                if self._on_error is not None:
                    self._on_error()
                deadline = self.clock() + 0.05  # no tight loop on a tick that keeps failing


__all__ = ["EventLoop"]
