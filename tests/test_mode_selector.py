"""The flight mode selector (issue 28): one vehicle's autopilot mode chosen from the page.

Pure: the station takes only the selectable modes (manual and stick modes are not
offered: a companion-only vehicle has no pilot on the sticks) and only for one agent;
the Command carries the mode's code; the agent's pilot makes a hold mode (AUTO.LOITER,
BRAKE) the autopilot's, in the air only, leaving the formation and saying it is not
following until a go-to, stop, take-off or follow takes control back; a landing or
return mode is LAND or RETURN; the setpoint mode (OFFBOARD, GUIDED) is its STOP.

End to end (real processes and the real page): ``swarm sim`` (PX4-like), ``swarm
agent`` and ``swarm gcs``; the operator takes off, selects AUTO.LOITER and confirms:
the station follows the vehicle to "done: in AUTO.LOITER", the panel offers the way
back, and "Take control (hold here)" brings it back under the swarm's setpoints."""

from __future__ import annotations

import json
import urllib.request
from collections.abc import Iterator
from typing import Any

import pytest
from gcs_browser import browser, new_page, poll, screenshot, start_station
from net_helpers import free_port, free_port_range

from swarm.cli.procs import Child
from swarm.core.flight.pilot import Call, Mode, Pilot, PilotConfig, Role
from swarm.core.station.commands import CommandRefused, parse_command
from swarm.core.wire.codes import SELECTABLE_MODES, mode_code
from swarm.core.wire.message_types import AckResult, Command, CommandKind, Phase, Pose
from swarm.core.wire.messages import decode, encode

ROLE = Role(Phase.MEMBER, 1, frozenset())


def flying() -> Pilot:
    p = Pilot(3, PilotConfig())
    p.airborne = True
    p.own = Pose(47.397742, 8.545594, 520.0)
    p.home = (47.397742, 8.545594, 500.0)
    p.hold("test")
    return p


def set_mode(name: str, target: int = 3) -> Command:
    return Command(255, 1, target, CommandKind.SET_MODE, mode=mode_code(name))


@pytest.mark.parametrize(
    ("body", "says"),
    [
        ({"target": 3, "kind": "set_mode", "mode": "MANUAL"}, "one of AUTO.LOITER"),
        ({"target": 3, "kind": "set_mode", "mode": "POSCTL"}, "one of AUTO.LOITER"),
        ({"target": 3, "kind": "set_mode", "mode": ["AUTO.LOITER"]}, "of type list"),
        ({"target": 3, "kind": "set_mode"}, "'mode' none"),
        ({"target": "swarm", "kind": "set_mode", "mode": "AUTO.LOITER"}, "for one agent"),
    ],
)
def test_the_station_takes_only_selectable_modes_for_one_agent(body: dict[str, Any], says: str) -> None:
    with pytest.raises(CommandRefused) as exc:
        parse_command(body)
    assert exc.value.status == 400 and says in exc.value.reason


def test_a_selectable_mode_crosses_the_air_as_its_code() -> None:
    spec = parse_command({"target": 3, "kind": "set_mode", "mode": "auto.loiter"})
    assert spec.mode == "AUTO.LOITER"
    cmd = set_mode("AUTO.LOITER")
    assert decode(encode(cmd)) == cmd and len(encode(cmd)) == 7
    assert set(SELECTABLE_MODES.values()) == {"hold", "land", "return", "swarm"}


def test_a_hold_mode_hands_the_vehicle_to_its_autopilot_until_taken_back() -> None:
    p = flying()
    result, why, calls = p.command(set_mode("AUTO.LOITER"), ROLE, 1.0)
    assert (result, why) == (AckResult.ACCEPTED, "switching to AUTO.LOITER") and p.mode == Mode.AUTOPILOT
    assert [(c.kind, c.mode) for c in calls] == [("mode", "AUTO.LOITER")]
    assert p.step(1.1, ROLE)[0] is None  # no setpoints: the autopilot flies it
    p.call_done(calls[0], True)
    assert p.control_lost == "AUTO.LOITER" and "at the operator's request" in p.events[-1]
    p.set_control(False, "AUTO.LOITER")
    p.set_control(False, "AUTO.LOITER")
    assert not any("by itself" in e for e in p.events)  # asked for: not a failsafe
    lat, lon = 47.3982, 8.545594
    result, why, calls = p.command(Command(255, 2, 3, CommandKind.GOTO, lat, lon, 20.0), ROLE, 2.0)
    assert result == AckResult.ACCEPTED and "taking control back from AUTO.LOITER" in why
    assert Call("control") in calls


def test_a_hold_mode_on_the_ground_and_an_unknown_code_are_refused() -> None:
    p = Pilot(3, PilotConfig())
    assert p.command(set_mode("BRAKE"), ROLE, 1.0)[0] == AckResult.REJECTED
    p = flying()
    result, why, _ = p.command(Command(255, 1, 3, CommandKind.SET_MODE, mode=mode_code("MANUAL")), ROLE, 1.0)
    assert result == AckResult.BAD_ARGUMENT and "MANUAL is not one to select" in why
    assert p.command(set_mode("AUTO.LOITER", target=0), ROLE, 1.0)[0] == AckResult.BAD_ARGUMENT


