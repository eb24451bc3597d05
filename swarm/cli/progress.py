"""Progress on stderr for the commands that run longer than a few seconds.

Theory of operation
-------------------
A command that knows how much work it has (K seeds, N benchmark steps, M records)
makes one :class:`Progress` and calls :meth:`Progress.advance` as each piece is
done; :meth:`Progress.close` (or leaving the ``with`` block) wipes the line. The
line is drawn on stderr, rewritten in place with a carriage return::

    swarm simulate: 12/40 seeds (30 %), about 9 s left

and only for a person: nothing is drawn when the stream is not a terminal (a
pipe, a file, a test's capture) or when the command was asked for ``--json``
(:func:`wanted`), so programs reading stdout or stderr never see it. The estimate
is the mean time per piece so far times the pieces left; it is drawn only after
the first piece, and at most a few times a second. The clock is a parameter, so a
test can drive the display without waiting.

A command that cannot count its pieces (a benchmark, a plot of a big capture)
uses :class:`Ticker` instead: a thread that redraws ``swarm bench radio: running,
12 s`` once a second from the first second on, under the same rules.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import TextIO

#: the least time between two redraws, seconds
REDRAW_S = 0.2


def wanted(stream: TextIO | None = None, *, as_json: bool = False) -> bool:
    """True when a progress line helps: not ``--json`` and ``stream`` (stderr) is a terminal."""
    s = sys.stderr if stream is None else stream
    if as_json:
        return False
    try:
        return bool(s.isatty())
    except (AttributeError, ValueError):  # a closed or odd stream
        return False


def format_left(seconds: float) -> str:
    """``about 9 s left``, ``about 2 min left``."""
    if seconds < 60:
        return f"about {max(1, round(seconds))} s left"
    return f"about {round(seconds / 60)} min left"


class Progress:
    """A counter with an estimate on one stderr line; a no-op when not :func:`wanted`.

    ``total`` pieces of ``unit`` ("seeds", "steps"); ``enabled`` None decides by
    :func:`wanted` (``as_json`` says the command prints JSON)."""

    def __init__(
        self,
        prog: str,
        total: int,
        unit: str,
        *,
        as_json: bool = False,
        enabled: bool | None = None,
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.enabled = wanted(self.stream, as_json=as_json) if enabled is None else enabled
        self.prog, self.total, self.unit, self.clock = prog, max(0, total), unit, clock
        self.done = 0
        self.started = clock()
        self._drawn_at: float | None = None
        self._width = 0
        if self.enabled:
            self._draw(self.started)

    def line(self, now: float) -> str:
        """The text of the progress line at ``now``."""
        text = f"{self.prog}: {self.done}/{self.total} {self.unit}"
        if self.total:
            text += f" ({100 * self.done // self.total} %)"
        if 0 < self.done < self.total:
            per = (now - self.started) / self.done
            text += f", {format_left(per * (self.total - self.done))}"
        return text

    def advance(self, n: int = 1) -> None:
        """``n`` more pieces done; redraws at most every :data:`REDRAW_S`."""
        self.done = min(self.total, self.done + n)
        if not self.enabled:
            return
        now = self.clock()
        if self.done >= self.total or self._drawn_at is None or now - self._drawn_at >= REDRAW_S:
            self._draw(now)

    def _draw(self, now: float) -> None:
        text = self.line(now)
        pad = " " * max(0, self._width - len(text))
        self._width = len(text)
        self._drawn_at = now
        self._write("\r" + text + pad)

    def close(self) -> None:
        """Wipe the line (the command's own output follows on a clean line)."""
        if self.enabled and self._width:
            self._write("\r" + " " * self._width + "\r")
            self._width = 0

    def overwrite(self, text: str) -> None:
        """``text`` over the line as it stands (nothing cleared after it)."""
        self._write("\r" + text)
        self._width = len(text)

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # the terminal went away: progress is not worth an error
            self.enabled = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class Ticker:
    """Elapsed seconds on one stderr line, redrawn once a second by a thread, for work
    that cannot be counted; a no-op when not :func:`wanted`. Use as a context manager."""

    def __init__(
        self, prog: str, what: str = "running", *, as_json: bool = False, stream: TextIO | None = None
    ) -> None:
        self.line = Progress(prog, 0, what, as_json=as_json, stream=stream, enabled=False)
        self.line.enabled = wanted(self.line.stream, as_json=as_json)
        self.what = what
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="progress", daemon=True)

    def _run(self) -> None:
        started = time.monotonic()
        while not self._stop.wait(1.0):
            seconds = round(time.monotonic() - started)
            text = f"{self.line.prog}: {self.what}, {seconds} s"
            self.line.overwrite(text)

    def __enter__(self) -> Ticker:
        if self.line.enabled:
            self._thread.start()
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._thread.is_alive():
            self._stop.set()
            self._thread.join()
        self.line.close()
