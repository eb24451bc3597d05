"""A network of emulated SiK radios on real pseudo terminals.

Theory of operation
-------------------
One process owns N pseudo terminals. ``DIR/radio<i>`` is a symbolic link to the
slave end of pty *i*: any program opens it as the serial port of a SiK radio
(pyserial, pymavlink, MAVProxy, ``swarm radio-config``). The emulator holds the
master ends and drives one :class:`radios.air.AirModel` in real time
(``time.monotonic``), in a single thread with ``poll``:

* host -> radio: a master is read only while the model's serial line for that
  radio is nearly idle (less than ``READ_AHEAD_S`` of bytes in flight), and at
  most what the serial rate carries in that time. Bytes therefore enter the radio
  at the configured serial speed, and a host writing faster blocks in its
  ``write`` exactly as on a real UART (the pty's kernel buffer fills);
* radio -> host: what the model's serial output has delivered is written to the
  master; a host that does not read loses bytes in the radio's output buffer;
* a pty nobody has open reports POLLHUP: its radio's output is discarded (bytes
  sent down an unplugged cable are lost) and stale input is flushed;
* each radio has its own SiK parameters and AT command interpreter, so ``+++``,
  ``ATI5``, ``ATS3=..``, ``AT&W``, ``ATZ`` and ``RT..`` behave as on hardware;
  ``aes=True`` makes every radio an RFD900P running a SiK build with AES
  (ENCRYPTION_LEVEL, ``AT&E``; standard firmware only);
* every MAVLink frame put on air is captured to a ``.tlog`` when asked (with
  ``capture_status`` also one radio's RADIO_STATUS reports to its host, as a capture
  on that host, say a ground station, holds them: RADIO_STATUS never goes on air), and the
  model's counters can be written to a JSON file (at exit and every 2 s);
* **unplug and plug back** (:meth:`Emulator.unplug`, :meth:`Emulator.replug`, or
  lines written to the FIFO ``DIR/control``: ``unplug I [FOR_S]``, ``replug I``):
  unplugging closes radio *i*'s master and removes ``DIR/radio<i>``, so the host's
  reads and writes fail as on a USB radio pulled out; plugging back creates a new
  pty at the same path. The radio itself stays powered (a radio fed by the
  vehicle, its USB cable pulled): it keeps its slot and its lock on the air, sends
  what it still held, and what it receives meanwhile is lost;
* **each pty is labelled** with the emulator's instance number (random, drawn at
  start) and the radio's index, in the pty's window size
  (:func:`radios.device_id.emulator_label`), as a USB adapter states its ids and
  serial number: a link reopening ``DIR/radio<i>`` after a replug knows its radio from
  another radio, another emulator's or another program's pty.

:class:`Emulator` is usable in-process (tests) or through ``swarm radio-emu``. Its
options, their checks and the parameters each radio boots with are in
:mod:`radios.emulator_config`.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import secrets
import select
import stat
import struct
import termios
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from radios.air import AirModel, LossModel, RadioConfig
from radios.device_id import emulator_label
from radios.emulator_config import (
    EmulatorConfig,
    radio_config_of,
    stored_params,
)
from radios.errors import CaptureError, ConfigError
from radios.loss import GilbertElliott, PositionFile, RangeLoss, UniformLoss, sensitivity_dbm
from radios.mavlink import MSG_RADIO_STATUS, FrameParser
from radios.sik.at import ATEngine
from radios.sik.params import SikParams

READ_AHEAD_S = 0.02
STATS_EVERY_S = 2.0
MAX_PENDING = 65536
CONTROL = "control"  # the control FIFO in DIR
CONTROL_HELP = "unplug I [FOR_S] | replug I | loss P"


class Emulator:
    """See the module docstring. ``open()`` creates the ptys, ``run(stop)`` drives
    them until ``stop`` is set, ``close()`` removes everything (safe twice)."""

    def __init__(self, cfg: EmulatorConfig, *, clock: Callable[[], float] = time.monotonic) -> None:
        cfg.validate()
        self.cfg = cfg
        self.clock = clock
        self.firmware = cfg.resolved_firmware()
        self.params: list[SikParams] = []
        self.masters: list[int] = []
        self.links: list[Path] = []
        self.slave_names: list[str] = []
        self.connected: list[bool] = []
        self._pending: list[bytearray] = []
        self._capture: Any = None
        self._parsers: list[FrameParser] = []
        self._status_parser = FrameParser()
        self._epoch_offset = time.time() - clock()
        self.model: AirModel | None = None
        self.frames_captured = 0
        self.dropped_output = 0
        self._closed = False
        self._last_stats = 0.0
        self.started = clock()
        self.plugged: list[bool] = []
        self.unplugs = 0
        self._requests: deque[tuple[str, int, float | None]] = deque()
        self._replug_at: dict[int, float] = {}
        self._control: Path | None = None
        self._control_fds: list[int] = []
        self._control_buf = bytearray()
        self.uniform_loss = UniformLoss(cfg.loss)
        #: this emulator's instance number, in every pty's label (see the module docstring)
        self.instance = secrets.randbits(32)
        #: called on the emulator's thread with one line per unplug, plug or bad control line
        self.on_event: Callable[[str], None] | None = None

    # -- set-up -------------------------------------------------------------
    def radio_config(self, i: int) -> RadioConfig:
        """The model's view of radio ``i``'s active parameters."""
        return radio_config_of(self.params[i])

    def _losses(self) -> list[LossModel]:
        # always there, so that ``loss P`` can raise it later; at 0 it draws no random
        # number, so a run without loss is unchanged
        out: list[LossModel] = [self.uniform_loss]
        if self.cfg.burst_loss:
            out.append(GilbertElliott.parse(self.cfg.burst_loss))
        if self.cfg.positions:
            out.append(
                RangeLoss(
                    PositionFile(self.cfg.positions), sensitivity_dbm=sensitivity_dbm(self.cfg.air_speed)
                )
            )
        return out

    def open(self) -> list[tuple[Path, str]]:
        """Create the ptys, links, capture file and model.

        Raises:
            ConfigError: the directory is missing or a link path is taken.
            CaptureError: the capture file cannot be created.
        """
        d = Path(self.cfg.directory)
        control = self._claim_directory(d)
        losses = self._losses()
        if self.cfg.capture:
            from radios.tlog import TlogWriter

            self._capture = TlogWriter(self.cfg.capture)
        try:
            for i in range(self.cfg.nodes):
                self.params.append(
                    SikParams(self.firmware, stored=stored_params(self.cfg, i), aes=self.cfg.aes)
                )
            for i in range(self.cfg.nodes):
                self.masters.append(-1)
                self.slave_names.append("")
                self.connected.append(False)
                self.plugged.append(False)
                self._pending.append(bytearray())
                self._parsers.append(FrameParser())
                self.links.append(d / f"radio{i}")
                self._plug(i)
            self._open_control(control)
            now = self.clock()
            self.started = now
            self.model = AirModel(
                [self.radio_config(i) for i in range(self.cfg.nodes)],
                seed=self.cfg.seed,
                losses=losses,
                start=now,
                at_factory=self._make_at,
                on_reboot=self._on_reboot,
                on_air=self._on_air if self._capture is not None else None,
                flow_control=self.cfg.flow_control,
            )
        except BaseException:
            self.close()
            raise
        return list(zip(self.links, self.slave_names, strict=True))

    def _claim_directory(self, d: Path) -> Path:
        """Check ``d`` and remove what a killed emulator left there; the control FIFO's
        path. Raises ConfigError."""
        if not d.is_dir():
            raise ConfigError(f"--dir {d}: no such directory (create it first: mkdir -p {d})")
        if not os.access(d, os.W_OK):
            raise ConfigError(f"--dir {d}: not writable")
        for i in range(self.cfg.nodes):
            link = d / f"radio{i}"
            if link.is_symlink():
                link.unlink()  # a stale link left by an emulator that was killed
            elif link.exists():
                raise ConfigError(f"{link} exists and is not a link: choose another --dir")
        control = d / CONTROL
        if control.is_symlink() or (control.exists() and stat.S_ISFIFO(control.stat().st_mode)):
            control.unlink()  # left by an emulator that was killed
        elif control.exists():
            raise ConfigError(f"{control} exists and is not a FIFO: choose another --dir")
        return control

    def _open_control(self, control: Path) -> None:
        os.mkfifo(control, 0o600)
        self._control = control
        # our own writer keeps the FIFO from reporting end-of-file between writers
        self._control_fds = [
            os.open(control, os.O_RDONLY | os.O_NONBLOCK),
            os.open(control, os.O_WRONLY | os.O_NONBLOCK),
        ]

    def _plug(self, i: int) -> None:
        """A new pty for radio ``i`` at ``DIR/radio<i>``."""
        master, slave = os.openpty()
        try:
            tty.setraw(slave)
            fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", *emulator_label(self.instance, i)))
            name = os.ttyname(slave)
        except BaseException:
            os.close(master)
            raise
        finally:
            os.close(slave)
        os.set_blocking(master, False)
        self.masters[i], self.slave_names[i] = master, name
        self.connected[i] = False
        self._pending[i].clear()
        link = self.links[i]
        with contextlib.suppress(FileNotFoundError):
            link.unlink()
        os.symlink(name, link)
        self.plugged[i] = True

    def _unplug(self, i: int) -> None:
        self.plugged[i] = False
        self.connected[i] = False
        self._pending[i].clear()
        with contextlib.suppress(OSError):
            if self.links[i].is_symlink():
                self.links[i].unlink()
        with contextlib.suppress(OSError):
            os.close(self.masters[i])
        self.masters[i] = -1
        self.unplugs += 1

    def unplug(self, i: int, for_s: float | None = None) -> None:
        """Pull radio ``i``'s cable (plugged back after ``for_s`` s if given). Safe from
        any thread: done by :meth:`run` within 0.1 s.

        Raises:
            ConfigError: no such radio or a bad duration.
        """
        self._check_radio(i)
        if for_s is not None and not 0.0 <= for_s <= 86400.0:
            raise ConfigError(f"unplug {i} {for_s}: a duration of 0 to 86400 s")
        self._requests.append(("unplug", i, for_s))

    def replug(self, i: int) -> None:
        """Plug radio ``i`` back (a new pty at the same path). Safe from any thread.

        Raises:
            ConfigError: no such radio.
        """
        self._check_radio(i)
        self._requests.append(("replug", i, None))

    def set_loss(self, p: float) -> None:
        """Change the uniform loss of every link while running (``loss P`` on the FIFO).

        Raises:
            ConfigError: not a probability.
        """
        if not 0.0 <= p <= 1.0:
            raise ConfigError(f"loss {p:g}: a probability between 0 and 1")
        self.uniform_loss.p = p
        self._tell(f"loss {p:g}")

    def _check_radio(self, i: int) -> None:
        if not 0 <= i < self.cfg.nodes:
            raise ConfigError(f"no radio {i}: radios are 0..{self.cfg.nodes - 1}")

    def _tell(self, text: str) -> None:
        if self.on_event is not None:
            with contextlib.suppress(Exception):
                self.on_event(text)

    def _serve(self, now: float, poller: Any, registered: list[int]) -> None:
        """Carry out unplug and plug requests (on the run thread)."""
        for i, t in list(self._replug_at.items()):
            if now >= t:
                del self._replug_at[i]
                self._requests.append(("replug", i, None))
        while self._requests:
            what, i, for_s = self._requests.popleft()
            if what == "unplug":
                if for_s is not None:
                    self._replug_at[i] = now + for_s
                if not self.plugged[i]:
                    continue
                if registered[i] > 0:
                    poller.unregister(self.masters[i])
                registered[i] = 0
                self._unplug(i)
                self._tell(f"radio{i} unplugged" + (f" for {for_s:g} s" if for_s is not None else ""))
            elif not self.plugged[i]:
                self._replug_at.pop(i, None)
                try:
                    self._plug(i)
                except OSError as exc:
                    self._tell(f"radio{i} not plugged back: {exc.strerror or exc}")
                    continue
                self._tell(f"radio{i} plugged back: {self.links[i]} -> {self.slave_names[i]}")

    def _read_control(self) -> None:
        try:
            data = os.read(self._control_fds[0], 4096)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EINTR):
                return
            raise
        self._control_buf += data
        if len(self._control_buf) > 4096 and b"\n" not in self._control_buf:
            self._control_buf.clear()
            self._tell(f"control: line too long (expected {CONTROL_HELP})")
        while b"\n" in self._control_buf:
            line, _, rest = bytes(self._control_buf).partition(b"\n")
            self._control_buf[:] = rest
            self.control(line.decode("utf-8", "replace"))

    def control(self, line: str) -> None:
        """One control line (``unplug I [FOR_S]`` or ``replug I``); a bad one is
        reported through ``on_event`` and changes nothing."""
        words = line.split()
        if not words:
            return
        try:
            if words[0] == "unplug" and len(words) in (2, 3):
                self.unplug(int(words[1]), float(words[2]) if len(words) == 3 else None)
            elif words[0] in ("replug", "plug") and len(words) == 2:
                self.replug(int(words[1]))
            elif words[0] == "loss" and len(words) == 2:
                self.set_loss(float(words[1]))
            else:
                raise ValueError
        except ValueError:
            self._tell(f"control: {line.strip()[:80]!r}: expected {CONTROL_HELP}")
        except ConfigError as exc:
            self._tell(f"control: {line.strip()[:80]!r}: {exc}")

    def _make_at(self, i: int, _cfg: RadioConfig) -> ATEngine:
        return ATEngine(
            self.params[i],
            flavour=self.firmware,
            board="RFD900P" if self.cfg.aes else "HM-TRP",
            ati6=lambda: self.model.ati6(i) if self.model else "",
            ati7=lambda: self.model.ati7(i) if self.model else "",
            node_id=i if self.firmware == "multipoint" else None,
        )

    def _on_reboot(self, i: int) -> RadioConfig:
        return self.radio_config(i)

    def _on_air(self, sender: int, payload: bytes, t0: float, t1: float, kind: str) -> None:
        if kind != "data" or self._capture is None:
            return
        for frame in self._parsers[sender].feed(payload):
            try:
                self._capture.write(frame.raw, self._epoch_offset + t1)
                self.frames_captured += 1
            except (CaptureError, OSError, ValueError):
                pass

    # -- running --------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Drive the ptys until ``stop`` is set."""
        model = self.model
        assert model is not None, "open() first"
        poller = select.poll()
        registered = [-1] * self.cfg.nodes
        next_hup_check = 0.0
        control = self._control_fds[0] if self._control_fds else None
        if control is not None:
            poller.register(control, select.POLLIN)
        while not stop.is_set():
            now = self.clock()
            self._serve(now, poller, registered)
            model.advance(now)
            self._deliver_output(model, now)
            if now >= next_hup_check:
                next_hup_check = now + 0.1
                self._check_connections()
            timeout = self._arm(model, now, poller, registered)
            if self.cfg.stats_json and now - self._last_stats >= STATS_EVERY_S:
                self._last_stats = now
                self.write_stats()
            events = poller.poll(max(0.0, timeout) * 1000.0)
            if events:
                self._handle(model, events, control, poller, registered)

    def _deliver_output(self, model: AirModel, now: float) -> None:
        """Each radio's serial output to its host (lost while nobody has the port open,
        the oldest bytes dropped beyond MAX_PENDING)."""
        for i in range(self.cfg.nodes):
            out = model.take_output(i, now)
            if out:
                if self.connected[i]:
                    pend = self._pending[i]
                    pend += out
                    if len(pend) > MAX_PENDING:
                        self.dropped_output += len(pend) - MAX_PENDING
                        del pend[: len(pend) - MAX_PENDING]
                else:
                    self.dropped_output += len(out)
            if out and i == self.cfg.capture_status:
                self._capture_status(out, now)
            if self._pending[i]:
                self._flush(i)

    def _capture_status(self, out: bytes | bytearray, now: float) -> None:
        """The RADIO_STATUS reports in what radio ``capture_status`` gave its host."""
        for frame in self._status_parser.feed(out):
            if frame.msgid == MSG_RADIO_STATUS and self._capture is not None:
                try:
                    self._capture.write(frame.raw, self._epoch_offset + now)
                    self.frames_captured += 1
                except (CaptureError, OSError, ValueError):
                    pass

    def _arm(self, model: AirModel, now: float, poller: Any, registered: list[int]) -> float:
        """Register what to wait for on each master (input while the radio's serial
        line is nearly idle, output while bytes are pending); the poll timeout."""
        timeout = 0.1
        dl = model.next_deadline()
        if dl is not None:
            timeout = min(timeout, dl - now)
        for i in range(self.cfg.nodes):
            mask = 0
            if self.connected[i]:
                backlog = model.serial_backlog_s(i, now)
                if backlog < READ_AHEAD_S / 2:
                    mask |= select.POLLIN
                elif backlog != float("inf"):
                    timeout = min(timeout, backlog - READ_AHEAD_S / 2)
                if self._pending[i]:
                    mask |= select.POLLOUT
            if mask != registered[i]:
                if mask:
                    if registered[i] > 0:
                        poller.modify(self.masters[i], mask)
                    else:
                        poller.register(self.masters[i], mask)
                elif registered[i] > 0:
                    poller.unregister(self.masters[i])
                registered[i] = mask
        return timeout

    def _handle(
        self,
        model: AirModel,
        events: list[tuple[int, int]],
        control: int | None,
        poller: Any,
        registered: list[int],
    ) -> None:
        """Control lines, hang-ups, and what the hosts wrote (at most READ_AHEAD_S of
        serial time per radio)."""
        t = self.clock()
        for fd, ev in events:
            if fd == control:
                self._read_control()
                continue
            i = self.masters.index(fd)
            if ev & (select.POLLHUP | select.POLLERR):
                self._disconnect(i)
                poller.unregister(fd)
                registered[i] = 0
                continue
            if ev & select.POLLIN:
                cfg = model.radios[i].cfg
                budget = max(1, int(READ_AHEAD_S * cfg.serial_baud / 10))
                try:
                    data = os.read(fd, budget)
                except (BlockingIOError, InterruptedError):
                    data = b""
                except OSError:
                    self._disconnect(i)
                    continue
                if data:
                    model.host_write(i, data, t)

    def _flush(self, i: int) -> None:
        pend = self._pending[i]
        try:
            k = os.write(self.masters[i], pend)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._disconnect(i)
            return
        del pend[:k]

    def _check_connections(self) -> None:
        for i, fd in enumerate(self.masters):
            if self.connected[i] or not self.plugged[i]:
                continue
            p = select.poll()
            p.register(fd, select.POLLIN)
            ev = p.poll(0)
            if ev and ev[0][1] & select.POLLHUP:
                continue
            # a host opened the port (nothing can have been written while none was open,
            # and what it writes right away must not be lost)
            self.connected[i] = True

    def _disconnect(self, i: int) -> None:
        self.connected[i] = False
        self._pending[i].clear()

    # -- reporting ------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        model = self.model
        assert model is not None
        now = self.clock()
        return {
            "nodes": self.cfg.nodes,
            "emulator": f"{self.instance:08x}",
            "firmware": self.firmware,
            "air_speed_kbps": model.radios[0].cfg.air_kbps,
            "serial_speed": model.radios[0].cfg.serial_baud,
            "round_s": model.round_s(0),
            "elapsed_s": now - self.started,
            "utilisation": model.utilisation(now),
            "frames_captured": self.frames_captured,
            "dropped_output_bytes": self.dropped_output,
            "radios": [
                {
                    "radio": i,
                    "link": str(self.links[i]),
                    "pty": self.slave_names[i],
                    "connected": self.connected[i],
                    "plugged": self.plugged[i],
                    # what ATI5 shows, what flash holds and what the radio runs with: a
                    # fault bench in another process sees an RT attack land and be undone
                    "params": self.params[i].as_dict(),
                    "saved": _named(self.params[i], self.params[i].eeprom),
                    "active": _named(self.params[i], self.params[i].active),
                    **model.status(i),
                }
                for i in range(self.cfg.nodes)
            ],
        }

    def write_stats(self) -> None:
        path = self.cfg.stats_json
        if not path or self.model is None:
            return
        tmp = f"{path}.tmp"
        try:
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump(self.stats(), fh, indent=1)
            os.replace(tmp, path)
        except OSError:
            pass

    def close(self) -> None:
        """Remove the links, close the ptys and the capture (safe twice)."""
        if self._closed:
            return
        self._closed = True
        if self.model is not None:
            self.write_stats()
        for link in self.links:
            with contextlib.suppress(OSError):
                if link.is_symlink():
                    link.unlink()
        for fd in self.masters:
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        for fd in self._control_fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        if self._control is not None:
            with contextlib.suppress(OSError):
                self._control.unlink()
        if self._capture is not None:
            self._capture.close()

    def __enter__(self) -> Emulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _named(p: SikParams, table: dict[int, int]) -> dict[str, int]:
    return {spec.name: table[spec.index] for spec in p.specs}


__all__ = ["CONTROL", "CONTROL_HELP", "Emulator"]
