"""SiK radio parameters (S registers) as data, and the firmware's three copies of them.

Theory of operation
-------------------
The parameter tables :data:`PARAMS_STANDARD` (SiK 2.2, S0..S15) and
:data:`PARAMS_MULTIPOINT` (SiK multipoint, S0..S18) are plain data: one frozen
:class:`ParamSpec` per register, saying its default, the range a user may ask for,
when a change takes effect (``applies``), what the firmware accepts on ``ATSn=`` and
how the firmware rewrites the value when it is set (``on_set``) and at boot
(``on_boot``).

A SiK radio keeps every parameter in three places, and :class:`SikParams` models all
three because the difference is visible from the AT interface:

* ``eeprom``: what ``AT&W`` saved to flash (a factory-fresh radio holds the defaults);
* ``ram``: the parameter table. ``ATSn=`` writes it; ``ATSn?`` and ``ATI5`` read it;
* ``active``: what the radio really runs with. At boot (``ATZ``) the firmware copies
  ``eeprom`` into ``ram`` (values that fail the firmware's check revert to the
  default), rewrites some of them (AIR_SPEED rounded up to a supported rate, TXPOWER
  to a power level, 0 frequencies/channels replaced by the band's, ...) so that ``ram``
  shows what the radio really uses, and runs with the result. After boot, ``ATSn=``
  also updates ``active`` at once for the 'now' parameters (TXPOWER, MAVLINK,
  DUTY_CYCLE, LBT_RSSI, RTSCTS, and in multipoint the node parameters); 'boot'
  parameters wait for ``AT&W`` + ``ATZ``. ``AT&F`` puts the defaults into ``ram``
  only: neither flash nor the running radio change until ``AT&W`` / ``ATZ``.

The boot rewrite changes ``ram`` (what ``ATI5`` shows) but not ``eeprom``, exactly like
the firmware: ``ATS2=100``, ``AT&W``, ``ATZ`` leaves 100 in flash and shows 128.

:func:`validate_user_value` is the host-side check run before anything is sent to a
radio. It is stricter than the firmware where the firmware silently clamps (for
example NETID must fit 16 bits, DUTY_CYCLE 0..100) and gives a message that names
the parameter, the value and the accepted range.

Only the HM-TRP (Si1000, 20 dBm) board is modelled: TXPOWER is capped at 20 and
rounded to the HM-TRP power levels whatever board an emulated radio claims to be.

**AES builds** (``SikParams(aes=True)``, standard flavour only). ArduPilot's SiK tree
has AES code behind ``INCLUDE_AES`` (parameters.c/h, at.c, tdm.c, packet.c,
serial.c, freq_hopping.c, AES/aes.c), built only for the RFD900+/RFD900U "e"
boards (Si1030) and switched off for every board since 2021 (commit 85c5ea2, "to
allow code to fit"). Such a build has one more register, S16 ``ENCRYPTION_LEVEL``
(default 0 = off; low nibble 1/2/3 = AES-128/192/256, high nibble 0 = CBC, 1 = CTR;
the firmware checks no value), and a key kept beside the parameters (flash, RAM and
the running copy like the registers): ``AT&E=<hex>`` sets the RAM key, its length
taken from the RAM ENCRYPTION_LEVEL (16/24/32 bytes; too few hex digits set the
default key of 0x62 bytes and still answer OK), ``AT&E?`` prints it, ``AT&W`` saves
it, ``ATZ`` runs with it. :class:`SikParams` keeps the three copies of the key in
``key_eeprom``/``key_ram``/``key_active``; :func:`validate_key_hex` is the host-side
check. The multipoint firmware has no AES at all.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal

from radios.errors import ConfigError

Flavour = Literal["standard", "multipoint"]
Applies = Literal["boot", "now", "readonly"]

FLAVOURS: tuple[Flavour, ...] = ("standard", "multipoint")

PARAM_FORMAT_CURRENT = 26  # 0x1a; S0 of both flavours
UINT32_MAX = 0xFFFF_FFFF  # parameters are uint32 in the firmware
BROADCAST = 0xFFFF  # multipoint NODEDESTINATION meaning "every node"

SERIAL_SPEEDS = (1, 2, 4, 9, 19, 38, 57, 115, 230)  # kbaud codes SERIAL_SPEED accepts
AIR_RATES = (2, 4, 8, 16, 19, 24, 32, 48, 64, 96, 128, 192, 250)  # kbit/s, Si1000
POWER_LEVELS = (1, 2, 5, 8, 11, 14, 17, 20)  # dBm, HM-TRP
BOARD_MAX_TXPOWER = 20  # HM-TRP
MAX_FREQ_CHANNELS = 50

# Standard S registers by name (same numbers in both flavours for S0..S14).
FORMAT, SERIAL_SPEED, AIR_SPEED, NETID, TXPOWER = 0, 1, 2, 3, 4
MIN_FREQ, MAX_FREQ = 8, 9
# Multipoint-only registers.
NODEID, NODEDESTINATION, SYNCANY, NODECOUNT = 15, 16, 17, 18
# AES builds of the standard firmware only (parameters.h, INCLUDE_AES).
ENCRYPTION_LEVEL = 16
KEY_BYTES = 32  # parameters.c keeps a 32-byte key whatever the level
DEFAULT_KEY_BYTE = 0x62  # param_set_default_encryption_key(): 'b' bytes
ENCRYPTION_LEVELS = (0, 1, 2, 3)  # what the host lets a user set (CBC; 0 = off)


@dataclass(frozen=True)
class Band:
    """What a radio's frequency band means for the parameters (frequencies in kHz)."""

    mhz: int
    code: int  # ATI3 answer
    min_freq: int  # MIN_FREQ used when the parameter is 0
    max_freq: int  # MAX_FREQ used when the parameter is 0
    limits: tuple[int, int]  # the range the boot code clamps MIN/MAX_FREQ into
    num_channels: int  # NUM_CHANNELS used when the parameter is 0
    txpower: int  # TXPOWER used when the parameter is 0


