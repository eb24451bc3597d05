"""Replay: captures as a receive-only link, re-fed to a port, decoded and summarised.

Theory of operation
-------------------
A capture (:mod:`radios.tlog`) stores when each frame passed. Replaying it means
handing the frames on with the same gaps, scaled and capped. One small object,
:class:`Pacer`, turns recorded times into deadlines on an injected clock:

* the first frame is due at once (``clock()`` when it is asked for);
* each next frame is due one step later, where the step is the recorded gap
  divided by ``speed`` and then capped at ``max_gap`` seconds (so a capture with a
  silent hour replays in seconds); ``speed=0`` makes every step zero (as fast as
  possible) and a timestamp that goes backwards counts as no gap;
* deadlines are absolute, so a slow consumer does not accumulate drift: frames
  that are late are handed on at once until the replay catches up.

Two things are built on it, both taking ``clock`` and ``sleep`` as parameters so
tests run on a fake clock without real time passing (python-can's ``player.py``,
improved, STYLE.md point 9):

* :class:`TlogLink` (``open_link("tlog:PATH?speed=X&max_gap=S")`` or a path ending in
  ``.tlog``; :func:`open_tlog_url` is the registry's factory): the link backend
  for replay. Receive-only. ``recv(timeout)`` returns the next frame when it is
  due, or None if it is not due within ``timeout``; at
  the end of the capture it raises ``LinkClosedError("... end of capture")``. A
  damaged capture delivers every whole frame, ends the same way, and keeps the
  damage in :attr:`TlogLink.damage`.
* :class:`Player`: writes the records to a port (a :class:`~radios.linkbase.Link` or any
  ``write(bytes)`` callable) at their time; a stop :class:`threading.Event` (set
  by a signal handler) ends it promptly.

Without an injected ``sleep`` both wait on real time, and ``close()``,
``Player.stop()`` or the stop event cut a long wait short (a signal handler that
sets the event does so within a quarter of a second).

For people, :func:`decode_record` turns a record into a JSON-ready dict,
:func:`format_record` into one MAVProxy-like text line, and
:func:`capture_stats` (:class:`CaptureStats`) summarises who used the air.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass
from typing import Any

from radios.errors import (
    CaptureDamagedError,
    CaptureError,
    ConfigError,
    FrameError,
    LinkClosedError,
    LinkOpenError,
)
from radios.linkbase import Link
from radios.mavlink import MSG_RADIO_STATUS, Frame, decode
from radios.tlog import TlogReader, TlogRecord, read_tlog
from radios.url import LinkURL, Options, parse_link_url

DEFAULT_SPEED = 1.0
DEFAULT_MAX_GAP = 5.0

#: Air-time approximation used by :func:`capture_stats`: bytes a frame costs on the
#: air beyond its own, as if each frame went in its own SiK packet with ECC off
#: (preamble 5, sync word 2, NETID header 2, length 1, packet CRC 2, TDM trailer 2).
#: Real SiK radios pack several frames per packet and spend time in TDM silences
#: and the peer's window; the emulator's air model accounts for all that. This
#: constant only keeps many short frames from looking free next to a few long ones.
AIRTIME_OVERHEAD_BYTES = 14

#: The ids a SiK radio gives the RADIO_STATUS it reports to its host (not on air).
LOCAL_RADIO_IDS = (51, 68)

#: Longest uninterrupted wait of the default sleeps (see _wait_unless).
_SIGNAL_SLICE = 0.25

Sleep = Callable[[float], object]
Clock = Callable[[], float]


def _wait_unless(event: threading.Event, seconds: float) -> None:
    """The default sleep: ``seconds`` of real time, ended at once by ``event``.

    It waits in slices because a Python signal handler (say one that sets
    ``event``, or raises KeyboardInterrupt) runs in the main thread only between
    bytecodes: a lock wait in the main thread is cut short only if the OS happens
    to deliver the signal to that thread rather than to another thread.
    """
    deadline = time.monotonic() + seconds
    while not event.is_set():
        left = deadline - time.monotonic()
        if left <= 0:
            return
        event.wait(min(left, _SIGNAL_SLICE))


# -- pacing ---------------------------------------------------------------------------


def _check_pacing(speed: float, max_gap: float) -> None:
    if not (math.isfinite(speed) and speed >= 0):
        raise ConfigError(f"speed must be a finite number >= 0 (0 = as fast as possible), not {speed}")
    if math.isnan(max_gap) or max_gap < 0:
        raise ConfigError(f"max_gap must be >= 0 seconds (inf = no cap), not {max_gap}")


class Pacer:
    """Deadlines on ``clock`` for records stamped with recorded times.

    Raises:
        ConfigError: ``speed`` is negative or not finite, or ``max_gap`` is
            negative or NaN.
    """

    def __init__(
        self,
        *,
        speed: float = DEFAULT_SPEED,
        max_gap: float = DEFAULT_MAX_GAP,
        clock: Clock = time.monotonic,
    ) -> None:
        _check_pacing(speed, max_gap)
        self.speed = speed
        self.max_gap = max_gap
        self.clock = clock
        self._due: float | None = None
        self._last_t = 0.0

    def step(self, gap: float) -> float:
        """Wall-clock seconds to wait for a recorded ``gap``."""
        if self.speed == 0 or gap <= 0:
            return 0.0
        return min(gap / self.speed, self.max_gap)

    def due(self, t: float) -> float:
        """The ``clock`` time at which the record stamped ``t`` is due. Call once per
        record, in order."""
        if self._due is None:
            self._due = self.clock()
        else:
            self._due += self.step(t - self._last_t)
        self._last_t = t
        return self._due


# -- the replay link ------------------------------------------------------------------


class TlogLink(Link):
    """Receive-only link over a capture file; see the module docstring.

    Build it with :func:`open_tlog_link` (or ``radios.link.open_link``).
    ``damage`` holds the damage message once a damaged capture has ended, and
    ``ended`` says the last frame has been delivered.
    """

    can_send = False

    def __init__(
        self,
        url: str,
        reader: TlogReader,
        *,
        speed: float = DEFAULT_SPEED,
        max_gap: float = DEFAULT_MAX_GAP,
        clock: Clock = time.monotonic,
        sleep: Sleep | None = None,
    ) -> None:
        super().__init__(url)
        self.path = reader.path
        self._reader = reader
        self._pacer = Pacer(speed=speed, max_gap=max_gap, clock=clock)
        self._clock = clock
        self._wake = threading.Event()
        self._sleep: Sleep = sleep if sleep is not None else self._wait
        self._next: TlogRecord | None = None
        self._next_due = 0.0
        self._end: str | None = None
        self.damage: str | None = None

    @property
    def ended(self) -> bool:
        return self._end is not None

    @property
    def speed(self) -> float:
        return self._pacer.speed

    @property
    def max_gap(self) -> float:
        return self._pacer.max_gap

    def _wait(self, seconds: float) -> None:
        _wait_unless(self._wake, seconds)

    def _read(self, timeout: float) -> bytes:  # pragma: no cover - recv is overridden
        """Unused: :meth:`recv` reads the capture records directly."""
        return b""

    def _write(self, data: bytes) -> None:
        raise LinkClosedError(f"{self.url} is receive-only")

    def _fetch(self) -> TlogRecord:
        if self._end is None:
            try:
                return next(self._reader)
            except StopIteration:
                self._end = f"{self.path}: end of capture"
            except CaptureDamagedError as exc:
                self.damage = str(exc)
                self._end = f"{self.path}: end of capture ({exc})"
        raise LinkClosedError(self._end)

    def recv(self, timeout: float | None = None) -> Frame | None:
        """The next recorded frame once it is due, or None if it is not due within
        ``timeout`` seconds of the injected clock (None waits as long as needed, 0
        polls).

        Raises:
            LinkClosedError: the link is closed, or the capture has ended (message
                "... end of capture"; after damage :attr:`damage` says what).
        """
        with self._recv_lock:
            if self._closed:
                raise LinkClosedError(f"{self.url} is closed")
            if self._next is None:
                self._next = self._fetch()
                self._next_due = self._pacer.due(self._next.t)
            wait = self._next_due - self._clock()
            if wait > 0:
                if timeout is not None and timeout < wait:
                    if timeout > 0:
                        self._sleep(timeout)
                    if self._closed:
                        raise LinkClosedError(f"{self.url} is closed")
                    return None
                self._sleep(wait)
                if self._closed:
                    raise LinkClosedError(f"{self.url} is closed")
            rec, self._next = self._next, None
            self._stats.frames_in += 1
            self._stats.bytes_in += len(rec.raw)
            return rec.frame

    def _close(self) -> None:
        self._wake.set()
        with self._recv_lock:
            self._reader.close()


def open_tlog_link(
    url: str,
    *,
    clock: Clock = time.monotonic,
    sleep: Sleep | None = None,
) -> TlogLink:
    """Open ``tlog:PATH?speed=X&max_gap=S`` (or a plain ``PATH.tlog``) for replay,
    see :func:`open_tlog_url`."""
    return open_tlog_url(parse_link_url(url), clock=clock, sleep=sleep)


def open_tlog_url(
    url: LinkURL,
    *,
    clock: Clock = time.monotonic,
    sleep: Sleep | None = None,
) -> TlogLink:
    """Open the capture ``url`` names for replay (the backend factory of ``tlog``).

    ``speed`` (default 1.0) scales the recorded pace, 0 means as fast as possible;
    ``max_gap`` (default 5 s, ``inf`` for none) caps each wait. ``clock`` and
    ``sleep`` are injected for tests; without ``sleep`` waits end early on close.

    Raises:
        LinkOpenError: malformed or unknown option, no path, or the capture cannot
            be opened (missing, a directory, no permission).
    """
    opts = Options(url)
    speed = opts.number("speed", DEFAULT_SPEED)
    max_gap = opts.number("max_gap", DEFAULT_MAX_GAP)
    opts.finish(("speed", "max_gap"))
    if not url.target:
        raise LinkOpenError(f"{url.url}: no capture file path")
    try:
        _check_pacing(speed, max_gap)
    except ConfigError as exc:
        raise LinkOpenError(f"{url.url}: {exc}") from None
    try:
        reader = read_tlog(url.target)
    except CaptureError as exc:
        raise LinkOpenError(str(exc)) from exc
    return TlogLink(url.url, reader, speed=speed, max_gap=max_gap, clock=clock, sleep=sleep)


# -- re-feeding a port ----------------------------------------------------------------


@dataclass
class PlayStats:
    """What a :class:`Player` has done so far. ``elapsed`` is on the player's
    clock; ``recorded`` is the span of recorded time covered."""

    frames: int = 0
    bytes: int = 0
    first_t: float | None = None
    last_t: float | None = None
    elapsed: float = 0.0
    stopped: bool = False

    @property
    def recorded(self) -> float:
        if self.first_t is None or self.last_t is None:
            return 0.0
        return self.last_t - self.first_t

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["recorded"] = self.recorded
        return d


class Player:
    """Hands the ``records`` of a capture on at their recorded pace.

    Iterating a Player yields each record when it is due (python-can's
    ``MessageSync``); :meth:`play` writes each one to a port. ``stop`` (an event,
    e.g. a :class:`~swarm.cli.util.StopFlag`'s) or :meth:`stop` ends it before the
    next record; without an injected ``sleep`` a wait ends at once when stopped
    from another thread, and within a quarter second when stopped by a signal.
    ``stats`` is kept up to date as records go, so it is valid after an error too.

    Raises:
        ConfigError: bad ``speed`` or ``max_gap`` (see :class:`Pacer`).
    """

    def __init__(
        self,
        records: Iterable[TlogRecord],
        *,
        speed: float = DEFAULT_SPEED,
        max_gap: float = DEFAULT_MAX_GAP,
        clock: Clock = time.monotonic,
        sleep: Sleep | None = None,
        stop: threading.Event | None = None,
    ) -> None:
        self._records = records
        self._pacer = Pacer(speed=speed, max_gap=max_gap, clock=clock)
        self._clock = clock
        self._stop = stop if stop is not None else threading.Event()
        self._sleep: Sleep = sleep if sleep is not None else self._wait
        self.stats = PlayStats()

    def stop(self) -> None:
        """Ask the player to stop before the next record (thread- and signal-safe)."""
        self._stop.set()

    def _wait(self, seconds: float) -> None:
        _wait_unless(self._stop, seconds)

    def __iter__(self) -> Iterator[TlogRecord]:
        """Yield each record when it is due.

        Raises:
            CaptureDamagedError: from the records, after the good ones.
        """
        stats = self.stats
        start = self._clock()
        try:
            for rec in self._records:
                if self._stop.is_set():
                    stats.stopped = True
                    return
                wait = self._pacer.due(rec.t) - self._clock()
                if wait > 0:
                    self._sleep(wait)
                    if self._stop.is_set():
                        stats.stopped = True
                        return
                yield rec
                if stats.first_t is None:
                    stats.first_t = rec.t
                stats.last_t = rec.t
                stats.frames += 1
                stats.bytes += len(rec.raw)
                stats.elapsed = self._clock() - start
        finally:
            stats.elapsed = self._clock() - start

    def play(self, target: Link | Callable[[bytes], object]) -> PlayStats:
        """Write every record's frame to ``target`` (a link's ``send`` or a
        ``write(bytes)`` callable) at its time; return the statistics.

        Raises:
            CaptureDamagedError: the capture is damaged (every good frame before
                the damage was written).
            LinkClosedError, LinkTimeoutError, OSError...: whatever ``target``
                raises; ``stats`` counts what was written before.
        """
        write = target.send if isinstance(target, Link) else target
        for rec in self:
            write(rec.raw)
        return self.stats


# -- decoding for people ----------------------------------------------------------


def _jsonable(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, bytes | bytearray):
        return bytes(value).hex()
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def _decode(rec: TlogRecord) -> tuple[Frame, Any, str | None]:
    frame = rec.frame
    try:
        return frame, decode(frame), None
    except FrameError as exc:
        return frame, None, str(exc)


def decode_record(rec: TlogRecord) -> dict[str, Any]:
    """A JSON-ready dict for one record::

        {"t": 1700000000.25, "sysid": 1, "compid": 1, "seq": 7, "msg": "HEARTBEAT",
         "msgid": 0, "len": 21, "fields": {"type": 18, ...}}

    ``fields`` is pymavlink's ``to_dict()`` without ``mavpackettype`` (kept apart
    because messages have fields such as ``seq`` of their own), with bytes as hex
    strings, tuples as lists and NaN or infinite floats as None, so
    :func:`json.dumps` accepts it. If pymavlink cannot decode the frame, ``fields``
    is empty and ``error`` says why. Never raises for a record from
    :func:`~radios.tlog.read_tlog`.
    """
    frame, msg, error = _decode(rec)
    out: dict[str, Any] = {
        "t": rec.t,
        "sysid": frame.sysid,
        "compid": frame.compid,
        "seq": frame.seq,
        "msg": frame.name,
        "msgid": frame.msgid,
        "len": len(frame.raw),
    }
    if msg is None:
        out["fields"] = {}
        out["error"] = error
    else:
        out["fields"] = {k: _jsonable(v) for k, v in msg.to_dict().items() if k != "mavpackettype"}
    return out


def format_time(t: float) -> str:
    """``HH:MM:SS.mmm`` in local time, as MAVProxy's logs show it."""
    ms = int(t * 1000)  # truncate, as clocks do
    return time.strftime("%H:%M:%S", time.localtime(ms // 1000)) + f".{ms % 1000:03d}"


def format_record(rec: TlogRecord) -> str:
    """One text line, like MAVProxy's log dump with the sender added::

        12:00:01.234 1/1 HEARTBEAT {type : 18, autopilot : 8, ...}

    Never raises for a record from :func:`~radios.tlog.read_tlog`.
    """
    frame, msg, error = _decode(rec)
    body = str(msg) if msg is not None else f"{frame.name} <cannot decode: {error}>"
    return f"{format_time(rec.t)} {frame.sysid}/{frame.compid} {body}"


# -- statistics ---------------------------------------------------------------------


class CaptureStats:
    """Accumulates :func:`capture_stats` one record at a time (so a caller that
    meets damage still has the figures for the whole records)."""

    def __init__(self) -> None:
        self.frames = 0
        self.bytes = 0
        self.start: float | None = None
        self.end: float | None = None
        self.messages: Counter[str] = Counter()
        self._systems: dict[int, _SystemStats] = {}

    def add(self, rec: TlogRecord) -> None:
        frame = rec.frame
        n = len(frame.raw)
        name = frame.name
        self.frames += 1
        self.bytes += n
        self.start = rec.t if self.start is None else min(self.start, rec.t)
        self.end = rec.t if self.end is None else max(self.end, rec.t)
        self.messages[name] += 1
        s = self._systems.get(frame.sysid)
        if s is None:
            s = self._systems[frame.sysid] = _SystemStats()
        s.frames += 1
        s.bytes += n
        s.messages[name] += 1
        if frame.msgid == MSG_RADIO_STATUS and (frame.sysid, frame.compid) == LOCAL_RADIO_IDS:
            s.local += n + AIRTIME_OVERHEAD_BYTES  # the radio's report to its host: never on air

    def as_dict(self) -> dict[str, Any]:
        duration = 0.0
        if self.start is not None and self.end is not None:
            duration = self.end - self.start
        local = sum(s.local for s in self._systems.values())
        air_total = self.bytes + AIRTIME_OVERHEAD_BYTES * self.frames - local
        systems = []
        for sysid in sorted(self._systems):
            s = self._systems[sysid]
            air = s.bytes + AIRTIME_OVERHEAD_BYTES * s.frames - s.local
            systems.append(
                {
                    "sysid": sysid,
                    "frames": s.frames,
                    "bytes": s.bytes,
                    "bytes_per_s": s.bytes / duration if duration > 0 else None,
                    "airtime_share": air / air_total if air_total else 0.0,
                    "messages": dict(s.messages.most_common()),
                }
            )
        return {
            "frames": self.frames,
            "bytes": self.bytes,
            "start": self.start,
            "end": self.end,
            "duration": duration,
            "airtime_overhead_bytes": AIRTIME_OVERHEAD_BYTES,
            "messages": dict(self.messages.most_common()),
            "systems": systems,
        }


class _SystemStats:
    __slots__ = ("bytes", "frames", "local", "messages")

    def __init__(self) -> None:
        self.frames = 0
        self.bytes = 0
        self.local = 0  # air-time bytes of frames that never went on air
        self.messages: Counter[str] = Counter()


def capture_stats(records: Iterable[TlogRecord]) -> dict[str, Any]:
    """Summary of a capture: ``frames``, ``bytes`` (frame bytes), ``start``,
    ``end``, ``duration`` (seconds between the first and last record), overall
    ``messages`` counts by name, and ``systems``: one entry per sysid, by sysid,
    with ``frames``, ``bytes``, ``bytes_per_s``, ``messages`` and
    ``airtime_share``.

    ``airtime_share`` is an approximation: the system's share of frame bytes plus
    :data:`AIRTIME_OVERHEAD_BYTES` per frame; a SiK radio's RADIO_STATUS to its own
    host (system 51, component 68: in a station's capture) never goes on air and
    counts for none. It ignores packing of several frames
    per SiK packet, TDM silences and retransmission-free loss; the emulator's air
    model is the fuller account.

    Raises:
        CaptureDamagedError: from ``records`` (use :class:`CaptureStats` to keep
            the figures gathered before the damage).
    """
    stats = CaptureStats()
    for rec in records:
        stats.add(rec)
    return stats.as_dict()


__all__ = [
    "AIRTIME_OVERHEAD_BYTES",
    "DEFAULT_MAX_GAP",
    "DEFAULT_SPEED",
    "CaptureStats",
    "Pacer",
    "PlayStats",
    "Player",
    "TlogLink",
    "capture_stats",
    "decode_record",
    "format_record",
    "format_time",
    "open_tlog_link",
    "open_tlog_url",
]
