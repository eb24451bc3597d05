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

import random
import socket
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Literal, Protocol

#: The socket kinds a test asks a free port of.
PortKind = Literal["tcp", "udp"]
_SOCK_TYPES = {"tcp": socket.SOCK_STREAM, "udp": socket.SOCK_DGRAM}
#: Not the seeded ``random``: two pytest sessions side by side must not pick alike.
_RANDOM = random.SystemRandom()


class Watched(Protocol):
    """A child process whose output is collected (``swarm.cli.procs.Child``)."""

    name: str
    lines: list[str]
    errors: list[str]

    @property
    def proc(self) -> Any: ...


def _bindable(port: int, kind: PortKind) -> bool:
    with socket.socket(socket.AF_INET, _SOCK_TYPES[kind]) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _ephemeral_range() -> tuple[int, int]:
    try:
        lo, hi = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    except (OSError, ValueError):
        return 32768, 60999
    return lo, hi


def _candidates() -> range:
    """Ports the kernel never hands out on its own: outside the ephemeral range, so a
    socket some process binds to port 0 (a simulator's sending socket, a client's
    connect, the other pytest session beside this one) cannot take a port a test chose
    and has not bound yet. CI saw exactly that race once (EADDRINUSE)."""
    lo, hi = _ephemeral_range()
    if lo - 1 - 10000 >= 5000:
        return range(10000, lo)
    return range(hi + 1, 65000)


def free_port(kind: PortKind = "tcp") -> int:
    """A ``kind`` port on 127.0.0.1 that was free a moment ago, chosen outside the
    kernel's ephemeral range (see :func:`_candidates`)."""
    pick = _RANDOM.choice
    ports = _candidates()
    for _ in range(200):
        port = pick(ports)
        if _bindable(port, kind):
            return port
    with socket.socket(socket.AF_INET, _SOCK_TYPES[kind]) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_port_range(count: int, kind: PortKind = "tcp", step: int = 1) -> int:
    """A base port P such that the ``kind`` ports P, P+step, ..., P+(count-1)*step on
    127.0.0.1 were free a moment ago (a simulator's vehicles: PX4's consecutive UDP
    ports, ArduPilot's TCP ports 10 apart)."""
    for _ in range(50):
        base = free_port(kind)
        if base + step * count > _candidates().stop:
            continue
        if all(_bindable(base + step * i, kind) for i in range(count)):
            return base
    raise RuntimeError(f"no {count} free {kind.upper()} ports {step} apart")


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