BANDS: dict[int, Band] = {
    433: Band(433, 67, 433050, 434790, (414000, 460000), 10, 10),
    470: Band(470, 71, 470000, 471000, (450000, 490000), 10, 10),
    868: Band(868, 134, 868000, 870000, (849000, 889000), 10, 10),
    915: Band(915, 145, 915000, 928000, (868000, 935000), MAX_FREQ_CHANNELS, 20),
}


def _constrain(value: int, low: int, high: int) -> int:
    return max(low, min(high, value))


def round_up(value: int, table: tuple[int, ...]) -> int:
    """The first entry of ascending ``table`` that is >= ``value``, else its last entry."""
    for entry in table:
        if entry >= value:
            return entry
    return table[-1]


def _bool(value: int) -> int:
    return 1 if value else 0


def _txpower_set(value: int) -> int:
    return round_up(value, POWER_LEVELS)


def _txpower_boot(value: int, band: Band) -> int:
    power = value if value else band.txpower
    return round_up(_constrain(power, 1, BOARD_MAX_TXPOWER), POWER_LEVELS)


def _air_boot(value: int, band: Band) -> int:
    return round_up(value, AIR_RATES)


def _duty(value: int) -> int:
    return _constrain(value, 0, 100)


def _duty_boot(value: int, band: Band) -> int:
    return _duty(value)


def _lbt(value: int) -> int:
    return value if value == 0 else _constrain(value, 25, 220)


def _lbt_boot(value: int, band: Band) -> int:
    return _lbt(value)


def _min_freq_boot(value: int, band: Band) -> int:
    return _constrain(value if value else band.min_freq, *band.limits)


def _max_freq_boot(value: int, band: Band) -> int:
    return _constrain(value if value else band.max_freq, *band.limits)


def _channels_boot(value: int, band: Band) -> int:
    return _constrain(value if value else band.num_channels, 1, MAX_FREQ_CHANNELS)


@dataclass(frozen=True)
class ParamSpec:
    """One S register.

    ``minimum``..``maximum`` (and ``allowed`` when set) is the range a user may ask
    for. ``strict`` says the firmware itself answers ERROR above ``maximum``; when it
    is False the firmware accepts any 32-bit value and clamps it (``on_set`` /
    ``on_boot``) or ignores the excess. ``on_set`` is the rewrite ``ATSn=`` applies
    before storing; ``on_boot`` the rewrite applied at boot (it gets the band).
    """

    index: int
    name: str
    default: int
    minimum: int
    maximum: int
    applies: Applies
    doc: str
    allowed: frozenset[int] | None = None
    strict: bool = True
    on_set: Callable[[int], int] | None = None
    on_boot: Callable[[int, Band], int] | None = None

    def firmware_accepts(self, value: int) -> bool:
        """Whether the firmware's own check lets ``ATSn=value`` through (cross-parameter
        checks of the multipoint node registers are in :meth:`SikParams.set`)."""
        if self.applies == "readonly" or not 0 <= value <= UINT32_MAX:
            return False
        if self.allowed is not None:
            return value in self.allowed
        return not self.strict or value <= self.maximum

    def describe_range(self) -> str:
        if self.allowed is not None:
            return "one of " + ", ".join(str(v) for v in sorted(self.allowed))
        return f"{self.minimum}..{self.maximum}"


