"""The page's fleet table, its honest state and its safe commands, in headless Chromium
against a real station: agents speaking the real connection protocol over Zenoh (each
with its own scripted telemetry, so every cell of the table has a known value) and the
station's real HTTP server and WebSocket.

* the fleet table lists every agent with its fields, one colour per agent shared by
  the row, the marker and the trail, sorts on a header click, selects on a row click;
* the command target never defaults to the whole swarm; land, return, disarm,
  take-off and every swarm command ask first: a cancel sends nothing, a confirm sends;
* "Hold all" sends the swarm STOP in one click;
* a silent agent's row goes stale; a frozen station (SIGSTOP) and a killed one
  (SIGKILL) grey the page out with a banner saying how old the data is.

Every wait polls for an outcome with a generous deadline. Screenshots in
``test-artifacts/``.
"""

from __future__ import annotations

import os
import re
import signal
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

import pytest
from gcs_browser import browser, new_page, poll, screenshot, start_station
from net_helpers import free_port, wait_until
from test_gcs_api import HOME, ScriptedAgent

from swarm.core.wire.codes import FLAG_AIRBORNE, FLAG_ARMED, FLAG_FC_OK, mode_code
from swarm.core.wire.message_types import CommandKind, Phase, Pose, Telemetry
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

pytestmark = pytest.mark.processes  # a browser against a running station

CONNECT_DEADLINE = 30.0
UI_DEADLINE = 15.0


@dataclass(frozen=True)
class Fields:
    mode: str
    armed: bool
    alt: float  # AMSL, as the telemetry carries it
    speed: float
    battery: int  # 255: unknown
    rssi: int
    remrssi: int
    fc_ok: bool = True  # the agent's link to its flight controller


class FleetAgent(ScriptedAgent):
    """A scripted agent whose telemetry carries ``fields``."""

    def __init__(self, ep: str, agent_id: int, fields: Fields, *, phase: Phase, leader: int) -> None:
        self.fields = fields  # before the agent's thread starts sending
        super().__init__(ep, agent_id, phase=phase, leader=leader)

    def pose(self) -> Pose:
        return Pose(HOME[0] + self.id * 1e-4, HOME[1], self.fields.alt, 30.0 * self.id)

    def telemetry(self) -> Telemetry:
        f = self.fields
        flags = (FLAG_FC_OK if f.fc_ok else 0) | (FLAG_ARMED | FLAG_AIRBORNE if f.armed else 0)
        return Telemetry(
            self.id, self.pose(), mode_code(f.mode), flags, self.phase, self.leader, f.battery, f.rssi,
            f.remrssi, f.speed,
        )  # fmt: skip

    def close(self) -> None:
        if not self.stop_ev.is_set():  # safe twice
            super().close()

    def kinds(self) -> list[CommandKind]:
        with self.lock:
            return [c.kind for c in self.commands]


FLEET = {
    1: Fields("OFFBOARD", True, 520.0, 4.5, 80, 150, 140),
    2: Fields("POSCTL", True, 515.5, 0.5, 35, 120, 110),
    3: Fields("AUTO.LOITER", False, 488.0, 0.0, 255, 90, 95),
    4: Fields("OFFBOARD", True, 530.2, 6.0, 60, 200, 180),
}


@dataclass
class Live:
    url: str
    station: Station
    agents: dict[int, FleetAgent]


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    station = Station("gcs", zenoh_listen=[ep]).start()
    server = GcsServer(station, ServerConfig(port=free_port())).start()
    agents: dict[int, FleetAgent] = {}
    try:
        for k, f in FLEET.items():
            agents[k] = FleetAgent(ep, k, f, phase=Phase.LEADER if k == 1 else Phase.MEMBER, leader=1)

        def ready() -> bool:
            snap = station.snapshot()
            return snap["leader"] == 1 and sum(a["connected"] for a in snap["agents"]) == len(FLEET)

        wait_until(ready, "every agent connected, agent1 the leader", CONNECT_DEADLINE)
        yield Live(server.url, station, agents)
    finally:
        for a in agents.values():
            a.close()
        server.stop()
        station.stop()


