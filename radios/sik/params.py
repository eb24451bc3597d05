"""SiK radio parameters: the firmware's three copies of them, and the host's checks.

Theory of operation
-------------------
The registers themselves are data in :mod:`radios.sik.param_table` (one frozen
``ParamSpec`` per S register, with its default, range, when it applies and the
firmware's rewrites); this module says what a radio does with them.

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

from collections.abc import Mapping

from radios.errors import ConfigError
from radios.sik.param_table import (
    BANDS,
    BROADCAST,
    DEFAULT_KEY_BYTE,
    ENCRYPTION_LEVEL,
    ENCRYPTION_LEVELS,
    FORMAT,
    KEY_BYTES,
    MAX_FREQ,
    MIN_FREQ,
    NODECOUNT,
    NODEDESTINATION,
    NODEID,
    PARAM_FORMAT_CURRENT,
    PARAMS_STANDARD_AES,
    Band,
    Flavour,
    ParamSpec,
    check_flavour,
    params_for,
    spec_for,
)


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


__all__ = ["SikParams", "key_length", "validate_key_hex", "validate_user_value"]
