"""Companion-side driver of a PX4 or ArduPilot flight controller over MAVLink 2.

Theory of operation. :func:`connect` parses a connection string, opens the link
with pymavlink (its blocking TCP connect and heartbeat wait are replaced by our own
deadlines), waits for the autopilot's HEARTBEAT (GCS and companion heartbeats are
ignored) and returns a :class:`Vehicle`. Three threads then run:

* the *receiver* reads every message, keeps only the autopilot's (target sysid and
  compid), folds telemetry into an immutable :class:`VehicleState` snapshot,
  records COMMAND_ACKs and STATUSTEXTs, and wakes whoever waits on a condition;
* the *housekeeper* sends the companion HEARTBEAT at 1 Hz (type ONBOARD_CONTROLLER,
  component 191), watches the link (no autopilot message for ``link_timeout`` ->
  ``on_link_lost`` once, then ``on_link_restored``) and re-requests telemetry that
  does not arrive (ArduPilot streams nothing until asked; UDP loses requests);
* the *streamer* (only while a target is set) sends the current position target at
  a fixed rate, yaw always finite, and records its own send intervals.

Commands go out as COMMAND_LONG one at a time, each waits for the COMMAND_ACK of
the same command id from the autopilot, with retries; a refusal raises
:class:`CommandRejected` with the autopilot's STATUSTEXT. Mode changes, arming and
OFFBOARD are verified on the next heartbeats, not only by the ACK (PX4 accepts
OFFBOARD while disarmed without a stream). Facts: reference/autopilot.md.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink picks its wire protocol

from pymavlink import mavutil

from firmware_bridge.errors import (
    BridgeError,
    CommandRejected,
    CommandTimeout,
    ConnectError,
    HeartbeatTimeout,
    SetpointError,
)
from firmware_bridge.modes import (
    MAV_AUTOPILOT_INVALID,
    MAV_MODE_FLAG_SAFETY_ARMED,
    autopilot_name,
    canonical_mode,
    decode_mode,
    encode_mode,
)

if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":  # pragma: no cover - imported earlier as v1
    os.environ["MAVLINK20"] = "1"
    mavutil.set_dialect(mavutil.current_dialect)

mavlink: Any = mavutil.mavlink
log = logging.getLogger(__name__)

__all__ = [
    "Endpoint",
    "GlobalTarget",
    "LocalTarget",
    "StatusText",
    "Vehicle",
    "VehicleState",
    "WaitTimeout",
    "connect",
    "parse_url",
    "validate_global",
    "validate_local",
]

# --- constants (reference/autopilot.md sections 1-4) -------------------------------
COMPANION_COMPONENT = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_STATE_ACTIVE = 4
FRAME_LOCAL_NED = 1
FRAME_GLOBAL_RELATIVE_ALT_INT = 6
MASK_POS_YAW = 2552  # ignore velocity, acceleration, force and yaw rate
MASK_POS_VEL_YAW = 2496  # position + velocity feed-forward + yaw
MAX_VELOCITY_MS = 30.0
MASK_POS = 3576

MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
FORCE_MAGIC_PX4 = 21196  # force arm/disarm
FORCE_ARM_ARDUPILOT = 2989

MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
MAV_RESULT_NAMES = {
    0: "ACCEPTED",
    1: "TEMPORARILY_REJECTED",
    2: "DENIED",
    3: "UNSUPPORTED",
    4: "FAILED",
    5: "IN_PROGRESS",
    6: "CANCELLED",
}

LANDED_UNDEFINED, LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = 0, 1, 2, 3, 4

# MAV_TYPEs that are never an autopilot (GCS, companion, gimbal, ADS-B, camera ...)
NON_VEHICLE_TYPES = frozenset({6, 18, 26, 27, 30, 31, 32, 33, 34, 36, 37, 38, 39, 40, 41, 42})

MSG_SYS_STATUS, MSG_GPS_RAW_INT, MSG_ATTITUDE = 1, 24, 30
MSG_LOCAL_POSITION_NED, MSG_GLOBAL_POSITION_INT = 32, 33
MSG_RADIO_STATUS, MSG_HOME_POSITION, MSG_EXTENDED_SYS_STATE = 109, 242, 245
MAV_SYS_STATUS_SENSOR_GPS = 32

# setpoint sanity limits
MAX_LOCAL_M = 10_000.0
MAX_ALT_M = 10_000.0
MIN_ALT_M = -1_000.0

DEFAULT_BAUD = 57600


class WaitTimeout(BridgeError, TimeoutError):
    """A :meth:`Vehicle.wait_for` condition did not come true in time."""


# --- connection strings --------------------------------------------------------------
@dataclass(frozen=True)
class Endpoint:
    """A parsed connection string: ``scheme`` is serial, udpin, udpout or tcp."""

    scheme: Literal["serial", "udpin", "udpout", "tcp"]
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.scheme == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.scheme}:{self.host}:{self.port}"


def _host_port(scheme: str, rest: str, url: str) -> tuple[str, int]:
    rest = rest.removeprefix("//")
    host, sep, port_s = rest.rpartition(":")
    if not sep:
        raise ConnectError(f"{url!r}: expected {scheme}:HOST:PORT")
    host = host.strip("[]")
    try:
        port = int(port_s)
    except ValueError:
        raise ConnectError(f"{url!r}: port {port_s!r} is not a number") from None
    if not 0 < port < 65536:
        raise ConnectError(f"{url!r}: port {port} out of range 1-65535")
    return host, port


def parse_url(url: str) -> Endpoint:
    """Parse ``serial:/dev/ttyAMA0:921600``, ``udp:``/``udpin:HOST:PORT`` (listen, as
    PX4 SITL's API port expects), ``udpout:HOST:PORT`` or ``tcp:HOST:PORT``. A bare
    ``/dev/...`` path is a serial port; ``udp://:14540`` (MAVSDK style) listens.

    Raises:
        ConnectError: malformed string or unknown scheme (nothing is opened here).
    """
    if not isinstance(url, str) or not url.strip():
        raise ConnectError(f"empty connection string {url!r}")
    url = url.strip()
    if url.startswith("/"):
        url = "serial:" + url
    scheme, sep, rest = url.partition(":")
    scheme = scheme.lower()
    if not sep or not rest:
        raise ConnectError(
            f"{url!r}: expected SCHEME:..., e.g. udpin:127.0.0.1:14540, "
            "tcp:127.0.0.1:5760 or serial:/dev/ttyAMA0:921600"
        )
    if scheme == "serial":
        device, colon, baud_s = rest.rpartition(":")
        if not colon:
            device, baud = rest, DEFAULT_BAUD
        else:
            try:
                baud = int(baud_s)
            except ValueError:
                raise ConnectError(f"{url!r}: baud rate {baud_s!r} is not a number") from None
            if baud <= 0:
                raise ConnectError(f"{url!r}: baud rate must be positive")
        if not device:
            raise ConnectError(f"{url!r}: no serial device")
        return Endpoint("serial", device=device, baud=baud)
    if scheme in ("udp", "udpin"):
        host, port = _host_port(scheme, rest, url)
        return Endpoint("udpin", host=host or "0.0.0.0", port=port)
    if scheme in ("udpout", "tcp"):
        host, port = _host_port(scheme, rest, url)
        if not host:
            raise ConnectError(f"{url!r}: {scheme} needs a host")
        return Endpoint("tcp" if scheme == "tcp" else "udpout", host=host, port=port)
    raise ConnectError(f"{url!r}: unknown scheme {scheme!r} (serial, udp, udpin, udpout, tcp)")


def _resolve(ep: Endpoint, kind: socket.SocketKind) -> str:
    try:
        infos = socket.getaddrinfo(ep.host, ep.port, socket.AF_INET, kind)
    except (socket.gaierror, UnicodeError) as e:
        raise ConnectError(f"{ep}: cannot resolve host {ep.host!r}: {e}") from None
    return str(infos[0][4][0])


class _TcpLink(mavutil.mavtcp):
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


def _open(ep: Endpoint, timeout: float, source_system: int) -> Any:
    """Open the pymavlink link for ``ep``.

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
            ip = _resolve(ep, socket.SOCK_DGRAM)
            return mavutil.mavlink_connection(f"udpin:{ip}:{ep.port}", **kw)
        if ep.scheme == "udpout":
            ip = _resolve(ep, socket.SOCK_DGRAM)
            return mavutil.mavlink_connection(f"udpout:{ip}:{ep.port}", **kw)
        ip = _resolve(ep, socket.SOCK_STREAM)
        _TcpLink.connect_timeout = max(0.1, min(timeout, 5.0))
        return _TcpLink(f"{ip}:{ep.port}", retries=0, **kw)
    except ConnectError:
        raise
    except (OSError, ValueError) as e:
        raise ConnectError(f"{ep}: cannot open: {e}") from None


def is_autopilot_heartbeat(msg: Any) -> bool:
    """True for a flight controller's HEARTBEAT (not a GCS, companion or gimbal)."""
    return (
        msg.get_type() == "HEARTBEAT"
        and msg.autopilot != MAV_AUTOPILOT_INVALID
        and msg.type not in NON_VEHICLE_TYPES
    )


# --- state ---------------------------------------------------------------------------
@dataclass(frozen=True)
class StatusText:
    """One STATUSTEXT from the autopilot (``time`` is time.monotonic())."""

    time: float
    severity: int
    text: str


@dataclass(frozen=True)
class VehicleState:
    """A snapshot of the vehicle's telemetry. Unknown values are None (positions) or
    the defaults below. Angles in radians, distances in metres, times monotonic."""

    autopilot: str = "other"
    system_id: int = 0
    component_id: int = 0
    lat: float | None = None
    lon: float | None = None
    alt_amsl: float | None = None
    rel_alt: float | None = None
    ned: tuple[float, float, float] | None = None
    velocity: tuple[float, float, float] | None = None
    yaw: float = 0.0
    armed: bool = False
    mode: str = ""
    base_mode: int = 0
    custom_mode: int = 0
    system_status: int = 0
    landed_state: int = LANDED_UNDEFINED
    battery_remaining: int = -1
    voltage: float | None = None
    home: tuple[float, float, float] | None = None
    gps_ok: bool = False
    time_boot_ms: int = 0
    last_message_time: float = 0.0
    position_time: float = 0.0  # when the last GLOBAL_POSITION_INT arrived (monotonic)
    last_heartbeat_time: float = 0.0

    @property
    def in_air(self) -> bool:
        """From EXTENDED_SYS_STATE if the vehicle sends it, else armed and above 0.5 m."""
        if self.landed_state != LANDED_UNDEFINED:
            return self.landed_state in (LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING)
        return self.armed and self.rel_alt is not None and self.rel_alt > 0.5


# --- setpoints -----------------------------------------------------------------------
@dataclass(frozen=True)
class LocalTarget:
    """Position in the autopilot's local NED frame (EKF origin), yaw in radians."""

    north: float
    east: float
    down: float
    yaw: float
    velocity: tuple[float, float, float] | None = None  # NED m/s feed-forward


@dataclass(frozen=True)
class GlobalTarget:
    """Latitude/longitude in degrees, altitude in metres above home."""

    lat: float
    lon: float
    rel_alt: float
    yaw: float
    velocity: tuple[float, float, float] | None = None  # NED m/s feed-forward


def _wrap(yaw: float) -> float:
    return math.atan2(math.sin(yaw), math.cos(yaw))


def _finite(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SetpointError(f"{name} {value!r} is not a number") from None
    if not math.isfinite(v):
        raise SetpointError(f"{name} is {v}: setpoints must be finite")
    return v


def _velocity(v: Sequence[float] | None) -> tuple[float, float, float] | None:
    if v is None:
        return None
    if len(v) != 3:
        raise SetpointError(f"velocity {v!r}: three components (north, east, down) in m/s")
    out = (_finite("velocity north", v[0]), _finite("velocity east", v[1]), _finite("velocity down", v[2]))
    if any(abs(x) > MAX_VELOCITY_MS for x in out):
        raise SetpointError(f"velocity {out} above {MAX_VELOCITY_MS:g} m/s")
    return out


def validate_local(
    north: float, east: float, down: float, yaw: float, velocity: Sequence[float] | None = None
) -> LocalTarget:
    """Check a local NED setpoint.

    Raises:
        SetpointError: NaN/inf, |north| or |east| > 10 km, altitude out of range.
    """
    n, e, d = _finite("north", north), _finite("east", east), _finite("down", down)
    y = _finite("yaw", yaw)
    for name, v in (("north", n), ("east", e)):
        if abs(v) > MAX_LOCAL_M:
            raise SetpointError(f"{name} {v:g} m is more than {MAX_LOCAL_M:g} m from the origin")
    if not MIN_ALT_M <= -d <= MAX_ALT_M:
        raise SetpointError(f"down {d:g} m is outside {-MAX_ALT_M:g}..{-MIN_ALT_M:g} m")
    return LocalTarget(n, e, d, _wrap(y), _velocity(velocity))


def validate_global(
    lat: float, lon: float, rel_alt: float, yaw: float, velocity: Sequence[float] | None = None
) -> GlobalTarget:
    """Check a global setpoint (altitude relative to home).

    Raises:
        SetpointError: NaN/inf, latitude/longitude out of range, altitude out of range.
    """
    la, lo, a = _finite("lat", lat), _finite("lon", lon), _finite("rel_alt", rel_alt)
    y = _finite("yaw", yaw)
    if not -90.0 <= la <= 90.0:
        raise SetpointError(f"latitude {la:g} outside -90..90")
    if not -180.0 <= lo <= 180.0:
        raise SetpointError(f"longitude {lo:g} outside -180..180")
    if not MIN_ALT_M <= a <= MAX_ALT_M:
        raise SetpointError(f"relative altitude {a:g} m outside {MIN_ALT_M:g}..{MAX_ALT_M:g} m")
    return GlobalTarget(la, lo, a, _wrap(y), _velocity(velocity))


def setpoint_message(
    target: LocalTarget | GlobalTarget, *, time_boot_ms: int, target_system: int, target_component: int
) -> Any:
    """The SET_POSITION_TARGET_* message for ``target``: LOCAL_NED (frame 1) or
    GLOBAL_INT (frame 6, relative altitude), type mask position + yaw (2552), or
    position + velocity feed-forward + yaw (2496) when the target has a velocity."""
    t = time_boot_ms & 0xFFFFFFFF
    vel = target.velocity
    mask = MASK_POS_YAW if vel is None else MASK_POS_VEL_YAW
    vn, ve, vd = vel if vel is not None else (0.0, 0.0, 0.0)
    if isinstance(target, LocalTarget):
        return mavlink.MAVLink_set_position_target_local_ned_message(
            t,
            target_system,
            target_component,
            FRAME_LOCAL_NED,
            mask,
            target.north,
            target.east,
            target.down,
            vn,
            ve,
            vd,
            0,
            0,
            0,
            target.yaw,
            0,
        )
    return mavlink.MAVLink_set_position_target_global_int_message(
        t,
        target_system,
        target_component,
        FRAME_GLOBAL_RELATIVE_ALT_INT,
        mask,
        round(target.lat * 1e7),
        round(target.lon * 1e7),
        target.rel_alt,
        vn,
        ve,
        vd,
        0,
        0,
        0,
        target.yaw,
        0,
    )


@dataclass
class _Ack:
    seq: int
    command: int
    result: int
    time: float


@dataclass
class _Options:
    link_timeout: float = 2.0
    on_link_lost: Callable[[], object] | None = None
    on_link_restored: Callable[[], object] | None = None
    setpoint_rate_hz: float = 10.0
    command_retries: int = 3
    command_timeout: float = 1.0
    telemetry_rate_hz: float = 10.0
    mode_timeout: float = 3.0
    interval_history: int = 2000
    requested: dict[int, float] = field(default_factory=dict)


# --- the vehicle -----------------------------------------------------------------------
class Vehicle:
    """A connected flight controller. Made by :func:`connect`; a context manager."""

    def __init__(
        self,
        conn: Any,
        endpoint: Endpoint,
        heartbeat: Any,
        opts: _Options,
        source_system: int | None,
        source_component: int = COMPANION_COMPONENT,
    ) -> None:
        self._conn = conn
        self.endpoint = endpoint
        self._opts = opts
        self.target_system: int = heartbeat.get_srcSystem()
        self.target_component: int = heartbeat.get_srcComponent()
        self.autopilot: str = autopilot_name(heartbeat.autopilot)
        conn.mav.srcSystem = source_system if source_system is not None else self.target_system
        conn.mav.srcComponent = source_component
        conn.target_system, conn.target_component = self.target_system, self.target_component
        self._t0 = time.monotonic()
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._send_lock = threading.Lock()
        self._cmd_lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        self._state = VehicleState(
            autopilot=self.autopilot, system_id=self.target_system, component_id=self.target_component
        )
        self._acks: deque[_Ack] = deque(maxlen=64)
        self._ack_seq = 0
        self._texts: deque[StatusText] = deque(maxlen=32)
        self._seen: dict[int, float] = {}
        self._last_request: dict[int, float] = {}
        self._gps_fix: int | None = None
        self._attitude_time = 0.0
        self._local_time = 0.0
        self.link_ok = True
        # streamer
        self._target: LocalTarget | GlobalTarget | None = None
        self._stream_thread: threading.Thread | None = None
        self._stream_stop = threading.Event()
        self._stream_started = 0.0
        self._intervals: deque[float] = deque(maxlen=opts.interval_history)
        self.setpoints_sent = 0
        self._handle(heartbeat, time.monotonic())
        self._threads = [
            threading.Thread(target=self._receive_loop, name="fb-receiver", daemon=True),
            threading.Thread(target=self._housekeeping_loop, name="fb-housekeeping", daemon=True),
        ]
        for t in self._threads:
            t.start()

    # -- context manager / lifetime
    def __enter__(self) -> Vehicle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the threads and close the link. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self._stop_streamer()
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(2.0)
        with self._send_lock, contextlib.suppress(Exception):
            self._conn.close()
        with self._cond:
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    # -- state access
    @property
    def state(self) -> VehicleState:
        """The latest telemetry snapshot (immutable)."""
        with self._lock:
            return self._state

    def statustexts(self) -> list[StatusText]:
        """The last STATUSTEXTs from the autopilot, oldest first."""
        with self._lock:
            return list(self._texts)

    def setpoint_intervals(self) -> list[float]:
        """Measured gaps between consecutive setpoint sends, in seconds (last N)."""
        with self._lock:
            return list(self._intervals)

    def wait_for(
        self, predicate: Callable[[VehicleState], bool], timeout: float, what: str = "condition"
    ) -> VehicleState:
        """Wait until ``predicate(state)`` is true; return that state.

        Raises:
            WaitTimeout: not true within ``timeout`` s.
            BridgeError: the vehicle was closed meanwhile.
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                if predicate(self._state):
                    return self._state
                if self._closed:
                    raise BridgeError("vehicle connection closed")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise WaitTimeout(
                        f"{what} not reached within {timeout:g} s "
                        f"(mode {self._state.mode}, armed {self._state.armed}, "
                        f"rel_alt {self._state.rel_alt})"
                    )
                self._cond.wait(min(left, 0.5))

    def wait_altitude(self, rel_alt: float, *, tolerance: float = 0.5, timeout: float = 60.0) -> VehicleState:
        """Wait until the altitude above home is within ``tolerance`` of ``rel_alt``."""
        return self.wait_for(
            lambda s: s.rel_alt is not None and abs(s.rel_alt - rel_alt) <= tolerance,
            timeout,
            f"altitude {rel_alt:g} m",
        )

    def wait_ned(
        self,
        north: float,
        east: float,
        down: float | None = None,
        *,
        tolerance: float = 0.5,
        timeout: float = 60.0,
    ) -> VehicleState:
        """Wait until the local position is within ``tolerance`` m of the point."""

        def near(s: VehicleState) -> bool:
            if s.ned is None:
                return False
            dz = 0.0 if down is None else s.ned[2] - down
            return math.hypot(s.ned[0] - north, s.ned[1] - east, dz) <= tolerance

        return self.wait_for(near, timeout, f"position ({north:g}, {east:g})")

    # -- sending
    def _send(self, msg: Any) -> None:
        with self._send_lock:
            if self._closed and msg.get_type() != "HEARTBEAT":
                raise BridgeError("vehicle connection closed")
            signing = self._conn.mav.signing
            if signing.sign_outgoing:  # pymavlink adds 10 µs a frame: keep up with the wall clock
                signing.timestamp = max(signing.timestamp, signing_timestamp())
            try:
                self._conn.mav.send(msg)
            except OSError as e:
                log.debug("send failed: %s", e)

    def _boot_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000)

    def _command_msg(self, command: int, params: Sequence[float], confirmation: int) -> Any:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        return mavlink.MAVLink_command_long_message(
            self.target_system, self.target_component, command, confirmation, *p
        )

    def send_command_nowait(self, command: int, params: Sequence[float] = ()) -> None:
        """Send a COMMAND_LONG without waiting for its ACK."""
        self._send(self._command_msg(command, params, 0))

    def command(
        self,
        command: int,
        params: Sequence[float] = (),
        *,
        retries: int | None = None,
        timeout: float | None = None,
        in_progress_timeout: float = 30.0,
    ) -> int:
        """Send COMMAND_LONG ``command`` and wait for its ACCEPTED COMMAND_ACK.

        Each try waits ``timeout`` s (default ``command_timeout``); IN_PROGRESS keeps
        waiting (up to ``in_progress_timeout``). Returns MAV_RESULT_ACCEPTED.

        Raises:
            CommandRejected: any other result (with the autopilot's STATUSTEXT).
            CommandTimeout: no ACK after ``retries`` tries.
        """
        tries = self._opts.command_retries if retries is None else max(1, retries)
        per_try = self._opts.command_timeout if timeout is None else timeout
        with self._cmd_lock:
            first_sent = time.monotonic()
            for attempt in range(tries):
                with self._lock:
                    seen = self._ack_seq
                self._send(self._command_msg(command, params, min(attempt, 255)))
                deadline = time.monotonic() + per_try
                hard_deadline = time.monotonic() + in_progress_timeout
                while True:
                    ack = self._wait_ack(command, seen, deadline)
                    if ack is None:
                        break
                    seen = ack.seq
                    if ack.result == MAV_RESULT_IN_PROGRESS:
                        deadline = min(hard_deadline, time.monotonic() + max(per_try, 5.0))
                        continue
                    if ack.result == MAV_RESULT_ACCEPTED:
                        return MAV_RESULT_ACCEPTED
                    text = self._texts_around(first_sent)
                    name = MAV_RESULT_NAMES.get(ack.result, str(ack.result))
                    raise CommandRejected(
                        f"{_cmd_name(command)} rejected by {self.autopilot}: {name}"
                        + (f" ({text})" if text else ""),
                        command=command,
                        result=ack.result,
                        text=text,
                    )
        raise CommandTimeout(
            f"{_cmd_name(command)}: no COMMAND_ACK from {self.autopilot} after {tries} tries of {per_try:g} s"
        )

    def _wait_ack(self, command: int, after_seq: int, deadline: float) -> _Ack | None:
        with self._cond:
            while True:
                for ack in self._acks:
                    if ack.seq > after_seq and ack.command == command:
                        return ack
                left = deadline - time.monotonic()
                if left <= 0 or self._closed:
                    return None
                self._cond.wait(left)

    def _texts_around(self, since: float, grace: float = 0.3) -> str:
        """STATUSTEXTs since ``since`` (minus a margin); waits ``grace`` for a late one."""
        deadline = time.monotonic() + grace
        with self._cond:
            while True:
                texts = [t.text for t in self._texts if t.time >= since - 0.5]
                left = deadline - time.monotonic()
                if texts or left <= 0:
                    return "; ".join(texts)
                self._cond.wait(left)

    # -- modes
    def set_mode(self, name: str) -> None:
        """Switch flight mode by name (PX4 ``OFFBOARD``, ``AUTO.LOITER``...; ArduPilot
        ``GUIDED``, ``LOITER``...; aliases HOLD, RTL, LAND) and verify it on the heartbeat.

        Raises:
            UnknownMode: no such mode on this autopilot.
            CommandRejected: refused, or accepted but the heartbeat never shows it.
            CommandTimeout: never acknowledged.
        """
        key = canonical_mode(self.autopilot, name)
        self.command(MAV_CMD_DO_SET_MODE, encode_mode(self.autopilot, key))
        try:
            self.wait_for(lambda s: s.mode == key, self._opts.mode_timeout, f"mode {key}")
        except WaitTimeout:
            text = self._texts_around(time.monotonic() - self._opts.mode_timeout, grace=0.0)
            raise CommandRejected(
                f"mode {key} accepted but the heartbeat still shows "
                f"{self.state.mode}" + (f" ({text})" if text else ""),
                command=MAV_CMD_DO_SET_MODE,
                result=MAV_RESULT_ACCEPTED,
                text=text,
            ) from None

    # -- arming, takeoff, landing
    def arm(self, force: bool = False) -> None:
        """Arm and wait until the heartbeat shows it.

        Raises:
            CommandRejected: arming refused (text says why), or not armed after the ACK.
            CommandTimeout: never acknowledged.
        """
        magic = 0 if not force else (FORCE_MAGIC_PX4 if self.autopilot == "px4" else FORCE_ARM_ARDUPILOT)
        self.command(MAV_CMD_COMPONENT_ARM_DISARM, (1, magic))
        self._verify(lambda s: s.armed, "armed", MAV_CMD_COMPONENT_ARM_DISARM)

    def disarm(self, force: bool = False) -> None:
        """Disarm (``force`` also in the air: the motors stop!) and verify it."""
        self.command(MAV_CMD_COMPONENT_ARM_DISARM, (0, FORCE_MAGIC_PX4 if force else 0))
        self._verify(lambda s: not s.armed, "disarmed", MAV_CMD_COMPONENT_ARM_DISARM)

    def _verify(self, pred: Callable[[VehicleState], bool], what: str, command: int) -> None:
        try:
            self.wait_for(pred, self._opts.mode_timeout, what)
        except WaitTimeout:
            raise CommandRejected(
                f"{_cmd_name(command)} accepted but the vehicle is not {what}",
                command=command,
                result=MAV_RESULT_ACCEPTED,
                text=self._texts_around(time.monotonic() - 3.0, grace=0.0),
            ) from None

    def home_amsl(self, timeout: float = 3.0) -> float:
        """Home altitude AMSL: HOME_POSITION, else GLOBAL_POSITION_INT alt - relative_alt.

        Raises:
            WaitTimeout: neither known within ``timeout``.
        """
        s = self.wait_for(
            lambda s: s.home is not None or (s.alt_amsl is not None and s.rel_alt is not None),
            timeout,
            "home position",
        )
        if s.home is not None:
            return s.home[2]
        assert s.alt_amsl is not None and s.rel_alt is not None
        return s.alt_amsl - s.rel_alt

    def takeoff(self, rel_alt_m: float, *, wait: bool = True, timeout: float = 60.0) -> None:
        """Take off to ``rel_alt_m`` above home, arming first if needed.

        PX4: MAV_CMD_NAV_TAKEOFF with param7 AMSL (home + rel). ArduPilot: GUIDED,
        arm, NAV_TAKEOFF with param7 relative. ``wait`` waits for the altitude.

        Raises:
            SetpointError: altitude not finite or out of 0.5..MAX_ALT_M.
            CommandRejected, CommandTimeout: from the mode change, arming or takeoff.
            WaitTimeout: the altitude is not reached in ``timeout``.
        """
        alt = _finite("takeoff altitude", rel_alt_m)
        if not 0.5 <= alt <= MAX_ALT_M:
            raise SetpointError(f"takeoff altitude {alt:g} m outside 0.5..{MAX_ALT_M:g} m")
        if self.autopilot == "ardupilot":
            self.set_mode("GUIDED")
            if not self.state.armed:
                self.arm()
            self.command(MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, alt))
        else:
            amsl = self.home_amsl() + alt
            if not self.state.armed:
                self.arm()
            nan = math.nan
            self.command(MAV_CMD_NAV_TAKEOFF, (0, 0, 0, nan, nan, nan, amsl))
        if wait:
            tol = max(0.5, 0.05 * alt)
            self.wait_for(
                lambda s: s.rel_alt is not None and s.rel_alt >= alt - tol,
                timeout,
                f"takeoff altitude {alt:g} m",
            )

    def land(self, *, wait: bool = False, timeout: float = 120.0) -> None:
        """Stop the setpoints and land where the vehicle is (PX4 AUTO.LAND, AP LAND)."""
        self._stop_streamer()
        self.set_mode("LAND")
        if wait:
            self.wait_for(lambda s: s.landed_state == LANDED_ON_GROUND or not s.armed, timeout, "landed")

    def return_to_launch(self) -> None:
        """Stop the setpoints and return home (PX4 AUTO.RTL, ArduPilot RTL)."""
        self._stop_streamer()
        self.set_mode("RTL")

    def hold(self) -> None:
        """Hold position: PX4 AUTO.LOITER; ArduPilot GUIDED at the current position
        (LOITER needs RC throttle, which a companion-only vehicle lacks)."""
        if self.autopilot == "ardupilot":
            s = self.state
            if s.mode != "GUIDED":
                self.set_mode("GUIDED")
            if s.ned is not None and s.in_air:
                self.set_target_ned(*s.ned, yaw=s.yaw)
            return
        self._stop_streamer()
        self.set_mode("AUTO.LOITER")

    # -- position control
    def set_target_ned(
        self,
        north: float,
        east: float,
        down: float,
        yaw: float | None = None,
        velocity: Sequence[float] | None = None,
    ) -> None:
        """Stream SET_POSITION_TARGET_LOCAL_NED to this point (z down, EKF origin);
        yaw defaults to the current heading. Starts the streamer if needed.

        Raises:
            SetpointError: NaN, inf or out of range; nothing is sent.
        """
        target = validate_local(north, east, down, self.state.yaw if yaw is None else yaw, velocity)
        self._set_target(target)

    def set_target_global(
        self,
        lat: float,
        lon: float,
        rel_alt: float,
        yaw: float | None = None,
        velocity: Sequence[float] | None = None,
    ) -> None:
        """Stream SET_POSITION_TARGET_GLOBAL_INT (altitude above home) to this point,
        with an optional NED velocity feed-forward (m/s) for a moving target.

        Raises:
            SetpointError: NaN, inf or out of range; nothing is sent.
        """
        target = validate_global(lat, lon, rel_alt, self.state.yaw if yaw is None else yaw, velocity)
        self._set_target(target)

    @property
    def target(self) -> LocalTarget | GlobalTarget | None:
        with self._lock:
            return self._target

    @property
    def streaming(self) -> bool:
        return self._stream_thread is not None and self._stream_thread.is_alive()

    def _set_target(self, target: LocalTarget | GlobalTarget) -> None:
        if self._closed:
            raise BridgeError("vehicle connection closed")
        with self._lock:
            self._target = target
        if not self.streaming:
            self._stream_stop = threading.Event()
            self._stream_started = time.monotonic()
            self._stream_thread = threading.Thread(
                target=self._stream_loop, args=(self._stream_stop,), name="fb-setpoints", daemon=True
            )
            self._stream_thread.start()

    def stop_setpoints(self) -> None:
        """Stop the setpoint stream (PX4 then leaves OFFBOARD after COM_OF_LOSS_T)."""
        self._stop_streamer()

    def _stop_streamer(self) -> None:
        self._stream_stop.set()
        t = self._stream_thread
        if t is not None and t is not threading.current_thread():
            t.join(2.0)
        self._stream_thread = None
        with self._lock:
            self._target = None

    def start_offboard(
        self, *, takeoff_alt: float = 2.5, stream_first: float = 1.0, timeout: float = 60.0
    ) -> None:
        """Put the vehicle under setpoint control.

        Takes off first if on the ground (to ``takeoff_alt``); holds the current
        position if no target is set. PX4: streams ``stream_first`` s, then OFFBOARD
        (verified on the heartbeat). ArduPilot: GUIDED.

        Raises:
            CommandRejected, CommandTimeout, WaitTimeout: as the steps it takes.
        """
        if not self.state.in_air:
            self.takeoff(takeoff_alt, wait=True, timeout=timeout)
        if self.target is None:
            s = self.wait_for(lambda s: s.ned is not None, 5.0, "local position")
            assert s.ned is not None
            self.set_target_ned(*s.ned, yaw=s.yaw)
        if self.autopilot == "px4":
            self.wait_for(
                lambda s: (
                    time.monotonic() - self._stream_started >= stream_first and self.setpoints_sent >= 3
                ),
                stream_first + 5.0,
                "setpoint stream",
            )
            self.set_mode("OFFBOARD")
        else:
            self.set_mode("GUIDED")

    def _stream_loop(self, stop: threading.Event) -> None:
        period = 1.0 / self._opts.setpoint_rate_hz
        next_t = time.monotonic()
        last: float | None = None
        while not stop.is_set() and not self._stop.is_set():
            now = time.monotonic()
            if now < next_t:
                stop.wait(next_t - now)
                continue
            with self._lock:
                target = self._target
            if target is None:
                break
            msg = setpoint_message(
                target,
                time_boot_ms=self._boot_ms(),
                target_system=self.target_system,
                target_component=self.target_component,
            )
            try:
                self._send(msg)
            except BridgeError:
                break
            t = time.monotonic()
            with self._cond:
                if last is not None:
                    self._intervals.append(t - last)
                self.setpoints_sent += 1
                self._cond.notify_all()
            last = t
            next_t += period
            if next_t < t - period:  # fell far behind (suspended): restart the schedule
                next_t = t + period

    # -- telemetry requests
    def request_message_interval(self, msg_id: int, rate_hz: float) -> None:
        """Ask for ``msg_id`` at ``rate_hz`` (SET_MESSAGE_INTERVAL, ACK not awaited;
        re-sent by the housekeeper while the message does not arrive)."""
        self._opts.requested[msg_id] = rate_hz
        self._last_request[msg_id] = time.monotonic()
        self.send_command_nowait(MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, 1e6 / rate_hz))

    def _request_telemetry(self) -> None:
        fast = self._opts.telemetry_rate_hz
        for msg_id, rate in (
            (MSG_GLOBAL_POSITION_INT, fast),
            (MSG_LOCAL_POSITION_NED, fast),
            (MSG_ATTITUDE, fast),
            (MSG_EXTENDED_SYS_STATE, 2.0),
            (MSG_SYS_STATUS, 1.0),
            (MSG_GPS_RAW_INT, 1.0),
            (MSG_HOME_POSITION, 1.0),
        ):
            self.request_message_interval(msg_id, rate)
        self.send_command_nowait(MAV_CMD_REQUEST_MESSAGE, (MSG_HOME_POSITION,))

    def _rerequest(self, now: float) -> None:
        for msg_id, rate in list(self._opts.requested.items()):
            stale = now - self._seen.get(msg_id, 0.0) > max(3.0, 3.0 / rate)
            if stale and now - self._last_request.get(msg_id, 0.0) > 3.0:
                self.request_message_interval(msg_id, rate)

    # -- threads
    def _receive_loop(self) -> None:
        conn = self._conn
        last_reconnect = 0.0
        while not self._stop.is_set():
            try:
                if getattr(conn, "eof", False):
                    now = time.monotonic()
                    if now - last_reconnect >= 1.0:
                        last_reconnect = now
                        if conn.try_reconnect():
                            log.info("%s: TCP reconnected", self.endpoint)
                            continue
                    self._stop.wait(0.1)
                    continue
                conn.select(0.05)
                while not self._stop.is_set():
                    msg = conn.recv_msg()
                    if msg is None:
                        break
                    self._handle(msg, time.monotonic())
            except Exception as e:  # a dying link must not kill the thread silently
                if self._stop.is_set():
                    break
                log.debug("receive error on %s: %s", self.endpoint, e)
                self._stop.wait(0.1)

    def _housekeeping_loop(self) -> None:
        next_hb = time.monotonic()
        next_check = next_hb + 1.0
        while not self._stop.wait(0.05):
            now = time.monotonic()
            if now >= next_hb:
                self._send_companion_heartbeat()
                next_hb = max(next_hb + 1.0, now + 0.5)
            last = self.state.last_message_time
            if self.link_ok and now - last > self._opts.link_timeout:
                self.link_ok = False
                log.warning("%s: autopilot link lost (%.1f s silent)", self.endpoint, now - last)
                self._callback(self._opts.on_link_lost)
                with self._cond:
                    self._cond.notify_all()
            elif not self.link_ok and now - last <= self._opts.link_timeout:
                self.link_ok = True
                log.info("%s: autopilot link restored", self.endpoint)
                self._callback(self._opts.on_link_restored)
            if now >= next_check:
                next_check = now + 1.0
                if self.link_ok:
                    try:
                        self._rerequest(now)
                        if self.state.home is None and now - self._last_request.get(-1, 0.0) > 3.0:
                            self._last_request[-1] = now
                            self.send_command_nowait(MAV_CMD_REQUEST_MESSAGE, (MSG_HOME_POSITION,))
                    except BridgeError:
                        pass

    @staticmethod
    def _callback(cb: Callable[[], object] | None) -> None:
        if cb is None:
            return
        try:
            cb()
        except Exception:
            log.exception("link callback failed")

    def _send_companion_heartbeat(self) -> None:
        with contextlib.suppress(BridgeError):
            self._send(
                mavlink.MAVLink_heartbeat_message(
                    MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE, 3
                )
            )

    def _handle(self, msg: Any, now: float) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            return
        src = msg.get_srcSystem()
        if src != self.target_system:
            return
        comp = msg.get_srcComponent()
        if mtype == "STATUSTEXT":
            with self._cond:
                self._texts.append(StatusText(now, msg.severity, _text(msg.text)))
                self._cond.notify_all()
            if comp != self.target_component:
                return
        if comp != self.target_component:
            return
        with self._cond:
            s = self._state
            upd: dict[str, Any] = {"last_message_time": now}
            self._seen[msg.get_msgId()] = now
            if mtype == "HEARTBEAT":
                if not is_autopilot_heartbeat(msg):
                    return
                upd.update(
                    armed=bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED),
                    mode=decode_mode(self.autopilot, msg.custom_mode, msg.base_mode),
                    base_mode=msg.base_mode,
                    custom_mode=msg.custom_mode,
                    system_status=msg.system_status,
                    last_heartbeat_time=now,
                )
            elif mtype == "GLOBAL_POSITION_INT":
                upd.update(
                    lat=msg.lat * 1e-7,
                    lon=msg.lon * 1e-7,
                    alt_amsl=msg.alt * 1e-3,
                    rel_alt=msg.relative_alt * 1e-3,
                    time_boot_ms=msg.time_boot_ms,
                    position_time=now,
                )
                if now - self._local_time > 1.0:
                    upd["velocity"] = (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01)
                if now - self._attitude_time > 1.0 and msg.hdg != 65535:
                    upd["yaw"] = _wrap(math.radians(msg.hdg * 0.01))
            elif mtype == "LOCAL_POSITION_NED":
                if all(math.isfinite(v) for v in (msg.x, msg.y, msg.z)):
                    upd.update(ned=(msg.x, msg.y, msg.z), velocity=(msg.vx, msg.vy, msg.vz))
                    self._local_time = now
            elif mtype == "ATTITUDE":
                if math.isfinite(msg.yaw):
                    upd["yaw"] = _wrap(msg.yaw)
                    self._attitude_time = now
            elif mtype == "EXTENDED_SYS_STATE":
                upd["landed_state"] = msg.landed_state
            elif mtype == "SYS_STATUS":
                upd.update(
                    battery_remaining=msg.battery_remaining,
                    voltage=None if msg.voltage_battery == 65535 else msg.voltage_battery * 1e-3,
                )
                if self._gps_fix is None and msg.onboard_control_sensors_present & MAV_SYS_STATUS_SENSOR_GPS:
                    upd["gps_ok"] = bool(msg.onboard_control_sensors_health & MAV_SYS_STATUS_SENSOR_GPS)
            elif mtype == "GPS_RAW_INT":
                self._gps_fix = msg.fix_type
                upd["gps_ok"] = msg.fix_type >= 3
            elif mtype == "HOME_POSITION":
                upd["home"] = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            elif mtype == "COMMAND_ACK":
                tgt = getattr(msg, "target_system", 0)
                if tgt in (0, self._conn.mav.srcSystem):
                    self._ack_seq += 1
                    self._acks.append(_Ack(self._ack_seq, msg.command, msg.result, now))
            self._state = replace(s, **upd)
            self._cond.notify_all()


def _text(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", "replace")
    return str(raw).rstrip("\x00").strip()


_CMD_NAMES = {
    MAV_CMD_NAV_TAKEOFF: "NAV_TAKEOFF",
    MAV_CMD_DO_SET_MODE: "DO_SET_MODE",
    MAV_CMD_COMPONENT_ARM_DISARM: "COMPONENT_ARM_DISARM",
    MAV_CMD_SET_MESSAGE_INTERVAL: "SET_MESSAGE_INTERVAL",
    MAV_CMD_REQUEST_MESSAGE: "REQUEST_MESSAGE",
    21: "NAV_LAND",
    20: "NAV_RETURN_TO_LAUNCH",
}


def _cmd_name(command: int) -> str:
    return _CMD_NAMES.get(command, f"command {command}")


def signing_timestamp() -> int:
    """The wall clock in MAVLink signing units (10 µs since 2015-01-01 UTC)."""
    return int((time.time() - 1420070400) * 100_000)


# --- connect ---------------------------------------------------------------------------
def connect(
    url: str,
    *,
    timeout: float = 10.0,
    source_system: int | None = None,
    source_component: int = COMPANION_COMPONENT,
    signing_key: bytes | None = None,
    link_timeout: float = 2.0,
    on_link_lost: Callable[[], object] | None = None,
    on_link_restored: Callable[[], object] | None = None,
    setpoint_rate_hz: float = 10.0,
    command_retries: int = 3,
    command_timeout: float = 1.0,
    telemetry_rate_hz: float = 10.0,
    mode_timeout: float = 3.0,
    request_telemetry: bool = True,
) -> Vehicle:
    """Open ``url``, wait for the autopilot's heartbeat and return the :class:`Vehicle`.

    The companion's own messages use ``source_system`` (default: the vehicle's sysid)
    and ``source_component`` (191). ``signing_key`` (32 bytes) signs everything sent
    and accepts only signed messages (and unsigned RADIO_STATUS). With
    ``request_telemetry`` false the vehicle's own stream rates are left alone
    (ArduPilot then sends nothing but heartbeats).

    Raises:
        ConnectError: malformed URL, missing device, unresolvable host, bad arguments.
        HeartbeatTimeout: no autopilot heartbeat within ``timeout`` s.
    """
    ep = parse_url(url)
    if signing_key is not None and (not isinstance(signing_key, bytes | bytearray) or len(signing_key) != 32):
        raise ConnectError("signing_key must be 32 bytes")
    if not 1.0 <= setpoint_rate_hz <= 200.0:
        raise ConnectError(f"setpoint_rate_hz {setpoint_rate_hz} outside 1..200 Hz")
    if timeout <= 0 or link_timeout <= 0:
        raise ConnectError("timeout and link_timeout must be positive")
    provisional = source_system if source_system is not None else 1
    conn = _open(ep, timeout, provisional)
    conn.mav.srcComponent = source_component
    try:
        if signing_key is not None:
            conn.setup_signing(
                bytes(signing_key),
                sign_outgoing=True,
                allow_unsigned_callback=lambda _mav, msg_id: msg_id == MSG_RADIO_STATUS,
            )
        hb = _wait_heartbeat(conn, ep, timeout, source_component)
    except BaseException:
        with contextlib.suppress(Exception):
            conn.close()
        raise
    opts = _Options(
        link_timeout=link_timeout,
        on_link_lost=on_link_lost,
        on_link_restored=on_link_restored,
        setpoint_rate_hz=setpoint_rate_hz,
        command_retries=max(1, command_retries),
        command_timeout=command_timeout,
        telemetry_rate_hz=telemetry_rate_hz,
        mode_timeout=mode_timeout,
    )
    vehicle = Vehicle(conn, ep, hb, opts, source_system, source_component)
    try:
        if request_telemetry:
            vehicle._request_telemetry()
    except BaseException:
        vehicle.close()
        raise
    return vehicle


def _wait_heartbeat(conn: Any, ep: Endpoint, timeout: float, component: int) -> Any:
    deadline = time.monotonic() + timeout
    next_hb = 0.0
    hb = mavlink.MAVLink_heartbeat_message(
        MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE, 3
    )
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
            while True:
                msg = conn.recv_msg()
                if msg is None:
                    break
                if (
                    msg.get_type() == "HEARTBEAT"
                    and is_autopilot_heartbeat(msg)
                    and msg.get_srcComponent() != component
                ):
                    return msg
        except OSError as e:
            raise ConnectError(f"{ep}: link error while waiting for a heartbeat: {e}") from None