@pytest.fixture(scope="module")
def ctx() -> Iterator[Any]:
    with browser() as context:
        yield context


@pytest.fixture
def page(ctx: Any) -> Iterator[Any]:
    with new_page(ctx) as p:
        yield p


def open_page(page: Any, url: str, rows: int) -> None:
    page.goto(url)
    page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=UI_DEADLINE * 1000)
    poll(lambda: row_ids(page) and len(row_ids(page)) == rows, f"{rows} rows in the fleet table", UI_DEADLINE)


def row_ids(page: Any) -> list[int]:
    ids = page.evaluate(
        "Array.from(document.querySelectorAll('#agents tbody tr[data-agent-id]')).map(r => r.dataset.agentId)"
    )
    return [int(i) for i in ids]


def cell(page: Any, k: int, name: str) -> str:
    return str(page.inner_text(f'#agents [data-agent-id="{k}"] [data-field="{name}"]')).strip()


def test_fleet_table_lists_every_agent_in_its_colour_sorts_and_selects(live: Live, page: Any) -> None:
    open_page(page, live.url, len(FLEET))
    poll(lambda: page.evaluate("window.gcs.markers") == len(FLEET), "a marker per agent", UI_DEADLINE)
    poll(lambda: cell(page, 3, "mode") == "AUTO.LOITER", "agent3's telemetry in its row", UI_DEADLINE)
    for k, f in FLEET.items():
        assert cell(page, k, "name") == f"agent{k} ({k})"
        assert cell(page, k, "role") == ("leader" if k == 1 else "member")
        assert cell(page, k, "mode") == f.mode
        assert cell(page, k, "armed") == ("armed" if f.armed else "disarmed")
        # above home once the station saw the agent on the ground (its home), else AMSL, marked so
        assert cell(page, k, "alt") == ("0.0" if not f.armed else f"{f.alt:.1f} AMSL ✈")  # ✈: airborne
        assert cell(page, k, "groundspeed") == f"{f.speed:.1f}"
        assert cell(page, k, "battery") == ("unknown" if f.battery > 100 else f"{f.battery} %")
        # RSSI / remote RSSI as sent, then the loss the station measures (it moves with the load)
        assert re.fullmatch(rf"{f.rssi} / {f.remrssi} · \d+ % loss", cell(page, k, "link")), cell(
            page, k, "link"
        )
        assert cell(page, k, "seen").endswith(" s")
    # the station says how often each agent beats: the page's measure of "silent"
    assert {a["id"]: a["hb_s"] for a in live.station.snapshot()["agents"]} == dict.fromkeys(FLEET, 0.2)
    # one colour per agent, the same on the row, the marker and the trail
    colours = {}
    for k in FLEET:
        row = page.get_attribute(f'#agents [data-agent-id="{k}"]', "data-colour")
        assert row == page.get_attribute(f'.agent-marker[data-agent-id="{k}"]', "data-colour")
        assert row == page.evaluate(f"window.gcs.trailColour({k})")
        colours[k] = row
    assert len(set(colours.values())) == len(FLEET), colours
    # the leader: its own colour, marked on the row and the marker
    assert page.locator('#agents [data-agent-id="1"] .lead').is_visible()
    assert page.locator('#agents [data-agent-id="2"] .lead').is_hidden()
    assert page.locator(".agent-marker.leader").count() == 1
    assert page.get_attribute(".agent-marker.leader", "data-agent-id") == "1"

    # sorted on a header click, reversed on the second
    by_battery = [2, 4, 1, 3]  # 35, 60, 80 %, unknown last
    page.click('#agents th[data-sort="battery"]')
    assert row_ids(page) == by_battery
    page.click('#agents th[data-sort="battery"]')
    assert row_ids(page) == [1, 4, 2, 3]  # unknown last either way
    page.click('#agents th[data-sort="groundspeed"]')
    assert row_ids(page) == [3, 2, 1, 4]
    # the order holds across state pushes
    count = page.evaluate("window.gcs.stateCount")
    poll(lambda: page.evaluate("window.gcs.stateCount") > count + 2, "more state pushes", UI_DEADLINE)
    assert row_ids(page) == [3, 2, 1, 4]

    # a row click selects the agent
    page.click('#agents [data-agent-id="4"]')
    assert page.evaluate("window.gcs.selected") == 4
    assert page.get_attribute("#telemetry", "data-agent-id") == "4"
    assert page.locator('#agents [data-agent-id="4"].selected').count() == 1
    assert page.locator('.agent-marker[data-agent-id="4"].selected').count() == 1
    assert page.locator("#agents tr.stale").count() == 0
    assert page.locator("#stale-banner").is_hidden()
    assert page.inner_text("#data-age").startswith("updated ")
    screenshot(page, "gcs_fleet_table.png")
    assert page.errors == []


