"""The ground station's HTTP + WebSocket server (aiohttp, on its own thread).

Theory of operation
-------------------
:class:`GcsServer` serves one *station view*: the live :class:`~swarm.runtime.station.Station`
or a :class:`~swarm.runtime.replay.ReplayStation`. Both give thread-safe snapshots
(``snapshot()``, ``agent(id)``), commands as futures (``submit(spec)``) and an event
feed (``add_listener``). The server runs an asyncio loop on its own thread;
:meth:`GcsServer.start` returns once the socket listens (or raises
:class:`ServerError`, e.g. the port is taken).

Routes (README, "Ground station", documents the bodies):

* ``GET /``, ``/static/<path>`` (``swarm/runtime/static``), ``/vendor/leaflet/<path>``
  (``node_modules/leaflet/dist``), ``/tiles/{z}/{x}/{y}.png`` (``--tiles-dir``);
* ``GET /api/config``, ``/api/state``, ``/api/agents/<id>``; ``POST /api/command``;
  ``GET|POST /api/replay`` (replay mode);
* ``GET /ws``: the state pushed at ``ws_hz``, events as they happen, commands and
  replay controls from the client.

Who may use it (README, "Security"), checked by one middleware before any route,
in this order:

1. ``Host`` must name this station: a localhost name, a loopback address, the
   listening address (any address when listening on all of them) or a name the
   operator allows (``allow_hosts``). A DNS-rebound page always comes under a
   foreign *name*: 403.
2. ``Origin``, when the browser sends one (every cross-origin request, every POST,
   every WebSocket handshake), must be this very origin (``http://`` + the Host);
   ``Sec-Fetch-Site: cross-site|same-site`` is refused too, except for the page
   and its files (a link to the station may be followed): 403.
3. The token, when the station has one (always when it listens beyond loopback;
   generated with :mod:`secrets` unless given): ``Authorization: Bearer``, the
   ``gcs_token_<port>`` cookie, or ``?token=`` (then set as that cookie, HttpOnly
   and SameSite=Strict), compared in constant time. Without it every route
   answers 401, ``GET /`` with a form asking for it.
4. Bodies: ``application/json`` (UTF-8) only (415), at most 64 KiB (413), read
   within ``body_timeout`` (408). JSON is parsed by :func:`parse_json`: deep
   nesting, over-long integers and bad UTF-8 are 400 with a one-line reason;
   NaN, infinities and huge integers parse and are refused by the argument checks
   (so a WebSocket answer still carries the request's id).

Every error is a JSON object ``{"error": reason}`` with a 4xx status (a handler
that fails unexpectedly answers 500 and logs the traceback, which never reaches
the client). A bad WebSocket message gets ``{"type": "error", "status", "reason",
"id"?}`` and the connection stays open. Idle connections (and clients that never
finish their headers) are closed after ``idle_timeout``. One state JSON text is
built per push and shared by all WebSocket clients.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import json
import logging
import math
import re
import secrets
import threading
from collections.abc import Awaitable, Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from aiohttp import WSMsgType, web

from swarm.core.station import CommandRefused, CommandSpec, parse_command
from swarm.errors import SwarmError

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
REPO_DIR = Path(__file__).resolve().parents[2]
LEAFLET_DIR = REPO_DIR / "node_modules" / "leaflet" / "dist"
OSM_TILES = "https://tile.openstreetmap.org/{z}/{x}/{y}.png"
OSM_ATTRIBUTION = '&copy; <a href="https://www.openstreetmap.org/copyright">OpenStreetMap</a> contributors'
LOCAL_TILES = "/tiles/{z}/{x}/{y}.png"
MAX_WS_HZ = 10.0
MAX_BODY = 64 * 1024  # a request body or a WebSocket message
MAX_WS_FRAME = 1024 * 1024  # beyond this the WebSocket closes (1009); up to it: a 413 answer
MAX_DEPTH = 16  # JSON nesting: a command is 1 deep
MAX_INT_DIGITS = 1000  # longer integers are malformed (Python refuses 4300 and more anyway)
MAX_ID = 64  # a WebSocket request's id: a string this long, or an integer
#: a token travels in a URL and a cookie: unreserved URL characters only
TOKEN_RE = re.compile(r"[A-Za-z0-9._~-]{16,256}")
TOKEN_RULE = "16 to 256 characters of A-Z a-z 0-9 . _ ~ -"
HOST_RE = re.compile(r"[a-z0-9]([a-z0-9-]*[a-z0-9])?(\.[a-z0-9]([a-z0-9-]*[a-z0-9])?)*")
WILDCARDS = ("", "0.0.0.0", "::")


class ServerError(SwarmError):
    """The server cannot start (address in use, bad host)."""


class ReplayControl(Protocol):
    def status(self) -> dict[str, Any]: ...

    def control(self, action: Any, value: Any) -> dict[str, Any]: ...


class StationView(Protocol):
    name: str
    id: int

    @property
    def replay(self) -> ReplayControl | None: ...

    def describe(self) -> str: ...

    def snapshot(self) -> dict[str, Any]: ...

    def snapshot_json(self) -> str: ...

    def agent(self, agent_id: int) -> dict[str, Any] | None: ...

    def center(self) -> list[float] | None: ...

    def submit(self, spec: CommandSpec) -> Future[tuple[int, dict[str, Any]]]: ...

    def add_listener(self, fn: Callable[[dict[str, Any]], None]) -> None: ...

    def remove_listener(self, fn: Callable[[dict[str, Any]], None]) -> None: ...


def is_loopback(host: str) -> bool:
    """``localhost`` (and ``*.localhost``) or a loopback address."""
    h = host.strip("[]").lower().rstrip(".")
    if h == "localhost" or h.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def check_token(token: str) -> str:
    """``token`` if it is usable (see :data:`TOKEN_RULE`). Raises ValueError."""
    if not TOKEN_RE.fullmatch(token):
        raise ValueError(f"token: {TOKEN_RULE}")
    return token


def check_host_name(name: str) -> str:
    """An ``allow_hosts`` entry, lower-cased: a DNS name or an IP address. Raises ValueError."""
    n = name.strip().lower().rstrip(".")
    try:
        return str(ipaddress.ip_address(n.strip("[]")))
    except ValueError:
        pass
    if len(n) > 253 or not HOST_RE.fullmatch(n):
        raise ValueError(f"host {name!r}: a DNS name (gcs.local) or an IP address")
    return n


def split_host(header: str) -> tuple[str, int | None] | None:
    """A ``Host``/origin authority as (lower-case name or address, port or None); None
    if it is not one."""
    h = header.strip().lower()
    if h.startswith("["):
        end = h.find("]")
        if end < 0:
            return None
        name, rest = h[1:end], h[end + 1 :]
        try:
            ipaddress.IPv6Address(name)
        except ValueError:
            return None
    else:
        name, sep, port_s = h.partition(":")
        rest = sep + port_s
        if ":" in port_s:
            return None
    name = name.rstrip(".")
    if not name:
        return None
    if not rest:
        return name, None
    if not (rest.startswith(":") and rest[1:].isdigit() and len(rest) <= 6):
        return None
    port = int(rest[1:])
    return (name, port) if port <= 65535 else None


def _parse_int(text: str) -> int:
    if len(text) > MAX_INT_DIGITS:
        raise ValueError(f"a number of {len(text)} digits (at most {MAX_INT_DIGITS})")
    return int(text)


def _too_deep(obj: Any, limit: int) -> bool:
    stack: list[tuple[Any, int]] = [(obj, 1)]
    while stack:
        o, depth = stack.pop()
        if depth > limit:
            return True
        for child in o.values() if isinstance(o, dict) else o:
            if isinstance(child, (list, dict)):
                stack.append((child, depth + 1))
        # (scalars never reach the stack)
    return False


def parse_json(text: str) -> Any:
    """One JSON text from a client, whatever it holds.

    NaN, ``Infinity`` and large integers parse (the argument checks refuse them with
    the field's name); nesting deeper than :data:`MAX_DEPTH` and integers longer than
    :data:`MAX_INT_DIGITS` digits do not.

    Raises:
        CommandRefused: (400) malformed or too deeply nested JSON, with a one-line reason.
    """
    too_deep = CommandRefused(400, f"JSON nested too deeply (at most {MAX_DEPTH} levels)")
    try:
        obj = json.loads(text, parse_int=_parse_int)
    except RecursionError:
        raise too_deep from None
    except ValueError as exc:
        raise CommandRefused(400, "malformed JSON: " + " ".join(str(exc).split())[:200]) from None
    if isinstance(obj, (list, dict)) and _too_deep(obj, MAX_DEPTH):
        raise too_deep
    return obj


@dataclass
class ServerConfig:
    """Where and how the station serves. ``token`` None beyond loopback: one is
    generated (read it back from here); given, it must follow :data:`TOKEN_RULE`.

    Raises:
        ValueError: a bad ``ws_hz``, token, allowed host or timeout.
    """

    host: str = "127.0.0.1"
    port: int = 8080
    tiles: str | None = OSM_TILES  # a URL template, or None for a plain background
    tiles_dir: Path | None = None  # serves /tiles/{z}/{x}/{y}.png (and wins over tiles)
    attribution: str = OSM_ATTRIBUTION
    center: tuple[float, float] | None = None
    ws_hz: float = 2.0
    command_timeout: float = 20.0
    static_dir: Path = STATIC_DIR
    leaflet_dir: Path = LEAFLET_DIR
    token: str | None = None
    allow_hosts: tuple[str, ...] = ()  # Host names served besides localhost and the address
    body_timeout: float = 10.0  # a request body not in by then: 408
    idle_timeout: float = 15.0  # an idle connection (or one stuck in its headers) is closed
    token_generated: bool = False  # set here when the token was made up

    def __post_init__(self) -> None:
        if not (math.isfinite(self.ws_hz) and 0 < self.ws_hz <= MAX_WS_HZ):
            raise ValueError(f"ws_hz {self.ws_hz}: (0, {MAX_WS_HZ:g}] pushes per second")
        for k in ("body_timeout", "idle_timeout"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{k} {v}: a positive number of seconds")
        if self.token is not None:
            check_token(self.token)
        elif not is_loopback(self.host):
            self.token = secrets.token_urlsafe(32)
            self.token_generated = True
        self.allow_hosts = tuple(check_host_name(h) for h in self.allow_hosts)

    @property
    def tile_template(self) -> str | None:
        return LOCAL_TILES if self.tiles_dir is not None else self.tiles


def _error(status: int, reason: str) -> web.Response:
    resp = web.json_response({"error": reason}, status=status)
    if status == 401:
        resp.headers["WWW-Authenticate"] = 'Bearer realm="swarm gcs"'
    return resp


LOGIN_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width">
<title>Ground station: token needed</title>
<style>body{font:16px system-ui,sans-serif;margin:3em auto;max-width:34em;padding:0 1em}
input{font:inherit;width:100%;margin:.5em 0;padding:.4em}button{font:inherit;padding:.4em 1.2em}</style>
</head><body><h1>This ground station needs its token</h1>
<p>Open the address the station printed when it started (it ends in
<code>/?token=&hellip;</code>), or paste the token here.</p>
<form method="get" action="/"><label for="token">Token</label>
<input id="token" name="token" type="password" autocomplete="current-password" required autofocus>
<button type="submit">Open the station</button></form></body></html>
"""


def safe_file(root: Path, rel: str) -> Path | None:
    """``root/rel`` if it is a file inside ``root`` (no traversal, no symlink out)."""
    if not rel or "\x00" in rel:
        return None
    try:
        base = root.resolve()
        p = (base / rel).resolve()
    except (OSError, ValueError, RuntimeError):
        return None
    if not p.is_relative_to(base) or not p.is_file():
        return None
    return p


def replay_args(obj: dict[str, Any]) -> tuple[str, float | None]:
    """A replay control's ``action`` and ``value`` (a finite number or absent).

    Raises:
        CommandRefused: (400) an action that is not a short string, a value that is
            not a finite number.
    """
    action, value = obj.get("action"), obj.get("value")
    if not isinstance(action, str) or len(action) > 16:
        raise CommandRefused(400, "a replay control needs an 'action': play, pause, seek or speed")
    if value is None:
        return action, None
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or (isinstance(value, int) and abs(value) > 10**15)
        or not math.isfinite(value)
    ):
        raise CommandRefused(400, f"replay {action}: 'value' must be a finite number")
    return action, float(value)


