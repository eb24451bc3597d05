"""The ``.tlog`` capture format: timestamped raw MAVLink frames.

Theory of operation
-------------------
A ``.tlog`` is what MAVProxy and pymavlink write and read (docs/design/radio-link.md):
a plain concatenation of records, each

* 8 bytes: big-endian unsigned microseconds since the Unix epoch (UTC), then
* one raw MAVLink frame (MAVLink 2 ``0xFD`` or MAVLink 1 ``0xFE``), whose own header
  says how long it is.

There is no file header, index or record length, so a reader finds the end of a
record only by parsing the frame header. That is also why damage cannot be skipped
reliably: after a bad record the reader no longer knows where the next one starts.

:class:`TlogWriter` appends records. Each record goes to the file in one
unbuffered write under a lock, so concurrent writers (a link's sending and
receiving threads) never interleave bytes, a reader following a live capture sees
whole records at once, and a process that dies leaves at most the last record
short.

:func:`read_tlog` streams records (never the whole file in memory). It checks every
record: a whole timestamp, a plausible time, a start byte, a whole frame, a known
message id and a good CRC. It yields each good record; at the first damaged one it
raises :class:`~radios.errors.CaptureDamagedError` naming the byte offset, the
reason and the number of whole records before it, so a caller can use everything
that was good and still report the damage.
"""

from __future__ import annotations

import io
import math
import os
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import BinaryIO

from radios.errors import CaptureDamagedError, CaptureError, FrameError
from radios.mavlink import CRC_EXTRA, STX_V1, STX_V2, Frame, frame_length, frame_msgid, frame_problem

TIMESTAMP = struct.Struct(">Q")
TIMESTAMP_LEN = TIMESTAMP.size  # 8

#: Records stamped before 2000-01-01 or after 2100-01-01 (UTC) are not plausible:
#: such a "timestamp" is almost always frame bytes read out of step.
EARLIEST_T = 946_684_800.0
LATEST_T = 4_102_444_800.0
#: Largest plausible step (either way) between two consecutive records, seconds.
MAX_STEP = 86_400.0

_READ_CHUNK = 1 << 16


@dataclass(frozen=True, slots=True)
class TlogRecord:
    """One record of a capture: ``t`` seconds since the epoch, the ``raw`` frame
    bytes, and the byte ``offset`` of the record (its timestamp) in the file."""

    t: float
    raw: bytes
    offset: int = 0

    @property
    def frame(self) -> Frame:
        """The frame as a :class:`~radios.mavlink.Frame` (already CRC-checked when
        the record came from :func:`read_tlog`)."""
        return Frame(self.raw)

    @property
    def size(self) -> int:
        """Bytes the record takes in the file (timestamp plus frame)."""
        return TIMESTAMP_LEN + len(self.raw)


def _describe_open_error(path: str, exc: OSError, what: str) -> str:
    if isinstance(exc, FileNotFoundError):
        parent = os.path.dirname(os.path.abspath(path))
        if what == "create" and not os.path.isdir(parent):
            return f"cannot create capture {path}: directory {parent} does not exist"
        return f"cannot {what} capture {path}: no such file"
    if isinstance(exc, NotADirectoryError):
        return f"cannot {what} capture {path}: a component of the path is not a directory"
    if isinstance(exc, IsADirectoryError):
        return f"cannot {what} capture {path}: it is a directory"
    if isinstance(exc, PermissionError):
        return f"cannot {what} capture {path}: permission denied"
    return f"cannot {what} capture {path}: {exc.strerror or exc}"


class TlogWriter:
    """Writes records to a new ``.tlog`` (an existing file is replaced).

    The file is opened by the constructor, so a bad path fails at once rather than
    at the first frame. ``clock`` gives the time stamped on records written without
    an explicit ``t`` (seconds since the epoch; default :func:`time.time`).
    Thread-safe; a context manager; ``close()`` is safe twice.

    Raises:
        CaptureError: the file cannot be created (missing directory, no
            permission, a directory in the way...).
    """

    def __init__(self, path: str | os.PathLike[str], *, clock: Callable[[], float] = time.time) -> None:
        self.path = os.fspath(path)
        self._clock = clock
        self._lock = threading.Lock()
        self._records = 0
        self._bytes = 0
        try:
            self._file: io.FileIO | None = io.FileIO(self.path, "wb")
        except OSError as exc:
            raise CaptureError(_describe_open_error(self.path, exc, "create")) from exc

    @property
    def records(self) -> int:
        """Records written so far."""
        return self._records

    @property
    def bytes_written(self) -> int:
        """Bytes written to the file so far (timestamps included)."""
        return self._bytes

    @property
    def closed(self) -> bool:
        return self._file is None

    def write(self, raw: bytes | bytearray | Frame, t: float | None = None) -> None:
        """Append one record: the frame ``raw`` stamped ``t`` (seconds since the
        epoch; default ``clock()``).

        Raises:
            FrameError: ``raw`` is not exactly one frame by its header (start byte
                and length); the CRC is not checked here.
            ValueError: ``t`` is negative, not finite or beyond what 64-bit
                microseconds hold.
            CaptureError: the writer is closed or the file cannot be written
                (disk full, device gone).
        """
        data = raw.raw if isinstance(raw, Frame) else bytes(raw)
        if frame_length(data) != len(data):
            raise FrameError(f"not exactly one MAVLink frame ({len(data)} bytes), not written to {self.path}")
        stamp = self._clock() if t is None else t
        usec = round(stamp * 1e6) if math.isfinite(stamp) else -1
        if not 0 <= usec < 1 << 64:
            raise ValueError(f"timestamp {stamp!r} cannot be stored in a .tlog")
        record = TIMESTAMP.pack(usec) + data
        with self._lock:
            f = self._file
            if f is None:
                raise CaptureError(f"capture {self.path} is closed")
            try:
                view = memoryview(record)
                while view:
                    n = f.write(view)
                    if n is None:  # pragma: no cover - only for non-blocking files
                        continue
                    view = view[n:]
            except OSError as exc:
                raise CaptureError(f"cannot write capture {self.path}: {exc.strerror or exc}") from exc
            self._records += 1
            self._bytes += len(record)

    def flush(self) -> None:
        """Make the records written so far durable (``fsync``). Records already
        reach the operating system one by one, so a reader sees them without this.

        Raises:
            CaptureError: the file cannot be synced.
        """
        with self._lock:
            if self._file is None:
                return
            try:
                os.fsync(self._file.fileno())
            except OSError as exc:
                raise CaptureError(f"cannot flush capture {self.path}: {exc}") from exc

    def close(self) -> None:
        """Close the file; safe to call more than once."""
        with self._lock:
            f, self._file = self._file, None
        if f is not None:
            f.close()

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return f"<TlogWriter {self.path} {state}, {self._records} records>"


