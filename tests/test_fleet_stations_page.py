"""Stations joined through a real Zenoh router (issue 16): another station's alerts and
swarms on this station's API and page (headless Chromium), and a hostile station.

Station A and station B are real fleets (one channel each: a real station with agents
speaking the real connection protocol, each swarm's leader at 10 % battery: a critical
alert), joined with one key through a router; A serves the page. A third "station",
``evil``, holds the key too (a station taken over) and publishes, through the real
federation, a state whose alerts are a flood of HTML-bearing, oversized and malformed
entries, and a swarm numbered with colour 0 as A's and B's are.

* A's API and page show B's alert marked "station gcsB"; the evil alerts come bounded,
  plain text, their junk dropped; nothing of them is parsed as HTML on the page;
* an acknowledgement of B's alert on A's page reaches B (B's own state says so);
* the three swarms (each station's colour 0) show three colours on A's page, the same
  on A's and B's views.

Screenshot: ``test-artifacts/gcs_stations.png``.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any

import pytest
from gcs_browser import browser, new_page, poll, screenshot
from net_helpers import free_port, wait_until
from test_fleet_view import LowBattery
from test_gcs_api import ScriptedAgent

from swarm.cli.commands.router import open_router
from swarm.core.flight.geofence import Geofence
from swarm.core.station.federation import MAX_ALERTS, fed_key
from swarm.core.wire.message_types import Phase
from swarm.runtime.station.federation import Federation
from swarm.runtime.station.fleet import Fleet
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

pytestmark = pytest.mark.processes  # stations, a router and a browser

KEY = fed_key(b"s" * 32)
DEADLINE = 30.0
INJECT = '<img src=x onerror="window.__pwned=1"><script>window.__pwned=2</script>'


def hostile_state() -> dict[str, Any]:
    junk: list[Any] = ["x", None, 7, [1], {"id": "1"}, {"id": 3, "raised": "now", "text": "t"}]
    alerts = [
        {"id": i, "kind": "<b>", "agent": 31, "level": "warning", "text": INJECT + "y" * 300,
         "raised": 1.0e9 + i, "onclick": INJECT}
        for i in range(1200)
    ]  # fmt: skip
    return {
        "agents": [{"id": 31, "name": "a31", "connected": True, "leader": 31}],
        "events": [],
        "swarms": [{"leader": 31, "members": [31], "colour": 0, "net": "ev"}],
        "alerts": junk * 20 + alerts,
    }


def fleet(stack: ExitStack, name: str, router: str, agents: dict[int, int]) -> Fleet:
    ep = f"tcp/127.0.0.1:{free_port()}"
    f = Fleet(name, 255, [(f"{name}-net", Station(name, zenoh_listen=[ep]))], Geofence())
    f.federation = Federation(
        name, connect=[router], key=KEY, local=f.local_state, run_local=f.run_local, on_event=f.note
    )
    stack.callback(f.stop)
    f.start()
    for aid, lead in agents.items():
        cls = LowBattery if aid == lead else ScriptedAgent
        a = cls(ep, aid, phase=Phase.LEADER if aid == lead else Phase.MEMBER, leader=lead)
        stack.callback(a.close)
    return f


@dataclass
class Live:
    a: Fleet
    b: Fleet
    url: str = ""
    errors: list[str] = field(default_factory=list)


def refuse(_body: Any) -> Future[tuple[int, dict[str, Any]]]:
    f: Future[tuple[int, dict[str, Any]]] = Future()
    f.set_result((403, {"ok": False, "error": "no"}))
    return f


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    with ExitStack() as stack:
        router = f"tcp/127.0.0.1:{free_port()}"
        stack.callback(open_router([router], []).close)
        a = fleet(stack, "gcsA", router, {1: 1, 2: 1})
        b = fleet(stack, "gcsB", router, {21: 21, 22: 21})
        evil = Federation("evil", connect=[router], key=KEY, local=hostile_state, run_local=refuse)
        stack.callback(evil.stop)
        evil.start()
        server = GcsServer(a, ServerConfig(port=free_port())).start()
        stack.callback(server.stop)

        def ready() -> bool:
            s = a.snapshot()
            swarms = {(w["station"], w["leader"]) for w in s["swarms"]}
            stations = {al.get("station") for al in s["alerts"] if al["kind"] == "battery"}
            return swarms == {("gcsA", 1), ("gcsB", 21), ("evil", 31)} and stations >= {"gcsA", "gcsB"}

        wait_until(ready, "A to show the three stations' swarms and B's battery alert", DEADLINE)
        yield Live(a, b, server.url)


def test_another_stations_alerts_reach_the_api_bounded_and_plain(live: Live) -> None:
    alerts = live.a.snapshot()["alerts"]
    b = [al for al in alerts if al["station"] == "gcsB"]
    assert [(al["kind"], al["level"], al["agent"]) for al in b] == [("battery", "critical", 21)]
    evil = [al for al in alerts if al["station"] == "evil"]
    assert 0 < len(evil) <= MAX_ALERTS
    assert all(len(al["text"]) <= 200 and al["kind"] == "other" and "onclick" not in al for al in evil)
    assert {al["station"] for al in alerts} == {"gcsA", "gcsB", "evil"}


def test_the_page_shows_them_marked_injects_nothing_and_acknowledges_at_their_station(live: Live) -> None:
    with browser() as ctx, new_page(ctx) as page:
        page.set_viewport_size({"width": 1280, "height": 800})
        page.goto(live.url)
        page.wait_for_function("() => window.gcs && window.gcs.ready && window.gcsAlerts", timeout=15_000)
        row = "#alerts-banner .alert[data-station='gcsB'][data-kind='battery']"
        poll(lambda: page.locator(row).count() == 1, "B's alert in A's banner", DEADLINE)
        assert page.locator(row + " .alert-station").text_content() == "station gcsB"
        # the banner keeps three rows (the criticals first): evil's warnings are in the list
        page.click("#alarms-button")
        evil = "#alarms-panel .alarm[data-station='evil']"
        poll(lambda: page.locator(evil).count() > 0, "evil's alerts in A's alarm list", DEADLINE)
        shown = page.locator(evil + " .alert-text").first.text_content()
        assert shown is not None and shown.startswith(INJECT)  # shown as text
        places = "#alerts-banner img, #alerts-banner script, #alarms-panel img, #alarms-panel script"
        assert page.evaluate(f"document.querySelectorAll('{places}').length") == 0
        assert page.evaluate("window.__pwned") is None
        screenshot(page, "gcs_stations.png")
        page.click("#alarms-panel .alarms-close")
        # acknowledged on A's page: carried to B, B's own state says so
        page.locator(row + " button.alert-ack").click()

        def acked_at_b() -> bool:
            return any(al["kind"] == "battery" and al["acked"] for al in live.b.snapshot()["alerts"])

        wait_until(acked_at_b, "B's alert acknowledged at B", 2 * DEADLINE)  # an unanswered ack is sent again
        poll(lambda: page.locator(row).count() == 0, "it leaves A's banner", DEADLINE)
        assert page.locator("#alerts-banner .alert[data-station=''][data-kind='battery']").count() == 1
        assert page.errors == []


def test_three_stations_swarms_show_three_colours_the_same_on_every_view(live: Live) -> None:
    def colours(f: Fleet) -> dict[tuple[str, int], int]:
        return {(w["station"], w["leader"]): w["colour"] for w in f.snapshot()["swarms"]}

    on_a = colours(live.a)
    assert len(set(on_a.values())) == 3 and {w["station_colour"] for w in live.a.snapshot()["swarms"]} == {0}
    wait_until(lambda: colours(live.b) == on_a, "B's view in the same colours", DEADLINE)
    with browser() as ctx, new_page(ctx) as page:
        page.goto(live.url)
        page.wait_for_function("() => window.gcs && window.gcs.ready && window.gcsSwarms", timeout=15_000)
        rows = """() => Array.from(document.querySelectorAll('#agents tbody tr[data-agent-id]'))
            .map((r) => [r.dataset.swarm, r.dataset.colour])"""

        def by_swarm() -> dict[str, set[str]] | None:
            got: dict[str, set[str]] = {}
            for swarm, colour in page.evaluate(rows):
                got.setdefault(swarm, set()).add(colour)
            return got if set(got) == {"1", "21", "31"} else None

        got = poll(by_swarm, "the three swarms in the fleet table", DEADLINE)
        assert all(len(c) == 1 for c in got.values())  # one colour per swarm
        assert len({next(iter(c)) for c in got.values()}) == 3  # three swarms, three colours
        cell = page.locator('#agents tr[data-agent-id="22"] td[data-field="swarm"]').text_content()
        assert cell is not None and "station gcsB" in cell
        options = "Array.from(document.querySelectorAll('#cmd-target option')).map((o) => o.text)"
        labels = page.evaluate(options)
        assert "swarm of agent21 (21) at station gcsB · 2 agents" in labels
        assert "swarm of agent1 (1) · 2 agents" in labels  # this station's own: no station named
        # other stations' events in the log, marked with their station
        kinds = "Array.from(document.querySelectorAll('#log li .kind')).map((k) => k.textContent)"
        poll(lambda: "gcsB · alert" in page.evaluate(kinds), "B's alert event marked in A's log", DEADLINE)
        assert page.errors == []


def test_a_bad_acknowledgement_for_another_station_is_one_line(live: Live) -> None:
    from swarm.core.station.commands import CommandRefused
    from swarm.core.station.federation import ack_any

    b_alert = next(al for al in live.a.snapshot()["alerts"] if al["station"] == "gcsB")
    for alert_id, station, status in (
        ("1", "gcsB", 400),
        (True, "gcsB", 400),
        (10**9, "gcsB", 404),
        (b_alert["id"], "nowhere", 404),
        (b_alert["id"], "<b>" + "x" * 500, 404),
        (b_alert["id"], ["gcsB"], 404),
    ):
        with pytest.raises(CommandRefused) as e:
            ack_any(live.a, alert_id, station)
        assert e.value.status == status and "\n" not in e.value.reason and len(e.value.reason) < 120
