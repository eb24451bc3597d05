"""The SiK parameter tables, the eeprom/ram/active model and user-value validation."""

from __future__ import annotations

import pytest

from radios.errors import ConfigError
from radios.sik.param_table import (
    AIR_RATES,
    BROADCAST,
    PARAMS_MULTIPOINT,
    PARAMS_STANDARD,
    POWER_LEVELS,
    SERIAL_SPEEDS,
    params_for,
    round_up,
    spec_for,
)
from radios.sik.params import SikParams, validate_user_value

STANDARD_DEFAULTS = {
    "FORMAT": 26,
    "SERIAL_SPEED": 57,
    "AIR_SPEED": 64,
    "NETID": 25,
    "TXPOWER": 20,
    "ECC": 0,
    "MAVLINK": 1,
    "OPPRESEND": 0,
    "MIN_FREQ": 0,
    "MAX_FREQ": 0,
    "NUM_CHANNELS": 0,
    "DUTY_CYCLE": 100,
    "LBT_RSSI": 0,
    "MANCHESTER": 0,
    "RTSCTS": 0,
    "MAX_WINDOW": 131,
}


# -- the tables --------------------------------------------------------------------------


def test_standard_table_matches_sik_2_2() -> None:
    assert [s.index for s in PARAMS_STANDARD] == list(range(16))
    assert {s.name: s.default for s in PARAMS_STANDARD} == STANDARD_DEFAULTS
    applies = {s.name: s.applies for s in PARAMS_STANDARD}
    assert applies["FORMAT"] == "readonly"
    assert {n for n, a in applies.items() if a == "now"} == {
        "TXPOWER",
        "MAVLINK",
        "OPPRESEND",
        "DUTY_CYCLE",
        "LBT_RSSI",
        "RTSCTS",
    }


def test_multipoint_table() -> None:
    names = [s.name for s in PARAMS_MULTIPOINT]
    assert names[:15] == [s.name for s in PARAMS_STANDARD][:15]
    assert names[15:] == ["NODEID", "NODEDESTINATION", "SYNCANY", "NODECOUNT"]
    assert "MAX_WINDOW" not in names
    defaults = {s.name: s.default for s in PARAMS_MULTIPOINT}
    assert defaults["AIR_SPEED"] == 128
    assert defaults["MAVLINK"] == 0
    assert defaults["RTSCTS"] == 1
    assert defaults["NODEDESTINATION"] == BROADCAST
    assert defaults["NODECOUNT"] > defaults["NODEID"]


def test_params_for_and_spec_for() -> None:
    assert params_for("standard") is PARAMS_STANDARD
    assert params_for("multipoint") is PARAMS_MULTIPOINT
    assert spec_for("standard", "air_speed").index == 2
    with pytest.raises(ConfigError, match="flavour"):
        params_for("rfd")


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (0, 2),
        (1, 2),
        (2, 2),
        (3, 4),
        (17, 19),
        (20, 24),
        (64, 64),
        (65, 96),
        (100, 128),
        (129, 192),
        (200, 250),
        (250, 250),
        (256, 250),
    ],
)
def test_air_speed_rounded_up_at_boot(value: int, expected: int) -> None:
    p = SikParams()
    assert p.set(2, value)
    assert p.ram[2] == value and p.active[2] == 64  # boot parameter: not active yet
    p.save()
    p.boot()
    assert p.ram[2] == expected
    assert p.active[2] == expected
    assert p.eeprom[2] == value  # the firmware rewrites RAM, not flash


def test_round_up_table_end() -> None:
    assert round_up(999, AIR_RATES) == 250
    assert round_up(19, POWER_LEVELS) == 20


# -- SikParams -------------------------------------------------------------------------


def test_fresh_radio_shows_band_values_after_boot() -> None:
    p = SikParams()
    values = p.as_dict()
    assert list(values) == list(STANDARD_DEFAULTS)
    assert values["MIN_FREQ"] == 915000
    assert values["MAX_FREQ"] == 928000
    assert values["NUM_CHANNELS"] == 50
    assert p.eeprom[8] == 0 and p.eeprom[10] == 0
    assert p.active == p.ram


