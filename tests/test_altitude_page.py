"""Acceptance: altitudes above home, on a real bench, from the page in headless Chromium.

A ``swarm sim`` vehicle at a home 584 m above sea level (the recorded ArduPilot field's
height), a ``swarm agent`` flying it and ``swarm gcs``, over Zenoh on loopback. The
station's own floor is 0.5 m, the agent's the default 2 m. The operator takes off, then
sends Gos below a floor: at 0.2 m above home (and 20 m AMSL through the API) the station
refuses it and sends nothing; at 1 m the station sends it and the agent refuses it. Each
reason is shown on the page and the vehicle does not come down. A Go at 20 m above home
flies it to 20 m above home, the page showing that height with its AMSL beside it.
Then the station is stopped and a new one started while the vehicle flies: it never
saw the vehicle on the ground, and its page shows the same 20 m above home (the agent's
autopilot says it), never AMSL in the same column, with the GPS fix and satellites.
Screenshots in ``test-artifacts/``.
"""

from __future__ import annotations

import json
import re
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from gcs_browser import browser, poll, screenshot, start_station
from net_helpers import free_port, free_port_range

from swarm.cli.procs import Child
from swarm.core.flight.formation import offset

pytestmark = pytest.mark.processes  # a browser against a bench of processes

HOME = (47.397742, 8.545594, 584.0)
DEADLINE = 90.0


@dataclass
class Bench:
    url: str
    children: list[Child]
    ep: str


@pytest.fixture(scope="module")
def bench() -> Iterator[Bench]:
    children: list[Child] = []
    try:
        sim = Child(
            [
                "sim",
                "--vehicles",
                "1",
                "--base-port",
                str(free_port_range(1, "udp")),
                f"--home={HOME[0]},{HOME[1]},{HOME[2]}",
            ],
            name="sim",
        )
        children.append(sim)
        fc = sim.wait_lines(2, DEADLINE)[0].split(" -> ")[1].split()[0]
        ep = f"tcp/127.0.0.1:{free_port()}"
        agent = Child(
            ["agent", "--name", "agent1", "--id", "1", "--zenoh-connect", ep, "--fc", fc, "--json"],
            name="agent1",
        )
        children.append(agent)
        assert json.loads(agent.wait_lines(1, DEADLINE)[0])["event"] == "ready"
        station, url = start_station(
            [
                "--zenoh-listen",
                ep,
                "--http",
                f"127.0.0.1:{free_port()}",
                "--tiles",
                "none",
                "--fence-floor",
                "0.5",
            ]
        )
        children.append(station)
        yield Bench(url, children, ep)
    finally:
        for c in reversed(children):
            c.stop(grace=3)


def api_agent(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "api/agents/1", timeout=30) as r:
        return dict(json.loads(r.read()))


def above_home(url: str) -> float | None:
    a = api_agent(url)
    return None if a["alt"] is None or a["home_alt"] is None else float(a["alt"] - a["home_alt"])


