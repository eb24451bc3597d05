"""Alerts end to end, every part a real process: ``swarm sim --battery-drain`` (a PX4-like
vehicle whose battery falls several percent a second and whose autopilot then says
"Low battery level!" and "Critical battery level!" in STATUSTEXT), ``swarm agent`` on
it, ``swarm gcs`` with its own thresholds, and the page in headless Chromium.

The station must raise a battery alert from the agent's Telemetry and the autopilot's
STATUSTEXT alerts from the agent's notices; the page shows them in its banner and the
event log, and acknowledging them clears the banner (and the state says so)."""

from __future__ import annotations

import json
import urllib.request
from typing import Any

import pytest
from gcs_browser import browser, poll, screenshot, start_station
from net_helpers import free_port

from swarm.cli.procs import Child

pytestmark = pytest.mark.processes  # a simulator, an agent, a station and a browser

DEADLINE = 60.0  # simulator start, Zenoh, the connection, the drain


def state(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "api/state", timeout=10) as r:
        return dict(json.loads(r.read()))


def alert_kinds(url: str) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for a in state(url)["alerts"]:
        out.setdefault(a["kind"], set()).add(a["level"])
    return out


def check_the_station(url: str, children: list[Child]) -> None:
    """The battery alert (Telemetry) and both autopilot texts (the agent's notices)."""

    def raised() -> bool:
        k = alert_kinds(url)
        return k.get("battery") == {"critical"} and k.get("statustext") == {"warning", "critical"}

    poll(raised, "a critical battery alert and both autopilot battery texts", DEADLINE, children)
    texts = {a["text"] for a in state(url)["alerts"]}
    assert "flyer (3): Low battery level! Return advised" in texts, texts
    assert "flyer (3): Critical battery level! Land now" in texts, texts
    events = [e["text"] for e in state(url)["events"]]
    assert any("WARNING Low battery level!" in t for t in events), events
    assert any(t.startswith("WARNING: flyer (3): battery") for t in events), events


def check_the_page(url: str) -> None:
    """The banner shows them, the log has them, acknowledging clears the banner."""
    with browser() as ctx:
        page = ctx.new_page()
        page.goto(url)
        page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=15000)
        banner = page.locator("#alerts-banner")
        poll(lambda: banner.is_visible() and int(banner.get_attribute("data-count") or 0) >= 3, "banner", 30)
        assert banner.locator('.alert[data-kind="battery"][data-level="critical"]').count() == 1
        assert banner.locator('.alert[data-kind="statustext"]', has_text="Low battery level!").count() == 1
        assert page.locator("#log li", has_text="Critical battery level! Land now").count() >= 1
        screenshot(page, "gcs_page_alerts.png")
        first = banner.locator(".alert").first
        first_id = int(first.get_attribute("data-alert-id") or 0)
        first.locator("button.alert-ack").click()
        poll(
            lambda: any(a["id"] == first_id and a["acked"] for a in state(url)["alerts"]),
            "one alert acknowledged at the station",
            20,
        )
        page.click("#alerts-ack-all")
        poll(lambda: banner.is_hidden(), "the banner gone once every alert is acknowledged", 20)
        poll(lambda: all(a["acked"] for a in state(url)["alerts"]), "every alert acknowledged", 20)
        screenshot(page, "gcs_page_alerts_acknowledged.png")
        page.reload()  # a fresh page shows no acknowledged alert again
        page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=15000)
        poll(lambda: page.evaluate("() => window.gcs.stateCount") > 1, "a state on the fresh page", 20)
        assert banner.is_hidden()


def test_low_battery_and_statustext_alerts_reach_the_page_and_are_acknowledged() -> None:
    port = str(free_port())
    sim = Child(["sim", "--vehicles", "1", "--base-port", port, "--battery-drain", "400"], name="sim")
    children = [sim]
    try:
        fc = sim.wait_lines(1, 30)[0].split(" -> ")[1].split()[0]
        ep = f"tcp/127.0.0.1:{free_port()}"
        http = f"127.0.0.1:{free_port()}"
        thresholds = ["--battery-warning", "40", "--battery-critical", "20"]
        gcs, url = start_station(["--zenoh-listen", ep, "--http", http, "--tiles", "none", *thresholds])
        children.append(gcs)
        agent = ["agent", "--name", "flyer", "--id", "3", "--fc", fc, "--zenoh-connect", ep]
        children.append(Child(agent, name="agent"))
        check_the_station(url, children)
        check_the_page(url)
    finally:
        for c in reversed(children):
            c.stop()