def sent_after(agent: FleetAgent, n: int) -> list[CommandKind]:
    return agent.kinds()[n:]


def test_an_unknown_armed_state_is_unknown_in_the_table_and_the_panel(live: Live, page: Any) -> None:
    """An airborne agent whose link to its flight controller dropped: armed is unknown,
    in the fleet table and in the telemetry panel alike (the panel once said
    "disarmed" over a flying vehicle)."""
    open_page(page, live.url, len(FLEET))
    agent = live.agents[4]
    flying = agent.fields
    agent.fields = replace(flying, fc_ok=False)
    try:
        poll(lambda: cell(page, 4, "armed") == "—", "agent4's armed state unknown in its row", UI_DEADLINE)
        page.click('#agents [data-agent-id="4"]')
        panel = '#telemetry [data-field="armed"]'
        poll(lambda: page.inner_text(panel).strip() != "", "the telemetry panel filled", UI_DEADLINE)
        assert page.inner_text(panel).strip() == "unknown (vehicle link lost)"
    finally:
        agent.fields = flying
    poll(lambda: page.inner_text(panel).strip() == "armed", "armed again once the link is back", UI_DEADLINE)


def test_an_agent_that_never_answers_is_no_answer_never_refused(live: Live, page: Any) -> None:
    """A command an agent never answered (it may not have heard it) is shown as no
    answer, in amber, on the status line and in the log: never as "refused" (it once was,
    in red)."""
    open_page(page, live.url, len(FLEET))
    agent = live.agents[3]
    answers = dict(agent.answers)
    agent.answers.pop(CommandKind.ARM)  # agent3 stays silent to an arm
    try:
        page.click('#agents [data-agent-id="3"]')
        page.click('#commands [data-kind="arm"]')
        poll(lambda: "no answer" in page.inner_text("#cmd-status"), "the arm's outcome", 60.0)
        line = page.inner_text("#cmd-status")
        assert "refused" not in line and "agent3 (3)" in line, line
        assert page.get_attribute("#cmd-status", "class") == "status pending"
        logged = page.locator("#log li", has_text="no answer from agent3")
        assert logged.count() == 1 and logged.get_attribute("class") == "pending"
    finally:
        agent.answers.update(answers)


def test_the_page_knows_the_fence_draws_it_and_refuses_outside_it_before_asking(
    live: Live, page: Any
) -> None:
    """The station hands the page its geofence: a take-off above the ceiling, or a go-to
    beyond the radius from the agent's home, is refused on the page at once, with the
    station's words, before any confirmation (it once asked "Take off to 150 m?" and
    the station refused); the fence is drawn around each home the station knows."""
    open_page(page, live.url, len(FLEET))
    before = {k: len(a.kinds()) for k, a in live.agents.items()}
    assert page.evaluate("window.gcsFence") == {"floor_m": 2.0, "ceiling_m": 120.0, "radius_m": 1000.0}
    # agent3 stands on the ground: the station knows its home, the page draws its fence
    poll(lambda: page.locator("path.plan-fence").count() >= 1, "a fence ring around a home", UI_DEADLINE)

    page.click('#agents [data-agent-id="3"]')
    page.fill("#takeoff-alt", "150")
    page.click('#commands [data-kind="takeoff"]')
    assert page.locator("#confirm").is_hidden()
    line = page.inner_text("#cmd-status")
    assert line == (
        "takeoff refused by the station's geofence: altitude 150 m above home is above the ceiling (120 m)"
    ), line
    home = live.station.agent(3)
    assert home is not None and "home" in home
    page.fill("#goto-lat", str(home["home"][0] + 0.02))  # about 2.2 km north
    page.fill("#goto-lon", str(home["home"][1]))
    page.fill("#goto-alt", "20")
    page.click("#goto-go")
    line = page.inner_text("#cmd-status")
    assert (
        line.startswith("goto refused by the station's geofence: target 22") and "radius (1000 m)" in line
    ), line
    page.fill("#takeoff-alt", "10")
    assert [len(a.kinds()) for a in live.agents.values()] == list(before.values())  # nothing was sent
    assert page.errors == []