class TlogReader:
    """Iterator over the records of a ``.tlog``; see :func:`read_tlog`.

    ``records`` counts the whole records yielded so far and ``offset`` is the byte
    offset of the next record. A context manager; ``close()`` is safe twice.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = os.fspath(path)
        try:
            self._file: BinaryIO | None = open(self.path, "rb", buffering=_READ_CHUNK)  # noqa: SIM115
        except OSError as exc:
            raise CaptureError(_describe_open_error(self.path, exc, "read")) from exc
        self.records = 0
        self.offset = 0
        self.unknown: dict[int, int] = {}  # message id -> frames skipped: no dialect here knows it
        self._last_t: float | None = None
        self._done = False

    def __iter__(self) -> Iterator[TlogRecord]:
        return self

    def __next__(self) -> TlogRecord:
        while True:
            rec = self._next()
            if rec is not None:
                return rec

    def _next(self) -> TlogRecord | None:
        """The next record, or None for a frame of a message id nobody here knows
        (skipped and counted in :attr:`unknown`: its CRC cannot be checked, its
        length still frames it; a real PX4 sends several such ids)."""
        if self._done or self._file is None:
            raise StopIteration
        f = self._file
        start = self.offset
        head = f.read(TIMESTAMP_LEN)
        if not head:
            self._finish()
            raise StopIteration
        if len(head) < TIMESTAMP_LEN:
            self._damaged("truncated timestamp")
        (usec,) = TIMESTAMP.unpack(head)
        t = usec / 1e6
        if not EARLIEST_T <= t < LATEST_T:
            self._damaged(f"implausible timestamp {_fmt_time(t)}")
        if self._last_t is not None and abs(t - self._last_t) > MAX_STEP:
            self._damaged(f"timestamp {_fmt_time(t)} is {t - self._last_t:+.0f} s from the previous record")
        hdr = f.read(3)
        if not hdr:
            self._damaged("truncated frame")
        if hdr[0] not in (STX_V2, STX_V1):
            self._damaged(f"no MAVLink start byte (0x{hdr[0]:02X})")
        if len(hdr) < 3:
            self._damaged("truncated frame")
        total = frame_length(hdr)
        assert total is not None  # a start byte and three header bytes
        rest = f.read(total - 3)
        if len(rest) < total - 3:
            self._damaged("truncated frame")
        raw = hdr + rest
        problem = frame_problem(raw)
        msgid = frame_msgid(raw)
        if problem and msgid not in CRC_EXTRA:
            self._last_t = t
            self.unknown[msgid] = self.unknown.get(msgid, 0) + 1
            self.offset = start + TIMESTAMP_LEN + total
            return None
        if problem:
            self._damaged(problem)
        self._last_t = t
        self.records += 1
        self.offset = start + TIMESTAMP_LEN + total
        return TlogRecord(t, raw, start)

    def _damaged(self, reason: str) -> None:
        offset, records = self.offset, self.records
        self._finish()
        raise CaptureDamagedError(
            f"{self.path}: damaged record at byte {offset} ({reason}) "
            f"after {records} whole record{'' if records == 1 else 's'}",
            offset=offset,
            records=records,
        )

    def _finish(self) -> None:
        self._done = True
        self.close()

    def close(self) -> None:
        """Close the file; safe to call more than once."""
        f, self._file = self._file, None
        if f is not None:
            f.close()

    def __enter__(self) -> TlogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _fmt_time(t: float) -> str:
    try:
        return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))
    except (OverflowError, OSError, ValueError):
        return f"{t:.0f} s after 1970"


def read_tlog(path: str | os.PathLike[str]) -> TlogReader:
    """Open a capture and return an iterator over its :class:`TlogRecord`s.

    The file is opened at once (so a missing file fails here, not at the first
    ``next``) and read in a streaming fashion. Every whole, valid record is yielded
    in order; the iterator closes the file when it ends.

    Raises:
        CaptureError: the file cannot be opened (missing, a directory, no
            permission).

    A frame of a message id that no dialect here knows (its CRC cannot be checked)
    is skipped and counted in the reader's ``unknown`` (message id -> frames): a real
    PX4 sends several (its events protocol).

    Iterating raises:
        CaptureDamagedError: at the first damaged record (truncated timestamp or
            frame, no MAVLink start byte, bad CRC, timestamp
            before 2000, after 2100 or more than a day from the previous record),
            after every good record before it was yielded. Its ``offset`` and
            ``records`` say where and after how many.
    """
    return TlogReader(path)


__all__ = [
    "EARLIEST_T",
    "LATEST_T",
    "MAX_STEP",
    "TlogReader",
    "TlogRecord",
    "TlogWriter",
    "read_tlog",
]
