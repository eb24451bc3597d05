"""Telemetry folding, link watching and stream requests: the driver's pure side.

Theory of operation. :class:`TelemetryFolder` is fed every message the link
delivers with the time it arrived (``fold(msg, now)``). It keeps only the
autopilot's (the system and component whose HEARTBEAT :func:`connect` took),
folds each telemetry message into a new immutable :class:`VehicleState` by one
function per message type (``_FOLDS``, the whole mapping in one table), keeps the
last STATUSTEXTs of the autopilot's system and returns what a command in flight
needs to hear (:class:`Heard`: a COMMAND_ACK addressed to us, a STATUSTEXT).
:class:`LinkWatch` decides from the time of the autopilot's last message whether
the link is lost (silent for longer than the timeout) or back, once per change.
:class:`StreamRequests` remembers which message intervals were asked for and says
which to ask again (not heard for 3 periods, at least 3 s; not asked in the last
3 s), and when to ask again for HOME_POSITION. No I/O, no thread, no clock: the
caller passes ``now`` (time.monotonic() in the driver, anything in tests).

Boot. A real autopilot sends positions before it has one: ArduPilot's
GLOBAL_POSITION_INT reads 0, 0, 0 for seconds after boot, its home and EKF origin
come later still, and arming is refused until its EKF uses the GPS. So a position
counts only when :func:`position_problem` finds nothing against it (a GPS report
with a 3D fix, not 0, 0, a non-zero home, and the EKF's absolute horizontal
position when the autopilot sends EKF_STATUS_REPORT); every fold writes the verdict
into :attr:`VehicleState.position_valid` and ``position_reason``.
:func:`arming_problems` says what stands between the vehicle and "armable": still
booting, no valid position or no local position (for position control), and the
pre-arm check bit of SYS_STATUS when the autopilot reports it.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, ClassVar, Literal

from firmware_bridge.modes import (
    MAV_AUTOPILOT_INVALID,
    MAV_MODE_FLAG_SAFETY_ARMED,
    decode_mode,
)
from firmware_bridge.px4_events import MSG_EVENT, EventCatalog, parse_event
from firmware_bridge.setpoints import wrap_yaw

__all__ = [
    "CommandAck",
    "Heard",
    "LinkWatch",
    "StatusText",
    "StreamRequests",
    "TelemetryFolder",
    "VehicleState",
    "arming_problems",
    "interruption",
    "is_autopilot_heartbeat",
    "position_problem",
]

LANDED_UNDEFINED, LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = 0, 1, 2, 3, 4

# MAV_TYPEs that are never an autopilot (GCS, companion, gimbal, ADS-B, camera ...)
NON_VEHICLE_TYPES = frozenset({6, 18, 26, 27, 30, 31, 32, 33, 34, 36, 37, 38, 39, 40, 41, 42})

MSG_SYS_STATUS, MSG_GPS_RAW_INT, MSG_ATTITUDE = 1, 24, 30
MSG_LOCAL_POSITION_NED, MSG_GLOBAL_POSITION_INT = 32, 33
MSG_RADIO_STATUS, MSG_EKF_STATUS_REPORT, MSG_HOME_POSITION, MSG_EXTENDED_SYS_STATE = 109, 193, 242, 245
MAV_SYS_STATUS_SENSOR_GPS = 32
MAV_SYS_STATUS_PREARM_CHECK = 0x10000000  # SYS_STATUS: pre-arm checks (health bit set: passed)
EKF_POS_HORIZ_ABS = 16  # EKF_STATUS_REPORT.flags: the EKF has an absolute horizontal position
MAV_STATE_UNINIT, MAV_STATE_BOOT = 0, 1
GPS_FIX_3D = 3
NO_POSITION_YET = "no position yet"
UNKNOWN_EVENT = f"UNKNOWN_{MSG_EVENT}"
MAV_SEVERITY_WARNING = 4
CHECK_REPORT_S = 1.0  # PX4's arming check events of one report come within this
MAX_CHECKS = 8  # pymavlink's name for an EVENT: its dialect lacks it

HOME_REQUEST = -1  # StreamRequests' key for the one-shot REQUEST_MESSAGE(HOME_POSITION)
REQUEST_AGAIN_S = 3.0  # at most one request per message per 3 s
FALLBACK_AFTER_S = 1.0  # GLOBAL_POSITION_INT's velocity/heading only when the better source is this old


def is_autopilot_heartbeat(msg: Any) -> bool:
    """True for a flight controller's HEARTBEAT (not a GCS, companion or gimbal)."""
    return (
        msg.get_type() == "HEARTBEAT"
        and msg.autopilot != MAV_AUTOPILOT_INVALID
        and msg.type not in NON_VEHICLE_TYPES
    )


