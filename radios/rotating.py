"""Flight logs: ``.tlog`` captures rotated by size and age, durable, kept under a budget.

Theory of operation
-------------------
An aircraft has no one to restart a capture, an SD card fills up and the power is
cut without warning. :class:`FlightLog` therefore writes one folder of ordinary
``.tlog`` files (:mod:`radios.tlog`: 8-byte time, raw frame) as a set:

* **Names** sort by time and say who wrote them:
  ``PREFIX-YYYYmmddTHHMMSSZ-NNNN.tlog`` (UTC when the file was opened, then a
  counter). Each *source* has its own file of the same stem: the radio's traffic
  (both directions, RADIO_STATUS included) in ``STEM.tlog``, the flight
  controller's messages in ``STEM.fc.tlog``; frames keep their own ids, so the
  sources are told apart by the file, not by guessing from ids.
* **The radio path never waits for the disk.** :meth:`FlightLog.put` stamps the
  frame and appends it to a bounded queue (a frame that does not fit is counted in
  ``dropped``); one writer thread takes the queue every ``tick_s`` (50 ms), writes
  the records, and ``fsync``\\ s at most once per ``sync_s`` (0.9 s), so a power cut
  loses at most about the last second and a ``kill -9`` only what is queued.
* **Rotation**: a file is closed (synced first) and the next opened when a record
  would take it past ``max_bytes`` or it is ``rotate_s`` old; both sources rotate
  together. A clock that jumps by more than ``rotate_s`` (a Pi without a real-time
  clock setting its time from GPS or NTP after take-off) starts a new file too, so
  no file holds the jump (readers take a day's step inside a file for damage). After
  each rotation the oldest files of this prefix are removed until the set, plus room
  for the new files, fits ``budget_bytes``; an open file is never removed, and files
  of other prefixes are not this log's.
* **A full disk never stops the aircraft.** A failing write, open or sync pauses
  the log: ``on_error`` hears one line, records are counted as ``lost``, and every
  ``retry_s`` (5 s) the writer frees space by the budget and tries a new file; when
  that works ``on_error`` hears one line again. Nothing here raises into the
  caller after the constructor.
* **A hostile folder** is refused at start (:func:`prepare_directory`): a
  symbolic link, a file where the folder should be, no permission. The folder is
  then held open and files are made inside it with ``O_EXCL | O_NOFOLLOW``, so a
  link planted later at a file's name, or the folder swapped for a link, cannot
  send the log elsewhere.

:mod:`radios.tlogset` reads such a set back as one capture.
"""

from __future__ import annotations

import os
import re
import stat
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from radios.errors import ConfigError
from radios.mavlink import frame_length
from radios.tlog import TIMESTAMP

MB = 1 << 20
RADIO = "radio"
FC = "fc"
SOURCES = (RADIO, FC)
SUFFIX = {RADIO: ".tlog", FC: ".fc.tlog"}
#: a flight log file's name: prefix, stamp, seq and whether it is the flight controller's
NAME = re.compile(
    r"^(?P<prefix>[A-Za-z0-9_-]{1,32})-(?P<stamp>\d{8}T\d{6}Z)-(?P<seq>\d{4,})(?P<fc>\.fc)?\.tlog$"
)
_PREFIX = re.compile(r"^[A-Za-z0-9_-]{1,32}$")


@dataclass(frozen=True)
class RotationPolicy:
    """How a :class:`FlightLog` rotates and syncs (defaults for a Pi's SD card).

    Raises:
        ConfigError: a size or time that is not positive, or a budget smaller than one file.
    """

    max_bytes: int = 16 * MB
    rotate_s: float = 600.0
    budget_bytes: int = 512 * MB
    sync_s: float = 0.9
    tick_s: float = 0.05
    retry_s: float = 5.0
    max_queue: int = 20_000

    def __post_init__(self) -> None:
        for name in ("max_bytes", "rotate_s", "budget_bytes", "sync_s", "tick_s", "retry_s", "max_queue"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and v == v and 0 < v < float("inf")):
                raise ConfigError(f"flight log {name} must be a positive number, not {v!r}")
        if self.max_bytes < 4096:
            raise ConfigError(f"flight log files must be allowed at least 4096 bytes, not {self.max_bytes}")
        if self.budget_bytes < self.max_bytes:
            raise ConfigError(
                f"the flight log budget ({self.budget_bytes} bytes) is smaller "
                f"than one file ({self.max_bytes} bytes)"
            )


