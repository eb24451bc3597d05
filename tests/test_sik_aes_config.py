"""SiK AES builds: the AT interface (ENCRYPTION_LEVEL, AT&E) and `swarm radio-config
--aes-key`, on a real pty; and the rogue's RT attack against keyed radios in the
pty emulator."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import serial
from emu_helpers import running_emulator
from sik_pty_radio import PtyRadio

from radios.errors import ConfigError
from radios.sik.at import ATEngine
from radios.sik.param_table import ENCRYPTION_LEVEL, NETID
from radios.sik.params import SikParams, validate_key_hex
from swarm.cli.commands.radio_config import main

pytestmark = pytest.mark.processes  # radios on ptys with real +++ guard times

KEY = "00112233445566778899aabbccddeeff"


def aes_engine(*, aes: bool = True) -> ATEngine:
    return ATEngine(
        SikParams(aes=aes), board="RFD900P" if aes else "HM-TRP", ati6=lambda: "", ati7=lambda: ""
    )


def run(e: ATEngine, line: str) -> bytes:
    return e.run_remote("RT" + line[2:]).output


def test_at_e_sets_and_prints_the_key_by_level() -> None:
    e = aes_engine()
    p = e.params
    assert p.as_dict()["ENCRYPTION_LEVEL"] == 0
    assert run(e, "ATS16=1") == b"OK\n"
    assert run(e, "AT&E=" + KEY.upper()) == b"key len 16\nOK\n"
    assert run(e, "AT&E?") == KEY.encode() + b"\n"
    assert p.active_key() == b""  # RAM only until AT&W + ATZ
    run(e, "AT&W")
    assert e.run_remote("RTZ").reboot
    assert p.active_key() == bytes.fromhex(KEY)
    # too short a key: the firmware takes its default key and still says OK
    assert run(e, "AT&E=1234") == b"ERROR - Key length:4, Required 32\nOK\n"
    assert run(e, "AT&E?") == b"62" * 16 + b"\n"


def test_no_at_e_without_aes_and_only_on_aes_boards() -> None:
    e = aes_engine(aes=False)
    assert run(e, "AT&E?") == b"ERROR\n"
    assert "ENCRYPTION_LEVEL" not in e.params.as_dict()
    with pytest.raises(ConfigError, match="only built for"):
        ATEngine(SikParams(aes=True), board="HM-TRP", ati6=str, ati7=str)
    with pytest.raises(ConfigError, match="multipoint"):
        SikParams("multipoint", aes=True)


def test_validate_key_hex() -> None:
    assert validate_key_hex(1, KEY) == bytes.fromhex(KEY)
    assert len(validate_key_hex(3, "ab" * 32)) == 32
    for level, key, message in [
        (1, KEY[:-2], "32 hex digits"),
        (1, "zz" * 16, "hex digits only"),
        (0, KEY, "1, 2 or 3"),
        (2, KEY, "48 hex digits"),
    ]:
        with pytest.raises(ConfigError, match=message) as info:
            validate_key_hex(level, key)
        assert KEY not in str(info.value)


def _key_file(tmp_path: Path, text: str = KEY) -> str:
    path = tmp_path / "radio.key"
    path.write_text(text + "\n")
    return str(path)


def _assert_key_hidden(text: str) -> None:
    assert KEY not in text.lower()
    assert KEY[:8] not in text.lower()


def test_radio_config_sets_level_and_key_never_printed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with PtyRadio(aes_engine(), start_in_command_mode=True) as radio:
        code = main([radio.path, "--set", "ENCRYPTION_LEVEL=1", "--aes-key", _key_file(tmp_path)])
        captured = capsys.readouterr()
        assert code == 0, captured.err
        _assert_key_hidden(captured.out + captured.err)
        assert "ENCRYPTION_LEVEL" in captured.out
        with radio.lock:
            p = radio.engine.params
            assert p.active[ENCRYPTION_LEVEL] == 1
            assert p.active_key() == bytes.fromhex(KEY)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--set", "ENCRYPTION_LEVEL=1"], "needs --aes-key"),
        (["--set", "ENCRYPTION_LEVEL=2", "--aes-key", "KEYFILE"], "48 hex digits"),
        (["--aes-key", "KEYFILE"], "needs --set ENCRYPTION_LEVEL"),
        (["--set", "ENCRYPTION_LEVEL=1", "--aes-key", "KEYFILE", "--remote"], "unencrypted"),
        (["--set", "ENCRYPTION_LEVEL=1", "--aes-key", "/nonexistent/key"], "cannot read"),
        # an endless device is no key file (it was read for ever)
        (["--set", "ENCRYPTION_LEVEL=1", "--aes-key", "/dev/zero"], "not a regular file"),
    ],
)
def test_radio_config_key_refusals_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    key = _key_file(tmp_path)
    argv = [key if a == "KEYFILE" else a for a in extra]
    with PtyRadio(aes_engine(), start_in_command_mode=True) as radio:
        assert main([radio.path, *argv]) == 2
        captured = capsys.readouterr()
        assert message in captured.err and captured.err.count("\n") == 1
        _assert_key_hidden(captured.out + captured.err)
        time.sleep(0.05)
        assert radio.received == b""  # refused before the port was opened


def test_radio_config_refuses_a_radio_without_aes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with PtyRadio(aes_engine(aes=False), start_in_command_mode=True) as radio:
        assert main([radio.path, "--set", "ENCRYPTION_LEVEL=1", "--aes-key", _key_file(tmp_path)]) == 2
        captured = capsys.readouterr()
        assert "no AES" in captured.err
        _assert_key_hidden(captured.out + captured.err)
        with radio.lock:
            assert b"AT&E" not in bytes(radio.received)
            assert b"ATS" not in bytes(radio.received)


def _rogue(path: str) -> None:
    """A rogue's host on its own radio: +++ and the three RT commands, twice each."""
    with serial.Serial(path, 57600, timeout=0.05) as s:
        time.sleep(1.2)
        s.write(b"+++")
        deadline = time.monotonic() + 5
        seen = b""
        while b"OK" not in seen and time.monotonic() < deadline:
            seen += s.read(64)
        assert b"OK" in seen
        for line in (b"RTS3=77", b"RT&W", b"RTZ") * 2:
            s.write(line + b"\r")
            time.sleep(0.6)


def test_keyed_radios_ignore_a_rogue_on_ptys(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    key = _key_file(tmp_path)
    with running_emulator(tmp_path, 3, firmware="standard", aes=True) as emu:
        for i in (0, 1):
            assert main([emu.paths[i], "--set", "ENCRYPTION_LEVEL=1", "--aes-key", key]) == 0
        capsys.readouterr()
        assert emu.emu.radio_config(0).key == emu.emu.radio_config(1).key != b""
        assert emu.emu.radio_config(2).key == b""
        _rogue(emu.paths[2])
        for i in (0, 1):
            p = emu.emu.params[i]
            assert (p.eeprom[NETID], p.active[NETID]) == (25, 25)
