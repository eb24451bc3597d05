"""Run simulated vehicles on real sockets: :class:`VehicleSim`.

Theory of operation. One thread runs every vehicle. Each vehicle is an I/O-free
:class:`~firmware_bridge.sim.autopilot.Autopilot` plus a transport:

* ``px4``: a UDP socket on an ephemeral local port that sends to
  ``host:(base_port or 14540)+i`` (as PX4 SITL instance i does) and, once a client has
  talked to it, replies to whoever sent last. Client: ``udpin:host:<port>``.
* ``ardupilot``: a TCP listener on ``host:(base_port or 5760)+10*i``; every accepted
  connection receives all output (as ArduPilot SITL's SERIAL0). Client: ``tcp:host:<port>``.
* ``serial``: vehicle 0 on a serial device (``SimConfig.serial``): ``"pty"`` makes a pseudo
  terminal pair and hands the client its other side (``/dev/pts/N``); any other value
  is opened with pyserial (``DEVICE`` or ``DEVICE:BAUD``, default 921600) and the client
  string returned is that same value (the client is at the other end of the cable).

Simulated time is ``(monotonic() - t0) * speedup``; t0 is ``start()``, or with
``wait_for_client`` (ardupilot's TCP links only) the moment a client first connects to
any vehicle: until then nothing is simulated or sent. Everything inside the autopilot
(physics, COM_OF_LOSS_T, auto-disarm, GUID_TIMEOUT, battery, stream rates and the
fault-hook durations) runs on simulated time, so at ``speedup=5`` a 10 Hz stream
arrives at 50 Hz of wall time. The thread sleeps in ``select`` until the earliest
physics step (50 Hz simulated) or socket event. Public methods are thread-safe.
"""

from __future__ import annotations

import contextlib
import errno
import heapq
import math
import os
import random
import selectors
import socket
import threading
import time
import tty
from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.errors import BridgeError, ConnectError
from firmware_bridge.sim import px4_boot
from firmware_bridge.sim.autopilot import FLAVOURS, LOSS_ACTIONS, Autopilot, Msg, VehicleState
from firmware_bridge.sim.boot import RECORDED_TOTAL

MAX_VEHICLES = 250
REALISTIC_BOOT = RECORDED_TOTAL  # s: ArduCopter SITL's recorded boot, to "EKF3 IMU0 is using GPS"
#: s: each profile's recorded boot (PX4: until arming is allowed)
REALISTIC_BOOTS = {"ardupilot": RECORDED_TOTAL, "px4": px4_boot.RECORDED_TOTAL}


@dataclass(frozen=True)
class SimConfig:
    """Configuration of a :class:`VehicleSim` (see the module docstring for ports)."""

    vehicles: int = 1
    profile: str = "px4"
    home: tuple[float, float, float] = (47.397742, 8.545594, 488.0)  # lat, lon deg, alt m AMSL
    spacing: float = 5.0  # vehicle i starts i*spacing metres east of home
    speedup: float = 1.0  # simulated seconds per wall second
    seed: int = 0
    base_port: int | None = None  # px4: 14540, ardupilot: 5760
    serial: str | None = None  # vehicle 0 on a serial device, or "pty"
    host: str = "127.0.0.1"
    #: PX4 COM_OBL_RC_ACT: position (0, PX4's default), hold (5), land (4) or rtl (3)
    offboard_loss_action: str = "position"
    #: the profile's recorded boot scaled to these simulated seconds (0: booted already;
    #: REALISTIC_BOOTS[profile]: as recorded)
    boot_time: float = 0.0
    #: percent per simulated minute every battery loses, armed or not (tests; 0: flight only)
    battery_drain: float = 0.0
    #: ardupilot over TCP: simulated time stands at 0 until a client connects (as
    #: ArduPilot SITL waits for its SERIAL0 client), so a client sees the boot from its
    #: first second. Not for px4 (its link sends first: a udpin client never talks first)
    #: nor a serial vehicle (nothing says a client is there)
    wait_for_client: bool = False

    def validate(self) -> None:
        """Raise :class:`ConnectError` (a :class:`BridgeError`) for impossible values."""
        if not 1 <= self.vehicles <= MAX_VEHICLES:
            raise ConnectError(f"vehicles must be 1..{MAX_VEHICLES}, got {self.vehicles}")
        if self.profile not in FLAVOURS:
            raise ConnectError(f"profile must be px4 or ardupilot, got {self.profile!r}")
        lat, lon, alt = self.home
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and -1000.0 <= alt <= 10000.0):
            raise ConnectError(f"home out of range: {self.home}")
        if not 0.01 <= self.speedup <= 100.0:
            raise ConnectError(f"speedup must be 0.01..100, got {self.speedup}")
        if not 0.0 <= self.spacing <= 10000.0:
            raise ConnectError(f"spacing must be 0..10000 m, got {self.spacing}")
        if self.offboard_loss_action not in LOSS_ACTIONS:
            raise ConnectError(
                f"offboard_loss_action must be {', '.join(LOSS_ACTIONS)}, got {self.offboard_loss_action!r}"
            )
        if not (math.isfinite(self.boot_time) and 0.0 <= self.boot_time <= 600.0):
            raise ConnectError(f"boot_time must be 0..600 s, got {self.boot_time}")
        if not (math.isfinite(self.battery_drain) and 0.0 <= self.battery_drain <= 6000.0):
            raise ConnectError(f"battery_drain must be 0..6000 percent per minute, got {self.battery_drain}")
        if self.wait_for_client and (FLAVOURS[self.profile].sitl_link != "tcp" or self.serial):
            raise ConnectError("wait_for_client needs the ardupilot profile on TCP (no serial vehicle)")
        base = self.first_port()
        last = base + (self.vehicles - 1) * FLAVOURS[self.profile].sitl_port_step
        if not base >= 1 or last > 65535:
            raise ConnectError(f"ports {base}..{last} out of range")

    def first_port(self) -> int:
        """Vehicle 0's port: ``base_port``, or the SITL default of the profile."""
        return self.base_port if self.base_port is not None else FLAVOURS[self.profile].sitl_base_port