def test_the_top_bar_shows_all_it_holds_at_1400_px(live: Live, page: Any) -> None:
    """At 1400 x 900 with a long swarm summary (several swarms) nothing in the top bar
    is cut off or pushed out of the window: Hold all and Fit swarm stay on screen (the
    bar once overflowed at 1400 px, its end hidden)."""
    page.set_viewport_size({"width": 1400, "height": 900})
    open_page(page, live.url, len(FLEET))
    # set and measured in one task: no state push redraws the summary in between
    out = page.evaluate(
        """() => {
          const s = document.querySelector('#swarm-summary');
          s.hidden = false;
          const names = Array.from({length: 8}, (_, i) => 'agent' + (i * 10 + 1) + ' · 10');
          s.textContent = 'swarms: ' + names.join(', ');
          const cut = (e) => {
            const r = e.getBoundingClientRect();
            return r.right > window.innerWidth + 0.5 || r.width === 0;
          };
          return Array.from(document.querySelectorAll('#topbar > *')).filter((e) => !e.hidden)
            .filter(cut).map((e) => e.id || e.className);
        }"""
    )
    assert out == [], out
    for sel in ("#hold-all", "#fit-swarm"):
        assert page.locator(sel).is_visible()


def test_twenty_rows_fit_at_1400_by_900_and_the_map_keeps_its_room(live: Live, page: Any) -> None:
    """The table's rows (every column: climb, home, GPS, ready...) are compact: with 20
    agents (the real rows, cloned in one task) all 20 show without scrolling at
    1400 x 900, on one line each, every column in view, and the map keeps a third of
    the window (less the alarm banner's fixed height when earlier tests left alarms)."""
    page.set_viewport_size({"width": 1400, "height": 900})
    open_page(page, live.url, len(FLEET))
    out = page.evaluate(
        """() => {
          const body = document.querySelector('#agents tbody');
          const rows = Array.from(body.querySelectorAll('tr[data-agent-id]'));
          for (let i = rows.length; i < 20; i++) body.append(rows[i % rows.length].cloneNode(true));
          const box = document.querySelector('#fleet');
          const heights = Array.from(body.querySelectorAll('tr'))
            .map((r) => r.getBoundingClientRect().height);
          return {rows: heights.length, hidden: box.scrollHeight - box.clientHeight,
                  cut: box.scrollWidth - box.clientWidth,
                  tallest: Math.max(...heights), map: document.querySelector('#map').clientHeight,
                  banner: document.querySelector('#alerts-banner').getBoundingClientRect().height};
        }"""
    )
    assert out["rows"] == 20 and out["hidden"] <= 1, out
    assert out["cut"] <= 1, out  # every column, the last seen too, without scrolling sideways
    assert out["tallest"] <= 22, out  # one line each
    assert out["map"] + out["banner"] >= 300, out  # the alarm banner (fixed, 3 rows) takes its share
    screenshot(page, "gcs_fleet_20_rows.png")


