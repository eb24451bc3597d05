"""The ground station's HTTP API and WebSocket against hostile senders, with a real
server on a free port, a real station over Zenoh and scripted agents that record
every command they receive.

Who may command the swarm: a foreign ``Origin`` (another page, another port), a
foreign ``Host`` (DNS rebinding), a body that is not ``application/json`` (a
no-cors text/plain fetch, a form), a missing or wrong token: refused before
anything reaches the station. The token: an "Authorization: Bearer" header (the
page's requests), the WebSocket subprotocol ``token.<TOKEN>`` or ``?token=``; never a
cookie (a host's cookies go to every port of it).

What may not break it: huge numbers, NaN/Infinity, deep nesting, wrong types,
bodies over 64 KiB, non-UTF-8, slow clients: always a 4xx with a one-line JSON
error, never a 5xx, and the WebSocket stays open after a bad message. Hypothesis
drives both with arbitrary JSON.
"""

from __future__ import annotations

import asyncio
import json
import socket
from collections.abc import Iterator
from typing import Any

import aiohttp
import pytest
from gcs_security_helpers import JSON, TAKEOFF, Swarm, live_swarm, request
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from net_helpers import ManualClock, free_port, wait_until

from swarm.core.station.commands import KINDS, CommandRefused, parse_command
from swarm.runtime.station.server import OSM_TILES, STATIC_DIR, GcsServer, ServerConfig, page_policy

TOKEN = "Zq0-test-token-with-enough-entropy_42"


@pytest.fixture(scope="module")
def swarm() -> Iterator[Swarm]:
    with live_swarm(2) as s:
        yield s


@pytest.fixture(scope="module")
def open_server(swarm: Swarm) -> Iterator[GcsServer]:
    """The default: loopback, no token (as `swarm demo` runs it)."""
    server = GcsServer(swarm.station, ServerConfig(port=free_port(), tiles=None)).start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="module")
def field_server(swarm: Swarm) -> Iterator[GcsServer]:
    """Bound to every address (as in the field), with a token and one allowed name."""
    server = GcsServer(
        swarm.station,
        ServerConfig(host="0.0.0.0", port=free_port(), tiles=None, token=TOKEN, allow_hosts=("gcs.field",)),
    ).start()
    try:
        yield server
    finally:
        server.stop()


def unchanged(swarm: Swarm, before: int) -> None:
    """No command reached the station or the agents."""
    assert swarm.commands() == before, "a command reached the swarm"


# -- who may command ------------------------------------------------------------------


@pytest.mark.parametrize("ctype", ["text/plain", "application/json", "application/x-www-form-urlencoded"])
@pytest.mark.parametrize(
    "origin",
    [
        "http://attacker.test:8000",
        "null",
        "http://127.0.0.1:{other}",
        "http://localhost:{port}",
        "https://127.0.0.1:{port}",
    ],
)
def test_a_foreign_origin_commands_nothing(
    swarm: Swarm, open_server: GcsServer, ctype: str, origin: str
) -> None:
    port = open_server.port
    origin = origin.format(port=port, other=port + 1)
    before = swarm.settled_commands()
    for path in ("/api/command", "/api/replay"):
        a = request(port, "POST", path, TAKEOFF, {"Content-Type": ctype, "Origin": origin})
        assert a.status == 403, (path, a.status, a.body[:200])
        assert "origin" in a.error()
    unchanged(swarm, before)


def test_a_foreign_origin_reads_nothing(open_server: GcsServer) -> None:
    port = open_server.port
    for path in ("/api/state", "/api/config", "/api/agents/1", "/api/replay"):
        a = request(port, "GET", path, headers={"Origin": "http://attacker.test"})
        assert a.status == 403 and b"agent" not in a.body, (path, a.status, a.body[:200])
    # a cross-site fetch the browser marks as such, whatever its Origin says
    a = request(port, "GET", "/api/state", headers={"Sec-Fetch-Site": "cross-site"})
    assert a.status == 403
    # the page's own requests: same origin
    same = f"http://127.0.0.1:{port}"
    assert (
        request(port, "GET", "/api/state", headers={"Origin": same, "Sec-Fetch-Site": "same-origin"}).status
        == 200
    )


