"""The radio guard (radios.sik.guard) and ``swarm agent --radio-params``.

The attack is real: radio 1 of a running emulator (real ptys) reconfigures radio 0
with RT commands, as a rogue in range would; the guard then reads radio 0 through
its pty, names what differs, and restores it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from emu_helpers import running_emulator
from net_helpers import wait_until

from radios.errors import ConfigError
from radios.sik.config import SikConfigurator, open_port
from radios.sik.guard import (
    Mismatch,
    RecheckTimer,
    check_radio,
    compare,
    describe,
    parse_expected,
    split_radio_url,
)
from radios.sik.param_table import NETID
from swarm.cli.commands import agent as agent_cmd
from swarm.cli.procs import Child, json_events

pytestmark = pytest.mark.processes  # agents on emulated radios, in real time

SWARM = {"NETID": 25, "AIR_SPEED": 64}


def test_parse_expected_list_and_files(tmp_path: Path) -> None:
    assert parse_expected("netid=25, AIR_SPEED=64") == SWARM
    j = tmp_path / "radio.json"
    j.write_text(json.dumps({"NETID": 25, "AIR_SPEED": 64}))
    assert parse_expected(str(j)) == SWARM
    t = tmp_path / "radio.toml"
    t.write_text("NETID = 25\nAIR_SPEED = 64\n")
    assert parse_expected(str(t)) == SWARM
    assert parse_expected("NODEID=3") == {"NODEID": 3}  # multipoint names too
    assert parse_expected("ENCRYPTION_LEVEL=1") == {"ENCRYPTION_LEVEL": 1}


@pytest.mark.parametrize(
    "spec, message",
    [
        ("NETID=", "not a whole number"),
        ("NETID=70000", "out of range"),
        ("FOO=1", "unknown"),
        ("NETID=25,,", "expected NAME=VALUE"),
        ("/nonexistent/radio.json", "radio parameters file"),
    ],
)
def test_parse_expected_rejects(spec: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_expected(spec)


def test_parse_expected_rejects_bad_files(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{nope")
    with pytest.raises(ConfigError, match="not valid JSON"):
        parse_expected(str(bad))
    arr = tmp_path / "arr.json"
    arr.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="table"):
        parse_expected(str(arr))
    boolean = tmp_path / "b.json"
    boolean.write_text('{"NETID": true}')
    with pytest.raises(ConfigError, match="whole number"):
        parse_expected(str(boolean))
    empty = tmp_path / "e.toml"
    empty.write_text("")
    with pytest.raises(ConfigError, match="nothing to check"):
        parse_expected(str(empty))


def test_compare_and_describe() -> None:
    found = compare({"NETID": 25, "AIR_SPEED": 64, "ENCRYPTION_LEVEL": 1}, {"NETID": 77, "AIR_SPEED": 64})
    assert found == [Mismatch("NETID", 25, 77), Mismatch("ENCRYPTION_LEVEL", 1, None)]
    assert describe(found) == "NETID=77 (expected 25), ENCRYPTION_LEVEL missing (expected 1)"
    assert compare(SWARM, {"NETID": 25, "AIR_SPEED": 64, "ECC": 0}) == []


def test_split_radio_url() -> None:
    assert split_radio_url("/dev/ttyUSB0") == ("/dev/ttyUSB0", 57600)
    assert split_radio_url("serial:/dev/ttyUSB0?baud=115200") == ("/dev/ttyUSB0", 115200)
    with pytest.raises(ConfigError):
        split_radio_url("socket://host:1")
    with pytest.raises(ConfigError):
        split_radio_url("/dev/x?baud=fast")


def _rogue_moves_radio0(path1: str) -> None:
    """Radio 1's host does what a rogue in range does: RTS3=77, RT&W, RTZ."""
    port = open_port(path1)
    try:
        conf = SikConfigurator(port, remote=True, port_name=path1)
        conf.enter_command_mode()
        conf.set_param("NETID", 77)
        conf.save()
        conf.reboot()
        conf.exit_command_mode()
    finally:
        port.close()


