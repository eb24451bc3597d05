"""The host-side configurator and `swarm radio-config` against a radio on a real pty.

The radio is an ATEngine served by tests/sik_pty_radio.py on the real clock, so the
+++ guard times are real: tests that enter command mode from data mode take about
2.5 s each; the others start the radio already in command mode.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import serial
from net_helpers import wait_until
from sik_pty_radio import PtyRadio, SilentPty, make_engine

from radios.errors import ATError, ATTimeoutError, ConfigError, LinkOpenError
from radios.sik import config as config_module
from radios.sik.config import SikConfigurator, open_port, strip_node
from radios.sik.readout import parse_local
from swarm.cli.commands.radio_config import main

pytestmark = pytest.mark.processes  # a radio on a pty with real +++ guard times

DEADLINE = 10.0  # the pty radio answers in milliseconds: this only bounds a failing test


@pytest.fixture
def radio() -> Iterator[PtyRadio]:
    with PtyRadio(start_in_command_mode=True) as r:
        yield r


@pytest.fixture
def port(radio: PtyRadio) -> Iterator[Any]:
    p = open_port(radio.path, 57600)
    yield p
    p.close()


# -- open_port ----------------------------------------------------------------------------


def test_open_port_missing_path(tmp_path: Path) -> None:
    with pytest.raises(LinkOpenError, match="no such device"):
        open_port(str(tmp_path / "ttyUSB9"), 57600)


def test_open_port_not_a_tty(tmp_path: Path) -> None:
    plain = tmp_path / "file"
    plain.write_text("x")
    with pytest.raises(LinkOpenError, match="not a serial device"):
        open_port(str(plain), 57600)
    with pytest.raises(LinkOpenError, match="not a serial device"):
        open_port("/dev/null", 57600)  # a character device, but not a tty


def test_open_port_permission(monkeypatch: pytest.MonkeyPatch) -> None:
    with SilentPty() as pty:

        def deny(*_args: Any, **_kwargs: Any) -> int:
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr(config_module.os, "open", deny)
        with pytest.raises(LinkOpenError, match=r"permission denied.*dialout"):
            open_port(pty.path, 57600)


def test_open_port_in_use() -> None:
    with SilentPty() as pty:
        first = open_port(pty.path, 57600)
        try:
            with pytest.raises(LinkOpenError, match="in use"):
                open_port(pty.path, 57600)
        finally:
            first.close()


# -- parsing ------------------------------------------------------------------------------


def test_parse_local_accepts_both_formats() -> None:
    lines = ["S0:FORMAT=26", "S1: SERIAL_SPEED=57", "[2] S2:AIR_SPEED=64"]
    assert parse_local(lines, "standard", "tty") == {
        "FORMAT": (0, 26),
        "SERIAL_SPEED": (1, 57),
        "AIR_SPEED": (2, 64),
    }
    assert strip_node("[12] OK") == "OK"
    assert strip_node("OK") == "OK"


# -- the configurator ---------------------------------------------------------------------


def test_enter_command_mode_from_data_mode() -> None:
    with PtyRadio() as radio:
        p = open_port(radio.path, 57600)
        try:
            conf = SikConfigurator(p)
            start = time.monotonic()
            conf.enter_command_mode()
            elapsed = time.monotonic() - start
            assert 2.0 <= elapsed < 4.0  # 1.2 s silence + 1 s guard
            assert radio.engine.in_command_mode
            assert conf.in_command_mode
            assert b"+++" in radio.air  # the pluses went to the air, as on a real radio
            assert conf.version() == "SiK 2.2 on HM-TRP"
            conf.exit_command_mode()
            wait_until(lambda: not radio.engine.in_command_mode, "ATO to leave command mode", DEADLINE)
        finally:
            p.close()


def test_enter_command_mode_when_already_there(radio: PtyRadio, port: Any) -> None:
    conf = SikConfigurator(port)
    start = time.monotonic()
    conf.enter_command_mode()
    assert time.monotonic() - start < 1.0  # the AT probe answered: no +++ needed
    assert b"+" not in radio.received


def test_read_set_save_reboot(radio: PtyRadio, port: Any) -> None:
    conf = SikConfigurator(port)
    conf.enter_command_mode()
    assert conf.command("ATI1") == ["2.2"]
    params = conf.read_params()
    assert params["AIR_SPEED"] == 64 and params["MIN_FREQ"] == 915000
    assert list(params)[:3] == ["FORMAT", "SERIAL_SPEED", "AIR_SPEED"]
    assert conf.indices["MAX_WINDOW"] == 15
    conf.set_param("air_speed", 100)
    conf.set_param("TXPOWER", "10")
    assert conf.read_params()["TXPOWER"] == 11
    conf.save()
    conf.reboot()
    wait_until(lambda: radio.reboots, "the reboot (ATZ)", DEADLINE)
    with radio.lock:
        assert radio.reboots == 1
        assert not radio.engine.in_command_mode
        assert radio.engine.params.active_value("AIR_SPEED") == 128
        assert radio.engine.params.eeprom[2] == 100


def test_set_param_invalid_writes_nothing(radio: PtyRadio, port: Any) -> None:
    conf = SikConfigurator(port)
    conf.enter_command_mode()
    before = len(radio.received)
    with pytest.raises(ConfigError, match="unknown standard SiK parameter 'BOGUS'"):
        conf.set_param("BOGUS", 1)
    with pytest.raises(ConfigError, match="out of range"):
        conf.set_param("AIR_SPEED", 999)
    time.sleep(0.05)
    assert len(radio.received) == before


def test_set_param_refused_by_radio() -> None:
    with PtyRadio(make_engine("multipoint"), start_in_command_mode=True) as radio:
        p = open_port(radio.path, 57600)
        try:
            conf = SikConfigurator(p, flavour="multipoint")
            conf.enter_command_mode()
            assert conf.version() == "MP SiK 2.2 on HM-TRP"
            assert conf.read_params()["NODECOUNT"] == 2
            with pytest.raises(ATError, match=r"refused NODEID=5 \(ATS15=5\)"):
                conf.set_param("NODEID", 5)  # not below NODECOUNT
            conf.set_param("NODECOUNT", 8)
            conf.set_param("NODEID", 5)
            assert conf.read_params()["NODEID"] == 5
        finally:
            p.close()


def test_command_without_command_mode_times_out() -> None:
    with PtyRadio() as radio:  # in data mode: the line goes to the air, no echo
        p = open_port(radio.path, 57600)
        try:
            conf = SikConfigurator(p)
            with pytest.raises(ATTimeoutError, match="not in command mode"):
                conf.command("ATI5", timeout=0.3)
        finally:
            p.close()


def test_remote_mode() -> None:
    peer = make_engine()
    with PtyRadio(peer=peer, start_in_command_mode=True) as radio:
        p = open_port(radio.path, 57600)
        try:
            conf = SikConfigurator(p, remote=True)
            conf.enter_command_mode()
            assert conf.version() == "SiK 2.2 on HM-TRP"
            assert conf.read_params()["NETID"] == 25
            conf.set_param("NETID", 7)
            conf.save()
            conf.reboot()
            conf.exit_command_mode()
            wait_until(lambda: radio.peer_reboots, "the peer's reboot (RTZ)", DEADLINE)
            assert radio.remote_commands[:2] == ["RTI", "RTI5"]
            assert radio.remote_commands[-3:] == ["RTS3=7", "RT&W", "RTZ"]
            # every register confirmed by a second answer: RTI5, then RTSn? each
            assert radio.remote_commands[2:18] == [f"RTS{n}?" for n in range(16)]
            assert radio.peer_reboots == 1
            assert peer.params.active_value("NETID") == 7
            assert radio.engine.params.active_value("NETID") == 25  # the local radio is untouched
        finally:
            p.close()


def test_remote_link_down(radio: PtyRadio, port: Any) -> None:
    conf = SikConfigurator(port, remote=True)  # radio.peer is None: nobody answers
    conf.enter_command_mode()
    start = time.monotonic()
    with pytest.raises(
        ATTimeoutError, match=r"remote radio answered neither RTI5 nor RTS0\? \(link down\?\)"
    ):
        conf.read_params()
    assert time.monotonic() - start < 6.0


def test_never_answering_port() -> None:
    with SilentPty() as pty:
        p = open_port(pty.path, 57600)
        try:
            conf = SikConfigurator(p)
            start = time.monotonic()
            with pytest.raises(ATTimeoutError, match=r"no answer to \+\+\+ on .* at 57600 baud"):
                conf.enter_command_mode(timeout=0.5)
            assert time.monotonic() - start < 5.0
        finally:
            p.close()


# -- swarm radio-config -------------------------------------------------------------------


def test_cli_show_from_data_mode(capsys: pytest.CaptureFixture[str]) -> None:
    with PtyRadio() as radio:
        assert main([radio.path, "--show"]) == 0
        wait_until(lambda: not radio.engine.in_command_mode, "ATO to leave command mode", DEADLINE)
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 16
    assert out[1].split() == ["S1", "SERIAL_SPEED", "57"]
    assert out[15].split() == ["S15", "MAX_WINDOW", "131"]


def test_cli_json(radio: PtyRadio, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([radio.path, "--json"]) == 0
    captured = capsys.readouterr()
    values = json.loads(captured.out)
    assert values["AIR_SPEED"] == 64
    assert all(isinstance(v, int) for v in values.values())
    assert len(values) == 16
    assert captured.out.count("\n") == 1


def test_cli_set_saves_reboots_and_reads_back(radio: PtyRadio, capsys: pytest.CaptureFixture[str]) -> None:
    code = main([radio.path, "--set", "AIR_SPEED=100", "--set", "txpower=10", "--set", "NETID=77", "--json"])
    assert code == 0
    values = json.loads(capsys.readouterr().out)
    assert values["AIR_SPEED"] == 128  # as the radio runs it after the reboot
    assert values["TXPOWER"] == 11
    assert values["NETID"] == 77
    wait_until(lambda: not radio.engine.in_command_mode, "ATO to leave command mode", DEADLINE)
    with radio.lock:
        assert radio.reboots == 1
        assert not radio.engine.in_command_mode
        assert radio.engine.params.eeprom[2] == 100
        assert radio.engine.params.active_value("NETID") == 77


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("BOGUS=1", "unknown standard SiK parameter 'BOGUS'"),
        ("AIR_SPEED=999", "out of range"),
        ("SERIAL_SPEED=56", "use one of"),
        ("NETID", "expects NAME=VALUE"),
    ],
)
def test_cli_bad_setting_exits_2_and_writes_nothing(
    radio: PtyRadio, setting: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([radio.path, "--set", "NETID=5", "--set", setting]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert message in captured.err
    assert captured.err.startswith("swarm radio-config: error: ")
    assert captured.err.count("\n") == 1
    time.sleep(0.05)
    assert radio.received == b""  # validated before the port was even opened


def test_cli_missing_port(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path / "nope"), "--show"]) == 2
    err = capsys.readouterr().err
    assert "no such device" in err and "Traceback" not in err


def test_cli_usage_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert main(["/dev/null", "--show", "--set", "NETID=1"]) == 2
    assert main(["/dev/null", "--firmware", "rfd"]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_cli_no_answer_exits_1(capsys: pytest.CaptureFixture[str]) -> None:
    with SilentPty() as pty:
        start = time.monotonic()
        assert main([pty.path, "--show"]) == 1
        assert time.monotonic() - start < 12.0
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1
    assert "no answer to +++" in captured.err and "wrong baud rate" in captured.err


def test_cli_firmware_mismatch(capsys: pytest.CaptureFixture[str]) -> None:
    with PtyRadio(make_engine("multipoint"), start_in_command_mode=True) as radio:
        assert main([radio.path, "--firmware", "standard", "--set", "NETID=5"]) == 2
        assert "--firmware multipoint" in capsys.readouterr().err
        assert radio.engine.params.ram[3] == 25
    with PtyRadio(make_engine("multipoint"), start_in_command_mode=True) as radio:
        # the README's old example: multipoint firmware has no MAX_WINDOW; refused before any write
        assert main([radio.path, "--set", "NETID=30", "--set", "MAX_WINDOW=33"]) == 2
        err = capsys.readouterr().err
        assert "runs multipoint firmware" in err and "no MAX_WINDOW: nothing was written" in err
        assert err.count("\n") == 1
        assert b"ATS" not in bytes(radio.received)
        assert radio.engine.params.ram[3] == 25 and radio.reboots == 0
    with PtyRadio(make_engine("multipoint"), start_in_command_mode=True) as radio:
        assert main([radio.path, "--firmware", "multipoint", "--set", "NODECOUNT=4", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["NODECOUNT"] == 4


def test_cli_remote_set(capsys: pytest.CaptureFixture[str]) -> None:
    peer = make_engine()
    with PtyRadio(peer=peer, start_in_command_mode=True) as radio:
        assert main([radio.path, "--remote", "--set", "NETID=9", "--json"]) == 0
        captured = capsys.readouterr()
        assert json.loads(captured.out)["NETID"] == 9
        assert "remote radio saved" in captured.err
        wait_until(lambda: not radio.engine.in_command_mode, "ATO to leave command mode", DEADLINE)
        assert peer.params.active_value("NETID") == 9
        assert radio.engine.params.active_value("NETID") == 25
        assert not radio.engine.in_command_mode


def test_cli_serial_port_is_released(radio: PtyRadio) -> None:
    assert main([radio.path, "--show"]) == 0
    again = serial.Serial(radio.path, 57600, exclusive=True)  # not left locked
    again.close()
    assert os.path.exists(radio.path)
