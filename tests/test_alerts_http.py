"""Alerts over the real server: a real station over Zenoh hears an agent's notices
(sent by a real Transport), the state carries the alerts, and acknowledging them
over HTTP and the WebSocket takes hostile input (unknown ids, huge, wrong types, not
JSON, the token missing) with a one-line error and never a 500."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from typing import Any

import aiohttp
import pytest
from gcs_security_helpers import JSON, request
from net_helpers import free_port, wait_until

from swarm.cli.procs import start_emulator
from swarm.core.wire.message_types import AgentNotice, NoticeSource
from swarm.runtime.keyspace.transport import Transport
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig

TOKEN = "alerts-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def live() -> Iterator[dict[str, Any]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    station = Station("gcs", zenoh_listen=[ep]).start()
    server = GcsServer(station, ServerConfig(port=free_port(), token=TOKEN)).start()
    tr = Transport.open("agent7", connect=[ep])
    try:

        def alerts() -> list[dict[str, Any]]:
            return list(station.snapshot()["alerts"])

        texts = ["PreArm: GPS not healthy", "Battery 1 is low"]

        def sent() -> bool:
            for i, text in enumerate(texts):  # Zenoh may drop the first puts while it connects
                if not any(text in a["text"] for a in alerts()):
                    tr.send("gcs", AgentNotice(7, NoticeSource.AUTOPILOT, 4 - 2 * i, text))
            return len(alerts()) == 2

        wait_until(sent, "two alerts from the agent's notices", 30)
        yield {"station": station, "server": server, "alerts": alerts}
    finally:
        tr.close()
        server.stop()
        station.stop()


def ack(port: int, body: bytes, headers: dict[str, str] | None = None) -> Any:
    return request(port, "POST", "/api/alerts/ack", body, {**JSON, **AUTH} if headers is None else headers)


BAD_BODIES = [
    (b"not json", 400),
    (b"[1]", 400),
    (b'"1"', 400),
    (b"{}", 400),
    (b'{"id": "1"}', 400),
    (b'{"id": true}', 400),
    (b'{"id": 1.5}', 400),
    (b'{"id": 1e400}', 400),
    (b'{"id": [1]}', 400),
    (b'{"id": {"id": 1}}', 400),
    (b'{"id": 99999}', 404),
    (b'{"id": -3}', 404),
    (b'{"id": ' + b"9" * 900 + b"}", 404),
    (b'{"id": ' + b"9" * 5000 + b"}", 400),
    (b'{"id": 1, "x": "' + b"a" * 70_000 + b'"}', 413),
    # another station's alert, at a station joined to none: one line, nothing acknowledged
    (b'{"id": 1, "station": "gcsB"}', 404),
    (b'{"id": 1, "station": ["gcsB"]}', 404),
    (b'{"id": 1, "station": "<b>\\u202e' + b"x" * 900 + b'"}', 404),
]


@pytest.mark.parametrize(("body", "status"), BAD_BODIES)
def test_a_bad_acknowledgement_over_http_is_one_line_never_a_500(
    live: dict[str, Any], body: bytes, status: int
) -> None:
    r = ack(live["server"].port, body)
    assert r.status == status, (r.status, r.body[:200])
    r.error()  # one line of JSON
    assert all(not a["acked"] for a in live["alerts"]())


SHELVE_BAD = [
    (b"[]", 400),
    (b'{"id": 1}', 400),
    (b'{"id": 1, "seconds": -5}', 400),
    (b'{"id": 1, "seconds": 3601}', 400),
    (b'{"id": 1, "seconds": 1e400}', 400),
    (b'{"id": 1, "seconds": NaN}', 400),
    (b'{"id": 1, "seconds": "600"}', 400),
    (b'{"id": 1, "seconds": true}', 400),
    (b'{"id": "1", "seconds": 600}', 400),
    (b'{"id": 99999, "seconds": 600}', 404),
    (b'{"id": 1, "seconds": 600, "station": "gcsB"}', 409),
    (b'{"id": 1, "seconds": 600, "station": {"x": 1}}', 409),
]


@pytest.mark.parametrize(("body", "status"), SHELVE_BAD)
def test_a_bad_shelving_over_http_is_one_line_and_shelves_nothing(
    live: dict[str, Any], body: bytes, status: int
) -> None:
    r = request(live["server"].port, "POST", "/api/alerts/shelve", body, {**JSON, **AUTH})
    assert r.status == status, (r.status, r.body[:200])
    assert "\n" not in r.error()
    assert all(a["quiet"] is None for a in live["alerts"]())


def test_shelving_over_http_quiets_the_alarm_for_its_time_and_needs_the_token(live: dict[str, Any]) -> None:
    port = live["server"].port
    first = live["alerts"]()[0]
    body = json.dumps({"id": first["id"], "seconds": 900}).encode()
    assert request(port, "POST", "/api/alerts/shelve", body, JSON).status == 401
    assert live["alerts"]()[0]["quiet"] is None
    r = request(port, "POST", "/api/alerts/shelve", body, {**JSON, **AUTH})
    assert r.status == 200 and r.json["alert"]["quiet"] == "shelved"
    row = next(a for a in live["alerts"]() if a["id"] == first["id"])
    assert row["quiet"] == "shelved" and row["shelved_until"] - row["raised"] > 890
    back = json.dumps({"id": first["id"], "seconds": 0}).encode()
    assert request(port, "POST", "/api/alerts/shelve", back, {**JSON, **AUTH}).json["alert"]["quiet"] is None


def test_acknowledging_needs_the_token(live: dict[str, Any]) -> None:
    (first, _) = live["alerts"]()
    r = ack(live["server"].port, json.dumps({"id": first["id"]}).encode(), JSON)
    assert r.status == 401
    assert not live["alerts"]()[0]["acked"]


def test_acknowledging_over_the_websocket_with_hostile_messages_first(live: dict[str, Any]) -> None:
    server = live["server"]
    first, second = live["alerts"]()

    async def talk() -> list[dict[str, Any]]:
        async with aiohttp.ClientSession(headers=AUTH) as s, s.ws_connect(server.url + "ws") as ws:
            for msg in (
                {"type": "ack_alert"},
                {"type": "ack_alert", "id": "abc"},
                {"type": "ack_alert", "id": 10**14},
                {"type": "ack_alert", "id": [1]},
                {"type": "ack_alert", "id": 10**20},
                {"type": "ack_alert", "id": second["id"]},
            ):
                await ws.send_str(json.dumps(msg))
            answers: list[dict[str, Any]] = []
            while len(answers) < 6:
                m = json.loads((await ws.receive(timeout=30)).data)
                if m["type"] in ("error", "alert_acked"):
                    answers.append(m)
            return answers

    answers = asyncio.run(talk())
    assert [(a["type"], a.get("status")) for a in answers] == [
        ("error", 400),
        ("error", 400),
        ("error", 404),
        ("error", 400),
        ("error", 400),
        ("alert_acked", None),
    ]
    assert all("\n" not in a.get("reason", "") for a in answers)
    assert answers[-1]["alert"]["id"] == second["id"] and answers[-1]["alert"]["acked"]
    r = ack(server.port, json.dumps({"id": first["id"]}).encode())
    assert r.status == 200 and r.json["alert"]["acked"] is True
    assert [a["acked"] for a in live["alerts"]()] == [True, True]
    state = request(server.port, "GET", "/api/state", None, AUTH).json
    assert {a["kind"] for a in state["alerts"]} == {"statustext"}
    assert {a["level"] for a in state["alerts"]} == {"advisory", "critical"}  # PreArm: an advisory


@pytest.mark.processes
def test_a_station_on_a_radio_shows_its_radio_margins(tmp_path: Any) -> None:
    """The radio emulator's SiK radios send RADIO_STATUS: the state's ``radio`` has RSSI,
    noise and their margins while the reports keep coming."""
    emu, links = start_emulator(1, tmp_path)
    station = None
    try:
        station = Station("gcs", radio=links[0]).start()
        st = wait_until(lambda: station.snapshot()["radio"], "the station radio's RADIO_STATUS", 30)
        assert set(st) == {"rssi", "noise", "margin", "remrssi", "remnoise", "remmargin"}
        assert st["margin"] == st["rssi"] - st["noise"] and st["remmargin"] == st["remrssi"] - st["remnoise"]
    finally:
        if station is not None:
            station.stop()
        emu.stop()
