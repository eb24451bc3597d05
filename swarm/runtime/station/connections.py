"""The station's HTTP connections under attack: a cap that keeps room for the operator,
and one rate-limited line per malformed request.

Theory of operation
-------------------
**The cap.** Every connection the station accepts costs a file descriptor, and a
process has a limit (1024 by default under systemd, soft). An attacker who opens
about 1,100 connections and sends nothing used to hold every descriptor: the
station could accept nothing more, the operator's page and commands included, and
asyncio logged a traceback for each failed accept. :class:`ConnectionLimiter` wraps
the server's protocol factory (aiohttp's low-level ``web.Server``, given to
``loop.create_server`` here instead of through a ``TCPSite``) and admits at most
``limit`` connections at once. The one over the limit makes room: the limiter
closes (resets) one *idle* connection, chosen in this order:

1. a connection that has not yet passed the guard (no request of it got past the
   Host, Origin and token checks; fetching the page's public files does not count:
   an attacker's, or a new one not yet used), from the peer holding the most
   connections (IPv6 peers by /64), the oldest first;
2. else an idle keep-alive connection of a client that did pass it, least recently
   used first (a browser opens a new one when it needs it);
3. never a connection with a request in progress (a command awaiting its answer, a
   WebSocket: the operator's live page). When every connection is busy the new one
   is closed at once.

So a flood of idle connections churns among itself: the operator's WebSocket and
requests in progress are never touched, and a new connection of the operator's
(the newest) outlives the flood's older ones, long enough to send its request. A
connection that never completes a request is also closed after the server's idle
timeout (aiohttp's keep-alive timer runs from the accept).

The limit (:func:`default_limit`) is half the soft open-file limit, at most
:data:`MAX_CONNECTIONS`: the rest stays for the station's radio, Zenoh, files and
the connections being swapped. The cap also keeps every descriptor number below
1024 in a station started with the default limit, which matters beyond HTTP: the
serial link waits on its device with ``select()``, which cannot watch a descriptor
of 1024 or more (a radio reopened after an unplug gets the lowest free number).
:func:`raise_file_limit` (called by ``swarm gcs`` at start) raises the soft limit to
the hard one (at most :data:`FILE_LIMIT_CEILING`), so Zenoh and the rest have room
too.

**Malformed requests.** aiohttp logs each request it cannot parse (a garbage request
line, a TLS hello, huge headers, bad chunking) as a traceback of some ten lines.
:class:`HttpLog` is the logger it is given instead: a malformed request is one line,
``http: malformed request from ADDR: REASON``, at most :data:`BURST` of them per
:data:`INTERVAL` seconds; the rest of the interval's are counted and summed up in one
line at its end, ``http: N more malformed requests in the last 10 s (not logged one
by one)``. The same gate takes the event loop's own errors (an accept that failed
for want of descriptors: one line, not a traceback each time). The decision is the
pure :class:`LineGate`, fed with ``now``.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import errno
import ipaddress
import logging
import resource
from collections.abc import Callable, Iterator
from typing import Any, cast

from aiohttp.http_exceptions import HttpProcessingError

log = logging.getLogger("swarm.runtime.station.server")

#: the most connections the HTTP server holds at once, whatever the file limit
MAX_CONNECTIONS = 512
#: the soft open-file limit is raised towards the hard one, up to this
FILE_LIMIT_CEILING = 65536
#: malformed-request lines per interval, then one "N more" line at its end
BURST = 5
INTERVAL = 10.0
#: an accept that failed for want of descriptors or memory
_NO_ROOM = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
#: how much of a reason a line shows
REASON_CHARS = 120


# -- the file limit -------------------------------------------------------------------------


def raise_file_limit(ceiling: int = FILE_LIMIT_CEILING) -> tuple[int, int]:
    """Raise the soft open-file limit to the hard one (at most ``ceiling``); never lowers
    it. Returns (before, after); a limit that cannot be changed is left as it is."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = ceiling if hard == resource.RLIM_INFINITY else min(hard, ceiling)
    if soft != resource.RLIM_INFINITY and soft < want:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
    return soft, resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def default_limit() -> int:
    """Half the soft open-file limit, at most :data:`MAX_CONNECTIONS`, at least 8."""
    soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return MAX_CONNECTIONS
    return max(8, min(MAX_CONNECTIONS, soft // 2))


# -- the cap ------------------------------------------------------------------------------


def peer_key(peername: Any) -> str:
    """Who a connection is from, for fairness: an IPv4 address, an IPv6 /64 (one host
    has a whole /64 to choose from), or "?"."""
    host = peername[0] if isinstance(peername, (tuple, list)) and peername else peername
    try:
        addr = ipaddress.ip_address(str(host).split("%", 1)[0])
    except ValueError:
        return "?"
    if isinstance(addr, ipaddress.IPv6Address):
        if addr.ipv4_mapped is not None:
            return str(addr.ipv4_mapped)
        return str(ipaddress.IPv6Network((addr, 64), strict=False))
    return str(addr)


class _Conn:
    __slots__ = ("busy", "peer", "proven", "transport")

    def __init__(self, transport: asyncio.Transport, peer: str) -> None:
        self.transport = transport
        self.peer = peer
        self.busy = 0  # requests in progress (a WebSocket: its whole life)
        self.proven = False  # a request of it passed the guard


class ConnectionLimiter:
    """At most ``limit`` connections, making room as the module docstring says.
    Counts in ``stats``: ``http_connections`` (open now), ``http_evicted`` (idle ones
    closed to make room), ``http_full`` (new ones closed: every connection busy)."""

    def __init__(self, limit: int, stats: dict[str, int]) -> None:
        if limit < 1:
            raise ValueError(f"connection limit {limit}: at least 1")
        self.limit = limit
        self.stats = stats
        for k in ("http_connections", "http_evicted", "http_full"):
            stats.setdefault(k, 0)
        self._conns: dict[asyncio.Transport, _Conn] = {}
        self._count: collections.Counter[str] = collections.Counter()
        # idle connections by peer, oldest first: never passed the guard / passed it
        self._fresh: dict[str, dict[_Conn, None]] = {}
        self._kept: dict[str, dict[_Conn, None]] = {}

    def __len__(self) -> int:
        return len(self._conns)

    def factory(self, make: Callable[[], asyncio.Protocol]) -> Callable[[], asyncio.Protocol]:
        """A protocol factory for ``loop.create_server``: ``make``'s protocols, admitted
        (or not) by this limiter."""
        return lambda: _Admitted(make(), self)

    # -- admission -------------------------------------------------------------------
    def admit(self, transport: asyncio.Transport) -> bool:
        """A new connection: True if it may stay (room was made if needed), False if
        it was closed (every connection busy)."""
        if len(self._conns) >= self.limit:
            victim = self._victim()
            if victim is None:
                self.stats["http_full"] += 1
                transport.abort()
                return False
            self._drop(victim)
            victim.transport.abort()
            self.stats["http_evicted"] += 1
        conn = _Conn(transport, peer_key(transport.get_extra_info("peername")))
        self._conns[transport] = conn
        self._count[conn.peer] += 1
        self._fresh.setdefault(conn.peer, {})[conn] = None
        self.stats["http_connections"] = len(self._conns)
        return True

    def release(self, transport: asyncio.Transport) -> None:
        """A connection closed (whoever closed it)."""
        conn = self._conns.get(transport)
        if conn is not None:
            self._drop(conn)

    def _drop(self, conn: _Conn) -> None:
        del self._conns[conn.transport]
        self._count[conn.peer] -= 1
        if self._count[conn.peer] <= 0:
            del self._count[conn.peer]
        self._unlist(conn)
        self.stats["http_connections"] = len(self._conns)

    def _unlist(self, conn: _Conn) -> None:
        for pool in (self._fresh, self._kept):
            idle = pool.get(conn.peer)
            if idle is not None and conn in idle:
                del idle[conn]
                if not idle:
                    del pool[conn.peer]

    def _victim(self) -> _Conn | None:
        for pool in (self._fresh, self._kept):
            if pool:
                peer = max(pool, key=lambda p: self._count[p])
                return next(iter(pool[peer]))
        return None

    # -- requests ------------------------------------------------------------------------
    @contextlib.contextmanager
    def serving(self, transport: asyncio.Transport | None, proven: bool = True) -> Iterator[None]:
        """A request that passed the guard is in progress on ``transport``: until it
        ends its connection is not idle; ``proven``: it had the token (or none is
        needed), and its connection is from then on a client's that passed the guard
        (the page's public files need no token: they prove nothing)."""
        conn = self._conns.get(transport) if transport is not None else None
        if conn is None:
            yield
            return
        conn.proven = conn.proven or proven
        conn.busy += 1
        self._unlist(conn)
        try:
            yield
        finally:
            conn.busy -= 1
            if conn.busy == 0 and self._conns.get(conn.transport) is conn:
                pool = self._kept if conn.proven else self._fresh
                pool.setdefault(conn.peer, {})[conn] = None  # the newest used, last


class _Admitted(asyncio.Protocol):
    """``inner`` (aiohttp's RequestHandler) behind the limiter's admission."""

    __slots__ = ("admitted", "inner", "limiter", "transport")

    def __init__(self, inner: asyncio.Protocol, limiter: ConnectionLimiter) -> None:
        self.inner = inner
        self.limiter = limiter
        self.admitted = False
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # a TCP server's
        if self.limiter.admit(self.transport):
            self.admitted = True
            self.inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self.inner.eof_received()

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.transport is not None:
            self.limiter.release(self.transport)
        if self.admitted:
            self.inner.connection_lost(exc)


# -- malformed requests ---------------------------------------------------------------------


class LineGate:
    """At most ``burst`` lines per ``interval`` seconds (the interval starts with its
    first line); what is held back is counted for one summary at its end. Pure: fed
    with ``now``."""

    def __init__(self, burst: int = BURST, interval: float = INTERVAL) -> None:
        self.burst = burst
        self.interval = interval
        self.end = -float("inf")  # the current interval's end
        self.shown = 0
        self.held = 0

    def note(self, now: float) -> bool:
        """One more line at ``now``: True to write it, False if held back."""
        if now >= self.end:
            self.end = now + self.interval
            self.shown = 0
        if self.shown < self.burst:
            self.shown += 1
            return True
        self.held += 1
        return False

    def summary(self) -> int:
        """The lines held back since the last summary (and none from now on)."""
        n, self.held = self.held, 0
        return n


def reason_of(exc: BaseException) -> str:
    """One short printable line from an exception's message (aiohttp's parser errors
    span several lines and quote the sender's bytes)."""
    text = exc.message if isinstance(exc, HttpProcessingError) else str(exc)
    if not isinstance(text, str) or not text.strip():
        text = type(exc).__name__
    text = " ".join(text.split())
    text = "".join(c if c.isprintable() else "?" for c in text)
    return text if len(text) <= REASON_CHARS else text[: REASON_CHARS - 3] + "..."


class HttpLog:
    """The logger given to aiohttp's request handlers (``logger=``), and the event
    loop's exception handler: a malformed request is one line, rate-limited by a
    :class:`LineGate`; counted in ``stats["http_malformed"]``. Anything else goes to
    the module's logger as it was, through the same gate."""

    def __init__(
        self,
        stats: dict[str, int],
        clock: Callable[[], float],
        burst: int = BURST,
        interval: float = INTERVAL,
    ) -> None:
        self.stats = stats
        stats.setdefault("http_malformed", 0)
        self.clock = clock
        self.gate = LineGate(burst, interval)
        self.loop: asyncio.AbstractEventLoop | None = None
        self._flush: asyncio.TimerHandle | None = None

    # -- what aiohttp calls ----------------------------------------------------------------
    def debug(self, msg: str, *args: Any, exc_info: Any = None, **kw: Any) -> None:
        if isinstance(exc_info, HttpProcessingError):  # a first request that is not HTTP
            self.malformed(_peer(args), reason_of(exc_info))
        elif log.isEnabledFor(logging.DEBUG):
            log.debug(msg, *args, exc_info=exc_info, **kw)

    def exception(self, msg: str, *args: Any, exc_info: Any = True, **kw: Any) -> None:
        if isinstance(exc_info, HttpProcessingError):
            self.malformed(_peer(args), reason_of(exc_info))
        elif self._pass():
            log.error(msg, *args, exc_info=exc_info, **kw)

    def error(self, msg: str, *args: Any, **kw: Any) -> None:
        if self._pass():
            log.error(msg, *args, **kw)

    def warning(self, msg: str, *args: Any, **kw: Any) -> None:
        if self._pass():
            log.warning(msg, *args, **kw)

    def info(self, msg: str, *args: Any, **kw: Any) -> None:
        log.info(msg, *args, **kw)

    # -- ours ------------------------------------------------------------------------------
    def malformed(self, peer: str, reason: str) -> None:
        """One malformed request from ``peer``: its line, if the gate lets it through."""
        self.stats["http_malformed"] += 1
        if self._pass():
            log.warning("http: malformed request from %s: %s", peer, reason)

    def loop_exception(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """The event loop's exception handler: an accept that failed for want of
        descriptors or memory is one line; anything else as asyncio would, rate-limited."""
        exc = context.get("exception")
        if isinstance(exc, OSError) and exc.errno in _NO_ROOM:
            if self._pass():
                log.warning("http: cannot accept a connection: %s (retrying)", exc.strerror or exc)
        elif self._pass():
            loop.default_exception_handler(context)

    def _pass(self) -> bool:
        if self.gate.note(self.clock()):
            return True
        if self._flush is None and self.loop is not None:
            delay = max(0.0, self.gate.end - self.clock())
            self._flush = self.loop.call_later(delay, self._summary)
        return False

    def _summary(self) -> None:
        self._flush = None
        n = self.gate.summary()
        if n:
            log.warning(
                "http: %d more malformed requests or errors in the last %g s (not logged one by one)",
                n,
                self.gate.interval,
            )

    def close(self) -> None:
        """Write the pending summary now (the server is stopping)."""
        if self._flush is not None:
            self._flush.cancel()
            self._summary()


def _peer(args: tuple[Any, ...]) -> str:
    """The sender named in aiohttp's "Error handling request from %s" arguments."""
    return str(args[0])[:64] if args else "?"


__all__ = [
    "BURST",
    "FILE_LIMIT_CEILING",
    "INTERVAL",
    "MAX_CONNECTIONS",
    "ConnectionLimiter",
    "HttpLog",
    "LineGate",
    "default_limit",
    "peer_key",
    "raise_file_limit",
    "reason_of",
]
