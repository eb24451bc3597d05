"""A command carried out whose answers were all lost, from the page to the agent and back:
a real station and server, an agent speaking the real connection protocol over Zenoh
that flies home on RETURN but whose answers never arrive, and the page in headless
Chromium. The API says CARRIED_OUT with how it knows; the page shows it as done (not a
refusal in red)."""

from __future__ import annotations

import json
import urllib.request
from collections.abc import Iterator

import pytest
from gcs_browser import browser
from net_helpers import free_port, wait_until
from test_gcs_api import ScriptedAgent

from swarm.core.station.model import StationConfig
from swarm.core.wire.message_types import Command, CommandKind, Phase
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

# timing: telemetry within a shortened 3 s give-up
pytestmark = [pytest.mark.processes, pytest.mark.timing]  # a browser against a running station


class HomingAgent(ScriptedAgent):
    """Answers nothing; RETURN switches its mode to AUTO.RTL (its answers 'lost')."""

    def __init__(self, ep: str) -> None:
        super().__init__(ep, 1, phase=Phase.LEADER, leader=1)
        self.answers = {}

    @property
    def got(self) -> list[Command]:
        return self.commands

    def on_command(self, m: Command) -> None:
        if m.kind == CommandKind.RETURN:
            self.mode = "AUTO.RTL"


@pytest.fixture
def live() -> Iterator[tuple[str, HomingAgent]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    # a shorter give-up than the 12 s default: the rule is the same, the test is quicker
    cfg = StationConfig(command_backoff=(0.5, 1.0), command_give_up=3.0)
    station = Station("gcs", zenoh_listen=[ep], config=cfg).start()
    server = GcsServer(station, ServerConfig(port=free_port())).start()
    agent = HomingAgent(ep)
    try:
        wait_until(lambda: any(a["connected"] for a in station.snapshot()["agents"]), "agent1 connected", 30)
        yield server.url, agent
    finally:
        agent.close()
        server.stop()
        station.stop()


def test_a_return_done_but_unanswered_is_carried_out_on_the_api_and_the_page(
    live: tuple[str, HomingAgent],
) -> None:
    url, agent = live
    data = json.dumps({"target": 1, "kind": "return"}).encode()
    req = urllib.request.Request(
        url + "api/command", data=data, method="POST", headers={"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(req, timeout=30) as r:
        status, body = r.status, json.loads(r.read())
    assert status == 200 and body["ok"] is True, body
    (res,) = body["results"]
    assert res["result"] == "CARRIED_OUT" and res["reason"].endswith("but it shows mode AUTO.RTL"), res
    assert len(agent.got) >= 2 and {c.seq for c in agent.got} == {agent.got[0].seq}  # retried, one seq
    with agent.lock:
        agent.mode = "POSCTL"  # back under control: the page's RETURN must show its own evidence
    with browser() as ctx:
        page = ctx.new_page()
        page.goto(url)
        page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=15000)
        page.click('#agents [data-agent-id="1"]')
        page.select_option("#cmd-target", "selected")
        page.click('#commands button[data-kind="return"]')
        page.click("#confirm-ok")  # a return is asked about first
        page.wait_for_function(
            "() => /carried out/.test(document.querySelector('#cmd-status').textContent)", timeout=20000
        )
        assert "ok" in str(page.get_attribute("#cmd-status", "class"))
