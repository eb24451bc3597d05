"""The demo's figures, report and display without running the demo: the formation figures'
one definition on a recorded demo capture (tests/data/demo/demo.tlog), the plot's panels and
legend, the targets a run missed and how the summary says them, a truncated capture, and the
progress line on a real terminal (a pty) and in a file."""

from __future__ import annotations

import io
import math
import os
import select
import time
from pathlib import Path

import pytest

from radios.tlog import TlogWriter, read_tlog
from swarm.cli.commands.demo import Lines, open_page
from swarm.cli.commands.replay import main as replay_main
from swarm.cli.demo_report import summary_lines, targets
from swarm.sim.trackplot import figure
from swarm.sim.tracks import FIGURES, INTERVAL, MOVING_MPS, Analysis, analyse, route_start

DEMO = str(Path(__file__).parent / "data" / "demo" / "demo.tlog")


@pytest.fixture(scope="module")
def an() -> Analysis:
    return analyse(DEMO)


def _rms(v: list[float]) -> float:
    return round(math.sqrt(sum(x * x for x in v) / len(v)), 3)


def test_figures_count_from_the_route_start_to_the_end_of_the_follow_task(an: Analysis) -> None:
    start = route_start(an)
    assert an.t_from == start and an.from_what == "route start"
    assert an.follow_at is not None and start is not None and start > an.follow_at + 10  # the V formed first
    # the leader hovered until then, and moved at that pose
    lead = an.tracks[an.leader]
    before = [p for t, p in lead if an.follow_at < t < start]
    assert before and all(math.hypot(p.vn, p.ve) <= MOVING_MPS for p in before)
    assert all(start <= t for t, _m, _e, _turn in an.errors)
    s = an.summary()
    straight = [e for _t, _m, e, turn in an.errors if not turn]
    turns = [e for _t, _m, e, turn in an.errors if turn]
    # 1.126 m before 2026-11-29: a turn counted from 0.01 degree, and the poses of agents
    # whose delays straddled the 2.56 s wrap stamped with their air time
    assert s["formation_rms_m"] == _rms(straight) == 0.795
    assert s["formation_max_m"] == round(max(straight), 2)
    assert s["turn_max_m"] == round(max(turns), 2)
    assert s["route_rms_m"] == _rms(straight + turns)
    assert s["straight_samples"] == len(straight) and s["interval"]["from"] == "route start"
    # every figure is named with its legs and interval
    assert set(FIGURES) >= {"formation_rms_m", "formation_max_m", "turn_max_m", "route_rms_m"}
    assert all(INTERVAL in FIGURES[k] for k in ("formation_rms_m", "formation_max_m", "turn_max_m"))
    assert "straight legs" in FIGURES["formation_rms_m"] and s["figures"] == FIGURES


@pytest.mark.parametrize("shift_s", [k * 0.32 + 0.05 for k in range(8)])
def test_the_figures_do_not_depend_on_where_the_capture_clock_falls_in_the_wrap(
    an: Analysis, tmp_path: Path, shift_s: float
) -> None:
    # the same flight captured by a clock shifted by any fraction of the 2.56 s wrap: the
    # delays (air time - sample time, modulo 2.56) straddle the wrap for some shifts, and
    # the poses of those agents were stamped with their bursty air time
    shifted = tmp_path / "shifted.tlog"
    with TlogWriter(shifted) as w:
        for rec in read_tlog(DEMO):
            w.write(rec.raw, rec.t + shift_s)
    got = analyse(str(shifted))
    for agent, track in an.tracks.items():
        times = [t for t, _p in track]
        assert [t - shift_s for t, _p in got.tracks[agent]] == pytest.approx(times, abs=1e-6), agent
    assert got.summary()["formation_rms_m"] == an.summary()["formation_rms_m"]


