"""Capture: a wrapper that records every frame a link carries to a ``.tlog``.

Theory of operation
-------------------
Capturing is a wrapper, not a backend feature (pyserial's ``spy://``, STYLE.md
point 8): :class:`CaptureLink` takes any open :class:`~radios.linkbase.Link` and
behaves exactly like it, except that

* each frame :meth:`~CaptureLink.send` hands over successfully, and
* each frame :meth:`~CaptureLink.recv` returns,

is also written, with the time it passed (``clock``, default :func:`time.time`,
seconds since the epoch), to a :class:`~radios.tlog.TlogWriter`, or to any
:class:`CaptureSink` handed in instead of a path (an aircraft's rotated flight log,
:class:`radios.rotating.FlightLogSink`, which stamps frames itself and never
raises: a full disk must not cost the radio a frame). Both directions go
to one file in the order they happened, as MAVProxy's telemetry logs do. The
wrapper adds no parsing, buffering or thread of its own: the inner link does the
work and its statistics are the wrapper's. ``close()`` closes the link, then the
file, and is safe twice.

Usually reached through ``open_link(url, capture=PATH)``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

from radios.device_id import DeviceIdentity
from radios.errors import LinkClosedError
from radios.linkbase import Link, LinkStats
from radios.mavlink import Frame
from radios.tlog import TlogWriter


@runtime_checkable
class CaptureSink(Protocol):
    """Where a :class:`CaptureLink` writes: ``write(raw)`` one frame, ``close()``, ``path``."""

    @property
    def path(self) -> str: ...

    def write(self, raw: bytes) -> None: ...

    def close(self) -> None: ...


class CaptureLink(Link):
    """``inner`` with every frame sent and received also written to ``path`` (a file
    name, or a :class:`CaptureSink`: the sink is closed with the link).

    Raises:
        CaptureError: the capture file cannot be created (the inner link is left
            open: the caller owns it until this constructor succeeds).
    """

    def __init__(
        self,
        inner: Link,
        path: str | os.PathLike[str] | CaptureSink,
        *,
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(inner.url)
        self.inner = inner
        self.can_send = inner.can_send
        self.can_recv = inner.can_recv
        self.writer: CaptureSink = path if isinstance(path, CaptureSink) else TlogWriter(path, clock=clock)

    @property
    def path(self) -> str:
        """The capture file."""
        return self.writer.path

    @property
    def closed(self) -> bool:
        return self._closed or self.inner.closed

    @property
    def stats(self) -> LinkStats:
        """The inner link's statistics."""
        return self.inner.stats

    def send(self, frame: Frame | bytes) -> None:
        """Send through the inner link, then record the frame.

        Raises:
            FrameError, LinkClosedError, LinkTimeoutError: as the inner link's
                ``send``; nothing is recorded then.
            CaptureError: the frame was sent but could not be recorded.
        """
        self.inner.send(frame)
        self.writer.write(frame.raw if isinstance(frame, Frame) else bytes(frame))

    def recv(self, timeout: float | None = None) -> Frame | None:
        """Receive from the inner link and record the frame, if any.

        Raises:
            LinkClosedError: as the inner link's ``recv``.
            CaptureError: a frame arrived but could not be recorded.
        """
        frame = self.inner.recv(timeout)
        if frame is not None:
            self.writer.write(frame.raw)
        return frame

    @property
    def can_reopen(self) -> bool:  # type: ignore[override]
        return self.inner.can_reopen

    @property
    def identity(self) -> DeviceIdentity | None:
        """The inner link's device identity."""
        return self.inner.identity

    def check_device(self) -> None:
        """The inner link's :meth:`~Link.check_device`."""
        self.inner.check_device()

    def reopen(self) -> None:
        """Reopen the inner link's device (see :meth:`Link.reopen`: only the device it
        opened first); the capture goes on in the same file."""
        if self._closed:
            raise LinkClosedError(f"{self.url} is closed")
        self.inner.reopen()

    def release(self) -> None:
        """Release the inner link's device (see :meth:`Link.release`)."""
        self.inner.release()

    def _close(self) -> None:
        try:
            self.inner.close()
        finally:
            self.writer.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return f"<CaptureLink {self.url} -> {self.path} {state}>"


__all__ = ["CaptureLink"]