def test_commands_ask_first_cancel_sends_nothing_confirm_sends(live: Live, page: Any) -> None:
    open_page(page, live.url, len(FLEET))
    # nothing selected: the target is not the swarm, the buttons wait for an agent
    assert page.input_value("#cmd-target") == "selected"
    assert page.inner_text("#cmd-to") == "select an agent"
    assert page.locator('#commands [data-kind="land"]').is_disabled()
    a2 = live.agents[2]
    before = {k: len(a.kinds()) for k, a in live.agents.items()}

    page.click('#agents [data-agent-id="2"]')
    assert page.locator('#commands [data-kind="land"]').is_enabled()
    page.click('#commands [data-kind="land"]')
    assert page.locator("#confirm").is_visible()
    assert page.inner_text("#confirm-text") == "Land agent2 (2)?"
    assert page.inner_text("#confirm-ok") == "Land"
    page.click("#confirm-cancel")
    assert page.locator("#confirm").is_hidden()
    # Escape, and Enter on the dialog as it opens (Cancel has the focus), cancel too
    for key in ("Escape", "Enter"):
        page.click('#commands [data-kind="land"]')
        assert page.locator("#confirm").is_visible()
        page.keyboard.press(key)
        page.wait_for_selector("#confirm", state="hidden", timeout=UI_DEADLINE * 1000)
    # a command that needs no confirmation goes after it: had the land been sent, it came first
    page.click('#commands [data-kind="arm"]')
    assert page.locator("#confirm").is_hidden()
    poll(lambda: CommandKind.ARM in sent_after(a2, before[2]), "agent2's arm", UI_DEADLINE)
    assert sent_after(a2, before[2])[0] == CommandKind.ARM and CommandKind.LAND not in sent_after(
        a2, before[2]
    )
    assert page.locator("#log li", has_text="not sent").count() == 3

    page.click('#commands [data-kind="land"]')
    page.click("#confirm-ok")
    poll(lambda: CommandKind.LAND in sent_after(a2, before[2]), "agent2's land", UI_DEADLINE)
    poll(lambda: "land" in page.inner_text("#cmd-status"), "the land's result", UI_DEADLINE)

    # the whole swarm, chosen on purpose: asked first, naming how many
    page.select_option("#cmd-target", "swarm")
    assert page.inner_text("#cmd-to") == "every agent"
    page.click('#commands [data-kind="return"]')
    assert page.inner_text("#confirm-text") == f"Return {len(FLEET)} agents?"
    screenshot(page, "gcs_confirm.png")
    page.click("#confirm-ok")
    for k, a in live.agents.items():
        poll(
            lambda a=a, k=k: CommandKind.RETURN in sent_after(a, before[k]), f"agent{k}'s return", UI_DEADLINE
        )
    # and not left chosen: the next command goes to the selected agent
    assert page.input_value("#cmd-target") == "selected"
    assert page.errors == []


def test_hold_all_holds_every_agent_in_one_click(live: Live, page: Any) -> None:
    open_page(page, live.url, len(FLEET))
    before = {k: len(a.kinds()) for k, a in live.agents.items()}
    page.set_viewport_size({"width": 1024, "height": 600})  # a small laptop: still in view
    box = page.locator("#hold-all").bounding_box()
    assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= 1024 and box["y"] >= 0
    assert page.locator("#hold-all").is_visible() and page.locator("#hold-all").is_enabled()
    page.click("#hold-all")
    assert page.locator("#confirm").is_hidden()  # no question in the way
    for k, a in live.agents.items():
        poll(lambda a=a, k=k: CommandKind.STOP in sent_after(a, before[k]), f"agent{k}'s stop", UI_DEADLINE)
    # the leader also got the swarm STOP (its members hold the swarm's HOLD task)
    with live.agents[1].lock:
        assert any(c.kind == CommandKind.STOP and c.target == 0 for c in live.agents[1].commands[before[1] :])
    poll(lambda: "stop" in page.inner_text("#cmd-status"), "the hold's result on the page", UI_DEADLINE)
    assert page.errors == []


