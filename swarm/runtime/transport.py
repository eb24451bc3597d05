"""The swarm's key space on Zenoh: one session per agent, a small typed API.

Theory of operation
-------------------
Keys (the paper's topics, DESIGN.md section 4):

==========================  ==============================================
``swarm/advertize``         Advertize: an agent announces name and id
``swarm/GSAdvertize``       GSAdvertize: the ground station announces itself
``swarm/<name>``            P2P messages to agent ``<name>`` (its inbox)
``swarm/<name>/pose``       the agent's pose stream
``swarm/<name>/state``      the agent's protocol state
==========================  ==============================================

Payloads are the compact messages of :mod:`swarm.core.messages`. Agents connect
either through Zenoh's own network over IP (peer mode, explicit endpoints,
multicast scouting off by default) or through the radio bridge
(:mod:`swarm.runtime.bridge`), which carries the same keys over MAVLink TUNNEL frames.
Callbacks run on Zenoh's threads; a payload that does not decode is counted and
dropped, never raised into Zenoh.
"""

from __future__ import annotations

import json
import re
import threading
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from swarm.core.messages import (
    Advertize,
    AgentState,
    GSAdvertize,
    Message,
    PoseReport,
    check_name,
    decode,
    encode,
)
from swarm.errors import DecodeError, TransportError

PREFIX = "swarm"
KEY_ADVERTIZE = f"{PREFIX}/advertize"
KEY_GS_ADVERTIZE = f"{PREFIX}/GSAdvertize"
RESERVED = {"advertize", "GSAdvertize"}


def inbox_key(name: str) -> str:
    return f"{PREFIX}/{name}"


def pose_key(name: str) -> str:
    return f"{PREFIX}/{name}/pose"


def state_key(name: str) -> str:
    return f"{PREFIX}/{name}/state"


def session_config(
    listen: Sequence[str] = (), connect: Sequence[str] = (), *, scouting: bool = False
) -> zenoh.Config:
    """A peer-mode Zenoh config with explicit endpoints (``tcp/127.0.0.1:7447``)."""
    cfg = zenoh.Config()
    try:
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("scouting/multicast/enabled", "true" if scouting else "false")
        if listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    except Exception as exc:  # zenoh raises its own ZError for bad JSON5 values
        raise TransportError(zenoh_config_message(str(exc))) from exc
    return cfg


def open_session(
    listen: Sequence[str] = (), connect: Sequence[str] = (), *, scouting: bool = False
) -> zenoh.Session:
    """Open a Zenoh session. Raises TransportError (bad endpoint, port in use)."""
    try:
        return zenoh.open(session_config(listen, connect, scouting=scouting))
    except TransportError:
        raise
    except Exception as exc:
        raise TransportError(zenoh_open_message(str(exc), listen, connect)) from exc


def has_peer(session: Any) -> bool:
    """True when ``session`` is connected to at least one other Zenoh node (peer or
    router). Zenoh keeps retrying a ``connect`` endpoint it cannot reach, silently:
    this is how a command can tell the user."""
    info = session.info
    return any(True for _ in info.peers_zid()) or any(True for _ in info.routers_zid())


#: Zenoh's errors end with where in its Rust source they were raised: " at /root/.cargo/...rs:61."
_RUST_SOURCE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_BOUND_TO = re.compile(r"bound to ([a-z]+/\S+?):\s")


_JSON5_MSG = re.compile(r'msg: "(.*?)"(?:, location|\s*\})')


def zenoh_config_message(text: str) -> str:
    """One line for Zenoh's refusal of an endpoint: its own sentence, without the
    Rust debug wrapping (``Json5Err(Message { msg: ...``) or source paths."""
    m = _JSON5_MSG.search(text)
    detail = _RUST_SOURCE.sub("", m.group(1) if m else text).strip().rstrip(".")
    return f"bad Zenoh endpoint: {detail} (for example tcp/127.0.0.1:7447)"


def zenoh_open_message(text: str, listen: Sequence[str], connect: Sequence[str]) -> str:
    """One line a user understands for Zenoh's ``zenoh.open`` error ``text``: a port in
    use or an address not of this machine named as such, and never the Rust source
    paths of the Zenoh build."""
    m = _BOUND_TO.search(text)
    endpoint = m.group(1) if m else (listen[0] if len(listen) == 1 else "")
    port = endpoint.rpartition(":")[2]
    if "Address already in use" in text and endpoint:
        return f"cannot listen on {endpoint}: port {port} in use (another program, or another swarm node?)"
    if "Cannot assign requested address" in text and endpoint:
        return f"cannot listen on {endpoint}: that address is not one of this machine's"
    detail = _RUST_SOURCE.sub("", text).replace("[", "").replace("]", "").strip().rstrip(".")
    where = "; ".join(f"{k} {' '.join(v)}" for k, v in (("listen", listen), ("connect", connect)) if v)
    return f"cannot open Zenoh session ({where or 'no endpoints'}): {detail}"


