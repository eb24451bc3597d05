"""A station-to-station command replayed after the receiving station restarts (issue 27),
with real processes: two channels (one agent each), a station on each joined through a
``swarm router``, one swarm key. A spy on the router's network (a raw Zenoh session
with a queryable on station B's command key) overhears station A's ARM for B's agent;
B is killed (-9) and started again; the spy replays the overheard command to it within
the 30 s window. Before the fix B's replay guard lived in memory only: the restarted
B carried the ARM out again (the agent logged a second ARM).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from net_helpers import wait_until

from swarm.cli.bench.scale_procs import Deployment, http, led_swarms
from swarm.cli.procs import Child, json_events
from swarm.core.station.federation import HEADER, WINDOW_S, command_key
from swarm.runtime.keyspace.transport import open_session

pytestmark = pytest.mark.processes  # emulators, agents, two stations and a router
DEADLINE = 60.0


def arms(agent: Child) -> list[str]:
    return [e["text"] for e in json_events(agent.lines, "pilot") if e["text"].startswith("command ARM")]


def envelope_age_s(data: bytes) -> float:
    return time.time() - HEADER.unpack_from(data)[3] / 1e6


def raw_get(session: Any, key: str, payload: bytes) -> list[bytes]:
    return [
        r.ok.payload.to_bytes()
        for r in session.get(key, payload=payload, timeout=3.0, target=zenoh.QueryTarget.ALL)
        if r.ok is not None
    ]


@pytest.mark.timeout(300)
def test_a_command_overheard_on_the_router_is_not_carried_out_again_after_a_restart(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    state = tmp_path / "state"
    state.mkdir(mode=0o700)
    monkeypatch.setenv("STATE_DIRECTORY", str(state))  # the stations' state folder, as systemd sets it
    dep = Deployment(tmp_path, channels=2, agents=1)
    spy: Any = None
    evil: Any = None
    try:
        dep.start()
        wait_until(lambda: len(led_swarms(dep.state(0))) == 2, "A to list both channels, led", DEADLINE)
        agent_b = next(c for c in dep.children if c.name == "a21")
        evil = open_session(connect=[dep.router_ep])
        caught: list[bytes] = []
        spy = evil.declare_queryable(
            command_key("st1"), lambda q: (caught.append(q.payload.to_bytes()), q.drop())
        )
        time.sleep(1.0)  # the spy's route through the router
        status, body = http(dep.urls[0] + "api/command", {"target": 21, "kind": "arm"})
        assert status == 200 and body["results"][0]["station"] == "st1", body
        wait_until(lambda: len(arms(agent_b)) == 1, "B's agent to get the ARM once", DEADLINE)
        overheard = wait_until(lambda: [p for p in caught if b'"arm"' in p], "the spy to overhear it", 10.0)

        # B killed and started again, as a service manager would
        b = dep.stations[1]
        os.killpg(b.proc.pid, signal.SIGKILL)
        b.proc.wait(10)
        b.stop()
        again = Child(b.argv[3:], name="st1 again")  # the same command line
        dep.children.append(again)
        dep.stations[1] = again
        json.loads(again.wait_lines(1, 60)[0])
        # a new command from A is carried out by the new B (it knows its agent again) ...
        wait_until(
            lambda: http(dep.urls[0] + "api/command", {"target": 21, "kind": "arm"})[0] == 200,
            "the new B to carry out a new command from A",
            DEADLINE,
        )
        wait_until(lambda: len(arms(agent_b)) == 2, "B's agent to get the new ARM", DEADLINE)

        # ... and the overheard one, replayed to it inside the window, is not
        assert envelope_age_s(overheard[0]) < WINDOW_S - 3, "too slow to replay inside the window"
        answers = raw_get(evil, command_key("st1"), overheard[0])
        time.sleep(3.0)  # room for a third ARM to reach the agent
        assert answers == [], "the restarted station answered a replayed command"
        assert len(arms(agent_b)) == 2, arms(agent_b)
    finally:
        if spy is not None:
            with contextlib.suppress(Exception):
                spy.undeclare()
        if evil is not None:
            evil.close()
        dep.stop()
    for c in dep.children:
        assert not [e for e in c.errors if "Traceback" in e], (c.name, c.errors[-5:])
