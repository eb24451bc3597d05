"""Two swarms on the page (static/swarms.js, issue 16), in headless Chromium against a
real station: six agents speaking the real connection protocol over a real Zenoh
session, naming two leaders in their Telemetry and AgentState (agent3 leads 1 and 2,
agent6 leads 4 and 5), the station's real HTTP server and WebSocket.

* the fleet table groups the agents by swarm, both leaders marked, every member in its
  swarm's colour (row, marker, trail), one colour per swarm;
* a land to one swarm, chosen in the "to" selector and confirmed in a dialog naming
  the swarm and its three agents, reaches that swarm's agents only;
* a follow in V to every swarm is refused on the page with one clear line, and by the
  station too (HTTP 409); a hostile or stale ``swarm`` gets HTTP 400 in one line.

Screenshot: ``test-artifacts/gcs_swarms.png``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any

import pytest
from gcs_browser import browser, new_page, poll, screenshot
from net_helpers import free_port, wait_until
from test_gcs_api import ScriptedAgent

from swarm.core.wire.message_types import CommandKind, Phase
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

pytestmark = pytest.mark.processes  # a browser against a running station

DEADLINE = 30.0
UI_DEADLINE = 15.0
LEADS = {1: 3, 2: 3, 3: 3, 4: 6, 5: 6, 6: 6}


@dataclass
class Live:
    station: Station
    url: str = ""
    agents: dict[int, ScriptedAgent] = field(default_factory=dict)

    def two_swarms(self) -> bool:
        snap = self.station.snapshot()
        return sum(a["connected"] for a in snap["agents"]) == len(LEADS) and [
            (s["leader"], s["members"]) for s in snap["swarms"]
        ] == [(3, [1, 2, 3]), (6, [4, 5, 6])]


def stop_agent(a: ScriptedAgent) -> None:
    a.stop_ev.set()
    a.thread.join(2)
    a.tr.close()


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ExitStack() as stack:
        live = Live(Station("gcs", zenoh_listen=[ep]).start())
        stack.callback(live.station.stop)
        server = GcsServer(live.station, ServerConfig(port=free_port())).start()
        stack.callback(server.stop)
        live.url = server.url
        for k, lead in LEADS.items():
            phase = Phase.LEADER if k == lead else Phase.MEMBER
            live.agents[k] = ScriptedAgent(ep, k, phase=phase, leader=lead)
            stack.callback(stop_agent, live.agents[k])
        wait_until(live.two_swarms, "six agents connected in two swarms (led by 3 and 6)", DEADLINE)
        yield live


@pytest.fixture(scope="module")
def page(live: Live) -> Iterator[Any]:
    with browser() as ctx, new_page(ctx) as p:
        p.set_viewport_size({"width": 1280, "height": 800})
        p.goto(live.url)
        ready = "() => window.gcs && window.gcs.ready && window.gcsSwarms"
        p.wait_for_function(ready, timeout=UI_DEADLINE * 1000)
        poll(lambda: p.evaluate("window.gcs.markers") == len(LEADS), "every marker drawn", UI_DEADLINE)
        yield p
        assert p.errors == []


def rows(page: Any) -> list[dict[str, Any]]:
    """The fleet table as shown: id, swarm, colour, leader mark, the swarm cell's text."""
    return list(
        page.evaluate(
            """() => Array.from(document.querySelectorAll('#agents tbody tr[data-agent-id]'))
            .filter((r) => !r.hidden).map((r) => ({
                id: Number(r.dataset.agentId), swarm: r.dataset.swarm, colour: r.dataset.colour,
                lead: r.classList.contains('leader'),
                cell: r.querySelector('td[data-field="swarm"]').textContent }))"""
        )
    )


def sent_kinds(live: Live, kind: CommandKind) -> set[int]:
    return {i for i, a in live.agents.items() if any(c.kind == kind for c in list(a.commands))}


def post(page: Any, body: dict[str, Any]) -> dict[str, Any]:
    """POST /api/command from the page (its own origin, as the page would)."""
    return dict(
        page.evaluate(
            """async (body) => { const r = await fetch('/api/command', {method: 'POST',
            headers: {'Content-Type': 'application/json'}, body: JSON.stringify(body)});
            return {status: r.status, body: await r.json()}; }""",
            body,
        )
    )


