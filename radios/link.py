"""Links: MAVLink frames over a byte channel, opened by URL.

Theory of operation
-------------------
A :class:`Link` moves whole MAVLink frames. Backends implement three small hooks
(``_read``, ``_write``, ``_close``) on raw bytes; the base class adds the public
API on top of them (python-can's ``BusABC`` pattern):

* :meth:`Link.send` checks that what it is given is exactly one valid frame
  before it reaches the backend (a malformed frame is the caller's bug);
* :meth:`Link.recv` feeds the backend's bytes through one :class:`FrameParser`,
  keeps the deadline on ``time.monotonic`` and returns the next whole frame or
  None on timeout;
* :class:`LinkStats` counts frames and bytes each way, CRC errors, bytes skipped
  while resynchronising, and drops;
* ``close()`` is safe twice and links are context managers;
* :meth:`Link.reopen` opens the device again at the same path after it went away
  (a USB radio unplugged and plugged back, an emulator pty dropped and recreated):
  serial links can (``can_reopen``), others raise ``LinkOpenError``. The link
  object stays the same, with its statistics; bytes of a half-received frame are
  dropped.

URLs (see :func:`open_link`):

========================================  =======================================
``/dev/ttyUSB0?baud=57600``               serial device (also ``serial:/dev/...``)
``DIR/radio0``                            an emulator pty: just a serial device
``loop://``, ``socket://host:port``       pyserial URL handlers
``tlog:flight.tlog?speed=1`` or ``*.tlog`` replay a capture (receive only)
========================================  =======================================

Any link can be captured to a ``.tlog`` by wrapping it (``open_link(url,
capture=PATH)``), see :mod:`radios.capture`.
"""

from __future__ import annotations

import os
import select
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any
from urllib.parse import parse_qsl

from radios.errors import FrameError, LinkClosedError, LinkOpenError, LinkTimeoutError
from radios.mavlink import Frame, FrameParser, parse_one

DEFAULT_BAUD = 57600


