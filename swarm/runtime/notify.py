"""The service manager's notify protocol: READY, STATUS, WATCHDOG and STOPPING datagrams.

Theory of operation
-------------------
systemd starts a ``Type=notify`` service with ``NOTIFY_SOCKET`` in its environment:
an AF_UNIX datagram socket, a path (``/run/systemd/notify``) or an abstract name
(``@...``). The service sends one datagram of newline-separated ``KEY=VALUE`` lines
per message: ``READY=1`` once it serves, ``STATUS=...`` one line for ``systemctl
status``, ``WATCHDOG=1`` to pet the watchdog, ``STOPPING=1`` when it begins to stop.
With ``WatchdogSec=`` the manager also passes ``WATCHDOG_USEC`` (the interval) and
``WATCHDOG_PID`` (the process it means); a service that does not pet within the
interval is killed and, with ``Restart=on-failure``, started again. No library is
needed: this module is the whole client.

* :class:`Notifier` sends. Made by :meth:`Notifier.from_environ`: without a usable
  ``NOTIFY_SOCKET`` it is disabled and every call does nothing (a command run by hand
  behaves as before). A send never blocks and never raises: a manager that is gone or
  slow loses a datagram, which is counted and logged once.
* :class:`Watchdog` pets. Every half interval it asks its ``probe`` for the service's
  loops, each as ``name -> (last round, longest legitimate wait)`` on
  ``time.monotonic()``, and pets only when :func:`stale_loops` (pure) finds none that
  has gone without a round for longer than its own wait plus the watchdog interval:
  a loop that hangs (a serial write that never ends, a callback blocked on a full
  pipe) stops the petting while the process lives on, so the manager restarts it.
  The first stale loop is named once in ``STATUS=`` and in the log; when every loop
  goes round again petting resumes and ``STATUS=`` says so.
* :class:`Service` is what a command uses: :meth:`Service.ready` (``READY=1`` with a
  status line, then the watchdog starts) and :meth:`Service.stopping`.

What counts as a loop is the runtime's: the agent's protocol loop, its radio bridge's
send and receive threads, its flight-controller session's receiver and housekeeper
and its pose thread (:meth:`swarm.runtime.agent.live.Agent.loop_beats`); the station's
loop and bridge and the HTTP server's event loop for ``swarm gcs``.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

#: a loop's last round and the longest it may legitimately wait between rounds (s)
Beat = tuple[float, float]
Probe = Callable[[], Mapping[str, Beat]]

_SUN_PATH_MAX = 107  # sockaddr_un.sun_path holds 108 bytes with the terminating NUL
_MIN_PET_S = 0.01


def socket_address(value: str | None) -> str | bytes | None:
    """The address ``NOTIFY_SOCKET`` names: a path, or an abstract name (``@name`` ->
    ``b"\\0name"``); None when unset. Raises ValueError for anything else (a relative
    path, a name too long for AF_UNIX, a NUL byte)."""
    if not value:
        return None
    raw = os.fsencode(value)
    if b"\0" in raw:
        raise ValueError("NOTIFY_SOCKET contains a NUL byte")
    if len(raw) > _SUN_PATH_MAX:
        raise ValueError(f"NOTIFY_SOCKET is {len(raw)} bytes, AF_UNIX allows {_SUN_PATH_MAX}")
    if raw.startswith(b"@") and len(raw) > 1:
        return b"\0" + raw[1:]
    if raw.startswith(b"/"):
        return value
    raise ValueError(f"NOTIFY_SOCKET {value!r}: neither an absolute path nor an abstract @name")


def _whole(text: str) -> int | None:
    """``text`` as a whole number of at most 20 ASCII digits (a 64-bit value), else None."""
    if not (text.isascii() and text.isdigit() and len(text) <= 20):
        return None
    return int(text)


def watchdog_interval(env: Mapping[str, str], pid: int) -> float | None:
    """The watchdog interval in seconds that ``WATCHDOG_USEC`` asks of process ``pid``,
    or None: unset, or meant for another process (``WATCHDOG_PID``). Raises ValueError
    for a value that is not a positive whole number of microseconds."""
    usec = env.get("WATCHDOG_USEC")
    if usec is None:
        return None
    owner = env.get("WATCHDOG_PID")
    if owner is not None:
        owner_pid = _whole(owner)
        if owner_pid is None:
            raise ValueError(f"WATCHDOG_PID {owner[:40]!r}: not a process id")
        if owner_pid != pid:
            return None
    micros = _whole(usec)
    if not micros:
        raise ValueError(f"WATCHDOG_USEC {usec[:40]!r}: not a positive number of microseconds")
    return micros / 1e6


def stale_loops(beats: Mapping[str, Beat], now: float, limit: float) -> list[str]:
    """The loops (sorted) that went without a round for longer than their own longest
    wait plus ``limit`` at ``now``. Pure."""
    out = []
    for name, (last, wait) in beats.items():
        if not (math.isfinite(last) and math.isfinite(wait)) or now - last > wait + limit:
            out.append(name)
    return sorted(out)


class Notifier:
    """Sends notify datagrams to ``address`` (None: disabled, every call does nothing)."""

    def __init__(self, address: str | bytes | None) -> None:
        self.address = address
        self.sent = 0
        self.failed = 0
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        if address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @classmethod
    def from_environ(cls, env: Mapping[str, str] | None = None) -> Notifier:
        """From ``NOTIFY_SOCKET`` (``os.environ`` by default). A value that cannot be a
        notify socket is logged in one line and leaves the notifier disabled."""
        env = os.environ if env is None else env
        try:
            return cls(socket_address(env.get("NOTIFY_SOCKET")))
        except ValueError as exc:
            log.warning("service notify off: %s", exc)
            return cls(None)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def send(self, **fields: str) -> bool:
        """One datagram ``KEY=VALUE\\n...`` (keys upper-cased); True if it left. Values
        are made one line (a STATUS with a newline would be a second assignment)."""
        sock, address = self._sock, self.address
        if sock is None or address is None:
            return False
        text = "".join(f"{k.upper()}={' '.join(str(v).split())}\n" for k, v in fields.items())
        with self._lock:
            try:
                sock.sendto(text.encode("utf-8", "replace"), socket.MSG_DONTWAIT, address)
            except OSError as exc:
                self.failed += 1
                if self.failed == 1:
                    log.warning("service notify: cannot send to %r: %s", self.address, exc)
                return False
        self.sent += 1
        return True

    def ready(self, status: str) -> bool:
        return self.send(ready="1", status=status)

    def status(self, text: str) -> bool:
        return self.send(status=text)

    def watchdog(self) -> bool:
        return self.send(watchdog="1")

    def stopping(self, status: str = "stopping") -> bool:
        return self.send(stopping="1", status=status)

    def close(self) -> None:
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None


class Watchdog:
    """Pets ``notifier`` every half ``interval`` while every loop ``probe`` names goes
    round (see the module docstring). :meth:`check` is one round (the thread's, or a
    test's with its own ``now``)."""

    def __init__(self, notifier: Notifier, probe: Probe, interval: float) -> None:
        self.notifier = notifier
        self.probe = probe
        self.interval = interval
        self.pets = 0
        self.stale: list[str] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def check(self, now: float) -> bool:
        """Pet if no loop is stale at ``now``; True if it petted. Says once in STATUS
        which loop stopped (and when they all go round again)."""
        try:
            stale = stale_loops(self.probe(), now, self.interval)
        except Exception:  # a probe that fails is a service that cannot tell it is alive
            log.exception("service watchdog: probe failed")
            stale = ["probe"]
        if stale != self.stale:
            if stale:
                what = ", ".join(stale)
                log.warning("service watchdog: %s stuck: not petting (the manager will restart us)", what)
                self.notifier.status(f"stuck: {what} (watchdog not petted)")
            else:
                log.warning("service watchdog: every loop runs again: petting")
                self.notifier.status("running (every loop runs again)")
            self.stale = stale
        if stale:
            return False
        self.pets += 1
        return self.notifier.watchdog()

    def start(self) -> Watchdog:
        self._thread = threading.Thread(target=self._run, name="service-watchdog", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        period = max(_MIN_PET_S, self.interval / 2)
        while True:
            self.check(time.monotonic())
            if self._stop.wait(period):
                return

    def stop(self) -> None:
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(2.0)


class Service:
    """A command's side of the protocol: :meth:`ready` once it serves (the watchdog then
    starts, if the manager asked for one), :meth:`stopping` when it ends. Without
    ``NOTIFY_SOCKET`` both do nothing."""

    def __init__(self, probe: Probe, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        self.notifier = Notifier.from_environ(env)
        self.probe = probe
        self.watchdog: Watchdog | None = None
        self.interval: float | None = None
        if self.notifier.enabled:
            try:
                self.interval = watchdog_interval(env, os.getpid())
            except ValueError as exc:
                log.warning("service watchdog off: %s", exc)

    def ready(self, status: str) -> None:
        if not self.notifier.enabled:
            return
        self.notifier.ready(status)
        if self.interval is not None and self.watchdog is None:
            self.watchdog = Watchdog(self.notifier, self.probe, self.interval).start()

    def stopping(self) -> None:
        if self.watchdog is not None:
            self.watchdog.stop()
        self.notifier.stopping()
        self.notifier.close()


__all__ = [
    "Beat",
    "Notifier",
    "Probe",
    "Service",
    "Watchdog",
    "socket_address",
    "stale_loops",
    "watchdog_interval",
]