def _common(
    *,
    air_speed: int,
    txpower: int,
    mavlink_max: int,
    mavlink: int,
    rtscts: int,
) -> tuple[ParamSpec, ...]:
    mavlink_set = _bool if mavlink_max == 1 else None
    return (
        ParamSpec(
            FORMAT,
            "FORMAT",
            PARAM_FORMAT_CURRENT,
            PARAM_FORMAT_CURRENT,
            PARAM_FORMAT_CURRENT,
            "readonly",
            "parameter format version (read-only)",
        ),
        ParamSpec(
            SERIAL_SPEED,
            "SERIAL_SPEED",
            57,
            1,
            230,
            "boot",
            "serial speed in kbaud (57 = 57600)",
            allowed=frozenset(SERIAL_SPEEDS),
        ),
        ParamSpec(
            AIR_SPEED,
            "AIR_SPEED",
            air_speed,
            0,
            256,
            "boot",
            "air data rate in kbit/s; rounded up at boot to one of " + ", ".join(map(str, AIR_RATES)),
            on_boot=_air_boot,
        ),
        ParamSpec(
            NETID, "NETID", 25, 0, 0xFFFF, "boot", "network id (16 bits); both ends must match", strict=False
        ),
        ParamSpec(
            TXPOWER,
            "TXPOWER",
            txpower,
            0,
            BOARD_MAX_TXPOWER,
            "now",
            "transmit power in dBm; rounded up to one of " + ", ".join(map(str, POWER_LEVELS)),
            on_set=_txpower_set,
            on_boot=_txpower_boot,
        ),
        ParamSpec(5, "ECC", 0, 0, 1, "boot", "error-correcting code (0/1)"),
        ParamSpec(
            6,
            "MAVLINK",
            mavlink,
            0,
            mavlink_max,
            "now",
            "MAVLink framing (0 raw, 1 framing" + (", 2 same as 1)" if mavlink_max == 2 else ")"),
            on_set=mavlink_set,
        ),
        ParamSpec(
            7, "OPPRESEND", 0, 0, 1, "now", "opportunistic resend (0/1; no effect since 2.0)", on_set=_bool
        ),
        ParamSpec(
            MIN_FREQ,
            "MIN_FREQ",
            0,
            0,
            1_000_000,
            "boot",
            "lowest frequency in kHz (0 = band default; clamped to the band at boot)",
            strict=False,
            on_boot=_min_freq_boot,
        ),
        ParamSpec(
            MAX_FREQ,
            "MAX_FREQ",
            0,
            0,
            1_000_000,
            "boot",
            "highest frequency in kHz (0 = band default; clamped to the band at boot)",
            strict=False,
            on_boot=_max_freq_boot,
        ),
        ParamSpec(
            10,
            "NUM_CHANNELS",
            0,
            0,
            MAX_FREQ_CHANNELS,
            "boot",
            "hopping channels (0 = band default; clamped to 1..50 at boot)",
            strict=False,
            on_boot=_channels_boot,
        ),
        ParamSpec(
            11,
            "DUTY_CYCLE",
            100,
            0,
            100,
            "now",
            "transmit duty cycle in percent",
            strict=False,
            on_set=_duty,
            on_boot=_duty_boot,
        ),
        ParamSpec(
            12,
            "LBT_RSSI",
            0,
            0,
            220,
            "now",
            "listen-before-talk threshold (0 = off; non-zero clamped to 25..220)",
            strict=False,
            on_set=_lbt,
            on_boot=_lbt_boot,
        ),
        ParamSpec(
            13,
            "MANCHESTER",
            0,
            0,
            1,
            "boot",
            "Manchester encoding (0/1; ignored above 128 kbit/s)",
            strict=False,
        ),
        ParamSpec(
            14, "RTSCTS", rtscts, 0, 1, "now", "hardware flow control (0/1)", strict=False, on_set=_bool
        ),
    )