def test_the_same_origin_and_plain_clients_command(swarm: Swarm, open_server: GcsServer) -> None:
    port = open_server.port
    n = len(swarm.agents[2].commands)
    body = json.dumps({"target": 2, "kind": "arm"}).encode()
    for headers in (
        {"Origin": f"http://127.0.0.1:{port}", **JSON},
        {"Origin": f"http://localhost:{port}", "Host": f"localhost:{port}", **JSON},
        {"Content-Type": "application/json; charset=utf-8"},
        JSON,
    ):
        a = request(port, "POST", "/api/command", body, headers)
        assert a.status == 200 and a.json["ok"] is True, (headers, a.body)
    assert len(swarm.agents[2].commands) >= n + 4


@pytest.mark.parametrize(
    "ctype",
    [
        None,
        "text/plain",
        "application/x-www-form-urlencoded",
        "multipart/form-data; boundary=x",
        "application/json; charset=latin-1",
        "application/jsonx",
        "text/json",
    ],
)
def test_a_body_that_is_not_json_is_415(swarm: Swarm, open_server: GcsServer, ctype: str | None) -> None:
    before = swarm.settled_commands()
    headers = {} if ctype is None else {"Content-Type": ctype}
    a = request(open_server.port, "POST", "/api/command", TAKEOFF, headers)
    assert a.status == 415 and "application/json" in a.error(), (a.status, a.body[:200])
    unchanged(swarm, before)


@pytest.mark.parametrize(
    "host",
    [
        "rebind.test:{port}",
        "rebind.test",
        "127.0.0.1.nip.io:{port}",
        "evil.localhost.attacker.test:{port}",
        "10.1.2.3:{port}",
        "",
        "[::1",
    ],
)
def test_a_foreign_host_is_refused(swarm: Swarm, open_server: GcsServer, host: str) -> None:
    port = open_server.port
    host = host.format(port=port)
    before = swarm.settled_commands()
    for method, path, body, headers in [
        ("GET", "/", None, {}),
        ("GET", "/api/state", None, {}),
        ("GET", "/static/app.js", None, {}),
        ("POST", "/api/command", TAKEOFF, JSON),
    ]:
        a = request(port, method, path, body, {"Host": host, **headers})
        assert a.status in (400, 403) and b"agent" not in a.body, (host, path, a.status, a.body[:200])
        assert a.status == 400 or "host" in a.error()
    unchanged(swarm, before)


@pytest.mark.parametrize(
    "host",
    [
        "127.0.0.1:{port}",
        "localhost:{port}",
        "LOCALHOST:{port}",
        "[::1]:{port}",
        "gcs.localhost:{port}",
        "127.0.0.1",
    ],
)
def test_local_names_are_served(open_server: GcsServer, host: str) -> None:
    a = request(open_server.port, "GET", "/api/config", headers={"Host": host.format(port=open_server.port)})
    assert a.status == 200, (host, a.body)


def test_websocket_from_a_foreign_origin_is_refused(swarm: Swarm, open_server: GcsServer) -> None:
    before = swarm.settled_commands()

    async def attempt(origin: str | None, host: str | None = None) -> Any:
        headers = {k: v for k, v in (("Origin", origin), ("Host", host)) if v is not None}
        async with aiohttp.ClientSession() as s:
            try:
                async with s.ws_connect(open_server.url + "ws", headers=headers) as ws:
                    first = await ws.receive_json(timeout=10)
                    await ws.send_str(
                        json.dumps(
                            {"type": "command", "id": 1, "target": "swarm", "kind": "follow", "heading": 90}
                        )
                    )
                    return first
            except aiohttp.WSServerHandshakeError as exc:
                return exc.status

    port = open_server.port
    for origin, host in [
        ("http://attacker.test", None),
        ("null", None),
        (f"http://127.0.0.1:{port + 1}", None),
        (f"http://rebind.test:{port}", f"rebind.test:{port}"),
    ]:
        assert asyncio.run(attempt(origin, host)) == 403, origin
    unchanged(swarm, before)
    # the station's own page: served (its FOLLOW goes out)
    first = asyncio.run(attempt(f"http://127.0.0.1:{port}"))
    assert isinstance(first, dict) and first["type"] == "state"


# -- the token -----------------------------------------------------------------------