def prepare_directory(path: str) -> str:
    """Make sure ``path`` is a folder this process may write flight logs in (creating
    it if missing) and return its absolute path.

    Raises:
        ConfigError: ``path`` is a symbolic link, a file, cannot be created, or is not
            writable.
    """
    if not path:
        raise ConfigError("no flight log folder given")
    full = os.path.abspath(path)
    if os.path.islink(full):
        raise ConfigError(f"flight log folder {path} is a symbolic link: give the real folder")
    if os.path.lexists(full) and not os.path.isdir(full):
        raise ConfigError(f"flight log folder {path} is not a folder")
    if not os.path.exists(full):
        try:
            os.makedirs(full, mode=0o750)
        except OSError as exc:
            raise ConfigError(f"cannot create flight log folder {path}: {exc.strerror or exc}") from None
    if not os.access(full, os.W_OK | os.X_OK):
        raise ConfigError(f"flight log folder {path}: permission denied")
    return full


def _stamp(t: float) -> str:
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(t))


@dataclass
class FlightLogStats:
    """What a :class:`FlightLog` did: records and bytes written, files opened and
    removed, syncs (count, longest and total seconds), records ``dropped`` (queue
    full) and ``lost`` (while paused), write errors, whether it is ``paused``."""

    records: int = 0
    bytes: int = 0
    paused: bool = False
    files: int = 0
    removed: int = 0
    sync_max_s: float = 0.0
    syncs: int = 0
    sync_total_s: float = 0.0
    dropped: int = 0
    lost: int = 0
    errors: int = 0


@dataclass
class _Open:
    name: str
    fd: int
    opened: float
    size: int = 0


@dataclass
class _Writer:
    """The writer thread's own state (only that thread touches it)."""

    files: dict[str, _Open] = field(default_factory=dict)
    stem: str | None = None
    stem_t: float = 0.0
    last_usec: int | None = None  # the stamp of the last record written
    seq: int = 0
    dirty: bool = False
    synced: float = 0.0
    paused_at: float | None = None
    retry_at: float = 0.0


