"""The stations' replay guard across restarts and states from the future
(swarm.core.station.federation's Gate: pure, times given), the station's file of it
(swarm.runtime.station.federation, without a session), and where nodes keep their state
(swarm.cli.state_dir, --state-dir and its config key)."""

from __future__ import annotations

import json
import logging
import os
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import pytest

from radios.statefile import read_state
from swarm.cli.commands import agent as agent_cmd
from swarm.cli.commands import gcs as gcs_cmd
from swarm.cli.configfile import read_arguments
from swarm.cli.state_dir import default_state_dir, open_state_dir
from swarm.cli.util import UsageError
from swarm.core.station.federation import (
    FUTURE_S,
    KIND_COMMAND,
    KIND_STATE,
    WINDOW_S,
    FederationRefused,
    Gate,
    fed_key,
    seal,
)
from swarm.runtime.station.federation import Federation

KEY = fed_key(b"k" * 32)
NOW = 1_790_000_000.0


def cmd(t: float, sender: str = "gcsA") -> bytes:
    return seal(KIND_COMMAND, sender, 1, int(t * 1e6), b'{"to": "gcsC"}', KEY)


def state(t: float, sender: str = "gcsC", key: bytes | None = KEY) -> bytes:
    return seal(KIND_STATE, sender, 1, int(t * 1e6), b'{"agents": []}', key, deflate=True)


def test_a_command_taken_before_a_restart_is_refused_after_it() -> None:
    gate = Gate(KEY)
    gate.open(cmd(NOW), NOW, KIND_COMMAND)
    saved = json.loads(json.dumps(gate.records(NOW + 1)))  # through a file's JSON
    again = Gate(KEY)  # the restarted station
    assert again.restore(saved, NOW + 5) == 1
    with pytest.raises(FederationRefused, match="replayed"):
        again.open(cmd(NOW), NOW + 5, KIND_COMMAND)
    again.open(cmd(NOW + 4), NOW + 5, KIND_COMMAND)  # a new one is taken
    # without the record (the code before), the replay was taken
    Gate(KEY).open(cmd(NOW), NOW + 5, KIND_COMMAND)


def test_a_state_record_crosses_the_restart_but_not_from_the_future() -> None:
    gate = Gate(None)
    gate.open(state(NOW, key=None), NOW, KIND_STATE)
    gate.open(state(NOW + 0.5, "gcsD", key=None), NOW, KIND_STATE)
    saved = gate.records(NOW + 1)
    again = Gate(None)
    # restored with a clock set 30 s back: gcsD's and gcsC's newest are ahead of it by more than
    # the skew and dropped (they would freeze both stations), nothing else
    assert again.restore(saved, NOW - 30.0) == 0
    assert again.restore(saved, NOW) == 2
    with pytest.raises(FederationRefused, match="replayed"):
        again.open(state(NOW, key=None), NOW + 1, KIND_STATE)
    again.open(state(NOW + 0.6, key=None), NOW + 1, KIND_STATE)


@pytest.mark.parametrize("key", [None, KEY], ids=["unsigned", "signed"])
def test_a_state_from_the_future_is_refused_and_does_not_freeze_the_sender(key: bytes | None) -> None:
    gate = Gate(key)
    with pytest.raises(FederationRefused, match="from the future"):
        gate.open(state(NOW + FUTURE_S + 1, key=key), NOW, KIND_STATE)
    gate.open(state(NOW + FUTURE_S - 1, key=key), NOW, KIND_STATE)  # a clock a little ahead: heard
    gate.open(state(NOW + FUTURE_S - 0.5, key=key), NOW + 0.5, KIND_STATE)
    assert gate.refused == {"from the future": 1}
    if key is None:
        with pytest.raises(FederationRefused, match="from the future"):
            gate.open(state(4_102_444_800.0, key=None), NOW, KIND_STATE)  # 2100


@pytest.mark.parametrize(
    "records",
    [
        None,
        [],
        {"states": "x", "taken": []},
        {"states": [], "taken": {}},
    ],
)
def test_a_record_that_is_none_is_refused(records: Any) -> None:
    with pytest.raises(FederationRefused, match="malformed"):
        Gate(KEY).restore(records, NOW)


def test_hostile_entries_of_a_record_are_skipped() -> None:
    t = int(NOW * 1e6)
    records = {
        "states": [
            ["gcsC", "S", t],  # kept
            ["bad name!", "S", t],
            ["gcsD", "X", t],
            ["gcsE", "S", "soon"],
            ["gcsF", "S", True],
            ["gcsG", "S", t, "extra"],
            "gcsH",
        ]
        + [[f"s{i}", "S", t] for i in range(1000)],  # more senders than a gate keeps
        "taken": [
            ["gcsA", "C", t, NOW - 1],  # kept
            ["gcsA", "C", t + 1, NOW - 3 * WINDOW_S],  # too old to matter
            ["gcsA", "C", t + 2, "yesterday"],
            ["gcsA", "C", t + 3, float("nan")],
            ["gcsA", "C", -5, NOW],
        ],
    }
    gate = Gate(KEY)
    kept = gate.restore(records, NOW)
    assert kept == 1 + (256 - 7) + 1  # the good ones of the first 256 states, and one command
    assert len(gate.records(NOW)["states"]) <= 256