def test_beyond_loopback_every_api_needs_the_token(swarm: Swarm, field_server: GcsServer) -> None:
    port = field_server.port
    before = swarm.settled_commands()
    for headers in (
        {},
        {"Authorization": "Bearer wrong"},
        {"Authorization": f"Bearer {TOKEN}x"},
        {"Authorization": f"Basic {TOKEN}"},
        {"Cookie": f"gcs_token_{port}=nope"},
        {"Authorization": "Bearer \u00e9\u00e9"},
        {"Cookie": f"gcs_token_{port + 1}={TOKEN}"},
    ):
        for method, path, body in [
            ("GET", "/api/state", None),
            ("GET", "/api/config", None),
            ("POST", "/api/command", TAKEOFF),
            ("GET", "/tiles/1/1/1.png", None),
        ]:
            h = {**JSON, **headers} if body else headers
            raw = {k: v.encode("utf-8").decode("latin-1") for k, v in h.items()}  # bytes as sent
            a = request(port, method, path, body, raw)
            assert a.status == 401 and "token" in a.error(), (headers, path, a.status, a.body[:200])
    for q in ("", "?token=wrong", f"?token={TOKEN[:-1]}"):
        a = request(port, "GET", "/api/state" + q)
        assert a.status == 401
    # the page without a token: its own file (a form asking for the token in it), nothing
    # of the swarm; its scripts too
    a = request(port, "GET", "/")
    assert a.status == 200 and a.body == (STATIC_DIR / "index.html").read_bytes()
    assert b'name="token"' in a.body and a.headers.get("Cache-Control") == "no-store"
    csp = a.headers.get("Content-Security-Policy", "")
    assert "default-src 'self'" in csp and "frame-ancestors 'none'" in csp, csp
    assert request(port, "GET", "/static/token.js").status == 200
    unchanged(swarm, before)


def test_the_token_by_header_and_url_never_by_cookie(swarm: Swarm, field_server: GcsServer) -> None:
    port = field_server.port
    bearer = {"Authorization": f"Bearer {TOKEN}"}
    a = request(port, "GET", "/api/state", headers=bearer)
    assert a.status == 200 and len(a.json["agents"]) == 2
    assert request(port, "GET", f"/api/state?token={TOKEN}").status == 200  # tools
    # the printed address: the page, and no cookie (cookies reach every port of the host)
    a = request(port, "GET", f"/?token={TOKEN}")
    assert a.status == 200 and b"<html" in a.body.lower()
    assert "Set-Cookie" not in a.headers, a.headers
    # the cookie earlier versions set opens nothing, and is deleted where it is shown
    name = f"gcs_token_{port}"
    jar = {"Cookie": f"{name}={TOKEN}"}
    assert request(port, "GET", "/api/state", headers=jar).status == 401
    a = request(port, "GET", "/", headers=jar)
    assert a.status == 200
    gone = a.headers.get("Set-Cookie", "")
    assert gone.startswith(f'{name}="";') and "Max-Age=0" in gone and "Path=/" in gone, gone
    n = len(swarm.agents[1].commands)
    a = request(
        port,
        "POST",
        "/api/command",
        json.dumps({"target": 1, "kind": "disarm"}).encode(),
        {**bearer, **JSON, "Origin": f"http://127.0.0.1:{port}"},
    )
    assert a.status == 200 and a.json["ok"] is True
    assert len(swarm.agents[1].commands) > n
    # an allowed name and any address of this machine's; a foreign name still refused
    for host in ("gcs.field", f"gcs.field:{port}", f"10.9.8.7:{port}", f"[fe80::1]:{port}"):
        assert request(port, "GET", "/api/config", headers={"Host": host, **bearer}).status == 200, host
    a = request(port, "GET", "/api/config", headers={"Host": f"rebind.test:{port}", **bearer})
    assert a.status == 403 and "--allow-host" in a.error()
    # but the token does not let another origin in
    a = request(
        port, "POST", "/api/command", TAKEOFF, {**bearer, **JSON, "Origin": f"http://127.0.0.1:{port + 1}"}
    )
    assert a.status == 403