@dataclass(frozen=True)
class StatusText:
    """One STATUSTEXT from the autopilot (``time`` is the ``now`` it was folded at)."""

    time: float
    severity: int
    text: str


@dataclass(frozen=True)
class CommandAck:
    """A COMMAND_ACK from the autopilot addressed to us (or to everyone)."""

    command: int
    result: int
    time: float


@dataclass(frozen=True)
class Heard:
    """What one folded message means to a command in flight."""

    ack: CommandAck | None = None
    text: StatusText | None = None


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
    gps_known: bool = False  # a GPS_RAW_INT or SYS_STATUS with a GPS has been heard
    gps_fix: int | None = None  # GPS_RAW_INT fix_type (GPS_FIX_TYPE: 3 3D, 4 DGPS, 5/6 RTK); None: not heard
    satellites: int | None = None  # GPS_RAW_INT satellites_visible; None: not heard or unknown (255)
    prearm_ok: bool | None = None  # SYS_STATUS pre-arm bit; None: the autopilot does not report it
    ekf_flags: int | None = None  # EKF_STATUS_REPORT.flags; None: not heard
    position_valid: bool = False  # the autopilot vouches for lat/lon/alt (position_problem)
    position_reason: str = NO_POSITION_YET  # why not ("" when valid)
    time_boot_ms: int = 0
    last_message_time: float = 0.0
    position_time: float = 0.0  # when the last GLOBAL_POSITION_INT arrived (monotonic)
    last_heartbeat_time: float = 0.0
    checks: tuple[str, ...] = ()  # PX4: the failing arming checks of its latest report (its events)
    checks_time: float = 0.0  # when that report came (monotonic)

    @property
    def in_air(self) -> bool:
        """From EXTENDED_SYS_STATE if the vehicle sends it, else armed and above 0.5 m."""
        if self.landed_state != LANDED_UNDEFINED:
            return self.landed_state in (LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING)
        return self.armed and self.rel_alt is not None and self.rel_alt > 0.5


def interruption(before: VehicleState, now: VehicleState, hold_mode: str | None = None) -> str | None:
    """Why a flight step that started in ``before`` can no longer complete in ``now``
    (None: it still can): the vehicle disarmed although it was armed, or, with
    ``hold_mode``, its autopilot is in another mode (a failsafe, a landing, RC)."""
    if before.armed and not now.armed:
        return f"the vehicle disarmed (mode {now.mode or 'unknown'})"
    if hold_mode is not None and now.mode and now.mode != hold_mode:
        return f"the autopilot left {hold_mode} by itself (now {now.mode})"
    return None


