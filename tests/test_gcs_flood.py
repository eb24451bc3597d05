"""The station's HTTP port under attack, with a real ``swarm gcs`` process.

* 2,000 idle connections, held by another process that opens a new one for each the
  station closes, against a station whose open-file limit is 1024 and cannot be
  raised: the operator's requests (the state, and commands a real Zenoh agent
  receives), each on a new connection, are all answered, and the station writes
  nothing about it but, at most, a few lines.
* Malformed requests over raw sockets (garbage request lines, a TLS hello, a bad
  HTTP version, huge headers, a header line without a colon, bad chunking before and
  after the handler started, a body cut off): each one line in the log, never a
  traceback, at most a burst of lines then one "N more" line per interval; the
  station answers well-formed requests throughout.
"""

from __future__ import annotations

import json
import re
import socket
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import pytest
from gcs_security_helpers import request
from net_helpers import wait_until
from test_gcs_api import ScriptedAgent

from swarm.cli.bench.gcs_flood import CONNECTIONS, Flood, limited_station, operator_request
from swarm.core.wire.message_types import CommandKind, Phase

# timing: requests per second and answers within 10 s under a flood
pytestmark = [pytest.mark.processes, pytest.mark.timing]

DEADLINE = 60.0
#: an operator's request during the flood is answered within this, or it failed (three SYN
#: retries of a connection the kernel dropped fit in it)
OPERATOR_TIMEOUT = 10.0


def _connected(port: int) -> bool:
    a = request(port, "GET", "/api/state", timeout=10)
    return a.status == 200 and any(x["id"] == 1 and x["connected"] for x in a.json["agents"])


def test_2000_idle_connections_do_not_shut_the_operator_out() -> None:
    with limited_station(1024) as (station, port, ep):
        agent = ScriptedAgent(ep, 1, phase=Phase.LEADER, leader=1)
        try:
            wait_until(lambda: _connected(port), "agent 1 connected", DEADLINE, 0.2)
            with Flood(port, CONNECTIONS) as flood:
                flood.wait_full(station.pid, 1024, 120)
                answers = []
                for _ in range(5):
                    answers.append(operator_request(port, "GET", "/api/state", timeout=OPERATOR_TIMEOUT)[0])
                    body = json.dumps({"target": 1, "kind": "arm"}).encode()
                    st, _t = operator_request(
                        port,
                        "POST",
                        "/api/command",
                        body,
                        {"Content-Type": "application/json"},
                        timeout=OPERATOR_TIMEOUT,
                    )
                    answers.append(st)
                status = flood.stop()
            assert answers == [200] * 10, (
                f"the operator's answers during the flood: {answers}, attacker {status}"
            )
            # each answered command was the agent's answer: it received them
            assert sum(1 for c in agent.commands if c.kind == CommandKind.ARM) >= 5
            # the attacker really pressed: its connections were taken and closed to make room
            assert status["opened"] >= CONNECTIONS and status["closed"] > 0, status
            assert station.proc.poll() is None
            wait_until(lambda: request(port, "GET", "/api/config", timeout=10).status == 200, "an answer", 30)
        finally:
            agent.close()
    log = station.errors + station.lines[1:]
    assert not any("Traceback" in line for line in log), "\n".join(log[:40])
    assert len([x for x in log if "http" in x.lower() or "connection" in x.lower()]) <= 20, "\n".join(
        log[:40]
    )


# -- malformed requests -----------------------------------------------------------------

