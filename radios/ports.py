"""Local ports for what the benches, the demo and the tests start on this machine.

A port picked by binding port 0 and closing the socket is in the kernel's ephemeral
range: until the child meant to use it binds it (a process start later), any socket
bound to port 0 or any outgoing connection on the machine can be given the same port,
and the child fails with EADDRINUSE. CI saw exactly that. So the ports here are drawn
at random (from the system's entropy: two processes side by side must not draw alike)
outside the ephemeral range, where the kernel never hands a port out on its own, and
checked free by binding them a moment before they are returned.

Checked free is not enough while the child is starting: a port drawn but not yet bound
passes the bind check in every other process, and two tests side by side drew the same
one (CI's station exited "port in use"). So each draw is recorded in a registry file of
this user's (:data:`REGISTRY`, under an exclusive lock), and a port drawn in the last
:data:`LEASE_S` seconds is never drawn again by any process of this user. A registry that
is not a plain file of this user's (a symlink planted there, another user's file) is
never written through: the draw goes on without it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import random
import socket
import stat
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Literal

#: the socket kinds a port is asked for
PortKind = Literal["tcp", "udp"]
_SOCK_TYPES = {"tcp": socket.SOCK_STREAM, "udp": socket.SOCK_DGRAM}
_RANDOM = random.SystemRandom()
#: the lowest port drawn (below: well-known and registered services more often run)
LOWEST = 10000
#: how long a drawn port is kept from every other draw (a child binds it long before)
LEASE_S = 600.0
#: the registry of drawn ports: "port expiry" lines (None: no registry)
#: (in /tmp whatever TMPDIR says: every process of the user must find the same file, and
#: a program that cleans its own TMPDIR, as the demo does, must not find it there)
REGISTRY: Path | None = Path("/tmp") / f"uav-swarm-ports-{os.getuid()}"
_DEFAULT = Path("/")  # "the module's REGISTRY" (read when called: tests point it elsewhere)


def bindable(port: int, kind: PortKind) -> bool:
    with socket.socket(socket.AF_INET, _SOCK_TYPES[kind]) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def ephemeral_range() -> tuple[int, int]:
    """The kernel's ephemeral ports (Linux: /proc/sys/net/ipv4/ip_local_port_range)."""
    try:
        lo, hi = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    except (OSError, ValueError):
        return 32768, 60999
    return lo, hi


def candidates() -> range:
    """The ports drawn from: below the ephemeral range, or above it if that is too narrow."""
    lo, hi = ephemeral_range()
    if lo - LOWEST >= 5000:
        return range(LOWEST, lo)
    return range(hi + 1, 65000)


@contextlib.contextmanager
def _leases(registry: Path | None, now: float) -> Iterator[dict[int, float]]:
    """The ports drawn and not yet expired (port -> expiry), under the registry's lock;
    what the caller adds is written back. Without a usable registry: an empty dict."""
    fd = -1
    if registry is not None:
        try:
            fd = os.open(registry, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid():
                os.close(fd)
                fd = -1
        except OSError:  # a symlink (O_NOFOLLOW), an unwritable folder: go on without it
            fd = -1
    if fd < 0:
        yield {}
        return
    with os.fdopen(fd, "r+", encoding="ascii") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        leases: dict[int, float] = {}
        for line in f.read().splitlines():
            with contextlib.suppress(ValueError):
                port, expiry = line.split()
                if float(expiry) > now:
                    leases[int(port)] = float(expiry)
        yield leases
        f.seek(0)
        f.truncate()
        f.write("".join(f"{p} {e:.0f}\n" for p, e in leases.items()))
        # the lock goes with the file's close


def free_port(
    kind: PortKind = "tcp", *, registry: Path | None = _DEFAULT, now: Callable[[], float] = time.time
) -> int:
    """A ``kind`` port on 127.0.0.1 that was free a moment ago and that no other draw
    of this user's got in the last :data:`LEASE_S` s (see the module docstring)."""
    return free_port_range(1, kind, registry=registry, now=now)


def free_port_range(
    count: int,
    kind: PortKind = "tcp",
    step: int = 1,
    *,
    registry: Path | None = _DEFAULT,
    now: Callable[[], float] = time.time,
) -> int:
    """A base port P such that the ``kind`` ports P, P+step, ..., P+(count-1)*step on
    127.0.0.1 were free a moment ago and drawn by no one else (a simulator's vehicles:
    PX4's consecutive UDP ports, ArduPilot's TCP ports 10 apart)."""
    ports = candidates()
    t = now()
    with _leases(REGISTRY if registry is _DEFAULT else registry, t) as leases:
        for _ in range(200):
            base = _RANDOM.choice(ports)
            wanted = [base + step * i for i in range(count)]
            if wanted[-1] >= ports.stop or any(p in leases for p in wanted):
                continue
            if all(bindable(p, kind) for p in wanted):
                leases.update(dict.fromkeys(wanted, t + LEASE_S))
                return base
    if count == 1:  # every draw taken or held: the kernel's choice (the old way)
        with socket.socket(socket.AF_INET, _SOCK_TYPES[kind]) as s:
            s.bind(("127.0.0.1", 0))
            return int(s.getsockname()[1])
    raise RuntimeError(f"no {count} free {kind.upper()} ports {step} apart on 127.0.0.1")


__all__ = ["LEASE_S", "REGISTRY", "PortKind", "candidates", "ephemeral_range", "free_port", "free_port_range"]
