"""The network plan (radios/sik/network.py): what one radio of N needs, checked per firmware."""

from __future__ import annotations

from pathlib import Path

import pytest

from radios.errors import ConfigError
from radios.sik.guard import parse_expected
from radios.sik.network import (
    NetworkPlan,
    agent_params,
    band_of,
    differences,
    expected_readback,
    params_text,
    plan_settings,
)
from radios.sik.param_table import BANDS


def test_multipoint_plan_writes_the_node_registers_first() -> None:
    settings = plan_settings(NetworkPlan(10, 7, 30), "multipoint")
    assert settings == {
        "NODECOUNT": 10,
        "NODEID": 7,
        "NODEDESTINATION": 65535,
        "NETID": 30,
        "AIR_SPEED": 64,
        "SERIAL_SPEED": 57,
        "ECC": 0,
        "MAVLINK": 1,
    }
    assert list(settings)[:2] == ["NODECOUNT", "NODEID"]  # NODEID must be below the NODECOUNT in RAM


def test_the_same_plan_differs_only_in_the_node() -> None:
    plans = [plan_settings(NetworkPlan(3, i, 30, 128, 115200, 1), "multipoint") for i in range(3)]
    assert [p.pop("NODEID") for p in plans] == [0, 1, 2]
    assert plans[0] == plans[1] == plans[2]
    assert plans[0]["SERIAL_SPEED"] == 115 and plans[0]["AIR_SPEED"] == 128 and plans[0]["ECC"] == 1


def test_standard_firmware_pairs_only() -> None:
    assert "NODEID" not in plan_settings(NetworkPlan(2, 1, 30), "standard")
    with pytest.raises(ConfigError, match="standard SiK firmware, which links two radios"):
        plan_settings(NetworkPlan(3, 1, 30), "standard")


@pytest.mark.parametrize(
    ("plan", "message"),
    [
        (NetworkPlan(1, 0, 30), "--network 1: a network has 2.."),
        (NetworkPlan(3, 3, 30), r"--node 3: the nodes of a 3-radio network are 0..2"),
        (NetworkPlan(3, -1, 30), "--node -1"),
        (NetworkPlan(3, 0, 70000), "NETID=70000 is out of range"),
        (NetworkPlan(3, 0, 30, air_speed=999), "AIR_SPEED=999 is out of range"),
        (NetworkPlan(3, 0, 30, serial_baud=56000), "--serial-speed 56000: one of"),
        (NetworkPlan(3, 0, 30, ecc=2), "ECC=2 is out of range"),
    ],
)
def test_bad_plans_are_refused_in_one_line(plan: NetworkPlan, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as info:
        plan.check()
    assert "\n" not in str(info.value)


def test_extra_settings_are_checked_against_the_radios_firmware() -> None:
    plan = NetworkPlan(3, 1, 30)
    with pytest.raises(ConfigError, match="multipoint firmware has no such parameter"):
        plan_settings(plan, "multipoint", {"MAX_WINDOW": 33})
    with pytest.raises(ConfigError, match="--set NETID: the network options already set it"):
        plan_settings(plan, "multipoint", {"netid": 31})
    assert plan_settings(NetworkPlan(2, 0, 30), "standard", {"MAX_WINDOW": 33})["MAX_WINDOW"] == 33
    with pytest.raises(ConfigError, match="TXPOWER=99 is out of range"):
        plan_settings(plan, "multipoint", {"TXPOWER": 99})


def test_expected_readback_follows_the_firmwares_rewrites() -> None:
    band = band_of("145")
    assert band is BANDS[915]
    assert band_of("12") is None and band_of("") is None
    settings = {"AIR_SPEED": 100, "TXPOWER": 10, "NUM_CHANNELS": 0, "NETID": 30}
    assert expected_readback("standard", settings, band) == {
        "AIR_SPEED": 128,
        "TXPOWER": 11,
        "NUM_CHANNELS": 50,
        "NETID": 30,
    }
    # band unknown: the band-dependent registers are not compared
    assert expected_readback("standard", settings, None) == {"AIR_SPEED": 128, "NETID": 30}
    # before the reboot (a remote radio): only the rewrite on set
    assert expected_readback("standard", settings, band, booted=False) == {
        "AIR_SPEED": 100,
        "TXPOWER": 11,
        "NUM_CHANNELS": 0,
        "NETID": 30,
    }


def test_differences_one_line_per_register() -> None:
    assert differences({"NETID": 30, "ECC": 0}, {"NETID": 30, "ECC": 0}) == []
    assert differences({"NETID": 30, "NODEID": 2}, {"NETID": 25}) == [
        "NETID: the radio shows 25, expected 30",
        "NODEID: not read back (expected 2)",
    ]


def test_agent_params_round_trip_through_the_guard(tmp_path: Path) -> None:
    values = {"FORMAT": 26, "SERIAL_SPEED": 57, "AIR_SPEED": 64, "NETID": 30, "TXPOWER": 20, "ECC": 0}
    values |= {"MAVLINK": 1, "NODEID": 2, "NODEDESTINATION": 65535, "NODECOUNT": 3}
    values |= {"NUM_CHANNELS": 50}
    params = agent_params(values)
    assert "FORMAT" not in params and params["TXPOWER"] == 20 and params["NODEID"] == 2
    line = params_text(params, "line")
    assert line == (
        "SERIAL_SPEED=57,AIR_SPEED=64,NETID=30,TXPOWER=20,ECC=0,"
        "MAVLINK=1,NODEID=2,NODEDESTINATION=65535,NODECOUNT=3,NUM_CHANNELS=50"
    )
    assert parse_expected(line) == params
    for kind in ("toml", "json"):
        path = tmp_path / f"agent.{kind}"
        path.write_text(params_text(params, kind))
        assert parse_expected(str(path)) == params
