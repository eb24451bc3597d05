"""The station page in replay (``swarm gcs --replay`` of the checked-in demo capture, in
headless Chromium): "REPLAY" and the capture's time instead of "live", the connected
count as it was in the capture at that time, and the event log rebuilt on seek (seek back:
only what had happened by then)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_browser import browser, poll, screenshot, start_station
from net_helpers import free_port

from swarm.cli.procs import Child

DEMO = Path(__file__).resolve().parent / "data" / "demo" / "demo.tlog"
UI_DEADLINE = 30.0


@pytest.fixture(scope="module")
def replay() -> Iterator[tuple[Child, str]]:
    station, url = start_station(
        ["--replay", str(DEMO), "--paused", "--http", f"127.0.0.1:{free_port()}", "--tiles", "none"]
    )
    try:
        yield station, url
    finally:
        assert station.stop() == 0


@pytest.fixture
def page(replay: tuple[Child, str]) -> Iterator[Any]:
    with browser() as ctx:
        p = ctx.new_page()
        errors: list[str] = []
        p.on("pageerror", lambda exc: errors.append(str(exc)))
        p.goto(replay[1])
        p.wait_for_function("() => window.gcs && window.gcs.ready", timeout=UI_DEADLINE * 1000)
        yield p
        assert errors == []


def api(page: Any, path: str) -> Any:
    return page.evaluate(f"fetch('/api/{path}', {{cache: 'no-store'}}).then(r => r.json())")


def seek(page: Any, station: Child, seconds: float) -> dict[str, Any]:
    """Seek with the page's slider, as an operator does; the station's status after it."""
    page.evaluate(
        "(s) => { const el = document.querySelector('#replay-seek');"
        " el.value = String(s); el.dispatchEvent(new Event('change')); }",
        seconds,
    )
    return dict(
        poll(
            lambda: (r := api(page, "replay")) and abs(r["position_s"] - seconds) < 0.01 and r,
            f"the station at {seconds} s",
            UI_DEADLINE,
            [station],
        )
    )


def header(page: Any) -> tuple[str, str, float]:
    el = page.locator("#link-status")
    return el.inner_text(), el.get_attribute("data-status"), float(el.get_attribute("data-time") or "nan")


def log_entries(page: Any) -> list[tuple[str, str]]:
    return [
        tuple(x)
        for x in page.evaluate(
            "Array.from(document.querySelectorAll('#log li')).map(li =>"
            " [li.querySelector('.kind').textContent, li.querySelector('.text').textContent])"
        )
    ]


def shows(page: Any, status: dict[str, Any]) -> bool:
    """The page's header, count and log are those of the station at ``status``."""
    text, state, t = header(page)
    st = api(page, "state")
    up = sum(1 for a in st["agents"] if a["connected"])
    # as sets: records stamped alike (frames that shared one radio packet) log once
    want_log = {(e["kind"], e["text"]) for e in st["events"]}
    return (
        text.startswith("REPLAY ")
        and state == "replay"
        and abs(t - status["time"]) < 0.01
        and page.inner_text("#agent-count") == f"{up}/{len(st['agents'])} agents connected"
        and set(log_entries(page)) == want_log
    )


@pytest.mark.processes
def test_replay_shows_capture_time_count_and_rebuilds_the_log_on_seek(
    replay: tuple[Child, str], page: Any
) -> None:
    station = replay[0]
    start = api(page, "replay")
    assert start["position_s"] == 0 and start["playing"] is False and start["time"] == start["start"]
    poll(lambda: header(page)[0].startswith("REPLAY "), '"REPLAY" instead of "live"', UI_DEADLINE, [station])
    assert "live" not in header(page)[0]

    # well into the flight: agents connected, the leader elected, events in capture time
    late = seek(page, station, 60.0)
    assert late["time"] == pytest.approx(start["start"] + 60.0, abs=0.01)
    poll(lambda: shows(page, late), "the page at 60 s", UI_DEADLINE, [station])
    st = api(page, "state")
    assert st["time"] == pytest.approx(late["time"], abs=0.01)  # capture time, not wall time
    up_late = sum(a["connected"] for a in st["agents"])
    assert up_late >= 3
    assert st["events"] and all(start["start"] <= e["t"] <= late["time"] for e in st["events"])
    radio = late["radio"]  # the station radio's link quality, as the capture holds it
    assert radio is not None
    assert f"radio RSSI {radio['rssi']}/{radio['remrssi']}" in page.inner_text("#replay-time")
    late_log = log_entries(page)
    assert any(k == "leader" for k, _ in late_log), late_log
    screenshot(page, "replay_page_60s.png")

    # back to the first agents heard: the count and the log are those of that moment
    early = seek(page, station, 2.0)
    poll(lambda: shows(page, early), "the page at 2 s", UI_DEADLINE, [station])
    st = api(page, "state")
    assert all(e["t"] <= early["time"] for e in st["events"])
    assert 0 < sum(a["connected"] for a in st["agents"]) < up_late
    early_log = log_entries(page)
    assert len(early_log) < len(late_log) and not any(k == "leader" for k, _ in early_log), early_log
    # the map too: only the agents heard by then, no leader mark from later
    heard = {a["id"] for a in st["agents"]}
    poll(
        lambda: set(page.evaluate("window.gcs.agents")) == heard,
        "the agents of 2 s on the page",
        UI_DEADLINE,
        [station],
    )
    assert page.locator(".agent-marker.leader").count() == 0
    screenshot(page, "replay_page_2s.png")
