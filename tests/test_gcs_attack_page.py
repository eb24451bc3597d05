"""Web pages against the ground station, in real headless Chromium: pages from a
second origin (another port, another host name) and a DNS-rebound name try every
way a browser lets a page reach a local server (a JSON fetch, a no-cors text/plain
fetch, a form post, a WebSocket); none may make a command reach the station or read
its state. Then the token flow as an operator lives it: the station bound to every
address, the URL token once, kept in the page's own origin's storage (never a cookie:
another web service on the same host must never receive it), the page working.

The host names resolve to 127.0.0.1 in this browser only (``--host-resolver-rules``);
every wait polls for an outcome until a generous deadline.
"""

from __future__ import annotations

import http.server
import re
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_browser import write_tiles
from gcs_security_helpers import Swarm, live_swarm
from net_helpers import free_port, wait_until

from swarm.cli.bench.gcs_page import BROWSER_ARGS, find_browser
from swarm.runtime.station.server import GcsServer, ServerConfig

pytestmark = pytest.mark.processes  # a browser against a running station

TOKEN = "page-test-token-0123456789abcdef"
DEADLINE = 30.0
RESOLVE = "MAP attacker.test 127.0.0.1, MAP rebind.test 127.0.0.1, MAP gcs.field 127.0.0.1"

ATTACK_PAGE = """<!doctype html><html><body><h1>cat pictures</h1>
<iframe name="sink" id="sink"></iframe>
<script>
const station = new URLSearchParams(location.search).get("station");
const body = JSON.stringify({target: "swarm", kind: "takeoff", alt: 10});
window.outcome = {};
const done = [];
done.push(fetch(station + "api/command", {method: "POST", headers: {"Content-Type": "application/json"},
                                          body, credentials: "include"})
  .then(r => r.text().then(t => { outcome.json = r.status + " " + t; }), e => { outcome.json = "failed"; }));
done.push(fetch(station + "api/command", {method: "POST", mode: "no-cors", credentials: "include",
                                          headers: {"Content-Type": "text/plain"}, body})
  .then(r => { outcome.nocors = "answered"; }, e => { outcome.nocors = "failed"; }));
done.push(fetch(station + "api/state", {credentials: "include"})
  .then(r => r.text().then(t => { outcome.state = t; }), e => { outcome.state = "failed"; }));
done.push(new Promise(resolve => {
  const f = document.createElement("form");
  f.method = "POST"; f.action = station + "api/command"; f.enctype = "text/plain"; f.target = "sink";
  const i = document.createElement("input");
  i.name = '{"target": "swarm", "kind": "takeoff", "alt": 10, "pad": "'; i.value = '"}';
  f.appendChild(i); document.body.appendChild(f);
  document.getElementById("sink").onload = () => { outcome.form = "answered"; resolve(); };
  f.submit();
}));
done.push(new Promise(resolve => {
  outcome.ws = [];
  const ws = new WebSocket(station.replace(/^http/, "ws") + "ws");
  ws.onopen = () => {
    outcome.ws.push("open");
    ws.send(JSON.stringify({type: "command", id: 1, target: "swarm", kind: "follow", heading: 90}));
  };
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    outcome.ws.push(m.type);
    if (m.type === "command_result" || m.type === "error") { ws.close(); }
  };
  ws.onclose = () => { outcome.ws.push("closed"); resolve(); };
}));
Promise.all(done).then(() => { window.attackDone = true; });
</script></body></html>"""


class AttackerHandler(http.server.BaseHTTPRequestHandler):
    def do_GET(self) -> None:
        data = ATTACK_PAGE.encode()
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, format: str, *args: Any) -> None:
        pass


@pytest.fixture(scope="module")
def attacker() -> Iterator[int]:
    """A plain web server on another port: the second origin."""
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), AttackerHandler)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    try:
        yield int(srv.server_address[1])
    finally:
        srv.shutdown()
        srv.server_close()