def test_the_websocket_needs_the_token_too(field_server: GcsServer) -> None:
    port = field_server.port
    base = f"http://127.0.0.1:{port}/"

    async def attempt(url: str, headers: dict[str, str], protocols: tuple[str, ...] = ()) -> Any:
        async with aiohttp.ClientSession() as s:
            try:
                async with s.ws_connect(url, headers=headers, protocols=protocols) as ws:
                    first = (await ws.receive_json(timeout=10))["type"]
                    return first if not protocols else (first, ws.protocol)
            except aiohttp.WSServerHandshakeError as exc:
                return exc.status

    assert asyncio.run(attempt(base + "ws", {})) == 401
    assert asyncio.run(attempt(base + "ws", {"Cookie": f"gcs_token_{port}={TOKEN}"})) == 401
    assert asyncio.run(attempt(base + "ws", {"Authorization": f"Bearer {TOKEN}"})) == "state"
    assert asyncio.run(attempt(base + f"ws?token={TOKEN}", {})) == "state"
    # the page's way: the token as a subprotocol; the answer names "swarm-gcs", not it
    page = ("swarm-gcs", f"token.{TOKEN}")
    assert asyncio.run(attempt(base + "ws", {}, page)) == ("state", "swarm-gcs")
    assert asyncio.run(attempt(base + "ws", {}, ("swarm-gcs", "token.wrong-token-0123456789"))) == 401
    assert asyncio.run(attempt(base + "api/state", {}, page)) == 401  # on /ws only


def test_the_pages_policy_names_the_tile_source() -> None:
    assert "img-src 'self' data: blob:;" in page_policy(None)
    assert "img-src 'self' data: blob: https://tile.openstreetmap.org;" in page_policy(OSM_TILES)
    assert "blob: https://*.tile.example.org;" in page_policy("https://{s}.tile.example.org/{z}/{x}/{y}.png")
    assert "blob: http://127.0.0.1:5555;" in page_policy("http://127.0.0.1:5555/{z}/{x}/{y}.png")
    assert "blob: https:;" in page_policy("https://a{s}b.example.org/{z}/{x}/{y}.png")  # no wildcard there
    assert "blob:;" in page_policy("/tiles/{z}/{x}/{y}.png")


def test_a_token_is_generated_beyond_loopback_and_optional_on_it(swarm: Swarm) -> None:
    cfg = ServerConfig(host="0.0.0.0", port=0)
    assert cfg.token is not None and len(cfg.token) >= 40
    assert ServerConfig(host="0.0.0.0", port=0).token != cfg.token
    assert ServerConfig(port=0).token is None and ServerConfig(host="::1", port=0).token is None
    with pytest.raises(ValueError, match="token"):
        ServerConfig(port=0, token="short")
    with pytest.raises(ValueError, match="token"):
        ServerConfig(port=0, token="has spaces and is long enough")
    # on loopback a token given is enforced
    server = GcsServer(swarm.station, ServerConfig(port=0, tiles=None, token=TOKEN)).start()
    try:
        assert request(server.port, "GET", "/api/state").status == 401
        bearer = {"Authorization": f"Bearer {TOKEN}"}
        assert request(server.port, "GET", "/api/state", headers=bearer).status == 200
        assert server.token_url == f"http://127.0.0.1:{server.port}/?token={TOKEN}"
    finally:
        server.stop()


# -- bad input ---------------------------------------------------------------------

HUGE = "1" + "0" * 400
DEEP = "[" * 5000 + "]" * 5000
BAD_BODIES: list[tuple[bytes, int, str]] = [
    (f'{{"target": 1, "kind": "takeoff", "alt": {HUGE}}}'.encode(), 400, "number"),
    (f'{{"target": 1, "kind": "takeoff", "alt": -{HUGE}}}'.encode(), 400, "number"),
    (f'{{"target": {HUGE}, "kind": "arm"}}'.encode(), 400, "number"),
    (b'{"target": 1, "kind": "takeoff", "alt": 1e999}', 400, "number"),
    (b'{"target": 1, "kind": "takeoff", "alt": NaN}', 400, "NaN"),
    (b'{"target": 1, "kind": "takeoff", "alt": Infinity}', 400, "Infinity"),
    (b'{"target": 1, "kind": "takeoff", "alt": -Infinity}', 400, "Infinity"),
    (b'{"target": "swarm", "kind": "follow", "heading": 1' + b"0" * 5000 + b"}", 400, "number"),
    (DEEP.encode(), 400, "nested"),
    (b'{"target": ' + DEEP.encode() + b', "kind": "arm"}', 400, "nested"),
    (b'{"target": 1, "kind": ' + b'{"a": ' * 3000 + b"1" + b"}" * 3000 + b"}", 400, "nested"),
    (b'{"target": [[[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]]], "kind": "arm"}', 400, "nested"),
    (b'{"target": {"x": 1}, "kind": "arm"}', 400, "target"),
    (b'{"target": 1, "kind": ["arm"]}', 400, "kind"),
    (b'{"target": 1, "kind": "takeoff", "alt": "10"}', 400, "number"),
    (b'{"target": 1, "kind": "takeoff", "alt": true}', 400, "number"),
    (b'{"target": 1, "kind": "' + b"x" * 20000 + b'"}', 400, "unknown command kind"),
    (b'{"target": "' + b"s" * 20000 + b'", "kind": "arm"}', 400, "target"),
    (b'"\xff\xfe\x00"', 400, "UTF-8"),
    (b"\xef\xbb\xbf{}", 400, "malformed JSON"),
    (b'{"target": 1, "kind": "arm", "x": "\\ud800"}', 200, ""),
    (b"", 400, "malformed JSON"),
    (b"{" + b" " * 70000 + b"}", 413, "too large"),
]


