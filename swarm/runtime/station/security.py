"""Who may use the ground station's server, and what it accepts from them.

Theory of operation
-------------------
Every request passes :meth:`Guard.middleware` before any route, which checks, in
this order (docs/security.md):

1. ``Host`` must name this station: a localhost name, a loopback address, the
   listening address (any address when listening on all of them) or a name the
   operator allows (``allow_hosts``). A DNS-rebound page always comes under a
   foreign *name*: 403.
2. ``Origin``, when the browser sends one (every cross-origin request, every POST,
   every WebSocket handshake), must be this very origin (``http://`` + the Host);
   ``Sec-Fetch-Site: cross-site|same-site`` is refused too, except for the page
   and its files (a link to the station may be followed): 403.
3. The token, when the station has one (always when it listens beyond loopback;
   generated with :mod:`secrets` unless given): ``Authorization: Bearer`` (the page's
   requests), the WebSocket subprotocol ``token.<TOKEN>`` beside ``swarm-gcs`` (a
   browser cannot set headers on a WebSocket), or ``?token=`` (tools), compared in
   constant time; without it every route answers 401 but the page itself (``GET /``,
   ``/static/``, ``/vendor/``: files that hold nothing of the swarm). The token is
   never a cookie: browsers send a host's cookies to every port of it, so every other
   web service on the station's machine would get it. The page keeps it in its
   origin's storage (scheme, host and port: this station's alone) and asks for it
   when the API refuses (static/token.js). A cookie an earlier version set is
   deleted when the browser shows it.

Then what a client sends is read by the functions here, each assuming a hostile
sender and refusing with a :class:`~swarm.core.station.core.CommandRefused` (a status and
a one-line reason):

4. Bodies (:func:`read_json`): ``application/json`` (UTF-8) only (415), at most
   64 KiB (413), read within ``body_timeout`` (408). JSON is parsed by
   :func:`parse_json`: deep nesting, over-long integers and bad UTF-8 are 400 with a
   one-line reason; NaN, infinities and huge integers parse and are refused by the
   argument checks (so a WebSocket answer still carries the request's id).
5. A replay control's arguments (:func:`replay_args`), a WebSocket request's id
   (:func:`ws_id`), a file path under a served folder (:func:`safe_file`: no
   traversal, no symlink out).

Used by :mod:`swarm.runtime.station.server` and
:mod:`swarm.runtime.station.websocket`.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import json
import math
import re
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError

from swarm.core.station.commands import CommandRefused

MAX_BODY = 64 * 1024  # a request body or a WebSocket message
MAX_WS_FRAME = 1024 * 1024  # beyond this the WebSocket closes (1009); up to it: a 413 answer
MAX_DEPTH = 16  # JSON nesting: a command is 1 deep
MAX_INT_DIGITS = 1000  # longer integers are malformed (Python refuses 4300 and more anyway)
MAX_ID = 64  # a WebSocket request's id: a string this long, or an integer
#: a token travels in a URL and a WebSocket subprotocol: unreserved URL characters only
TOKEN_RE = re.compile(r"[A-Za-z0-9._~-]{16,256}")
TOKEN_RULE = "16 to 256 characters of A-Z a-z 0-9 . _ ~ -"
HOST_RE = re.compile(r"[a-z0-9]([a-z0-9-]*[a-z0-9])?(\.[a-z0-9]([a-z0-9-]*[a-z0-9])?)*")
WILDCARDS = ("", "0.0.0.0", "::")
#: a request's key: it passed rule 3 (the page's files pass without a token)
AUTHORIZED = web.RequestKey("gcs_authorized", bool)
#: the page's WebSocket subprotocol, and the prefix of the one that carries the token
WS_PROTOCOL = "swarm-gcs"
WS_TOKEN_PREFIX = "token."


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


def error_response(status: int, reason: str) -> web.Response:
    resp = web.json_response({"error": reason}, status=status)
    if status == 401:
        resp.headers["WWW-Authenticate"] = 'Bearer realm="swarm gcs"'
    return resp


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


async def read_json(request: web.Request, body_timeout: float) -> Any:
    """The request's JSON body (rule 4).

    Raises:
        CommandRefused: 415 not ``application/json`` (UTF-8), 413 over
            :data:`MAX_BODY`, 400 not UTF-8 or malformed (:func:`parse_json`);
            :class:`BodyBroken`: 408 not in within ``body_timeout``, 400 cut off.
    """
    charset = (request.charset or "utf-8").lower()
    if request.content_type != "application/json" or charset not in ("utf-8", "utf8"):
        raise CommandRefused(415, "send the body as Content-Type: application/json (UTF-8)")
    if request.content_length is not None and request.content_length > MAX_BODY:
        raise CommandRefused(413, f"request body too large (at most {MAX_BODY // 1024} KiB)")
    try:
        raw = await asyncio.wait_for(request.read(), body_timeout)
    except TimeoutError:
        raise BodyBroken(408, f"the body did not arrive in {body_timeout:g} s") from None
    except (ConnectionError, web.RequestPayloadError, HttpProcessingError) as exc:
        raise BodyBroken(400, "the body could not be read: " + " ".join(str(exc).split())[:120]) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise CommandRefused(400, "malformed JSON: the body is not UTF-8 text") from None
    return parse_json(text)


class BodyBroken(CommandRefused):
    """A body that did not arrive whole (408: not in time, which is also what bad
    chunking after the headers comes to; 400: the connection lost): a malformed
    request, logged as one (:class:`swarm.runtime.station.connections.HttpLog`)."""


class Guard:
    """Rules 1 to 3 for one server: its listening ``host``, the ``allow_hosts``, its
    ``token`` (None: none needed) and the name of the cookie earlier versions kept it
    in (asked at each request: the port is known once the server listens), deleted
    wherever a browser still sends it. Refusals are counted in ``stats["http_refused"]``."""

    def __init__(
        self,
        host: str,
        allow_hosts: tuple[str, ...],
        token: str | None,
        cookie_name: Callable[[], str],
        stats: dict[str, int],
    ) -> None:
        self.host = host
        self.allow_hosts = allow_hosts
        self.token = token
        self.cookie_name = cookie_name
        self.stats = stats

    def host_refusal(self, request: web.Request) -> tuple[int, str] | None:
        """Why the request's Host is not this station's, or None (rule 1)."""
        header = request.headers.get("Host", "")
        parsed = split_host(header)
        if parsed is None:
            return 400, "a Host header naming this station is needed"
        name = parsed[0]
        if name in self.allow_hosts or is_loopback(name):
            return None
        bound = self.host.strip("[]").lower()
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

    def origin_refusal(self, request: web.Request, page: bool) -> str | None:
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

    def token_source(self, request: web.Request) -> str | None:
        """Where the request's valid token came from ("header", "protocol", "query"), or
        None; compared in constant time (rule 3)."""
        want = (self.token or "").encode()
        candidates: list[tuple[str, str]] = []
        auth = request.headers.get("Authorization", "")
        if auth[:7].lower() == "bearer ":
            candidates.append(("header", auth[7:].strip()))
        if request.path == "/ws":
            for proto in request.headers.get("Sec-WebSocket-Protocol", "").split(",")[:8]:
                proto = proto.strip()
                if proto.startswith(WS_TOKEN_PREFIX):
                    candidates.append(("protocol", proto[len(WS_TOKEN_PREFIX) :]))
        query = request.query.get("token")
        if query is not None:
            candidates.append(("query", query))
        for source, given in candidates:
            if hmac.compare_digest(given.encode("utf-8", "replace"), want):
                return source
        return None

    @web.middleware
    async def middleware(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        refused = self.host_refusal(request)
        if refused is not None:
            self.stats["http_refused"] += 1
            return error_response(*refused)
        page = request.method in ("GET", "HEAD") and (
            request.path == "/" or request.path.startswith(("/static/", "/vendor/"))
        )
        why = self.origin_refusal(request, page)
        if why is not None:
            self.stats["http_refused"] += 1
            return error_response(403, why)
        authorized = self.token is None or self.token_source(request) is not None
        request[AUTHORIZED] = authorized  # the connection's owner has the token (or none is needed)
        if not authorized and not page:
            self.stats["http_refused"] += 1
            return error_response(
                401,
                "this station needs its token: open the address it printed "
                "(.../?token=...) or send Authorization: Bearer TOKEN",
            )
        resp = await handler(request)
        legacy = self.cookie_name()
        if legacy in request.cookies and not resp.prepared:
            resp.del_cookie(legacy, path="/")  # an earlier version's: every port of the host got it
        return resp
