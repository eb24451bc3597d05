"""The ground station page in a real headless browser (Debian's chromium driven by
Playwright), against a running bench: the radio emulator, simulated vehicles,
``swarm agent`` processes on the radios and ``swarm gcs`` on the last radio, with
map tiles from an offline folder the test writes.

The page shows one marker per agent and the leader; selecting an agent (in the
list or on the map) shows its telemetry; a go-to command moves it on the map; a
disconnected agent turns grey and a command to it is refused with the reason on
the page. A station with no tiles and no agents still works, refuses a follow
with no leader, and the page reconnects when the station comes back.

Every wait polls for an outcome until a generous deadline; no duration is asserted.
Screenshots are kept in ``test-artifacts/``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from gcs_browser import (
    browser,
    distance_m,
    new_page,
    poll,
    screenshot,
    start_station,
    write_tiles,
)
from net_helpers import free_port, free_port_range

from radios.errors import CaptureDamagedError
from radios.tlog import TlogWriter, read_tlog
from swarm.cli.procs import Child, start_emulator

pytestmark = pytest.mark.processes  # a browser against a bench of processes

N = 3
HOME = (47.397742, 8.545594)  # the simulator's default home (PX4 SITL's)
SPACING_M = 30  # apart enough that markers do not overlap at zoom 18
START_DEADLINE = 30.0
SHOW_DEADLINE = 90.0  # radio hop lock, GSAdvertize, connect, first telemetry
ELECT_DEADLINE = 90.0
MOVE_DEADLINE = 90.0
DROP_DEADLINE = 30.0  # station's telemetry timeout: 3 heartbeats (at least 2 s)
UI_DEADLINE = 15.0


@dataclass
class Bench:
    url: str
    capture: Path
    station: Child
    agents: list[Child]
    children: list[Child]


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Bench]:
    root = tmp_path_factory.mktemp("gcs-page")
    tiles = root / "tiles"
    write_tiles(tiles, *HOME)
    radios = root / "radios"
    radios.mkdir()
    capture = root / "air.tlog"
    emu, paths = start_emulator(N + 1, radios, "--capture", str(capture))
    children: list[Child] = []
    try:
        base = free_port_range(N, "udp")  # the simulator's vehicles
        sim = Child(
            ["sim", "--vehicles", str(N), "--spacing", str(SPACING_M), "--base-port", str(base)], name="sim"
        )
        children.append(sim)
        fcs = [line.split(" -> ")[1].split()[0] for line in sim.wait_lines(N + 1, START_DEADLINE)[:N]]
        agents = []
        for k in range(1, N + 1):
            agents.append(
                Child(
                    [
                        "agent",
                        "--name",
                        f"agent{k}",
                        "--id",
                        str(k),
                        "--radio",
                        paths[k - 1],
                        "--fc",
                        fcs[k - 1],
                        "--json",
                    ],
                    name=f"agent{k}",
                )
            )
        children += agents
        for a in agents:
            assert json.loads(a.wait_lines(1, START_DEADLINE)[0])["event"] == "ready"
        station, url = start_station(
            ["--radio", paths[N], "--http", f"127.0.0.1:{free_port()}", "--tiles-dir", str(tiles)]
        )
        children.append(station)
        yield Bench(url, capture, station, agents, children)
    finally:
        for c in reversed(children):
            c.stop(grace=3)
        emu.stop()


@pytest.fixture(scope="module")
def ctx() -> Iterator[Any]:
    with browser() as context:
        yield context


@pytest.fixture
def page(ctx: Any) -> Iterator[Any]:
    with new_page(ctx) as p:  # keeps the page's script errors in p.errors
        yield p


def gcs(page: Any, expr: str) -> Any:
    return page.evaluate(f"window.gcs.{expr}")


def field(page: Any, name: str) -> str:
    return str(page.inner_text(f'#telemetry [data-field="{name}"]')).strip()


def open_page(page: Any, url: str) -> None:
    page.goto(url)
    page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=UI_DEADLINE * 1000)


def test_page_shows_every_agent_its_telemetry_and_the_leader(bench: Bench, page: Any) -> None:
    open_page(page, bench.url)
    poll(lambda: gcs(page, "markers") == N, f"{N} markers on the map", SHOW_DEADLINE, bench.children)
    for k in range(1, N + 1):
        assert page.locator(f'.agent-marker[data-agent-id="{k}"]').count() == 1
        assert page.locator(f'#agents [data-agent-id="{k}"]').count() == 1

    # the leader: one marker and one list row marked, the one the station names
    def leader_marked() -> int | None:
        lead = gcs(page, "leader")
        marked = page.locator(".agent-marker.leader").all()
        if not lead or len(marked) != 1 or marked[0].get_attribute("data-agent-id") != str(lead):
            return None
        return int(lead)

    leader = poll(leader_marked, "one leader marked on the map", ELECT_DEADLINE, bench.children)
    assert page.locator(f'#agents [data-agent-id="{leader}"] .lead').is_visible()
    assert f"agent{leader}" in page.inner_text("#election [data-field='leader']")

    # the offline tiles were drawn
    poll(
        lambda: page.evaluate(
            "Array.from(document.querySelectorAll('img.leaflet-tile-loaded'))"
            ".some(i => i.src.includes('/tiles/'))"
        ),
        "an offline tile drawn",
        UI_DEADLINE,
    )

    # select in the list: the telemetry panel fills in
    page.click('#agents [data-agent-id="2"]')
    assert page.get_attribute("#telemetry", "data-agent-id") == "2"
    poll(
        lambda: all(field(page, f) != "—" for f in ("mode", "alt", "heading", "battery", "last_seen")),
        "agent2's telemetry",
        UI_DEADLINE,
    )
    assert "m" in field(page, "alt") and "%" in field(page, "battery")
    assert field(page, "armed") in ("armed", "disarmed")
    assert "s ago" in field(page, "last_seen")
    assert "/" in field(page, "rssi")
    assert page.locator('.agent-marker[data-agent-id="2"].selected').count() == 1

    # select on the map
    page.click('.agent-marker[data-agent-id="3"]')
    poll(
        lambda: page.get_attribute("#telemetry", "data-agent-id") == "3",
        "agent3 selected from its marker",
        UI_DEADLINE,
    )
    assert "agent3" in page.inner_text("#telemetry-title")
    shot = screenshot(page, "gcs_page.png")
    assert shot.stat().st_size > 10_000
    assert page.errors == []


def test_goto_from_the_page_moves_the_agent_on_the_map(bench: Bench, page: Any) -> None:
    open_page(page, bench.url)
    poll(lambda: gcs(page, "markers") == N, f"{N} markers on the map", SHOW_DEADLINE, bench.children)
    page.click('#agents [data-agent-id="1"]')
    page.select_option("#cmd-target", "selected")

    def accepted(kind: str) -> bool:
        text = page.inner_text("#cmd-status")
        if kind in text and "refused" in text:
            raise AssertionError(f"{kind} refused: {text}")
        # the agent's yes, then what the station follows on the vehicle (in progress, done)
        return kind in text and (text.endswith("accepted") or ": in progress" in text or ": done" in text)

    page.click('#commands [data-kind="arm"]')
    poll(lambda: accepted("arm"), "arm accepted", MOVE_DEADLINE, bench.children)
    page.fill("#takeoff-alt", "10")
    page.click('#commands [data-kind="takeoff"]')
    page.click("#confirm-ok")  # a take-off is asked about first
    poll(lambda: accepted("takeoff"), "takeoff accepted", MOVE_DEADLINE, bench.children)
    # take-off done: the agent holds its position under setpoint control (PX4 OFFBOARD)
    poll(
        lambda: "airborne" in field(page, "alt") and field(page, "mode") == "OFFBOARD",
        "agent1 airborne in OFFBOARD",
        MOVE_DEADLINE,
        bench.children,
    )

    # click on the map 80 px north of the agent: the go-to fields fill in
    start = gcs(page, "markerLatLng(1)")
    box = page.locator('.agent-marker[data-agent-id="1"]').bounding_box()
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2 - 80)
    target = [float(page.input_value("#goto-lat")), float(page.input_value("#goto-lon"))]
    assert page.locator("#goto-target").count() == 1
    far = distance_m(start, target)
    assert far > 10, (start, target)
    page.click("#goto-go")
    poll(lambda: accepted("goto"), "goto accepted", MOVE_DEADLINE, bench.children)

    def moved() -> bool:
        now = gcs(page, "markerLatLng(1)")
        return distance_m(now, target) < far / 2 and distance_m(now, start) > far / 3

    poll(moved, "agent1 to cover half the way to the target on the map", MOVE_DEADLINE, bench.children)
    screenshot(page, "gcs_page_goto.png")
    assert page.errors == []


def whole_records(src: Path, dst: Path) -> int:
    """Copy the whole records of a capture still being written (its end may be cut)."""
    n = 0
    with TlogWriter(dst) as out:
        try:
            for rec in read_tlog(src):
                out.write(rec.raw, rec.t)
                n += 1
        except CaptureDamagedError:
            pass
    return n


def test_replay_of_the_bench_capture_with_pause_and_speed(bench: Bench, page: Any, tmp_path: Path) -> None:
    # the air so far: agents electing, connecting to the station, flying
    poll(
        lambda: bench.capture.exists() and bench.capture.stat().st_size > 10_000,
        "a capture",
        SHOW_DEADLINE,
        bench.children,
    )
    capture = tmp_path / "flight.tlog"
    assert whole_records(bench.capture, capture) > 0
    station, url = start_station(
        ["--replay", str(capture), "--http", f"127.0.0.1:{free_port()}", "--tiles", "none", "--speed", "4"]
    )
    try:
        open_page(page, url)
        assert gcs(page, "config")["replay"] is True
        assert page.locator("#replay").is_visible()
        poll(lambda: gcs(page, "markers") >= 1, "agents of the capture on the map", UI_DEADLINE, [station])
        poll(
            lambda: page.get_attribute("#replay-play", "data-playing") in ("0", "1"),
            "the replay status",
            UI_DEADLINE,
            [station],
        )
        if page.get_attribute("#replay-play", "data-playing") == "1":
            page.click("#replay-play")  # pause
            poll(
                lambda: page.get_attribute("#replay-play", "data-playing") == "0",
                "paused",
                UI_DEADLINE,
                [station],
            )
        page.select_option("#replay-speed", "2")
        poll(
            lambda: page.evaluate("fetch('/api/replay').then(r => r.json())")["speed"] == 2,
            "speed 2 at the station",
            UI_DEADLINE,
            [station],
        )
        page.click("#replay-play")  # play
        poll(
            lambda: page.evaluate("fetch('/api/replay').then(r => r.json())")["playing"] is True,
            "playing at the station",
            UI_DEADLINE,
            [station],
        )
        # nothing to command in a replay
        assert page.locator('#commands [data-kind="land"]').is_disabled()
        assert page.locator("#goto-go").is_disabled()
        assert page.locator("#hold-all").is_disabled()
        screenshot(page, "gcs_page_replay.png")
        assert page.errors == []
    finally:
        station.stop()


def test_disconnected_agent_is_greyed_and_a_command_to_it_refused(bench: Bench, page: Any) -> None:
    open_page(page, bench.url)
    poll(lambda: gcs(page, "markers") == N, f"{N} markers on the map", SHOW_DEADLINE, bench.children)
    gone = bench.agents[-1]
    k = N
    gone.stop(grace=3)
    marker = f'.agent-marker[data-agent-id="{k}"]'
    poll(
        lambda: page.locator(f'{marker}.disconnected[data-connected="0"]').count() == 1,
        f"agent{k} greyed on the map",
        DROP_DEADLINE,
        [bench.station],
    )
    assert page.locator(f'#agents [data-agent-id="{k}"].disconnected').count() == 1
    page.click(f'#agents [data-agent-id="{k}"]')
    page.fill("#goto-lat", f"{HOME[0] + 0.0005:.7f}")
    page.fill("#goto-lon", f"{HOME[1]:.7f}")
    page.click("#goto-go")
    poll(
        lambda: "not connected" in page.inner_text("#cmd-status"),
        "the refusal's reason on the page",
        UI_DEADLINE,
        [bench.station],
    )
    assert "refused" in (page.get_attribute("#cmd-status", "class") or "")
    assert page.locator("#log li.refused", has_text="not connected").count() >= 1
    screenshot(page, "gcs_page_refused.png")
    assert page.errors == []


def test_station_without_tiles_or_agents_still_works_and_reconnects(tmp_path: Path, page: Any) -> None:
    port = free_port()
    argv = [
        "--zenoh-listen",
        f"tcp/127.0.0.1:{free_port()}",
        "--http",
        f"127.0.0.1:{port}",
        "--tiles",
        "none",
    ]
    station, url = start_station(argv)
    try:
        open_page(page, url)
        assert gcs(page, "config")["tiles"] is None
        assert "no-tiles" in (page.get_attribute("#map", "class") or "")
        assert page.locator("img.leaflet-tile").count() == 0
        poll(
            lambda: gcs(page, "wsStatus") == "live" and gcs(page, "stateCount") > 0,
            "live state",
            UI_DEADLINE,
            [station],
        )
        assert page.locator("#agents .empty").count() == 1
        # follow in V with no leader: refused, and the reason is on the page
        page.select_option("#cmd-target", "swarm")
        page.click('#commands [data-kind="follow"]')
        page.click("#confirm-ok")  # every swarm command is asked about first
        poll(
            lambda: "no leader" in page.inner_text("#cmd-status"),
            "the follow refusal on the page",
            UI_DEADLINE,
            [station],
        )
        assert page.locator("#log li.refused", has_text="no leader").count() >= 1
        screenshot(page, "gcs_page_no_tiles.png")

        # the station goes away and comes back on the same address: the page reconnects
        station.stop()
        poll(lambda: gcs(page, "wsStatus") == "reconnecting", "the page to notice", UI_DEADLINE)
        station, url2 = start_station(argv)
        assert url2 == url
        count = gcs(page, "stateCount")
        poll(
            lambda: gcs(page, "wsStatus") == "live" and gcs(page, "stateCount") > count,
            "the page live again",
            UI_DEADLINE * 2,
            [station],
        )
        assert page.errors == []
    finally:
        station.stop()
