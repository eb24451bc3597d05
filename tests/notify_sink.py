"""A service manager's end of the notify protocol for tests: a real AF_UNIX datagram
socket that collects what a service sends (``READY=1``, ``WATCHDOG=1``...), each
datagram as a dict of its ``KEY=VALUE`` lines with the time it arrived."""

from __future__ import annotations

import os
import socket
import threading
import time
from typing import Any


class NotifySink:
    """Binds ``address`` (a path, or ``@name`` for an abstract socket) and collects
    datagrams on a thread until :meth:`close`."""

    def __init__(self, address: str) -> None:
        self.address = address
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind("\0" + address[1:] if address.startswith("@") else address)
        self.sock.settimeout(0.2)
        self.messages: list[tuple[float, dict[str, str]]] = []
        self.raw: list[bytes] = []
        self._lock = threading.Lock()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="notify-sink", daemon=True)
        self._thread.start()

    def env(self, watchdog_usec: int | None = None, **extra: str) -> dict[str, str]:
        """The variables a service manager sets (to add to a child's environment)."""
        env = {"NOTIFY_SOCKET": self.address, **extra}
        if watchdog_usec is not None:
            env["WATCHDOG_USEC"] = str(watchdog_usec)
        return env

    def _run(self) -> None:
        while not self._closed:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            fields = dict(line.split("=", 1) for line in data.decode().splitlines() if "=" in line)
            with self._lock:
                self.raw.append(data)
                self.messages.append((time.monotonic(), fields))

    def having(self, key: str, value: str | None = None) -> list[tuple[float, dict[str, str]]]:
        """The datagrams (time, fields) with ``key`` (equal to ``value`` if given)."""
        with self._lock:
            return [(t, m) for t, m in self.messages if key in m and (value is None or m[key] == value)]

    def count(self, key: str, value: str | None = None) -> int:
        return len(self.having(key, value))

    def statuses(self) -> list[str]:
        return [m["STATUS"] for _, m in self.having("STATUS")]

    def close(self) -> None:
        self._closed = True
        self._thread.join(2.0)
        self.sock.close()
        if not self.address.startswith("@"):
            try:
                os.unlink(self.address)
            except OSError:
                pass

    def __enter__(self) -> NotifySink:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