def ws_id(obj: dict[str, Any]) -> Any:
    """A WebSocket request's ``id`` if it is one to echo (a short string, an integer
    of at most 15 digits, or absent: None).

    Raises:
        CommandRefused: (400) any other id.
    """
    mid = obj.get("id")
    if (
        mid is None
        or (isinstance(mid, str) and len(mid) <= MAX_ID)
        or (isinstance(mid, int) and not isinstance(mid, bool) and abs(mid) < 10**15)
    ):
        return mid
    raise CommandRefused(400, f"'id' must be a string of at most {MAX_ID} characters or an integer")


class GcsServer:
    """The HTTP + WebSocket server of one station view. See the module docstring."""

    def __init__(self, station: StationView, config: ServerConfig | None = None) -> None:
        self.station = station
        self.cfg = config or ServerConfig()
        self.port = self.cfg.port
        self.stats = {"ws_clients": 0, "ws_sent": 0, "ws_send_errors": 0, "http_errors": 0, "http_refused": 0}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._clients: set[web.WebSocketResponse] = set()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._stopped = False

    @property
    def url(self) -> str:
        """The page's address (on this machine when listening on every address)."""
        host = self.cfg.host
        if host in WILDCARDS:
            host = "::1" if host == "::" else "127.0.0.1"
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}/"

    @property
    def token_url(self) -> str:
        """:attr:`url` with the token (``?token=...``) when there is one."""
        return self.url + (f"?token={self.cfg.token}" if self.cfg.token else "")

    @property
    def cookie_name(self) -> str:
        """One cookie per port: cookies are per host, and two stations may share one."""
        return f"gcs_token_{self.port}"

    # -- life cycle ---------------------------------------------------------------
    def start(self) -> GcsServer:
        """Listen and serve on a thread.

        Raises:
            ServerError: the address cannot be bound (in use, bad host).
        """
        loop = asyncio.new_event_loop()
        self._loop = loop
        ready = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            asyncio.set_event_loop(loop)
            try:
                loop.run_until_complete(self._startup())
            except BaseException as exc:
                failure.append(exc)
                ready.set()
                with contextlib.suppress(Exception):
                    loop.run_until_complete(self._shutdown())
                loop.close()
                return
            ready.set()
            try:
                loop.run_forever()
            finally:
                with contextlib.suppress(Exception):
                    loop.run_until_complete(self._shutdown())
                loop.close()

        self._thread = threading.Thread(target=run, name="gcs-http", daemon=True)
        self._thread.start()
        if not ready.wait(30.0):
            raise ServerError("the HTTP server did not start in 30 s")
        if failure:
            exc = failure[0]
            if isinstance(exc, OSError):
                why = exc.strerror or str(exc)
                raise ServerError(f"cannot listen on {self.cfg.host}:{self.cfg.port}: {why}") from None
            raise ServerError(f"cannot start the HTTP server: {exc}") from exc
        return self

    def stop(self) -> None:
        """Close WebSockets and the listener; safe twice."""
        if self._stopped:
            return
        self._stopped = True
        loop = self._loop
        if loop is not None and self._thread is not None and self._thread.is_alive():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(loop.stop)
            self._thread.join(10.0)

    async def _startup(self) -> None:
        app = web.Application(middlewares=[self._errors, self._guard], client_max_size=MAX_BODY)
        r = app.router
        r.add_get("/", self._index)
        r.add_get("/static/{path:.+}", self._static)
        r.add_get("/vendor/leaflet/{path:.+}", self._leaflet)
        r.add_get(r"/tiles/{z:\d{1,2}}/{x:\d{1,9}}/{y:\d{1,9}}.png", self._tile)
        r.add_get("/api/config", self._config)
        r.add_get("/api/state", self._state)
        r.add_get(r"/api/agents/{id:\d{1,9}}", self._agent)
        r.add_post("/api/command", self._command_http)
        r.add_get("/api/replay", self._replay_get)
        r.add_post("/api/replay", self._replay_post)
        r.add_get("/ws", self._ws)
        self._runner = web.AppRunner(
            app, access_log=None, handle_signals=False, keepalive_timeout=self.cfg.idle_timeout
        )
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.cfg.host, self.cfg.port)
        await site.start()
        addrs = self._runner.addresses
        if addrs and isinstance(addrs[0], tuple):
            self.port = int(addrs[0][1])
        self.station.add_listener(self._on_event)
        self._spawn(self._broadcast())

    async def _shutdown(self) -> None:
        self.station.remove_listener(self._on_event)
        for t in list(self._tasks):
            t.cancel()
        for ws in list(self._clients):
            with contextlib.suppress(Exception):
                await ws.close(code=1001, message=b"station stopping")
        if self._runner is not None:
            await self._runner.cleanup()
        # what is left (a connection still draining a refused body): cancelled, not
        # abandoned with the loop
        rest = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for t in rest:
            t.cancel()
        await asyncio.gather(*rest, return_exceptions=True)

    def _spawn(self, coro: Awaitable[Any]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # -- who may use it ---------------------------------------------------------------
    def _host_refusal(self, request: web.Request) -> tuple[int, str] | None:
        """Why the request's Host is not this station's, or None (rule 1)."""
        header = request.headers.get("Host", "")
        parsed = split_host(header)
        if parsed is None:
            return 400, "a Host header naming this station is needed"
        name = parsed[0]
        if name in self.cfg.allow_hosts or is_loopback(name):
            return None
        bound = self.cfg.host.strip("[]").lower()
        try:
            addr = ipaddress.ip_address(name)
        except ValueError:
            if name == bound:
                return None
        else:
            if bound in WILDCARDS:
                return None  # listening on every address: any address of this machine's
            with contextlib.suppress(ValueError):
                if addr == ipaddress.ip_address(bound):
                    return None
        shown = name[:64]
        return 403, (
            f"host {shown!r} is not this station's name: use its address, or start it "
            f"with --allow-host {shown}"
        )

    def _origin_refusal(self, request: web.Request, page: bool) -> str | None:
        """Why the request comes from another page, or None (rule 2)."""
        origin = request.headers.get("Origin")
        if origin is None:
            site = request.headers.get("Sec-Fetch-Site", "").lower()
            if site in ("cross-site", "same-site") and not page:
                return f"a request from another site ({site}) is refused"
            return None
        scheme, sep, authority = origin.partition("://")
        ours = split_host(request.headers.get("Host", ""))
        theirs = split_host(authority) if sep and "/" not in authority else None
        default = 443 if scheme.lower() == "https" else 80
        if (
            theirs is None
            or ours is None
            or scheme.lower() != request.scheme
            or (theirs[0], theirs[1] or default) != (ours[0], ours[1] or 80)
        ):
            return f"origin {origin[:80]!r} is not this station's page: only its own page may use the API"
        return None

    def _token_source(self, request: web.Request) -> str | None:
        """Where the request's valid token came from ("header", "cookie", "query"), or
        None; compared in constant time (rule 3)."""
        want = (self.cfg.token or "").encode()
        candidates: list[tuple[str, str]] = []
        auth = request.headers.get("Authorization", "")
        if auth[:7].lower() == "bearer ":
            candidates.append(("header", auth[7:].strip()))
        cookie = request.cookies.get(self.cookie_name)
        if cookie is not None:
            candidates.append(("cookie", cookie))
        query = request.query.get("token")
        if query is not None:
            candidates.append(("query", query))
        for source, given in candidates:
            if hmac.compare_digest(given.encode("utf-8", "replace"), want):
                return source
        return None

    @web.middleware
    async def _guard(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        refused = self._host_refusal(request)
        if refused is not None:
            self.stats["http_refused"] += 1
            return _error(*refused)
        page = request.method in ("GET", "HEAD") and (
            request.path == "/" or request.path.startswith(("/static/", "/vendor/"))
        )
        why = self._origin_refusal(request, page)
        if why is not None:
            self.stats["http_refused"] += 1
            return _error(403, why)
        source = None
        if self.cfg.token is not None:
            source = self._token_source(request)
            if source is None:
                self.stats["http_refused"] += 1
                if request.method in ("GET", "HEAD") and request.path == "/":
                    return web.Response(
                        status=401,
                        text=LOGIN_PAGE,
                        content_type="text/html",
                        headers={"WWW-Authenticate": 'Bearer realm="swarm gcs"', "Cache-Control": "no-store"},
                    )
                return _error(
                    401,
                    "this station needs its token: open the address it printed "
                    "(.../?token=...) or send Authorization: Bearer TOKEN",
                )
        resp = await handler(request)
        if source == "query" and not resp.prepared:
            resp.set_cookie(
                self.cookie_name, self.cfg.token or "", path="/", httponly=True, samesite="Strict"
            )
        return resp

    # -- errors -------------------------------------------------------------------
    @web.middleware
    async def _errors(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        try:
            return await handler(request)
        except web.HTTPException as exc:
            if exc.status < 400:
                raise
            self.stats["http_errors"] += 1
            reason = {
                404: f"not found: {request.path[:200]}",
                405: f"method {request.method} not allowed on {request.path[:200]}",
                413: f"request body too large (at most {MAX_BODY // 1024} KiB)",
            }.get(exc.status, exc.reason)
            return _error(exc.status, reason)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self.stats["http_errors"] += 1
            log.exception("gcs server: %s %s failed", request.method, request.path)
            return _error(500, f"internal error: {type(exc).__name__}")

    # -- files ---------------------------------------------------------------------
    async def _file(self, root: Path, rel: str, what: str) -> web.StreamResponse:
        p = safe_file(root, rel)
        if p is None:
            return _error(404, f"{what} not found: {rel}")
        return web.FileResponse(p, headers={"Cache-Control": "no-cache"})

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return await self._file(self.cfg.static_dir, "index.html", "page")

    async def _static(self, request: web.Request) -> web.StreamResponse:
        return await self._file(self.cfg.static_dir, request.match_info["path"], "file")

    async def _leaflet(self, request: web.Request) -> web.StreamResponse:
        return await self._file(
            self.cfg.leaflet_dir,
            request.match_info["path"],
            "Leaflet file (install it with the set-up: npm ci)",
        )

    async def _tile(self, request: web.Request) -> web.StreamResponse:
        if self.cfg.tiles_dir is None:
            return _error(404, "no tile folder: start the station with --tiles-dir DIR")
        m = request.match_info
        return await self._file(self.cfg.tiles_dir, f"{int(m['z'])}/{int(m['x'])}/{int(m['y'])}.png", "tile")

    # -- API -----------------------------------------------------------------------
    async def _config(self, request: web.Request) -> web.Response:
        center = list(self.cfg.center) if self.cfg.center is not None else self.station.center()
        return web.json_response(
            {
                "tiles": self.cfg.tile_template,
                "attribution": self.cfg.attribution if self.cfg.tile_template else "",
                "station": {"name": self.station.name, "id": self.station.id},
                "replay": self.station.replay is not None,
                "center": center,
                "ws_hz": self.cfg.ws_hz,
            }
        )

    def _snapshot_text(self) -> str:
        """The state as JSON text (with the replay status in replay mode)."""
        text = self.station.snapshot_json()
        rp = self.station.replay
        if rp is not None:
            text = text[:-1] + ', "replay": ' + json.dumps(rp.status()) + "}"
        return text

    async def _state(self, request: web.Request) -> web.Response:
        return web.Response(text=self._snapshot_text(), content_type="application/json")

    async def _agent(self, request: web.Request) -> web.Response:
        aid = int(request.match_info["id"])
        a = self.station.agent(aid)
        if a is None:
            return _error(404, f"unknown agent {aid}")
        return web.json_response(a)

    async def _json_body(self, request: web.Request) -> Any:
        """The request's JSON body (rule 4).

        Raises:
            CommandRefused: 415 not ``application/json`` (UTF-8), 413 over
                :data:`MAX_BODY`, 408 not in within ``body_timeout``, 400 not UTF-8 or
                malformed (:func:`parse_json`).
        """
        charset = (request.charset or "utf-8").lower()
        if request.content_type != "application/json" or charset not in ("utf-8", "utf8"):
            raise CommandRefused(415, "send the body as Content-Type: application/json (UTF-8)")
        if request.content_length is not None and request.content_length > MAX_BODY:
            raise CommandRefused(413, f"request body too large (at most {MAX_BODY // 1024} KiB)")
        try:
            raw = await asyncio.wait_for(request.read(), self.cfg.body_timeout)
        except TimeoutError:
            raise CommandRefused(408, f"the body did not arrive in {self.cfg.body_timeout:g} s") from None
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise CommandRefused(400, "malformed JSON: the body is not UTF-8 text") from None
        return parse_json(text)

    async def run_command(self, body: Any) -> tuple[int, dict[str, Any]]:
        """Validate, send and await one command: (status, body)."""
        try:
            spec = parse_command(body)
            fut = self.station.submit(spec)
        except CommandRefused as exc:
            return exc.status, {"ok": False, "error": exc.reason}
        except Exception as exc:  # a bug, not the sender's fault: say so, keep serving
            log.exception("gcs server: command %r failed", type(body).__name__)
            return 500, {"ok": False, "error": f"internal error: {type(exc).__name__}"}
        try:
            status, out = await asyncio.wait_for(asyncio.wrap_future(fut), self.cfg.command_timeout)
        except TimeoutError:
            return 504, {"ok": False, "error": "no answer"}
        return status, out

    async def _command_http(self, request: web.Request) -> web.Response:
        try:
            body = await self._json_body(request)
        except CommandRefused as exc:
            return _error(exc.status, exc.reason)
        status, out = await self.run_command(body)
        return web.json_response(out, status=status)

    async def _replay_get(self, request: web.Request) -> web.Response:
        rp = self.station.replay
        if rp is None:
            return _error(404, "not in replay mode (swarm gcs --replay CAPTURE)")
        return web.json_response(rp.status())

    async def _replay_post(self, request: web.Request) -> web.Response:
        rp = self.station.replay
        if rp is None:
            return _error(404, "not in replay mode (swarm gcs --replay CAPTURE)")
        try:
            body = await self._json_body(request)
            if not isinstance(body, dict):
                raise CommandRefused(400, "a replay control is a JSON object")
            return web.json_response(rp.control(*replay_args(body)))
        except CommandRefused as exc:
            return _error(exc.status, exc.reason)

    # -- WebSocket -------------------------------------------------------------------
    async def _ws(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(heartbeat=30.0, max_msg_size=MAX_WS_FRAME)
        await ws.prepare(request)
        self._clients.add(ws)
        self.stats["ws_clients"] = len(self._clients)
        try:
            await self._send(ws, self._state_texts())
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    try:
                        await self._ws_message(ws, msg.data)
                    except Exception as exc:  # a bug: answer, log, keep the connection
                        log.exception("gcs server: WebSocket message failed")
                        await self._send(ws, [self._ws_error(500, f"internal error: {type(exc).__name__}")])
                elif msg.type == WSMsgType.BINARY:
                    await self._send(ws, [self._ws_error(400, "send JSON text, not binary")])
                elif msg.type == WSMsgType.ERROR:
                    break
        finally:
            self._clients.discard(ws)
            self.stats["ws_clients"] = len(self._clients)
        return ws

    @staticmethod
    def _ws_error(status: int, reason: str, mid: Any = None) -> str:
        d: dict[str, Any] = {"type": "error", "status": status, "reason": reason}
        if mid is not None:
            d["id"] = mid
        return json.dumps(d)

    async def _ws_message(self, ws: web.WebSocketResponse, text: str) -> None:
        if len(text) > MAX_BODY:
            await self._send(ws, [self._ws_error(413, f"message too large (at most {MAX_BODY // 1024} KiB)")])
            return
        try:
            obj = parse_json(text)
            if not isinstance(obj, dict):
                raise CommandRefused(400, "a message is a JSON object with a 'type'")
            mid = ws_id(obj)
        except CommandRefused as exc:
            await self._send(ws, [self._ws_error(exc.status, exc.reason)])
            return
        mtype = obj.get("type")
        if mtype == "command":
            self._spawn(self._ws_command(ws, obj))
        elif mtype == "replay":
            rp = self.station.replay
            if rp is None:
                await self._send(ws, [self._ws_error(409, "not in replay mode", mid)])
                return
            try:
                st = rp.control(*replay_args(obj))
            except CommandRefused as exc:
                await self._send(ws, [self._ws_error(exc.status, exc.reason, mid)])
                return
            await self._send(ws, [json.dumps({"type": "replay", "id": mid, **st})])
        elif mtype == "state":
            await self._send(ws, self._state_texts())
        else:
            shown = (
                repr(mtype[:24])
                if isinstance(mtype, str)
                else "null"
                if mtype is None
                else f"of type {type(mtype).__name__}"
            )
            await self._send(
                ws, [self._ws_error(400, f"unknown message type {shown}: command, replay or state", mid)]
            )

    async def _ws_command(self, ws: web.WebSocketResponse, obj: dict[str, Any]) -> None:
        body = {k: v for k, v in obj.items() if k not in ("type", "id")}
        status, out = await self.run_command(body)
        await self._send(
            ws, [json.dumps({"type": "command_result", "id": ws_id(obj), "status": status, **out})]
        )

    def _state_texts(self) -> list[str]:
        texts = ['{"type": "state", ' + self.station.snapshot_json()[1:]]
        rp = self.station.replay
        if rp is not None:
            texts.append(json.dumps({"type": "replay", **rp.status()}))
        return texts

    async def _send(self, ws: web.WebSocketResponse, texts: list[str]) -> None:
        try:
            for t in texts:
                await asyncio.wait_for(ws.send_str(t), 10.0)
                self.stats["ws_sent"] += 1
        except (ConnectionError, RuntimeError, TimeoutError):
            self.stats["ws_send_errors"] += 1
            self._clients.discard(ws)
            with contextlib.suppress(Exception):
                await ws.close()

    async def _broadcast(self) -> None:
        period = 1.0 / self.cfg.ws_hz
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            next_t += period
            await asyncio.sleep(max(0.0, next_t - loop.time()))
            if next_t < loop.time() - period:
                next_t = loop.time()  # fell behind: do not burst
            if not self._clients:
                continue
            try:
                texts = self._state_texts()
            except Exception:
                log.exception("gcs server: snapshot failed")
                continue
            await asyncio.gather(*(self._send(ws, texts) for ws in list(self._clients)))

    def _on_event(self, event: dict[str, Any]) -> None:
        """Station thread: hand the event to the loop."""
        loop = self._loop
        if loop is None or self._stopped:
            return
        text = json.dumps({"type": "event", "event": event})
        with contextlib.suppress(RuntimeError):  # the loop is closing
            loop.call_soon_threadsafe(self._push, text)

    def _push(self, text: str) -> None:
        for ws in list(self._clients):
            self._spawn(self._send(ws, [text]))


__all__ = [
    "LEAFLET_DIR",
    "LOCAL_TILES",
    "MAX_BODY",
    "OSM_ATTRIBUTION",
    "OSM_TILES",
    "STATIC_DIR",
    "TOKEN_RULE",
    "GcsServer",
    "ServerConfig",
    "ServerError",
    "StationView",
    "check_host_name",
    "check_token",
    "is_loopback",
    "parse_json",
    "replay_args",
    "safe_file",
    "split_host",
    "ws_id",
]