@pytest.mark.parametrize(
    ("raw", "status", "reason"), BAD_BODIES, ids=[f"{i}-{r[:24]!r}" for i, (r, _, _) in enumerate(BAD_BODIES)]
)
def test_extreme_json_is_a_4xx_with_a_reason(
    swarm: Swarm, open_server: GcsServer, raw: bytes, status: int, reason: str
) -> None:
    a = request(open_server.port, "POST", "/api/command", raw, JSON)
    assert a.status == status, (a.status, a.body[:300])
    if status >= 400:
        assert reason in a.error()
    assert request(open_server.port, "GET", "/api/config").status == 200


def test_a_huge_declared_body_is_413_unread(open_server: GcsServer) -> None:
    with socket.create_connection(("127.0.0.1", open_server.port), timeout=30) as s:
        s.sendall(
            f"POST /api/command HTTP/1.1\r\nHost: 127.0.0.1:{open_server.port}\r\n"
            "Content-Type: application/json\r\nContent-Length: 100000000000\r\n\r\n{".encode()
        )
        head = s.recv(65536).decode("latin-1")
    assert head.startswith("HTTP/1.1 413"), head[:200]
    assert '"error"' in head


def test_a_huge_chunked_body_is_413(open_server: GcsServer) -> None:
    import http.client

    conn = http.client.HTTPConnection("127.0.0.1", open_server.port, timeout=30)
    try:
        chunks = (b"[" + b"1," * 8000 for _ in range(10))  # 160 KB, no Content-Length
        conn.request("POST", "/api/command", body=chunks, headers=JSON, encode_chunked=True)
        r = conn.getresponse()
        assert r.status == 413 and b"too large" in r.read()
    finally:
        conn.close()
    assert request(open_server.port, "GET", "/api/config").status == 200


def test_parse_command_takes_any_json_value() -> None:
    """The pure check alone: anything JSON can hold is a CommandRefused or a spec."""
    deep: Any = 1
    for _ in range(2000):
        deep = [deep]
    for body in [
        {"target": 1, "kind": "takeoff", "alt": 10**400},
        {"target": 1, "kind": "takeoff", "alt": -(10**400)},
        {"target": 10**400, "kind": "arm"},
        {"target": deep, "kind": "arm"},
        {"target": 1, "kind": deep},
        {"target": 1, "kind": "goto", "lat": float("nan"), "lon": 0, "alt": 0},
        {"target": "swarm", "kind": "follow", "heading": float("inf")},
        {"target": 1, "kind": "x" * 100000},
    ]:
        with pytest.raises(CommandRefused) as ei:
            parse_command(body)
        assert ei.value.status == 400 and len(ei.value.reason) < 300 and "\n" not in ei.value.reason


