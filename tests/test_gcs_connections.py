"""The station's connection cap and its malformed-request lines
(:mod:`swarm.runtime.station.connections`).

The choice of which connection makes room, and the line gate, are logic: checked
here without sockets (a transport is what ``loop.create_server`` hands a protocol:
the test's stands in with its peer address and records being reset). Then a real
server in this process with a small cap: idle connections of an attacker fill it,
the operator's WebSocket and new requests are served, a connection that never
finishes its headers is closed after the idle timeout, and the soft file limit is
raised at start.
"""

from __future__ import annotations

import asyncio
import json
import resource
import socket
import time
from collections.abc import Iterator
from typing import Any

import aiohttp
import pytest
from gcs_security_helpers import live_swarm, request
from net_helpers import free_port, wait_until

from swarm.runtime.station.connections import (
    MAX_CONNECTIONS,
    ConnectionLimiter,
    LineGate,
    default_limit,
    peer_key,
    raise_file_limit,
    reason_of,
)
from swarm.runtime.station.server import GcsServer, ServerConfig


class Peer:
    """A connection's transport as the limiter sees it: its peer, and whether it was reset."""

    def __init__(self, host: str, port: int = 40000) -> None:
        self.peer = (host, port)
        self.aborted = False

    def get_extra_info(self, name: str) -> Any:
        return self.peer if name == "peername" else None

    def abort(self) -> None:
        self.aborted = True


def _open(lim: ConnectionLimiter, host: str) -> Peer:
    t = Peer(host)
    lim.admit(t)  # type: ignore[arg-type]
    return t


def test_a_full_limiter_closes_the_busiest_peers_oldest_unproven_connection() -> None:
    stats: dict[str, int] = {}
    lim = ConnectionLimiter(6, stats)
    operator = _open(lim, "10.0.0.2")
    with lim.serving(operator):  # type: ignore[arg-type]
        pass  # one request passed the guard: proven, idle again
    ws = _open(lim, "10.0.0.2")
    attacker = [_open(lim, "10.0.0.9") for _ in range(4)]
    assert len(lim) == 6 and stats["http_connections"] == 6
    with lim.serving(ws):  # type: ignore[arg-type]  # the operator's WebSocket: in progress all along
        # the operator's new connection: the attacker's oldest makes room
        new = _open(lim, "10.0.0.2")
        assert attacker[0].aborted and not new.aborted and stats["http_evicted"] == 1
        # the attacker's next ones evict its own older ones, never the operator's
        more = [_open(lim, "10.0.0.9") for _ in range(10)]
        assert not any(t.aborted for t in (operator, ws, new))
        assert sum(t.aborted for t in attacker + more) == 11 and len(lim) == 6
        for t in [new, *attacker, *more]:  # closed (those reset: already gone)
            lim.release(t)  # type: ignore[arg-type]
        assert len(lim) == 2  # the operator's idle proven one and its WebSocket
        # another peer's new connections: its own oldest go before the operator's
        others = [_open(lim, "10.0.0.3") for _ in range(5)]
        assert others[0].aborted and not operator.aborted and not ws.aborted
        for t in others:
            lim.release(t)  # type: ignore[arg-type]
    assert stats["http_full"] == 0


def test_when_every_connection_is_busy_the_new_one_is_closed() -> None:
    stats: dict[str, int] = {}
    lim = ConnectionLimiter(2, stats)
    a, b = _open(lim, "10.0.0.2"), _open(lim, "10.0.0.3")
    with lim.serving(a), lim.serving(b):  # type: ignore[arg-type]
        c = _open(lim, "10.0.0.4")
        assert c.aborted and not a.aborted and not b.aborted and stats["http_full"] == 1
    d = _open(lim, "10.0.0.4")  # idle again: one of them makes room (b, used before a)
    assert b.aborted and not a.aborted and not d.aborted
    with pytest.raises(ValueError):
        ConnectionLimiter(0, {})


def test_peers_and_reasons() -> None:
    assert peer_key(("192.0.2.7", 5000)) == "192.0.2.7"
    assert peer_key(("2001:db8::1", 5000, 0, 0)) == peer_key(("2001:db8::ffff:1", 1, 0, 0)) == "2001:db8::/64"
    assert peer_key(("::ffff:192.0.2.7", 5000, 0, 0)) == "192.0.2.7"
    assert peer_key(("fe80::1%eth0", 5000, 0, 2)) == "fe80::/64"
    assert peer_key(None) == peer_key("junk") == "?"
    assert reason_of(ValueError("a\n  b\x00c " + "x" * 500)).startswith("a b?c x")
    assert len(reason_of(ValueError("x" * 500))) == 120
    assert reason_of(ValueError("")) == "ValueError"


