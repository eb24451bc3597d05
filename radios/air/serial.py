"""The serial side of one radio: the wire from the host, the input and output buffers.

Theory of operation
-------------------
Bytes the host writes travel on ``RadioState.wire`` as chunks ``(start, end,
data)`` at the serial rate; :func:`arrivals` hands on the bytes that have crossed
by a time ``t``. Without flow control they all arrive and :func:`inbuf_add` drops
what does not fit the 1850-byte input buffer (``srx``). With flow control, a full
buffer stalls the line instead (the host honours CTS): the rest of the wire waits
at ``stalled_at`` and :func:`unstall` shifts it later by the time it waited once
more than 34 bytes are free.

Received data goes through the 645-byte output buffer (:func:`output`, truncated
when full: ``stx``) and leaves at the serial rate: :func:`drain` moves what the
line has carried by ``t`` to ``host_ready``, in closed form (byte ``n`` of a busy
spell leaves at ``drain_base + n * byte_s``), so draining once or at every step
gives the same bytes at the same times. :func:`txbuf_percent` is the free
input buffer as RADIO_STATUS reports it. Pure functions of one
:class:`~radios.air.radio.RadioState`; the model decides when to call them.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator

from radios.air.radio import RadioState

#: CTS is released above this many free bytes in the input buffer.
CTS_RELEASE = 34


def arrivals(r: RadioState, t: float, flow_control: bool) -> Iterator[tuple[bytes, float]]:
    """Yield ``(data, when)`` for the bytes that have crossed the line by ``t``, in
    order; the caller hands each to the radio before asking for the next (a full
    buffer under flow control stalls the line: ``stalled_at`` is set and the
    iteration ends)."""
    while r.wire:
        start, end, data = r.wire[0]
        if end <= t + 1e-12:
            k = len(data)
        elif start < t:
            k = int((t - start) / r.byte_s)
            if k <= 0:
                break
        else:
            break
        if flow_control and (r.at is None or not r.at.in_command_mode):
            room = r.cfg.in_buf - len(r.inbuf)
            if room < k:
                k = max(room, 0)
                if k == 0:
                    r.stalled_at = start
                    break
        arrive = start + k * r.byte_s
        if k < len(data):
            r.wire[0] = (arrive, end, data[k:])
        else:
            r.wire.popleft()
        yield data[:k], min(arrive, t)
        if r.wire and r.wire[0][0] < t and flow_control and r.cfg.in_buf - len(r.inbuf) <= 0:
            r.stalled_at = r.wire[0][0]
            break


def unstall(r: RadioState, t: float) -> float | None:
    """Resume a stalled line once the radio has room again. Returns when the first
    chunk now on the wire ends (the model's next serial event), or None if the line
    stays stalled or is empty."""
    assert r.stalled_at is not None
    if r.cfg.in_buf - len(r.inbuf) <= CTS_RELEASE:
        return None
    delta = max(0.0, t - r.stalled_at)
    r.stalled_at = None
    if delta > 0:
        r.wire = deque((s0 + delta, e0 + delta, d) for s0, e0, d in r.wire)
        r.wire_free_at += delta
    return r.wire[0][1] if r.wire else None


def inbuf_add(r: RadioState, data: bytes) -> None:
    """Data for the air into the input buffer; what does not fit is dropped (srx)."""
    room = r.cfg.in_buf - len(r.inbuf)
    if len(data) > room:
        r.stats.srx += len(data) - max(room, 0)
        data = data[: max(room, 0)]
    r.inbuf += data


def output(r: RadioState, data: bytes, t: float) -> None:
    """Data for the host into the output buffer; what does not fit is cut (stx)."""
    drain(r, t)
    room = r.cfg.out_buf - len(r.outbuf)
    if len(data) > room:
        r.stats.stx += len(data) - max(room, 0)
        data = data[: max(room, 0)]
    r.outbuf += data


def drain(r: RadioState, t: float) -> None:
    """Move the bytes the serial line has carried by ``t`` to the host side.

    Closed form: the line has been busy since ``drain_base`` and byte ``n`` of that
    busy spell has left at ``drain_base + n * byte_s``, so one call at ``t`` moves
    exactly what many calls up to ``t`` would (a simulator may skip steps).
    ``drain_clock`` is when the last byte moved finished; a line found idle (or
    emptied before ``t``) starts its next spell at ``t``, where new bytes begin."""
    if not r.outbuf:
        if r.drain_clock < t:
            r.drain_base = r.drain_clock = t
            r.drained = 0
        return
    k = int((t - r.drain_base) / r.byte_s + 1e-9) - r.drained
    if k <= 0:
        return
    if k > len(r.outbuf):
        k = len(r.outbuf)
    r.host_ready += r.outbuf[:k]
    del r.outbuf[:k]
    r.drained += k
    r.drain_clock = r.drain_base + r.drained * r.byte_s
    if not r.outbuf and r.drain_clock < t:
        r.drain_base = r.drain_clock = t  # the line went idle: a new spell starts at t
        r.drained = 0


def drain_time(r: RadioState, n: int) -> float:
    """When the ``n``-th byte still in the output buffer (1 = the first) has left
    for the host (the same closed form as :func:`drain`)."""
    return r.drain_base + (r.drained + n) * r.byte_s


def txbuf_percent(r: RadioState) -> int:
    """Free input buffer in percent, as RADIO_STATUS ``txbuf`` reports it."""
    free = r.cfg.in_buf - len(r.inbuf)
    return (100 * (free // 8)) // (r.cfg.in_buf // 8)


__all__ = [
    "CTS_RELEASE",
    "arrivals",
    "drain",
    "drain_time",
    "inbuf_add",
    "output",
    "txbuf_percent",
    "unstall",
]