PARAMS_STANDARD: tuple[ParamSpec, ...] = (
    *_common(air_speed=64, txpower=20, mavlink_max=2, mavlink=1, rtscts=0),
    ParamSpec(15, "MAX_WINDOW", 131, 0, 131, "boot", "longest transmit window in ms (33 for low latency)"),
)

PARAMS_MULTIPOINT: tuple[ParamSpec, ...] = (
    *_common(air_speed=128, txpower=0, mavlink_max=1, mavlink=0, rtscts=1),
    ParamSpec(
        NODEID,
        "NODEID",
        1,
        0,
        0x7FFF,
        "now",
        "this node's id (0 = base, which keeps sync); unique, below NODECOUNT",
        strict=False,
    ),
    ParamSpec(
        NODEDESTINATION,
        "NODEDESTINATION",
        BROADCAST,
        0,
        BROADCAST,
        "now",
        "destination node id (65535 = broadcast); not this node, below NODECOUNT",
        strict=False,
    ),
    ParamSpec(SYNCANY, "SYNCANY", 0, 0, 1, "now", "sync from any node, not only the base (0/1)"),
    ParamSpec(
        NODECOUNT,
        "NODECOUNT",
        2,
        2,
        0x8000,
        "now",
        "number of nodes in the network (= highest node id + 1)",
        strict=False,
    ),
)


AES_PARAM = ParamSpec(
    ENCRYPTION_LEVEL,
    "ENCRYPTION_LEVEL",
    0,
    0,
    3,
    "boot",
    "AES encryption (0 off, 1 AES-128, 2 AES-192, 3 AES-256; only on firmware built "
    "with AES); the key is set with AT&E (swarm radio-config --aes-key)",
    strict=False,
)

PARAMS_STANDARD_AES: tuple[ParamSpec, ...] = (*PARAMS_STANDARD, AES_PARAM)


def key_length(level: int) -> int:
    """Key bytes for an ENCRYPTION_LEVEL (aes.h's AES_KEY_LENGTH: 8 * (1 + low nibble))."""
    return 8 * (1 + (level & 0xF))


def validate_key_hex(level: int, key: str) -> bytes:
    """Check a key a user gives for ENCRYPTION_LEVEL ``level``; return its bytes.

    The key must be exactly ``2 * key_length(level)`` hex digits (the firmware would
    silently take the default key for fewer and ignore extra digits). The message
    never repeats the key. Raises :class:`ConfigError`.
    """
    if level not in ENCRYPTION_LEVELS or level == 0:
        raise ConfigError(f"a key needs ENCRYPTION_LEVEL 1, 2 or 3, not {level}")
    text = key.strip()
    want = 2 * key_length(level)
    if len(text) != want:
        raise ConfigError(
            f"the key for ENCRYPTION_LEVEL={level} must be {want} hex digits "
            f"({want * 4} bits), got {len(text)} characters"
        )
    if not all(c in "0123456789abcdefABCDEF" for c in text):
        raise ConfigError("the key must contain hex digits only (0-9, a-f)")
    return bytes.fromhex(text)


def _hex_nibble(c: str) -> int:
    """parameters.c's read_hex_nibble: a hex digit's value, 0 for anything else."""
    return int(c, 16) if c in "0123456789abcdefABCDEF" else 0


def check_flavour(flavour: str) -> Flavour:
    """Return ``flavour`` if it names a firmware flavour; raise :class:`ConfigError` if not."""
    for known in FLAVOURS:
        if flavour == known:
            return known
    raise ConfigError(f"unknown SiK firmware flavour {flavour!r}: use standard or multipoint")


def params_for(flavour: str) -> tuple[ParamSpec, ...]:
    """The parameter table of a firmware flavour. Raises :class:`ConfigError` if unknown."""
    return PARAMS_STANDARD if check_flavour(flavour) == "standard" else PARAMS_MULTIPOINT


def spec_for(flavour: str, name: str) -> ParamSpec:
    """The :class:`ParamSpec` called ``name`` (case-insensitive).

    Raises :class:`ConfigError` for an unknown flavour or name.
    """
    specs = params_for(flavour)
    wanted = name.strip().upper()
    for spec in specs:
        if spec.name == wanted:
            return spec
    if flavour == "standard" and wanted == AES_PARAM.name:
        return AES_PARAM  # exists only on AES builds; the radio's ATI5 decides
    hint = ""
    if flavour == "standard" and any(s.name == wanted for s in PARAMS_MULTIPOINT):
        hint = " (it is a multipoint parameter: use the multipoint firmware flavour)"
    elif flavour == "multipoint" and any(s.name == wanted for s in PARAMS_STANDARD):
        hint = " (multipoint firmware has no such parameter)"
    known = ", ".join(s.name for s in specs if s.applies != "readonly")
    raise ConfigError(f"unknown {flavour} SiK parameter {name!r}{hint}; known: {known}")