class FlightLog:
    """A rotated, durable capture in ``directory`` (see the module docstring).

    ``prefix`` names the files (an agent's name); ``clock`` stamps records and names
    files (seconds since the epoch); ``on_error(text)`` hears one line when the log
    pauses and one when it resumes (from the writer thread). Thread-safe; a context
    manager; :meth:`close` writes what is queued, syncs and is safe twice.

    Raises:
        ConfigError: a bad prefix or folder (:func:`prepare_directory`).
    """

    def __init__(
        self,
        directory: str,
        prefix: str,
        policy: RotationPolicy | None = None,
        *,
        clock: Callable[[], float] = time.time,
        on_error: Callable[[str], object] | None = None,
    ) -> None:
        if not _PREFIX.match(prefix):
            raise ConfigError(f"flight log prefix {prefix!r}: 1-32 of A-Z a-z 0-9 _ -")
        self.directory = prepare_directory(directory)
        self.prefix = prefix
        self.policy = policy or RotationPolicy()
        self.clock = clock
        self.on_error = on_error
        self.stats = FlightLogStats()
        try:
            self._dir_fd = os.open(self.directory, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except OSError as exc:
            raise ConfigError(f"cannot open flight log folder {directory}: {exc.strerror or exc}") from None
        self._queue: deque[tuple[str, bytes]] = deque()
        self._w = _Writer()
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"flightlog-{prefix}", daemon=True)
        self._thread.start()

    # -- the producers' side ----------------------------------------------------------
    def put(self, source: str, raw: bytes, t: float | None = None) -> None:
        """Queue one frame of ``source`` (``"radio"`` or ``"fc"``) stamped ``t`` (default
        ``clock()``). Never blocks on the disk and never raises: a frame that is not
        one whole frame, or that finds the queue full or the log closed, is dropped
        and counted."""
        if len(self._queue) >= self.policy.max_queue or self._closing.is_set():
            self.stats.dropped += 1
            return
        data = bytes(raw)
        stamp = self.clock() if t is None else t
        usec = round(stamp * 1e6) if stamp == stamp and 0 <= stamp < 1.8e13 else -1
        if usec < 0 or source not in SUFFIX or frame_length(data) != len(data):
            self.stats.dropped += 1
            return
        self._queue.append((source, TIMESTAMP.pack(usec) + data))

    def sink(self, source: str) -> FlightLogSink:
        """A capture sink for :class:`radios.capture.CaptureLink` writing to ``source``."""
        if source not in SUFFIX:
            raise ConfigError(f"unknown flight log source {source!r}: {', '.join(SOURCES)}")
        return FlightLogSink(self, source)

    @property
    def current(self) -> list[str]:
        """The names of the files being written now."""
        return [f.name for f in list(self._w.files.values())]

    def close(self, timeout: float = 5.0) -> None:
        """Write what is queued, sync, close the files; safe twice."""
        self._closing.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def __enter__(self) -> FlightLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the writer thread --------------------------------------------------------------
    def _run(self) -> None:
        w = self._w
        self._enforce_budget()
        while True:
            closing = self._closing.wait(self.policy.tick_s)
            now = self.clock()
            self._drain(now)
            if w.dirty and (closing or now - w.synced >= self.policy.sync_s):
                self._guard(self._sync, now)
            if closing:
                break
        for src in list(w.files):
            self._close_file(src, sync=False)
        try:
            os.close(self._dir_fd)
        except OSError:
            pass

    def _drain(self, now: float) -> None:
        q, w = self._queue, self._w
        while q:
            batch: dict[str, list[bytes]] = {}
            for _ in range(len(q)):
                src, rec = q.popleft()
                batch.setdefault(src, []).append(rec)
            for src, recs in batch.items():
                if w.paused_at is not None and not self._resume(now):
                    self.stats.lost += len(recs)
                    continue
                self._guard(self._write, src, recs, now)

    def _guard(self, fn: Callable[..., object], *args: object) -> None:
        try:
            fn(*args)
        except OSError as exc:
            self._pause(exc)

    def _write(self, src: str, recs: list[bytes], now: float) -> None:
        """Append ``recs`` to ``src``'s file, rotating when the file is old or a record
        would take it past ``max_bytes`` (a record is never split between files)."""
        w = self._w
        if w.stem is None or abs(now - w.stem_t) >= self.policy.rotate_s:
            self._rotate(now)
        chunk: list[bytes] = []
        pending = 0
        jump = int(self.policy.rotate_s * 1e6)
        for rec in recs:
            f = w.files.get(src)
            used = (f.size if f is not None else 0) + pending
            (usec,) = TIMESTAMP.unpack_from(rec)
            stepped = w.last_usec is not None and abs(usec - w.last_usec) > jump
            w.last_usec = usec
            if (used > 0 and used + len(rec) > self.policy.max_bytes) or (used > 0 and stepped):
                if chunk:
                    self._append(src, chunk, now)
                    chunk, pending = [], 0
                self._rotate(now)
            chunk.append(rec)
            pending += len(rec)
        if chunk:
            self._append(src, chunk, now)

    def _append(self, src: str, recs: list[bytes], now: float) -> None:
        w = self._w
        f = w.files.get(src)
        if f is None:
            f = w.files[src] = self._open(src, now)
        view = memoryview(b"".join(recs))
        while view:
            n = os.write(f.fd, view)
            view = view[n:]
            f.size += n
            self.stats.bytes += n
        w.dirty = True
        self.stats.records += len(recs)

    def _open(self, src: str, now: float) -> _Open:
        w = self._w
        assert w.stem is not None
        name = w.stem + SUFFIX[src]
        flags = (
            os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_APPEND | getattr(os, "O_CLOEXEC", 0)
        )
        fd = os.open(name, flags, 0o640, dir_fd=self._dir_fd)
        self.stats.files += 1
        return _Open(name, fd, now)

    def _rotate(self, now: float) -> None:
        w = self._w
        for src in list(w.files):
            self._close_file(src, sync=True)
        w.seq += 1
        taken = self._names()
        while True:
            stem = f"{self.prefix}-{_stamp(now)}-{w.seq:04d}"
            if not any(stem + s in taken for s in SUFFIX.values()):
                break
            w.seq += 1
        w.stem, w.stem_t = stem, now
        self._enforce_budget()

    def _close_file(self, src: str, *, sync: bool) -> None:
        f = self._w.files.pop(src)
        try:
            if sync:
                self._timed_sync(f.fd)
        finally:
            os.close(f.fd)

    def _sync(self, now: float) -> None:
        for f in list(self._w.files.values()):
            self._timed_sync(f.fd)
        self._w.dirty = False
        self._w.synced = now

    def _timed_sync(self, fd: int) -> None:
        t0 = time.monotonic()
        os.fsync(fd)
        took = time.monotonic() - t0
        s = self.stats
        s.syncs += 1
        s.sync_total_s += took
        s.sync_max_s = max(s.sync_max_s, took)

    # -- the budget ------------------------------------------------------------------------
    def _names(self) -> set[str]:
        try:
            return set(os.listdir(self._dir_fd))
        except OSError:
            return set()

    def _enforce_budget(self) -> None:
        """Remove this prefix's oldest closed files until the set and room for the
        open ones fit the budget."""
        ours: list[tuple[tuple[str, int, bool], str, int]] = []
        try:
            with os.scandir(self._dir_fd) as it:
                for e in it:
                    m = NAME.match(e.name)
                    if m is None or m["prefix"] != self.prefix:
                        continue
                    st = e.stat(follow_symlinks=False)
                    if stat.S_ISREG(st.st_mode):
                        ours.append(((m["stamp"], int(m["seq"]), bool(m["fc"])), e.name, st.st_size))
        except OSError:
            return
        open_names = set(self.current)
        room = self.policy.max_bytes
        total = sum(size for _, _, size in ours) + room
        for _, name, size in sorted(ours):
            if total <= self.policy.budget_bytes:
                break
            if name in open_names or (self._w.stem is not None and name.startswith(self._w.stem + ".")):
                continue
            try:
                os.unlink(name, dir_fd=self._dir_fd)
            except OSError:
                continue
            total -= size
            self.stats.removed += 1

    # -- pausing on errors -------------------------------------------------------------------
    def _pause(self, exc: OSError) -> None:
        w = self._w
        self.stats.errors += 1
        for src in list(w.files):
            try:
                self._close_file(src, sync=False)
            except OSError:
                pass
        w.stem = None
        w.dirty = False
        if w.paused_at is None:
            w.paused_at = self.clock()
            self.stats.paused = True
            self._say(
                f"flight log paused: cannot write in {self.directory}: {exc.strerror or exc}; "
                f"the agent goes on, retrying every {self.policy.retry_s:g} s"
            )
        w.retry_at = self.clock() + self.policy.retry_s

    def _resume(self, now: float) -> bool:
        """While paused: try again once ``retry_s`` has passed (True: writing again)."""
        w = self._w
        if w.paused_at is None:
            return True
        if now < w.retry_at:
            return False
        w.retry_at = now + self.policy.retry_s
        try:
            self._rotate(now)
        except OSError:
            return False
        away, w.paused_at = now - w.paused_at, None
        self.stats.paused = False
        self._say(f"flight log resumed after {away:.0f} s ({self.stats.lost} records lost so far)")
        return True

    def _say(self, text: str) -> None:
        if self.on_error is not None:
            try:
                self.on_error(text)
            except Exception:  # a broken reporter must not stop the log
                pass

    def __repr__(self) -> str:
        return f"<FlightLog {self.directory}/{self.prefix}-* {self.stats.records} records>"


class FlightLogSink:
    """One source of a :class:`FlightLog` as a capture sink (``write``, ``close``,
    ``path``): what :class:`radios.capture.CaptureLink` writes to. ``close`` leaves
    the log open (its owner closes it)."""

    def __init__(self, log: FlightLog, source: str) -> None:
        self.log = log
        self.source = source

    @property
    def path(self) -> str:
        return os.path.join(self.log.directory, f"{self.log.prefix}-*{SUFFIX[self.source]}")

    def write(self, raw: bytes | bytearray, t: float | None = None) -> None:
        self.log.put(self.source, bytes(raw), t)

    def close(self) -> None:
        """Nothing: the flight log outlives the link."""


__all__ = [
    "FC",
    "NAME",
    "RADIO",
    "SOURCES",
    "SUFFIX",
    "FlightLog",
    "FlightLogSink",
    "FlightLogStats",
    "RotationPolicy",
    "prepare_directory",
]