class RecordingHandler(http.server.BaseHTTPRequestHandler):
    """Another web service on the same host: answers every GET and keeps its headers."""

    seen: list[str] = []

    def do_GET(self) -> None:
        RecordingHandler.seen.append(f"{self.requestline}\n{self.headers}")
        data = b"<!doctype html><title>another service</title><p>hello"
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, format: str, *args: Any) -> None:
        pass


@pytest.fixture
def other_service() -> Iterator[tuple[int, list[str]]]:
    """A plain web server on another port of 127.0.0.1, and the requests it received."""
    RecordingHandler.seen = []
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), RecordingHandler)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    try:
        yield int(srv.server_address[1]), RecordingHandler.seen
    finally:
        srv.shutdown()
        srv.server_close()


@pytest.fixture(scope="module")
def swarm() -> Iterator[Swarm]:
    with live_swarm(2) as s:
        yield s


@pytest.fixture(scope="module")
def chromium() -> Iterator[Any]:
    path = find_browser()
    if path is None:
        pytest.fail("no chromium: `make setup` installs Debian's chromium (or set CHROMIUM)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(
            executable_path=path, headless=True, args=[*BROWSER_ARGS, f"--host-resolver-rules={RESOLVE}"]
        )
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def ctx(chromium: Any) -> Iterator[Any]:
    c = chromium.new_context(viewport={"width": 1200, "height": 800})
    try:
        yield c
    finally:
        c.close()


def attack(ctx: Any, attacker_origin: str, station: str) -> dict[str, Any]:
    page = ctx.new_page()
    page.goto(f"{attacker_origin}/?station={station}")
    page.wait_for_function("() => window.attackDone === true", timeout=DEADLINE * 1000)
    out = dict(page.evaluate("window.outcome"))
    page.close()
    return out


def assert_nothing_reached(swarm: Swarm, before: int, out: dict[str, Any]) -> None:
    assert swarm.commands() == before, f"a command reached the swarm: {out}"
    assert '"agents"' not in str(out.get("state")), out  # no state read
    assert "state" not in out["ws"] and "command_result" not in out["ws"], out


@pytest.mark.parametrize("attacker_host", ["attacker.test", "127.0.0.1"])
def test_another_origin_cannot_command_a_loopback_station(
    swarm: Swarm, attacker: int, ctx: Any, attacker_host: str
) -> None:
    server = GcsServer(swarm.station, ServerConfig(port=free_port(), tiles=None)).start()
    try:
        before = swarm.commands()
        out = attack(ctx, f"http://{attacker_host}:{attacker}", server.url)
        assert_nothing_reached(swarm, before, out)
    finally:
        server.stop()


def login(ctx: Any, base: str) -> Any:
    page = ctx.new_page()
    page.errors = []
    page.on("pageerror", lambda exc: page.errors.append(str(exc)))
    page.goto(f"{base}?token={TOKEN}")
    page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=DEADLINE * 1000)
    wait_until(
        lambda: page.evaluate("window.gcs.wsStatus === 'live' && window.gcs.stateCount > 0"),
        "the page live",
        DEADLINE,
        interval=0.2,
    )
    return page