class _Transport(ABC):
    """One vehicle's link: bytes in, bytes out, selectable file objects."""

    endpoint = ""
    kind = ""

    def fileobjs(self) -> list[Any]:
        return []

    def on_readable(self, fileobj: Any, sel: selectors.BaseSelector) -> list[bytes]:
        return []

    def has_client(self) -> bool:
        """A client is connected (only a link with connections can tell)."""
        return False

    @abstractmethod
    def send(self, data: bytes) -> None:
        """Send one packet of MAVLink bytes to the client (dropped if none yet)."""

    @abstractmethod
    def close(self, sel: selectors.BaseSelector) -> None:
        """Unregister from ``sel`` and close the sockets."""


class _UdpTransport(_Transport):
    kind = "udp"

    def __init__(self, host: str, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.sock.setblocking(False)
        self.peer: tuple[str, int] = (host, port)
        self.endpoint = f"udpin:{host}:{port}"

    def fileobjs(self) -> list[Any]:
        return [self.sock]

    def on_readable(self, fileobj: Any, sel: selectors.BaseSelector) -> list[bytes]:
        out = []
        for _ in range(64):
            try:
                data, addr = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break  # e.g. ICMP port unreachable from an earlier send
            self.peer = (addr[0], addr[1])
            out.append(data)
        return out

    def send(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            self.sock.sendto(data, self.peer)

    def close(self, sel: selectors.BaseSelector) -> None:
        with contextlib.suppress(KeyError, ValueError):
            sel.unregister(self.sock)
        self.sock.close()


class _TcpTransport(_Transport):
    kind = "tcp"

    def __init__(self, host: str, port: int) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.listener.bind((host, port))
        except OSError as exc:
            self.listener.close()
            if exc.errno == errno.EADDRINUSE:
                raise ConnectError(f"TCP port {port} is already in use") from None
            raise ConnectError(f"cannot listen on {host}:{port}: {exc.strerror}") from None
        self.listener.listen(4)
        self.listener.setblocking(False)
        self.clients: list[socket.socket] = []
        self.endpoint = f"tcp:{host}:{port}"

    def fileobjs(self) -> list[Any]:
        return [self.listener]

    def on_readable(self, fileobj: Any, sel: selectors.BaseSelector) -> list[bytes]:
        if fileobj is self.listener:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                return []
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.clients.append(conn)
            sel.register(conn, selectors.EVENT_READ, self)
            return []
        try:
            data = fileobj.recv(65536)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError:
            data = b""
        if not data:
            self._drop(fileobj, sel)
            return []
        return [data]

    def _drop(self, conn: socket.socket, sel: selectors.BaseSelector) -> None:
        with contextlib.suppress(KeyError, ValueError):
            sel.unregister(conn)
        if conn in self.clients:
            self.clients.remove(conn)
        conn.close()

    def has_client(self) -> bool:
        return bool(self.clients)

    def send(self, data: bytes) -> None:
        for c in list(self.clients):
            try:
                c.send(data)  # a full buffer drops this frame, like a slow link
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                pass  # closed: noticed on the next read

    def close(self, sel: selectors.BaseSelector) -> None:
        for c in list(self.clients):
            self._drop(c, sel)
        with contextlib.suppress(KeyError, ValueError):
            sel.unregister(self.listener)
        self.listener.close()


class _SerialTransport(_Transport):
    kind = "serial"

    def __init__(self, url: str) -> None:
        self.port: Any = None
        self.slave: int | None = None
        if url == "pty":
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self.fd = master
            self.slave = slave
            self.endpoint = os.ttyname(slave)
            return
        import serial  # pyserial, only when a serial device is used

        dev, baud = url, 921600
        if dev.startswith("serial:"):
            dev = dev[len("serial:") :]
        head, _, tail = dev.rpartition(":")
        if head and tail.isdigit():
            dev, baud = head, int(tail)
        try:
            self.port = serial.serial_for_url(dev, baudrate=baud, timeout=0)
            self.fd = self.port.fileno()
        except (serial.SerialException, OSError, ValueError) as exc:
            # pyserial repeats the errno in its text ("[Errno 2] could not open port X: [Errno 2] ...")
            errno = getattr(exc, "errno", None)
            why = os.strerror(errno) if isinstance(errno, int) else str(exc)
            raise ConnectError(f"cannot open serial device {dev!r}: {why}") from None
        self.endpoint = url

    def fileobjs(self) -> list[Any]:
        return [self.fd]

    def on_readable(self, fileobj: Any, sel: selectors.BaseSelector) -> list[bytes]:
        try:
            data = os.read(self.fd, 65536)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError:
            return []  # pty with no client side open (EIO)
        return [data] if data else []

    def send(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            os.write(self.fd, data)

    def close(self, sel: selectors.BaseSelector) -> None:
        with contextlib.suppress(KeyError, ValueError):
            sel.unregister(self.fd)
        if self.port is not None:
            self.port.close()
        else:
            os.close(self.fd)
            if self.slave is not None:
                os.close(self.slave)


class Vehicle:
    """One simulated vehicle as tests see it: its state and fault hooks.

    All durations are in simulated seconds.
    """

    def __init__(
        self,
        sim: VehicleSim,
        index: int,
        core: Autopilot,
        transport: _Transport,
        start_geo: tuple[float, float, float],
    ) -> None:
        self._sim = sim
        self.index = index
        self.sysid = core.sysid
        self.core = core
        self.transport = transport
        self.endpoint = transport.endpoint
        self.start_geo = start_geo
        self.mav = mavlink.MAVLink(None, core.sysid, 1)
        self.mav.robust_parsing = True
        self.link_down_until = -1.0
        self.latency = 0.0
        self.queue: list[tuple[float, int, bytes]] = []  # (release sim time, seq, bytes)
        self._qseq = 0

    @property
    def state(self) -> VehicleState:
        with self._sim._lock:  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)
            return self.core.snapshot()

    def drop_link(self, seconds: float) -> None:
        """No message in either direction for ``seconds`` of simulated time from now."""
        with self._sim._lock:  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)
            self.link_down_until = self._sim._now() + max(0.0, seconds)  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)

    def set_latency(self, seconds: float) -> None:
        """Delay every outgoing message by ``seconds`` of simulated time (0 = none)."""
        with self._sim._lock:  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)
            self.latency = max(0.0, seconds)

    def fail_gps(self, on: bool) -> None:
        """Fail (True) or restore (False) the GPS: no position, arming refused."""
        with self._sim._lock:  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)
            self.core.set_gps(not on)
            self._sim._wake()  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)

    # ------------------------------------------------------------ loop side
    def _link_up(self, now: float) -> bool:
        return now >= self.link_down_until

    def _emit(self, msgs: list[Msg], now: float) -> None:
        if not msgs or not self._link_up(now):
            return
        data = b"".join(self._pack(m) for m in msgs)
        if self.latency > 0.0:
            self._qseq += 1
            heapq.heappush(self.queue, (now + self.latency, self._qseq, data))
        else:
            self.transport.send(data)

    def _pack(self, m: Msg) -> bytes:
        buf: bytes = m.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def _release(self, now: float) -> None:
        while self.queue and self.queue[0][0] <= now:
            _, _, data = heapq.heappop(self.queue)
            if self._link_up(now):
                self.transport.send(data)

    def _received(self, data: bytes, now: float) -> None:
        if not self._link_up(now):
            return
        try:
            msgs = self.mav.parse_buffer(data) or []
        except mavlink.MAVError:
            return
        for m in msgs:
            if m.get_type() == "BAD_DATA":
                continue
            self._emit(self.core.handle(m, now), now)


