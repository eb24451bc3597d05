"""Helpers every kind of test shares, each written once: a polling wait, free ports
on loopback, and a manual clock.

Nothing here sleeps to hope that something happened: :func:`wait_until` polls for an
outcome until a generous deadline and fails with a message saying what never
happened (and, when it watches child processes, which one died and what it said).
:class:`ManualClock` is the clock of the pure cores' tests: time moves only when the
test moves it or when the code under test sleeps on it. ``tests/conftest.py`` hands
one out as the ``manual_clock`` fixture.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

# free ports live in the library (the benches and the demo need them too): re-exported
from radios.ports import PortKind as PortKind
from radios.ports import free_port as free_port
from radios.ports import free_port_range as free_port_range


class Watched(Protocol):
    """A child process whose output is collected (``swarm.cli.procs.Child``)."""

    name: str
    lines: list[str]
    errors: list[str]

    @property
    def proc(self) -> Any: ...


def _exited(children: Sequence[Watched], what: str) -> None:
    for c in children:
        if c.proc.poll() is not None:
            raise AssertionError(
                f"{c.name} exited with {c.proc.returncode} while waiting for {what}: "
                f"{' | '.join(c.errors[-5:])}"
            )


def wait_until(
    pred: Callable[[], Any],
    what: str,
    timeout: float,
    interval: float = 0.02,
    *,
    children: Sequence[Watched] = (),
    detail: Callable[[], object] | None = None,
) -> Any:
    """Poll ``pred`` every ``interval`` s until it returns something truthy (returned).

    Fails the test (AssertionError) with ``what`` after ``timeout`` seconds, adding
    ``detail()`` and the last stdout line of each of ``children`` if given, or as soon
    as one of ``children`` exits (with its last stderr lines): a dead process never
    makes a test wait out its whole deadline.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        _exited(children, what)
        if time.monotonic() > deadline:
            message = f"timed out after {timeout} s waiting for {what}"
            if detail is not None:
                message += f": {detail()}"
            if children:
                message += f"; last lines: { {c.name: c.lines[-1:] for c in children} }"
            raise AssertionError(message)
        time.sleep(interval)


class ManualClock:
    """A monotonic clock that moves only when the test moves it (:meth:`advance`, or
    setting :attr:`now`) or when the code under test sleeps on it (:meth:`sleep`,
    recorded in :attr:`sleeps`). Calling it reads the time, as ``time.monotonic``."""

    def __init__(self, start: float = 0.0) -> None:
        self.now = start
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> float:
        """Move the clock on by ``seconds`` (never back) and return the new time."""
        assert seconds >= 0, f"a monotonic clock never goes back ({seconds} s)"
        self.now += seconds
        return self.now

    def sleep(self, seconds: float) -> None:
        """What the code under test calls instead of ``time.sleep``."""
        assert seconds >= 0, f"asked to sleep {seconds} s"
        self.sleeps.append(seconds)
        self.now += seconds


def live_processes() -> Iterator[tuple[int, int, int]]:
    """``(pid, parent pid, session id)`` of every live (not zombie) process, from /proc;
    one that ends while it is read is left out."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue  # gone meanwhile
        fields = stat[stat.rindex(")") + 2 :].split()  # after the command name, which may hold ")"
        if fields[0] != "Z":
            yield int(entry.name), int(fields[1]), int(fields[3])
