"""The ground station's HTTP + WebSocket server (aiohttp, on its own thread).

Theory of operation
-------------------
:class:`GcsServer` serves one *station view*: the live :class:`~swarm.runtime.station.live.Station`
or a :class:`~swarm.runtime.station.replay.ReplayStation`. Both give thread-safe snapshots
(``snapshot()``, ``agent(id)``), commands as futures (``submit(spec)``) and an event
feed (``add_listener``). The server runs an asyncio loop on its own thread;
:meth:`GcsServer.start` returns once the socket listens (or raises
:class:`ServerError`, e.g. the port is taken).

Routes (docs/station.md documents the bodies):

* ``GET /``, ``/static/<path>`` (``swarm/runtime/station/static``), ``/vendor/leaflet/<path>``
  (``swarm/runtime/station/vendor/leaflet``: the pinned Leaflet, vendored with its licence),
  ``/tiles/{z}/{x}/{y}.png`` (``--tiles-dir``; from an MBTiles file, ``--tiles-mbtiles``,
  ``.png``, ``.jpg`` or ``.webp`` as its metadata says: :mod:`swarm.runtime.station.tiles`, read
  on a worker thread; a tile that is missing or bad is a 404). The page and Leaflet are
  package data: found beside this module, in a checkout as in an installed wheel;
* ``GET /api/config``, ``/api/state``, ``/api/agents/<id>``; ``POST /api/command``;
  ``POST /api/alerts/ack`` (``{"id": N}``: an alert acknowledged; ``"station"``: one of
  another station's, acknowledged there, :func:`swarm.core.station.federation.ack_any`);
  ``POST /api/alerts/shelve`` (``{"id": N, "seconds": S}``: an alarm shelved, 0..3600 s;
  0 unshelves; this station's alarms only);
  ``GET|POST /api/replay`` (replay mode);
* ``GET /ws``: the whole state once, then what changed (deltas with sequence
  numbers, :mod:`swarm.runtime.station.websocket`) at ``ws_hz``, events as they happen,
  commands and replay controls from the client. ``GET /api/state`` (the page's
  fallback while the socket is down) is always the whole state.

Who may use it (docs/security.md: Host, Origin, token) is checked by one
middleware before any route, :meth:`swarm.runtime.station.security.Guard.middleware`;
bodies are read and parsed by the same module's :func:`~swarm.runtime.station.security.read_json`
and :func:`~swarm.runtime.station.security.parse_json` (each refusal a status and a one-line
reason). The WebSocket is :class:`swarm.runtime.station.websocket.WsHub`'s.

Every error is a JSON object ``{"error": reason}`` with a 4xx status (a handler
that fails unexpectedly answers 500 and logs the traceback, which never reaches
the client). Idle connections (and clients that never finish their headers) are
closed after ``idle_timeout``. At most ``max_connections`` are open at once: the one
over makes room by closing an idle one, never the operator's WebSocket or a request
in progress; a malformed request is one log line, rate-limited
(:mod:`swarm.runtime.station.connections`). A task notes the event loop's time twice a second
(:meth:`GcsServer.beats`): a handler that blocks the loop stops it, and the service
watchdog sees it (:mod:`swarm.runtime.notify`).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import math
import os
import re
import secrets
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aiohttp import web

from swarm.core.station.commands import CommandRefused, parse_command
from swarm.core.station.federation import ack_any, shelve_any
from swarm.errors import SwarmError
from swarm.runtime.station.connections import ConnectionLimiter, HttpLog, default_limit
from swarm.runtime.station.security import (
    AUTHORIZED,
    MAX_BODY,
    WILDCARDS,
    BodyBroken,
    Guard,
    check_host_name,
    check_token,
    error_response,
    is_loopback,
    read_json,
    replay_args,
    safe_file,
)
from swarm.runtime.station.served import ServedStation
from swarm.runtime.station.tiles import MbTiles
from swarm.runtime.station.websocket import WsHub

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
LEAFLET_DIR = Path(__file__).resolve().parent / "vendor" / "leaflet"
OSM_TILES = "https://tile.openstreetmap.org/{z}/{x}/{y}.png"
OSM_ATTRIBUTION = '&copy; <a href="https://www.openstreetmap.org/copyright">OpenStreetMap</a> contributors'
LOCAL_TILES = "/tiles/{z}/{x}/{y}.png"
MAX_WS_HZ = 10.0
BACKLOG = 128  # connections the kernel holds for the server to accept (aiohttp's default)


def page_policy(tiles: str | None) -> str:
    """The page's Content-Security-Policy: scripts, styles and connections of its own
    origin only, images also from the tile source ``tiles`` (a URL template), no
    frames around it (no clickjacking of the command buttons)."""
    img = "'self' data: blob:"
    m = re.match(r"(https?)://([^/?#]+)", tiles or "")
    if m:
        host = re.sub(r"\{[^}]*\}", "*", m.group(2))  # {s}.tile.example.org
        ok = re.fullmatch(r"(\*\.)?[A-Za-z0-9.-]+(:\d{1,5})?|\[[0-9A-Fa-f:.]+\](:\d{1,5})?", host)
        img += f" {m.group(1)}://{host}" if ok else f" {m.group(1)}:"
    return (
        f"default-src 'self'; img-src {img}; object-src 'none'; base-uri 'none'; "
        "frame-ancestors 'none'; form-action 'self'"
    )


class ServerError(SwarmError):
    """The server cannot start (address in use, bad host)."""


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
    tiles_mbtiles: MbTiles | None = None  # serves /tiles/{z}/{x}/{y}.<format> (wins over both)
    attribution: str = OSM_ATTRIBUTION  # HTML; the default means an MBTiles file's own
    center: tuple[float, float] | None = None
    ws_hz: float = 5.0
    command_timeout: float = 20.0
    static_dir: Path = STATIC_DIR
    leaflet_dir: Path = LEAFLET_DIR
    token: str | None = None
    allow_hosts: tuple[str, ...] = ()  # Host names served besides localhost and the address
    body_timeout: float = 10.0  # a request body not in by then: 408
    idle_timeout: float = 15.0  # an idle connection (or one stuck in its headers) is closed
    max_connections: int | None = None  # open at once; None: half the file limit, at most 512
    token_generated: bool = False  # set here when the token was made up

    def __post_init__(self) -> None:
        if not (math.isfinite(self.ws_hz) and 0 < self.ws_hz <= MAX_WS_HZ):
            raise ValueError(f"ws_hz {self.ws_hz}: (0, {MAX_WS_HZ:g}] pushes per second")
        for k in ("body_timeout", "idle_timeout"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{k} {v}: a positive number of seconds")
        if self.max_connections is not None and self.max_connections < 1:
            raise ValueError(f"max_connections {self.max_connections}: at least 1")
        if self.token is not None:
            check_token(self.token)
        elif not is_loopback(self.host):
            self.token = secrets.token_urlsafe(32)
            self.token_generated = True
        self.allow_hosts = tuple(check_host_name(h) for h in self.allow_hosts)
        if self.tiles_mbtiles is not None and self.attribution == OSM_ATTRIBUTION:
            self.attribution = self.tiles_mbtiles.meta.attribution  # the file's own credit, as text

    @property
    def tile_template(self) -> str | None:
        if self.tiles_mbtiles is not None:
            return LOCAL_TILES[: -len("png")] + self.tiles_mbtiles.meta.format
        return LOCAL_TILES if self.tiles_dir is not None else self.tiles

    @property
    def tiles_max_zoom(self) -> int:
        """The deepest zoom the tile source has (the page enlarges it beyond): an MBTiles
        file's own, a tile folder's deepest zoom folder (0-30), else 19."""
        if self.tiles_mbtiles is not None:
            return self.tiles_mbtiles.meta.max_zoom
        if self.tiles_dir is not None:
            try:
                zooms = [int(p.name) for p in self.tiles_dir.iterdir() if p.name.isdigit() and p.is_dir()]
            except OSError:
                zooms = []
            zooms = [z for z in zooms if z <= 30]
            if zooms:
                return max(zooms)
        return 19


class GcsServer:
    """The HTTP + WebSocket server of one station view. See the module docstring."""

    def __init__(self, station: ServedStation, config: ServerConfig | None = None) -> None:
        self.station = station
        self.cfg = config or ServerConfig()
        self.port = self.cfg.port
        self.stats = {"ws_clients": 0, "ws_sent": 0, "ws_send_errors": 0, "http_errors": 0, "http_refused": 0}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._listener: asyncio.Server | None = None
        self.limiter: ConnectionLimiter | None = None  # once started
        self.http_log = HttpLog(self.stats, time.monotonic)
        self.ws = WsHub(self.station, self.cfg.ws_hz, self.stats, self.run_command, self._spawn)
        self._tasks: set[asyncio.Task[Any]] = set()
        self._stopped = False
        self._beat = time.monotonic()  # the event loop's last round (liveness)

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
        """The cookie earlier versions kept the token in (deleted where a browser sends it)."""
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
                # aiohttp's text repeats the address: "error while attempting to bind on ..."
                why = os.strerror(exc.errno) if exc.errno else exc.strerror or str(exc)
                if exc.errno == errno.EADDRINUSE:
                    why = f"port {self.cfg.port} in use (another program, or another station?)"
                raise ServerError(f"cannot listen on {self.cfg.host}:{self.cfg.port}: {why}") from None
            raise ServerError(f"cannot start the HTTP server: {exc}") from exc
        return self

    def stop(self) -> None:
        """Close WebSockets and the listener; safe twice."""
        if self._stopped:
            return
        self._stopped = True
        self.ws.detach()
        loop = self._loop
        if loop is not None and self._thread is not None and self._thread.is_alive():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(loop.stop)
            self._thread.join(10.0)

    async def _startup(self) -> None:
        guard = Guard(
            self.cfg.host, self.cfg.allow_hosts, self.cfg.token, lambda: self.cookie_name, self.stats
        )
        app = web.Application(
            middlewares=[self._errors, guard.middleware, self._serving], client_max_size=MAX_BODY
        )
        r = app.router
        r.add_get("/", self._index)
        r.add_get("/static/{path:.+}", self._static)
        r.add_get("/vendor/leaflet/{path:.+}", self._leaflet)
        r.add_get(r"/tiles/{z:\d{1,2}}/{x:\d{1,9}}/{y:\d{1,9}}.{ext:png|jpg|webp}", self._tile)
        r.add_get("/api/config", self._config)
        r.add_get("/api/state", self._state)
        r.add_get(r"/api/agents/{id:\d{1,9}}", self._agent)
        r.add_post("/api/command", self._command_http)
        r.add_post("/api/alerts/ack", self._ack_alert_http)
        r.add_post("/api/alerts/shelve", self._shelve_alert_http)
        r.add_get("/api/replay", self._replay_get)
        r.add_post("/api/replay", self._replay_post)
        r.add_get("/ws", self.ws.handle)
        loop = asyncio.get_running_loop()
        self.http_log.loop = loop
        loop.set_exception_handler(self.http_log.loop_exception)  # a failed accept: one line
        self._runner = web.AppRunner(
            app,
            access_log=None,
            handle_signals=False,
            keepalive_timeout=self.cfg.idle_timeout,
            logger=self.http_log,  # a malformed request: one line, rate-limited
        )
        await self._runner.setup()
        server = self._runner.server
        assert server is not None
        # the listener is ours (not a TCPSite): each connection passes the limiter
        self.limiter = ConnectionLimiter(self.cfg.max_connections or default_limit(), self.stats)
        self._listener = await loop.create_server(
            self.limiter.factory(server), self.cfg.host or None, self.cfg.port, backlog=BACKLOG
        )
        sockets = self._listener.sockets
        if sockets:
            self.port = int(sockets[0].getsockname()[1])
        self.ws.attach(loop)
        self._spawn(self.ws.broadcast())
        self._spawn(self._pulse())

    async def _pulse(self) -> None:
        while True:
            self._beat = time.monotonic()
            await asyncio.sleep(0.5)

    def beats(self) -> dict[str, tuple[float, float]]:
        """The event loop's last round (``time.monotonic()``) and its longest wait."""
        return {"http": (self._beat, 0.5)}

    async def _shutdown(self) -> None:
        self.ws.detach()
        for t in list(self._tasks):
            t.cancel()
        if self._listener is not None:
            self._listener.close()
        await self.ws.close_clients()
        if self._runner is not None:
            await self._runner.cleanup()
        self.http_log.close()
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
            return error_response(exc.status, reason)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self.stats["http_errors"] += 1
            log.exception("gcs server: %s %s failed", request.method, request.path)
            return error_response(500, f"internal error: {type(exc).__name__}")

    @web.middleware
    async def _serving(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        """A request that passed the guard: busy until it ends (never closed to make room
        for another); its connection is the operator's if it had the token."""
        if self.limiter is None:
            return await handler(request)
        with self.limiter.serving(request.transport, proven=request.get(AUTHORIZED, True)):
            return await handler(request)

    async def _body(self, request: web.Request) -> Any:
        """:func:`read_json`; a body broken on the wire is also a malformed request's line."""
        try:
            return await read_json(request, self.cfg.body_timeout)
        except BodyBroken as exc:
            self.http_log.malformed(request.remote or "?", exc.reason)
            raise

    # -- files ---------------------------------------------------------------------
    async def _file(
        self, root: Path, rel: str, what: str, headers: dict[str, str] | None = None
    ) -> web.StreamResponse:
        p = safe_file(root, rel)
        if p is None:
            return error_response(404, f"{what} not found: {rel}")
        return web.FileResponse(p, headers=headers or {"Cache-Control": "no-cache"})

    async def _index(self, request: web.Request) -> web.StreamResponse:
        # public (it holds nothing of the swarm); its address may hold the token once:
        # kept out of the browser's cache. The page's scripts can read the token, so
        # they may run only from here and talk only to here (and load the map's tiles)
        headers = {
            "Cache-Control": "no-store",
            "Content-Security-Policy": page_policy(self.cfg.tile_template),
            "X-Content-Type-Options": "nosniff",
        }
        return await self._file(self.cfg.static_dir, "index.html", "page", headers)

    async def _static(self, request: web.Request) -> web.StreamResponse:
        return await self._file(self.cfg.static_dir, request.match_info["path"], "file")

    async def _leaflet(self, request: web.Request) -> web.StreamResponse:
        return await self._file(self.cfg.leaflet_dir, request.match_info["path"], "Leaflet file")

    async def _tile(self, request: web.Request) -> web.StreamResponse:
        m = request.match_info
        z, x, y = int(m["z"]), int(m["x"]), int(m["y"])
        mb = self.cfg.tiles_mbtiles
        if mb is not None:
            data = None
            if m["ext"] == mb.meta.format:
                data = await asyncio.get_running_loop().run_in_executor(None, mb.tile, z, x, y)
            if data is None:
                return error_response(404, f"tile not found: {z}/{x}/{y}.{m['ext']}")
            return web.Response(
                body=data,
                content_type=mb.meta.content_type,
                headers={"Cache-Control": "max-age=3600", "X-Content-Type-Options": "nosniff"},
            )
        if self.cfg.tiles_dir is None:
            return error_response(
                404, "no tile source: start the station with --tiles-dir or --tiles-mbtiles"
            )
        if m["ext"] != "png":
            return error_response(404, f"tile not found: {z}/{x}/{y}.{m['ext']}")
        return await self._file(self.cfg.tiles_dir, f"{z}/{x}/{y}.png", "tile")

    # -- API -----------------------------------------------------------------------
    async def _config(self, request: web.Request) -> web.Response:
        center = list(self.cfg.center) if self.cfg.center is not None else self.station.center()
        fence = self.station.fence
        return web.json_response(
            {
                "tiles": self.cfg.tile_template,
                "attribution": self.cfg.attribution if self.cfg.tile_template else "",
                "tiles_max_zoom": self.cfg.tiles_max_zoom,
                "station": {"name": self.station.name, "id": self.station.id},
                "replay": self.station.replay is not None,
                "center": center,
                "ws_hz": self.cfg.ws_hz,
                # the page checks a target against it before it asks to confirm, and draws it
                "fence": {"floor_m": fence.floor_m, "ceiling_m": fence.ceiling_m, "radius_m": fence.radius_m},
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
            return error_response(404, f"unknown agent {aid}")
        return web.json_response(a)

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
            body = await self._body(request)
        except CommandRefused as exc:
            return error_response(exc.status, exc.reason)
        status, out = await self.run_command(body)
        return web.json_response(out, status=status)

    async def _ack_alert_http(self, request: web.Request) -> web.Response:
        """``{"id": N}``: acknowledge alert N (the alert back; 400/404 one line);
        ``"station"``: another station's alert N, acknowledged there."""
        try:
            body = await self._body(request)
            if not isinstance(body, dict):
                raise CommandRefused(400, 'an acknowledgement is a JSON object {"id": N}')
            alert = ack_any(self.station, body.get("id"), body.get("station"))
            return web.json_response({"ok": True, "alert": alert})
        except CommandRefused as exc:
            return error_response(exc.status, exc.reason)

    async def _shelve_alert_http(self, request: web.Request) -> web.Response:
        """``{"id": N, "seconds": S}``: shelve alarm N for S seconds (0..3600; 0:
        unshelve); the alarm back; 400/404/409 one line."""
        try:
            body = await self._body(request)
            if not isinstance(body, dict):
                raise CommandRefused(400, 'a shelving is a JSON object {"id": N, "seconds": S}')
            alert = shelve_any(self.station, body.get("id"), body.get("seconds"), body.get("station"))
            return web.json_response({"ok": True, "alert": alert})
        except CommandRefused as exc:
            return error_response(exc.status, exc.reason)

    async def _replay_get(self, request: web.Request) -> web.Response:
        rp = self.station.replay
        if rp is None:
            return error_response(404, "not in replay mode (swarm gcs --replay CAPTURE)")
        return web.json_response(rp.status())

    async def _replay_post(self, request: web.Request) -> web.Response:
        rp = self.station.replay
        if rp is None:
            return error_response(404, "not in replay mode (swarm gcs --replay CAPTURE)")
        try:
            body = await self._body(request)
            if not isinstance(body, dict):
                raise CommandRefused(400, "a replay control is a JSON object")
            return web.json_response(rp.control(*replay_args(body)))
        except CommandRefused as exc:
            return error_response(exc.status, exc.reason)


__all__ = [
    "LEAFLET_DIR",
    "LOCAL_TILES",
    "MAX_WS_HZ",
    "OSM_ATTRIBUTION",
    "OSM_TILES",
    "STATIC_DIR",
    "GcsServer",
    "ServerConfig",
    "ServerError",
    "page_policy",
]
