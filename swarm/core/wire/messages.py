"""The swarm messages' one compact binary codec.

Theory of operation
-------------------
Every message is a frozen dataclass of :mod:`swarm.core.wire.message_types` (import the
types from there).
:func:`encode` turns it into bytes and :func:`decode` turns any byte string into a
message or raises :class:`DecodeError` (and nothing else). A SiK radio gives the whole swarm a few
kilobytes per second, so the encoding is tight:

* byte 0 = ``version << 5 | type``: 32 message types, and a protocol version in
  every message at no cost. A message of another version raises
  :class:`VersionMismatch` naming both versions, so mismatched agents fail
  clearly instead of misreading each other;
* agents are named by their MAVLink system id (1 byte) once Advertize has told
  everyone the name; only Advertize and GSAdvertize carry names;
* positions are fixed point: latitude/longitude int32 degE7 (1 cm), altitude
  uint16 decimetres AMSL offset by 1000 m, heading uint16 centidegrees, velocity
  int8 in 0.25 m/s, sample time uint8 in 10 ms (wraps every 2.56 s);
* pools are sorted id sets, sent as a list (1 + n bytes) or, above 32 members,
  a 256-bit bitmap (1 + 32 bytes); an unchanged pool travels as its CRC-32
  digest (crcmod) only: SyncPool of an unchanged pool is 8 bytes;
* optional fields are announced by a flag and absent otherwise, so that what an
  agent without the feature sends keeps its bytes: an Advertize's size byte (only
  an agent with a size cap sends it) follows when its flag ADV_SIZE is set, then its
  swarm name's 16-bit tag (only a named agent sends it) when ADV_SWARM is set;
  a Telemetry's detail block (7 bytes: height above the autopilot's home int16
  decimetres, climb int8 in 0.25 m/s, GPS fix type, satellites, distance from home
  uint16 metres; each field's own "unknown" value) follows its ground speed when the
  agent knows any of them, and an earlier agent's Telemetry without it still decodes.

The field layout of each type is declared once (``_LAYOUT``), and encoder and
decoder are driven by it, so they cannot disagree.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable
from dataclasses import fields
from enum import IntEnum
from typing import Any

from swarm.core.wire import message_types as mt
from swarm.errors import DecodeError, MessageError, VersionMismatch

# -- primitive codecs -----------------------------------------------------------


class _W:
    def __init__(self) -> None:
        self.b = bytearray()

    def u8(self, v: int) -> None:
        if not 0 <= v <= 0xFF:
            raise MessageError(f"value {v} does not fit one byte")
        self.b.append(v)

    def pack(self, fmt: str, *v: Any) -> None:
        try:
            self.b += struct.pack("<" + fmt, *v)
        except struct.error as exc:
            raise MessageError(f"value out of range: {exc}") from None


class _R:
    def __init__(self, data: bytes) -> None:
        self.d = data
        self.i = 1

    def take(self, n: int) -> bytes:
        if self.i + n > len(self.d):
            raise DecodeError(f"truncated message ({len(self.d)} bytes)")
        out = self.d[self.i : self.i + n]
        self.i += n
        return out

    def u8(self) -> int:
        return self.take(1)[0]

    def unpack(self, fmt: str) -> tuple[Any, ...]:
        f = "<" + fmt
        return struct.unpack(f, self.take(struct.calcsize(f)))


def _w_ids(w: _W, ids: Iterable[int]) -> None:
    s = sorted(set(ids))
    for i in s:
        mt.check_id(i)
    if len(s) <= 32:
        w.u8(len(s))
        w.b += bytes(s)
    else:
        w.u8(0x80)
        bits = bytearray(32)
        for i in s:
            bits[i >> 3] |= 1 << (i & 7)
        w.b += bits


def _r_ids(r: _R) -> frozenset[int]:
    n = r.u8()
    if n == 0x80:
        bits = r.take(32)
        ids = frozenset(i for i in range(256) if bits[i >> 3] >> (i & 7) & 1)
        if len(ids) <= 32:  # the encoder sends a list: one message, one spelling
            raise DecodeError(f"pool of {len(ids)} sent as a bitmap")
    elif n > 32:
        raise DecodeError(f"bad pool length byte {n}")
    else:
        raw = r.take(n)
        if list(raw) != sorted(set(raw)):
            raise DecodeError("pool ids not sorted and unique")
        ids = frozenset(raw)
    if ids and (min(ids) < 1 or max(ids) > 250):
        raise DecodeError("pool holds an id outside 1..250")
    return ids


def _w_str(w: _W, s: str, limit: int = 32) -> None:
    raw = s.encode("utf-8")
    if len(raw) > limit:
        raise MessageError(f"text {s!r} longer than {limit} bytes")
    w.u8(len(raw))
    w.b += raw


def _r_str(r: _R, limit: int = 32) -> str:
    n = r.u8()
    if n > limit:
        raise DecodeError(f"text length {n} > {limit}")
    try:
        return r.take(n).decode("utf-8")
    except UnicodeDecodeError:
        raise DecodeError("text is not UTF-8") from None


def _r_name(r: _R) -> str:
    s = _r_str(r)
    if not mt.NAME_RE.match(s):
        raise DecodeError(f"invalid agent name {s!r}")
    return s


def _clamp_i8(v: float, scale: float) -> int:
    return max(-128, min(127, round(v * scale)))


def _w_pose(w: _W, p: mt.Pose) -> None:
    w.pack(
        "iiHHbbB",
        round(p.lat * 1e7),
        round(p.lon * 1e7),
        max(0, min(0xFFFF, round((p.alt + 1000.0) * 10))),
        round((p.heading % 360.0) * 100) % 36000,
        _clamp_i8(p.vn, 4),
        _clamp_i8(p.ve, 4),
        round(p.t * 100) & 0xFF,
    )


def _r_pose(r: _R) -> mt.Pose:
    lat, lon, alt, hdg, vn, ve, t = r.unpack("iiHHbbB")
    if not -900_000_000 <= lat <= 900_000_000 or not -1_800_000_000 <= lon <= 1_800_000_000:
        raise DecodeError("pose latitude/longitude out of range")
    if hdg >= 36000:
        raise DecodeError("pose heading out of range")
    return mt.Pose(lat / 1e7, lon / 1e7, alt / 10.0 - 1000.0, hdg / 100.0, vn / 4.0, ve / 4.0, t / 100.0)


def _w_task(w: _W, t: mt.Task) -> None:
    w.u8(int(t.kind))
    if t.kind == mt.TaskKind.FOLLOW:
        w.pack(
            "HBBBb",
            round((t.heading % 360.0) * 100) % 36000,
            round(t.back_m * 4),
            round(t.side_m * 4),
            t.gen & 0xFF,
            max(-127, min(127, round(t.turn_rate * 2))),
        )
        w.u8(len(t.assignments))
        for a in t.assignments:
            w.pack("BBb", mt.check_id(a.member), mt.check_id(a.follows), int(a.side))


def _r_task(r: _R) -> mt.Task:
    try:
        kind = mt.TaskKind(r.u8())
    except ValueError:
        raise DecodeError("unknown task kind") from None
    if kind != mt.TaskKind.FOLLOW:
        return mt.Task(kind)
    hdg, back, side, gen, rate = r.unpack("HBBBb")
    if hdg >= 36000:
        raise DecodeError("task heading out of range")
    if rate == -128:
        raise DecodeError("task turn rate out of range")
    n = r.u8()
    out = []
    for _ in range(n):
        m, f, s = r.unpack("BBb")
        if s not in (-1, 1):
            raise DecodeError("formation side must be -1 or 1")
        if not (1 <= m <= 250 and 1 <= f <= 250):
            raise DecodeError("formation slot names an id outside 1..250")
        out.append(mt.Assignment(m, f, mt.Side(s)))
    return mt.Task(kind, hdg / 100.0, back / 4.0, side / 4.0, tuple(out), gen, rate / 2.0)


def _enum(cls: type[IntEnum]) -> tuple[Callable[[_W, Any], None], Callable[[_R], Any]]:
    def w(wr: _W, v: Any) -> None:
        wr.u8(int(cls(v)))

    def r(rd: _R) -> Any:
        try:
            return cls(rd.u8())
        except ValueError:
            raise DecodeError(f"bad {cls.__name__} value") from None

    return w, r


def _fmt(fmt: str) -> tuple[Callable[[_W, Any], None], Callable[[_R], Any]]:
    return (lambda w, v: w.pack(fmt, v)), (lambda r: r.unpack(fmt)[0])


def _bool() -> tuple[Callable[[_W, Any], None], Callable[[_R], Any]]:
    def r(rd: _R) -> bool:
        v = rd.u8()
        if v > 1:
            raise DecodeError("boolean byte must be 0 or 1")
        return bool(v)

    return (lambda w, v: w.u8(1 if v else 0)), r


Codec = tuple[Callable[[_W, Any], None], Callable[[_R], Any]]


def _scaled(fmt: str, scale: float, offset: float = 0.0) -> Codec:
    def w(wr: _W, v: float) -> None:
        if not math.isfinite(v):
            raise MessageError(f"{v!r} is not a finite number")
        wr.pack(fmt, round((v + offset) * scale))

    return w, (lambda rd: rd.unpack(fmt)[0] / scale - offset)


def _opt_ids() -> tuple[Callable[[_W, Any], None], Callable[[_R], Any]]:
    def w(wr: _W, v: Any) -> None:
        if v is None:
            wr.u8(0xFF)
        else:
            _w_ids(wr, v)

    def r(rd: _R) -> Any:
        if rd.d[rd.i : rd.i + 1] == b"\xff":
            rd.i += 1
            return None
        return _r_ids(rd)

    return w, r


def _heading() -> tuple[Callable[[_W, Any], None], Callable[[_R], Any]]:
    def w(wr: _W, v: float) -> None:
        if not math.isfinite(v) or not 0.0 <= v < 360.0:
            raise MessageError(f"heading {v!r} outside 0..360 degrees")
        wr.pack("H", round(v * 100) % 36000)

    def r(rd: _R) -> float:
        v = rd.unpack("H")[0]
        if v >= 36000:
            raise DecodeError("heading out of range")
        return float(v / 100.0)

    return w, r


def _id(gcs: bool = False) -> tuple[Callable[[_W, Any], None], Callable[[_R], Any]]:
    def w(wr: _W, v: int) -> None:
        wr.u8(mt.check_id(v, gcs=gcs))

    def r(rd: _R) -> int:
        v = rd.u8()
        if not 1 <= v <= (mt.GCS_ID if gcs else 250):
            raise DecodeError(f"agent id {v} out of range")
        return v

    return w, r


def _opt_id() -> Codec:
    """An agent id, or 0 for none (a leader, a candidate, a command's target: the swarm)."""

    def w(wr: _W, v: int) -> None:
        wr.u8(v if v == 0 else mt.check_id(v))

    def r(rd: _R) -> int:
        v = rd.u8()
        if v > 250:
            raise DecodeError(f"agent id {v} out of range")
        return v

    return w, r


U8, U16, U32 = _fmt("B"), _fmt("H"), _fmt("I")
ID, ANY_ID, OPT_ID = _id(), _id(gcs=True), _opt_id()
NAME = ((lambda w, v: _w_str(w, mt.check_name(v))), _r_name)
TEXT = ((lambda w, v: _w_str(w, v, mt.REASON_MAX)), (lambda r: _r_str(r, mt.REASON_MAX)))
NOTICE_TEXT = ((lambda w, v: _w_str(w, v, mt.NOTICE_MAX)), (lambda r: _r_str(r, mt.NOTICE_MAX)))
IDS = (_w_ids, _r_ids)
POSE = (_w_pose, _r_pose)
TASK = (_w_task, _r_task)
BOOL = _bool()

_LAYOUT: dict[type[mt.Message], list[tuple[str, tuple[Callable[[_W, Any], None], Callable[[_R], Any]]]]] = {
    mt.Advertize: [("sender", ID), ("name", NAME), ("flags", U8)],
    mt.GSAdvertize: [("sender", ANY_ID), ("name", NAME)],
    mt.Heartbeat: [("sender", ID), ("epoch", U16), ("seq", U8), ("members", IDS), ("task", TASK)],
    mt.HeartbeatAck: [("sender", ID), ("seq", U8), ("pose", POSE)],
    mt.StartPool: [("sender", ID)],
    mt.StartPoolAck: [("sender", ID), ("status", _enum(mt.PoolStatus)), ("locked", BOOL), ("members", IDS)],
    mt.SyncPool: [("sender", ID), ("digest", U32), ("locked", BOOL), ("members", _opt_ids())],
    mt.SyncPoolAck: [("sender", ID), ("same", BOOL), ("locked", BOOL), ("members", IDS)],
    mt.Selection: [("sender", ID), ("candidate", ID), ("weight", U32), ("epoch", U16)],
    mt.PoseReport: [("pose", POSE)],
    mt.AgentState: [
        ("sender", ID),
        ("phase", _enum(mt.Phase)),
        ("leader", OPT_ID),
        ("candidate", OPT_ID),
        ("weight", U32),
        ("epoch", U16),
        ("locked", BOOL),
        ("pool", IDS),
        ("members", IDS),
    ],
    mt.GSConnect: [("sender", ANY_ID), ("seq", U16)],
    mt.GSConnectAck: [("sender", ID), ("seq", U16), ("hb_interval_ms", U16)],
    mt.Telemetry: [
        ("sender", ID),
        ("pose", POSE),
        ("mode", U8),
        ("flags", U8),
        ("phase", _enum(mt.Phase)),
        ("leader", OPT_ID),
        ("battery", U8),
        ("rssi", U8),
        ("remrssi", U8),
        ("groundspeed", _scaled("B", 4)),
    ],
    mt.GSHeartbeat: [("sender", ANY_ID), ("seq", U8)],
    mt.Command: [("sender", ANY_ID), ("seq", U16), ("target", OPT_ID), ("kind", _enum(mt.CommandKind))],
    mt.CommandAck: [("sender", ID), ("seq", U16), ("result", _enum(mt.AckResult)), ("reason", TEXT)],
    mt.NameConflict: [("sender", ID), ("name", NAME), ("other_id", ID)],
    mt.AgentNotice: [
        ("sender", ID),
        ("source", _enum(mt.NoticeSource)),
        ("severity", U8),
        ("repeats", U8),
        ("text", NOTICE_TEXT),
    ],
}

# per-kind arguments of a Command
_CMD_ARGS: dict[mt.CommandKind, list[tuple[str, tuple[Callable[[_W, Any], None], Callable[[_R], Any]]]]] = {
    mt.CommandKind.TAKEOFF: [("alt", _scaled("H", 10))],
    mt.CommandKind.GOTO: [
        ("lat", _scaled("i", 1e7)),
        ("lon", _scaled("i", 1e7)),
        ("alt", _scaled("H", 10, 1000.0)),
    ],
    mt.CommandKind.FOLLOW: [("heading", _heading())],
    mt.CommandKind.SET_MODE: [("mode", U8)],
    mt.CommandKind.WAYPOINT: [
        ("lat", _scaled("i", 1e7)),
        ("lon", _scaled("i", 1e7)),
        ("alt", _scaled("H", 10, 1000.0)),
    ],
    mt.CommandKind.GOTO_AMSL: [
        ("lat", _scaled("i", 1e7)),
        ("lon", _scaled("i", 1e7)),
        ("alt", _scaled("H", 10, 1000.0)),
    ],
    mt.CommandKind.WAYPOINT_AMSL: [
        ("lat", _scaled("i", 1e7)),
        ("lon", _scaled("i", 1e7)),
        ("alt", _scaled("H", 10, 1000.0)),
    ],
}

BY_TYPE: dict[int, type[mt.Message]] = {cls.TYPE: cls for cls in _LAYOUT}


def encode(msg: mt.Message) -> bytes:
    """Encode a message.

    Raises:
        MessageError: a field is out of range (our own misuse, not a peer's).
    """
    layout = _LAYOUT.get(type(msg))
    if layout is None:
        raise MessageError(f"{type(msg).__name__} is not a swarm message")
    w = _W()
    w.u8(mt.PROTOCOL_VERSION << 5 | msg.TYPE)
    for name, (wr, _) in layout:
        wr(w, getattr(msg, name))
    if isinstance(msg, mt.Command):
        for name, (wr, _) in _CMD_ARGS.get(msg.kind, []):
            wr(w, getattr(msg, name))
    if isinstance(msg, mt.Advertize) and msg.size:
        w.u8(msg.size)  # a capped agent's size (flag ADV_SIZE, checked by Advertize)
    if isinstance(msg, mt.Advertize) and msg.swarm:
        w.pack("H", msg.swarm)  # a named agent's swarm tag (flag ADV_SWARM)
    if isinstance(msg, mt.Telemetry) and msg.has_detail:
        block = _detail(msg)
        if block != _UNKNOWN:  # a block that knows nothing is left out
            w.pack("hbBBH", *block)
    return bytes(w.b)


# a Telemetry's detail block: the values that mean "unknown"
_NO_ALT, _NO_CLIMB, _NO_FIX, _NO_SATS, _NO_DIST = -32768, -128, 0xFF, 0xFF, 0xFFFF


_UNKNOWN = (_NO_ALT, _NO_CLIMB, _NO_FIX, _NO_SATS, _NO_DIST)


def _detail(m: mt.Telemetry) -> tuple[int, int, int, int, int]:
    def fin(v: float | None) -> float | None:
        return v if v is not None and math.isfinite(v) else None

    alt, climb, dist = fin(m.rel_alt), fin(m.climb), fin(m.home_dist)
    return (
        _NO_ALT if alt is None else max(-32767, min(32767, round(alt * 10))),
        _NO_CLIMB if climb is None else max(-127, min(127, round(climb * 4))),
        _NO_FIX if m.gps_fix is None or not 0 <= m.gps_fix <= 8 else m.gps_fix,
        _NO_SATS if m.satellites is None or not 0 <= m.satellites < 255 else m.satellites,
        _NO_DIST if dist is None else max(0, min(65534, round(dist))),
    )


def _r_detail(r: _R) -> dict[str, Any]:
    alt, climb, fix, sats, dist = r.unpack("hbBBH")
    if fix != _NO_FIX and fix > 8:
        raise DecodeError(f"GPS fix type {fix} out of range")
    if (alt, climb, fix, sats, dist) == _UNKNOWN:
        raise DecodeError("a Telemetry detail block that knows nothing (it is left out)")  # one encoding
    return {
        "rel_alt": None if alt == _NO_ALT else alt / 10.0,
        "climb": None if climb == _NO_CLIMB else climb / 4.0,
        "gps_fix": None if fix == _NO_FIX else fix,
        "satellites": None if sats == _NO_SATS else sats,
        "home_dist": None if dist == _NO_DIST else float(dist),
    }


def decode(data: bytes) -> mt.Message:
    """Decode one message.

    Raises:
        DecodeError: ``data`` is not exactly one valid message (VersionMismatch,
            a subclass, when it is of another protocol version).
    """
    try:
        if not data:
            raise DecodeError("empty message")
        head = data[0]
        version, mtype = head >> 5, head & 0x1F
        if version != mt.PROTOCOL_VERSION:
            raise VersionMismatch(version, mt.PROTOCOL_VERSION)
        cls = BY_TYPE.get(mtype)
        if cls is None:
            raise DecodeError(f"unknown message type {mtype}")
        r = _R(bytes(data))
        values = {name: rd(r) for name, (_, rd) in _LAYOUT[cls]}
        if cls is mt.Command:
            for name, (_, rd) in _CMD_ARGS.get(values["kind"], []):
                values[name] = rd(r)
        if cls is mt.Advertize and values["flags"] & mt.ADV_SIZE:
            values["size"] = r.u8()
        if cls is mt.Advertize and values["flags"] & mt.ADV_SWARM:
            values["swarm"] = r.unpack("H")[0]
        if cls is mt.Telemetry and r.i < len(r.d):  # the detail block (a newer agent)
            values.update(_r_detail(r))
        if r.i != len(r.d):
            raise DecodeError(f"{len(r.d) - r.i} trailing bytes after {cls.__name__}")
        return cls(**values)
    except DecodeError:
        raise
    except (MessageError, ValueError, TypeError, struct.error, IndexError) as exc:
        raise DecodeError(f"invalid message: {exc}") from None


def message_types() -> list[type[mt.Message]]:
    return list(_LAYOUT)


def field_names(cls: type[mt.Message]) -> list[str]:
    return [f.name for f in fields(cls)]


__all__ = ["BY_TYPE", "decode", "encode", "field_names", "message_types"]
