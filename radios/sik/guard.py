"""The radio guard: does a SiK radio still run the swarm's parameters? Put them back.

Theory of operation
-------------------
Any radio in range can reconfigure a SiK radio with ``RT`` commands (``RTS3=77``,
``RT&W``, ``RTZ``): the firmware runs them whatever their origin, and MAVLink
signing never sees them (they are the radio's own traffic, not MAVLink). The swarm
cannot stop that on the air; an agent can notice it on its own radio and undo it.

**What is guarded: every register.** Every writable register the radio's ``ATI5``
shows (all but the read-only FORMAT; ENCRYPTION_LEVEL on AES builds; NODEID,
NODEDESTINATION, SYNCANY and NODECOUNT on multipoint) is one a rogue can change and
one the swarm depends on: the ones both ends must share (NETID, AIR_SPEED, ECC,
MIN_FREQ, MAX_FREQ, NUM_CHANNELS, MAX_WINDOW, MANCHESTER, the multipoint node
registers) isolate the radio; the others degrade it without isolating it (TXPOWER,
DUTY_CYCLE and LBT_RSSI silence or weaken it, MAVLINK=0 cuts frames in two and stops
RADIO_STATUS, RTSCTS and SERIAL_SPEED break the serial line, OPPRESEND is harmless
but costs nothing to keep). The user names the values the radio must have
(``--radio-params``); :func:`baseline` completes them with the values the radio
showed at the agent's start check (after any restore) for every other register, and
that full table is what every later check compares.

* Pure part: :func:`parse_expected` reads the expected parameters (``NETID=25,
  AIR_SPEED=64`` or a JSON/TOML file of name -> value) and checks every name and
  value against the firmware's tables before any port is touched;
  :func:`compare` lists what differs from the values a radio reports (``ATI5``,
  i.e. after the boot rewrites: give AIR_SPEED and TXPOWER as the radio shows them);
  :func:`describe` says it in one line; :func:`baseline` builds the full table.
  :class:`CheckSchedule` (fed with ``now``) says when a running agent checks again:
  every ``period_s`` (the radio-check period), and after ``quiet_s`` of hearing no
  one (:class:`RecheckTimer`: a radio moved to another network hears nothing, so
  isolation is the symptom of the changes that isolate).
* I/O part: :func:`check_radio` opens the radio's serial port, enters command mode
  (1 s of silence, ``+++``, 1 s: this interrupts the link, which is why the agent does
  it before its bridge opens the port, or on a port the bridge lends), reads ``ATI5``
  and compares. With ``restore=True`` it writes each differing value (``ATSn=``),
  saves (``AT&W``), reboots (``ATZ``) and reads the parameters back to prove it
  worked. It always leaves the radio in data mode. Given what the start check learnt
  (``known``: the firmware and the number of registers) a re-check skips the probe for
  a radio left in command mode, the banner and the quiet gap after ``ATI5``: the link
  is down about 2.3 s instead of 2.6 s (measured on the emulator).

Not covered: the AES key itself (``AT&E?`` would print it on the serial line; only
ENCRYPTION_LEVEL is compared); a change made and undone between two checks (flash
written with ``RT&W`` then RAM set back: it shows at the next reboot, and a reboot
of a radio moved off the network isolates it); SERIAL_SPEED changed and applied
(``RTZ``) on real hardware: the radio then talks at another baud rate and the check
finds it silent (``radio-check-failed``) until an operator resets it.
"""

from __future__ import annotations

import json
import time
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from radios.errors import ATError, ConfigError, LinkOpenError, RadioError
from radios.seriallink import DEFAULT_BAUD
from radios.sik.config import SERIAL_BAUD, SikConfigurator, open_port
from radios.sik.param_table import FLAVOURS, UNGUARDED, spec_for
from radios.sik.params import validate_user_value
from radios.smallfile import read_small_file
from radios.url import Options, parse_link_url

REBOOT_SETTLE = 0.5  # seconds for a rebooted radio to start before talking to it again


@dataclass(frozen=True)
class Mismatch:
    name: str
    expected: int
    actual: int | None  # None: the radio has no such parameter


@dataclass
class GuardReport:
    """What :func:`check_radio` found and did."""

    mismatches: list[Mismatch]
    restored: bool = False
    values: dict[str, int] = field(default_factory=dict)  # as read (after restoring)
    flavour: str = "standard"  # the radio's firmware

    @property
    def ok(self) -> bool:
        return not self.mismatches or self.restored


@dataclass(frozen=True)
class Known:
    """What the start check learnt of a radio, for quick re-checks: its firmware
    flavour and how many register lines its ``ATI5`` prints."""

    flavour: str
    registers: int