def test_replay_plot_reports_the_same_figures_with_their_definition(
    an: Analysis, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert replay_main([DEMO, "--plot", str(tmp_path / "p.png")]) == 0
    text = capsys.readouterr().out
    assert "formation_rms_m: 0.795 m (RMS on the straight legs)" in text
    assert INTERVAL in text and "None" not in text


def test_a_truncated_capture_prints_no_none(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(Path(DEMO).read_bytes()[:60_000])  # before the route
    assert replay_main([str(cut), "--plot", str(tmp_path / "p.png")]) == 2  # a damaged capture: bad input
    got = capsys.readouterr()
    assert "None" not in got.out and "formation_rms_m: n/a" in got.out
    assert "damaged record" in got.err


def test_the_plot_has_a_map_and_an_error_panel_with_their_legend(an: Analysis) -> None:
    import matplotlib.pyplot as plt

    fig = figure(an, target_m=1.5)
    try:
        ax, ax2 = fig.axes
        labels = set(ax.get_legend_handles_labels()[1])
        assert {"start of route", "end", "turn (leader shaded)", "take-off, V forming, landing"} <= labels
        assert "agent 4 (leader)" in labels and any(lb.startswith("slot") for lb in labels)
        arrows = [c for c in ax.texts if getattr(c, "arrow_patch", None) is not None]
        assert len(arrows) >= 5  # direction along 200 m of route
        labels2 = set(ax2.get_legend_handles_labels()[1])
        assert {"agent 1", "agent 2", "agent 3", "agent 5", "turn", "target RMS 1.5 m"} <= labels2
        assert ax2.get_xlabel() == "time from the route's start (s)"
        assert "formation_rms_m" in fig.texts[0].get_text() and "0.795 m" in fig.texts[0].get_text()
    finally:
        plt.close(fig)


def test_a_missed_target_says_which_and_by_how_much() -> None:
    s = {"formation_rms_m": 1.518, "route_rms_m": 1.6, "turn_max_m": 15.5}
    missed = targets(s, 1.5, 10.0)
    assert [m["target"] for m in missed] == ["formation_rms_m", "turn_max_m"]
    assert missed[0]["text"] == f"formation RMS 1.518 m > 1.5 m (straight legs, {INTERVAL})"
    assert missed[0]["measured"] == 1.518 and missed[0]["limit"] == 1.5
    assert missed[1]["text"].startswith("largest error in the turn 15.5 m > 10 m (turns,")
    assert targets({"formation_rms_m": 1.2, "route_rms_m": 1.3, "turn_max_m": 4.0}, 1.5, 10.0) == []
    # a route with no straight legs is judged whole; a run with nothing measured misses it
    short = targets({"formation_rms_m": None, "route_rms_m": 1.7, "turn_max_m": None}, 1.5, 10.0)
    assert [m["target"] for m in short] == ["route_rms_m"] and "1.7 m > 1.5 m (whole route" in short[0][
        "text"
    ]
    none = targets({"formation_rms_m": None, "route_rms_m": None}, 1.5, 10.0)
    assert none[0]["text"].startswith("formation RMS: nothing measured")


def test_the_summary_says_what_was_missed_and_where_things_were() -> None:
    s = {
        "leader": 2,
        "elect_s": 7.5,
        "formation_rms_m": 1.518,
        "formation_max_m": 3.2,
        "turn_max_m": 15.5,
        "route_rms_m": 2.0,
        "interval": {"duration_s": 45.0},
        "air_utilisation": 0.31,
        "capture": None,
        "plot": "/home/me/flight.png",
        "workdir": "/tmp/swarm-demo-x",
        "workdir_kept": False,
        "gcs": "http://127.0.0.1:8080/",
        "gcs_running": False,
        "missed": targets({"formation_rms_m": 1.518, "route_rms_m": 2.0, "turn_max_m": 15.5}, 1.5, 10.0),
        "ok": False,
    }
    text = "\n".join(summary_lines(s))
    assert "MISSED: formation RMS 1.518 m > 1.5 m (straight legs, from the route's start" in text
    assert "MISSED: largest error in the turn 15.5 m > 10 m" in text
    assert "capture: removed with the working folder (--keep keeps it)" in text
    assert "plot: /home/me/flight.png" in text and "working folder: /tmp/swarm-demo-x (removed)" in text
    assert "ground station: was at http://127.0.0.1:8080/ (stopped with the demo)" in text
    assert "ok: false" in text and "None" not in text
    # a step that did not happen (run_demo puts it in the same list)
    failed = {"leader": 0, "missed": [{"target": "election", "text": "election: timed out after 120 s"}]}
    text = "\n".join(
        summary_lines({**failed, "workdir_kept": True, "workdir": "/w", "capture": "/w/air.tlog"})
    )
    assert "MISSED: election: timed out after 120 s" in text and "None" not in text


def test_progress_is_one_updating_line_on_a_terminal() -> None:
    master, slave = os.openpty()
    stream = os.fdopen(slave, "w")
    try:
        lines = Lines(stream, quiet=False)
        assert lines.tty
        lines.progress("   t=  1.0 s route 1/45 s: leader agent2")
        lines.progress("   t=  2.0 s route 2/45 s: leader agent2")
        lines.step("== landing")
        got = ""
        end = time.monotonic() + 10
        while not got.endswith("== landing\r\n") and time.monotonic() < end:
            if select.select([master], [], [], 0.5)[0]:  # a pty delivers in pieces
                got += os.read(master, 4096).decode()
    finally:
        stream.close()
        os.close(master)
    assert got.startswith("\r\x1b[Kt=  1.0 s route 1/45 s") and "\r\x1b[Kt=  2.0 s" in got
    assert got.count("\n") == 1 and got.endswith("\r\x1b[K== landing\r\n")  # the pty's own CR


def test_progress_is_plain_lines_in_a_file_and_silent_with_json() -> None:
    buf = io.StringIO()
    lines = Lines(buf, quiet=False)
    for k in range(5):  # every second: a plain line every 5 s, the first at once
        lines.progress(f"   t={k} s")
    lines.step("== landing")
    assert buf.getvalue() == "   t=0 s\n== landing\n"
    quiet = io.StringIO()
    q = Lines(quiet, quiet=True)
    q.progress("x")
    q.step("== y")
    assert quiet.getvalue() == ""


def test_without_a_display_the_page_not_opening_is_said(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    open_page("http://127.0.0.1:8080/", Lines(io.StringIO(), quiet=False))
    err = capsys.readouterr().err
    assert err == "   page not opened: no display here; open http://127.0.0.1:8080/ while the demo runs\n"


def test_the_bench_names_its_figures_with_the_same_definitions() -> None:
    import dataclasses

    from swarm.cli.bench.formation import FIGURE_NAMES
    from swarm.sim.flightsim import FlightResult

    fields = {f.name for f in dataclasses.fields(FlightResult)}
    assert set(FIGURE_NAMES) <= fields and set(FIGURE_NAMES.values()) <= set(FIGURES)
    assert FIGURE_NAMES["rms_straight_m"] == "formation_rms_m" and FIGURE_NAMES["max_turn_m"] == "turn_max_m"
