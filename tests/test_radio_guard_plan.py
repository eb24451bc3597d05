"""The radio guard's pure parts: what it keeps, when it checks, what a rogue sends."""

from __future__ import annotations

from pathlib import Path

import pytest
from emu_helpers import heartbeat
from test_sik_rogue import AtBench

from radios.emulator import Emulator
from radios.emulator_config import EmulatorConfig
from radios.errors import ConfigError
from radios.sik.at import ATEngine
from radios.sik.guard import CheckSchedule, baseline
from radios.sik.param_table import PARAMS_MULTIPOINT, PARAMS_STANDARD
from radios.sik.params import SikParams
from radios.sik.rogue import RtAttackOutcome, landed, plan_attack, registers_from_stats
from swarm.cli.commands import agent as agent_cmd


def test_the_guard_keeps_every_register_but_format_and_the_given_values_win() -> None:
    shown = {"FORMAT": 26, "NETID": 25, "NUM_CHANNELS": 20, "TXPOWER": 20}
    assert baseline({"NETID": 30}, shown) == {"NETID": 30, "NUM_CHANNELS": 20, "TXPOWER": 20}
    # a given register the radio did not show is kept too (the check names it missing)
    assert baseline({"NODEID": 2}, {"FORMAT": 26})["NODEID"] == 2


def test_check_schedule_periodic_and_isolated() -> None:
    s = CheckSchedule(30.0, 0.0, now=100.0)
    assert s.active
    assert s.due(False, 129.9) is None
    assert s.due(False, 130.0) == "period"
    s.checked(133.0)  # the check took 3 s: the next one a period after it ended
    assert s.due(True, 162.9) is None
    assert s.due(True, 163.0) == "period"

    both = CheckSchedule(60.0, 10.0, now=0.0)
    assert both.due(True, 0.0) is None
    assert both.due(True, 10.0) == "isolated"
    both.checked(12.0)
    assert both.due(False, 20.0) is None  # heard someone: no isolation check
    assert both.due(False, 71.9) is None  # the isolation check started the period over
    assert both.due(False, 72.0) == "period"

    off = CheckSchedule(0.0, 0.0, now=0.0)
    assert not off.active and off.due(True, 1e9) is None
    with pytest.raises(ConfigError):
        CheckSchedule(-1.0, 0.0, now=0.0)


@pytest.mark.parametrize("flavour", ["standard", "multipoint"])
def test_a_planned_attack_lands_as_planned_on_the_firmware_model(flavour: str) -> None:
    """For every register: the planned value differs, the firmware takes it as it is
    (no rewrite on set, nor at boot), and RTSn= + RT&W + RTZ make the radio run with it
    (registers SiK applies at once: already after RTSn=)."""
    specs = PARAMS_STANDARD if flavour == "standard" else PARAMS_MULTIPOINT
    node = 1 if flavour == "multipoint" else None
    for spec in specs[1:]:
        stored = {"NODECOUNT": 3, "NODEID": 1} if flavour == "multipoint" else {}
        params = SikParams(flavour, stored=stored)
        engine = ATEngine(params, flavour=flavour, ati6=str, ati7=str)
        attack = plan_attack(flavour, spec.name, params.as_dict(), node=node)
        assert params.as_dict()[spec.name] != attack.value
        result = engine.run_remote(attack.set_line)
        assert b"OK" in result.output, attack
        assert landed(params.as_dict(), attack)
        assert result.applied == attack.applies_now == (spec.applies == "now")
        if attack.applies_now:
            assert params.active_value(spec.name) == attack.value
        else:
            assert params.active_value(spec.name) != attack.value  # not before the reboot
        after = attack.value if spec.name == "NODEID" else node
        assert attack.save_line == ("RT&W" if after is None else f"RT&W,{after}")
        assert engine.run_remote(attack.save_line).output.endswith(b"OK\n")
        assert engine.run_remote(attack.reboot_line).reboot
        assert landed(params.as_dict(), attack) and params.active_value(spec.name) == attack.value