class RecheckTimer:
    """When to re-check an isolated radio: once it has been isolated for ``quiet_s``
    seconds, then every ``quiet_s`` seconds while it stays isolated; hearing anyone
    starts over. Pure: fed with the isolation state and ``now``."""

    def __init__(self, quiet_s: float) -> None:
        if quiet_s <= 0:
            raise ConfigError(f"the radio re-check needs a positive delay, not {quiet_s}")
        self.quiet_s = quiet_s
        self._since: float | None = None

    def update(self, isolated: bool, now: float) -> bool:
        """Returns True when the radio should be checked now."""
        if not isolated:
            self._since = None
            return False
        if self._since is None:
            self._since = now
        if now - self._since >= self.quiet_s:
            self._since = now  # next check after another quiet_s of isolation
            return True
        return False


class CheckSchedule:
    """When a running agent checks its radio again. Pure: fed with ``now``.

    ``period_s`` (0: off) is the radio-check period: a check every ``period_s``
    seconds whatever the radio hears, so that a change that does not isolate the
    radio (TXPOWER, MAVLINK, DUTY_CYCLE...) is found within one period and undone
    within two. ``quiet_s`` (0: off) checks a radio that has heard no other agent for
    that long (:class:`RecheckTimer`). Any check starts the period over. ``first_s``
    (default: one period) is when the first periodic check comes: agents started
    together should not all pause their radios at once (the caller draws it).
    """

    def __init__(self, period_s: float, quiet_s: float, now: float, first_s: float | None = None) -> None:
        if period_s < 0 or quiet_s < 0 or (first_s is not None and first_s < 0):
            raise ConfigError("radio checks need delays of 0 (off) or more seconds")
        self.period_s = period_s
        self.isolation = RecheckTimer(quiet_s) if quiet_s > 0 else None
        first = period_s if first_s is None else first_s
        self._next = now + first if period_s > 0 else None

    @property
    def active(self) -> bool:
        return self._next is not None or self.isolation is not None

    def due(self, isolated: bool, now: float) -> str | None:
        """``"period"`` or ``"isolated"`` when the radio should be checked now, else None."""
        if self.isolation is not None and self.isolation.update(isolated, now):
            self.checked(now)
            return "isolated"
        if self._next is not None and now >= self._next:
            self.checked(now)
            return "period"
        return None

    def checked(self, now: float) -> None:
        """A check ended at ``now``: the next periodic one is a period later."""
        if self.period_s > 0:
            self._next = now + self.period_s


def baseline(expected: Mapping[str, int], values: Mapping[str, int]) -> dict[str, int]:
    """What the guard keeps from now on: ``expected`` (the user's), and for every other
    register the radio reported in ``values`` (all but FORMAT) the value it showed."""
    kept = {name: value for name, value in values.items() if name not in UNGUARDED}
    kept.update(expected)
    return kept


def _canonical(name: str, value: int | str) -> tuple[str, int]:
    """Validate one expected setting against whichever firmware table knows it."""
    errors: list[str] = []
    for flavour in FLAVOURS:
        try:
            spec = spec_for(flavour, name)
        except ConfigError as exc:
            errors.append(str(exc))
            continue
        return spec.name, validate_user_value(flavour, spec.name, value)
    raise ConfigError(errors[0])


def parse_expected(spec: str) -> dict[str, int]:
    """Expected parameters from ``NAME=V[,NAME=V...]`` or the path of a ``.json`` /
    ``.toml`` file holding a table of name -> integer.

    Raises :class:`ConfigError` for a malformed list, an unreadable or malformed file,
    an unknown name, a bad value, or nothing at all to check.
    """
    text = spec.strip()
    raw: Mapping[str, object]
    if "=" in text:
        pairs: dict[str, object] = {}
        for item in text.split(","):
            name, sep, value = item.partition("=")
            if not sep or not name.strip():
                raise ConfigError(f"radio parameters: expected NAME=VALUE, got {item.strip()!r}")
            pairs[name.strip()] = value.strip()
        raw = pairs
    else:
        path = Path(text)
        try:  # a regular file of at most 64 KiB: never a FIFO or a device read for ever
            data = read_small_file(path, 65536)
        except ValueError as exc:
            raise ConfigError(f"radio parameters file {text}: {exc}") from None
        try:
            loaded = tomllib.loads(data.decode()) if path.suffix == ".toml" else json.loads(data)
        except (UnicodeDecodeError, ValueError) as exc:
            raise ConfigError(
                f"radio parameters file {text}: not valid "
                f"{'TOML' if path.suffix == '.toml' else 'JSON'}: {exc}"
            ) from None
        if not isinstance(loaded, dict):
            raise ConfigError(f"radio parameters file {text}: expected a table of NAME = value")
        raw = loaded
    expected: dict[str, int] = {}
    for key, given in raw.items():
        if not isinstance(given, (int, str)) or isinstance(given, bool):
            raise ConfigError(f"radio parameter {key}: {given!r} is not a whole number")
        canonical, number = _canonical(str(key), given)
        expected[canonical] = number
    if not expected:
        raise ConfigError("radio parameters: nothing to check")
    return expected


