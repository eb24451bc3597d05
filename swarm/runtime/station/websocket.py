"""The ground station's WebSocket: state pushes as deltas, events, commands and replay controls.

Theory of operation
-------------------
:class:`WsHub` serves ``GET /ws`` for :class:`swarm.runtime.station.server.GcsServer`, on
the server's asyncio loop.

State: at ``ws_hz`` the hub takes one snapshot of the station (a *push*, numbered
``seq`` 1, 2, ...) and builds one delta from the previous push
(:func:`swarm.core.station.delta.build`), one text shared by every client:
``{"type": "delta", "seq": N, "base": N - 1, ...}``. A client that is in step (it
holds push N - 1) gets the delta; any other gets the whole state of push N,
``{"type": "state", "seq": N, ...the /api/state body}``, and is in step from then
on. A client gets the whole state of the newest push at once when it connects and
whenever it sends ``{"type": "state"}`` (a page that sees a gap in ``seq``, or a
delta that does not fit, asks so). The whole state of a push is formatted once,
when a client first needs it. Nothing is pushed while no client is connected (the
next client starts a new push at once).

Events: each station event as it happens (:meth:`WsHub.on_event`, called on the
station's thread, hands it to the loop) as ``{"type": "event", "event": ...}``; the
same events also travel in the state, so a page that misses one finds it there.

Messages from a client are JSON objects with a ``type``: ``command`` (answered by
a ``command_result`` with the request's ``id``, the command awaited on its own
task), ``replay`` (a replay control; 409 when not in replay mode), ``state`` and
``ack_alert`` (``{"type": "ack_alert", "id": N}``, answered ``alert_acked`` with the
alert; with ``"station"``, another station's alert, acknowledged there).
A bad message (binary, too large, malformed, an unknown type, a bad id) gets
``{"type": "error", "status", "reason", "id"?}`` and the connection stays open; a
message that fails unexpectedly answers 500 and logs the traceback.

A slow client: each client has its own queue, written by its own task. A queue
over :data:`QUEUE_MESSAGES` texts or :data:`QUEUE_BYTES` bytes is emptied and the
client falls out of step: its next push is the whole state (what it missed is in
there; a command answer it had not taken yet is lost, the command's outcome is in
the events). A request for the whole state while one is still queued for that
client is not queued again, and a client that holds the newest push gets the
whole state at the next push: a resync storm costs at most two whole states per
push to the client that makes it. A client that does not
take a text within :data:`SEND_TIMEOUT` seconds is dropped. So a client that never
reads holds at most one bounded queue and never slows the others.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from aiohttp import WSMsgType, web

from swarm.core.station.commands import CommandRefused
from swarm.core.station.delta import build
from swarm.core.station.federation import ack_any
from swarm.core.station.rows import EventRow, Snapshot
from swarm.runtime.station.security import MAX_BODY, MAX_WS_FRAME, WS_PROTOCOL, parse_json, replay_args, ws_id

if TYPE_CHECKING:
    from swarm.runtime.station.served import ServedStation

log = logging.getLogger(__name__)

QUEUE_MESSAGES = 64
QUEUE_BYTES = 2 * 1024 * 1024
SEND_TIMEOUT = 10.0


class _Client:
    """One WebSocket client: its queue of texts, written by its own task."""

    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.queue: deque[str] = deque()
        self.queued_bytes = 0
        self.wake = asyncio.Event()
        self.seq = 0  # the push this client holds (0: none, the next is the whole state)
        self.full_queued = False  # a whole state waits in the queue
        self.full_seq = 0  # the push whose whole state it was last given
        self.closed = False


class WsHub:
    """The WebSocket clients of one server. ``run_command`` validates, sends and
    awaits one command; ``spawn`` runs a coroutine on the server's loop as a task it
    cancels at shutdown; ``stats`` is the server's."""

    def __init__(
        self,
        station: ServedStation,
        ws_hz: float,
        stats: dict[str, int],
        run_command: Callable[[Any], Awaitable[tuple[int, dict[str, Any]]]],
        spawn: Callable[[Awaitable[Any]], None],
    ) -> None:
        self.station = station
        self.ws_hz = ws_hz
        self.stats = stats
        for k in ("ws_pushes", "ws_full_states", "ws_overflows", "ws_bytes"):
            stats.setdefault(k, 0)
        self._run_command = run_command
        self._spawn = spawn
        self._clients: dict[web.WebSocketResponse, _Client] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._seq = 0
        self._base: Snapshot | None = None  # the newest push's state
        self._base_text: str | None = None  # ... as a whole-state message, once needed
        self._replay_text: str | None = None  # the replay status sent with it

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
        # the page offers "swarm-gcs" and "token.<TOKEN>" (its token: security.py); the
        # answer names the first, never the token
        ws = web.WebSocketResponse(heartbeat=30.0, max_msg_size=MAX_WS_FRAME, protocols=(WS_PROTOCOL,))
        await ws.prepare(request)
        c = _Client(ws)
        self._clients[ws] = c
        self.stats["ws_clients"] = len(self._clients)
        writer = asyncio.ensure_future(self._writer(c))
        try:
            try:
                self._send_full(c)
            except Exception:  # the station could not give its state: the next push tries again
                log.exception("gcs server: snapshot failed")
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    try:
                        await self._message(c, msg.data)
                    except Exception as exc:  # a bug: answer, log, keep the connection
                        log.exception("gcs server: WebSocket message failed")
                        self._enqueue(c, self._error(500, f"internal error: {type(exc).__name__}"))
                elif msg.type == WSMsgType.BINARY:
                    self._enqueue(c, self._error(400, "send JSON text, not binary"))
                elif msg.type == WSMsgType.ERROR:
                    break
                if c.closed:
                    break
        finally:
            c.closed = True
            c.wake.set()
            self._clients.pop(ws, None)
            self.stats["ws_clients"] = len(self._clients)
            writer.cancel()
            with contextlib.suppress(BaseException):
                await writer
            if not self._clients:
                self._base = self._base_text = None  # nobody to push to: hold nothing
        return ws

    @staticmethod
    def _error(status: int, reason: str, mid: Any = None) -> str:
        d: dict[str, Any] = {"type": "error", "status": status, "reason": reason}
        if mid is not None:
            d["id"] = mid
        return json.dumps(d)

    async def _message(self, c: _Client, text: str) -> None:
        if len(text) > MAX_BODY:
            self._enqueue(c, self._error(413, f"message too large (at most {MAX_BODY // 1024} KiB)"))
            return
        try:
            obj = parse_json(text)
            if not isinstance(obj, dict):
                raise CommandRefused(400, "a message is a JSON object with a 'type'")
            mid = ws_id(obj)
        except CommandRefused as exc:
            self._enqueue(c, self._error(exc.status, exc.reason))
            return
        mtype = obj.get("type")
        if mtype == "command":
            self._spawn(self._command(c, obj))
        elif mtype == "replay":
            self._replay(c, obj, mid)
        elif mtype == "state":
            if self._base is not None and self._seq in (c.seq, c.full_seq):
                # it has this push (or it is queued), or had its whole state already: the
                # whole state at the next push, so a storm of requests gets at most one a push
                c.seq = 0
            else:
                self._send_full(c)
        elif mtype == "ack_alert":
            self._ack_alert(c, mid, obj.get("station"))
        else:
            shown = (
                repr(mtype[:24])
                if isinstance(mtype, str)
                else "null"
                if mtype is None
                else f"of type {type(mtype).__name__}"
            )
            self._enqueue(
                c, self._error(400, f"unknown message type {shown}: command, replay, state or ack_alert", mid)
            )

    def _ack_alert(self, c: _Client, mid: Any, station: Any) -> None:
        try:
            alert = ack_any(self.station, mid, station)  # the request's id is the alert's
        except CommandRefused as exc:
            self._enqueue(c, self._error(exc.status, exc.reason, mid))
            return
        self._enqueue(c, json.dumps({"type": "alert_acked", "id": mid, "alert": alert}))

    def _replay(self, c: _Client, obj: dict[str, Any], mid: Any) -> None:
        rp = self.station.replay
        if rp is None:
            self._enqueue(c, self._error(409, "not in replay mode", mid))
            return
        try:
            st = rp.control(*replay_args(obj))
        except CommandRefused as exc:
            self._enqueue(c, self._error(exc.status, exc.reason, mid))
            return
        self._enqueue(c, json.dumps({"type": "replay", "id": mid, **st}))

    async def _command(self, c: _Client, obj: dict[str, Any]) -> None:
        body = {k: v for k, v in obj.items() if k not in ("type", "id")}
        status, out = await self._run_command(body)
        self._enqueue(c, json.dumps({"type": "command_result", "id": ws_id(obj), "status": status, **out}))

    # -- state pushes ---------------------------------------------------------------
    def _send_full(self, c: _Client) -> None:
        """The whole state of the newest push to ``c`` (a new push if there is none)."""
        if self._base is None:
            self.push()  # sends ``c`` the whole state: it is not in step
            return
        if c.full_queued:
            return  # one is on its way: a resync storm costs nothing
        if self._base_text is None:
            self._base_text = json.dumps({"type": "state", "seq": self._seq, **self._base})
        self._enqueue(c, self._base_text, full=True)
        if self._replay_text is not None:
            self._enqueue(c, self._replay_text)
        c.seq = c.full_seq = self._seq

    def push(self) -> None:
        """One push: a new snapshot, its delta to the clients in step, the whole state
        to the others."""
        new = self.station.snapshot()
        rp = self.station.replay
        if rp is not None:
            new["replay"] = rp.status()
        old, self._base, self._base_text = self._base, new, None
        self._seq += 1
        self.stats["ws_pushes"] += 1
        self._replay_text = json.dumps({"type": "replay", **new["replay"]}) if rp is not None else None
        delta_text = None
        if old is not None:
            d = {"type": "delta", "seq": self._seq, "base": self._seq - 1, **build(old, new)}
            delta_text = json.dumps(d, separators=(",", ":"))
        for c in list(self._clients.values()):
            if delta_text is not None and c.seq == self._seq - 1:
                self._enqueue(c, delta_text)
                if self._replay_text is not None:
                    self._enqueue(c, self._replay_text)
                c.seq = self._seq
            else:
                self._send_full(c)

    def _enqueue(self, c: _Client, text: str, *, full: bool = False) -> None:
        if c.closed:
            return
        if len(c.queue) >= QUEUE_MESSAGES or c.queued_bytes + len(text) > QUEUE_BYTES:
            # a client that does not keep up: forget what it missed, resync it at the next push
            self.stats["ws_overflows"] += 1
            c.queue.clear()
            c.queued_bytes = 0
            c.seq = 0
            c.full_queued = False
            if not full:
                return
        c.queue.append(text)
        c.queued_bytes += len(text)
        if full:
            c.full_queued = True
            self.stats["ws_full_states"] += 1
        c.wake.set()

    async def _writer(self, c: _Client) -> None:
        ws = c.ws
        while not c.closed:
            await c.wake.wait()
            c.wake.clear()
            while c.queue and not c.closed:
                text = c.queue.popleft()
                c.queued_bytes -= len(text)
                if text.startswith('{"type": "state"'):
                    c.full_queued = False
                try:
                    await asyncio.wait_for(ws.send_str(text), SEND_TIMEOUT)
                except (ConnectionError, RuntimeError, TimeoutError):
                    self.stats["ws_send_errors"] += 1
                    c.closed = True
                    with contextlib.suppress(Exception):
                        await ws.close()
                    return
                self.stats["ws_sent"] += 1
                self.stats["ws_bytes"] += len(text)

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
                self.push()
            except Exception:
                log.exception("gcs server: snapshot failed")

    def on_event(self, event: EventRow) -> None:
        """Station thread: hand the event to the loop."""
        loop = self._loop
        if loop is None:
            return
        text = json.dumps({"type": "event", "event": event})
        with contextlib.suppress(RuntimeError):  # the loop is closing
            loop.call_soon_threadsafe(self._push_event, text)

    def _push_event(self, text: str) -> None:
        for c in list(self._clients.values()):
            self._enqueue(c, text)
