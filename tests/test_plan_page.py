"""The plan on the map (static/plan.js), in headless Chromium against a real station:
agents speaking the real connection protocol over Zenoh, a leader whose Heartbeats
carry a FOLLOW task (heard by the station on their way to the members' inboxes), the
station's real HTTP server and WebSocket.

* route, waypoints and go-to target drawn from the station's GOTO and WAYPOINT, gone
  when the agent says "arrived"; the layer control hides and shows a layer;
* each member's formation slot where swarm.core.flight.formation puts it, and each home;
* the measure tool's distance and bearing against pymap3d (Vincenty, WGS-84), the
  go-to target untouched while measuring, Escape clearing it;
* "Follow swarm" keeps every agent in view when the swarm moves 2 km;
* name tags of a tight V do not overlap; a hidden one shows on hover.

Screenshot: ``test-artifacts/gcs_plan.png``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pymap3d.vincenty
import pytest
from gcs_browser import browser, new_page, poll, screenshot
from net_helpers import free_port, wait_until
from test_gcs_api import HOME, ScriptedAgent

from swarm.core.flight.formation import slot_error
from swarm.core.station.commands import CommandSpec
from swarm.core.wire.codes import FLAG_FC_OK, mode_code
from swarm.core.wire.message_types import (
    AgentNotice,
    Assignment,
    Command,
    CommandKind,
    Heartbeat,
    NoticeSource,
    Phase,
    Pose,
    Side,
    Task,
    TaskKind,
    Telemetry,
)
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

pytestmark = pytest.mark.processes  # a browser against a running station

DEADLINE = 30.0
UI_DEADLINE = 15.0
#: a tight V, metres (north, east) from the leader: five agents' tags collide at zoom 18
V = {1: (0.0, 0.0), 2: (-4.0, -3.0), 3: (-4.0, 3.0), 4: (-8.0, -6.0), 5: (-8.0, 6.0)}
TASK = Task(
    TaskKind.FOLLOW,
    heading=20.0,
    back_m=10.0,
    side_m=5.0,
    assignments=(
        Assignment(2, 1, Side.LEFT),
        Assignment(3, 1, Side.RIGHT),
        Assignment(4, 2, Side.LEFT),
        Assignment(5, 3, Side.RIGHT),
    ),
)
M_PER_DEG = 111_200.0


class VAgent(ScriptedAgent):
    """On the ground (so the station learns its home) at its place in the V, moved by ``shift``."""

    shift = [0.0, 0.0]  # degrees (lat, lon) added to every agent's position

    def pose(self) -> Pose:
        n, e = V[self.id]
        return Pose(
            HOME[0] + n / M_PER_DEG + self.shift[0], HOME[1] + e / 75_800.0 + self.shift[1], 500.0, 20.0
        )

    def telemetry(self) -> Telemetry:
        return Telemetry(
            self.id, self.pose(), mode_code("POSCTL"), FLAG_FC_OK, self.phase, self.leader, 80, 150, 140, 0.0
        )


@dataclass
class Live:
    station: Station
    url: str = ""
    agents: dict[int, VAgent] = field(default_factory=dict)

    def connected(self) -> bool:
        snap = self.station.snapshot()
        return snap["leader"] == 1 and sum(a["connected"] for a in snap["agents"]) == len(V)


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    live = Live(Station("gcs", zenoh_listen=[ep]).start())
    server = GcsServer(live.station, ServerConfig(port=free_port())).start()
    live.url = server.url
    try:
        live.agents.update(
            {k: VAgent(ep, k, phase=Phase.LEADER if k == 1 else Phase.MEMBER, leader=1) for k in V}
        )
        wait_until(live.connected, "every agent connected, agent1 the leader", DEADLINE)
        seq = [0]

        def task_heard() -> bool:
            seq[0] += 1  # the leader's Heartbeat, to a member's inbox (the station overhears it)
            live.agents[1].tr.send("agent2", Heartbeat(1, 1, seq[0] & 0xFF, frozenset({2, 3, 4, 5}), TASK))
            return live.station.snapshot()["slots"] is not None

        wait_until(task_heard, "the leader's task in the station's state", DEADLINE)
        yield live
    finally:
        for a in live.agents.values():
            a.stop_ev.set()
            a.thread.join(2)
            a.tr.close()
        server.stop()
        live.station.stop()


@pytest.fixture(scope="module")
def page(live: Live) -> Iterator[Any]:
    with browser() as ctx, new_page(ctx) as p:
        p.set_viewport_size({"width": 1280, "height": 800})
        p.goto(live.url)
        p.wait_for_function(
            "() => window.gcs && window.gcs.ready && window.gcsPlan", timeout=UI_DEADLINE * 1000
        )
        poll(lambda: p.evaluate("window.gcs.markers") == len(V), "every marker drawn", UI_DEADLINE)
        p.evaluate(f"window.gcs.map.setView([{HOME[0] - 4 / M_PER_DEG}, {HOME[1]}], 18, {{animate: false}})")
        yield p
        assert p.errors == []


def count(page: Any, sel: str) -> int:
    return int(page.evaluate(f"document.querySelectorAll({sel!r}).length"))


def cross_shown(page: Any) -> bool:
    """app.js's cross where the operator clicked (the form's point)."""
    return bool(
        page.evaluate(
            "(() => { const e = document.querySelector('#goto-target');"
            " return !!e && getComputedStyle(e).display !== 'none'; })()"
        )
    )


def test_route_target_slots_and_homes(live: Live, page: Any) -> None:
    # the operator clicks the map: the form's cross; once sent, the route's target replaces it
    page.mouse.click(
        *page.evaluate(
            f"""(() => {{ const m = window.gcs.map;
            const p = m.latLngToContainerPoint([{HOME[0] + 30 / M_PER_DEG}, {HOME[1]}]);
            const r = m.getContainer().getBoundingClientRect(); return [r.left + p.x, r.top + p.y]; }})()"""
        )
    )
    assert cross_shown(page)
    wp1 = (float(page.input_value("#goto-lat")), float(page.input_value("#goto-lon")))
    wp2 = (HOME[0] + 50 / M_PER_DEG, HOME[1] - 10 / 75_800.0)
    live.station.submit(CommandSpec(1, CommandKind.GOTO, lat=wp1[0], lon=wp1[1], alt=20.0)).result(DEADLINE)
    live.station.submit(CommandSpec(1, CommandKind.WAYPOINT, lat=wp2[0], lon=wp2[1], alt=25.0)).result(
        DEADLINE
    )
    poll(lambda: count(page, ".plan-wp") == 1, "one numbered waypoint before the target", UI_DEADLINE)
    assert not cross_shown(page)  # the form's cross is the route's now
    # another station's GOTO to agent3, overheard on its way to agent3's inbox
    far = (HOME[0] + 20 / M_PER_DEG, HOME[1] + 40 / 75_800.0)
    live.agents[1].tr.send("agent3", Command(252, 77, 3, CommandKind.GOTO, far[0], far[1], 15.0))
    poll(lambda: count(page, '.plan-target[data-agent-id="3"]') == 1, "agent3's target", UI_DEADLINE)
    live.agents[3].tr.send("gcs", AgentNotice(3, NoticeSource.AGENT, 6, "arrived: holding"))
    poll(lambda: count(page, '.plan-target[data-agent-id="3"]') == 0, "agent3 arrived", UI_DEADLINE)
    assert count(page, '.plan-route[data-agent-id="1"]') == 1
    target = page.evaluate(
        """() => { const el = document.querySelector('.plan-target[data-agent-id="1"]');
        const r = el.getBoundingClientRect();
        return window.gcs.map.containerPointToLatLng(L.point(
            r.left + r.width / 2 - window.gcs.map.getContainer().getBoundingClientRect().left,
            r.top + r.height / 2 - window.gcs.map.getContainer().getBoundingClientRect().top)); }"""
    )
    d = pymap3d.vincenty.vdist(target["lat"], target["lng"], wp2[0], wp2[1])[0]
    assert d < 1.0, f"the target is drawn {d:.2f} m from the last waypoint"
    # slots: where the formation's own geometry puts them, from the followed agent
    for member, a in ((2, 1), (3, 1), (4, 2), (5, 3)):
        slot = poll(
            lambda m=member: page.evaluate(f"window.gcsPlan.slot({m})"), f"slot {member}", UI_DEADLINE
        )
        followed = live.agents[a].pose()
        side = next(x.side for x in TASK.assignments if x.member == member)
        err = slot_error(
            Pose(slot[0], slot[1], 500.0), followed, TASK.heading, side, TASK.back_m, TASK.side_m
        )
        assert err < 0.05, f"agent{member}'s slot is {err:.3f} m off"
    assert count(page, ".plan-slot") == 4
    poll(lambda: count(page, ".plan-home") == len(V), "every home drawn", UI_DEADLINE)
    page.evaluate(f"window.gcs.map.setView([{HOME[0] + 15 / M_PER_DEG}, {HOME[1]}], 19, {{animate: false}})")
    poll(lambda: count(page, ".plan-home") == len(V), "homes drawn after the zoom", UI_DEADLINE)
    screenshot(page, "gcs_plan.png")
    # the layer control hides a layer and shows it again
    page.get_by_label("Go-to targets").uncheck()
    assert count(page, ".plan-target") == 0
    page.get_by_label("Go-to targets").check()
    assert count(page, '.plan-target[data-agent-id="1"]') == 1
    # "arrived": the route and the target go
    live.agents[1].tr.send("gcs", AgentNotice(1, NoticeSource.AGENT, 6, "arrived: holding"))
    poll(
        lambda: count(page, ".plan-target") == 0 and count(page, ".plan-route") == 0,
        "route cleared",
        UI_DEADLINE,
    )
    assert not cross_shown(page)  # the sent point does not linger after "arrived"


def test_measure_tool_against_pymap3d(page: Any) -> None:
    before = page.evaluate("document.querySelector('#goto-lat').value")
    page.click("#plan-measure")
    box = page.evaluate(
        """(() => { const r = window.gcs.map.getContainer().getBoundingClientRect();
        return [r.left, r.top, r.width, r.height]; })()"""
    )
    a = (box[0] + box[2] * 0.3, box[1] + box[3] * 0.7)
    b = (box[0] + box[2] * 0.75, box[1] + box[3] * 0.25)
    page.mouse.click(*a)
    page.mouse.click(*b)
    out = page.locator("#plan-measure-out")
    poll(lambda: out.get_attribute("data-m"), "a distance", UI_DEADLINE)
    pts = page.evaluate(
        f"[[{a[0] - box[0]}, {a[1] - box[1]}], [{b[0] - box[0]}, {b[1] - box[1]}]].map(p => {{"
        " const ll = window.gcs.map.containerPointToLatLng(L.point(p[0], p[1])); return [ll.lat, ll.lng]; })"
    )
    got = page.evaluate("window.gcsPlan.points")
    for p, q in zip(pts, got, strict=True):  # the points clicked (to a pixel: 0.4 m at zoom 18)
        assert pymap3d.vincenty.vdist(p[0], p[1], q[0], q[1])[0] < 1.0
    m, deg = pymap3d.vincenty.vdist(got[0][0], got[0][1], got[1][0], got[1][1])
    assert abs(float(out.get_attribute("data-m")) - float(m)) < 0.05
    assert abs(float(out.get_attribute("data-deg")) - float(deg)) < 0.05
    assert f"{float(m):.1f} m" in out.inner_text() and f"{float(deg):.1f}°" in out.inner_text()
    assert page.evaluate("document.querySelector('#goto-lat').value") == before  # the go-to did not move
    page.keyboard.press("Escape")
    assert out.get_attribute("data-m") is None and not page.evaluate("window.gcsPlan.measuring")


def test_labels_do_not_overlap_and_show_on_hover(page: Any) -> None:
    page.evaluate(f"window.gcs.map.setView([{HOME[0] - 4 / M_PER_DEG}, {HOME[1]}], 19, {{animate: false}})")

    def boxes() -> list[list[float]]:
        return list(
            page.evaluate(
                """Array.from(document.querySelectorAll('#map .agent-marker .tag'))
                .filter(t => getComputedStyle(t).visibility !== 'hidden')
                .map(t => { const r = t.getBoundingClientRect();
                  return [r.left, r.top, r.right, r.bottom]; })"""
            )
        )

    def apart() -> bool:
        bs = boxes()
        return all(
            not (p[0] < q[2] and q[0] < p[2] and p[1] < q[3] and q[1] < p[3])
            for i, p in enumerate(bs)
            for q in bs[i + 1 :]
        )

    poll(apart, "no two visible name tags overlap", UI_DEADLINE)
    # zoomed out, the V's tags collide: some hide; find one whose marker is on top where
    # the pointer goes (markers overlap too when the V is a few pixels wide)
    spot = None
    for zoom in (18, 17, 16):
        page.evaluate(f"window.gcs.map.setZoom({zoom}, {{animate: false}})")
        poll(
            lambda: count(page, ".tag.tag-hidden") > 0 and apart(),
            f"colliding tags hidden at zoom {zoom}",
            UI_DEADLINE,
        )
        spot = page.evaluate(
            """(() => { for (const t of document.querySelectorAll('#map .agent-marker .tag.tag-hidden')) {
              const m = t.closest('.agent-marker'), r = m.getBoundingClientRect();
              for (let i = 1; i < 8; i++) for (let j = 1; j < 8; j++) {
                const x = r.left + r.width * i / 8, y = r.top + r.height * j / 8;
                const top = document.elementFromPoint(x, y);
                if (top && top.closest('.agent-marker') === m) return [m.dataset.agentId, x, y];
              }
            } return null; })()"""
        )
        if spot is not None:
            break
    assert spot is not None, "no hidden tag's marker is uncovered at any zoom"
    page.mouse.move(spot[1], spot[2])
    tag = f'#map .agent-marker[data-agent-id="{spot[0]}"] .tag'
    vis = page.evaluate(f"getComputedStyle(document.querySelector({tag!r})).visibility")
    assert vis == "visible"


def test_follow_swarm_keeps_the_agents_in_view(live: Live, page: Any) -> None:
    page.evaluate(f"window.gcs.map.setView([{HOME[0]}, {HOME[1]}], 18, {{animate: false}})")
    zoom = page.evaluate("window.gcs.map.getZoom()")
    page.click("#plan-follow")
    assert page.evaluate("window.gcsPlan.follow")
    VAgent.shift[0] = 0.02  # the swarm flies 2.2 km north

    def in_view() -> bool:
        return bool(
            page.evaluate(
                """(() => { const m = window.gcs.map, b = m.getBounds();
                return window.gcs.agents.every(id => { const p = window.gcs.markerLatLng(id);
                  return p && b.contains(p) && p[0] > 47.41; }); })()"""
            )
        )

    try:
        poll(in_view, "every agent in view after the swarm moved", DEADLINE)
        assert page.evaluate("window.gcs.map.getZoom()") <= zoom
    finally:
        VAgent.shift[0] = 0.0
        page.click("#plan-follow")