def test_the_station_file_is_kept_only_with_a_key_and_a_failed_save_is_one_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    def run(_body: Any) -> Future[tuple[int, dict[str, Any]]]:
        f: Future[tuple[int, dict[str, Any]]] = Future()
        f.set_result((200, {}))
        return f

    def fed(path: Path, key: bytes | None) -> Federation:
        return Federation("gcsC", key=key, local=dict, run_local=run, state_file=str(path), wall=lambda: NOW)

    unsigned = fed(tmp_path / "u.json", None)
    assert unsigned.state_file is None and not unsigned.save()
    f = fed(tmp_path / "s.json", KEY)
    f.command_gate.open(cmd(NOW), NOW, KIND_COMMAND)
    assert f.save()
    obj = read_state(tmp_path / "s.json", 1 << 20)
    assert obj["commands"]["taken"][0][:3] == ["gcsA", "C", int(NOW * 1e6)]
    again = fed(tmp_path / "s.json", KEY)
    again.load()
    with pytest.raises(FederationRefused, match="replayed"):
        again.command_gate.open(cmd(NOW), NOW, KIND_COMMAND)
    # a hostile file: one warning, the gates start empty
    caplog.set_level(logging.WARNING, "swarm.runtime.station.federation")
    (tmp_path / "h.json").write_text(
        '{"format": "uav-swarm station replay guard", "version": 1, "states": 7}'
    )
    fed(tmp_path / "h.json", KEY).load()
    gone = fed(tmp_path / "no" / "such" / "folder.json", KEY)
    assert not gone.save() and not gone.save()
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 2 and "ignored" in msgs[0] and "not saved" in msgs[1], msgs


# -- where a node keeps its state ----------------------------------------------------------


def test_the_default_state_folder() -> None:
    assert default_state_dir({"STATE_DIRECTORY": "/var/lib/uav-swarm:/var/lib/other"}) == Path(
        "/var/lib/uav-swarm"
    )
    assert default_state_dir({"XDG_STATE_HOME": "/x", "HOME": "/h"}) == Path("/x/uav-swarm")
    assert default_state_dir({"XDG_STATE_HOME": "relative", "HOME": "/h"}) == Path(
        "/h/.local/state/uav-swarm"
    )
    assert default_state_dir({}) is None


def test_a_state_folder_given_that_cannot_be_used_is_a_usage_error(tmp_path: Path) -> None:
    afile = tmp_path / "file"
    afile.write_text("")
    for given, why in ((str(afile), "not a folder"), (str(tmp_path / "a" / "b"), "No such file")):
        with pytest.raises(UsageError, match=why):
            open_state_dir(given, "swarm agent")
    made = open_state_dir(str(tmp_path / "new"), "swarm agent")
    assert made is not None and oct(os.stat(made).st_mode & 0o777) == "0o700"


def test_the_default_folder_that_cannot_be_used_is_one_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    afile = tmp_path / "file"
    afile.write_text("")
    assert open_state_dir(None, "swarm agent", {"STATE_DIRECTORY": str(afile)}) is None
    assert open_state_dir(None, "swarm agent", {}) is None
    assert open_state_dir(None, "swarm agent", {"HOME": str(tmp_path / "no-home")}) is None
    assert not (tmp_path / "no-home").exists()  # a home that is not there is not made
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(e.startswith("swarm agent: warning: no state folder") for e in err), err
    open_to_all = tmp_path / "shared"
    open_to_all.mkdir()
    open_to_all.chmod(0o777)
    assert open_state_dir(str(open_to_all), "swarm gcs") == open_to_all
    assert "writable by other users" in capsys.readouterr().err


def test_state_dir_from_the_flag_or_the_config_file_names_a_file_per_node(tmp_path: Path) -> None:
    key = tmp_path / "swarm.key"
    key.write_text("k\n")
    key.chmod(0o600)  # a key others may read is refused
    conf = tmp_path / "a1.toml"
    conf.write_text('name = "a1"\nid = 3\nradio = "/dev/null"\nkey = "swarm.key"\nstate_dir = "st"\n')
    a = read_arguments(agent_cmd.build_parser(), ["--config", str(conf)])
    agent_cmd.check_arguments(a)
    assert a.node.signing_state is None  # what swarm doctor runs too: it makes no folder
    assert not (tmp_path / "st").exists()
    agent_cmd.check_state_files(a)
    assert a.node.signing_state == str(tmp_path / "st" / "agent-a1-3.signing.json")
    # without a key nothing is kept, and no folder made
    b = read_arguments(agent_cmd.build_parser(), ["--name", "a2", "--id", "4", "--radio", "/dev/null"])
    b.state_dir = str(tmp_path / "never")
    agent_cmd.check_arguments(b)
    agent_cmd.check_state_files(b)
    assert b.node.signing_state is None and not (tmp_path / "never").exists()
    # a station on two radios: one file per channel, and one for its replay guard
    g = read_arguments(
        gcs_cmd.build_parser(),
        [
            "--radio",
            "n1=/dev/null",
            "--radio",
            "n2=/dev/zero",
            "--key",
            str(key),
            "--state-dir",
            str(tmp_path / "g"),
        ],
    )
    gcs_cmd.check_arguments(g)
    assert g.state_folder == tmp_path / "g"
    with pytest.raises(UsageError, match="--state-dir"):
        gcs_cmd.check_arguments(
            read_arguments(
                gcs_cmd.build_parser(), ["--radio", "/dev/null", "--key", str(key), "--state-dir", str(key)]
            )
        )