def test_plan_attack_refuses_what_the_firmware_lacks() -> None:
    with pytest.raises(ConfigError):
        plan_attack("multipoint", "MAX_WINDOW", {})
    with pytest.raises(ConfigError):
        plan_attack("standard", "FORMAT", {"FORMAT": 26})


def test_mavlink_off_over_rt_stops_radio_status_at_once_in_the_air_model() -> None:
    """SiK's param_set applies MAVLINK at once: a rogue's ``RTS6=0`` (no ``RT&W``, no
    ``RTZ``) stops the victim's RADIO_STATUS and framing there and then, as on the
    firmware; ``RTS6=1`` brings them back. Virtual time, the real AT interpreter."""
    params = [SikParams("standard") for _ in range(2)]
    bench = AtBench(params)
    bench.run(30.0)  # locked
    assert bench.model.status(0)["locked"]

    def reports(seconds: float) -> int:
        before = bench.model.status(0)["radio_status"]
        for _ in range(int(seconds)):
            bench.write(0, heartbeat(1))
            bench.run(1.0)
        return int(bench.model.status(0)["radio_status"] - before)

    assert reports(5) >= 4
    bench.command_mode(1)
    bench.send(1, "RTS6=0", wait=2.0)
    assert params[0].active_value("MAVLINK") == 0 and params[0].eeprom[6] == 1  # not saved
    assert bench.model.radios[0].cfg.mavlink == 0  # the running radio, not at the next boot
    assert reports(5) == 0
    bench.send(1, "RTS6=1", wait=2.0)
    assert reports(5) >= 4


def test_a_bench_reads_a_victims_registers_from_the_emulators_statistics(tmp_path: Path) -> None:
    stats = tmp_path / "stats.json"
    emu = Emulator(EmulatorConfig(nodes=2, directory=str(tmp_path), stats_json=str(stats), netids=[30]))
    try:
        emu.open()
        emu.params[1].set(10, 20)  # ATS10=20: RAM only, until AT&W and ATZ
        emu.write_stats()
    finally:
        emu.close()
    regs = registers_from_stats(str(stats), 1)
    assert regs is not None
    ram, saved, active = regs
    assert ram["NETID"] == saved["NETID"] == active["NETID"] == 30
    assert (ram["NUM_CHANNELS"], saved["NUM_CHANNELS"], active["NUM_CHANNELS"]) == (20, 0, 50)
    assert registers_from_stats(str(stats), 5) is None
    stats.write_text("{not json")
    assert registers_from_stats(str(stats), 0) is None
    assert registers_from_stats(str(tmp_path / "none.json"), 0) is None


def test_an_outcome_says_what_was_injected_and_observed() -> None:
    attack = plan_attack("multipoint", "NUM_CHANNELS", {"NUM_CHANNELS": 50}, node=0)
    assert RtAttackOutcome(attack, 50, True, 3.21, 9.54).describe() == (
        "RTS10=20,0 + RT&W,0 + RTZ,0 (NUM_CHANNELS 50 -> 20): landed after 3.2 s, restored 9.5 s later"
    )
    assert RtAttackOutcome(attack, 50, False, None, None).describe().endswith("did not land")
    assert RtAttackOutcome(attack, 50, True, 1.0, None).describe().endswith("never restored")


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--radio-check-period", "30"], "need --radio-params"),
        (["--radio-params", "NETID=25", "--radio-check-period", "5"], "at least 10 s"),
        (["--radio-params", "NETID=25", "--radio-check-period", "nan"], "seconds, 0 for off"),
        (["--radio-params", "NETID=25", "--radio-check-period", "-1"], "seconds, 0 for off"),
    ],
)
def test_radio_check_period_usage_errors(
    extra: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert agent_cmd.main(["--name", "a1", "--id", "1", "--radio", "/dev/null", *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
