"""The ground station's HTTP + WebSocket server (aiohttp, on its own thread).

Theory of operation
-------------------
:class:`GcsServer` serves one *station view*: the live :class:`~swarm.gcs.station.Station`
or a :class:`~swarm.gcs.replay.ReplayStation`. Both give thread-safe snapshots
(``snapshot()``, ``agent(id)``), commands as futures (``submit(spec)``) and an event
feed (``add_listener``). The server runs an asyncio loop on its own thread;
:meth:`GcsServer.start` returns once the socket listens (or raises
:class:`ServerError`, e.g. the port is taken).

Routes (README, "Ground station", documents the bodies):

* ``GET /``, ``/static/<path>`` (``swarm/gcs/static``), ``/vendor/leaflet/<path>``
  (``node_modules/leaflet/dist``), ``/tiles/{z}/{x}/{y}.png`` (``--tiles-dir``);
* ``GET /api/config``, ``/api/state``, ``/api/agents/<id>``; ``POST /api/command``;
  ``GET|POST /api/replay`` (replay mode);
* ``GET /ws``: the state pushed at ``ws_hz``, events as they happen, commands and
  replay controls from the client.

Every error is a JSON object ``{"error": reason}`` with a 4xx/5xx status; a handler
that fails unexpectedly answers 500 with a reason and logs the traceback, which
never reaches the client. One state JSON text is built per push and shared by all
WebSocket clients.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import threading
from collections.abc import Awaitable, Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from aiohttp import WSMsgType, web

from swarm.errors import SwarmError
from swarm.gcs.station import CommandRefused, CommandSpec, parse_command

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
REPO_DIR = Path(__file__).resolve().parents[2]
LEAFLET_DIR = REPO_DIR / "node_modules" / "leaflet" / "dist"
OSM_TILES = "https://tile.openstreetmap.org/{z}/{x}/{y}.png"
OSM_ATTRIBUTION = "&copy; <a href=\"https://www.openstreetmap.org/copyright\">OpenStreetMap</a> contributors"
LOCAL_TILES = "/tiles/{z}/{x}/{y}.png"
MAX_WS_HZ = 10.0


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


@dataclass
class ServerConfig:
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

    def __post_init__(self) -> None:
        if not (math.isfinite(self.ws_hz) and 0 < self.ws_hz <= MAX_WS_HZ):
            raise ValueError(f"ws_hz {self.ws_hz}: (0, {MAX_WS_HZ:g}] pushes per second")

    @property
    def tile_template(self) -> str | None:
        return LOCAL_TILES if self.tiles_dir is not None else self.tiles


def _error(status: int, reason: str) -> web.Response:
    return web.json_response({"error": reason}, status=status)


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


class GcsServer:
    """The HTTP + WebSocket server of one station view. See the module docstring."""

    def __init__(self, station: StationView, config: ServerConfig | None = None) -> None:
        self.station = station
        self.cfg = config or ServerConfig()
        self.port = self.cfg.port
        self.stats = {"ws_clients": 0, "ws_sent": 0, "ws_send_errors": 0, "http_errors": 0}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._clients: set[web.WebSocketResponse] = set()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._stopped = False

    @property
    def url(self) -> str:
        host = self.cfg.host
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}/"

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
        app = web.Application(middlewares=[self._errors], client_max_size=64 * 1024)
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
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
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

    def _spawn(self, coro: Awaitable[Any]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # -- errors -------------------------------------------------------------------
    @web.middleware
    async def _errors(self, request: web.Request,
                      handler: Callable[[web.Request], Awaitable[web.StreamResponse]]) -> web.StreamResponse:
        try:
            return await handler(request)
        except web.HTTPException as exc:
            if exc.status < 400:
                raise
            self.stats["http_errors"] += 1
            reason = {404: f"not found: {request.path}",
                      405: f"method {request.method} not allowed on {request.path}",
                      413: "request body too large"}.get(exc.status, exc.reason)
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
        return await self._file(self.cfg.leaflet_dir, request.match_info["path"],
                                "Leaflet file (install it with the set-up: npm ci)")

    async def _tile(self, request: web.Request) -> web.StreamResponse:
        if self.cfg.tiles_dir is None:
            return _error(404, "no tile folder: start the station with --tiles-dir DIR")
        m = request.match_info
        return await self._file(self.cfg.tiles_dir, f"{int(m['z'])}/{int(m['x'])}/{int(m['y'])}.png",
                                "tile")

    # -- API -----------------------------------------------------------------------
    async def _config(self, request: web.Request) -> web.Response:
        center = list(self.cfg.center) if self.cfg.center is not None else self.station.center()
        return web.json_response({
            "tiles": self.cfg.tile_template,
            "attribution": self.cfg.attribution if self.cfg.tile_template else "",
            "station": {"name": self.station.name, "id": self.station.id},
            "replay": self.station.replay is not None,
            "center": center,
            "ws_hz": self.cfg.ws_hz,
        })

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
        raw = await request.read()
        try:
            return json.loads(raw)
        except ValueError as exc:
            raise CommandRefused(400, f"malformed JSON: {exc}") from None

    async def run_command(self, body: Any) -> tuple[int, dict[str, Any]]:
        """Validate, send and await one command: (status, body)."""
        try:
            spec = parse_command(body)
            fut = self.station.submit(spec)
        except CommandRefused as exc:
            return exc.status, {"ok": False, "error": exc.reason}
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
            return web.json_response(rp.control(body.get("action"), body.get("value")))
        except CommandRefused as exc:
            return _error(exc.status, exc.reason)

    # -- WebSocket -------------------------------------------------------------------
    async def _ws(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(heartbeat=30.0, max_msg_size=64 * 1024)
        await ws.prepare(request)
        self._clients.add(ws)
        self.stats["ws_clients"] = len(self._clients)
        try:
            await self._send(ws, self._state_texts())
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await self._ws_message(ws, msg.data)
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
        try:
            obj = json.loads(text)
        except ValueError as exc:
            await self._send(ws, [self._ws_error(400, f"malformed JSON: {exc}")])
            return
        if not isinstance(obj, dict):
            await self._send(ws, [self._ws_error(400, "a message is a JSON object with a 'type'")])
            return
        mtype, mid = obj.get("type"), obj.get("id")
        if mtype == "command":
            self._spawn(self._ws_command(ws, obj))
        elif mtype == "replay":
            rp = self.station.replay
            if rp is None:
                await self._send(ws, [self._ws_error(409, "not in replay mode", mid)])
                return
            try:
                st = rp.control(obj.get("action"), obj.get("value"))
            except CommandRefused as exc:
                await self._send(ws, [self._ws_error(exc.status, exc.reason, mid)])
                return
            await self._send(ws, [json.dumps({"type": "replay", "id": mid, **st})])
        elif mtype == "state":
            await self._send(ws, self._state_texts())
        else:
            await self._send(ws, [self._ws_error(
                400, f"unknown message type {mtype!r}: command, replay or state", mid)])

    async def _ws_command(self, ws: web.WebSocketResponse, obj: dict[str, Any]) -> None:
        body = {k: v for k, v in obj.items() if k not in ("type", "id")}
        status, out = await self.run_command(body)
        await self._send(ws, [json.dumps({"type": "command_result", "id": obj.get("id"),
                                          "status": status, **out})])

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


__all__ = ["LEAFLET_DIR", "LOCAL_TILES", "OSM_ATTRIBUTION", "OSM_TILES", "STATIC_DIR", "GcsServer",
           "ServerConfig", "ServerError", "StationView", "safe_file"]
