"""The radio side of the SiK AT command interface, as a pure state machine.

Theory of operation
-------------------
:class:`ATEngine` is what one emulated SiK radio does with the bytes its host writes
to it. It does no I/O and reads no clock: the driver passes every byte with the time
it arrived (``feed(data, now)``), calls ``poll(now)`` when ``next_deadline()`` says
time alone will change something, and carries out the returned :class:`ATOutput`
(bytes for the air, bytes for the host, a remote command to send, a reboot).

Two modes, as in the firmware's at.c and serial.c:

* **Data mode.** Every byte goes to the air (``to_air``) and through the ``+++``
  detector: after at least 1 s with no serial input, three ``+`` (any gap between
  them, extra ``+`` allowed, any other byte starts over) followed by 1 s of silence
  enter command mode and print ``OK``. The ``+`` bytes are not swallowed: they were
  already sent to the air, as on a real radio.
* **Command mode.** Bytes are not forwarded. Printable bytes are echoed upper-cased
  into a 16-character line; BS/DEL erase (echo ``\\b \\b``); LF is ignored; CR echoes
  ``\\r\\n`` and runs the line. A 17th character abandons the line and silently
  returns to data mode. Lines not starting ``AT``/``RT`` get no reply; replies end
  ``\\r\\n``. ``ATO``, ``ATZ`` and ``AT&T...`` print nothing.

Detector states (timer = "1 s after the last byte"; it is started by boot, by
``ATO`` and by any byte in IDLE/ENABLE, and runs out only once)::

    IDLE --timer--> PLUS1 --'+'--> PLUS2 --'+'--> PLUS3 --'+'--> ENABLE --timer--> command mode
      any byte other than '+' --> IDLE (timer restarted); '+' in IDLE/ENABLE restarts the timer

A quirk follows from this and is kept: after a line overflow the timer is not running,
so the first byte after it only restarts the timer; ``+++`` then needs 1 s of silence
before it like anywhere else.

``RT...`` lines are for the remote radio(s): nothing is printed, the line comes back
once as ``ATOutput.remote_command`` and the rest of that ``feed`` chunk is dropped (the
firmware drops serial input while a command is pending until its next TX slot). The
radio that receives it over the air runs it with :meth:`ATEngine.run_remote`, which
returns the captured reply (bare ``\\n`` line ends, no echo, at most 252 bytes) for
the caller to send back. In multipoint firmware ``RTI5,2`` targets node 2: the
whole text, target included, is handed out and the emulator routes it
(:func:`split_remote_target` parses it); ``run_remote`` ignores a target suffix.

Multipoint firmware prefixes every line it prints, locally and remotely, with
``[<node id>] `` (``[1] OK``) and prints its registers as ``S3: NETID=25`` (a space
after the colon); the standard firmware prints bare lines and ``S3:NETID=25``. A
multipoint ``RTI5`` (exactly that) is not captured into one 252-byte reply: every
register line goes back in a packet of its own (``RemoteResult.per_line``).

A command line holds 16 characters on Si1000 boards and 69 on the Si103x boards
(RFD900P, RFD900U, MRO900), as at.h's AT_CMD_MAXLEN; a received ``RT`` line longer
than that is ignored. On an AES build (``SikParams(aes=True)``, RFD900P/RFD900U only)
``AT&E=<hex>`` sets the key (printing ``key len N`` then ``OK``; too short a key prints
``ERROR - Key length:..`` then ``OK`` and sets the default key) and ``AT&E?`` prints
it, locally and over the air alike: the firmware asks nothing more of an ``RT`` line.

Not modelled: the bootloader and board extras (``AT&UPDATE``, ``AT&P``, ``ATP...``,
``AT+...``, and ``AT&E`` without AES answer ``ERROR``), multipoint ``ATI8``, the short window in which
the firmware drops bytes while a local command runs, and the TDM debug output of
``AT&T=TDM`` (the flag is kept). ``AT&T=RSSI`` prints the ATI7 line every 0.5 s.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass

from radios.errors import ConfigError
from radios.sik.param_table import BROADCAST, NODEID, UINT32_MAX, check_flavour
from radios.sik.params import SikParams

BOARD_IDS: dict[str, int] = {
    "HM-TRP": 78,
    "HB1060": 80,
    "3DR1060": 81,
    "RFD900A": 67,
    "RFD900P": 130,
    "RFD900U": 129,
    "MRO900": 145,
}
BOOTLOADER_VERSION = 2  # ATI4; a plausible value for an HM-TRP bootloader
AT_CMD_MAXLEN = 16  # Si1000 boards (Si103x boards allow 69)
AT_CMD_MAXLEN_SI103X = 69
SI103X_BOARDS = frozenset({"RFD900P", "RFD900U", "MRO900"})
AES_BOARDS = frozenset({"RFD900P", "RFD900U"})  # the only boards ever built with AES
REMOTE_REPLY_MAX = 252  # bytes of captured output a remote command returns
GUARD_TIME = 1.0  # seconds of serial silence before and after +++
RSSI_REPORT_INTERVAL = 0.5  # AT&T=RSSI prints the ATI7 line this often

_CR, _LF, _BS, _DEL, _PLUS = 0x0D, 0x0A, 0x08, 0x7F, 0x2B


class _Plus(enum.IntEnum):
    """States of the +++ detector (at.c's ATP_*)."""

    IDLE = 0
    PLUS1 = 1
    PLUS2 = 2
    PLUS3 = 3
    ENABLE = 4


@dataclass
class ATOutput:
    """What the radio does in response to serial input or time passing."""

    to_air: bytes = b""
    """Data-mode bytes for the radio's transmit buffer (including the ``+`` of ``+++``)."""
    to_host: bytes = b""
    """Echo and replies, for the host's serial side."""
    remote_command: str | None = None
    """An ``RT...`` line (upper-cased, <= 16 chars) to send once to the remote radio(s)."""
    reboot: bool = False
    """``ATZ``: the engine already ran ``params.boot()``; the caller re-inits its timing
    (air speed, windows, serial speed) from ``params.active``."""
    applied: bool = False
    """An ``ATSn=`` of a register the firmware applies at once (param_set: TXPOWER,
    DUTY_CYCLE, LBT_RSSI, MAVLINK, RTSCTS, OPPRESEND; multipoint NODEID,
    NODEDESTINATION, SYNCANY, NODECOUNT) changed ``params.active``: the caller runs
    with it from now on, without a reboot."""


@dataclass(frozen=True)
class RemoteResult:
    """What a radio does with an ``RT...`` command received over the air."""

    output: bytes = b""
    """The captured reply to send back (bare ``\\n`` line ends, <= 252 bytes); empty means
    send nothing."""
    per_line: bool = False
    """Multipoint ``RTI5``: each line of ``output`` goes in a packet of its own and the
    whole table is sent, not cut at 252 bytes (tdm.c's packet_ati5_inject)."""
    reboot: bool = False
    """``RTZ``: the engine already ran ``params.boot()``; the caller re-inits this radio."""
    applied: bool = False
    """As :attr:`ATOutput.applied`: a register that applies at once was set over the air."""


def split_remote_target(command: str) -> tuple[str, int]:
    """Split a multipoint remote command into (command, destination node).

    ``'RTI5,2'`` -> ``('RTI5', 2)``; without a comma the destination is
    :data:`BROADCAST` (65535). Like the firmware, the comma is looked for from the
    fourth character on, the number stops at the first non-digit (``'RTI5,'`` -> 0)
    and is truncated to 16 bits.
    """
    comma = command.find(",", 3)
    if comma < 0:
        return command, BROADCAST
    return command[:comma], _parse_number(command, comma + 1)[0] & 0xFFFF


def _parse_number(text: str, start: int) -> tuple[int, int]:
    """at.c's at_parse_number: decimal digits from ``start`` (uint32 arithmetic).

    Returns (value, index of the first non-digit).
    """
    value, i = 0, start
    while i < len(text) and "0" <= text[i] <= "9":
        value = (value * 10 + ord(text[i]) - 48) & UINT32_MAX
        i += 1
    return value, i


class _Out:
    """Accumulates one ATOutput."""

    def __init__(self) -> None:
        self.air = bytearray()
        self.host = bytearray()
        self.remote: str | None = None
        self.reboot = False
        self.applied = False

    def build(self) -> ATOutput:
        return ATOutput(bytes(self.air), bytes(self.host), self.remote, self.reboot, self.applied)


class ATEngine:
    """The AT command interpreter of one emulated SiK radio (see the module docstring).

    ``ati6``/``ati7`` produce the text of ``ATI6``/``ATI7`` (lines separated by ``\\n``;
    the engine adds the line ends). ``node_id`` overrides the id multipoint firmware
    prints in its ``[id]`` prefix (default: the active NODEID). ``boot_time`` is when
    the radio powered on (the first ``+++`` needs 1 s of silence after it); None means
    long ago.

    Raises :class:`ConfigError` if ``flavour`` differs from ``params.flavour``, the
    board is unknown, or ``params`` is an AES build on a board never built with AES.
    """

    def __init__(
        self,
        params: SikParams,
        *,
        flavour: str = "standard",
        board: str = "HM-TRP",
        version: str = "2.2",
        ati6: Callable[[], str],
        ati7: Callable[[], str],
        node_id: int | None = None,
        boot_time: float | None = None,
    ) -> None:
        if check_flavour(flavour) != params.flavour:
            raise ConfigError(
                f"ATEngine flavour {flavour!r} does not match the parameters' flavour {params.flavour!r}"
            )
        if board not in BOARD_IDS:
            raise ConfigError(f"unknown SiK board {board!r}: use one of " + ", ".join(BOARD_IDS))
        if getattr(params, "aes", False) and board not in AES_BOARDS:
            raise ConfigError(
                f"SiK firmware with AES was only built for {' and '.join(sorted(AES_BOARDS))}, not {board}"
            )
        self.params = params
        self.max_line = AT_CMD_MAXLEN_SI103X if board in SI103X_BOARDS else AT_CMD_MAXLEN
        self.flavour = params.flavour
        self.board = board
        self.version = version
        self._ati6 = ati6
        self._ati7 = ati7
        self._node_id = node_id
        self._now = -math.inf if boot_time is None else boot_time
        self._line = bytearray()
        self._at_mode = False
        self._plus = _Plus.IDLE
        self._plus_deadline: float | None = None
        self._test_rssi = False
        self._test_tdm = False
        self._rssi_deadline: float | None = None
        self._applied = False  # an ATSn= of a 'now' register since the last output
        self._restart(boot_time)

    # -- public state ---------------------------------------------------------------

    @property
    def in_command_mode(self) -> bool:
        return self._at_mode

    @property
    def banner(self) -> str:
        prefix = "MP " if self.flavour == "multipoint" else ""
        return f"{prefix}SiK {self.version} on {self.board}"

    @property
    def debug_rssi(self) -> bool:
        """AT&T=RSSI is on (the ATI7 line is printed every 0.5 s)."""
        return self._test_rssi

    @property
    def debug_tdm(self) -> bool:
        """AT&T=TDM is on (its output is not modelled)."""
        return self._test_tdm

    # -- driving ----------------------------------------------------------------------

    def feed(self, data: bytes, now: float) -> ATOutput:
        """Bytes that arrived from the host's serial side at time ``now`` (seconds)."""
        out = _Out()
        now = self._advance(now, out)
        for c in data:
            if not self._at_mode:
                self._detect_plus(c, now)
                out.air.append(c)
            elif self._at_input(c, now, out):
                break  # RT pending or rebooting: the rest of this chunk is lost
        return out.build()

    def poll(self, now: float) -> ATOutput:
        """Time has passed until ``now``: the +++ guard may elapse, debug lines may print."""
        out = _Out()
        self._advance(now, out)
        return out.build()

    def next_deadline(self) -> float | None:
        """When :meth:`poll` next has something to do (None: not until more input)."""
        deadlines = [self._rssi_deadline] if self._rssi_deadline is not None else []
        if self._plus == _Plus.ENABLE and self._plus_deadline is not None:
            deadlines.append(self._plus_deadline)
        return min(deadlines) if deadlines else None

    def run_remote(self, command: str, now: float | None = None) -> RemoteResult:
        """Run an ``RT...`` command received over the air as ``AT...``.

        Returns the captured output (no echo, bare ``\\n`` line ends, cut at 252 bytes)
        for the caller to send back; empty for ``RTZ``, which reboots this radio
        (``reboot=True``) and for lines that are not commands. In multipoint a
        ``,<node>`` target suffix is ignored. ``now`` (default: the last time seen) only
        matters for the guard timer restarted by ``RTO``/``RTZ``.
        """
        t = self._now if now is None else max(now, self._now)
        self._now = t
        line = command.strip().upper()
        if len(line) > self.max_line:
            return RemoteResult()  # tdm.c's handle_at_command drops it
        if self.flavour == "multipoint":
            line = split_remote_target(line)[0]
        if line.startswith("RT"):
            line = "AT" + line[2:]
        elif not line.startswith("AT"):
            return RemoteResult()
        self._applied = False
        lines, reboot = self._run_at(line, t)
        applied, self._applied = self._applied, False
        if reboot:
            return RemoteResult(b"", reboot=True)
        text = "".join(f"{self._prefix()}{entry}\n" for entry in lines).encode("ascii", "replace")
        if self.flavour == "multipoint" and line == "ATI5":
            return RemoteResult(text, per_line=True)
        return RemoteResult(text[:REMOTE_REPLY_MAX], applied=applied)

    # -- time ---------------------------------------------------------------------------

    def _advance(self, now: float, out: _Out) -> float:
        """Fire the timers due by ``now``; return ``now`` (never earlier than before)."""
        now = max(now, self._now)
        self._now = now
        if self._plus_deadline is not None and now >= self._plus_deadline:
            self._plus_deadline = None
            if self._plus == _Plus.IDLE:
                self._plus = _Plus.PLUS1
            elif self._plus == _Plus.ENABLE and not self._at_mode:
                self._plus = _Plus.IDLE
                self._at_mode = True
                self._line.clear()
                out.host += self._format(["OK"])  # at.c stuffs an empty "AT" command
        if self._rssi_deadline is not None and now >= self._rssi_deadline:
            out.host += self._format(self._text_lines(self._ati7))
            self._rssi_deadline += RSSI_REPORT_INTERVAL
            if self._rssi_deadline <= now:  # polled late: one line, then back on the beat
                self._rssi_deadline = now + RSSI_REPORT_INTERVAL
        return now

    def _restart(self, now: float | None) -> None:
        """The AT layer's state at power-on (``now`` None: powered on long ago)."""
        self._at_mode = False
        self._line.clear()
        self._test_rssi = self._test_tdm = False
        self._rssi_deadline = None
        if now is None:
            self._plus, self._plus_deadline = _Plus.PLUS1, None
        else:
            self._plus, self._plus_deadline = _Plus.IDLE, now + GUARD_TIME

    def _detect_plus(self, c: int, now: float) -> None:
        """at.c's at_plus_detector, for one byte in data mode."""
        if c != _PLUS:
            self._plus = _Plus.IDLE
        if self._plus in (_Plus.PLUS1, _Plus.PLUS2):
            self._plus = _Plus(self._plus + 1)
        elif self._plus == _Plus.PLUS3:
            self._plus = _Plus.ENABLE
            self._plus_deadline = now + GUARD_TIME
        else:  # IDLE or ENABLE: (re)start the 1 s timer
            self._plus_deadline = now + GUARD_TIME

    # -- command mode -------------------------------------------------------------------

    def _at_input(self, c: int, now: float, out: _Out) -> bool:
        """at.c's at_input for one byte. Returns True if the rest of the chunk is lost."""
        if c == _CR:
            out.host += b"\r\n"
            line = self._line.decode("ascii")
            self._line.clear()
            return self._execute(line, now, out)
        if c in (_BS, _DEL):
            if self._line:
                out.host += b"\b \b"
                del self._line[-1]
            return False
        if len(self._line) < self.max_line:
            if 0x20 <= c < 0x7F:
                upper = ord(chr(c).upper())
                self._line.append(upper)
                out.host.append(upper)
            return False
        # Overflow: abandon the line and go back to data mode, silently.
        self._at_mode = False
        self._line.clear()
        return False

    def _execute(self, line: str, now: float, out: _Out) -> bool:
        if line.startswith("RT"):
            out.remote = line
            return True
        if not line.startswith("AT"):
            return False
        lines, reboot = self._run_at(line, now)
        out.host += self._format(lines)
        if self._applied:
            self._applied = False
            out.applied = True
        if reboot:
            out.reboot = True
        return reboot

    def _run_at(self, line: str, now: float) -> tuple[list[str], bool]:
        """Run one ``AT...`` line: (reply lines, reboot). at.c's at_command."""
        rest = line[2:]
        if rest == "":
            return ["OK"], False
        op, arg = rest[0], rest[1:]
        if op == "I":
            return self._info(arg), False
        if op == "S":
            return self._register(arg), False
        if op == "&":
            return self._ampersand(arg, now), False
        if op == "O":
            self._at_mode = False
            self._plus_deadline = now + GUARD_TIME
            return [], False
        if op == "Z":
            self.params.boot()
            self._restart(now)
            return [], True
        return ["ERROR"], False

    def _info(self, arg: str) -> list[str]:
        which = arg[:1]  # the firmware looks at one character only: ATI5X is ATI5
        if which in ("", "0"):
            return [self.banner]
        if which == "1":
            return [self.version]
        if which == "2":
            return [str(BOARD_IDS[self.board])]
        if which == "3":
            return [str(self.params.band.code)]
        if which == "4":
            return [str(BOOTLOADER_VERSION)]
        if which == "5":  # multipoint's param_print puts a space after the colon
            sep = ": " if self.flavour == "multipoint" else ":"
            return [
                f"S{spec.index}{sep}{spec.name}={self.params.ram[spec.index]}" for spec in self.params.specs
            ]
        if which == "6":
            return self._text_lines(self._ati6)
        if which == "7":
            return self._text_lines(self._ati7)
        return ["ERROR"]

    def _register(self, arg: str) -> list[str]:
        """ATSn? and ATSn=v (at.c's at_s); ``arg`` is what follows 'ATS'."""
        number, i = _parse_number(arg, 0)
        index = number & 0xFF  # the register number is a uint8_t in the firmware
        if index >= len(self.params.specs):
            return ["ERROR"]
        op = arg[i : i + 1]
        if op == "?":
            return [str(self.params.get(index))]
        if op == "=" and index > 0:
            value = _parse_number(arg, i + 1)[0]
            if not self.params.set(index, value):
                return ["ERROR"]
            if self.params.specs[index].applies == "now":
                self._applied = True
            return ["OK"]
        return ["ERROR"]

    def _ampersand(self, arg: str, now: float) -> list[str]:
        which = arg[:1]
        if which == "F":
            self.params.factory_reset()
            return ["OK"]
        if which == "W":
            self.params.save()
            return ["OK"]
        if which == "E" and self.params.aes:
            if arg[1:2] == "?":
                return [self.params.key_hex()]
            if arg[1:2] == "=":
                length = len(self.params.key_hex()) // 2
                if self.params.set_key(arg[2:]):
                    return [f"key len {length}", "OK"]
                return [f"ERROR - Key length:{len(arg[2:])}, Required {2 * length}", "OK"]
            return ["ERROR"]
        if which == "T":
            mode = arg[1:]
            if mode == "":
                self._test_rssi = self._test_tdm = False
            elif mode == "=RSSI":
                self._test_rssi = not self._test_rssi
            elif mode == "=TDM":
                self._test_tdm = not self._test_tdm
            else:
                return ["ERROR"]
            self._rssi_deadline = now + RSSI_REPORT_INTERVAL if self._test_rssi else None
            return []
        return ["ERROR"]

    # -- output -------------------------------------------------------------------------

    def _prefix(self) -> str:
        if self.flavour != "multipoint":
            return ""
        node = self._node_id if self._node_id is not None else self.params.active[NODEID]
        return f"[{node}] "

    def _format(self, lines: list[str]) -> bytes:
        return "".join(f"{self._prefix()}{line}\r\n" for line in lines).encode("ascii", "replace")

    @staticmethod
    def _text_lines(source: Callable[[], str]) -> list[str]:
        return [line for line in source().splitlines() if line]
