"""The ground station's WebSocket: state pushes, events, commands and replay controls.

Theory of operation
-------------------
:class:`WsHub` serves ``GET /ws`` for :class:`swarm.runtime.server.GcsServer`, on
the server's asyncio loop. A client gets the state at once, then the state pushed
at ``ws_hz`` (one JSON text built per push and shared by all clients) and each
station event as it happens (:meth:`WsHub.on_event`, called on the station's
thread, hands it to the loop). A client sends JSON objects with a ``type``:
``command`` (answered by a ``command_result`` with the request's ``id``, the
command awaited on its own task), ``replay`` (a replay control; 409 when not in
replay mode), ``state`` and ``ack_alert`` (``{"type": "ack_alert", "id": N}``, answered
``alert_acked`` with the alert). A bad message (binary, too large, malformed, an
unknown type, a bad id) gets ``{"type": "error", "status", "reason", "id"?}`` and
the connection stays open; a message that fails unexpectedly answers 500 and logs
the traceback. A client that does not take a text within 10 s is dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from aiohttp import WSMsgType, web

from swarm.core.station import CommandRefused
from swarm.runtime.security import MAX_BODY, MAX_WS_FRAME, parse_json, replay_args, ws_id

if TYPE_CHECKING:
    from swarm.runtime.server import StationView

log = logging.getLogger(__name__)


class WsHub:
    """The WebSocket clients of one server. ``run_command`` validates, sends and
    awaits one command; ``spawn`` runs a coroutine on the server's loop as a task it
    cancels at shutdown; ``stats`` is the server's."""

    def __init__(
        self,
        station: StationView,
        ws_hz: float,
        stats: dict[str, int],
        run_command: Callable[[Any], Awaitable[tuple[int, dict[str, Any]]]],
        spawn: Callable[[Awaitable[Any]], None],
    ) -> None:
        self.station = station
        self.ws_hz = ws_hz
        self.stats = stats
        self._run_command = run_command
        self._spawn = spawn
        self._clients: set[web.WebSocketResponse] = set()
        self._loop: asyncio.AbstractEventLoop | None = None

    def attach(self, loop: asyncio.AbstractEventLoop) -> None:
        """Take the station's events from now on, onto ``loop``."""
        self._loop = loop
        self.station.add_listener(self.on_event)

    def detach(self) -> None:
        """Take no more events (the server is stopping). Safe twice, from any thread."""
        self._loop = None
        self.station.remove_listener(self.on_event)

    async def close_clients(self) -> None:
        """Close every client (1001: going away)."""
        for ws in list(self._clients):
            with contextlib.suppress(Exception):
                await ws.close(code=1001, message=b"station stopping")

    async def handle(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(heartbeat=30.0, max_msg_size=MAX_WS_FRAME)
        await ws.prepare(request)
        self._clients.add(ws)
        self.stats["ws_clients"] = len(self._clients)
        try:
            await self._send(ws, self._state_texts())
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    try:
                        await self._message(ws, msg.data)
                    except Exception as exc:  # a bug: answer, log, keep the connection
                        log.exception("gcs server: WebSocket message failed")
                        await self._send(ws, [self._error(500, f"internal error: {type(exc).__name__}")])
                elif msg.type == WSMsgType.BINARY:
                    await self._send(ws, [self._error(400, "send JSON text, not binary")])
                elif msg.type == WSMsgType.ERROR:
                    break
        finally:
            self._clients.discard(ws)
            self.stats["ws_clients"] = len(self._clients)
        return ws

    @staticmethod
    def _error(status: int, reason: str, mid: Any = None) -> str:
        d: dict[str, Any] = {"type": "error", "status": status, "reason": reason}
        if mid is not None:
            d["id"] = mid
        return json.dumps(d)

    async def _message(self, ws: web.WebSocketResponse, text: str) -> None:
        if len(text) > MAX_BODY:
            await self._send(ws, [self._error(413, f"message too large (at most {MAX_BODY // 1024} KiB)")])
            return
        try:
            obj = parse_json(text)
            if not isinstance(obj, dict):
                raise CommandRefused(400, "a message is a JSON object with a 'type'")
            mid = ws_id(obj)
        except CommandRefused as exc:
            await self._send(ws, [self._error(exc.status, exc.reason)])
            return
        mtype = obj.get("type")
        if mtype == "command":
            self._spawn(self._command(ws, obj))
        elif mtype == "replay":
            await self._replay(ws, obj, mid)
        elif mtype == "state":
            await self._send(ws, self._state_texts())
        elif mtype == "ack_alert":
            await self._ack_alert(ws, obj, mid)
        else:
            shown = (
                repr(mtype[:24])
                if isinstance(mtype, str)
                else "null"
                if mtype is None
                else f"of type {type(mtype).__name__}"
            )
            await self._send(
                ws,
                [self._error(400, f"unknown message type {shown}: command, replay, state or ack_alert", mid)],
            )

    async def _ack_alert(self, ws: web.WebSocketResponse, obj: dict[str, Any], mid: Any) -> None:
        try:
            alert = self.station.ack_alert(mid)  # the request's id is the alert's
        except CommandRefused as exc:
            await self._send(ws, [self._error(exc.status, exc.reason, mid)])
            return
        await self._send(ws, [json.dumps({"type": "alert_acked", "id": mid, "alert": alert})])

    async def _replay(self, ws: web.WebSocketResponse, obj: dict[str, Any], mid: Any) -> None:
        rp = self.station.replay
        if rp is None:
            await self._send(ws, [self._error(409, "not in replay mode", mid)])
            return
        try:
            st = rp.control(*replay_args(obj))
        except CommandRefused as exc:
            await self._send(ws, [self._error(exc.status, exc.reason, mid)])
            return
        await self._send(ws, [json.dumps({"type": "replay", "id": mid, **st})])

    async def _command(self, ws: web.WebSocketResponse, obj: dict[str, Any]) -> None:
        body = {k: v for k, v in obj.items() if k not in ("type", "id")}
        status, out = await self._run_command(body)
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

    async def broadcast(self) -> None:
        """Push the state at ``ws_hz`` for ever (a task of the server's)."""
        period = 1.0 / self.ws_hz
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

    def on_event(self, event: dict[str, Any]) -> None:
        """Station thread: hand the event to the loop."""
        loop = self._loop
        if loop is None:
            return
        text = json.dumps({"type": "event", "event": event})
        with contextlib.suppress(RuntimeError):  # the loop is closing
            loop.call_soon_threadsafe(self._push, text)

    def _push(self, text: str) -> None:
        for ws in list(self._clients):
            self._spawn(self._send(ws, [text]))