def _text(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", "replace")
    return str(raw).rstrip("\x00").strip()


CHUNK = 50  # characters in one STATUSTEXT
CHUNK_WAIT_S = 1.0  # a text's next chunk comes within this, or the text is given as cut
MAX_PENDING_TEXTS = 8  # texts being joined at once (the oldest given up beyond)
MAX_CHUNKS = 40  # chunks of one text kept (2,000 characters)


class TextJoiner:
    """Joins a MAVLink 2 STATUSTEXT sent in chunks (``id`` not 0, ``chunk_seq`` 0, 1...;
    the last chunk shorter than 50 characters). A text whose next chunk does not come
    within :data:`CHUNK_WAIT_S` is given as far as it came, marked ``[cut]``."""

    def __init__(self) -> None:
        # (component, id) -> (severity, chunks, last heard)
        self._pending: dict[tuple[int, int], tuple[int, dict[int, str], float]] = {}

    def add(self, component: int, text_id: int, seq: int, severity: int, raw: Any, now: float) -> str | None:
        """A chunk heard at ``now``: the whole text once complete, else None."""
        chunk = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
        chunk = chunk.split("\x00", 1)[0]
        if text_id == 0:
            return chunk.strip()
        key = (component, text_id)
        _sev, chunks, _t = self._pending.get(key, (severity, {}, now))
        if len(chunks) < MAX_CHUNKS:
            chunks[seq] = chunk
        if len(chunk) < CHUNK:
            self._pending.pop(key, None)
            return "".join(chunks[i] for i in sorted(chunks)).strip()
        self._pending[key] = (severity, chunks, now)
        while len(self._pending) > MAX_PENDING_TEXTS:
            self._pending.pop(next(iter(self._pending)))
        return None

    def overdue(self, now: float) -> list[tuple[int, str]]:
        """(severity, text) of the texts whose next chunk is overdue at ``now``."""
        out = []
        for key, (sev, chunks, heard) in list(self._pending.items()):
            if now - heard > CHUNK_WAIT_S:
                del self._pending[key]
                out.append((sev, "".join(chunks[i] for i in sorted(chunks)).strip() + " [cut]"))
        return out


_Updates = dict[str, Any]


class TelemetryFolder:
    """Folds the autopilot's messages into :attr:`state` (see the module header).

    ``own_system`` is our MAVLink system id: a COMMAND_ACK for another system is
    not ours. Telemetry fields come only from ``(target_system, target_component)``;
    STATUSTEXTs from any component of ``target_system``.
    """

    def __init__(
        self,
        autopilot: str,
        target_system: int,
        target_component: int,
        own_system: int,
        texts: int = 32,
        events: EventCatalog | None = None,
    ) -> None:
        self.autopilot = autopilot
        self.target_system = target_system
        self.target_component = target_component
        self.own_system = own_system
        self.state = VehicleState(autopilot=autopilot, system_id=target_system, component_id=target_component)
        self.texts: deque[StatusText] = deque(maxlen=texts)
        self._joiner = TextJoiner()
        self.events = events if events is not None else EventCatalog()
        self._checks: list[tuple[float, str]] = []  # PX4's latest failing arming checks, heard when
        self.seen: dict[int, float] = {}  # message id -> when last heard
        self._gps_fix: int | None = None
        self._attitude_time = 0.0
        self._local_time = 0.0

    def texts_since(self, since: float) -> list[str]:
        """The STATUSTEXTs folded at ``since`` or later, oldest first."""
        return [t.text for t in self.texts if t.time >= since]

    def fold(self, msg: Any, now: float) -> Heard:
        """Fold ``msg`` (a pymavlink message) heard at ``now``; never raises on a
        message of the autopilot's dialect (BAD_DATA and strangers are ignored)."""
        mtype = msg.get_type()
        if mtype == UNKNOWN_EVENT:
            return self._event(msg, now)
        if mtype == "BAD_DATA" or msg.get_srcSystem() != self.target_system:
            return Heard()
        text = None
        for severity, cut in self._joiner.overdue(now):
            self.texts.append(StatusText(now, severity, cut))
        if mtype == "STATUSTEXT":
            whole = self._joiner.add(
                msg.get_srcComponent(),
                getattr(msg, "id", 0),
                getattr(msg, "chunk_seq", 0),
                msg.severity,
                msg.text,
                now,
            )
            if whole is not None:
                text = StatusText(now, msg.severity, whole)
                self.texts.append(text)
        if msg.get_srcComponent() != self.target_component:
            return Heard(text=text)
        self.seen[msg.get_msgId()] = now
        if mtype == "HEARTBEAT" and not is_autopilot_heartbeat(msg):
            return Heard(text=text)
        upd: _Updates = {"last_message_time": now}
        ack = None
        if mtype == "COMMAND_ACK":
            if getattr(msg, "target_system", 0) in (0, self.own_system):
                ack = CommandAck(msg.command, msg.result, now)
        else:
            fold = self._FOLDS.get(mtype)
            if fold is not None:
                upd.update(fold(self, msg, now))
        state = replace(self.state, **upd)
        reason = position_problem(state)
        if reason != state.position_reason:
            state = replace(state, position_valid=not reason, position_reason=reason)
        self.state = state
        return Heard(ack=ack, text=text)

    def _event(self, msg: Any, now: float) -> Heard:
        """PX4's events protocol (its reasons: :mod:`firmware_bridge.px4_events`): an
        EVENT of the autopilot's system for everyone or for us, as a text at its level.
        pymavlink hands it over as an unknown frame, header unparsed: read from the bytes."""
        raw = bytes(getattr(msg, "data", b""))
        ev = parse_event(raw)
        if ev is None or raw[5] != self.target_system or ev.destination_system not in (0, self.own_system):
            return Heard()
        text = StatusText(now, ev.level, self.events.text(ev))
        self.texts.append(text)
        if self.events.group(ev) == "arming_check" and ev.level <= MAV_SEVERITY_WARNING:
            # one report's failing checks come together: a new report starts after a pause
            fresh = [(t, c) for t, c in self._checks if now - t <= CHECK_REPORT_S and c != text.text]
            self._checks = [*fresh, (now, text.text)][-MAX_CHECKS:]
            self.state = replace(self.state, checks=tuple(c for _t, c in self._checks), checks_time=now)
        return Heard(text=text)

    # one function per telemetry message: the fields it sets in the next state
    def _heartbeat(self, msg: Any, now: float) -> _Updates:
        return {
            "armed": bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED),
            "mode": decode_mode(self.autopilot, msg.custom_mode, msg.base_mode),
            "base_mode": msg.base_mode,
            "custom_mode": msg.custom_mode,
            "system_status": msg.system_status,
            "last_heartbeat_time": now,
        }

    def _global_position(self, msg: Any, now: float) -> _Updates:
        upd: _Updates = {
            "lat": msg.lat * 1e-7,
            "lon": msg.lon * 1e-7,
            "alt_amsl": msg.alt * 1e-3,
            "rel_alt": msg.relative_alt * 1e-3,
            "time_boot_ms": msg.time_boot_ms,
            "position_time": now,
        }
        if now - self._local_time > FALLBACK_AFTER_S:  # no LOCAL_POSITION_NED lately
            upd["velocity"] = (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01)
        if now - self._attitude_time > FALLBACK_AFTER_S and msg.hdg != 65535:  # no ATTITUDE lately
            upd["yaw"] = wrap_yaw(math.radians(msg.hdg * 0.01))
        return upd

    def _local_position(self, msg: Any, now: float) -> _Updates:
        if not all(math.isfinite(v) for v in (msg.x, msg.y, msg.z)):
            return {}
        self._local_time = now
        return {"ned": (msg.x, msg.y, msg.z), "velocity": (msg.vx, msg.vy, msg.vz)}

    def _attitude(self, msg: Any, now: float) -> _Updates:
        if not math.isfinite(msg.yaw):
            return {}
        self._attitude_time = now
        return {"yaw": wrap_yaw(msg.yaw)}

    def _extended_sys_state(self, msg: Any, now: float) -> _Updates:
        return {"landed_state": msg.landed_state}

    def _sys_status(self, msg: Any, now: float) -> _Updates:
        upd: _Updates = {
            "battery_remaining": msg.battery_remaining,
            "voltage": None if msg.voltage_battery == 65535 else msg.voltage_battery * 1e-3,
        }
        present, health = msg.onboard_control_sensors_present, msg.onboard_control_sensors_health
        if self._gps_fix is None and present & MAV_SYS_STATUS_SENSOR_GPS:
            upd["gps_ok"] = bool(health & MAV_SYS_STATUS_SENSOR_GPS)
            upd["gps_known"] = True
        upd["prearm_ok"] = (
            bool(health & MAV_SYS_STATUS_PREARM_CHECK) if present & MAV_SYS_STATUS_PREARM_CHECK else None
        )
        return upd

    def _gps_raw(self, msg: Any, now: float) -> _Updates:
        self._gps_fix = msg.fix_type  # from now on GPS_RAW_INT, not SYS_STATUS, says whether GPS is ok
        sats = msg.satellites_visible
        return {
            "gps_ok": msg.fix_type >= GPS_FIX_3D,
            "gps_known": True,
            "gps_fix": msg.fix_type if 0 <= msg.fix_type <= 8 else None,
            "satellites": sats if 0 <= sats < 255 else None,
        }

    def _ekf_status(self, msg: Any, now: float) -> _Updates:
        return {"ekf_flags": msg.flags}

    def _home_position(self, msg: Any, now: float) -> _Updates:
        return {"home": (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)}

    #: one function per message type, the whole mapping in one table
    _FOLDS: ClassVar[dict[str, Callable[[TelemetryFolder, Any, float], _Updates]]] = {
        "HEARTBEAT": _heartbeat,
        "GLOBAL_POSITION_INT": _global_position,
        "LOCAL_POSITION_NED": _local_position,
        "ATTITUDE": _attitude,
        "EXTENDED_SYS_STATE": _extended_sys_state,
        "SYS_STATUS": _sys_status,
        "GPS_RAW_INT": _gps_raw,
        "EKF_STATUS_REPORT": _ekf_status,
        "HOME_POSITION": _home_position,
    }


