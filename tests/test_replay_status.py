"""The replay station's status on the checked-in demo capture (in process, a fake clock):
the capture's time at the play position, the seek count the page rebuilds its log on, the
station radio's RADIO_STATUS, and a seek back that forgets what came later."""

from __future__ import annotations

from pathlib import Path

import pytest

from swarm.runtime.station.replay import ReplayStation, load_capture

DEMO = Path(__file__).resolve().parent / "data" / "demo" / "demo.tlog"


@pytest.fixture(scope="module")
def station() -> ReplayStation:
    return ReplayStation(load_capture(str(DEMO)), playing=False, clock=lambda: 0.0)


def test_status_in_capture_time_with_the_station_radios_link(station: ReplayStation) -> None:
    station.seek(0.0)
    s0 = station.status()
    assert s0["time"] == s0["start"] == pytest.approx(station.capture.t0, abs=1e-3)
    assert s0["radio"] is None  # nothing heard from the radio yet
    station.seek(60.0)
    s = station.status()
    assert s["time"] == pytest.approx(s0["start"] + 60.0, abs=1e-3) and s["seeks"] == s0["seeks"] + 1
    radio = s["radio"]
    assert radio is not None and {"rssi", "remrssi", "noise", "remnoise", "txbuf", "rxerrors"} <= radio.keys()
    assert s0["start"] < radio["t"] <= s["time"]
    snap = station.snapshot()
    assert snap["time"] == pytest.approx(s["time"], abs=1e-3)  # the state's time is the capture's
    assert all(s0["start"] <= e["t"] <= s["time"] for e in snap["events"])


def test_seek_back_forgets_what_came_later(station: ReplayStation) -> None:
    station.seek(60.0)
    late = station.snapshot()
    station.seek(2.0)
    early = station.snapshot()
    st = station.status()
    assert len(early["events"]) < len(late["events"])
    assert all(e["t"] <= st["time"] for e in early["events"])
    assert sum(a["connected"] for a in early["agents"]) < sum(a["connected"] for a in late["agents"])
    assert st["radio"] is None or st["radio"]["t"] <= st["time"]
