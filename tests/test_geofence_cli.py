"""The geofence's flags and config-file keys on ``swarm agent`` and ``swarm gcs``:
nonsense is one line naming the flag (or the file and the key), exit 2, before
anything opens; sound limits reach the pilot's and the station's fences."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_config_file import NODE, one_error, parse

from swarm.cli.commands import agent as agent_cmd
from swarm.cli.commands import gcs as gcs_cmd
from swarm.cli.fence_args import fence_from
from swarm.core.flight.geofence import Geofence

AGENT = ["--name", "a1", "--id", "1", "--zenoh-listen", "tcp/127.0.0.1:1"]
GCS = ["--zenoh-listen", "tcp/127.0.0.1:1"]

FLAG_CASES = [
    (["--fence-floor", "nan"], "--fence-floor nan: geofence floor nan: a finite number"),
    (["--fence-ceiling", "inf"], "--fence-ceiling inf: geofence ceiling inf"),
    (["--fence-radius=-inf"], "--fence-radius -inf: geofence radius -inf"),
    (["--fence-floor=-1"], "--fence-floor -1: geofence floor -1 m: 0 or more"),
    (
        ["--fence-floor", "50", "--fence-ceiling", "50"],
        "--fence-ceiling 50: geofence ceiling 50 m: above the floor",
    ),
    (["--fence-floor", "80", "--fence-ceiling", "40"], "above the floor (80 m)"),
    (["--fence-radius", "0"], "--fence-radius 0: geofence radius 0 m"),
    (["--fence-ceiling", "1e9"], "at most 5000 m"),
]


@pytest.mark.parametrize(("flags", "words"), FLAG_CASES)
def test_nonsense_limits_on_the_command_line_are_exit_2(
    flags: list[str], words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert agent_cmd.main([*AGENT, *flags]) == 2
    assert words in one_error(capsys, "agent")
    assert gcs_cmd.main([*GCS, *flags]) == 2
    assert words in one_error(capsys, "gcs")


@pytest.mark.parametrize(
    ("keys", "words"),
    [
        ("fence_floor = -3.0\n", "fence_floor = -3.0: geofence floor -3 m: 0 or more"),
        ("fence_floor = 100.0\nfence_ceiling = 90.0\n", "fence_ceiling = 90.0: geofence ceiling 90 m"),
        ("fence_radius = -1\n", "fence_radius = -1"),
        ("fence_ceiling = nan\n", "fence_ceiling = nan: not a finite number"),
        ('fence_floor = "2 m"\n', 'fence_floor = "2 m": a string, not a number'),
    ],
)
def test_nonsense_limits_in_a_config_file_name_the_file_and_the_key(
    keys: str, words: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for cmd, prog, head in ((agent_cmd, "agent", 'name = "a1"\nid = 1\n'), (gcs_cmd, "gcs", "")):
        path = tmp_path / f"{prog}.toml"
        path.write_text(head + keys + NODE)
        assert cmd.main(["--config", str(path)]) == 2
        line = one_error(capsys, prog)
        assert line.startswith(f"swarm {prog}: error: {path}: ") and words in line, line


def test_sound_limits_from_flags_and_file(tmp_path: Path) -> None:
    a = parse(agent_cmd, [*AGENT, "--fence-floor", "5", "--fence-ceiling", "60", "--fence-radius", "300"])
    assert fence_from(a) == Geofence(5.0, 60.0, 300.0)
    path = tmp_path / "gcs.toml"
    path.write_text("fence_floor = 3\nfence_radius = 2500.5\n" + NODE)
    g = parse(gcs_cmd, ["--config", str(path), "--fence-ceiling", "90"])
    assert fence_from(g) == Geofence(3.0, 90.0, 2500.5)
    assert fence_from(parse(gcs_cmd, GCS)) == Geofence()  # defaults: 2, 120, 1000
