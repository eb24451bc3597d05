"""Swarms across channels with real processes: 2 emulators (NETIDs 25 and 26) x 2
agents, a station on each joined through a ``swarm router``, one swarm key. Station A's
API and page list all four agents (the API with their channel and station); a command from A reaches an
agent on B's channel (checked by A's geofence first) and is answered; B killed, its
agents are shown gone on A while A's own channel stays. Then the command line's bad
input: one line, exit 2."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
from gcs_browser import browser, new_page

from radios.ports import free_port
from swarm.cli.bench.scale_procs import Deployment, http, led_swarms, poll
from swarm.cli.commands.gcs import main as gcs_main
from swarm.cli.commands.router import main as router_main
from swarm.cli.procs import Child


@pytest.mark.processes
def test_two_channels_two_stations_one_router(tmp_path: Path) -> None:
    dep = Deployment(tmp_path, channels=2, agents=2)
    try:
        dep.start()
        poll(lambda: len(led_swarms(dep.state(0))) == 2, "A to list both channels' swarms, led")
        four = {(1, "c0", "st0"), (2, "c0", "st0"), (21, "c1", "st1"), (22, "c1", "st1")}
        # a swarm is led before A has heard every member of it (a loaded machine: seconds)
        poll(
            lambda: {(a["id"], a["net"], a["station"]) for a in dep.state(0)["agents"]} == four,
            "A to list all four agents with their channel and station",
        )
        s = dep.state(0)
        assert {(w["net"], w["station"]) for w in s["swarms"]} == {("c0", "st0"), ("c1", "st1")}
        assert [(x["name"], x["alive"]) for x in s["stations"]] == [("st0", True), ("st1", True)]
        # the page (headless Chromium): one fleet table with both channels' agents
        with browser() as ctx, new_page(ctx) as page:
            page.goto(dep.urls[0])
            rows = "Array.from(document.querySelectorAll('#agents tbody tr[data-agent-id]'))"
            rows += ".map(r => +r.dataset.agentId)"
            poll(lambda: sorted(page.evaluate(rows)) == [1, 2, 21, 22], "the page to list all four agents")
            assert page.errors == []
        url = dep.urls[0] + "api/command"
        # to one agent of B's: carried by B on its radio, the agent's own answer back
        st, body = http(url, {"target": 22, "kind": "arm"})
        assert st == 200 and body["results"] == [
            {
                "agent": 22,
                "result": "FAILED",
                "reason": "no flight controller on this agent",
                "net": "c1",
                "station": "st1",
            }
        ], body
        # checked here first: A's geofence (120 m ceiling) refuses, nothing sent
        st, body = http(url, {"target": 21, "kind": "takeoff", "alt": 500})
        assert st == 400 and "geofence" in body["error"], body
        # a route to every swarm: refused, A's swarm and B's would fly one way and meet
        leader_b = next(a["leader"] for a in s["agents"] if a["net"] == "c1")
        st, body = http(url, {"target": "swarm", "kind": "follow", "heading": 90})
        assert st == 409 and "one swarm" in body["error"], body
        # to B's swarm by its leader: B's leader answers, through B
        st, body = http(url, {"target": "swarm", "swarm": leader_b, "kind": "follow", "heading": 90})
        assert st == 200, body
        assert {(r["agent"], r["result"], r.get("station")) for r in body["results"]} >= {
            (leader_b, "ACCEPTED", "st1")
        }
        dep.kill_station(1)
        poll(
            lambda: all(not a["connected"] for a in dep.state(0)["agents"] if a["net"] == "c1"),
            "B's agents shown gone on A",
        )
        s = dep.state(0)
        assert list(led_swarms({"agents": [a for a in s["agents"] if a["net"] == "c0"]})) == ["c0"]
        assert [(x["name"], x["alive"]) for x in s["stations"]] == [("st0", True), ("st1", False)]
        st, body = http(url, {"target": 21, "kind": "land"})
        assert st == 409 and "station st1 is gone" in body["error"], body
    finally:
        dep.stop()
    router, station_a = dep.children[0], dep.stations[0]
    assert (router.proc.returncode, station_a.proc.returncode) == (0, 0)  # SIGTERM: a clean stop
    for c in dep.children:
        assert not [e for e in c.errors if "Traceback" in e], (c.name, c.errors[-5:])


def test_bad_radios_and_router_endpoints_are_one_line_errors(capsys: pytest.CaptureFixture[str]) -> None:
    for argv, why in (
        (["--radio", "a=/dev/x", "--radio", "a=/dev/y"], "each channel needs its own name and radio"),
        (["--radio", "/dev/x", "--radio", "/dev/x"], "each channel needs its own name and radio"),
        (["--radio", "/dev/x", "--allow-unsigned-remote"], "--allow-unsigned-remote is for a station"),
        (["--radio", "/dev/x", "--radio", "/dev/y", "--capture", "f.tlog"], "--capture records one radio"),
    ):
        assert gcs_main(argv) == 2
        err = capsys.readouterr().err
        assert why in err and len(err.strip().splitlines()) == 1, err
    assert router_main(["--listen", "tcp/127.0.0.1:notaport"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("swarm router: error:") and len(err.strip().splitlines()) == 1, err


@pytest.mark.processes
def test_the_router_stops_on_sigint_with_130() -> None:
    ep = f"tcp/127.0.0.1:{free_port('tcp')}"
    router = Child(["router", "--listen", ep, "--json"], name="router")
    try:
        ready = json.loads(router.wait_lines(1, 30)[0])
        assert ready["event"] == "ready" and ready["listen"] == [ep] and ready["zid"]
        router.proc.send_signal(signal.SIGINT)
        assert router.proc.wait(10) == 130
    finally:
        router.stop()
    assert not router.errors, router.errors
