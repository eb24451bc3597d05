"""Test helpers for the radio link layer: frames, garbage, polling, a running emulator.

Nothing here sleeps to hope that something happened: :func:`recv_until` (and
``net_helpers.wait_until``, which the emulator's waits use) poll for an outcome
until a generous deadline and fail with a message saying what never happened.
:class:`RunningEmulator` runs a real :class:`~radios.emulator.Emulator` (real ptys,
real clock) in a thread and always stops it, so a failing test leaves no thread or
pty behind.
"""

from __future__ import annotations

import os
import random
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

from net_helpers import wait_until

from radios.emulator import Emulator
from radios.emulator_config import EmulatorConfig
from radios.link import Link, open_link
from radios.mavlink import STX_V1, STX_V2, Frame, FrameBuilder, FrameParser

#: Deadline for anything that crosses the emulated air (a few TDM rounds on a
#: busy two-core machine need far less; this only bounds a failing test).
AIR_DEADLINE = 10.0

#: Two standard radios find each other's hopping sequence after 0.4 to 20 s of model
#: time depending on the seed, as real SiK radios take seconds to sync (their frequency
#: hopping). Tests only wait for the lock (up to LOCK_DEADLINE); this seed, whose pair
#: locks in about 0.4 s, just keeps them quick. Nothing depends on it for correctness.
FAST_LOCK_SEED = 16
LOCK_DEADLINE = 60.0


def recv_until(
    link: Link, match: Callable[[Frame], bool], timeout: float = AIR_DEADLINE, seen: list[Frame] | None = None
) -> Frame | None:
    """Receive frames until one matches (returned) or ``timeout`` passes (None).
    Every frame received is appended to ``seen`` if given."""
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        frame = link.recv(min(left, 0.5))
        if frame is None:
            continue
        if seen is not None:
            seen.append(frame)
        if match(frame):
            return frame


def drain(link: Link, quiet: float = 0.3, limit: float = AIR_DEADLINE) -> list[Frame]:
    """Every frame received until the link stays quiet for ``quiet`` s."""
    out: list[Frame] = []
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        frame = link.recv(quiet)
        if frame is None:
            break
        out.append(frame)
    return out


def is_raw(raw: bytes) -> Callable[[Frame], bool]:
    """A ``recv_until`` predicate: exactly this frame."""
    return lambda f: f.raw == raw


def heartbeat(sysid: int, compid: int = 0) -> bytes:
    return FrameBuilder(sysid, compid).heartbeat()


def tunnel(sysid: int, payload: bytes, seq: int = 0) -> bytes:
    """A TUNNEL frame (never makes a radio inject RADIO_STATUS, unlike HEARTBEAT)."""
    b = FrameBuilder(sysid)
    b.mav.seq = seq
    return b.tunnel(payload)


def garbage(n: int, seed: int, *, with_stx: bool = True) -> bytes:
    """``n`` random bytes that contain no valid MAVLink frame. With ``with_stx``
    they include start bytes (0xFD/0xFE) followed by large length bytes, i.e.
    false starts; without, they contain neither start byte."""
    rng = random.Random(seed)
    while True:
        if with_stx:
            data = bytearray(rng.randbytes(n))
            for k in range(0, n - 1, 97):  # make sure there are false starts
                data[k] = STX_V2 if k % 2 else STX_V1
                data[k + 1] = 0xF0
        else:
            data = bytearray(b for b in rng.randbytes(2 * n) if b not in (STX_V1, STX_V2))[:n]
        if not FrameParser().feed(bytes(data) + bytes(300)):
            return bytes(data)
        # else (about never): a valid frame by chance; draw again


class RunningEmulator:
    """An :class:`Emulator` driven in a background thread (real time, real ptys)."""

    def __init__(self, cfg: EmulatorConfig) -> None:
        self.emu = Emulator(cfg)
        self.ports = self.emu.open()
        self.paths = [str(link) for link, _pty in self.ports]
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="emulator", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self.emu.run(self._stop)
        except BaseException as exc:  # reported by close(): a crash must fail the test
            self._error = exc

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def radio(self, i: int) -> dict[str, Any]:
        """Emulator statistics of radio ``i``."""
        radios: list[dict[str, Any]] = self.emu.stats()["radios"]
        return radios[i]

    def wait_connected(self, *radios: int) -> None:
        """Wait until the emulator has seen a host open each of ``radios``: bytes a
        host writes before that are discarded (see test_emulator)."""
        for i in radios:
            wait_until(partial(self.emu.connected.__getitem__, i), f"radio{i} connected", AIR_DEADLINE)

    def wait_locked(self, *radios: int) -> None:
        """Wait until each of ``radios`` has locked onto its peers' hopping sequence:
        until then it hears a packet only by chance, as a SiK radio that just booted."""
        for i in radios:
            wait_until(partial(self._locked, i), f"radio{i} locked", LOCK_DEADLINE)

    def _locked(self, i: int) -> bool:
        return bool(self.radio(i)["locked"])

    def wait_ready(self, *radios: int) -> None:
        self.wait_connected(*radios)
        self.wait_locked(*radios)

    def open(self, i: int, **kw: Any) -> Link:
        return open_link(self.paths[i], **kw)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        alive = self._thread.is_alive()
        self.emu.close()
        if alive:
            raise AssertionError("the emulator thread did not stop within 10 s")
        if self._error is not None:
            raise AssertionError(f"the emulator thread crashed: {self._error!r}") from self._error


@contextmanager
def running_emulator(directory: Path | str, nodes: int, **options: Any) -> Iterator[RunningEmulator]:
    """Run an emulator of ``nodes`` radios in ``directory`` for the ``with`` block."""
    options.setdefault("seed", FAST_LOCK_SEED)
    run = RunningEmulator(EmulatorConfig(nodes=nodes, directory=str(directory), **options))
    try:
        yield run
    finally:
        run.close()


@contextmanager
def opened(*links: Link) -> Iterator[tuple[Link, ...]]:
    """Close every link at the end of the block."""
    try:
        yield links
    finally:
        for link in links:
            link.close()


def raw_pty() -> tuple[int, str]:
    """A fresh pty in raw mode: (master fd, slave path). The slave is not held open."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    name = os.ttyname(slave)
    os.close(slave)
    return master, name