def test_a_silent_agent_goes_stale_and_a_frozen_or_killed_station_greys_the_page(page: Any) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    station, url = start_station(
        ["--zenoh-listen", ep, "--http", f"127.0.0.1:{free_port()}", "--tiles", "none"]
    )
    agents = [
        FleetAgent(ep, k, FLEET[k], phase=Phase.LEADER if k == 1 else Phase.MEMBER, leader=1) for k in (1, 2)
    ]
    try:
        open_page(page, url, 2)
        poll(
            lambda: page.inner_text("#agent-count") == "2/2 agents connected",
            "both connected",
            CONNECT_DEADLINE,
        )
        assert page.locator("#agents tr.stale").count() == 0

        # an agent goes silent: its row shows its last values, greyed, with their age
        agents[1].close()
        poll(
            lambda: page.locator('#agents [data-agent-id="2"].stale').count() == 1,
            "agent2 stale",
            UI_DEADLINE,
        )
        poll(lambda: cell(page, 2, "seen").endswith("(lost)"), "agent2 lost", UI_DEADLINE)
        assert cell(page, 2, "battery") == "35 %"  # the last value, kept and greyed
        # a swarm command's dialog counts what the station will send to, and names the
        # table's agents it will not reach (it once said "Arm 1 agent?" beside two rows)
        poll(lambda: page.inner_text("#agent-count") == "1/2 agents connected", "1 of 2", UI_DEADLINE)
        page.select_option("#cmd-target", "swarm")
        page.click('#commands [data-kind="arm"]')
        text = page.inner_text("#confirm-text")
        assert text == "Arm 1 agent? Not connected, will not get it: agent2 (2).", text
        page.click("#confirm-cancel")
        page.click('#agents [data-agent-id="2"]')
        poll(
            lambda: "stale" in (page.get_attribute("#telemetry", "class") or ""),
            "its telemetry greyed",
            UI_DEADLINE,
        )
        assert page.locator('#agents [data-agent-id="1"].stale').count() == 0

        # the station freezes (its sockets stay open): the page says so from the data's age
        os.kill(station.pid, signal.SIGSTOP)
        t0 = time.monotonic()
        try:
            poll(lambda: page.locator("#stale-banner").is_visible(), "the banner", UI_DEADLINE)
            frozen_s = time.monotonic() - t0
            assert "station silent" in page.inner_text("#stale-banner")
            assert page.evaluate("document.body.classList.contains('stale')")
            # the link pill agrees with the banner (it once stayed a green "live" for ever)
            assert page.inner_text("#link-status") == "silent"
        finally:
            os.kill(station.pid, signal.SIGCONT)
        poll(lambda: page.locator("#stale-banner").is_hidden(), "fresh data again", UI_DEADLINE)
        assert page.inner_text("#link-status") == "live"

        # the station is killed: grey, a banner with the data's age, the count history
        os.kill(station.pid, signal.SIGKILL)
        t0 = time.monotonic()
        poll(lambda: page.locator("#stale-banner").is_visible(), "the banner", UI_DEADLINE)
        killed_s = time.monotonic() - t0
        assert "station lost: data " in page.inner_text("#stale-banner")
        assert page.inner_text("#agent-count").startswith("last known: ")
        assert page.inner_text("#data-age").startswith("updated ")
        # nothing stays shown as live: every row goes stale as the data ages
        poll(lambda: page.locator("#agents tr.stale").count() == 2, "every row stale", UI_DEADLINE)
        poll(lambda: "s old" in page.inner_text("#stale-banner"), "the data's age", UI_DEADLINE)
        screenshot(page, "gcs_station_lost.png")
        print(f"banner after SIGSTOP {frozen_s:.2f} s, after SIGKILL {killed_s:.2f} s")
        # a command now reaches no station: "not sent", in words, never the browser's error
        page.click('#agents [data-agent-id="1"]')
        page.click('#commands [data-kind="arm"]')
        poll(lambda: "not sent" in page.inner_text("#cmd-status"), "the arm's outcome", UI_DEADLINE)
        line = page.inner_text("#cmd-status")
        assert "the station did not answer" in line and "TypeError" not in line, line
        assert page.errors == []
    finally:
        for a in agents:
            a.close()
        station.stop(grace=3)