def test_the_line_gate() -> None:
    g = LineGate(burst=3, interval=10.0)
    assert [g.note(t) for t in (0.0, 1.0, 2.0, 3.0, 4.0)] == [True, True, True, False, False]
    assert g.end == 10.0 and g.summary() == 2 and g.summary() == 0
    assert g.note(9.9) is False and g.note(10.0) is True  # a new interval from its first line
    assert g.end == 20.0 and g.summary() == 1


def test_the_file_limit_is_raised_and_the_cap_follows_it() -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(256, hard), hard))
        assert default_limit() == min(256, hard) // 2
        before, after = raise_file_limit(ceiling=min(4096, hard))
        assert before == min(256, hard) and after == min(4096, hard)
        assert resource.getrlimit(resource.RLIMIT_NOFILE) == (after, hard)
        assert default_limit() == min(MAX_CONNECTIONS, after // 2)
        assert raise_file_limit(ceiling=16) == (after, after)  # never lowered
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


# -- a real server --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_server() -> Iterator[GcsServer]:
    with live_swarm(1) as s:
        cfg = ServerConfig(port=free_port(), tiles=None, max_connections=16, idle_timeout=2.0)
        server = GcsServer(s.station, cfg).start()
        try:
            yield server
        finally:
            server.stop()


@pytest.mark.processes
def test_idle_connections_make_room_for_the_operator(small_server: GcsServer) -> None:
    port = small_server.port

    async def scenario() -> dict[str, Any]:
        out: dict[str, Any] = {}
        async with aiohttp.ClientSession() as s, s.ws_connect(small_server.url + "ws") as ws:
            first = await ws.receive_json(timeout=10)
            out["ws_first"] = first["type"]
            attacker = []
            for _ in range(60):  # far more than the cap, all idle
                sock = socket.create_connection(("127.0.0.1", port))
                attacker.append(sock)
            await asyncio.sleep(0.5)
            loop = asyncio.get_running_loop()
            answers = [
                (
                    await loop.run_in_executor(None, lambda: request(port, "GET", "/api/state", timeout=10))
                ).status
                for _ in range(5)
            ]
            out["answers"] = answers
            # the WebSocket lived through it: a command over it is answered
            await ws.send_str(json.dumps({"type": "command", "id": 7, "target": 1, "kind": "arm"}))
            while True:
                msg = await ws.receive_json(timeout=20)
                if msg.get("type") == "command_result":
                    out["ws_command"] = msg["status"]
                    break
            closed = 0
            for sock in attacker:
                sock.setblocking(False)
                try:
                    closed += sock.recv(1) == b""
                except BlockingIOError:
                    pass
                except ConnectionResetError:
                    closed += 1
                sock.close()
            out["attacker_closed"] = closed
        return out

    out = asyncio.run(scenario())
    assert out["ws_first"] == "state" and out["answers"] == [200] * 5 and out["ws_command"] == 200, out
    assert out["attacker_closed"] >= 60 - 16, out
    assert small_server.stats["http_evicted"] >= 60 - 16 and small_server.stats["http_full"] == 0
    assert small_server.stats["http_connections"] <= 16


@pytest.mark.processes
def test_a_connection_that_never_finishes_its_headers_is_closed(small_server: GcsServer) -> None:
    with socket.create_connection(("127.0.0.1", small_server.port), timeout=30) as s:
        t0 = time.monotonic()
        s.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        got = b""
        while True:  # one header byte a second, never the blank line
            s.settimeout(1.0)
            try:
                chunk = s.recv(100)
            except TimeoutError:
                s.sendall(b"X")
                assert time.monotonic() - t0 < 30, "still open after 30 s"
                continue
            except ConnectionResetError:
                chunk = b""
            got += chunk
            if not chunk:
                break
    assert b"200" not in got
    wait_until(lambda: request(small_server.port, "GET", "/api/config").status == 200, "an answer", 10)


def test_the_pages_public_files_prove_nothing() -> None:
    """On a station with a token, fetching the page (no token needed) does not move a
    connection out of the first ones to close."""
    lim = ConnectionLimiter(3, {})
    operator = _open(lim, "10.0.0.2")
    with lim.serving(operator, proven=True):  # type: ignore[arg-type]
        pass
    page_only = _open(lim, "10.0.0.2")
    with lim.serving(page_only, proven=False):  # type: ignore[arg-type]
        pass
    _open(lim, "10.0.0.2")
    _open(lim, "10.0.0.2")  # full: the oldest that proved nothing goes, not the operator's
    assert page_only.aborted and not operator.aborted