def test_replay_controls_take_extreme_values(tmp_path: Any, manual_clock: ManualClock) -> None:
    from test_gcs_api import write_capture

    from swarm.runtime.station.replay import ReplayStation, load_capture

    path = tmp_path / "flight.tlog"
    write_capture(path)
    rp = ReplayStation(load_capture(str(path)), clock=manual_clock, playing=False)
    server = GcsServer(rp, ServerConfig(port=0, tiles=None)).start()
    try:
        for body in (
            f'{{"action": "seek", "value": {HUGE}}}',
            f'{{"action": "speed", "value": -{HUGE}}}',
            '{"action": "seek", "value": NaN}',
            '{"action": "speed", "value": 1e999}',
            '{"action": ' + "[" * 3000 + "]" * 3000 + "}",
            '{"action": "' + "p" * 30000 + '"}',
            '{"action": {"play": 1}}',
            '{"action": "seek", "value": [1]}',
        ):
            a = request(server.port, "POST", "/api/replay", body.encode(), JSON)
            assert a.status == 400, (body[:60], a.status, a.body[:200])
            a.error()
        seek = b'{"action": "seek", "value": 2}'
        for ctype in ("text/plain", "application/x-www-form-urlencoded"):
            a = request(server.port, "POST", "/api/replay", seek, {"Content-Type": ctype})
            assert a.status == 415 and "application/json" in a.error()
        a = request(server.port, "POST", "/api/replay", seek, {**JSON, "Origin": "http://attacker.test"})
        assert a.status == 403
        a = request(server.port, "POST", "/api/replay", seek, JSON)
        assert a.status == 200 and a.json["position_s"] == 2.0
    finally:
        server.stop()


# -- the WebSocket after bad messages ------------------------------------------------------

WS_BAD = [
    (f'{{"type": "command", "id": "h", "target": 1, "kind": "takeoff", "alt": {HUGE}}}', "h", 400),
    ('{"type": "command", "id": "n", "target": 1, "kind": "takeoff", "alt": NaN}', None, 400),
    ('{"type": "command", "id": "i", "target": 1, "kind": "takeoff", "alt": 1e999}', None, 400),
    (DEEP, None, 400),
    ('{"type": "command", "id": "d", "target": ' + DEEP + "}", None, 400),
    ('{"type": "command", "id": ' + "[" * 50 + "]" * 50 + ', "target": 1, "kind": "arm"}', None, 400),
    ('{"type": "command", "id": {"a": 1}, "target": 1, "kind": "arm"}', None, 400),
    (f'{{"type": "command", "id": {HUGE}, "target": 1, "kind": "arm"}}', None, 400),
    ('{"type": "command", "id": "t", "target": [1], "kind": "arm"}', "t", 400),
    ('{"type": ["command"], "id": 3}', 3, 400),
    ('{"type": "command", "id": "' + "q" * 1000 + '", "target": 1, "kind": "arm"}', None, 400),
    ('{"type": "replay", "id": 7, "action": "seek", "value": ' + HUGE + "}", 7, 409),
    ('{"type": "replay", "id": 8, "action": "seek", "value": 5}', 8, 409),
    ("{" + " " * 70000 + "}", None, 413),
]


def test_the_websocket_stays_open_after_extreme_messages(swarm: Swarm, open_server: GcsServer) -> None:
    async def session() -> list[dict[str, Any]]:
        answers: list[dict[str, Any]] = []
        async with aiohttp.ClientSession() as s, s.ws_connect(open_server.url + "ws") as ws:
            for k, (text, _, _) in enumerate(WS_BAD):
                await ws.send_str(text)
                await ws.send_str(json.dumps({"type": "ping-probe", "id": f"probe{k}"}))
                got: dict[str, Any] | None = None
                probed = False
                while not (probed and got):  # a command's answer may come after the probe's
                    m = await ws.receive(timeout=20)
                    assert m.type == aiohttp.WSMsgType.TEXT, (k, text[:60], m)
                    obj = json.loads(m.data)
                    if obj.get("type") in ("state", "delta", "event", "replay"):
                        continue
                    if obj.get("id") == f"probe{k}":
                        probed = True
                        continue
                    assert got is None, (k, got, obj)
                    got = obj
                assert got is not None, (k, text[:60], "no answer")
                answers.append(got)
            await ws.send_str(json.dumps({"type": "state"}))
            while (await ws.receive_json(timeout=20))["type"] != "state":
                pass
            assert not ws.closed
        return answers

    before = swarm.settled_commands()
    answers = asyncio.run(session())
    for (text, mid, status), got in zip(WS_BAD, answers, strict=True):
        assert got["type"] in ("error", "command_result"), got
        assert got["status"] == status, (text[:60], got)
        reason = got.get("reason") or got.get("error")
        assert isinstance(reason, str) and "\n" not in reason and len(reason) < 400, got
        if mid is not None:
            assert got.get("id") == mid, (text[:60], got)
        else:
            assert got.get("id") in (None, "h", "n", "i", "d"), got
    unchanged(swarm, before)


