"""``swarm demo --autopilot sitl:mix``: the demo on a mixed swarm of real autopilots
(ArduCopter and PX4 SITL, started by the demo from $SITL_DIR), as a user runs it,
shortened (three agents: two ArduCopter, one PX4; a short route). Every step happens
on the real flight stacks: they boot (the take-off waits for them), the V forms, the
route turns, they land; nothing accepted goes undone; every autopilot is stopped."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from test_demo import run_swarm

pytestmark = [pytest.mark.processes, pytest.mark.sitl, pytest.mark.timeout(600)]


def _autopilots_running(under: Path) -> list[str]:
    """Command lines of the arducopter / px4 processes alive now that run in a folder
    under ``under`` (the SITL scripts run each in its work folder): this demo's own,
    whatever other tests run beside it."""
    out = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmd = (Path("/proc") / pid / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            cwd = os.readlink(Path("/proc") / pid / "cwd")
        except OSError:
            continue
        if ("arducopter" in cmd or "/px4 " in cmd or cmd.startswith("px4 ")) and cwd.startswith(str(under)):
            out.append(cmd)
    return out


def test_a_mixed_swarm_of_real_autopilots_flies_the_demo(tmp_path: Path) -> None:
    p = run_swarm(
        "demo",
        *("--autopilot", "sitl:mix", "--agents", "3", "--leg", "40", "--settle", "10"),
        *("--max-rms", "3.0", "--max-turn", "30", "--headless", "--no-gcs", "--json"),
        *("--dir", str(tmp_path / "work")),
        timeout=560,
    )
    assert p.stdout.strip(), p.stderr[-3000:]
    s = json.loads(p.stdout)
    assert s["autopilots"] == ["ardupilot", "px4", "ardupilot"]
    figures = ("formation_rms_m", "formation_max_m", "turn_max_m", "route_rms_m")
    steps = [m for m in s["missed"] if m["target"] not in figures]
    assert steps == [], s["missed"]  # elected, took off after the boot, followed, arrived, landed
    assert s["leader"] in (1, 2, 3) and s["false_accepted"] == []
    # 40 m legs are all turn: the whole route's figure, and the heading after the turn
    assert s["route_rms_m"] is not None and s["heading_error_after_turn_deg"] is not None
    assert set(s["autopilot_cpu_pct"]) == {"ardupilot", "px4"}
    assert all(v is not None and v > 0 for v in s["autopilot_cpu_pct"].values())
    assert _autopilots_running(tmp_path) == []  # every autopilot it started is gone
