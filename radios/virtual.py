"""The virtual backend: links in one process that hear each other, no device.

Theory of operation
-------------------
``virtual://NAME`` opens a member of the in-process bus called NAME (python-can's
``virtual`` interface): every frame a member sends reaches every *other* member
open on that bus at that moment, whole and in the order it was sent, as if they
shared one perfect radio channel. There is no air time and no TDM: the SiK air
model is the emulator's (:mod:`radios.emulator`), this is for tests and
in-process tools that need a real :class:`~radios.linkbase.Link` without ptys.

* A bus exists while it has members; the last member to close forgets it. Bus
  names are process-wide, so tests give each bus a unique name.
* Each member keeps the frames addressed to it in its own queue, bounded at
  :data:`MAX_PENDING` frames: a member that never reads drops the newest frames
  (counted in its ``stats.drops``) and never holds up the senders.
* ``?loss=P`` (0 to 1) drops each frame for each receiver with probability P,
  drawn from a generator seeded by ``?seed=N`` (default 0), so a lossy test is
  repeatable.
* :meth:`VirtualLink.write_bytes` puts raw bytes on the bus unchecked, as a
  noisy line or a foreign device would: the way to feed receivers garbage.

The base class gives the rest of the link semantics: ``send`` checks frames,
``recv(timeout)`` returns None on timeout, statistics, ``close()`` safe twice and
``LinkClosedError`` afterwards (a receiver blocked in ``recv`` wakes at once).
"""

from __future__ import annotations

import math
import random
import threading
from collections import deque
from typing import Any

from radios.errors import LinkClosedError, LinkOpenError
from radios.linkbase import Link
from radios.url import LinkURL, Options

#: Frames a member's queue holds before it drops the newest.
MAX_PENDING = 4096

_lock = threading.Lock()
_buses: dict[str, list[VirtualLink]] = {}


class VirtualLink(Link):
    """One member of the in-process bus ``name``; see the module docstring."""

    def __init__(self, url: str, name: str, *, loss: float = 0.0, seed: int = 0) -> None:
        if not name:
            raise LinkOpenError(f"{url}: no bus name (virtual://NAME)")
        if not (math.isfinite(loss) and 0.0 <= loss <= 1.0):
            raise LinkOpenError(f"{url}: loss must be between 0 and 1, not {loss}")
        super().__init__(url)
        self.name = name
        self.loss = loss
        self._rng = random.Random(seed)
        self._inbox: deque[bytes] = deque()
        self._ready = threading.Condition()
        with _lock:
            _buses.setdefault(name, []).append(self)

    def write_bytes(self, data: bytes) -> None:
        """Put ``data`` on the bus as it is, not checked as a frame and not counted.

        Raises:
            LinkClosedError: this member is closed.
        """
        if self._closed:
            raise LinkClosedError(f"{self.url} is closed")
        self._write(bytes(data))

    def _deliver(self, data: bytes) -> None:
        with self._ready:
            if self._closed:
                return
            if len(self._inbox) >= MAX_PENDING:
                self._stats.drops += 1
                return
            self._inbox.append(data)
            self._ready.notify()

    def _read(self, timeout: float) -> bytes:
        with self._ready:
            if not self._inbox and not self._closed and timeout > 0:
                self._ready.wait(timeout)
            if self._closed:
                raise LinkClosedError(f"{self.url} is closed")
            data = b"".join(self._inbox)
            self._inbox.clear()
            return data

    def _write(self, data: bytes) -> None:
        with _lock:
            members = [m for m in _buses.get(self.name, ()) if m is not self]
        for m in members:
            if self.loss and self._rng.random() < self.loss:
                continue
            m._deliver(data)  # noqa: SLF001 (the peer link, of the same class)

    def _close(self) -> None:
        with _lock:
            members = _buses.get(self.name, [])
            if self in members:
                members.remove(self)
            if not members:
                _buses.pop(self.name, None)
        with self._ready:
            self._inbox.clear()
            self._ready.notify_all()


def open_virtual(url: LinkURL, **options: Any) -> VirtualLink:
    """Open a member of the bus ``url.target`` (the backend factory of ``virtual``).

    Raises:
        LinkOpenError: no bus name, a malformed or unknown option, a loss outside
            0-1, or keyword ``options`` (a virtual link takes none).
    """
    if options:
        raise LinkOpenError(f"unexpected options for a virtual link: {', '.join(options)}")
    opts = Options(url)
    loss = opts.number("loss", 0.0)
    seed = opts.integer("seed", 0)
    opts.finish(("loss", "seed"))
    return VirtualLink(url.url, url.target, loss=loss, seed=seed)


__all__ = ["MAX_PENDING", "VirtualLink", "open_virtual"]