class VehicleSim:
    """N simulated multicopters speaking MAVLink 2 like PX4 or ArduPilot SITL.

    ``start()`` opens the links and starts the thread, returning one pymavlink
    connection string per vehicle for the client. ``stop()`` is safe twice and returns
    within 2 s. Raises :class:`~firmware_bridge.errors.ConnectError` for a bad
    configuration or a port that cannot be opened.
    """

    def __init__(self, config: SimConfig) -> None:
        config.validate()
        self.config = config
        self._lock = threading.RLock()
        self._vehicles: list[Vehicle] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._sel: selectors.BaseSelector | None = None
        self._t0 = 0.0
        self._running = not config.wait_for_client  # simulated time runs
        self._wake_r, self._wake_w = -1, -1
        self.error: BaseException | None = None

    # ---------------------------------------------------------------- public
    def start(self) -> list[str]:
        if self._thread is not None:
            return self.endpoints
        cfg = self.config
        sel = selectors.DefaultSelector()
        flavour = FLAVOURS[cfg.profile]
        link = _UdpTransport if flavour.sitl_link == "udp" else _TcpTransport
        base = cfg.first_port()
        transports: list[_Transport] = []
        try:
            for i in range(cfg.vehicles):
                if i == 0 and cfg.serial:
                    transports.append(_SerialTransport(cfg.serial))
                else:
                    transports.append(link(cfg.host, base + flavour.sitl_port_step * i))
        except (ConnectError, OSError) as exc:
            for tr in transports:
                tr.close(sel)
            sel.close()
            if isinstance(exc, ConnectError):
                raise
            raise ConnectError(f"cannot open vehicle link: {exc}") from None
        import pymap3d

        for i, tr in enumerate(transports):
            lat, lon, alt = pymap3d.ned2geodetic(0.0, i * cfg.spacing, 0.0, *cfg.home)
            start = (float(lat), float(lon), float(alt))
            core = Autopilot(
                cfg.profile,
                i + 1,
                start,
                rng=random.Random(cfg.seed * 1009 + i),
                offboard_loss_action=cfg.offboard_loss_action,
                boot_time=cfg.boot_time,
                battery_drain=cfg.battery_drain,
            )
            v = Vehicle(self, i, core, tr, start)
            self._vehicles.append(v)
            for fo in tr.fileobjs():
                sel.register(fo, selectors.EVENT_READ, tr)
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._sel = sel
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="vehicle-sim", daemon=True)
        self._thread.start()
        return self.endpoints

    @property
    def endpoints(self) -> list[str]:
        return [v.endpoint for v in self._vehicles]

    def vehicle(self, i: int) -> Vehicle:
        return self._vehicles[i]

    @property
    def vehicles(self) -> list[Vehicle]:
        return list(self._vehicles)

    def stop(self) -> None:
        self._stop.set()
        th = self._thread
        if th is not None:
            self._wake()
            th.join(timeout=1.5)
        with self._lock:
            sel = self._sel
            self._sel = None
            if sel is not None:
                for v in self._vehicles:
                    v.transport.close(sel)
                sel.close()
            for fd in (self._wake_r, self._wake_w):
                if fd >= 0:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self._wake_r = self._wake_w = -1

    def __enter__(self) -> VehicleSim:
        self.start()
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    # ------------------------------------------------------------------ loop
    def _now(self) -> float:
        if not self._running:
            return 0.0  # waiting for a client: time stands still
        return (time.monotonic() - self._t0) * self.config.speedup

    @property
    def waiting(self) -> bool:
        """Waiting for a client before simulated time starts (``wait_for_client``)."""
        return not self._running

    def _wake(self) -> None:
        if self._wake_w >= 0:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"x")

    def _run(self) -> None:
        try:
            self._loop()
        except Exception as exc:  # keep the reason for whoever looks; never raise in a thread
            self.error = BridgeError(f"vehicle simulator stopped: {exc!r}")
            self.error.__cause__ = exc

    def _loop(self) -> None:
        speed = self.config.speedup
        while not self._stop.is_set():
            sel = self._sel
            if sel is None:
                return
            with self._lock:
                deadline = float("inf")
                if self._running:
                    now = self._now()
                    for v in self._vehicles:
                        v._release(now)  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)
                        v._emit(v.core.tick(now), now)  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)
                        deadline = min(deadline, v.core.next_deadline())
                        if v.queue:
                            deadline = min(deadline, v.queue[0][0])
            timeout = max(0.0, min((deadline - self._now()) / speed, 0.1))
            events = sel.select(timeout)
            if not events:
                continue
            with self._lock:
                now = self._now()
                for key, _ in events:
                    tr = key.data
                    if tr is None:
                        with contextlib.suppress(OSError):
                            os.read(self._wake_r, 4096)
                        continue
                    chunks = tr.on_readable(key.fileobj, sel)
                    if not self._running and tr.has_client():
                        self._t0, self._running = time.monotonic(), True  # the first client
                        now = 0.0
                    if not chunks:
                        continue
                    v = next(x for x in self._vehicles if x.transport is tr)
                    for data in chunks:
                        v._received(data, now)  # noqa: SLF001 (the loop and its vehicles are one unit: one module, one lock)
