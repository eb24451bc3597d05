"""The packetiser of one radio (SiK packet.c): what the next packet carries.

Theory of operation
-------------------
:func:`packet_get_next` takes at most ``mx`` bytes for the next packet from what a
radio holds: first a remote AT reply waiting to be sent (``injected``, at most 32
bytes a packet; a multipoint ``RTI5`` answer line by line, ``inject_packets``), then
the input buffer. In raw mode (``mavlink == 0``) bytes go as
they come. With MAVLink framing it

* waits for a whole frame, but no longer than the frame's own serial time
  (``mav_pending``, ``mav_start``, ``mav_max_time``), then sends what it has;
* sends the non-MAVLink bytes before a frame start on their own;
* packs as many whole frames as fit (:func:`_mavlink_frames`);
* lets a frame too large for one packet go as plain bytes, split.

Each frame it packs is checked for a HEARTBEAT from the host (packet.c's
``check_heartbeat``): the first one while no report is pending asks for a
RADIO_STATUS, which :func:`packet_get_next` returns as the MAVLink version to
answer in (0: none), for the model to schedule. AES builds carry at most 31 bytes.
Pure: state in, state and bytes out.
"""

from __future__ import annotations

from radios.air.radio import INJECT_MAX, RadioState
from radios.mavlink import STX_V1, STX_V2, frame_length


def packet_get_next(r: RadioState, mx: int, t: float) -> tuple[bytes, bool, int]:
    """``(payload, is_command, heartbeat_version)`` for the next packet at ``t``."""
    if r.cfg.key:
        # packet.c: encrypted packets are at most 32 bytes of cipher text
        mx = 0 if mx <= 16 else 15 if mx <= 32 else 31
    if r.injected and mx > 0:
        n = min(mx, INJECT_MAX)
        chunk = bytes(r.injected[:n])
        del r.injected[:n]
        return chunk, True, 0
    if r.inject_packets and mx >= len(r.inject_packets[0]):
        return r.inject_packets.popleft(), True, 0
    buf = r.inbuf
    if not buf or mx <= 0:
        return b"", False, 0
    if r.cfg.mavlink == 0:
        chunk = bytes(buf[:mx])
        del buf[:mx]
        return chunk, False, 0
    slen = min(len(buf), mx)
    if r.mav_pending == 1:
        hdr = 3 if buf[0] == STX_V2 else 2
        if len(buf) < hdr:
            return _give_up_waiting(r, slen, t), False, 0
        r.mav_pending = 0
    if r.mav_pending:
        if slen < r.mav_pending:
            return _give_up_waiting(r, slen, t), False, 0
        return _mavlink_frames(r, mx)
    return _scan(r, mx, slen, t)


def _give_up_waiting(r: RadioState, slen: int, t: float) -> bytes:
    """While a frame is incomplete: nothing, or once it took longer than its serial
    time, what has come so far."""
    if t - r.mav_start > r.mav_max_time:
        chunk = bytes(r.inbuf[:slen])
        del r.inbuf[:slen]
        r.mav_pending = 0
        return chunk
    return b""


def _wait_for(r: RadioState, flen: int, t: float) -> None:
    r.mav_pending = flen
    r.mav_start = t
    r.mav_max_time = flen * r.byte_s


def _scan(r: RadioState, mx: int, slen: int, t: float) -> tuple[bytes, bool, int]:
    """No frame pending: find the first frame start in the buffer."""
    buf = r.inbuf
    i = 0
    while i < slen:
        c = buf[i]
        if c in (STX_V2, STX_V1):
            hdr = 3 if c == STX_V2 else 2
            if len(buf) - i < hdr:
                if i == 0:
                    r.mav_pending = 1
                    r.mav_start = t
                    r.mav_max_time = r.byte_s * hdr
                    return b"", False, 0
                break
            if buf[i + 1] + 25 > r.t.mav_max_xmit:
                i += 1  # too big to frame: its bytes go as they come
                continue
            flen = frame_length(buf, i) or 0
            if i > 0:
                chunk = bytes(buf[:i])
                del buf[:i]
                _wait_for(r, flen, t)
                return chunk, False, 0
            if flen > len(buf) or flen > mx:
                _wait_for(r, flen, t)
                return b"", False, 0
            return _mavlink_frames(r, mx)
        i += 1
    chunk = bytes(buf[:i])
    del buf[:i]
    return chunk, False, 0


def _mavlink_frames(r: RadioState, mx: int) -> tuple[bytes, bool, int]:
    """As many whole frames from the start of the buffer as fit in ``mx`` bytes."""
    buf = r.inbuf
    first = frame_length(buf, 0) or len(buf)
    used = first
    report = _check_heartbeat(r, buf, 0)
    while len(buf) - used >= 8:
        c = buf[used]
        if c != STX_V2 and c != STX_V1:
            break
        flen = frame_length(buf, used)
        if flen is None or buf[used + 1] + 25 > r.t.mav_max_xmit:
            break
        if flen > mx - used or flen > len(buf) - used:
            break
        report = _check_heartbeat(r, buf, used) or report
        used += flen
    chunk = bytes(buf[:used])
    del buf[:used]
    r.mav_pending = 0
    return chunk, False, report


def _check_heartbeat(r: RadioState, buf: bytearray, i: int) -> int:
    """packet.c's check_heartbeat: one flag, so one report per main-loop pass
    however many heartbeats a packet carried. Returns the version to report in when
    this frame asks for a report, else 0."""
    version = 0
    if buf[i] == STX_V2:
        if len(buf) - i >= 10 and buf[i + 1] <= 9 and buf[i + 7] == 0 and buf[i + 8] == 0 and buf[i + 9] == 0:
            version = 2
    elif buf[i] == STX_V1 and len(buf) - i >= 6 and buf[i + 1] == 9 and buf[i + 5] == 0:
        version = 1
    if version and not r.rs_pending:
        r.rs_pending = True
        return version
    return 0


__all__ = ["packet_get_next"]