def test_the_token_flow_in_the_browser_and_a_same_site_page_still_fails(
    swarm: Swarm, attacker: int, ctx: Any
) -> None:
    server = GcsServer(
        swarm.station, ServerConfig(host="0.0.0.0", port=free_port(), tiles=None, token=TOKEN)
    ).start()
    base = f"http://127.0.0.1:{server.port}/"
    try:
        # no token: the page (it holds nothing of the swarm) asks for it, the API refuses
        page = ctx.new_page()
        r = page.goto(base)
        assert r.status == 200
        page.locator('#token-needed input[name="token"]').wait_for(state="visible", timeout=DEADLINE * 1000)
        assert page.evaluate("fetch('/api/state').then(r => r.status)") == 401
        page.close()
        # the URL token once: the page works, the token leaves the address bar; it is
        # kept in the station's origin's storage, never in a cookie
        page = login(ctx, base)
        assert "token" not in page.url and page.url == base
        assert page.evaluate("localStorage.getItem('gcs_token')") == TOKEN
        assert ctx.cookies() == [] and page.evaluate("document.cookie") == ""
        assert page.locator("#token-needed").is_hidden()
        n = len(swarm.agents[2].commands)
        page.click('#agents [data-agent-id="2"]')
        page.select_option("#cmd-target", "selected")
        page.click('#commands [data-kind="arm"]')
        # the agent's yes ("accepted"), then what the station follows on the vehicle (in progress, done)
        answered = re.compile(r": (accepted$|in progress|done)")
        wait_until(lambda: answered.search(page.inner_text("#cmd-status")), "arm accepted", DEADLINE, 0.2)
        assert len(swarm.agents[2].commands) > n
        # POST from the page itself (as while the socket is down) works with the token;
        # nothing the browser adds on its own carries it
        st = page.evaluate("""gcsToken.fetch('/api/command', {method: 'POST',
                                headers: {'Content-Type': 'application/json'},
                                body: JSON.stringify({target: 2, kind: 'disarm'})}).then(r => r.status)""")
        assert st == 200
        st = page.evaluate("""fetch('/api/command', {method: 'POST', credentials: 'include',
                                headers: {'Content-Type': 'application/json'},
                                body: JSON.stringify({target: 2, kind: 'disarm'})}).then(r => r.status)""")
        assert st == 401
        # a reload without the token: the page's storage holds it
        page.goto(base)
        page.wait_for_function(
            "() => window.gcs && window.gcs.ready && window.gcs.stateCount > 0", timeout=DEADLINE * 1000
        )
        assert page.errors == []
        page.close()
        # a page of another port on the same host (same site): it has no token, and the
        # station refuses it
        before = swarm.commands()
        out = attack(ctx, f"http://127.0.0.1:{attacker}", base)
        assert_nothing_reached(swarm, before, out)
        out = attack(ctx, f"http://attacker.test:{attacker}", base)
        assert_nothing_reached(swarm, before, out)
    finally:
        server.stop()


def test_the_login_form_and_an_allowed_name(swarm: Swarm, ctx: Any) -> None:
    server = GcsServer(
        swarm.station,
        ServerConfig(host="0.0.0.0", port=free_port(), tiles=None, token=TOKEN, allow_hosts=("gcs.field",)),
    ).start()
    try:
        page = ctx.new_page()
        assert page.goto(f"http://gcs.field:{server.port}/").status == 200
        page.fill('#token-needed input[name="token"]', TOKEN)  # shown once the API refused
        page.click('#token-needed button[type="submit"]')
        page.wait_for_function(
            "() => window.gcs && window.gcs.ready && window.gcs.stateCount > 0", timeout=DEADLINE * 1000
        )
        assert "token" not in page.url
        page.close()
    finally:
        server.stop()


def test_a_dns_rebound_name_is_refused(swarm: Swarm, ctx: Any) -> None:
    server = GcsServer(swarm.station, ServerConfig(port=free_port(), tiles=None)).start()
    try:
        before = swarm.commands()
        page = ctx.new_page()
        r = page.goto(f"http://rebind.test:{server.port}/")
        assert r.status == 403 and "host" in page.inner_text("body")
        out = page.evaluate("""async () => {
          const body = JSON.stringify({target: "swarm", kind: "takeoff", alt: 10});
          const a = await fetch("/api/command",
                                {method: "POST", headers: {"Content-Type": "application/json"}, body});
          const b = await fetch("/api/state");
          const ws = await new Promise(resolve => {
            const s = new WebSocket("ws://" + location.host + "/ws");
            s.onmessage = (ev) => resolve("read: " + ev.data.slice(0, 40));
            s.onclose = () => resolve("closed");
          });
          return {command: a.status, state: b.status, ws};
        }""")
        assert out == {"command": 403, "state": 403, "ws": "closed"}, out
        assert swarm.commands() == before
        page.close()
    finally:
        server.stop()


