"""The station's geofence attacked over its real HTTP API and WebSocket: a real server,
a real station over Zenoh and a scripted agent (tests/test_gcs_api.py's) standing on
the ground at 500 m AMSL, so the station knows its home. Every hostile altitude is
refused with a reason and nothing reaches the agent; an altitude above home inside
the fence reaches it as sent."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from typing import Any

import aiohttp
import pytest
from net_helpers import free_port, wait_until
from test_gcs_api import HOME, ScriptedAgent, http

from swarm.core.flight.formation import offset
from swarm.core.flight.geofence import Geofence
from swarm.core.station.model import StationConfig
from swarm.core.wire.message_types import CommandKind, Phase
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

AGENT = 4
GROUND = 500.0  # the scripted agent's altitude AMSL, on the ground: its home
LAT, LON = HOME[0] + AGENT * 1e-4, HOME[1]


def near(n: float = 30.0, e: float = 0.0) -> tuple[float, float]:
    return offset(LAT, LON, n, e)


@pytest.fixture(scope="module")
def bench() -> Iterator[dict[str, Any]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    station = Station("gcs", zenoh_listen=[ep], config=StationConfig(fence=Geofence(radius_m=500.0))).start()
    server = GcsServer(station, ServerConfig(port=free_port(), tiles=None, ws_hz=5.0)).start()
    agent = ScriptedAgent(ep, AGENT, phase=Phase.LEADER, leader=AGENT)
    try:
        wait_until(
            lambda: (
                (station.agent(AGENT) or {}).get("connected") and station.agent(AGENT)["home_alt"] == GROUND
            ),
            "the agent connected, its home seen",
            30,
        )
        yield {"base": server.url, "agent": agent}
    finally:
        agent.close()
        server.stop()
        station.stop()


def goto(**kw: Any) -> dict[str, Any]:
    lat, lon = near()
    return {"target": AGENT, "kind": "goto", "lat": lat, "lon": lon, **kw}


def raw_goto(alt_json: str) -> bytes:
    lat, lon = near()
    return f'{{"target": {AGENT}, "kind": "goto", "lat": {lat}, "lon": {lon}, "alt": {alt_json}}}'.encode()


far_lat, far_lon = near(n=600.0)
HOSTILE: list[tuple[Any, int, str]] = [
    (raw_goto("NaN"), 400, "not NaN"),
    (raw_goto("Infinity"), 400, "not Infinity"),
    (raw_goto("-Infinity"), 400, "not -Infinity"),
    (raw_goto("1e999"), 400, "not Infinity"),
    (raw_goto("-0"), 400, "below the floor (2 m above home)"),
    (raw_goto("-0.0"), 400, "below the floor"),
    (raw_goto("1" + "0" * 400), 400, "more than 15 digits"),
    (raw_goto('"20 m"'), 400, "'alt' must be a number, not a string"),
    (raw_goto("null"), 400, "not null"),
    (goto(), 400, "goto needs 'alt' (metres above home)"),
    (goto(alt=1.5), 400, "below the floor (2 m above home)"),
    (goto(alt=520.0), 400, "above the ceiling (120 m)"),  # AMSL given as above home
    (goto(alt_amsl=20.0), 400, "-480 m above home is below the floor"),  # 20 m AMSL, named so
    (goto(alt=20, alt_amsl=520), 400, "not both"),
    ({**goto(alt=20.0), "lat": far_lat, "lon": far_lon}, 400, "beyond the radius (500 m)"),
    ({"target": AGENT, "kind": "takeoff", "alt": 0.5}, 400, "below the floor"),
    ({"target": AGENT, "kind": "takeoff", "alt": 520}, 400, "above the ceiling"),
    ({"target": AGENT, "kind": "takeoff", "alt": "20 m"}, 400, "must be a number"),
    ({"target": "swarm", "kind": "takeoff", "alt": 1}, 400, "below the floor"),
]


@pytest.mark.processes
@pytest.mark.parametrize(("body", "status", "words"), HOSTILE)
def test_http_refuses_hostile_altitudes_and_sends_nothing(
    bench: dict[str, Any], body: Any, status: int, words: str
) -> None:
    agent = bench["agent"]
    n = len(agent.commands)
    raw = body if isinstance(body, bytes) else None
    st, answer, _ = http(bench["base"], "POST", "/api/command", None if raw else body, raw=raw)
    assert st == status and words in answer["error"], answer
    assert "\n" not in answer["error"]
    assert len(agent.commands) == n, "nothing sent"


@pytest.mark.processes
def test_http_sends_an_altitude_above_home_as_given(bench: dict[str, Any]) -> None:
    agent = bench["agent"]
    st, body, _ = http(bench["base"], "POST", "/api/command", goto(alt=20.0))
    assert st == 200 and body["ok"] is True
    assert (agent.commands[-1].kind, agent.commands[-1].alt) == (CommandKind.GOTO, 20.0)
    st, body, _ = http(bench["base"], "POST", "/api/command", goto(alt_amsl=GROUND + 35.0))
    assert st == 200 and agent.commands[-1].alt == pytest.approx(35.0)


async def _ws(base: str, bodies: list[Any]) -> dict[str, dict[str, Any]]:
    results: dict[str, dict[str, Any]] = {}
    async with aiohttp.ClientSession() as s, s.ws_connect(base + "ws") as ws:
        for i, b in enumerate(bodies):
            if isinstance(b, bytes):  # the raw JSON text, with NaN and the rest as sent
                text = b.decode()[:-1] + f', "type": "command", "id": "h{i}"}}'
            else:
                text = json.dumps({**b, "type": "command", "id": f"h{i}"})
            await ws.send_str(text)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 30
        while loop.time() < deadline and len(results) < len(bodies):
            m = await ws.receive_json(timeout=max(0.1, deadline - loop.time()))
            if m.get("type") == "command_result":
                results[m["id"]] = m
    return results


@pytest.mark.processes
def test_the_websocket_refuses_hostile_altitudes_and_sends_nothing(bench: dict[str, Any]) -> None:
    agent = bench["agent"]
    n = len(agent.commands)
    bodies = [b for b, _, _ in HOSTILE]
    results = asyncio.run(_ws(bench["base"], bodies))
    for i, (_, status, words) in enumerate(HOSTILE):
        r = results[f"h{i}"]
        assert r["status"] == status and words in r["error"], (i, r)
    assert len(agent.commands) == n, "nothing sent"
