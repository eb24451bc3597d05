"""The link base class: whole MAVLink frames over a byte channel.

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
  backends that can say so with ``can_reopen``, others raise ``LinkOpenError``.
  The link object stays the same, with its statistics; bytes of a half-received
  frame are dropped. A link with a device notes its identity (``identity``,
  :mod:`radios.device_id`) and reopens only that device: another one at the same
  path is refused (``DeviceMismatchError``); :meth:`Link.check_device` asks the same
  question without opening anything.

Backends (:mod:`radios.seriallink`, :mod:`radios.virtual`, :mod:`radios.replay`,
the :mod:`radios.capture` wrapper) import this module, never the URL factory
:mod:`radios.link` that opens them: the factory imports each backend only when a
URL names it.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import asdict, dataclass

from radios.device_id import DeviceIdentity
from radios.errors import LinkClosedError, LinkOpenError, LinkTimeoutError
from radios.mavlink import Frame, FrameParser, parse_one


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

    @property
    def identity(self) -> DeviceIdentity | None:
        """The device this link opened first, which is the only one it reopens (None: a
        link without a device identity, such as ``loop://`` or ``virtual://``)."""
        return None

    def check_device(self) -> None:
        """Check, without opening it, that the device at the link's path is still the one
        it opened (before lending the path to another program); nothing to check for a
        link without an identity.

        Raises:
            DeviceMismatchError: another device is there.
            LinkOpenError: none is there, or it cannot be identified.
        """

    def reopen(self) -> None:
        """Open the device behind this link again, at the same URL, after it went away.

        Raises:
            LinkClosedError: the link was closed by its owner.
            DeviceMismatchError: another device is at the path than the one the link
                opened first (it is not opened).
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


__all__ = ["Link", "LinkStats"]
