"""``replay_json_speed``: how fast ``swarm replay --json`` reads a demo capture.

Theory of operation
-------------------
The figure is capture seconds per wall second: the capture's span (first to last
record) divided by the wall time of ``swarm replay CAPTURE --json`` with its output
thrown away. The capture is the project's checked-in demo capture
(``tests/data/demo/demo.tlog``: ``swarm demo`` with its ground station, five
agents, 10 % loss; see the README beside it), so the figure compares across runs
and machines; another capture can be given.

* ``replay_json_speed``: the whole command as a user runs it, a new Python process
  each time (start-up and imports included), best of ``runs``;
* ``replay_json_decode_speed``: the same command run in this process (imports
  done), best of ``runs``: the decoding alone, which longer captures approach.

Best-of because the machines are shared and noisy: the best run is the one least
disturbed. Target (issue 13): ``replay_json_speed`` >= 200. The project's own bench
(``python -m tools.bench replay``, from a checkout: the demo capture is the checkout's);
without the capture the figures are null with ``replay_error``.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from radios.errors import CaptureError
from radios.tlog import read_tlog

DEMO_CAPTURE = Path(__file__).resolve().parents[2] / "tests" / "data" / "demo" / "demo.tlog"
TARGET_SPEED = 200.0


def _span(path: Path) -> float:
    first = last = None
    for rec in read_tlog(path):
        first = rec.t if first is None else first
        last = rec.t
    return 0.0 if first is None or last is None else last - first


def _in_process(path: Path) -> float:
    from swarm.cli.commands.replay import main

    with open(os.devnull, "w") as sink, contextlib.redirect_stdout(sink):
        t = time.perf_counter()
        code = main([str(path), "--json"])
        wall = time.perf_counter() - t
    if code != 0:
        raise RuntimeError(f"swarm replay {path} --json exited {code}")
    return wall


def _process(path: Path) -> float:
    t = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "swarm.cli", "replay", str(path), "--json"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        check=True,
        timeout=120,
    )
    return time.perf_counter() - t


def run(quick: bool = False) -> dict[str, Any]:
    """``python -m tools.bench replay``: :func:`measure` on the demo capture."""
    return measure(runs=3 if quick else 5)


def measure(path: Path = DEMO_CAPTURE, runs: int = 3) -> dict[str, Any]:
    """The replay figures (see the module's text) for the capture at ``path``."""
    out: dict[str, Any] = {"replay_capture": path.name, "replay_json_target": TARGET_SPEED}
    try:
        span = _span(path)
    except CaptureError as exc:
        out.update(replay_json_speed=None, replay_json_decode_speed=None, replay_error=str(exc))
        return out
    proc = min(_process(path) for _ in range(runs))
    inproc = min(_in_process(path) for _ in range(runs))
    out.update(
        replay_capture_s=round(span, 3),
        replay_json_wall_s=round(proc, 3),
        replay_json_speed=round(span / proc, 1),
        replay_json_decode_speed=round(span / inproc, 1),
    )
    return out


__all__ = ["DEMO_CAPTURE", "TARGET_SPEED", "measure", "run"]