@dataclass
class LinkStats:
    frames_in: int = 0
    frames_out: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    crc_errors: int = 0
    unknown_msgid: int = 0
    bytes_skipped: int = 0
    drops: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class Link:
    """Base class: whole MAVLink frames over a byte channel. Thread-safe for one
    receiving thread and any number of sending threads."""

    can_send = True
    can_recv = True
    can_reopen = False

    def __init__(self, url: str) -> None:
        self.url = url
        self._parser = FrameParser()
        self._pending: deque[Frame] = deque()
        self._send_lock = threading.Lock()
        self._recv_lock = threading.Lock()
        self._closed = False
        self._stats = LinkStats()

    # -- hooks for backends -------------------------------------------------
    def _read(self, timeout: float) -> bytes:
        """Return the bytes available within ``timeout`` s (b"" if none).
        Raise LinkClosedError when the channel is gone."""
        raise NotImplementedError

    def _write(self, data: bytes) -> None:
        """Write all of ``data``. Raise LinkTimeoutError if it cannot."""
        raise NotImplementedError

    def _close(self) -> None:
        """Release the backend's resources (called once)."""

    # -- public API -----------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def stats(self) -> LinkStats:
        """Counters including the parser's resynchronisation figures."""
        p = self._parser.stats
        s = self._stats
        s.crc_errors, s.unknown_msgid, s.bytes_skipped = p.crc_errors, p.unknown_msgid, p.bytes_skipped
        return s

    def send(self, frame: Frame | bytes) -> None:
        """Send one whole MAVLink frame.

        Raises:
            FrameError: ``frame`` is not exactly one valid MAVLink frame.
            LinkClosedError: the link is closed or its device went away.
            LinkTimeoutError: the channel did not accept the bytes in time (the
                frame is counted as a drop).
        """
        if not self.can_send:
            raise LinkClosedError(f"{self.url} is receive-only")
        raw = frame.raw if isinstance(frame, Frame) else parse_one(bytes(frame)).raw
        with self._send_lock:
            if self._closed:
                raise LinkClosedError(f"{self.url} is closed")
            try:
                self._write(raw)
            except LinkTimeoutError:
                self._stats.drops += 1
                raise
            self._stats.frames_out += 1
            self._stats.bytes_out += len(raw)

    def recv(self, timeout: float | None = None) -> Frame | None:
        """The next whole, CRC-valid frame, or None if none arrives in ``timeout``
        seconds (None waits for ever, 0 polls).

        Raises:
            LinkClosedError: the link is closed or its device went away.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._recv_lock:
            while True:
                if self._pending:
                    return self._pending.popleft()
                if self._closed:
                    raise LinkClosedError(f"{self.url} is closed")
                if deadline is None:
                    wait = 0.5
                else:
                    wait = deadline - time.monotonic()
                    if wait < 0:
                        wait = 0.0
                data = self._read(wait)
                now = time.monotonic()
                if data:
                    self._stats.bytes_in += len(data)
                    frames = self._parser.feed(data)
                    self._stats.frames_in += len(frames)
                    self._pending.extend(frames)
                # the deadline holds even while bytes that make no frame keep coming;
                # a partial frame waits for its rest however long it takes (SiK splits
                # frames across air packets in raw mode and for frames too large to fit)
                if not self._pending and deadline is not None and now >= deadline:
                    return None

    def reopen(self) -> None:
        """Open the device behind this link again, at the same URL, after it went away.

        Raises:
            LinkClosedError: the link was closed by its owner.
            LinkOpenError: the device is (still) missing or cannot be opened, or this
                kind of link cannot be reopened (``can_reopen`` is False).
        """
        raise LinkOpenError(f"{self.url}: this kind of link cannot be reopened")

    def release(self) -> None:
        """Close the device but keep the link, as if it went away: reads and writes fail
        until :meth:`reopen` (so that another program, such as an AT configurator, can
        use the port meanwhile).

        Raises:
            LinkOpenError: this kind of link cannot be reopened.
        """
        raise LinkOpenError(f"{self.url}: this kind of link cannot be released and reopened")

    def close(self) -> None:
        """Close the link; safe to call more than once."""
        with self._send_lock:
            if self._closed:
                return
            self._closed = True
        self._close()

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<{type(self).__name__} {self.url} {state}>"


class SerialLink(Link):
    """A serial device (real radio, emulator pty) or a pyserial URL handler."""

    can_reopen = True

    def __init__(self, url: str, port: Any) -> None:
        super().__init__(url)
        self.port = port
        self._gone = False  # the device went away; reopen() may bring it back
        self._fd = self._fileno(port)

    @staticmethod
    def _fileno(port: Any) -> int | None:
        try:
            return int(port.fileno())
        except Exception:
            return None

    def reopen(self) -> None:
        """See :meth:`Link.reopen`: the old port is closed first, then the device is
        opened again with the same options."""
        with self._send_lock, self._recv_lock:
            if self._closed:
                raise LinkClosedError(f"{self.url} is closed")
            if not self._gone:
                self._gone = True
                self._close()
            fresh = open_serial(self.url)
            self.port, self._fd = fresh.port, fresh._fd
            self._parser = FrameParser(stats=self._parser.stats)
            self._pending.clear()
            self._gone = False

    def release(self) -> None:
        """See :meth:`Link.release`."""
        with self._send_lock, self._recv_lock:
            if not self._closed and not self._gone:
                self._gone = True
                self._close()

    def _read(self, timeout: float) -> bytes:
        if self._closed:
            raise LinkClosedError(f"{self.url} is closed")
        if self._gone:
            raise LinkClosedError(f"{self.url}: device gone")
        try:
            if self._fd is not None:
                r, _, _ = select.select([self._fd], [], [], timeout)
                if not r:
                    return b""
                data = os.read(self._fd, 4096)
                if not data:
                    raise LinkClosedError(f"{self.url}: device closed")
                return data
            self.port.timeout = timeout
            n = max(1, self.port.in_waiting)
            return bytes(self.port.read(n))
        except OSError as exc:
            # EIO on a pty whose master went away, EBADF after close()
            raise LinkClosedError(f"{self.url}: {exc.strerror or exc}") from exc
        except ValueError as exc:  # select on a closed fd
            raise LinkClosedError(f"{self.url} is closed") from exc

    def _write(self, data: bytes) -> None:
        import serial

        if self._gone:
            raise LinkClosedError(f"{self.url}: device gone")
        try:
            n = self.port.write(data)
        except serial.SerialTimeoutException as exc:
            raise LinkTimeoutError(f"{self.url}: write timed out (nobody reading?)") from exc
        except (OSError, serial.SerialException) as exc:
            raise LinkClosedError(f"{self.url}: {exc}") from exc
        if n is not None and n != len(data):
            raise LinkTimeoutError(f"{self.url}: only {n} of {len(data)} bytes written")

    def _close(self) -> None:
        try:
            self.port.close()
        except Exception:  # closing a device that already vanished
            pass


# -- URL handling ---------------------------------------------------------------

_PYSERIAL_SCHEMES = ("loop://", "socket://", "rfc2217://", "spy://", "alt://", "hwgrep://")
SCHEMES = ("serial:", "tlog:", *_PYSERIAL_SCHEMES)


def split_query(url: str) -> tuple[str, dict[str, str]]:
    if "?" in url:
        path, query = url.split("?", 1)
        return path, dict(parse_qsl(query, keep_blank_values=True))
    return url, {}


def _int_opt(opts: dict[str, str], name: str, default: int, url: str) -> int:
    if name not in opts:
        return default
    try:
        return int(opts.pop(name))
    except ValueError:
        raise LinkOpenError(f"{url}: {name} must be an integer") from None


def _float_opt(opts: dict[str, str], name: str, default: float, url: str) -> float:
    if name not in opts:
        return default
    try:
        return float(opts.pop(name))
    except ValueError:
        raise LinkOpenError(f"{url}: {name} must be a number") from None


def open_serial(url: str) -> SerialLink:
    """Open a serial device or pyserial URL, see :func:`open_link`."""
    import serial

    target, opts = split_query(url)
    if target.startswith("serial:"):
        target = target[len("serial:") :]
        if target.startswith("//"):
            target = target[2:]
    baud = _int_opt(opts, "baud", DEFAULT_BAUD, url)
    rtscts = bool(_int_opt(opts, "rtscts", 0, url))
    write_timeout = _float_opt(opts, "write_timeout", 2.0, url)
    if opts:
        raise LinkOpenError(f"{url}: unknown option(s) {', '.join(sorted(opts))}")
    if baud <= 0:
        raise LinkOpenError(f"{url}: baud must be positive")
    is_url = target.startswith(_PYSERIAL_SCHEMES)
    if not is_url:
        if not target:
            raise LinkOpenError(f"{url}: no device path")
        if not os.path.exists(target):
            raise LinkOpenError(f"{target}: no such device (is the radio plugged in / the emulator running?)")
    try:
        if is_url:
            port = serial.serial_for_url(
                target, baudrate=baud, rtscts=rtscts, write_timeout=write_timeout, timeout=0
            )
        else:
            port = serial.Serial(
                target, baudrate=baud, rtscts=rtscts, write_timeout=write_timeout, timeout=0, exclusive=False
            )
    except (serial.SerialException, OSError, ValueError) as exc:
        raise LinkOpenError(f"cannot open {target}: {exc}") from exc
    return SerialLink(url, port)


def open_link(url: str, *, capture: str | os.PathLike[str] | None = None, **options: Any) -> Link:
    """Open a link by URL (see the module docstring for the forms).

    ``capture`` wraps the link so every frame sent and received is also written to
    that ``.tlog``. Extra keyword ``options`` go to the backend (the replay backend
    takes ``clock`` and ``sleep``).

    Raises:
        LinkOpenError: unknown scheme, malformed URL or option, missing device.
        CaptureError: the capture file cannot be created.
    """
    if not isinstance(url, str) or not url:
        raise LinkOpenError("empty link URL")
    path, _ = split_query(url)
    link: Link
    if url.startswith("tlog:") or path.endswith(".tlog"):
        from radios.replay import open_tlog_link

        link = open_tlog_link(url, **options)
    elif url.startswith("serial:") or url.startswith(_PYSERIAL_SCHEMES) or "://" not in url:
        head = path.split("/", 1)[0]
        if (
            ":" in head
            and not url.startswith(("serial:", *_PYSERIAL_SCHEMES))
            and not head.upper().startswith("COM")
        ):
            scheme = path.split(":", 1)[0]
            raise LinkOpenError(f"{url}: unknown link scheme {scheme!r} (known: {', '.join(SCHEMES)})")
        if options:
            raise LinkOpenError(f"unexpected options for a serial link: {', '.join(options)}")
        link = open_serial(url)
    else:
        scheme = url.split("://", 1)[0]
        raise LinkOpenError(f"{url}: unknown link scheme {scheme!r} (known: {', '.join(SCHEMES)})")
    if capture is not None:
        from radios.capture import CaptureLink

        try:
            link = CaptureLink(link, capture)
        except BaseException:
            link.close()
            raise
    return link


__all__ = [
    "DEFAULT_BAUD",
    "SCHEMES",
    "FrameError",
    "Link",
    "LinkStats",
    "SerialLink",
    "open_link",
    "open_serial",
]