# -- slow clients ---------------------------------------------------------------------


@pytest.mark.processes
def test_slow_clients_do_not_hold_the_station(swarm: Swarm) -> None:
    cfg = ServerConfig(port=0, tiles=None, body_timeout=2.0, idle_timeout=2.0)
    server = GcsServer(swarm.station, cfg).start()
    try:
        slow_clients(server.port)
    finally:
        server.stop()


def slow_clients(port: int) -> None:
    # a client that never finishes its headers, and one that never finishes its body
    stalled = socket.create_connection(("127.0.0.1", port), timeout=30)
    stalled.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
    slow_body = socket.create_connection(("127.0.0.1", port), timeout=30)
    slow_body.sendall(
        f"POST /api/command HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
        'Content-Type: application/json\r\nContent-Length: 50\r\n\r\n{"tar'.encode()
    )
    try:
        # others are served meanwhile
        for _ in range(5):
            assert request(port, "GET", "/api/config", timeout=10).status == 200
        # the slow body gets a 408 with a reason; the stalled headers are closed
        head = slow_body.recv(65536).decode("latin-1")
        assert head.startswith("HTTP/1.1 408") and '"error"' in head, head[:300]
        assert stalled.recv(65536) == b""
    finally:
        stalled.close()
        slow_body.close()
    assert request(port, "GET", "/api/config").status == 200


# -- property tests: arbitrary JSON never breaks it ---------------------------------------

JSON_LEAF = (
    st.none()
    | st.booleans()
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.integers()
    | st.integers(min_value=10**300, max_value=10**330)
    | st.text(max_size=40)
)
JSON_VALUE = st.recursive(
    JSON_LEAF,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)
KIND = st.sampled_from(sorted(KINDS)) | st.text(max_size=8)
COMMANDISH = st.fixed_dictionaries(
    {"kind": KIND, "target": st.sampled_from(["swarm", 1, 2, 99]) | JSON_VALUE},
    optional={
        "alt": JSON_VALUE | st.floats(),
        "lat": JSON_VALUE | st.floats(),
        "lon": JSON_VALUE,
        "heading": JSON_VALUE | st.floats(),
        "extra": JSON_VALUE,
    },
)
#: the answers the README documents for POST /api/command (504: no agent answered)
DOCUMENTED = {200, 400, 404, 409, 413, 415, 504}


@pytest.fixture(scope="module")
def quiet_server() -> Iterator[GcsServer]:
    """A station with no agents: any command is refused or finds nobody, quickly."""
    with live_swarm(0) as s:
        server = GcsServer(s.station, ServerConfig(port=free_port(), tiles=None)).start()
        try:
            yield server
        finally:
            server.stop()


PROPS = settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@PROPS
@given(body=JSON_VALUE | COMMANDISH)
def test_property_http_any_json(quiet_server: GcsServer, body: Any) -> None:
    raw = json.dumps(body).encode()
    for path in ("/api/command", "/api/replay"):
        a = request(quiet_server.port, "POST", path, raw, JSON)
        assert a.status in DOCUMENTED, (a.status, a.body[:300])
        if a.status >= 400:
            a.error()


@PROPS
@given(raw=st.binary(max_size=200) | st.text(max_size=200).map(lambda t: t.encode("utf-8", "surrogatepass")))
def test_property_http_any_bytes(quiet_server: GcsServer, raw: bytes) -> None:
    a = request(quiet_server.port, "POST", "/api/command", raw, JSON)
    assert a.status in DOCUMENTED and a.status != 200, (a.status, a.body[:300])
    a.error()