def validate_user_value(flavour: str, name: str, value: int | str) -> int:
    """Check a value a user wants to give parameter ``name``; return it as an int.

    ``value`` may be an int or a decimal string (as typed on a command line).
    Raises :class:`ConfigError` for an unknown flavour or name, the read-only FORMAT,
    a value that is not a whole number, or one outside the parameter's range.
    """
    spec = spec_for(flavour, name)
    if spec.applies == "readonly":
        raise ConfigError(f"{spec.name} is read-only")
    if isinstance(value, bool):
        raise ConfigError(f"{spec.name}: {value!r} is not a whole number")
    if isinstance(value, str):
        text = value.strip()
        digits = text[1:] if text[:1] in "+-" else text
        if not digits.isdigit() or not digits.isascii():
            raise ConfigError(f"{spec.name}: {value!r} is not a whole number")
        number = int(text)
    else:
        number = int(value)
    if spec.allowed is not None:
        if number not in spec.allowed:
            raise ConfigError(
                f"{spec.name}={number} is not accepted: use {spec.describe_range()}. {spec.name}: {spec.doc}"
            )
    elif not spec.minimum <= number <= spec.maximum:
        raise ConfigError(
            f"{spec.name}={number} is out of range {spec.describe_range()}. {spec.name}: {spec.doc}"
        )
    return number


