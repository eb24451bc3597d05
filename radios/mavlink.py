"""MAVLink framing: whole frames out of a byte stream, and frames built with pymavlink.

Theory of operation
-------------------
Every byte on the air is a MAVLink frame (docs/design/radio-link.md). :class:`FrameParser`
turns an arbitrary byte stream into whole :class:`Frame` objects:

* it looks for a start byte (0xFD for MAVLink 2, 0xFE for MAVLink 1, which old
  SiK firmware still uses for RADIO_STATUS), reads the header to learn the frame
  length (plus 13 signature bytes when the MAVLink 2 "signed" flag is set), and
  waits until the whole frame has arrived: frames may be split at any byte;
* it checks the CRC-16/MCRF4XX with the message's CRC_EXTRA from the pymavlink
  dialect. A frame whose CRC fails, or whose message id is unknown (so its CRC
  cannot be checked), is not trusted: the parser skips only its start byte and
  scans again, so a false start byte inside garbage never swallows the real
  frames that follow;
* every byte it discards is counted (``bytes_skipped``), as is every CRC failure.

Frames are built with pymavlink (:class:`FrameBuilder`) and decoded into pymavlink
message objects with :func:`decode`. The CRC uses crcmod's C implementation; the
parser never raises on input: it only returns frames and counts.
"""

from __future__ import annotations

import random
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import crcmod
from pymavlink.dialects.v20 import ardupilotmega as dialect

from radios.errors import FrameError

STX_V2 = 0xFD
STX_V1 = 0xFE
HEADER_V2 = 10  # STX, len, incompat, compat, seq, sysid, compid, msgid(3)
HEADER_V1 = 6  # STX, len, seq, sysid, compid, msgid
CRC_LEN = 2
SIGNATURE_LEN = 13
IFLAG_SIGNED = 0x01
MAX_FRAME_LEN = HEADER_V2 + 255 + CRC_LEN + SIGNATURE_LEN  # 280

MSG_HEARTBEAT = 0
MSG_RADIO_STATUS = 109
MSG_TUNNEL = 385

_crc16 = crcmod.mkCrcFun(0x11021, initCrc=0xFFFF, rev=True, xorOut=0x0000)

#: msgid -> CRC_EXTRA for every message of the dialect (common + ardupilotmega).
CRC_EXTRA: dict[int, int] = {mid: cls.crc_extra for mid, cls in dialect.mavlink_map.items()}


def x25_crc(data: bytes, crc_extra: int | None = None) -> int:
    """MAVLink's CRC-16/MCRF4XX over ``data``, then over ``crc_extra`` if given."""
    crc = _crc16(data)
    if crc_extra is not None:
        crc = _crc16(bytes((crc_extra,)), crc)
    return int(crc)


def frame_length(buf: bytes | bytearray, start: int = 0) -> int | None:
    """Total length of the frame starting at ``buf[start]`` from its header alone.

    Returns None if ``buf[start]`` is not a start byte or the header is incomplete.
    This is all a SiK radio knows about a frame (it never checks the CRC).
    """
    if len(buf) - start < 3:
        return None
    stx = buf[start]
    if stx == STX_V2:
        n = HEADER_V2 + buf[start + 1] + CRC_LEN
        if buf[start + 2] & IFLAG_SIGNED:
            n += SIGNATURE_LEN
        return n
    if stx == STX_V1:
        return HEADER_V1 + buf[start + 1] + CRC_LEN
    return None


def frame_msgid(raw: bytes) -> int:
    """The message id in the header of the whole frame ``raw`` (v1 or v2)."""
    return raw[7] | (raw[8] << 8) | (raw[9] << 16) if raw[0] == STX_V2 else raw[5]