class Transport:
    """One agent's (or the ground station's) view of the key space."""

    def __init__(self, name: str, session: zenoh.Session, *, owns_session: bool = False) -> None:
        check_name(name)
        if name in RESERVED:
            raise TransportError(f"{name!r} is a reserved key, not an agent name")
        self.name = name
        self.session = session
        self._owns = owns_session
        self._subs: list[Any] = []
        self._lock = threading.Lock()
        self.decode_errors = 0
        self.last_decode_error = ""
        self._closed = False

    @classmethod
    def open(
        cls, name: str, *, listen: Sequence[str] = (), connect: Sequence[str] = (), scouting: bool = False
    ) -> Transport:
        return cls(name, open_session(listen, connect, scouting=scouting), owns_session=True)

    # -- publishing -------------------------------------------------------------
    def put(self, key: str, msg: Message) -> None:
        self.session.put(key, encode(msg))

    def send(self, to: str, msg: Message) -> None:
        """A P2P message to agent ``to``'s inbox."""
        self.put(inbox_key(check_name(to)), msg)

    def advertise(self, msg: Advertize) -> None:
        self.put(KEY_ADVERTIZE, msg)

    def gs_advertise(self, msg: GSAdvertize) -> None:
        self.put(KEY_GS_ADVERTIZE, msg)

    def publish_pose(self, msg: PoseReport) -> None:
        self.put(pose_key(self.name), msg)

    def publish_state(self, msg: AgentState) -> None:
        self.put(state_key(self.name), msg)

    # -- subscribing ------------------------------------------------------------
    def subscribe(
        self,
        key: str,
        callback: Callable[[str, Message], None],
        accept: Callable[[str, bytes], bool] | None = None,
    ) -> None:
        """Call ``callback(key, message)`` for every decodable sample on ``key``
        (wildcards allowed); with ``accept``, only for samples it accepts (key and raw
        bytes, looked at before decoding: a wide subscription that wants few)."""

        def handler(sample: Any) -> None:
            data = sample.payload.to_bytes()
            if accept is not None and not accept(str(sample.key_expr), data):
                return
            try:
                msg = decode(data)
            except DecodeError as exc:
                with self._lock:
                    self.decode_errors += 1
                    self.last_decode_error = str(exc)
                return
            callback(str(sample.key_expr), msg)

        with self._lock:
            if self._closed:
                raise TransportError("transport is closed")
            self._subs.append(self.session.declare_subscriber(key, handler))

    def on_inbox(self, callback: Callable[[Message], None]) -> None:
        self.subscribe(inbox_key(self.name), lambda _k, m: callback(m))

    def on_advertize(self, callback: Callable[[Advertize], None]) -> None:
        self.subscribe(KEY_ADVERTIZE, lambda _k, m: callback(m) if isinstance(m, Advertize) else None)

    def on_gs_advertize(self, callback: Callable[[GSAdvertize], None]) -> None:
        self.subscribe(KEY_GS_ADVERTIZE, lambda _k, m: callback(m) if isinstance(m, GSAdvertize) else None)

    def on_pose(self, name: str, callback: Callable[[str, PoseReport], None]) -> None:
        """Pose stream of ``name`` ('*' for every agent); callback gets the agent name."""
        key = pose_key(name if name == "*" else check_name(name))
        self.subscribe(key, lambda k, m: callback(k.split("/")[1], m) if isinstance(m, PoseReport) else None)

    def on_state(self, name: str, callback: Callable[[str, AgentState], None]) -> None:
        key = state_key(name if name == "*" else check_name(name))
        self.subscribe(key, lambda k, m: callback(k.split("/")[1], m) if isinstance(m, AgentState) else None)

    def close(self) -> None:
        """Undeclare subscribers (and close the session if this object opened it)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            subs, self._subs = self._subs, []
        for s in subs:
            try:
                s.undeclare()
            except Exception:  # the session may already be closed
                pass
        if self._owns:
            try:
                self.session.close()
            except Exception:
                pass

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