def position_problem(s: VehicleState) -> str:
    """Why ``s``'s position is not (yet) a position, or "" when the autopilot vouches
    for it: a GPS report with a 3D fix, not 0, 0 (what ArduPilot sends while it has
    none), a non-zero home, and, when EKF_STATUS_REPORT is heard, the EKF's absolute
    horizontal position (and latitudes and longitudes that exist)."""
    if s.lat is None or s.lon is None or s.alt_amsl is None:
        return NO_POSITION_YET
    if not all(map(math.isfinite, (s.lat, s.lon, s.alt_amsl))) or (s.lat == 0.0 and s.lon == 0.0):
        return "the autopilot reports no position (0, 0)"
    if not _on_earth(s.lat, s.lon):
        return "position out of range"
    if not s.gps_known:
        return "no GPS report yet"
    if not s.gps_ok:
        return "no GPS fix"
    if s.ekf_flags is not None and not s.ekf_flags & EKF_POS_HORIZ_ABS:
        return "EKF has no absolute position"
    if s.home is None:
        return "no home position yet"
    if s.home[0] == 0.0 and s.home[1] == 0.0:
        return "home is 0, 0"
    if not _on_earth(s.home[0], s.home[1]):
        return "home out of range"
    return ""


def _on_earth(lat: float, lon: float) -> bool:
    return -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0