def compare(expected: Mapping[str, int], actual: Mapping[str, int]) -> list[Mismatch]:
    """Every expected parameter the radio does not report with the expected value."""
    return [
        Mismatch(name, value, actual.get(name))
        for name, value in expected.items()
        if actual.get(name) != value
    ]


def describe(mismatches: list[Mismatch]) -> str:
    """``NETID=77 (expected 25), ENCRYPTION_LEVEL missing (expected 1)``."""
    parts = []
    for m in mismatches:
        got = " missing" if m.actual is None else f"={m.actual}"
        parts.append(f"{m.name}{got} (expected {m.expected})")
    return ", ".join(parts)


def split_radio_url(url: str) -> tuple[str, int]:
    """``serial:/dev/ttyUSB0?baud=115200`` -> (``/dev/ttyUSB0``, 115200); default 57600.
    Parsed with the links' grammar (:func:`radios.url.parse_link_url`).

    Raises :class:`ConfigError` for a URL that is not a local serial device.
    """
    try:
        link = parse_link_url(url)
        if link.scheme != "serial" or "://" in link.target or not link.target:
            raise ConfigError(f"the radio check needs a serial device, not {url!r}")
        baud = Options(link).integer("baud", DEFAULT_BAUD)
    except LinkOpenError as exc:
        raise ConfigError(str(exc)) from None
    if baud <= 0:
        raise ConfigError(f"{url}: bad baud rate {baud}")
    return link.target, baud


def check_radio(
    url: str, expected: Mapping[str, int], *, restore: bool = False, known: Known | None = None
) -> GuardReport:
    """Read the radio on ``url`` and compare it with ``expected``; see the module docstring.
    ``known`` (from an earlier check of the same radio, which a bridge just had in data
    mode) makes the check quicker: no probe, no banner, no quiet gap after ``ATI5``.

    Raises :class:`LinkOpenError` if the port cannot be opened, :class:`ATTimeoutError`
    if the radio does not answer, :class:`ATError` if it refuses a value or still
    differs after restoring, :class:`ConfigError` for a bad URL or expected value.
    """
    path, baud = split_radio_url(url)
    port = open_port(path, baud)
    try:
        conf = SikConfigurator(port, flavour=known.flavour if known else "standard", port_name=path)
        conf.enter_command_mode(probe=known is None)
        try:
            report = _check(conf, expected, restore, known)
        except RadioError:
            if conf.in_command_mode:
                try:
                    conf.exit_command_mode()
                except RadioError:
                    pass
            raise
    finally:
        port.close()
    return report


def known_of(flavour: str, values: Mapping[str, int]) -> Known:
    """What a quick re-check needs of a radio read as ``values`` (its whole ``ATI5``)."""
    return Known(flavour, len(values))


def _check(
    conf: SikConfigurator, expected: Mapping[str, int], restore: bool, known: Known | None
) -> GuardReport:
    if known is None:
        banner = conf.version()
        conf.flavour = "multipoint" if banner.startswith("MP ") else "standard"
        values = conf.read_params()
    else:
        banner = f"{known.flavour} firmware"
        values = conf.read_params(lines=known.registers)
    mismatches = compare(expected, values)
    if not mismatches or not restore:
        conf.exit_command_mode()
        return GuardReport(mismatches, values=values, flavour=conf.flavour)
    missing = [m.name for m in mismatches if m.actual is None]
    if missing:
        conf.exit_command_mode()
        raise ATError(f"the radio ({banner}) has no {', '.join(missing)}: cannot restore")
    # NODECOUNT first: the multipoint firmware refuses a NODEID not below it
    for m in sorted(mismatches, key=lambda m: m.name != "NODECOUNT"):
        conf.set_param(m.name, m.expected)
    conf.save()
    conf.reboot()
    if "SERIAL_SPEED" in expected:
        conf.port.baudrate = SERIAL_BAUD[expected["SERIAL_SPEED"]]
    time.sleep(REBOOT_SETTLE)
    conf.enter_command_mode(probe=False)  # it rebooted into data mode
    values = conf.read_params(lines=known.registers if known else None)
    conf.exit_command_mode()
    still = compare(expected, values)
    if still:
        raise ATError(f"restored and rebooted, but the radio still differs: {describe(still)}")
    return GuardReport(mismatches, restored=True, values=values, flavour=conf.flavour)
