"""The operator's requests while an attacker floods the station with idle connections.

A ``swarm gcs`` process runs with an open-file limit of 1024, soft and hard (a
service manager's usual soft limit, here one it may not raise). Another process
(this module with ``--attack``) opens ``connections`` TCP connections to its HTTP
port, sends nothing on them, and opens a new one whenever the station closes one:
an attacker that keeps 2,000 idle connections pressed on the station. Meanwhile the
operator's requests (each on a new connection, the hardest case: it has to be
accepted) are timed:

* ``flood_operator_answered`` of ``flood_operator_requests`` answered (GET /api/state and
  POST /api/command), with ``flood_operator_ms_p50``, ``_p95`` and ``_max`` against
  ``flood_baseline_ms_p50`` (the same requests before the flood);
  The operator starts once the station is full (its open files seen in ``/proc``:
  80 % of its limit, or 100 of the attacker's connections closed to make room);
* ``flood_attacker_opened``: connections the attacker opened in all,
  ``flood_attacker_opened_during`` of them from the moment the station was full to
  the attacker's first report after the operator's requests (it reports once a
  second), ``flood_closed_by_station``: those the station closed (the oldest idle
  ones, to make room: docs/security.md, "The ground station's API");
* ``flood_station_cpu_percent`` (of one core) and ``flood_station_log_lines``: what
  the flood cost the station, and the lines it wrote about it.

``python -m swarm.cli.bench.gcs_flood --attack HOST PORT N SECONDS`` is the attacker:
one JSON line a second, ``{"held", "opened", "closed", "failed"}``.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import http.client
import json
import os
import resource
import selectors
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Mapping
from typing import Any

from radios.ports import free_port
from swarm.cli.procs import Child, cpu_seconds

CONNECTIONS = 2000
FILE_LIMIT = 1024


# -- the attacker (its own process) --------------------------------------------------------


def attack(host: str, port: int, connections: int, seconds: float) -> None:
    """Hold ``connections`` idle connections to ``host:port`` for ``seconds``, opening a
    new one for each the other side closes; a status line on stdout each second."""
    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    sel = selectors.DefaultSelector()
    counts = {"opened": 0, "closed": 0, "failed": 0}
    held: set[socket.socket] = set()

    def open_one() -> None:
        s = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        s.setblocking(False)
        err = s.connect_ex((host, port))
        if err not in (0, errno.EINPROGRESS):
            s.close()
            counts["failed"] += 1
            return
        sel.register(s, selectors.EVENT_READ | selectors.EVENT_WRITE)
        counts["opened"] += 1

    def drop(s: socket.socket, by_station: bool) -> None:
        sel.unregister(s)
        held.discard(s)
        s.close()
        counts["closed" if by_station else "failed"] += 1

    for _ in range(connections):
        open_one()
    end = time.monotonic() + seconds
    report = 0.0
    while time.monotonic() < end:
        for key, events in sel.select(0.1):
            s = key.fileobj
            assert isinstance(s, socket.socket)
            if s not in held and events & selectors.EVENT_WRITE:
                if s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR):
                    drop(s, by_station=False)
                    continue
                held.add(s)
                sel.modify(s, selectors.EVENT_READ)
                continue
            try:
                data = s.recv(4096)
            except OSError:
                data = b""
            if not data:
                drop(s, by_station=s in held)
        while len(sel.get_map()) < connections and time.monotonic() < end:
            open_one()
            if counts["failed"] > 10 * connections:
                break
        if time.monotonic() >= report:
            report = time.monotonic() + 1.0
            print(json.dumps({"held": len(held), **counts}), flush=True)


class Flood:
    """The attacker process against 127.0.0.1:``port``, its newest status in :attr:`status`."""

    def __init__(self, port: int, connections: int = CONNECTIONS, seconds: float = 600.0) -> None:
        self.connections = connections
        self.status: dict[str, int] = {"held": 0, "opened": 0, "closed": 0, "failed": 0}
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                __name__,
                "--attack",
                "127.0.0.1",
                str(port),
                str(connections),
                str(seconds),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with contextlib.suppress(ValueError), self._cond:
                self.status = json.loads(line)
                self._cond.notify_all()

    def wait_opened(self, n: int, timeout: float) -> dict[str, int]:
        """The status once the attacker has opened ``n`` connections.

        Raises:
            RuntimeError: it exited or did not in ``timeout`` s.
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            while self.status["opened"] < n:
                if self.proc.poll() is not None:
                    raise RuntimeError(
                        f"the attacker exited: {self.proc.stderr.read() if self.proc.stderr else ''}"
                    )
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"the attacker opened {self.status['opened']} of {n} in {timeout:.0f} s"
                    )
                self._cond.wait(0.5)
            return dict(self.status)

    def wait_full(self, station_pid: int, file_limit: int, timeout: float) -> dict[str, int]:
        """The status once the attacker has opened its connections and the station is
        full: it holds 80 % of its file limit in open files (it takes whatever comes) or
        has closed 100 of the attacker's (it makes room). Seen from outside: the
        station's descriptors in ``/proc``.

        Raises:
            RuntimeError: the attacker exited, or the station was not full in ``timeout`` s.
        """
        deadline = time.monotonic() + timeout
        self.wait_opened(self.connections, timeout)
        while True:
            if open_files(station_pid) >= 0.8 * file_limit or self.status["closed"] >= 100:
                return dict(self.status)
            if self.proc.poll() is not None or time.monotonic() > deadline:
                files = open_files(station_pid)
                raise RuntimeError(f"station not full in {timeout:.0f} s: {files} files, {self.status}")
            time.sleep(0.2)

    def next_status(self, timeout: float = 5.0) -> dict[str, int]:
        """The attacker's next report (it reports once a second), or its last one."""
        with self._cond:
            seen = self.status
            deadline = time.monotonic() + timeout
            while self.status is seen and time.monotonic() < deadline and self.proc.poll() is None:
                self._cond.wait(0.2)
            return dict(self.status)

    def stop(self) -> dict[str, int]:
        """Stop the attacker (its connections close with it); its last status."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._thread.join(2)
        return dict(self.status)

    def __enter__(self) -> Flood:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def open_files(pid: int) -> int:
    """How many descriptors process ``pid`` holds (Linux ``/proc``; 0 once it is gone)."""
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return 0


# -- the operator ------------------------------------------------------------------------


def operator_request(
    port: int,
    method: str,
    path: str,
    body: bytes | None = None,
    headers: Mapping[str, str] | None = None,
    timeout: float = 20.0,
) -> tuple[int, float]:
    """One request on a new connection: (status, seconds); status 0 when it failed or
    timed out."""
    t0 = time.monotonic()
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        conn.request(method, path, body=body, headers=dict(headers or {}))
        r = conn.getresponse()
        r.read()
        return r.status, time.monotonic() - t0
    except (OSError, http.client.HTTPException):
        return 0, time.monotonic() - t0
    finally:
        conn.close()


def operator_round(port: int, rounds: int, timeout: float = 20.0) -> list[tuple[int, float]]:
    """``rounds`` times: GET /api/state, then a command (to agent 1)."""
    command = json.dumps({"target": 1, "kind": "arm"}).encode()
    out = []
    for _ in range(rounds):
        out.append(operator_request(port, "GET", "/api/state", timeout=timeout))
        out.append(
            operator_request(
                port, "POST", "/api/command", command, {"Content-Type": "application/json"}, timeout=timeout
            )
        )
    return out


def _ms(values: list[float], q: float) -> float | None:
    if not values:
        return None
    v = sorted(values)
    return round(1000.0 * v[min(len(v) - 1, int(q * len(v)))], 1)


@contextlib.contextmanager
def limited_station(file_limit: int = FILE_LIMIT) -> Iterator[tuple[Child, int, str]]:
    """``swarm gcs`` over Zenoh on loopback with at most ``file_limit`` open files:
    (the process, its HTTP port, its Zenoh endpoint)."""
    ep = f"tcp/127.0.0.1:{free_port('tcp')}"
    port = free_port("tcp")
    station = Child(
        ["gcs", "--zenoh-listen", ep, "--http", f"127.0.0.1:{port}", "--tiles", "none", "--json"],
        name="gcs",
        nofile=file_limit,
    )
    try:
        station.wait_lines(1, 30)
        yield station, port, ep
    finally:
        station.stop()


def measure(quick: bool = False) -> dict[str, Any]:
    """The figures of the module docstring."""
    rounds = 5 if quick else 10
    out: dict[str, Any] = {"flood_connections": CONNECTIONS, "flood_file_limit": FILE_LIMIT}
    with limited_station() as (station, port, _ep):
        base = operator_round(port, rounds)
        out["flood_baseline_ms_p50"] = _ms([t for s, t in base if s], 0.5)
        lines0 = len(station.lines) + len(station.errors)
        with Flood(port) as flood:
            start = flood.wait_full(station.pid, FILE_LIMIT, 120)["opened"]
            cpu0, w0 = cpu_seconds(station.pid), time.monotonic()
            got = operator_round(port, rounds)
            cpu1, w1 = cpu_seconds(station.pid), time.monotonic()
            end = flood.next_status()
        times = [t for s, t in got if s]
        out["flood_operator_requests"] = len(got)
        out["flood_operator_answered"] = sum(1 for s, _t in got if 0 < s < 500)
        out["flood_operator_ms_p50"] = _ms(times, 0.5)
        out["flood_operator_ms_p95"] = _ms(times, 0.95)
        out["flood_operator_ms_max"] = _ms(times, 1.0)
        out["flood_attacker_opened"] = end["opened"]
        out["flood_attacker_opened_during"] = end["opened"] - start
        out["flood_closed_by_station"] = end["closed"]
        out["flood_station_cpu_percent"] = round(100.0 * (cpu1 - cpu0) / max(1e-9, w1 - w0), 1)
        out["flood_station_log_lines"] = len(station.lines) + len(station.errors) - lines0
    return out


def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m swarm.cli.bench.gcs_flood")
    p.add_argument("--attack", nargs=4, metavar=("HOST", "PORT", "N", "SECONDS"), required=True)
    a = p.parse_args(argv)
    host, port, n, seconds = a.attack
    try:
        attack(host, int(port), int(n), float(seconds))
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(_main())
