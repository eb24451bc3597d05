"""The alarm banner, list and sound on the real page (headless Chromium) over a real
station: two agents that speak the real station protocol over Zenoh, a healthy start
with no alarm, then criticals that sound once each while the sound is on and never
once it is switched off; the banner keeps its height under four alarms (the map keeps
its room), the list shows every alarm and shelves one after a confirmation (the
station says so, the banner drops it), and an advisory (a refused command) is listed
but never in the banner."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from gcs_browser import browser, new_page, poll, screenshot
from net_helpers import free_port, wait_until
from test_gcs_api import ScriptedAgent

from swarm.core.wire.codes import FLAG_ARMED, FLAG_FC_OK, FLAG_READY, FLAG_READY_KNOWN
from swarm.core.wire.message_types import AgentNotice, NoticeSource, Telemetry
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

pytestmark = pytest.mark.processes  # a station, two agents over Zenoh, a browser

DEADLINE = 30.0


class Agent(ScriptedAgent):
    """A scripted agent whose battery and flight-controller link the test sets."""

    battery = 80
    fc = True
    ready: bool | None = None

    def telemetry(self) -> Telemetry:
        t = super().telemetry()
        flags = FLAG_ARMED | (FLAG_FC_OK if self.fc else 0)
        if self.ready is not None:
            flags |= FLAG_READY_KNOWN | (FLAG_READY if self.ready else 0)
        return Telemetry(t.sender, t.pose, t.mode, flags, t.phase, t.leader, self.battery, 150, 140, 1.5)


@pytest.fixture
def live() -> Iterator[tuple[Station, str, list[Agent]]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    station = Station("gcs", zenoh_listen=[ep]).start()
    server = GcsServer(station, ServerConfig(port=free_port())).start()
    agents = [Agent(ep, 1), Agent(ep, 2)]
    try:
        wait_until(
            lambda: sum(a["connected"] for a in station.snapshot()["agents"]) == 2,
            "both agents connected",
            DEADLINE,
        )
        yield station, server.url, agents
    finally:
        for a in agents:
            a.close()
        server.stop()
        station.stop()


def banner_ids(page: Any) -> list[int]:
    return list(page.evaluate("() => window.gcsAlerts.open"))


def test_alarms_sound_once_keep_the_banner_small_and_shelve_from_the_list(
    live: tuple[Station, str, list[Agent]],
) -> None:
    station, url, (one, two) = live
    with browser() as ctx, new_page(ctx) as page:
        page.set_viewport_size({"width": 1400, "height": 900})
        page.on("dialog", lambda d: d.accept())
        page.goto(url)
        page.wait_for_function("() => window.gcs && window.gcs.ready && window.gcsAlerts", timeout=15_000)
        poll(lambda: page.evaluate("() => window.gcs.stateCount") > 2, "states on the page", DEADLINE)
        # a healthy start: no alarm at all, the banner hidden, nothing sounded
        assert station.snapshot()["alerts"] == []
        assert page.locator("#alerts-banner").is_hidden()
        map_h = page.locator("#map").bounding_box()["height"]

        # not ready to arm: the autopilot's reason is an advisory (listed, not in the banner)
        # and the ready cell's hover text
        one.ready = False
        cell = '#agents [data-agent-id="1"] td[data-field="ready"]'
        poll(lambda: page.inner_text(cell) == "not ready", "agent1 not ready", DEADLINE)

        def said() -> bool:
            if not any("PreArm" in a["text"] for a in station.snapshot()["alerts"]):
                one.tr.send("gcs", AgentNotice(1, NoticeSource.AUTOPILOT, 2, "PreArm: GPS not healthy"))
                return False
            return True

        poll(said, "the autopilot's reason at the station", DEADLINE)
        poll(
            lambda: "PreArm: GPS not healthy" in (page.get_attribute(cell, "title") or ""),
            "the reason",
            DEADLINE,
        )
        assert page.locator("#alerts-banner").is_hidden()  # an advisory: no banner, no sound
        one.ready = True

        two.battery = 10  # a new critical: in the banner, sounded once, its text spoken
        poll(lambda: len(banner_ids(page)) == 1, "the battery alarm in the banner", DEADLINE)
        poll(lambda: page.evaluate("() => window.gcsAlerts.sounded") == 1, "one sound", DEADLINE)
        assert "battery 10 %" in page.evaluate("() => window.gcsAlerts.spoken")[0]

        page.click("#sound-toggle")  # off: kept, and nothing sounds any more
        assert page.get_attribute("#sound-toggle", "aria-pressed") == "false"
        one.battery = 10
        one.fc = two.fc = False  # three more criticals: the vehicle links, the other battery
        poll(lambda: len(banner_ids(page)) == 4, "four alarms in the banner", DEADLINE)
        assert page.evaluate("() => window.gcsAlerts.sounded") == 1
        assert page.locator("#alerts-banner .alert").count() == 3
        assert page.locator("#alerts-banner .alerts-more").inner_text().startswith("and 1 more")
        box = page.locator("#alerts-banner").bounding_box()
        assert box["height"] < 130, box  # fixed: three rows, never a growing list over the map
        assert page.locator("#map").bounding_box()["height"] >= map_h - 140
        screenshot(page, "gcs_page_alarms.png")

        page.click("#alarms-button")  # the list: all four, each with its actions
        rows = page.locator("#alarms-panel .alarm")
        poll(lambda: rows.count() == 5, "the list's four alarms and the advisory", DEADLINE)
        bat = next(a for a in station.snapshot()["alerts"] if a["kind"] == "battery")
        row = page.locator(f"#alarms-panel .alarm[data-alert-id='{bat['id']}']")
        row.locator("button.alarm-shelve").first.click()  # 10 min, confirmed
        poll(
            lambda: (
                next(a for a in station.snapshot()["alerts"] if a["id"] == bat["id"])["quiet"] == "shelved"
            ),
            "the alarm shelved at the station",
            DEADLINE,
        )
        poll(lambda: bat["id"] not in banner_ids(page), "the shelved alarm out of the banner", DEADLINE)
        poll(lambda: row.get_attribute("data-state") == "shelved", "the list says shelved", DEADLINE)
        assert row.locator("button.alarm-unshelve").count() == 1
        screenshot(page, "gcs_page_alarm_list.png")

        page.click("#sound-toggle")  # on again
        assert page.get_attribute("#sound-toggle", "aria-pressed") == "true"

        def link_two() -> dict[str, Any]:
            return next(
                a for a in station.snapshot()["alerts"] if a["kind"] == "vehicle_link" and a["agent"] == 2
            )

        two.fc = True  # over, but latched: still in the banner until acknowledged
        poll(lambda: link_two()["cleared"] is not None, "agent 2's vehicle link back", DEADLINE)
        assert link_two()["id"] in banner_ids(page)
        two.fc = False  # back while still unacknowledged: the same alarm, counted, not announced again
        poll(
            lambda: any(
                a["kind"] == "vehicle_link" and a["agent"] == 2 and a["count"] == 2
                for a in station.snapshot()["alerts"]
            ),
            "the second occurrence counted on the same alarm",
            DEADLINE,
        )
        assert page.evaluate("() => window.gcsAlerts.sounded") == 1
        assert page.errors == []
