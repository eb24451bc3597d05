"""Local ports for what the benches, the demo and the tests start on this machine.

A port picked by binding port 0 and closing the socket is in the kernel's ephemeral
range: until the child meant to use it binds it (a process start later), any socket
bound to port 0 or any outgoing connection on the machine can be given the same port,
and the child fails with EADDRINUSE. CI saw exactly that. So the ports here are drawn
at random (from the system's entropy: two processes side by side must not draw alike)
outside the ephemeral range, where the kernel never hands a port out on its own, and
checked free by binding them a moment before they are returned.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path
from typing import Literal

#: the socket kinds a port is asked for
PortKind = Literal["tcp", "udp"]
_SOCK_TYPES = {"tcp": socket.SOCK_STREAM, "udp": socket.SOCK_DGRAM}
_RANDOM = random.SystemRandom()
#: the lowest port drawn (below: well-known and registered services more often run)
LOWEST = 10000


def _bindable(port: int, kind: PortKind) -> bool:
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


def free_port(kind: PortKind = "tcp") -> int:
    """A ``kind`` port on 127.0.0.1 that was free a moment ago (see the module docstring)."""
    ports = candidates()
    for _ in range(200):
        port = _RANDOM.choice(ports)
        if _bindable(port, kind):
            return port
    with socket.socket(socket.AF_INET, _SOCK_TYPES[kind]) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_port_range(count: int, kind: PortKind = "tcp", step: int = 1) -> int:
    """A base port P such that the ``kind`` ports P, P+step, ..., P+(count-1)*step on
    127.0.0.1 were free a moment ago (a simulator's vehicles: PX4's consecutive UDP
    ports, ArduPilot's TCP ports 10 apart)."""
    top = candidates().stop
    for _ in range(50):
        base = free_port(kind)
        if base + step * count > top:
            continue
        if all(_bindable(base + step * i, kind) for i in range(count)):
            return base
    raise RuntimeError(f"no {count} free {kind.upper()} ports {step} apart on 127.0.0.1")


__all__ = ["PortKind", "candidates", "ephemeral_range", "free_port", "free_port_range"]