class SikParams:
    """The parameters of one radio: ``eeprom`` (saved), ``ram`` (the table AT commands
    read and write) and ``active`` (what the radio runs with), each a map from S
    register number to value. A new instance has booted from ``eeprom``.

    ``stored`` seeds ``eeprom`` by parameter name (a radio configured earlier).
    ``aes`` models a firmware built with AES (S16 ENCRYPTION_LEVEL and a key;
    ``stored_key`` seeds the key in flash). Raises :class:`ConfigError` for an unknown
    flavour or band, a bad ``stored`` value, or AES asked of the multipoint firmware.
    """

    def __init__(
        self,
        flavour: str = "standard",
        *,
        band: int = 915,
        stored: Mapping[str, int] | None = None,
        aes: bool = False,
        stored_key: bytes | None = None,
    ) -> None:
        self.flavour: Flavour = check_flavour(flavour)
        if aes and self.flavour != "standard":
            raise ConfigError("the multipoint SiK firmware has no AES encryption")
        self.aes = aes
        self.specs: tuple[ParamSpec, ...] = PARAMS_STANDARD_AES if aes else params_for(self.flavour)
        # the key: flash, RAM (AT&E=) and running copies, like the registers
        self.key_eeprom = (
            (bytes(stored_key) + bytes(KEY_BYTES))[:KEY_BYTES] if stored_key else bytes(KEY_BYTES)
        )
        self.key_ram = self.key_eeprom
        self.key_active = self.key_eeprom
        if band not in BANDS:
            raise ConfigError(f"unknown band {band} MHz: use one of " + ", ".join(str(b) for b in BANDS))
        self.band: Band = BANDS[band]
        self.eeprom: dict[int, int] = self.defaults()
        for name, value in (stored or {}).items():
            spec = spec_for(self.flavour, name)
            if spec.index >= len(self.specs) or self.specs[spec.index] is not spec:
                raise ConfigError(f"{spec.name} exists only on firmware built with AES")
            self.eeprom[spec.index] = validate_user_value(self.flavour, name, value)
        self.ram: dict[int, int] = {}
        self.active: dict[int, int] = {}
        self.boot()

    # -- lookups ---------------------------------------------------------------

    def defaults(self) -> dict[int, int]:
        return {spec.index: spec.default for spec in self.specs}

    def by_name(self, name: str) -> ParamSpec:
        """The spec of parameter ``name``; raises :class:`ConfigError` if unknown."""
        return spec_for(self.flavour, name)

    def spec(self, index: int) -> ParamSpec:
        """The spec of S register ``index``; raises :class:`ConfigError` if out of table."""
        if not 0 <= index < len(self.specs):
            raise ConfigError(
                f"no S{index} in the {self.flavour} parameter table (S0..S{len(self.specs) - 1})"
            )
        return self.specs[index]

    def get(self, index: int) -> int:
        """The RAM value of S register ``index`` (what ``ATSn?`` answers).

        Raises :class:`ConfigError` if ``index`` is out of table.
        """
        return self.ram[self.spec(index).index]

    def active_value(self, name: str) -> int:
        """The value the radio runs with; raises :class:`ConfigError` for an unknown name."""
        return self.active[self.by_name(name).index]

    def as_dict(self) -> dict[str, int]:
        """Parameter name -> RAM value, in register order (what ``ATI5`` shows)."""
        return {spec.name: self.ram[spec.index] for spec in self.specs}

    # -- the firmware's operations ----------------------------------------------

    def set(self, index: int, value: int) -> bool:
        """``ATSn=value``. Returns False where the firmware answers ERROR: S0, a register
        out of table, or a value the firmware rejects. Otherwise the rewritten value
        goes to ``ram`` and, for a 'now' parameter, to ``active`` too."""
        if not 0 < index < len(self.specs):
            return False
        spec = self.specs[index]
        if not spec.firmware_accepts(value) or not self._cross_ok(index, value, self.ram):
            return False
        if spec.on_set is not None:
            value = spec.on_set(value)
        self.ram[index] = value
        if spec.applies == "now":
            self.active[index] = value
        return True

    def save(self) -> None:
        """``AT&W``: RAM to flash, tagged with the current format (and the key, on AES
        builds)."""
        self.eeprom = dict(self.ram)
        self.eeprom[FORMAT] = PARAM_FORMAT_CURRENT
        self.key_eeprom = self.key_ram

    # -- AES builds ---------------------------------------------------------------

    def set_key(self, hex_digits: str) -> bool:
        """``AT&E=hex``: set the RAM key (param_set_encryption_key). Its length comes
        from the RAM ENCRYPTION_LEVEL; fewer digits than that set the default key and
        return False (the firmware prints an error line, then OK); extra digits are
        ignored; a non-hex digit reads as 0."""
        length = min(key_length(self.ram.get(ENCRYPTION_LEVEL, 0)), KEY_BYTES)
        if len(hex_digits) < 2 * length:
            key = bytes([DEFAULT_KEY_BYTE]) * length
            ok = False
        else:
            key = bytes(
                _hex_nibble(hex_digits[2 * i]) << 4 | _hex_nibble(hex_digits[2 * i + 1])
                for i in range(length)
            )
            ok = True
        self.key_ram = key + self.key_ram[length:]
        return ok

    def key_hex(self) -> str:
        """``AT&E?``: the RAM key in lower-case hex, as many bytes as the RAM level says."""
        return self.key_ram[: min(key_length(self.ram.get(ENCRYPTION_LEVEL, 0)), KEY_BYTES)].hex()

    def active_key(self) -> bytes:
        """The key the radio encrypts with, or b'' when it runs without encryption."""
        if not self.aes or self.active.get(ENCRYPTION_LEVEL, 0) & 0xF == 0:
            return b""
        return self.key_active[: key_length(self.active[ENCRYPTION_LEVEL])]

    def factory_reset(self) -> None:
        """``AT&F``: defaults into RAM only (flash and the running radio are unchanged)."""
        self.ram = self.defaults()

    def boot(self) -> None:
        """Power-on or ``ATZ``: load flash into RAM (invalid values revert to their
        default), apply the boot rewrites to RAM and run with the result."""
        ram = dict(self.eeprom)
        for spec in self.specs:
            value = ram[spec.index]  # FORMAT is read-only: firmware_accepts() is False
            if not spec.firmware_accepts(value) or not self._cross_ok(spec.index, value, ram):
                ram[spec.index] = spec.default
        for spec in self.specs:
            if spec.on_boot is not None:
                ram[spec.index] = spec.on_boot(ram[spec.index], self.band)
        if ram[MAX_FREQ] == ram[MIN_FREQ]:
            ram[MAX_FREQ] = ram[MIN_FREQ] + 1000
        self.ram = ram
        self.active = dict(ram)
        self.key_ram = self.key_active = self.key_eeprom

    def _cross_ok(self, index: int, value: int, table: Mapping[int, int]) -> bool:
        """The multipoint firmware's checks that involve other registers."""
        if self.flavour != "multipoint":
            return True
        if index == NODEID:
            return value < table[NODECOUNT]
        if index == NODEDESTINATION:
            if value == BROADCAST:
                return True
            return value != table[NODEID] and value < table[NODECOUNT]
        return True