HEAD = b"POST /api/command HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
CHUNKED = HEAD + b"Transfer-Encoding: chunked\r\n\r\n"
#: (what, bytes sent at once, bytes sent after a pause or None, close our side after)
GARBAGE = [
    ("garbage request line", b"GARBAGE\r\n\r\n", None, False),
    ("tls hello", b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03" + bytes(range(40)), None, False),
    ("bad version", b"GET / HTTP/9.9\r\nHost: 127.0.0.1\r\n\r\n", None, False),
    ("huge header", b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-A: " + b"a" * 20000 + b"\r\n\r\n", None, False),
    ("many headers", b"GET / HTTP/1.1\r\n" + b"X-A: b\r\n" * 300 + b"\r\n", None, False),
    ("huge request line", b"GET /" + b"a" * 20000 + b" HTTP/1.1\r\n\r\n", None, False),
    ("header without colon", b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nbad header line\r\n\r\n", None, False),
    ("bad chunk size", CHUNKED + b"zz\r\nhello\r\n0\r\n\r\n", None, False),
    ("bad chunk later", CHUNKED, b"zz\r\nhello\r\n", False),
    ("chunk extension too long", CHUNKED, b"3;" + b"x" * 9000 + b"\r\nabc\r\n", False),
    ("huge chunk size", CHUNKED, b"ffffffffffffffffffff\r\n", False),
    ("cut-off body", CHUNKED, b"5\r\nhel", True),
    ("cut-off length", HEAD + b"Content-Length: 100\r\n\r\n{", None, True),
    ("nul in the path", b"GET /\x00 HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", None, False),
]


def _send(port: int, first: bytes, later: bytes | None, close: bool) -> bytes:
    """Send one malformed request; what the station answered (b"" when it only closed)."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall(first)
        if later is not None:
            time.sleep(0.2)  # the handler has started reading the body
            s.sendall(later)
        if close:
            s.shutdown(socket.SHUT_WR)
        got = b""
        s.settimeout(30)
        try:
            while True:
                chunk = s.recv(65536)
                if not chunk:
                    break
                got += chunk
                if b"\r\n\r\n" in got and (close or later is not None or b"400" in got[:20]):
                    break
        except (TimeoutError, ConnectionResetError):
            pass
        return got


@pytest.fixture(scope="module")
def garbage_station() -> Iterator[tuple[object, int]]:
    with limited_station(1024) as (station, port, _ep):
        yield station, port


def test_each_malformed_request_is_one_line_without_a_traceback(garbage_station: tuple[object, int]) -> None:
    station, port = garbage_station
    with ThreadPoolExecutor(len(GARBAGE)) as pool:  # at once: three of them wait out the body timeout
        answers = list(pool.map(lambda g: _send(port, *g[1:]), GARBAGE))
    for (what, *_rest), got in zip(GARBAGE, answers, strict=True):
        assert b"500" not in got[:20], (what, got[:200])
    assert request(port, "GET", "/api/config").status == 200
    # the first lines one by one, the rest of the interval in its "N more" line
    wait_until(lambda: _counted(station.errors) >= len(GARBAGE), "a line per malformed request", 30, 0.2)  # type: ignore[attr-defined]
    log = list(station.errors)  # type: ignore[attr-defined]
    assert _counted(log) == len(GARBAGE), "\n".join(log)
    assert all(x.startswith("http: ") and len(x) < 300 for x in log), "\n".join(log)


def _counted(lines: list[str]) -> int:
    """Malformed requests the log lines tell of: one each, or N in a summary."""
    one = sum(1 for x in lines if x.startswith("http: malformed request from "))
    more = sum(int(m.group(1)) for x in lines if (m := re.match(r"http: (\d+) more malformed", x)))
    return one + more


def test_a_flood_of_malformed_requests_is_rate_limited(garbage_station: tuple[object, int]) -> None:
    station, port = garbage_station
    before = len(station.errors)  # type: ignore[attr-defined]
    sent = 0
    t0 = time.monotonic()
    while time.monotonic() - t0 < 4.0:
        for _what, first, later, close in GARBAGE[:8]:  # the ones answered at once
            _send(port, first, later, close)
            sent += 1
    assert request(port, "GET", "/api/config").status == 200
    # the interval's summary: "N more malformed requests ..."
    wait_until(
        lambda: any("more malformed" in x for x in station.errors[before:]),  # type: ignore[attr-defined]
        "the suppressed count",
        30,
        0.2,
    )
    new = station.errors[before:]  # type: ignore[attr-defined]
    assert sent > 200, sent
    assert len(new) <= 30, f"{len(new)} lines for {sent} malformed requests:\n" + "\n".join(new[:40])
    assert not any("Traceback" in line for line in new)