def frame_problem(raw: bytes) -> str | None:
    """Why the whole frame ``raw`` cannot be trusted, or None if its CRC checks out.
    A frame of an unknown message id cannot have its CRC checked."""
    msgid = frame_msgid(raw)
    end = (HEADER_V2 if raw[0] == STX_V2 else HEADER_V1) + raw[1]
    extra = CRC_EXTRA.get(msgid)
    if extra is None:
        return f"unknown message id {msgid}, its CRC cannot be checked"
    if x25_crc(raw[1:end], extra) != raw[end] | (raw[end + 1] << 8):
        return "bad frame CRC"
    return None


@dataclass(frozen=True, slots=True)
class Frame:
    """One whole, CRC-checked MAVLink frame as it was on the wire."""

    raw: bytes

    @property
    def version(self) -> int:
        return 2 if self.raw[0] == STX_V2 else 1

    @property
    def payload_len(self) -> int:
        return self.raw[1]

    @property
    def signed(self) -> bool:
        return self.version == 2 and bool(self.raw[2] & IFLAG_SIGNED)

    @property
    def seq(self) -> int:
        return self.raw[4] if self.version == 2 else self.raw[2]

    @property
    def sysid(self) -> int:
        return self.raw[5] if self.version == 2 else self.raw[3]

    @property
    def compid(self) -> int:
        return self.raw[6] if self.version == 2 else self.raw[4]

    @property
    def msgid(self) -> int:
        if self.version == 2:
            r = self.raw
            return r[7] | (r[8] << 8) | (r[9] << 16)
        return self.raw[5]

    @property
    def payload(self) -> bytes:
        h = HEADER_V2 if self.version == 2 else HEADER_V1
        return self.raw[h : h + self.payload_len]

    @property
    def name(self) -> str:
        cls = dialect.mavlink_map.get(self.msgid)
        return cls.msgname if cls is not None else f"UNKNOWN_{self.msgid}"

    def __len__(self) -> int:
        return len(self.raw)


@dataclass
class ParserStats:
    frames: int = 0
    bytes: int = 0
    crc_errors: int = 0
    unknown_msgid: int = 0
    bytes_skipped: int = 0


@dataclass
class FrameParser:
    """Incremental MAVLink stream parser that resynchronises after garbage.

    Feed it any bytes with :meth:`feed`; it returns the whole frames completed by
    them. Never raises on input.
    """

    accept_v1: bool = True
    stats: ParserStats = field(default_factory=ParserStats)
    _buf: bytearray = field(default_factory=bytearray)
    #: frames already found valid, shared by parsers that see the same frames (the
    #: simulator's receivers of one broadcast): their CRC is checked once. The caller
    #: bounds its size.
    trusted: set[bytes] | None = None

    def feed(self, data: bytes | bytearray) -> list[Frame]:
        buf = self._buf
        buf += data
        trusted = self.trusted
        self.stats.bytes += len(data)
        out: list[Frame] = []
        i = 0
        n = len(buf)
        while i < n:
            b = buf[i]
            if b != STX_V2 and not (b == STX_V1 and self.accept_v1):
                j = self._next_stx(buf, i + 1)
                self.stats.bytes_skipped += j - i
                i = j
                continue
            total = frame_length(buf, i)
            if total is None or n - i < total:
                break  # wait for more bytes
            raw = bytes(buf[i : i + total])
            if (trusted is not None and raw in trusted) or self._check(raw):
                if trusted is not None:
                    trusted.add(raw)
                out.append(Frame(raw))
                self.stats.frames += 1
                i += total
            else:
                self.stats.bytes_skipped += 1
                i += 1
        del buf[:i]
        return out

    def _next_stx(self, buf: bytearray, start: int) -> int:
        j = buf.find(STX_V2, start)
        if self.accept_v1:
            k = buf.find(STX_V1, start)
            if k != -1 and (j == -1 or k < j):
                j = k
        return len(buf) if j == -1 else j

    def _check(self, raw: bytes) -> bool:
        problem = frame_problem(raw)
        if problem is None:
            return True
        if problem.startswith("unknown"):
            self.stats.unknown_msgid += 1
        else:
            self.stats.crc_errors += 1
        return False

    @property
    def pending(self) -> int:
        """Bytes held while waiting for the rest of a frame."""
        return len(self._buf)

    @property
    def held(self) -> bytearray:
        """The bytes held while waiting for the rest of a frame: the buffer itself, for a
        reader that looks ahead without a copy (the simulator); never change it."""
        return self._buf

    def reset(self) -> None:
        self._buf.clear()


