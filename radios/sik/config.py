"""The host side of SiK AT configuration: talk to a radio (real or emulated) over serial.

Theory of operation
-------------------
:class:`SikConfigurator` drives one radio through an already-open pyserial-like port
(:func:`open_port` opens one with clear errors). It never blocks without a deadline:
every read is a short poll (``READ_SLICE``) inside a loop bounded by
``time.monotonic()``.

* :meth:`~SikConfigurator.enter_command_mode` first sends ``\\r\\nAT\\r\\n`` in case the
  radio was left in command mode (the echo ``AT`` followed by ``OK`` proves it). If
  not, it keeps silent for 1.2 s, writes ``+++`` with no line end and waits for
  ``OK``, which the radio prints after another 1 s of silence (on a busy link right
  after data from the air: then it is the last thing received); it tries twice. The
  probe and the ``+`` bytes reach the remote end as data, as with any SiK tool.
* :meth:`~SikConfigurator.command` writes one line plus CR and collects the reply:
  the echo of the line is dropped; the reply is complete at an ``OK``/``ERROR`` line,
  after an expected number of lines, or after a quiet gap with no byte once at least
  one reply line arrived (0.3 s locally). Replies of multipoint firmware carry an
  ``[id] `` prefix, kept in the returned lines and ignored when interpreting them.
* ``remote=True`` sends the radio's operations as ``RT...`` to the radio at the other
  end of the link (``RTI5,<node>`` with ``remote_node`` in multipoint). The local
  radio echoes the line and prints nothing else; the remote answer arrives later in
  small packets with bare ``\\n`` line ends, so the first-byte wait is longer (2 s)
  and so is the quiet gap (1 s). No answer means the link is down.

Parameters are read strictly (:mod:`radios.sik.readout`): a local ``ATI5`` line that
is not a register line of the firmware's table is an error; over the air every value
is confirmed by two answers and what cannot be confirmed is named, never guessed.
"""

from __future__ import annotations

import os
import re
import stat
import time
from typing import Any, Protocol

import serial

from radios.errors import ATError, ATTimeoutError, ConfigError, LinkClosedError, LinkOpenError
from radios.sik.param_table import check_flavour, spec_for
from radios.sik.params import validate_user_value
from radios.sik.readout import DEFAULT_TRIES, parse_local, read_remote

READ_SLICE = 0.05  # seconds: the longest a single port read blocks
GUARD_SILENCE = 1.2  # seconds of silence before +++ (the radio needs 1 s)
PROBE_TIME = 0.5  # seconds to wait for OK to the "already in command mode?" probe
LOCAL_QUIET = 0.3  # seconds without a byte that end a local informational reply
REMOTE_QUIET = 1.0  # the same for a remote (RT) reply, which comes in packets
LOCAL_TIMEOUT = 1.0  # default wait for the first reply line of a local command
REMOTE_TIMEOUT = 2.0  # default wait for the first reply line of a remote command
ASK_MIN = 0.6  # the shortest wait for a one-line remote answer (RTSn?)
HARD_EXTRA = 5.0  # a reply that keeps streaming is cut this long after its timeout

# After +++ the radio prints OK and then nothing more (command mode drops air data),
# but data from the air may come just before it, not ending in a line break.
_OK_AFTER_PLUS = re.compile(rb"(?:^|\n)(?:\[\d+\] )?OK\r\n|(?:\[\d+\] )?OK\r\n\Z")
_OK_AFTER_PROBE = re.compile(rb"AT\r\n(?:\[\d+\] )?OK\r\n")
_NODE_PREFIX = re.compile(r"^\[\d+\]\s*")

# SERIAL_SPEED code -> baud rate.
SERIAL_BAUD = {1: 1200, 2: 2400, 4: 4800, 9: 9600, 19: 19200, 38: 38400, 57: 57600, 115: 115200, 230: 230400}


class SerialPort(Protocol):
    """The part of ``serial.Serial`` the configurator uses."""

    timeout: float | None
    baudrate: int

    def write(self, data: bytes, /) -> int | None: ...

    def read(self, size: int = 1, /) -> bytes: ...

    def reset_input_buffer(self) -> None: ...

    @property
    def in_waiting(self) -> int: ...


