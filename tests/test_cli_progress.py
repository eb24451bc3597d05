"""Progress on stderr (issue 18): drawn for a person on a terminal (a real pty
here), never with ``--json`` or when stderr is not a terminal."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

import pytest
from net_helpers import wait_until

from swarm.cli.progress import Progress, Ticker, format_left, wanted


@contextmanager
def terminal() -> Iterator[tuple[int, TextIO]]:
    """A real pseudo terminal: (the master's fd, the slave as a text stream)."""
    master, slave = os.openpty()
    stream = open(slave, "w", encoding="utf-8", closefd=True)  # noqa: SIM115 - closed below
    try:
        yield master, stream
    finally:
        stream.close()
        os.close(master)


def read_all(master: int) -> str:
    os.set_blocking(master, False)
    got = b""
    try:
        while chunk := os.read(master, 65536):
            got += chunk
    except (BlockingIOError, OSError):
        pass
    return got.decode()


def test_wanted_only_on_a_terminal_and_not_for_json() -> None:
    with terminal() as (_m, tty):
        assert wanted(tty) and not wanted(tty, as_json=True)
    assert not wanted(io.StringIO())


def test_counter_with_an_estimate_then_wiped() -> None:
    now = [100.0]
    with terminal() as (master, tty):
        with Progress("swarm simulate", 4, "seeds", stream=tty, clock=lambda: now[0]) as bar:
            now[0] = 102.0
            bar.advance()  # 2 s a seed: 6 s for the 3 left
            now[0] = 102.1
            bar.advance()  # too soon after the last draw: not drawn
            now[0] = 104.0
            bar.advance()
        shown = read_all(master)
    assert "swarm simulate: 0/4 seeds (0 %)" in shown
    assert "swarm simulate: 1/4 seeds (25 %), about 6 s left" in shown
    assert "2/4" not in shown
    assert "swarm simulate: 3/4 seeds (75 %), about 1 s left" in shown
    assert shown.endswith("\r")  # wiped: the command's output starts on a clean line


def test_silent_when_not_a_terminal() -> None:
    out = io.StringIO()
    with Progress("swarm simulate", 2, "seeds", stream=out) as bar:
        bar.advance(2)
    with Ticker("swarm bench radio", stream=out):
        pass
    assert out.getvalue() == ""


def test_estimates_read_as_people_say_them() -> None:
    assert [format_left(s) for s in (0.2, 9.4, 59, 61, 600)] == [
        "about 1 s left",
        "about 9 s left",
        "about 59 s left",
        "about 1 min left",
        "about 10 min left",
    ]


@pytest.mark.processes
@pytest.mark.parametrize("as_json", [False, True], ids=["text", "json"])
def test_simulate_draws_progress_on_a_terminal_only_without_json(as_json: bool) -> None:
    argv = ["simulate", "--agents", "3", "--seeds", "4", "--duration", "10", "--jobs", "1"]
    with terminal() as (master, tty):
        r = subprocess.run(
            [sys.executable, "-m", "swarm.cli", *argv, *(["--json"] if as_json else [])],
            stdout=subprocess.PIPE,
            stderr=tty,
            text=True,
            timeout=120,
        )
        shown = read_all(master)
    assert r.returncode == 0
    assert "\r" not in r.stdout  # the figures are clean either way
    if as_json:
        assert shown == ""
    else:
        assert "swarm simulate: 4/4 seeds (100 %)" in shown


def test_ticker_counts_seconds_for_work_it_cannot_count() -> None:
    seen: list[str] = []
    with terminal() as (master, tty):

        def first_second_shown() -> bool:
            seen.append(read_all(master))
            return "swarm bench radio: running, 1 s" in "".join(seen)

        with Ticker("swarm bench radio", stream=tty):
            wait_until(first_second_shown, "the ticker's first second", 15)
        seen.append(read_all(master))
    assert "".join(seen).endswith("\r")  # wiped on the way out


def test_bench_text_is_a_table_for_people() -> None:
    from swarm.cli.commands.bench import text_table

    text = text_table(
        {
            "latency_ms_p50": 114.7,
            "payload_bytes": {"Advertize": 10, "Heartbeat": 31},
            "targets": {"pose_payload_le_16": True, "latency_p50_within_1_5x_model": False},
            "missing": None,
            "runs": [1, 2],
        }
    )
    assert text.splitlines() == [
        "latency_ms_p50  114.7",
        "payload_bytes",
        "  Advertize  10",
        "  Heartbeat  31",
        "targets",
        "  pose_payload_le_16             yes",
        "  latency_p50_within_1_5x_model  no",
        "missing         -",
        "runs            1, 2",
    ]
