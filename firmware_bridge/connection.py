"""The link to the flight controller: connection strings and the pymavlink connection.

Theory of operation. :func:`parse_url` parses the driver's connection strings
(serial, udp/udpin, udpout, tcp, a bare ``/dev/...`` path, or a radio link's
``/dev/x?baud=N``) with the link layer's grammar (:func:`radios.url.parse_endpoint`:
one grammar for radios and flight controllers); it is pure and opens nothing.
:func:`open_link` opens the pymavlink connection for an :class:`Endpoint` (its
blocking TCP connect and reconnect loop replaced by :class:`TcpLink`, which has a
connect timeout and reports EOF instead of retrying; a refused TCP connect is tried
again every 0.25 s within the caller's timeout, so a script started together with
its simulator or SITL finds it), sets up MAVLink 2 signing, and waits for the
autopilot's HEARTBEAT within what is left of the same deadline while sending the
companion's heartbeat once a second (udpout and serial peers may wait to hear from
us first). On any failure the connection is closed again before the error leaves.
:func:`close_link` closes it, never raising. Errors are one-line
:class:`ConnectError` or :class:`HeartbeatTimeout`.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import socket
import time
from typing import Any

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink picks its wire protocol

from pymavlink import mavutil

from firmware_bridge.errors import ConnectError, HeartbeatTimeout
from firmware_bridge.modes import MAV_AUTOPILOT_INVALID
from firmware_bridge.telemetry import MSG_RADIO_STATUS, is_autopilot_heartbeat
from radios.errors import LinkOpenError
from radios.url import FC_DEFAULT_BAUD as DEFAULT_BAUD
from radios.url import Endpoint, parse_endpoint

if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":  # pragma: no cover - imported earlier as v1
    os.environ["MAVLINK20"] = "1"
    mavutil.set_dialect(mavutil.current_dialect)

mavlink: Any = mavutil.mavlink
log = logging.getLogger("firmware_bridge.driver")

__all__ = [
    "Endpoint",
    "TcpLink",
    "close_link",
    "companion_heartbeat",
    "open_link",
    "parse_url",
    "signing_timestamp",
]

COMPANION_COMPONENT = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_STATE_ACTIVE = 4
RELOCK_SILENCE_S = 3.0  # the locked autopilot silent this long: its system id from elsewhere is it
TCP_RETRY_S = 0.25  # between tries of a refused TCP connect, within connect()'s timeout


def parse_url(url: str) -> Endpoint:
    """Parse a connection string with the link layer's grammar
    (:func:`radios.url.parse_endpoint`): ``serial:/dev/ttyAMA0:921600`` or
    ``/dev/ttyAMA0?baud=921600``, ``udp:``/``udpin:HOST:PORT`` (listen, as PX4 SITL's
    API port expects), ``udpout:HOST:PORT`` or ``tcp:HOST:PORT``. A bare ``/dev/...``
    path is a serial port at 57600 baud; ``udp://:14540`` (MAVSDK style) listens.

    Raises:
        ConnectError: malformed string or unknown scheme (nothing is opened here).
    """
    try:
        return parse_endpoint(url, default_baud=DEFAULT_BAUD)
    except LinkOpenError as exc:
        raise ConnectError(str(exc)) from None


def _resolve(ep: Endpoint, kind: socket.SocketKind) -> str:
    try:
        infos = socket.getaddrinfo(ep.host, ep.port, socket.AF_INET, kind)
    except (socket.gaierror, UnicodeError) as e:
        raise ConnectError(f"{ep}: cannot resolve host {ep.host!r}: {e}") from None
    return str(infos[0][4][0])


class UdpInLink(mavutil.mavudp):
    """``udpin:``: pymavlink's UDP server, kept to one autopilot. pymavlink's own reads
    every sender on the port and writes to every one it heard: with a second vehicle
    sending there, every command went to both. Once :meth:`lock` names the address
    of the autopilot whose heartbeat was taken, datagrams from any other address are
    dropped (counted in :attr:`strangers`, each new one said once in the log) and
    everything is written to that address only. The same system id from a new address
    after :data:`RELOCK_SILENCE_S` of silence from the locked one is the autopilot
    restarted (a simulator or a UDP bridge sends from a new port each start): followed,
    and said."""

    def __init__(self, device: str, **kw: Any) -> None:
        super().__init__(device, input=True, **kw)
        self.last_from: tuple[str, int] | None = None  # the sender of the last datagram read
        self.locked: tuple[str, int] | None = None
        self.locked_system = 0
        self.strangers: dict[tuple[str, int], int] = {}
        self.systems: dict[tuple[str, int], int] = {}  # before the lock: who sent from where
        self.locked_heard = 0.0  # when the locked address last sent (monotonic)

    def lock(self, address: tuple[str, int], system: int) -> None:
        self.locked, self.locked_system = address, system
        self.locked_heard = time.monotonic()
        self.clients = {address}
        self.clients_last_alive = {address: time.time()}

    def recv(self, n: int | None = None) -> Any:
        try:
            data, addr = self.port.recvfrom(mavutil.UDP_MAX_PACKET_LEN)
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return ""
            raise
        now = time.monotonic()
        if self.locked is not None and addr != self.locked:
            system = _first_system(data)
            if system == self.locked_system and now - self.locked_heard > RELOCK_SILENCE_S:
                # the same autopilot from a new address after a silence: it restarted
                # (a simulator or a UDP bridge sends from a new port each start)
                log.warning(
                    "%s: the autopilot (system %d) is now at %s:%d, silent at %s:%d for %.0f s: following it",
                    self.address,
                    system,
                    *addr,
                    *self.locked,
                    now - self.locked_heard,
                )
                self.strangers.pop(addr, None)
                self.lock(addr, system)
        if self.locked is not None and addr != self.locked:
            if addr not in self.strangers:
                system = _first_system(data)
                log.warning(
                    "%s: another MAVLink sender at %s:%d (system %d) ignored: this link is locked to "
                    "the autopilot at %s:%d (system %d); give each vehicle a port of its own",
                    self.address,
                    *addr,
                    system,
                    *self.locked,
                    self.locked_system,
                )
            self.strangers[addr] = self.strangers.get(addr, 0) + 1
            return ""
        self.last_from = addr
        self.locked_heard = now
        if self.locked is None:
            self.clients.add(addr)
            self.clients_last_alive[addr] = time.time()
            self.systems[addr] = _first_system(data)
        return data

    def sender_of(self, system: int) -> tuple[str, int] | None:
        """The address a datagram of ``system`` came from (the last datagram's first)."""
        if self.last_from is not None and self.systems.get(self.last_from) == system:
            return self.last_from
        return next((a for a, sy in self.systems.items() if sy == system), self.last_from)


def _first_system(data: bytes) -> int:
    """The system id in the header of a datagram's first frame (0 if none)."""
    if data[:1] == b"\xfd" and len(data) > 5:
        return data[5]
    if data[:1] == b"\xfe" and len(data) > 3:
        return data[3]
    return 0


class TcpLink(mavutil.mavtcp):
    """pymavlink's TCP link with a connect timeout and no retry loop on EOF."""

    connect_timeout = 5.0
    port: socket.socket | None
    eof: bool

    def do_connect(self) -> None:
        sock = socket.create_connection(self.destination_addr, timeout=self.connect_timeout)
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        mavutil.set_close_on_exec(sock.fileno())
        self.port = sock
        self.eof = False
        if hasattr(self, "fd"):
            self.fd = sock.fileno()

    def handle_eof(self) -> None:
        self.eof = True

    def handle_disconnect(self) -> None:
        self.eof = True

    def recv(self, n: int | None = None) -> bytes:
        if getattr(self, "eof", False) or self.port is None:
            return b""
        try:
            data: bytes = super().recv(n)
        except OSError:
            self.eof = True
            return b""
        return data

    def write(self, buf: bytes) -> None:
        if getattr(self, "eof", False) or self.port is None:
            return
        super().write(buf)

    def try_reconnect(self) -> bool:
        with contextlib.suppress(OSError):
            if self.port is not None:
                self.port.close()
        self.port = None
        try:
            self.connect_timeout = 1.0
            self.do_connect()
        except OSError:
            self.port = None
            return False
        return True


def _open(ep: Endpoint, deadline: float, source_system: int) -> Any:
    """Open the pymavlink link for ``ep``; a refused TCP connect is tried again until
    ``deadline`` (monotonic): the autopilot's port may open a moment after we start.

    Raises:
        ConnectError: missing device, unresolvable host, port in use, refused.
    """
    kw = {"source_system": source_system, "source_component": COMPANION_COMPONENT}
    try:
        if ep.scheme == "serial":
            if not os.path.exists(ep.device):
                raise ConnectError(f"{ep}: serial device {ep.device} does not exist")
            return mavutil.mavlink_connection(ep.device, baud=ep.baud, autoreconnect=False, **kw)
        if ep.scheme == "udpin":
            return UdpInLink(f"{_resolve(ep, socket.SOCK_DGRAM)}:{ep.port}", **kw)
        if ep.scheme == "udpout":
            ip = _resolve(ep, socket.SOCK_DGRAM)
            return mavutil.mavlink_connection(f"{ep.scheme}:{ip}:{ep.port}", **kw)
        ip = _resolve(ep, socket.SOCK_STREAM)
        while True:
            TcpLink.connect_timeout = max(0.1, min(deadline - time.monotonic(), 5.0))
            try:
                return TcpLink(f"{ip}:{ep.port}", retries=0, **kw)
            except ConnectionRefusedError:
                if time.monotonic() + TCP_RETRY_S >= deadline:
                    raise
                time.sleep(TCP_RETRY_S)
    except ConnectError:
        raise
    except (OSError, ValueError) as e:
        raise ConnectError(f"{ep}: cannot open: {e}") from None


def open_link(
    ep: Endpoint,
    *,
    timeout: float,
    source_system: int,
    source_component: int,
    signing_key: bytes | None = None,
) -> tuple[Any, Any]:
    """Open ``ep``, set up signing and wait for the autopilot's HEARTBEAT; return
    ``(connection, heartbeat)``. With ``signing_key`` everything sent is signed and
    only signed messages (and unsigned RADIO_STATUS) are accepted.

    Raises:
        ConnectError: missing device, unresolvable host, refused, link error.
        HeartbeatTimeout: no autopilot heartbeat within ``timeout`` s.
    """
    deadline = time.monotonic() + timeout
    conn = _open(ep, deadline, source_system)
    conn.mav.srcComponent = source_component
    try:
        if signing_key is not None:
            conn.setup_signing(
                bytes(signing_key),
                sign_outgoing=True,
                allow_unsigned_callback=lambda _mav, msg_id: msg_id == MSG_RADIO_STATUS,
            )
        hb = _wait_heartbeat(conn, ep, deadline, timeout, source_component)
        if isinstance(conn, UdpInLink):
            sender = conn.sender_of(hb.get_srcSystem())
            if sender is not None:
                conn.lock(sender, hb.get_srcSystem())
        return conn, hb
    except BaseException:
        close_link(conn)
        raise


def close_link(conn: Any) -> None:
    """Close the pymavlink connection; never raises (closing twice is fine)."""
    with contextlib.suppress(Exception):
        conn.close()


def companion_heartbeat() -> Any:
    """The companion computer's HEARTBEAT (ONBOARD_CONTROLLER, no autopilot, active)."""
    return mavlink.MAVLink_heartbeat_message(
        MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE, 3
    )


def signing_timestamp() -> int:
    """The wall clock in MAVLink signing units (10 µs since 2015-01-01 UTC)."""
    return int((time.time() - 1420070400) * 100_000)


def _autopilot_heartbeat_in(conn: Any, component: int) -> Any | None:
    """The first autopilot HEARTBEAT (not from ``component``) among the messages
    waiting on ``conn``, or None once they are read."""
    while True:
        msg = conn.recv_msg()
        if msg is None:
            return None
        if is_autopilot_heartbeat(msg) and msg.get_srcComponent() != component:
            return msg


def _wait_heartbeat(conn: Any, ep: Endpoint, deadline: float, timeout: float, component: int) -> Any:
    next_hb = 0.0
    hb = companion_heartbeat()
    while True:
        now = time.monotonic()
        if now >= deadline:
            raise HeartbeatTimeout(f"{ep}: no autopilot heartbeat within {timeout:g} s")
        if getattr(conn, "eof", False):
            raise ConnectError(f"{ep}: connection closed by the peer before any heartbeat")
        if now >= next_hb:  # udpout and serial peers may wait to hear from us first
            with contextlib.suppress(OSError):
                conn.mav.send(hb)
            next_hb = now + 1.0
        try:
            conn.select(min(0.1, max(0.0, deadline - now)))
            msg = _autopilot_heartbeat_in(conn, component)
        except OSError as e:
            raise ConnectError(f"{ep}: link error while waiting for a heartbeat: {e}") from None
        if msg is not None:
            return msg