def open_port(path: str, baud: int = 57600) -> Any:
    """Open serial device ``path`` at ``baud`` for :class:`SikConfigurator`.

    Returns an open ``serial.Serial`` (locked against other pyserial users).
    Raises :class:`LinkOpenError` if the path does not exist, is not a tty, cannot be
    opened for lack of permission, is locked by another program, or the baud rate is
    invalid.
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise LinkOpenError(
            f"{path}: no such device (radio unplugged, wrong path, or emulator not running?)"
        ) from None
    except PermissionError:
        raise LinkOpenError(f"{path}: permission denied") from None
    if not stat.S_ISCHR(mode):
        raise LinkOpenError(f"{path} is not a serial device (not a tty)")
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except PermissionError:
        raise LinkOpenError(
            f"{path}: permission denied (on Linux, add your user to the 'dialout' group and log in again)"
        ) from None
    except OSError as exc:
        raise LinkOpenError(f"cannot open {path}: {exc.strerror or exc}") from None
    try:
        is_tty = os.isatty(fd)
    finally:
        os.close(fd)
    if not is_tty:
        raise LinkOpenError(f"{path} is not a serial device (not a tty)")
    try:
        return serial.Serial(path, baud, timeout=READ_SLICE, write_timeout=2.0, exclusive=True)
    except ValueError as exc:
        raise LinkOpenError(f"{path}: bad serial settings: {exc}") from None
    except serial.SerialException as exc:
        if "lock" in str(exc).lower():
            raise LinkOpenError(f"{path} is in use by another program") from None
        raise LinkOpenError(f"cannot open {path}: {exc}") from None


def strip_node(line: str) -> str:
    """``'[2] OK'`` -> ``'OK'``: drop the node prefix multipoint firmware prints."""
    return _NODE_PREFIX.sub("", line, count=1)


class SikConfigurator:
    """Read and write one SiK radio's parameters with AT (or RT) commands.

    ``port`` is an open pyserial-like port; the configurator sets its read timeout to
    a short slice and uses it exclusively until done. ``flavour`` chooses the
    parameter table used to validate values. With ``remote=True`` the radio's
    operations go to the radio at the other end of the link (``remote_node`` picks one
    node in multipoint). Raises :class:`ConfigError` for an unknown flavour.
    """

    def __init__(
        self,
        port: SerialPort,
        *,
        flavour: str = "standard",
        remote: bool = False,
        remote_node: int | None = None,
        port_name: str | None = None,
    ) -> None:
        self.port = port
        self.flavour = check_flavour(flavour)
        self.remote = remote
        self.remote_node = remote_node
        self.port_name = port_name or str(getattr(port, "port", None) or "the serial port")
        self.indices: dict[str, int] = {}
        self.in_command_mode = False  # as far as we know: set by enter, cleared by ATO/ATZ
        self.tries = DEFAULT_TRIES  # answers asked for per register over the air
        self.unreadable: list[str] = []  # registers the last remote read could not confirm
        self.garbled = 0  # lines of the last remote RTI5 that were not whole register lines
        self._rtt: float | None = None  # the slowest RTSn? answer so far (seconds)
        self.port.timeout = READ_SLICE
        self._pending = bytearray()

    # -- low level ----------------------------------------------------------------------

    def _write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except (OSError, serial.SerialException) as exc:
            raise LinkClosedError(f"cannot write to {self.port_name}: {exc}") from None

    def _read_some(self) -> bytes:
        """Whatever arrives within one READ_SLICE (possibly nothing)."""
        try:
            waiting = self.port.in_waiting
            return bytes(self.port.read(waiting if waiting > 0 else 1))
        except (OSError, serial.SerialException) as exc:
            raise LinkClosedError(f"cannot read from {self.port_name}: {exc}") from None

    def _discard_input(self) -> None:
        self._pending.clear()
        try:
            self.port.reset_input_buffer()
        except (OSError, serial.SerialException) as exc:
            raise LinkClosedError(f"cannot use {self.port_name}: {exc}") from None

    def _wait_for(self, pattern: re.Pattern[bytes], seconds: float) -> bool:
        """Read until ``pattern`` matches what arrived, for at most ``seconds``."""
        deadline = time.monotonic() + seconds
        seen = bytearray()
        while time.monotonic() < deadline:
            seen += self._read_some()
            if pattern.search(seen):
                return True
        return False

    def _drain_until(self, deadline: float) -> None:
        """Read and drop input until ``deadline`` (keeps our side of the line silent)."""
        while time.monotonic() < deadline:
            self._read_some()

    # -- command mode -------------------------------------------------------------------

    def enter_command_mode(self, timeout: float = 3.0, *, probe: bool = True) -> None:
        """Put the local radio into AT command mode.

        ``timeout`` bounds each wait for ``OK`` after ``+++`` (the radio's 1 s guard
        plus margin). ``probe=False`` skips the probe for a radio already in command
        mode (the caller knows it is in data mode: 0.5 s less). Raises
        :class:`ATTimeoutError` if the radio never answers.
        """
        self._discard_input()
        last_write = time.monotonic()
        if probe:
            self._write(b"\r\nAT\r\n")
            last_write = time.monotonic()
        if probe and self._wait_for(_OK_AFTER_PROBE, PROBE_TIME):
            self._drain_until(time.monotonic() + 0.05)  # the echo of the trailing LF, if any
            self.in_command_mode = True
            return
        for _attempt in range(2):
            self._drain_until(last_write + GUARD_SILENCE)
            self._write(b"+++")
            last_write = time.monotonic()
            if self._wait_for(_OK_AFTER_PLUS, timeout):
                self.in_command_mode = True
                return
        baud = getattr(self.port, "baudrate", "?")
        raise ATTimeoutError(
            f"no answer to +++ on {self.port_name} at {baud} baud: wrong baud "
            "rate, port in use, or not a SiK radio"
        )

    def exit_command_mode(self) -> None:
        """``ATO``: back to data mode (always the local radio).

        Raises :class:`ATTimeoutError` if the radio does not echo the command.
        """
        self.command("ATO", expect_reply=False)
        self.in_command_mode = False

    # -- commands -----------------------------------------------------------------------

    def command(
        self, cmd: str, timeout: float | None = None, *, lines: int | None = None, expect_reply: bool = True
    ) -> list[str]:
        """Send one command line and return its reply lines (echo and blank lines removed).

        ``timeout`` is the wait for the first reply line (default 1 s, 2 s for ``RT``
        commands). The reply ends at an ``OK``/``ERROR`` line, after ``lines`` lines
        if given, or after a quiet gap. With ``expect_reply=False`` (``ATO``, ``ATZ``)
        only the echo is awaited. Raises :class:`ATTimeoutError` if the radio does not
        echo the line, or (remote) if no reply comes back; :class:`LinkClosedError` if
        the port fails.
        """
        text = cmd.strip().upper()
        is_remote = text.startswith("RT")
        if timeout is None:
            timeout = REMOTE_TIMEOUT if is_remote else LOCAL_TIMEOUT
        quiet = REMOTE_QUIET if is_remote else LOCAL_QUIET
        self._discard_input()
        self._write(text.encode("ascii") + b"\r")
        start = time.monotonic()
        first_deadline = start + timeout
        hard_deadline = first_deadline + HARD_EXTRA
        echoed = False
        reply: list[str] = []
        buf = bytearray()
        last_rx = start
        while True:
            chunk = self._read_some()
            now = time.monotonic()
            if chunk:
                last_rx = now
                buf += chunk
                *complete, rest = bytes(buf).split(b"\n")
                buf = bytearray(rest)
                for raw in complete:
                    line = raw.rstrip(b"\r").decode("ascii", "replace").strip()
                    if not line:
                        continue
                    if not echoed and line == text:
                        echoed = True
                        if not expect_reply:
                            return []
                        continue
                    reply.append(line)
                    if strip_node(line) in ("OK", "ERROR"):
                        return reply
                    if lines is not None and len(reply) >= lines:
                        return reply
            if reply and now - last_rx >= quiet:
                return reply
            if (not reply and now >= first_deadline) or now >= hard_deadline:
                break
        if reply:
            return reply
        raise self._no_answer(text, echoed, is_remote)

    def _no_answer(self, text: str, echoed: bool, is_remote: bool) -> ATTimeoutError:
        """The error for a command that got no reply: who did not answer."""
        if not echoed:
            return ATTimeoutError(
                f"no answer to {text} on {self.port_name}: the radio is not "
                "in command mode (or not a SiK radio)"
            )
        if is_remote:
            return ATTimeoutError(f"remote radio did not answer {text} (link down?)")
        return ATTimeoutError(f"no reply to {text} on {self.port_name}")

    def _op(self, at_command: str) -> str:
        """The command line for a radio operation: AT locally, RT (with target) remotely."""
        if not self.remote:
            return at_command
        line = "RT" + at_command[2:]
        if self.remote_node is not None:
            line += f",{self.remote_node}"
        return line

    def _expect_ok(self, lines: list[str], what: str) -> None:
        status = [strip_node(line) for line in lines]
        if "OK" in status:
            return
        where = "remote radio" if self.remote else f"radio on {self.port_name}"
        if "ERROR" in status:
            raise ATError(f"{where} refused {what} (answered ERROR)")
        raise ATError(f"{where} gave an unexpected answer to {what}: {lines!r}")

    # -- operations ---------------------------------------------------------------------

    def version(self) -> str:
        """The radio's banner (``ATI``), e.g. ``'SiK 2.2 on HM-TRP'`` (node prefix removed).
        A local radio's banner also sets :attr:`flavour` (``MP SiK ...``: multipoint).

        Raises :class:`ATTimeoutError` without an answer.
        """
        lines = self.command(self._op("ATI"), lines=1)
        banner = strip_node(lines[0])
        if not self.remote:  # the local banner says which table the registers follow
            self.flavour = "multipoint" if banner.startswith("MP ") else "standard"
        return banner

    def read_params(self, lines: int | None = None) -> dict[str, int]:
        """All parameters as name -> value, in register order, read strictly
        (:mod:`radios.sik.readout`): locally one ``ATI5`` whose every line must be a
        register line of the flavour's table; remotely every register confirmed by two
        answers (``RTI5``, then ``RTSn?``), the registers that could not be read left out
        and named in :attr:`unreadable`.

        ``lines`` (local only): the number of register lines expected, so that the
        reply ends with the last one instead of after a quiet gap.

        Raises :class:`ATError` for a garbled local answer, :class:`ATTimeoutError`
        without an answer.
        """
        if self.remote:
            readout = read_remote(self._ask, self.flavour, self.remote_node, self.tries)
            parsed, self.unreadable, self.garbled = readout.values, readout.unreadable, readout.garbled
        else:
            parsed = parse_local(self.command("ATI5", lines=lines), self.flavour, self.port_name)
            self.unreadable, self.garbled = [], 0
        ordered = sorted(parsed.items(), key=lambda item: item[1][0])
        self.indices = {name: index for name, (index, _) in ordered}
        return {name: value for name, (_, value) in ordered}

    def _ask(self, line: str) -> list[str]:
        """One remote command line as given (target included); one line for ``RTSn?``,
        awaited three times the slowest answer seen so far (0.6 s to 2 s): a lost
        question costs less, and a late answer is outvoted (two answers must agree)."""
        if not line.partition(",")[0].endswith("?"):
            return self.command(line)
        wait = REMOTE_TIMEOUT if self._rtt is None else min(REMOTE_TIMEOUT, max(ASK_MIN, 3 * self._rtt))
        start = time.monotonic()
        lines = self.command(line, wait, lines=1)
        self._rtt = max(self._rtt or 0.0, time.monotonic() - start)
        return lines

    def set_param(self, name: str, value: int | str) -> None:
        """``ATSn=value`` for parameter ``name`` (validated first, nothing sent if bad).

        Raises :class:`ConfigError` for an unknown name or a bad value, :class:`ATError`
        if the radio answers ERROR, :class:`ATTimeoutError` without an answer.
        """
        number = validate_user_value(self.flavour, name, value)
        spec = spec_for(self.flavour, name)
        index = self.indices.get(spec.name, spec.index)
        lines = self.command(self._op(f"ATS{index}={number}"))
        self._expect_ok(lines, f"{spec.name}={number} (ATS{index}={number})")

    def set_key(self, key: bytes) -> None:
        """``AT&E=<hex>``: give the local radio its AES key (AES builds only; the key
        length must match the ENCRYPTION_LEVEL already set in RAM). No message this
        raises contains the key. Raises :class:`ConfigError` in remote mode (an ``RT``
        line crosses the air in clear), :class:`ATError` if the radio does not take
        it, :class:`ATTimeoutError` without an answer.
        """
        if self.remote:
            raise ConfigError(
                "an AES key is never sent to a remote radio: RT commands cross the air unencrypted"
            )
        try:
            lines = self.command("AT&E=" + key.hex().upper())
        except ATTimeoutError:
            raise ATTimeoutError(f"no answer to AT&E=<key> on {self.port_name}") from None
        status = [strip_node(line) for line in lines]
        if "OK" in status and any(line.lower().startswith("key len") for line in status):
            return
        raise ATError(
            f"radio on {self.port_name} did not take the key (AT&E=<key>): is "
            "ENCRYPTION_LEVEL set to match the key length?"
        )

    def key_matches(self, key: bytes) -> bool:
        """``AT&E?``: whether the radio's RAM key is ``key`` (the answer is never
        returned or printed). Raises :class:`ATTimeoutError` without an answer."""
        try:
            lines = self.command("AT&E?", lines=1)
        except ATTimeoutError:
            raise ATTimeoutError(f"no answer to AT&E? on {self.port_name}") from None
        return any(strip_node(line).lower() == key.hex() for line in lines)

    def save(self) -> None:
        """``AT&W``: save the parameters to flash. Raises :class:`ATError` unless OK."""
        self._expect_ok(self.command(self._op("AT&W")), "AT&W")

    def reboot(self) -> None:
        """``ATZ``: reboot the radio into data mode with the saved parameters (no reply).

        Raises :class:`ATTimeoutError` if the local radio does not echo the command.
        """
        self.command(self._op("ATZ"), expect_reply=False)
        if not self.remote:
            self.in_command_mode = False