def post(url: str, body: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    req = urllib.request.Request(
        url + "api/command", json.dumps(body).encode(), {"Content-Type": "application/json"}, method="POST"
    )
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def status(page: Any) -> str:
    return str(page.inner_text("#cmd-status"))


def accepted(page: Any, kind: str) -> bool:
    text = status(page)
    if kind in text and "refused" in text:
        raise AssertionError(text)
    # the agent's yes, then what the station follows on the vehicle (in progress, done)
    return kind in text and (text.endswith("accepted") or ": in progress" in text or ": done" in text)


def take_off(page: Any, url: str, kids: list[Child]) -> None:
    """Select agent1 once its home is seen on the ground, arm it and take off to 10 m."""
    poll(lambda: page.locator('#agents [data-agent-id="1"]').count() == 1, "agent1 listed", DEADLINE, kids)
    poll(lambda: api_agent(url)["home_alt"] is not None, "agent1's home seen", DEADLINE, kids)
    assert api_agent(url)["home_alt"] == pytest.approx(HOME[2], abs=1.0)
    page.click('#agents [data-agent-id="1"]')
    page.select_option("#cmd-target", "selected")
    page.click('#commands [data-kind="arm"]')
    poll(lambda: accepted(page, "arm"), "arm accepted", DEADLINE, kids)
    page.fill("#takeoff-alt", "10")
    page.click('#commands [data-kind="takeoff"]')
    page.click("#confirm-ok")  # a take-off is asked about first
    poll(lambda: accepted(page, "takeoff"), "take-off accepted", DEADLINE, kids)
    poll(lambda: (above_home(url) or 0.0) > 8.0, "agent1 10 m above home", DEADLINE, kids)


def refused_below_the_floors(page: Any, url: str, kids: list[Child]) -> None:
    """Gos under the station's floor (on the page and as AMSL through the API) and under
    the agent's: each refused with its reason; the vehicle stays up."""
    lat, lon = offset(HOME[0], HOME[1], 20.0, 0.0)
    page.fill("#goto-lat", f"{lat:.7f}")
    page.fill("#goto-lon", f"{lon:.7f}")
    page.fill("#goto-alt", "0.2")
    poll(
        lambda: "584.2 m AMSL" in page.inner_text("#goto-amsl"),
        "the AMSL beside the altitude",
        DEADLINE,
        kids,
    )
    page.click("#goto-go")
    poll(lambda: "station's geofence" in status(page), "the station's refusal on the page", 30, kids)
    assert "refused" in status(page) and "below the floor (0.5 m above home)" in status(page)
    screenshot(page, "altitude_floor_refused_by_station.png")
    # 20 m AMSL, named as such through the API: 564 m under home, refused, nothing sent
    st, body = post(url, {"target": 1, "kind": "goto", "lat": lat, "lon": lon, "alt_amsl": 20})
    assert st == 400 and "-564 m above home is below the floor" in body["error"], body
    # 1 m above home: inside the station's fence, under the agent's: the agent refuses it
    page.fill("#goto-alt", "1")
    page.click("#goto-go")
    poll(lambda: "BAD_ARGUMENT" in status(page), "the agent's refusal on the page", DEADLINE, kids)
    assert "below the floor (2 m above home)" in status(page) and "station's geofence" not in status(page)
    assert page.locator("#log li.refused", has_text="below the floor (2 m").count() >= 1
    screenshot(page, "altitude_floor_refused_by_agent.png")
    # the vehicle did not come down (it holds its 10 m while the refusals are looked at)
    for _ in range(10):
        h = above_home(url)
        assert h is not None and h > 8.0, h
        page.wait_for_timeout(200)


def test_a_go_below_the_floor_is_refused_and_a_go_at_20_m_flies_20_m_above_home(bench: Bench) -> None:
    url, kids = bench.url, bench.children
    with browser() as ctx:
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(url)
        page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=15000)
        take_off(page, url, kids)
        refused_below_the_floors(page, url, kids)
        # 20 m above home: flown there
        page.fill("#goto-alt", "20")
        page.click("#goto-go")
        poll(lambda: accepted(page, "goto"), "goto accepted", DEADLINE, kids)
        poll(lambda: abs((above_home(url) or 0.0) - 20.0) < 1.5, "agent1 at 20 m above home", DEADLINE, kids)
        shown = r"(19|20|21)\.\d m above home \(60[3-5]\.\d m AMSL\)"
        poll(
            lambda: re.search(shown, page.inner_text('#telemetry [data-field="alt"]')),
            "the page showing 20 m above home and its AMSL",
            15,
            kids,
        )
        screenshot(page, "altitude_go_20m_above_home.png")
        assert errors == []


def test_a_station_restarted_in_flight_shows_the_same_height_above_home(bench: Bench) -> None:
    """After the 20 m go-to when it ran first on this bench; else it flies there itself."""
    kids = bench.children

    def known() -> bool:
        try:
            return api_agent(bench.url)["home_alt"] is not None
        except urllib.error.HTTPError:  # 404 until the station hears agent1
            return False

    poll(known, "agent1 and its home", DEADLINE, kids)
    if abs((above_home(bench.url) or 0.0) - 20.0) >= 1.5:  # this worker's own bench: up to 20 m
        assert post(bench.url, {"target": 1, "kind": "arm"})[0] == 200
        poll(lambda: api_agent(bench.url)["armed"] is True, "agent1 armed", DEADLINE, kids)
        assert post(bench.url, {"target": 1, "kind": "takeoff", "alt": 20})[0] == 200
        poll(lambda: abs((above_home(bench.url) or 0.0) - 20.0) < 1.5, "agent1 at 20 m", DEADLINE, kids)
    old = kids.pop()  # the station: stopped, a new one on the same Zenoh endpoint
    old.stop(grace=3)
    station, url = start_station(
        ["--zenoh-listen", bench.ep, "--http", f"127.0.0.1:{free_port()}", "--tiles", "none"]
    )
    kids.append(station)

    def heard() -> bool:
        try:
            return api_agent(url)["rel_alt"] is not None
        except urllib.error.HTTPError:  # 404 until it hears agent1
            return False

    poll(heard, "the new station hears agent1's height", DEADLINE, kids)
    a = api_agent(url)
    assert abs(a["rel_alt"] - 20.0) < 1.5 and a["home_alt"] == pytest.approx(HOME[2], abs=1.0)
    assert (a["gps_fix"], a["satellites"]) == (3, 12)  # the simulated PX4's 3D fix
    with browser() as ctx:
        page = ctx.new_page()
        page.goto(url)
        page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=15000)
        cell = '#agents [data-agent-id="1"] td[data-field="alt"]'
        poll(lambda: page.locator(cell).count() == 1, "agent1's row", DEADLINE, kids)
        poll(
            lambda: re.match(r"(19|20|21)\.\d ✈", page.inner_text(cell)),
            "20 m above home in the table",
            15,
            kids,
        )
        assert "AMSL" not in page.inner_text(cell)
        gps = page.inner_text('#agents [data-agent-id="1"] td[data-field="gps"]')
        assert gps == "3D · 12 sat", gps
        page.click('#agents [data-agent-id="1"]')
        shown = r"(19|20|21)\.\d m above home \(60[3-5]\.\d m AMSL\)"
        poll(
            lambda: re.search(shown, page.inner_text('#telemetry [data-field="alt"]')), "the panel", 15, kids
        )
        screenshot(page, "altitude_after_station_restart.png")
