"""SiK radio parameters (S registers) as data: the firmware's tables.

Theory of operation
-------------------
The parameter tables :data:`PARAMS_STANDARD` (SiK 2.2, S0..S15) and
:data:`PARAMS_MULTIPOINT` (SiK multipoint, S0..S18) are plain data: one frozen
:class:`ParamSpec` per register, saying its default, the range a user may ask for,
when a change takes effect (``applies``), what the firmware accepts on ``ATSn=`` and
how the firmware rewrites the value when it is set (``on_set``) and at boot
(``on_boot``, given the radio's :class:`Band`). AES builds of the standard firmware
add :data:`AES_PARAM` (S16 ``ENCRYPTION_LEVEL``). :func:`check_flavour`,
:func:`params_for` and :func:`spec_for` look the tables up with a one-line
:class:`~radios.errors.ConfigError` for an unknown flavour or name.

Only the HM-TRP (Si1000, 20 dBm) board is modelled: TXPOWER is capped at 20 and
rounded to the HM-TRP power levels whatever board an emulated radio claims to be.
What a radio does with these values (its three copies, the host-side checks) is
:mod:`radios.sik.params`'s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from radios.errors import ConfigError

Flavour = Literal["standard", "multipoint"]
Applies = Literal["boot", "now", "readonly"]

FLAVOURS: tuple[Flavour, ...] = ("standard", "multipoint")

PARAM_FORMAT_CURRENT = 26  # 0x1a; S0 of both flavours
UNGUARDED = frozenset({"FORMAT"})  # the radio guard keeps every register but the read-only one
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


def _link_registers(air_speed: int, txpower: int) -> tuple[ParamSpec, ...]:
    """S0-S4: format, serial speed, air speed, network id, power."""
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
    )


def _framing_registers(mavlink_max: int, mavlink: int) -> tuple[ParamSpec, ...]:
    """S5-S7: ECC, MAVLink framing, opportunistic resend."""
    mavlink_set = _bool if mavlink_max == 1 else None
    return (
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
    )


def _band_registers() -> tuple[ParamSpec, ...]:
    """S8-S10: the frequencies and hopping channels (0 = the band's)."""
    return (
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
    )


def _access_registers(rtscts: int) -> tuple[ParamSpec, ...]:
    """S11-S14: duty cycle, listen before talk, Manchester, flow control."""
    return (
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


def _common(
    *,
    air_speed: int,
    txpower: int,
    mavlink_max: int,
    mavlink: int,
    rtscts: int,
) -> tuple[ParamSpec, ...]:
    """S0-S14, the registers both flavours share (with their own defaults)."""
    return (
        *_link_registers(air_speed, txpower),
        *_framing_registers(mavlink_max, mavlink),
        *_band_registers(),
        *_access_registers(rtscts),
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


__all__ = [
    "AES_PARAM",
    "AIR_RATES",
    "AIR_SPEED",
    "BANDS",
    "BOARD_MAX_TXPOWER",
    "BROADCAST",
    "DEFAULT_KEY_BYTE",
    "ENCRYPTION_LEVEL",
    "ENCRYPTION_LEVELS",
    "FLAVOURS",
    "FORMAT",
    "KEY_BYTES",
    "MAX_FREQ",
    "MAX_FREQ_CHANNELS",
    "MIN_FREQ",
    "NETID",
    "NODECOUNT",
    "NODEDESTINATION",
    "NODEID",
    "PARAMS_MULTIPOINT",
    "PARAMS_STANDARD",
    "PARAMS_STANDARD_AES",
    "PARAM_FORMAT_CURRENT",
    "POWER_LEVELS",
    "SERIAL_SPEED",
    "SERIAL_SPEEDS",
    "SYNCANY",
    "TXPOWER",
    "UINT32_MAX",
    "UNGUARDED",
    "Applies",
    "Band",
    "Flavour",
    "ParamSpec",
    "check_flavour",
    "params_for",
    "round_up",
    "spec_for",
]
