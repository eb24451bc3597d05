"""`swarm radio-config`: network set-up, read-back that is compared, and `--remote` reads
that never show a value they could not confirm.

Radios on real ptys: an ATEngine served by tests/sik_pty_radio.py (hostile variants: a
flash that keeps nothing, a remote whose answers lose packets) and the emulator with its
loss option.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from emu_helpers import running_emulator
from net_helpers import wait_until
from sik_pty_radio import PtyRadio, make_engine

from radios.sik.at import ATEngine, RemoteResult
from radios.sik.config import SikConfigurator, open_port
from radios.sik.guard import parse_expected
from swarm.cli.commands.radio_config import main

pytestmark = pytest.mark.processes  # radios on ptys with real +++ guard times

DEADLINE = 10.0


class LosingEngine(ATEngine):
    """A remote radio whose answers lose some of their 32-byte packets on the way, or
    arrive as noise."""

    drop: dict[str, set[int]]  # command -> packet numbers lost from its answer (set by the test)
    garble: set[str]  # commands whose answer arrives as noise

    def run_remote(self, command: str, now: float | None = None) -> RemoteResult:
        result = super().run_remote(command, now)
        if command in getattr(self, "garble", set()):
            return RemoteResult(b"S#:E?C=\n", result.reboot)
        lost = getattr(self, "drop", {}).get(command, set())
        packets = [result.output[i : i + 32] for i in range(0, len(result.output), 32)]
        kept = b"".join(p for n, p in enumerate(packets) if n not in lost)
        return RemoteResult(kept, result.reboot)


def test_network_setup_of_one_radio(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params_file = tmp_path / "agent2.toml"
    with PtyRadio(make_engine("multipoint"), start_in_command_mode=True) as radio:
        argv = [radio.path, "--network", "5", "--node", "2", "--netid", "30", "--air-speed", "100"]
        assert main([*argv, "--ecc", "1", "--json", "--write-params", str(params_file)]) == 0
        wait_until(lambda: not radio.engine.in_command_mode, "ATO to leave command mode", DEADLINE)
        with radio.lock:
            active = {
                name: radio.engine.params.active_value(name) for name in ("NETID", "NODEID", "NODECOUNT")
            }
            assert active == {"NETID": 30, "NODEID": 2, "NODECOUNT": 5}
            assert radio.engine.params.active_value("MAVLINK") == 1  # multipoint's default is raw
            assert radio.engine.params.active_value("ECC") == 1
            assert radio.reboots == 1
    captured = capsys.readouterr()
    values = json.loads(captured.out)
    assert values["AIR_SPEED"] == 128 and values["NODEDESTINATION"] == 65535
    assert (
        "for swarm agent: --radio-params SERIAL_SPEED=57,AIR_SPEED=128,NETID=30,TXPOWER=20,ECC=1,"
        in captured.err
    )
    # every register the guard keeps, as the radio reads back: the frequencies and
    # channels too (a rogue moved them and the agent had nothing to compare them with)
    written = parse_expected(str(params_file))
    assert written == {name: value for name, value in values.items() if name != "FORMAT"}
    assert {"NUM_CHANNELS", "MIN_FREQ", "MAX_FREQ", "TXPOWER", "DUTY_CYCLE", "LBT_RSSI"} <= set(written)
    assert written["NODEID"] == 2 and written["NODECOUNT"] == 5 and written["MAX_FREQ"] == 928000


def test_a_radio_that_reads_back_other_values_exits_1_naming_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    params_file = tmp_path / "agent.json"
    with PtyRadio(make_engine("multipoint"), start_in_command_mode=True) as radio:
        monkeypatch.setattr(radio.engine.params, "save", lambda: None)  # AT&W says OK, keeps nothing
        argv = [
            radio.path,
            "--network",
            "3",
            "--node",
            "2",
            "--netid",
            "30",
            "--write-params",
            str(params_file),
        ]
        assert main(argv) == 1
    err = capsys.readouterr().err.splitlines()
    assert "swarm radio-config: NODECOUNT: the radio shows 2, expected 3" in err
    assert "swarm radio-config: NETID: the radio shows 25, expected 30" in err
    assert "swarm radio-config: MAVLINK: the radio shows 0, expected 1" in err
    assert not any("--radio-params" in line for line in err)
    assert not params_file.exists()  # only a radio that reads back right gets its agent file


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--network", "3", "--node", "1"], "--network N needs --node I and --netid X"),
        (["--node", "1", "--netid", "30"], "belong to --network N"),
        (["--network", "3", "--node", "1", "--netid", "30", "--remote"], "sets up the local radio"),
        (
            ["--network", "3", "--node", "3", "--netid", "30"],
            "--node 3: the nodes of a 3-radio network are 0..2",
        ),
        (["--network", "3", "--node", "0", "--netid", "30", "--set", "BOGUS=1"], "unknown"),
        (["--remote-node", "1", "--show"], "--remote-node I needs --remote"),
        (["--remote", "--remote-node", "-1"], "--remote-node -1: a node id is 0..32767"),
        (["--show", "--set", "NETID=3"], "--show only reads"),
        (
            ["--network", "2", "--node", "0", "--netid", "3", "--write-params", "/nonexistent/a.toml"],
            "does not exist",
        ),
    ],
)
def test_bad_requests_exit_2_before_the_port_is_touched(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with PtyRadio(make_engine("multipoint"), start_in_command_mode=True) as radio:
        assert main([radio.path, *argv]) == 2
        assert radio.received == b""
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_multipoint_remote_needs_a_node(capsys: pytest.CaptureFixture[str]) -> None:
    with PtyRadio(
        make_engine("multipoint"), peer=make_engine("multipoint"), start_in_command_mode=True
    ) as radio:
        assert main([radio.path, "--remote", "--show"]) == 2
        assert radio.remote_commands == []
        wait_until(lambda: not radio.engine.in_command_mode, "ATO after the refusal", DEADLINE)
    assert "--remote on multipoint firmware needs --remote-node I" in capsys.readouterr().err


def test_remote_answer_with_lost_packets_shows_only_confirmed_values(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """RTI5's second and fourth packets are lost (spliced lines, a garbled name): the
    reads confirm every register with RTSn? and show the true values."""
    peer = make_engine(cls=LosingEngine, stored={"NETID": 42})
    assert isinstance(peer, LosingEngine)
    peer.drop = {"RTI5": {1, 3}}
    with PtyRadio(peer=peer, start_in_command_mode=True) as radio:
        assert main([radio.path, "--remote", "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out) == peer.params.as_dict()
    assert captured.err == ""


def test_remote_register_that_never_arrives_is_named_exit_1(capsys: pytest.CaptureFixture[str]) -> None:
    peer = make_engine(cls=LosingEngine)
    assert isinstance(peer, LosingEngine)
    peer.garble = {"RTI5", "RTS5?", "RTS15?"}  # ECC and MAX_WINDOW never arrive whole
    with PtyRadio(peer=peer, start_in_command_mode=True) as radio:
        assert main([radio.path, "--remote", "--show"]) == 1
        assert radio.remote_commands.count("RTS5?") == 5  # bounded retries
    captured = capsys.readouterr()
    assert len(captured.out.splitlines()) == 14
    assert captured.err == (
        "swarm radio-config: could not read ECC, MAX_WINDOW of the remote radio (14 of 16 read)\n"
    )


def test_remote_show_over_a_lossy_emulated_link(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The emulator's --loss: every value shown is the remote radio's; a register that
    could not be confirmed is named and the exit code says so."""
    with running_emulator(tmp_path, 2, loss=0.1, air_speed=250, netids=[33]) as emu:
        emu.wait_locked(0, 1)
        code = main([emu.paths[0], "--remote", "--json"])
        truth = emu.emu.params[1].as_dict()  # nothing changes it: read-only commands
    captured = capsys.readouterr()
    shown = json.loads(captured.out)
    assert all(truth[name] == value for name, value in shown.items())
    missing = [name for name in truth if name not in shown]
    if missing:
        assert code == 1 and ", ".join(missing) in captured.err
    else:
        assert code == 0 and captured.err == ""


def test_emulated_multipoint_rti5_comes_back_whole_a_line_per_packet(tmp_path: Path) -> None:
    """The multipoint firmware answers RTI5 one register per packet, all 19 of them, each
    line with one [id] prefix (the emulator cut it at 252 bytes and doubled the prefix)."""
    with running_emulator(tmp_path, 3, air_speed=128) as emu:
        emu.wait_locked(0, 1, 2)
        port = open_port(emu.paths[0])
        try:
            conf = SikConfigurator(port, remote=True, remote_node=2)
            conf.enter_command_mode()
            lines = conf.command("RTI5,2")
            conf.exit_command_mode()
        finally:
            port.close()
    assert len(lines) == 19
    assert lines[0] == "[2] S0: FORMAT=26" and lines[18] == "[2] S18: NODECOUNT=3"
