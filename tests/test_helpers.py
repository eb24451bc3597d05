"""The tests' shared helpers keep their promises: ``wait_until`` returns the first
truthy value, says what never happened and fails at once when a watched child
exits; free ports bind; the manual clock moves only when told to."""

from __future__ import annotations

import socket
import subprocess
import sys
from dataclasses import dataclass, field
from itertools import count
from typing import Any

import pytest
from net_helpers import ManualClock, PortKind, free_port, free_port_range, wait_until


@dataclass
class Proc:
    """What ``wait_until`` watches of a ``swarm.cli.procs.Child``."""

    name: str
    proc: Any
    lines: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


def test_wait_until_returns_the_first_truthy_value() -> None:
    calls = count()
    assert wait_until(lambda: next(calls) >= 3 and "done", "three calls", 10.0, 0.0) == "done"


def test_wait_until_says_what_never_happened_with_the_detail() -> None:
    with pytest.raises(AssertionError, match=r"timed out after 0.05 s waiting for the moon: it is day"):
        wait_until(lambda: False, "the moon", 0.05, detail=lambda: "it is day")


def test_wait_until_fails_at_once_when_a_watched_child_exits() -> None:
    p = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    try:
        p.wait(30)
        child = Proc("crasher", p, errors=["boom"])
        # the exit, not the 60 s deadline, ends the wait
        with pytest.raises(AssertionError, match=r"crasher exited with 3 while waiting for the sky: boom"):
            wait_until(lambda: False, "the sky", 60.0, children=[child])
    finally:
        if p.poll() is None:
            p.kill()


def test_wait_until_names_the_children_s_last_lines_on_timeout() -> None:
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        child = Proc("sleeper", p, lines=["first", "last"])
        with pytest.raises(AssertionError, match=r"last lines: \{'sleeper': \['last'\]\}"):
            wait_until(lambda: False, "a word", 0.05, children=[child])
    finally:
        p.kill()
        p.wait(30)


@pytest.mark.parametrize("kind", ["tcp", "udp"])
def test_free_port_binds(kind: PortKind) -> None:
    sock_type = socket.SOCK_STREAM if kind == "tcp" else socket.SOCK_DGRAM
    with socket.socket(socket.AF_INET, sock_type) as s:
        s.bind(("127.0.0.1", free_port(kind)))


@pytest.mark.parametrize(("kind", "step"), [("udp", 1), ("tcp", 10)])
def test_free_port_range_binds_every_port(kind: PortKind, step: int) -> None:
    sock_type = socket.SOCK_STREAM if kind == "tcp" else socket.SOCK_DGRAM
    base = free_port_range(3, kind, step)
    socks = [socket.socket(socket.AF_INET, sock_type) for _ in range(3)]
    try:
        for i, s in enumerate(socks):
            s.bind(("127.0.0.1", base + step * i))
    finally:
        for s in socks:
            s.close()


def test_manual_clock_moves_only_when_told(manual_clock: ManualClock) -> None:
    assert manual_clock() == manual_clock.now == 1000.0
    manual_clock.sleep(0.5)
    assert manual_clock.advance(2.0) == 1002.5
    assert manual_clock() == 1002.5 and manual_clock.sleeps == [0.5]
    with pytest.raises(AssertionError):
        manual_clock.advance(-1.0)
    with pytest.raises(AssertionError):
        manual_clock.sleep(-0.1)
    assert manual_clock() == 1002.5