def test_the_fleet_is_grouped_by_swarm_in_one_colour_per_swarm(page: Any) -> None:
    poll(lambda: [r["swarm"] for r in rows(page)] == ["3"] * 3 + ["6"] * 3, "two groups", UI_DEADLINE)
    shown = rows(page)
    assert [r["id"] for r in shown] == [3, 1, 2, 6, 4, 5]  # each swarm's leader first
    assert [r["id"] for r in shown if r["lead"]] == [3, 6]
    assert [r["cell"] for r in shown] == [
        "leads",
        "agent3 (3)",
        "agent3 (3)",
        "leads",
        "agent6 (6)",
        "agent6 (6)",
    ]
    colours = {r["swarm"]: {x["colour"] for x in shown if x["swarm"] == r["swarm"]} for r in shown}
    assert all(len(c) == 1 for c in colours.values()) and colours["3"] != colours["6"]
    for r in shown:  # the marker and the trail in the row's colour
        marker = page.evaluate(
            f"document.querySelector('.agent-marker[data-agent-id=\"{r['id']}\"]').dataset.colour"
        )
        assert marker == r["colour"] == page.evaluate(f"window.gcs.trailColour({r['id']})")
    assert page.evaluate("document.querySelector('#swarm-summary').hidden") is False
    # "show" filters the table to one swarm
    page.select_option("#swarm-filter", "6")
    poll(lambda: [r["id"] for r in rows(page)] == [6, 4, 5], "swarm 6 only", UI_DEADLINE)
    page.select_option("#swarm-filter", "all")
    poll(lambda: len(rows(page)) == 6, "every agent again", UI_DEADLINE)


def test_a_land_to_one_swarm_reaches_only_its_agents(live: Live, page: Any) -> None:
    page.select_option("#cmd-target", "swarm:3")
    page.click('#commands button[data-kind="land"]')
    page.wait_for_selector("#confirm[open]", timeout=UI_DEADLINE * 1000)
    assert page.text_content("#confirm-text") == "Land the swarm of agent3 (3): 3 agents?"
    screenshot(page, "gcs_swarms_confirm.png")
    page.click("#confirm-ok")
    poll(lambda: sent_kinds(live, CommandKind.LAND) == {1, 2, 3}, "land at agents 1, 2 and 3", DEADLINE)
    poll(
        lambda: re.search(r": (accepted|in progress|done)", page.text_content("#cmd-status") or ""),
        "the land accepted on the page",
        DEADLINE,
    )
    assert "the swarm of agent3 (3)" in (page.text_content("#cmd-status") or "")
    assert sent_kinds(live, CommandKind.LAND) == {1, 2, 3}  # swarm 6 heard nothing
    assert page.input_value("#cmd-target") == "selected"  # a swarm is never left chosen


def test_a_follow_to_every_swarm_is_refused_in_one_line(live: Live, page: Any) -> None:
    page.select_option("#cmd-target", "swarm")
    page.click('#commands button[data-kind="follow"]')
    status = page.text_content("#cmd-status") or ""
    assert status == 'follow: 2 swarms sent the same way would meet: choose one swarm in "to"'
    assert page.evaluate("document.querySelector('#confirm').open") is False
    screenshot(page, "gcs_swarms.png")
    # a hold to every swarm is allowed: the dialog names them and counts the agents
    page.select_option("#cmd-target", "swarm")
    page.click('#commands button[data-kind="stop"]')
    page.wait_for_selector("#confirm[open]", timeout=UI_DEADLINE * 1000)
    assert page.text_content("#confirm-text") == "Hold every swarm (2 swarms, 6 agents)?"
    page.click("#confirm-cancel")
    # the station refuses it too, and any swarm that is not one
    r = post(page, {"target": "swarm", "kind": "follow", "heading": 90})
    assert r["status"] == 409 and r["body"]["error"].startswith(
        "follow goes to one swarm (2 swarms led by 3, 6)"
    )
    for bad, why in (
        (2, "no swarm led by agent 2 now (2 swarms led by 3, 6)"),
        ("3", "swarm '3': its leader's agent id (1..250) or \"all\""),
        (1e30, 'swarm of type float: its leader\'s agent id (1..250) or "all"'),
    ):
        r = post(page, {"target": "swarm", "kind": "stop", "swarm": bad})
        assert r["status"] == 400 and r["body"] == {"ok": False, "error": why}
    assert sent_kinds(live, CommandKind.FOLLOW) == set() and sent_kinds(live, CommandKind.STOP) == set()