def test_guard_detects_and_restores_a_radio_moved_by_a_rogue(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_emulator(tmp_path, 2) as emu:
        emu.wait_locked(0, 1)
        _rogue_moves_radio0(emu.paths[1])
        assert emu.emu.params[0].eeprom[NETID] == 77  # the hole, on the emulator

        report = check_radio(emu.paths[0], SWARM)
        assert report.mismatches == [Mismatch("NETID", 25, 77)] and not report.ok

        # the agent refuses to start on it, in one line, before opening the bridge
        code = agent_cmd.main(
            ["--name", "a1", "--id", "1", "--radio", emu.paths[0], "--radio-params", "NETID=25,AIR_SPEED=64"]
        )
        err = capsys.readouterr().err
        assert code == 1
        assert err.count("\n") == 1 and "NETID=77 (expected 25)" in err

        restored = check_radio(emu.paths[0], SWARM, restore=True)
        assert restored.restored and restored.values["NETID"] == 25
        p = emu.emu.params[0]
        assert (p.eeprom[NETID], p.active[NETID]) == (25, 25)
        assert check_radio(emu.paths[0], SWARM).mismatches == []


def test_agent_radio_params_usage_errors(capsys: pytest.CaptureFixture[str]) -> None:
    base = ["--name", "a1", "--id", "1"]
    cases: list[tuple[list[str], str]] = [
        ([*base, "--radio", "/dev/null", "--radio-params", "NETID=x"], "whole number"),
        ([*base, "--zenoh-listen", "tcp/127.0.0.1:7447", "--radio-params", "NETID=25"], "--radio"),
        ([*base, "--radio", "/dev/null", "--restore-radio"], "need --radio-params"),
        ([*base, "--radio", "/dev/null", "--radio-recheck", "30"], "need --radio-params"),
        ([*base, "--radio", "/dev/null", "--radio-params", "NETID=25", "--radio-recheck", "-1"], "seconds"),
    ]
    for argv, message in cases:
        assert agent_cmd.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err


def test_guard_on_a_port_that_is_not_a_radio(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = agent_cmd.main(
        ["--name", "a1", "--id", "1", "--radio", str(tmp_path / "nope"), "--radio-params", "NETID=25"]
    )
    assert code == 2
    assert "no such device" in capsys.readouterr().err


def _events(child: Child, kind: str) -> list[dict[str, Any]]:
    return json_events(child.lines, kind)


def test_isolated_agent_rechecks_and_restores_its_radio(tmp_path: Path) -> None:
    # A real `swarm agent` process alone on radio 0: it hears no other agent, so it
    # re-checks its radio every 12 s. A rogue on radio 1 moves radio 0 to NETID 77
    # right after one check; the next check puts it back.
    with running_emulator(tmp_path, 2) as emu:
        emu.wait_locked(0, 1)
        agent = Child(
            [
                "agent",
                "--name",
                "a1",
                "--id",
                "1",
                "--radio",
                emu.paths[0],
                "--json",
                "--radio-params",
                "NETID=25,AIR_SPEED=64",
                "--restore-radio",
                "--radio-recheck",
                "12",
            ],
            name="agent",
        )
        try:
            wait_until(
                lambda: _events(agent, "radio-checked") or agent.proc.poll() is not None,
                "the agent's first re-check",
                90.0,
            )
            assert agent.proc.poll() is None, agent.errors
            emu.wait_locked(0, 1)
            _rogue_moves_radio0(emu.paths[1])
            assert emu.emu.params[0].eeprom[NETID] == 77
            restored = wait_until(
                lambda: _events(agent, "radio-restored") or agent.proc.poll() is not None, "the restore", 90.0
            )
            assert agent.proc.poll() is None, agent.errors
            assert restored[0]["differed"] == {"NETID": 77}
            p = emu.emu.params[0]
            assert (p.eeprom[NETID], p.active[NETID]) == (25, 25)
        finally:
            agent.stop()


def test_recheck_timer() -> None:
    timer = RecheckTimer(10.0)
    assert not timer.update(True, 0.0)
    assert not timer.update(True, 9.9)
    assert timer.update(True, 10.0)
    assert not timer.update(True, 15.0)
    assert not timer.update(False, 16.0)  # heard someone: start over
    assert not timer.update(True, 17.0)
    assert not timer.update(True, 26.9)
    assert timer.update(True, 27.0)
    with pytest.raises(ConfigError):
        RecheckTimer(0)


@pytest.mark.parametrize("path", ["/dev/zero", "/"])
def test_a_radio_params_path_that_is_no_regular_file_is_refused(path: str) -> None:
    """An endless device was read for ever (a hang, then memory)."""
    with pytest.raises(ConfigError, match="not a regular file"):
        parse_expected(path)
