"""The one-command demo end to end, as a user runs it (a real emulator, simulated PX4
vehicles, agent processes, the demo's ground node), shortened: three agents, a
short route. Then ``swarm replay --plot`` on the capture it left, and bad input."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from functools import partial
from pathlib import Path

import pytest
from net_helpers import wait_until

from radios.tlog import TlogWriter
from swarm.cli.commands.replay import main as replay_main
from swarm.sim.tracks import analyse

pytestmark = pytest.mark.processes  # the whole demo


def run_swarm(*args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "swarm.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, object], Path]:
    d = tmp_path_factory.mktemp("demo")
    # a short route, and a formation threshold with room for a loaded CI machine
    p = run_swarm(
        "demo",
        "--agents",
        "3",
        "--leg",
        "80",
        "--settle",
        "10",
        "--max-rms",
        "2.0",
        "--headless",
        "--no-gcs",
        "--json",
        "--dir",
        str(d),
        "--duration",
        "300",
        timeout=400,
    )
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    return json.loads(p.stdout), d


def test_demo_elects_flies_in_formation_and_summarises(demo: tuple[dict[str, object], Path]) -> None:
    s, d = demo
    assert s["ok"] is True and s["leader"] in (1, 2, 3)
    for key in ("elect_s", "formation_max_m", "air_utilisation"):
        assert isinstance(s[key], (int, float)), key
    rms = s["formation_rms_m"] if s["formation_rms_m"] is not None else s["route_rms_m"]
    assert 0 < rms <= 2.0  # type: ignore[operator]
    assert 0 < s["air_utilisation"] < 1  # type: ignore[operator]
    assert s["capture"] == str(d / "air.tlog") and os.path.getsize(str(s["capture"])) > 10_000
    plot = str(s["plot"])
    with open(plot, "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
    assert set(s["per_member"]) == {str(k) for k in (1, 2, 3) if k != s["leader"]}  # type: ignore[arg-type]


def test_replay_plots_the_demo_capture(
    demo: tuple[dict[str, object], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    s, _d = demo
    out = tmp_path / "tracks.png"
    assert replay_main([str(s["capture"]), "--plot", str(out), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["leader"] == s["leader"] and got["agents"] == [1, 2, 3]
    assert got["samples"] > 50 and got["turn_max_m"] is not None and got["turn_max_m"] < 10.0
    # This short route is nearly all turn: its few straight samples (4 to 20, right where the V is
    # still settling) give a noisy RMS, so the formation is judged here as the demo judges a route
    # without straight legs: every slot error the capture yields, in the demo's own bound.
    an = analyse(str(s["capture"]))
    assert len(an.errors) == got["samples"]
    errs = [e for _t, _m, e, _turn in an.errors]
    assert math.sqrt(sum(e * e for e in errs) / len(errs)) < 2.0
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_replay_plot_refuses_what_it_cannot_draw(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty.tlog"
    TlogWriter(str(empty)).close()
    assert replay_main([str(empty), "--plot", str(tmp_path / "x.png")]) == 2  # bad input, as in gcs --replay
    assert "no pose stream" in capsys.readouterr().err
    assert replay_main([str(empty), "--plot", str(tmp_path / "no" / "x.png")]) == 2


def test_demo_bad_input_is_refused_cleanly() -> None:
    p = run_swarm("demo", "--agents", "1", timeout=30)
    assert p.returncode == 2 and "--agents" in p.stderr and "Traceback" not in p.stderr
    p = run_swarm("demo", "--loss", "2", timeout=30)
    assert p.returncode == 2 and "Traceback" not in p.stderr


def _processes_mentioning(text: str) -> list[int]:
    pids = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                if text.encode() in fh.read():
                    pids.append(int(pid))
        except OSError:
            continue
    return pids


def test_sigterm_stops_the_demo_and_everything_it_started(tmp_path: Path) -> None:
    import signal

    p = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "swarm.cli",
            "demo",
            "--agents",
            "2",
            "--headless",
            "--no-gcs",
            "--dir",
            str(tmp_path),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert p.stdout is not None
        for line in p.stdout:
            if line.startswith("== election"):
                break
        assert _processes_mentioning(str(tmp_path)), "the demo's children are running"
        p.send_signal(signal.SIGTERM)
        assert p.wait(60) == 130
    finally:
        if p.poll() is None:
            p.kill()
    left = partial(_processes_mentioning, str(tmp_path))
    wait_until(lambda: left() == [], "nothing left behind", 20, 0.2, detail=left)