def parse_one(data: bytes) -> Frame:
    """Parse ``data`` as exactly one whole, valid MAVLink frame.

    Raises:
        FrameError: if ``data`` is not exactly one frame with a valid CRC.
    """
    if len(data) > MAX_FRAME_LEN:
        raise FrameError(f"{len(data)} bytes is larger than any MAVLink frame ({MAX_FRAME_LEN})")
    total = frame_length(data)
    if total is None or total != len(data):
        raise FrameError("not exactly one MAVLink frame (bad start byte or length)")
    parser = FrameParser()
    frames = parser.feed(data)
    if len(frames) != 1:
        raise FrameError("MAVLink frame has a bad CRC or an unknown message id")
    return frames[0]


#: MAVLink signing time base: 10 µs units since 2015-01-01 00:00 UTC.
SIGNING_EPOCH = 1420070400


class SigningClock:
    """Signing timestamps for one process (MAVLink 2 signing specification).

    :meth:`issue` returns ``max(last issued + 1, reference())`` where :meth:`reference` is
    the wall clock in 10 µs units since 2015, or the newest timestamp accepted from a
    signed peer if that is later (:meth:`observe`): timestamps follow the wall clock, never
    repeat or go back when the clock steps back, and a machine whose clock is behind (a Pi
    without a real-time clock) takes the swarm's time from the first signed frame it
    accepts. Thread-safe; share one clock between the builders and the verifier of a node.

    ``start``: the node's start reference (:mod:`radios.signing_state`: the time the last
    run reached, carried across the restart): the clock never issues less, and the
    verifier refuses any frame stamped before it (0: none, the clock of a node that keeps
    no state). :meth:`mark` is what is kept for the next start: the latest time issued or
    accepted.
    """

    def __init__(self, start: int = 0) -> None:
        self.start = start
        self._last = 0
        self._seen = start
        self._lock = threading.Lock()

    def reference(self) -> int:
        """The current time: the wall clock, or the newest peer timestamp (or the start
        reference) if later."""
        return max(int((time.time() - SIGNING_EPOCH) * 100_000), self._seen)

    def issue(self) -> int:
        with self._lock:
            self._last = max(self._last + 1, self.reference())
            return self._last

    def observe(self, ts: int) -> None:
        """A timestamp from a frame whose signature was verified."""
        with self._lock:
            if ts > self._seen:
                self._seen = ts

    def mark(self) -> int:
        """The latest timestamp this clock issued or accepted (or its start reference)."""
        with self._lock:
            return max(self._last, self._seen)