def test_other_band() -> None:
    p = SikParams(band=433)
    assert p.as_dict()["MIN_FREQ"] == 433050
    assert p.as_dict()["MAX_FREQ"] == 434790
    assert p.as_dict()["NUM_CHANNELS"] == 10
    with pytest.raises(ConfigError, match="band"):
        SikParams(band=2400)


def test_set_rejects_like_the_firmware() -> None:
    p = SikParams()
    assert not p.set(0, 26)  # FORMAT is read-only
    assert not p.set(16, 1)  # out of table
    assert not p.set(-1, 1)
    assert not p.set(2, 257)  # AIR_SPEED > 256
    assert not p.set(4, 21)  # TXPOWER above the board's 20 dBm
    assert not p.set(5, 2)  # ECC is 0/1
    assert not p.set(6, 3)  # MAVLINK 0..2
    assert not p.set(15, 132)  # MAX_WINDOW <= 131
    assert not p.set(3, 2**32)  # parameters are uint32
    assert p.as_dict()["AIR_SPEED"] == 64


@pytest.mark.parametrize("speed", SERIAL_SPEEDS)
def test_serial_speed_accepted(speed: int) -> None:
    assert SikParams().set(1, speed)


@pytest.mark.parametrize("speed", [0, 3, 56, 58, 96, 231])
def test_serial_speed_rejected(speed: int) -> None:
    assert not SikParams().set(1, speed)


@pytest.mark.parametrize(("value", "stored"), [(0, 1), (1, 1), (3, 5), (9, 11), (20, 20)])
def test_txpower_applies_now_rounded_up(value: int, stored: int) -> None:
    p = SikParams()
    assert p.set(4, value)
    assert p.ram[4] == stored
    assert p.active[4] == stored  # 'now': the radio already uses it
    assert p.eeprom[4] == 20


def test_now_params_clamp_on_set() -> None:
    p = SikParams()
    assert p.set(11, 150) and p.ram[11] == 100 and p.active[11] == 100  # DUTY_CYCLE
    assert p.set(12, 10) and p.ram[12] == 25  # LBT_RSSI non-zero low
    assert p.set(12, 250) and p.ram[12] == 220
    assert p.set(12, 0) and p.ram[12] == 0
    assert p.set(14, 5) and p.ram[14] == 1 and p.active[14] == 1  # RTSCTS -> bool
    assert p.set(6, 2) and p.active[6] == 2


def test_boot_params_wait_for_save_and_reboot() -> None:
    p = SikParams()
    assert p.set(3, 77)  # NETID: boot
    assert p.ram[3] == 77 and p.active[3] == 25
    p.boot()  # ATZ without AT&W: the change is lost
    assert p.ram[3] == 25
    assert p.set(3, 77)
    p.save()
    p.boot()
    assert p.active[3] == 77 and p.eeprom[3] == 77


def test_channels_and_frequencies_at_boot() -> None:
    p = SikParams()
    assert p.set(10, 60)  # firmware accepts it; boot clamps
    assert p.set(8, 100)  # far below the band: clamped to the board's range
    assert p.set(9, 920000)
    p.save()
    p.boot()
    assert p.ram[10] == 50
    assert p.ram[8] == 868000
    assert p.ram[9] == 920000


def test_equal_frequencies_get_one_mhz() -> None:
    p = SikParams()
    p.set(8, 920000)
    p.set(9, 920000)
    p.save()
    p.boot()
    assert (p.ram[8], p.ram[9]) == (920000, 921000)


def test_factory_reset_touches_ram_only() -> None:
    p = SikParams()
    p.set(4, 11)
    p.set(2, 128)
    p.save()
    p.boot()
    p.factory_reset()
    assert p.ram[2] == 64 and p.ram[8] == 0  # defaults, before the boot rewrite
    assert p.ram[4] == 20
    assert p.active[2] == 128 and p.active[4] == 11
    assert p.eeprom[2] == 128
    p.save()
    p.boot()
    assert p.active[2] == 64 and p.active[8] == 915000


def test_boot_reverts_invalid_flash_values() -> None:
    p = SikParams()
    p.eeprom[1] = 56  # not a serial speed: the firmware's load check resets it
    p.eeprom[0] = 99
    p.boot()
    assert p.ram[1] == 57 and p.ram[0] == 26