@PROPS
@given(
    messages=st.lists(
        st.one_of(
            JSON_VALUE,
            COMMANDISH.map(lambda d: {"type": "command", "id": "x", **d}),
            st.dictionaries(st.sampled_from(["type", "id", "action", "value"]), JSON_VALUE),
        ),
        min_size=1,
        max_size=4,
    )
)
def test_property_websocket_any_json(quiet_server: GcsServer, messages: list[Any]) -> None:
    async def session() -> None:
        async with aiohttp.ClientSession() as s, s.ws_connect(quiet_server.url + "ws") as ws:
            for m in messages:
                await ws.send_str(json.dumps(m))
            await ws.send_str(json.dumps({"type": "probe", "id": "end"}))
            while True:
                msg = await ws.receive(timeout=20)
                assert msg.type == aiohttp.WSMsgType.TEXT, msg
                obj = json.loads(msg.data)
                if obj.get("type") == "error" or obj.get("type") == "command_result":
                    assert obj["status"] in DOCUMENTED, obj
                if obj.get("id") == "end":
                    break
            assert not ws.closed

    asyncio.run(session())


def test_the_server_answers_after_the_property_runs(quiet_server: GcsServer) -> None:
    wait_until(lambda: request(quiet_server.port, "GET", "/api/config").status == 200, "an answer", 10)


# -- the command line ---------------------------------------------------------------------


def test_swarm_gcs_beyond_loopback_prints_a_generated_token_once(tmp_path: Any) -> None:
    from swarm.cli.procs import Child

    gcs = Child(
        [
            "gcs",
            "--zenoh-listen",
            f"tcp/127.0.0.1:{free_port()}",
            "--http",
            "0.0.0.0:0",
            "--tiles",
            "none",
            "--allow-host",
            "GCS.Field",
            "--json",
        ],
        name="gcs",
    )
    try:
        ready = json.loads(gcs.wait_lines(1, 30)[0])
        assert ready["event"] == "ready" and ready["token"] == "generated", ready
        port = int(ready["listen"].rsplit(":", 1)[1])
        assert ready["url"] == f"http://127.0.0.1:{port}/"
        assert ready["open"].startswith(f"http://127.0.0.1:{port}/?token=")
        token = ready["open"].split("?token=", 1)[1]
        assert len(token) >= 40
        assert request(port, "GET", "/api/state").status == 401
        assert request(port, "GET", "/api/state", headers={"Authorization": f"Bearer {token}"}).status == 200
        assert (
            request(
                port,
                "GET",
                "/api/config",
                headers={"Authorization": f"Bearer {token}", "Host": f"gcs.field:{port}"},
            ).status
            == 200
        )
        a = request(port, "GET", f"/?token={token}")
        assert a.status == 200 and "Set-Cookie" not in a.headers
    finally:
        gcs.stop()
    assert sum(token in line for line in gcs.lines + gcs.errors) == 1, "the token printed once"


def test_swarm_gcs_with_a_token_file_does_not_print_it(tmp_path: Any) -> None:
    from swarm.cli.procs import Child

    path = tmp_path / "gcs.token"
    path.write_text(TOKEN + "\n")
    path.chmod(0o600)
    gcs = Child(
        [
            "gcs",
            "--zenoh-listen",
            f"tcp/127.0.0.1:{free_port()}",
            "--http",
            "127.0.0.1:0",
            "--tiles",
            "none",
            "--token-file",
            str(path),
        ],
        name="gcs",
    )
    try:
        line = gcs.wait_lines(1, 30)[0]
        assert "(token required)" in line and TOKEN not in line, line
        port = int(line.split("http://127.0.0.1:", 1)[1].split("/", 1)[0])
        assert request(port, "GET", "/api/state").status == 401
        assert request(port, "GET", "/api/state", headers={"Authorization": f"Bearer {TOKEN}"}).status == 200
    finally:
        gcs.stop()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--token", "short"], "--token: 16 to 256 characters"),
        (["--token", "has spaces but is long enough"], "--token: 16 to 256 characters"),
        (["--token-file", "/nonexistent/gcs.token"], "--token-file /nonexistent/gcs.token: No such file"),
        # an endless device or a folder is not a token file (it was read for ever)
        (["--token-file", "/dev/zero"], "--token-file /dev/zero: not a regular file"),
        (["--token-file", "/"], "--token-file /: not a regular file"),
        (["--allow-host", "bad name!"], "--allow-host: host 'bad name!'"),
        (["--allow-host", "evil.test/x"], "--allow-host: host 'evil.test/x'"),
    ],
)
def test_swarm_gcs_refuses_bad_security_flags(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from swarm.cli.commands.gcs import main as gcs_main

    assert gcs_main(["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