class FrameBuilder:
    """Builds MAVLink 2 frames for one (sysid, compid) with its own sequence counter.

    With ``signing_key`` every frame is signed, stamped by ``clock`` (by default one of its
    own) on link ``link_id`` (by default drawn at random, so a restarted process opens a new
    signing stream).
    """

    def __init__(
        self,
        sysid: int,
        compid: int = 0,
        *,
        signing_key: bytes | None = None,
        link_id: int | None = None,
        clock: SigningClock | None = None,
    ) -> None:
        if not 1 <= sysid <= 255:
            raise FrameError(f"system id {sysid} is outside 1..255")
        if not 0 <= compid <= 255:
            raise FrameError(f"component id {compid} is outside 0..255")
        self.mav = dialect.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True
        self.clock: SigningClock | None = None
        if signing_key is not None:
            if len(signing_key) != 32:
                raise FrameError("a MAVLink signing key is 32 bytes")
            self.clock = clock or SigningClock()
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = (random.randrange(256) if link_id is None else link_id) & 0xFF

    def build(self, msg: Any) -> bytes:
        """Pack a pymavlink message object and advance the sequence number."""
        if self.clock is not None:  # pymavlink stamps with this, then adds one we ignore
            self.mav.signing.timestamp = self.clock.issue()
        raw = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return raw

    def heartbeat(self, type_: int = 18, autopilot: int = 8) -> bytes:
        """A HEARTBEAT (default: onboard controller, no autopilot)."""
        return self.build(dialect.MAVLink_heartbeat_message(type_, autopilot, 0, 0, 4, 3))

    def tunnel(self, payload: bytes, *, target_system: int = 0, payload_type: int = 32768) -> bytes:
        if len(payload) > 128:
            raise FrameError(f"TUNNEL payload of {len(payload)} bytes exceeds 128")
        if self.clock is not None:  # signed: pymavlink signs it
            data = payload.ljust(128, b"\0")
            msg = dialect.MAVLink_tunnel_message(target_system, 0, payload_type, len(payload), data)
            return self.build(msg)
        # unsigned: the same bytes pymavlink packs, without building its message object
        # (the simulator sends thousands a second). Field order on the wire: uint16
        # payload_type, then target_system, target_component, payload_length, payload.
        body = _TUNNEL_HEAD.pack(payload_type, target_system, 0, len(payload)) + payload
        seq = self.mav.seq
        self.mav.seq = (seq + 1) % 256
        return pack_frame(MSG_TUNNEL, body, sysid=self.mav.srcSystem, compid=self.mav.srcComponent, seq=seq)


_TUNNEL_HEAD = struct.Struct("<HBBB")

_decoder = dialect.MAVLink(None)
_decoder.robust_parsing = False


def decode(frame: Frame | bytes) -> Any:
    """Decode a frame into a pymavlink message object.

    Raises:
        FrameError: if pymavlink cannot decode it.
    """
    raw = frame.raw if isinstance(frame, Frame) else frame
    try:
        return _decoder.decode(bytearray(raw))
    except Exception as exc:  # pymavlink raises its own MAVError and struct errors
        raise FrameError(f"cannot decode frame: {exc}") from exc


def radio_status_fields(frame: Frame) -> dict[str, int]:
    """The fields of a RADIO_STATUS frame (v1 or v2, zero-extended payload)."""
    p = frame.payload.ljust(9, b"\0")
    rxerrors, fixed, rssi, remrssi, txbuf, noise, remnoise = struct.unpack("<HHBBBBB", p[:9])
    return {
        "rxerrors": rxerrors,
        "fixed": fixed,
        "rssi": rssi,
        "remrssi": remrssi,
        "txbuf": txbuf,
        "noise": noise,
        "remnoise": remnoise,
    }


def pack_frame(msgid: int, payload: bytes, *, sysid: int, compid: int, seq: int, version: int = 2) -> bytes:
    """Pack an unsigned frame from raw payload bytes (used where pymavlink objects are
    overkill, e.g. the emulator's RADIO_STATUS). MAVLink 2 payloads are truncated of
    trailing zeros as the spec requires."""
    extra = CRC_EXTRA[msgid]
    if version == 2:
        body = payload.rstrip(b"\0") or payload[:1]
        hdr = struct.pack(
            "<BBBBBBBHB",
            STX_V2,
            len(body),
            0,
            0,
            seq & 0xFF,
            sysid,
            compid,
            msgid & 0xFFFF,
            msgid >> 16,
        )
    else:
        body = payload
        hdr = struct.pack("<BBBBBB", STX_V1, len(body), seq & 0xFF, sysid, compid, msgid)
    crc = x25_crc(hdr[1:] + body, extra)
    return hdr + body + struct.pack("<H", crc)
