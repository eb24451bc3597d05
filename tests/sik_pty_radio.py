"""Test helper: one emulated SiK radio's AT interface on a real pseudo terminal.

:class:`PtyRadio` opens a pty, gives its slave path to the code under test (which
opens it with pyserial like a real radio's /dev/ttyUSB0) and runs a thread that feeds
every byte written to it into an :class:`ATEngine`, using ``time.monotonic()`` as the
engine's clock, and writes the engine's output back. Remote (``RT``) commands are run
at once on an optional ``peer`` engine and its reply is printed locally, as if the
link were perfect and instant. Nothing goes over any air: ``air`` just collects the
data-mode bytes.

:class:`SilentPty` is a pty that nobody answers on.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from types import TracebackType

from radios.sik.at import ATEngine
from radios.sik.params import SikParams


def make_engine(
    flavour: str = "standard",
    *,
    stored: dict[str, int] | None = None,
    node_id: int | None = None,
    board: str = "HM-TRP",
    boot_time: float | None = None,
    cls: type[ATEngine] = ATEngine,
) -> ATEngine:
    """An ATEngine (or ``cls``, a subclass) with fixed ATI6/ATI7 text."""
    return cls(
        SikParams(flavour, stored=stored),
        flavour=flavour,
        board=board,
        ati6=lambda: "silence_period: 260\ntx_window_width: 7140\nmax_data_packet_length: 252",
        ati7=lambda: (
            "L/R RSSI: 180/175  L/R noise: 40/42 pkts: 10  txe=0 rxe=0 stx=0 srx=0 ecc=0/0 temp=30 dco=0"
        ),
        node_id=node_id,
        boot_time=boot_time,
    )


class PtyRadio:
    """Serve ``engine`` on a pty until :meth:`close` (use as a context manager)."""

    def __init__(
        self,
        engine: ATEngine | None = None,
        *,
        peer: ATEngine | None = None,
        start_in_command_mode: bool = False,
    ) -> None:
        self.engine = engine if engine is not None else make_engine()
        self.peer = peer
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.lock = threading.Lock()
        self.received = bytearray()  # every byte the host wrote
        self.air = bytearray()
        self.remote_commands: list[str] = []
        self.reboots = 0
        self.peer_reboots = 0
        if start_in_command_mode:
            t = time.monotonic()
            self.engine.feed(b"+++", t - 2.0)
            self.engine.poll(t - 0.5)
            assert self.engine.in_command_mode
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pty-radio", daemon=True)
        self._thread.start()

    def __enter__(self) -> PtyRadio:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=2.0)
        os.close(self.master)
        os.close(self.slave)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            written = os.write(self.master, view)
            view = view[written:]

    def _run(self) -> None:
        while not self._stop.is_set():
            with self.lock:
                deadline = self.engine.next_deadline()
            wait = 0.02
            if deadline is not None:
                wait = min(wait, max(0.0, deadline - time.monotonic()))
            ready, _, _ = select.select([self.master], [], [], wait)
            data = b""
            if ready:
                try:
                    data = os.read(self.master, 4096)
                except OSError:
                    data = b""
            now = time.monotonic()
            with self.lock:
                self.received += data
                out = self.engine.feed(data, now) if data else self.engine.poll(now)
                self.air += out.to_air
                if out.reboot:
                    self.reboots += 1
                reply = b""
                if out.remote_command is not None:
                    self.remote_commands.append(out.remote_command)
                    if self.peer is not None:
                        result = self.peer.run_remote(out.remote_command, now)
                        reply = result.output
                        self.peer_reboots += int(result.reboot)
            self._write(out.to_host + reply)


class SilentPty:
    """A pty whose other end never answers."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)

    def __enter__(self) -> SilentPty:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        os.close(self.master)
        os.close(self.slave)