def test_get_by_name_and_errors() -> None:
    p = SikParams()
    assert p.get(2) == 64
    assert p.by_name("netid").index == 3
    assert p.active_value("AIR_SPEED") == 64
    assert p.spec(15).name == "MAX_WINDOW"
    with pytest.raises(ConfigError, match="S16"):
        p.get(16)
    with pytest.raises(ConfigError, match="unknown"):
        p.by_name("NODEID")


def test_stored_seeds_flash() -> None:
    p = SikParams(stored={"AIR_SPEED": 100, "netid": 7})
    assert p.eeprom[2] == 100
    assert p.as_dict()["AIR_SPEED"] == 128
    assert p.as_dict()["NETID"] == 7
    with pytest.raises(ConfigError):
        SikParams(stored={"AIR_SPEED": 999})


def test_unknown_flavour() -> None:
    with pytest.raises(ConfigError, match="flavour"):
        SikParams("rfd")


# -- multipoint ------------------------------------------------------------------------


def test_multipoint_defaults_after_boot() -> None:
    p = SikParams("multipoint")
    values = p.as_dict()
    assert values["TXPOWER"] == 20  # 0 means the band's default power
    assert values["AIR_SPEED"] == 128
    assert len(values) == 19
    assert not p.set(6, 2)  # MAVLINK is 0/1 in multipoint
    assert p.set(6, 1)


def test_multipoint_node_checks() -> None:
    p = SikParams("multipoint")  # NODEID 1, NODECOUNT 2
    assert not p.set(15, 2)  # NODEID must be below NODECOUNT
    assert p.set(18, 5)
    assert p.set(15, 3) and p.active[15] == 3  # node parameters apply now
    assert not p.set(16, 3)  # NODEDESTINATION may not be this node
    assert not p.set(16, 5)  # ... nor at/above NODECOUNT
    assert p.set(16, 4)
    assert p.set(16, BROADCAST)
    assert p.set(17, 1) and not p.set(17, 2)


def test_multipoint_boot_reverts_node_beyond_count() -> None:
    p = SikParams("multipoint")
    p.set(18, 5)
    p.set(15, 4)
    p.save()
    p.eeprom[18] = 3  # NODEID 4 no longer fits: the load check resets it
    p.boot()
    assert p.ram[15] == 1


# -- validate_user_value ---------------------------------------------------------------


def test_validate_accepts_and_converts() -> None:
    assert validate_user_value("standard", "air_speed", "128") == 128
    assert validate_user_value("standard", "NETID", 65535) == 65535
    assert validate_user_value("multipoint", "NODEID", " 3 ") == 3
    assert validate_user_value("standard", "SERIAL_SPEED", 115) == 115


@pytest.mark.parametrize(
    ("flavour", "name", "value", "message"),
    [
        ("standard", "BOGUS", 1, "unknown standard SiK parameter 'BOGUS'"),
        ("standard", "NODEID", 1, "multipoint parameter"),
        ("multipoint", "MAX_WINDOW", 33, "multipoint firmware has no such parameter"),
        ("standard", "FORMAT", 26, "read-only"),
        ("standard", "NETID", "x", "not a whole number"),
        ("standard", "NETID", "1.5", "not a whole number"),
        ("standard", "NETID", True, "not a whole number"),
        ("standard", "NETID", 65536, r"NETID=65536 is out of range 0\.\.65535"),
        ("standard", "AIR_SPEED", 300, r"AIR_SPEED=300 is out of range 0\.\.256"),
        ("standard", "AIR_SPEED", -1, "out of range"),
        ("standard", "TXPOWER", 30, r"0\.\.20"),
        ("standard", "SERIAL_SPEED", 56, "use one of 1, 2, 4, 9, 19, 38, 57, 115, 230"),
        ("standard", "DUTY_CYCLE", 101, "out of range"),
        ("multipoint", "NODECOUNT", 1, "out of range"),
        ("rfd", "NETID", 1, "flavour"),
    ],
)
def test_validate_rejects_with_clear_message(flavour: str, name: str, value: int | str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        validate_user_value(flavour, name, value)