def test_another_service_on_the_host_never_receives_the_token(
    swarm: Swarm, ctx: Any, other_service: tuple[int, list[str]]
) -> None:
    """Cookies are per host, not per port: a token kept in one reached every web
    service of the machine the browser visited. The page holds it in its own
    origin's storage and sends it only to the station."""
    port, seen = other_service
    server = GcsServer(
        swarm.station, ServerConfig(host="0.0.0.0", port=free_port(), tiles=None, token=TOKEN)
    ).start()
    base = f"http://127.0.0.1:{server.port}/"
    try:
        page = login(ctx, base)
        page.goto(base)  # a reload: still working, without the token in the address
        page.wait_for_function(
            "() => window.gcs && window.gcs.ready && window.gcs.stateCount > 0", timeout=DEADLINE * 1000
        )
        assert page.errors == []
        # the station's page may talk to its station only (its Content-Security-Policy):
        # a script on it could not even send what it holds elsewhere
        out = page.evaluate(
            f"""() => fetch('http://127.0.0.1:{port}/exfiltrated', {{mode: 'no-cors'}})
                      .then(() => 'sent', () => 'blocked')"""
        )
        assert out == "blocked" and seen == []
        # the operator visits the other service: its page, and what its page loads
        page.goto(f"http://127.0.0.1:{port}/visited")
        page.evaluate(
            """() => { fetch('/fetched', {credentials: 'include'});
                       const i = new Image(); i.src = '/image';
                       const f = document.createElement('iframe'); f.src = '/frame';
                       document.body.append(f); }"""
        )
        wait_until(lambda: len(seen) >= 4, "the other service's four requests", DEADLINE, 0.2)
        page.close()
    finally:
        server.stop()
    assert not any(TOKEN in r for r in seen), "\n\n".join(seen)
    assert all("gcs_token" not in r for r in seen), "\n\n".join(seen)


def test_the_stations_own_tiles_come_with_the_token(swarm: Swarm, ctx: Any, tmp_path: Path) -> None:
    """An <img> cannot send the token: the page fetches each of the station's tiles
    with it; without the token a tile is refused like the API."""
    lat, lon = 47.397742, 8.545594
    write_tiles(tmp_path, lat, lon, zooms=(17,), radius=2)
    server = GcsServer(
        swarm.station,
        ServerConfig(host="0.0.0.0", port=free_port(), tiles_dir=tmp_path, center=(lat, lon), token=TOKEN),
    ).start()
    base = f"http://127.0.0.1:{server.port}/"
    try:
        page = login(ctx, base)
        loaded = (
            "Array.from(document.querySelectorAll('img.leaflet-tile-loaded'))"
            ".filter(i => (i.dataset.tile || '').startsWith('/tiles/17/')).length"
        )
        seen = (  # what the map holds, should the tiles never come
            "(() => { const m = window.gcs.map;"
            " const imgs = Array.from(document.querySelectorAll('#map img')).slice(0, 6)"
            ".map(i => [i.dataset.tile || i.src.slice(0, 40), i.className]);"
            " return {zoom: m.getZoom(), size: m.getSize(), imgs}; })()"
        )
        wait_until(  # at zoom 18 too (the page zooms to the agents): the folder's 17 enlarged
            lambda: page.evaluate(loaded) > 0,
            "the station's tiles drawn",
            DEADLINE,
            0.2,
            detail=lambda: (page.evaluate(seen), page.errors, dict(server.stats)),
        )
        assert page.evaluate("fetch('/tiles/17/1/1.png').then(r => r.status)") == 401
        assert page.errors == []
        page.close()
    finally:
        server.stop()