@pytest.mark.parametrize(("mode", "call"), [("AUTO.LAND", "land"), ("RTL", "return")])
def test_a_landing_or_return_mode_is_that_command(mode: str, call: str) -> None:
    p = flying()
    result, _, calls = p.command(set_mode(mode), ROLE, 1.0)
    assert result == AckResult.ACCEPTED and [c.kind for c in calls] == [call]


def test_the_setpoint_mode_is_the_agents_stop_taking_control_back() -> None:
    p = flying()
    p.command(set_mode("AUTO.LOITER"), ROLE, 1.0)
    p.call_done(Call("mode", mode="AUTO.LOITER"), True)
    result, _, calls = p.command(set_mode("OFFBOARD"), ROLE, 2.0)
    assert result == AckResult.ACCEPTED and Call("control") in calls and p.mode == Mode.HOLD


# -- end to end --------------------------------------------------------------------------

HOME = (47.397742, 8.545594, 488.0)
DEADLINE = 90.0


@pytest.fixture(scope="module")
def bench() -> Iterator[tuple[str, list[Child]]]:
    children: list[Child] = []
    try:
        sim = Child(["sim", "--vehicles", "1", "--base-port", str(free_port_range(1, "udp")),
                     f"--home={HOME[0]},{HOME[1]},{HOME[2]}"], name="sim")  # fmt: skip
        children.append(sim)
        fc = sim.wait_lines(2, DEADLINE)[0].split(" -> ")[1].split()[0]
        ep = f"tcp/127.0.0.1:{free_port()}"
        agent = Child(["agent", "--name", "agent1", "--id", "1", "--zenoh-connect", ep, "--fc", fc, "--json"],
                      name="agent1")  # fmt: skip
        children.append(agent)
        assert json.loads(agent.wait_lines(1, DEADLINE)[0])["event"] == "ready"
        station, url = start_station(
            ["--zenoh-listen", ep, "--http", f"127.0.0.1:{free_port()}", "--tiles", "none"]
        )
        children.append(station)
        yield url, children
    finally:
        for c in reversed(children):
            c.stop(grace=3)


def api_agent(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "api/agents/1", timeout=30) as r:
        return dict(json.loads(r.read()))


@pytest.mark.processes
def test_the_page_switches_a_flying_vehicle_to_its_autopilots_hold_and_takes_it_back(
    bench: tuple[str, list[Child]],
) -> None:
    url, kids = bench
    with browser() as ctx, new_page(ctx) as page:
        page.set_viewport_size({"width": 1400, "height": 900})
        page.goto(url)
        page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=15_000)
        row = '#agents [data-agent-id="1"]'
        poll(lambda: page.locator(row).count() == 1, "agent1 listed", DEADLINE, kids)
        poll(lambda: api_agent(url)["home_alt"] is not None, "agent1's home", DEADLINE, kids)
        assert page.locator("#mode-row").is_hidden()  # no agent selected: no mode to set
        page.click(row)
        page.click('#commands [data-kind="arm"]')
        poll(lambda: "arm" in page.inner_text("#cmd-status") and "done" in page.inner_text("#cmd-status"),
             "armed", DEADLINE, kids)  # fmt: skip
        page.fill("#takeoff-alt", "10")
        page.click('#commands [data-kind="takeoff"]')
        page.click("#confirm-ok")
        poll(lambda: "done: airborne" in page.inner_text("#cmd-status"), "the take-off done", DEADLINE, kids)
        poll(
            lambda: api_agent(url)["mode"] == "OFFBOARD",
            "holding under setpoints after the climb",
            DEADLINE,
            kids,
        )
        # the page's own view, not only the API's: the confirmation names the mode the page shows
        poll(
            lambda: page.inner_text('#telemetry [data-field="mode"]') == "OFFBOARD",
            "the page",
            DEADLINE,
            kids,
        )
        assert page.locator("#mode-row").is_visible()
        options = page.eval_on_selector_all("#mode-select option", "os => os.map((o) => o.value)")
        assert options == ["AUTO.LOITER", "AUTO.RTL", "AUTO.LAND", "OFFBOARD"]  # PX4's, no manual mode
        page.select_option("#mode-select", "AUTO.LOITER")
        page.click("#mode-set")
        text = page.inner_text("#confirm-text")
        assert (
            "Switch agent1 (1) from OFFBOARD to AUTO.LOITER?" in text and "stops following the swarm" in text
        )
        page.click("#confirm-ok")
        poll(lambda: "done: in AUTO.LOITER" in page.inner_text("#cmd-status"), "the mode set", DEADLINE, kids)
        assert api_agent(url)["mode"] == "AUTO.LOITER"
        poll(lambda: page.locator("#take-back").is_visible(), "the way back offered", DEADLINE, kids)
        screenshot(page, "gcs_mode_selector_loiter.png")
        page.click('#take-back [data-take="stop"]')
        page.click("#confirm-ok")
        poll(lambda: "done: holding" in page.inner_text("#cmd-status"), "control taken back", DEADLINE, kids)
        poll(lambda: api_agent(url)["mode"] == "OFFBOARD", "back under the swarm's setpoints", DEADLINE, kids)
        poll(lambda: page.locator("#take-back").is_hidden(), "the box gone", DEADLINE, kids)
        assert page.errors == []