def arming_problems(s: VehicleState, *, position: bool = True) -> list[str]:
    """What keeps ``s``'s vehicle from being armable ([] = nothing known against it):
    still booting (PX4: its arming checks failing, with the checks its events named),
    and with ``position`` (position control: GUIDED, OFFBOARD) no valid
    position or no local position, then the pre-arm check bit of SYS_STATUS when the
    autopilot reports it (ArduPilot and PX4 set it when their checks pass)."""
    out = []
    if s.autopilot == "px4" and s.system_status == MAV_STATE_UNINIT:
        # PX4 says "uninitialised" whenever its arming checks fail, booted or not
        out.append("arming checks failing" + (f" ({', '.join(s.checks)})" if s.checks else ""))
    elif s.system_status in (MAV_STATE_UNINIT, MAV_STATE_BOOT):
        out.append("autopilot still booting")
    if position and not s.position_valid:
        out.append(s.position_reason)
    if position and s.ned is None:
        out.append("no local position yet")
    if s.prearm_ok is False:
        out.append("pre-arm checks failing")
    return out


class LinkWatch:
    """Lost when the autopilot has been silent for more than ``timeout`` s, back
    when it is heard again; :meth:`check` reports each change once."""

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout
        self.ok = True

    def check(self, last_message_time: float, now: float) -> Literal["lost", "restored"] | None:
        """The change at ``now`` given the time of the autopilot's last message, if any."""
        silent = now - last_message_time > self.timeout
        if self.ok and silent:
            self.ok = False
            return "lost"
        if not self.ok and not silent:
            self.ok = True
            return "restored"
        return None


class StreamRequests:
    """The message intervals asked for, and which to ask for again."""

    def __init__(self) -> None:
        self.rates: dict[int, float] = {}  # message id -> Hz asked for
        self.last_asked: dict[int, float] = {}  # message id (or HOME_REQUEST) -> when

    def asked(self, msg_id: int, rate_hz: float, now: float) -> None:
        """Record that ``msg_id`` was asked for at ``rate_hz`` at ``now``."""
        self.rates[msg_id] = rate_hz
        self.last_asked[msg_id] = now

    def due(self, seen: Mapping[int, float], now: float) -> list[tuple[int, float]]:
        """(message id, rate) of each stream not heard for 3 periods (at least 3 s)
        and not asked for in the last 3 s; the caller asks again and records it."""
        out = []
        for msg_id, rate in self.rates.items():
            stale = now - seen.get(msg_id, 0.0) > max(REQUEST_AGAIN_S, 3.0 / rate)
            if stale and now - self.last_asked.get(msg_id, 0.0) > REQUEST_AGAIN_S:
                out.append((msg_id, rate))
        return out

    def home_due(self, home_known: bool, now: float) -> bool:
        """True (and recorded as asked) when HOME_POSITION should be requested again."""
        if home_known or now - self.last_asked.get(HOME_REQUEST, 0.0) <= REQUEST_AGAIN_S:
            return False
        self.last_asked[HOME_REQUEST] = now
        return True
