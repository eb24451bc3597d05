"""After an autopilot failsafe, on the real page (headless Chromium) over a real station:
an agent that speaks the real station protocol over Zenoh and whose vehicle its
autopilot holds in AUTO.LOITER (the agent says ``control_lost``), accepting a Go that
then moves it 0 m, as the issue saw it. The page must not leave "accepted" standing: the
Go's status goes on to "did not happen: the autopilot has control (mode AUTO.LOITER)"
and the station raises a warning alarm; the telemetry panel says what happened and
offers the way back; "Take control (hold here)" asks first, sends the agent's STOP,
and the result follows the vehicle to "done: holding"."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from gcs_browser import browser, new_page, poll, screenshot
from net_helpers import free_port, wait_until
from test_gcs_api import HOME, ScriptedAgent

from swarm.core.wire.codes import (
    FLAG_AIRBORNE,
    FLAG_ARMED,
    FLAG_CONTROL_LOST,
    FLAG_FC_OK,
    FLAG_HOLDING,
    mode_code,
)
from swarm.core.wire.message_types import Command, CommandKind, Phase, Pose, Telemetry
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

pytestmark = pytest.mark.processes  # a station, an agent over Zenoh, a browser

DEADLINE = 40.0  # the station's follow-up gives a Go LOST_S (5 s) of an autopilot in control


class HeldByItsAutopilot(ScriptedAgent):
    """Flying at 20 m, its autopilot in AUTO.LOITER after a failsafe: it accepts every
    command, and only a STOP (taking control back) changes anything: then it holds."""

    def __init__(self, ep: str, agent_id: int) -> None:
        self.lost = True
        super().__init__(ep, agent_id, phase=Phase.LEADER, leader=agent_id)

    def pose(self) -> Pose:
        return Pose(HOME[0], HOME[1], 520.0, 90.0)

    def telemetry(self) -> Telemetry:
        flags = FLAG_ARMED | FLAG_AIRBORNE | FLAG_FC_OK
        flags |= FLAG_CONTROL_LOST if self.lost else FLAG_HOLDING
        mode = "AUTO.LOITER" if self.lost else "OFFBOARD"
        return Telemetry(
            self.id, self.pose(), mode_code(mode), flags, self.phase, self.leader, 70, 150, 140, 0.0,
            rel_alt=20.0, gps_fix=3, satellites=12, home_dist=0.0,
        )  # fmt: skip

    def on_command(self, m: Command) -> None:
        if m.kind == CommandKind.STOP:
            self.lost = False


@pytest.fixture
def live() -> Iterator[tuple[Station, str, HeldByItsAutopilot]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    station = Station("gcs", zenoh_listen=[ep]).start()
    server = GcsServer(station, ServerConfig(port=free_port())).start()
    agent = HeldByItsAutopilot(ep, 1)
    try:
        wait_until(
            lambda: any(a["connected"] for a in station.snapshot()["agents"]), "agent1 connected", DEADLINE
        )
        yield station, server.url, agent
    finally:
        agent.close()
        server.stop()
        station.stop()


def status(page: Any) -> str:
    return str(page.inner_text("#cmd-status"))


def test_a_go_after_a_failsafe_is_not_left_accepted_and_the_page_takes_control_back(
    live: tuple[Station, str, HeldByItsAutopilot],
) -> None:
    station, url, agent = live
    with browser() as ctx, new_page(ctx) as page:
        page.set_viewport_size({"width": 1400, "height": 900})
        page.goto(url)
        page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=15_000)
        row = '#agents [data-agent-id="1"]'
        poll(lambda: page.locator(row).count() == 1, "agent1 in the table", DEADLINE)
        page.click(row)
        box = page.locator("#take-back")
        poll(lambda: box.is_visible(), "the way back offered", DEADLINE)
        assert "its autopilot flies it (mode AUTO.LOITER)" in box.inner_text()
        assert page.locator('#take-back [data-take="follow"]').is_hidden()  # no formation to resume

        page.fill("#goto-lat", f"{HOME[0] + 0.0005:.7f}")  # 55 m north
        page.fill("#goto-lon", f"{HOME[1]:.7f}")
        page.fill("#goto-alt", "20")
        page.click("#goto-go")
        poll(lambda: "accepted" in status(page) or "in progress" in status(page), "the agent's yes", DEADLINE)
        poll(lambda: "did not happen" in status(page), "the Go's real outcome", DEADLINE)
        assert "the autopilot has control (mode AUTO.LOITER)" in status(page), status(page)
        assert "accepted" not in status(page)
        doing = page.inner_text('#telemetry [data-field="doing"]')
        assert doing.startswith("goto: did not happen"), doing
        alarms = [a for a in station.snapshot()["alerts"] if a["kind"] == "command"]
        assert [(a["level"], a["text"]) for a in alarms] == [
            ("warning", "agent1 (1): goto did not happen: the autopilot has control (mode AUTO.LOITER): "
             "take control back first")
        ]  # fmt: skip
        screenshot(page, "gcs_failsafe_go_did_not_happen.png")

        page.click('#take-back [data-take="stop"]')  # asks first
        assert page.locator("#confirm").is_visible()
        assert "Take control of agent1 (1) back?" in page.inner_text("#confirm-text")
        page.click("#confirm-ok")
        poll(lambda: "done: holding" in status(page), "the stop's outcome on the vehicle", DEADLINE)
        poll(lambda: box.is_hidden(), "the way back gone once under control", DEADLINE)
        assert not agent.lost
        screenshot(page, "gcs_failsafe_taken_back.png")
        assert page.errors == []
