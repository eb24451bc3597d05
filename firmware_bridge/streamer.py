"""The setpoint stream: the current position target, sent at a fixed rate.

Theory of operation. PX4 leaves OFFBOARD when setpoints stop coming (below 2 Hz,
``COM_OF_LOSS_T``), so a target is not sent once but streamed. A
:class:`SetpointStreamer` keeps the current target (validated before it gets
here, :mod:`firmware_bridge.setpoints`) and, while there is one, runs a thread
that builds its SET_POSITION_TARGET_* message with the boot time of the moment
and sends it every ``1 / rate`` s on a fixed schedule (a send late by more than a
period, e.g. after a suspend, restarts the schedule instead of bursting). It
records the measured gaps between sends and the count, and wakes the vehicle's
condition after each send (``start_offboard`` waits for the first ones).
:meth:`~SetpointStreamer.stop` ends the stream and forgets the target; a new
target starts it again.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from firmware_bridge.errors import BridgeError
from firmware_bridge.setpoints import GlobalTarget, LocalTarget

Target = LocalTarget | GlobalTarget

__all__ = ["SetpointStreamer"]


class SetpointStreamer:
    """Streams the current target with ``send(message(target))`` at ``rate_hz``.

    ``cond`` is the vehicle's condition (its lock guards the target and the
    figures); ``closing`` is set when the vehicle closes. ``send`` raises
    :class:`BridgeError` once the link is closed, which ends the stream.
    """

    def __init__(
        self,
        send: Callable[[Any], None],
        message: Callable[[Target], Any],
        *,
        rate_hz: float,
        history: int,
        cond: threading.Condition,
        closing: threading.Event,
    ) -> None:
        self._send = send
        self._message = message
        self._period = 1.0 / rate_hz
        self._cond = cond
        self._closing = closing
        self._target: Target | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.started = 0.0  # time.monotonic() when the current stream started
        self.sent = 0
        self._intervals: deque[float] = deque(maxlen=history)

    @property
    def target(self) -> Target | None:
        """The target being streamed, or None."""
        with self._cond:
            return self._target

    @property
    def streaming(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def intervals(self) -> list[float]:
        """Measured gaps between consecutive sends, in seconds (last ``history``)."""
        with self._cond:
            return list(self._intervals)

    def set(self, target: Target) -> None:
        """Stream ``target`` from now on; start the thread if it is not running."""
        with self._cond:
            self._target = target
        if not self.streaming:
            self._stop = threading.Event()
            self.started = time.monotonic()
            self._thread = threading.Thread(
                target=self._loop, args=(self._stop,), name="fb-setpoints", daemon=True
            )
            self._thread.start()

    def stop(self) -> None:
        """End the stream (joined, unless called from the stream itself); forget the target."""
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(2.0)
        self._thread = None
        with self._cond:
            self._target = None

    def _loop(self, stop: threading.Event) -> None:
        next_t = time.monotonic()
        last: float | None = None
        while not stop.is_set() and not self._closing.is_set():
            now = time.monotonic()
            if now < next_t:
                stop.wait(next_t - now)
                continue
            with self._cond:
                target = self._target
            if target is None:
                break
            try:
                self._send(self._message(target))
            except BridgeError:
                break
            t = time.monotonic()
            with self._cond:
                if last is not None:
                    self._intervals.append(t - last)
                self.sent += 1
                self._cond.notify_all()
            last = t
            next_t += self._period
            if next_t < t - self._period:  # fell far behind (suspended): restart the schedule
                next_t = t + self._period
