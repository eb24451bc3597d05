"""The emulator's capture with ``capture_status``: one radio's RADIO_STATUS reports to its
host go into the capture beside what was on air (as a ground station's own capture holds
them), so a replay of the bench shows the station's link quality; bad values refused."""

from __future__ import annotations

from pathlib import Path

import pytest
from emu_helpers import heartbeat, opened, recv_until, running_emulator, tunnel

from radios.air import RADIO_STATUS_COMPID, RADIO_STATUS_SYSID
from radios.emulator import Emulator
from radios.emulator_config import EmulatorConfig
from radios.errors import ConfigError
from radios.mavlink import MSG_RADIO_STATUS
from radios.tlog import read_tlog
from swarm.cli.commands.radio_emu import main as emu_main


def test_capture_holds_the_chosen_radios_status_reports(tmp_path: Path) -> None:
    cap = tmp_path / "air.tlog"
    with (
        running_emulator(tmp_path, 2, capture=str(cap), capture_status=1) as emu,
        opened(emu.open(0), emu.open(1)) as (l0, l1),
    ):
        emu.wait_ready(0, 1)
        l0.send(heartbeat(3))  # radio0's host: its reports are not the station's
        l1.send(heartbeat(255))
        assert recv_until(l1, lambda f: f.msgid == MSG_RADIO_STATUS) is not None
        assert recv_until(l0, lambda f: f.msgid == MSG_RADIO_STATUS) is not None
        l0.send(tunnel(3, b"on air"))
        assert recv_until(l1, lambda f: f.msgid == 385) is not None
    frames = [r.frame for r in read_tlog(cap)]
    status = [f for f in frames if f.msgid == MSG_RADIO_STATUS]
    assert status and {(f.sysid, f.compid) for f in status} == {(RADIO_STATUS_SYSID, RADIO_STATUS_COMPID)}
    on_air = [f for f in frames if f.msgid != MSG_RADIO_STATUS]
    assert {f.sysid for f in on_air} == {3, 255}  # the HEARTBEATs and the TUNNEL crossed the air
    # only radio1's reports: one per HEARTBEAT its host sent (one), none of radio0's
    assert len(status) == 1


def test_without_capture_status_the_capture_is_the_air_only(tmp_path: Path) -> None:
    cap = tmp_path / "air.tlog"
    with running_emulator(tmp_path, 2, capture=str(cap)) as emu, opened(emu.open(1)) as (l1,):
        emu.wait_ready(1)
        l1.send(heartbeat(255))
        assert recv_until(l1, lambda f: f.msgid == MSG_RADIO_STATUS) is not None
    assert not [r for r in read_tlog(cap) if r.frame.msgid == MSG_RADIO_STATUS]


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"capture": "x.tlog", "capture_status": 2}, r"--capture-status 2: a radio 0\.\.1, with --capture"),
        ({"capture": "x.tlog", "capture_status": -1}, r"--capture-status -1"),
        ({"capture_status": 0}, r"with --capture"),
    ],
)
def test_bad_capture_status_is_refused(tmp_path: Path, options: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        Emulator(EmulatorConfig(nodes=2, directory=str(tmp_path), **options))  # type: ignore[arg-type]


def test_cli_refuses_capture_status_without_capture(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert emu_main(["--nodes", "2", "--dir", str(tmp_path), "--capture-status", "1"]) == 2
    err = capsys.readouterr().err
    assert "--capture-status 1" in err and "Traceback" not in err
