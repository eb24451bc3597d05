"""Child processes the bench, the demo and the tests start: spawn, wait until
ready, measure CPU, and stop cleanly (SIGTERM, then SIGKILL after a grace period)."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from swarm.errors import SwarmError


class ChildError(SwarmError):
    """A child process failed to start or exited early."""


def json_events(lines: Sequence[str], event: str | None = None) -> list[dict[str, Any]]:
    """The JSON objects among a process's output lines (``--json``), those whose
    ``"event"`` is ``event`` if given; other lines are skipped."""
    out = []
    for line in list(lines):
        if not line.startswith("{"):
            continue
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        if isinstance(obj, dict) and (event is None or obj.get("event") == event):
            out.append(obj)
    return out


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a running process (Linux /proc)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def _limit_files(n: int) -> None:
    """In a child before it runs: at most ``n`` open files (soft and hard limit)."""
    import resource

    resource.setrlimit(resource.RLIMIT_NOFILE, (n, n))


class Child:
    """A ``swarm`` subcommand in its own process, with its output collected."""

    def __init__(self, argv: Sequence[str], *, name: str, nofile: int | None = None) -> None:
        """``nofile``: the child's open-file limit, soft and hard (as a service manager
        may set it); default: this process's."""
        self.name = name
        self.argv = [sys.executable, "-m", "swarm.cli", *argv]
        self.proc = subprocess.Popen(
            self.argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=None if nofile is None else functools.partial(_limit_files, nofile),
        )
        self.lines: list[str] = []
        self.errors: list[str] = []
        self._cond = threading.Condition()
        self._threads = [
            threading.Thread(target=self._pump, args=(self.proc.stdout, self.lines), daemon=True),
            threading.Thread(target=self._pump, args=(self.proc.stderr, self.errors), daemon=True),
        ]
        for t in self._threads:
            t.start()

    def _pump(self, stream: object, sink: list[str]) -> None:
        assert stream is not None
        for line in stream:  # type: ignore[attr-defined]
            with self._cond:
                sink.append(line.rstrip("\n"))
                self._cond.notify_all()

    def wait_lines(self, count: int, timeout: float) -> list[str]:
        """Wait until the child printed ``count`` lines on stdout.

        Raises:
            ChildError: it exited or did not print them in time (its stderr attached).
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            while len(self.lines) < count:
                if self.proc.poll() is not None:
                    self._cond.wait(0.2)  # let the pumps finish
                    if len(self.lines) >= count:
                        break
                    raise ChildError(
                        f"{self.name} exited with {self.proc.returncode}: " + " | ".join(self.errors[-5:])
                    )
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ChildError(f"{self.name} not ready after {timeout:.0f} s")
                self._cond.wait(min(left, 0.2))
            return list(self.lines[:count])

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stop(self, grace: float = 5.0) -> int:
        """SIGTERM, then SIGKILL to the whole process group after ``grace`` s."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        for t in self._threads:
            t.join(1)
        return self.proc.returncode


def start_emulator(
    nodes: int, directory: str | Path, *args: str, timeout: float = 30.0
) -> tuple[Child, list[str]]:
    """Start ``swarm radio-emu`` and return it with the radio link paths, once ready."""
    child = Child(["radio-emu", "--nodes", str(nodes), "--dir", str(directory), *args], name="radio emulator")
    try:
        lines = child.wait_lines(nodes, timeout)
    except BaseException:
        child.stop()
        raise
    return child, [line.split()[1] for line in lines]
