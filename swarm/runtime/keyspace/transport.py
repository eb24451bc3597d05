"""The swarm's key space on Zenoh: one session per agent, a small typed API.

Theory of operation
-------------------
Keys (the paper's topics, docs/design/messages.md):

==========================  ==============================================
``swarm/advertize``         Advertize: an agent announces name and id
``swarm/GSAdvertize``       GSAdvertize: the ground station announces itself
``swarm/<name>``            P2P messages to agent ``<name>`` (its inbox)
``swarm/<name>/command``    Commands to agent ``<name>`` (from stations only)
``swarm/<name>/pose``       the agent's pose stream
``swarm/<name>/state``      the agent's protocol state
==========================  ==============================================

Commands have a key of their own so that Zenoh's access control can tell them
from the election's messages, which agents send to each other's inboxes: only a
station's certificate may put on ``swarm/*/command`` (:mod:`swarm.core.keyspace.acl`).
:meth:`Transport.send` puts a Command there, and :meth:`Transport.on_inbox` takes
Commands from there only: one found on an inbox is dropped, counted in
``misplaced_commands`` and logged once. Over a radio the bytes on the air are the
same P2P frame as before; the bridge maps the key (:mod:`swarm.runtime.bridge.radio_bridge`).

Payloads are the compact messages of :mod:`swarm.core.wire.messages`. Agents connect
either through Zenoh's own network over IP (explicit endpoints, multicast scouting
off by default) or through the radio bridge (:mod:`swarm.runtime.bridge.radio_bridge`), which
carries the same keys over MAVLink TUNNEL frames.

A session listens only where it is told to (:func:`session_config`): a node that
listens is a Zenoh peer, a node that only connects is a Zenoh client (through the
router or peer it reaches: :class:`ClientSession`, which opens in the background so a
router down never holds up a node), and a node on a radio has no endpoint at all:
its session is reached only from its own process (its transport and radio bridge).
Callbacks run on Zenoh's threads; a payload that does not decode is counted and
dropped, never raised into Zenoh.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import zenoh

from swarm.core.keyspace.endpoints import key_over_ip
from swarm.core.keyspace.zenoh_errors import RUST_SOURCE, zenoh_config_message, zenoh_open_message
from swarm.core.wire.message_types import (
    Advertize,
    AgentState,
    Command,
    GSAdvertize,
    Message,
    PoseReport,
    check_name,
)
from swarm.core.wire.messages import decode, encode
from swarm.errors import DecodeError, TransportError

if TYPE_CHECKING:
    from swarm.runtime.options import TlsFiles

log = logging.getLogger(__name__)

PREFIX = "swarm"
KEY_ADVERTIZE = f"{PREFIX}/advertize"
KEY_GS_ADVERTIZE = f"{PREFIX}/GSAdvertize"
RESERVED = {"advertize", "GSAdvertize"}


def inbox_key(name: str) -> str:
    return f"{PREFIX}/{name}"


def command_key(name: str) -> str:
    return f"{PREFIX}/{name}/command"


def pose_key(name: str) -> str:
    return f"{PREFIX}/{name}/pose"


def state_key(name: str) -> str:
    return f"{PREFIX}/{name}/state"


def session_mode(listen: Sequence[str], connect: Sequence[str]) -> str:
    """The Zenoh mode of a node's session: ``peer`` when it listens (it was asked to),
    ``client`` when it only connects (every sample goes through the router or peer it
    reached; it listens nowhere), and ``peer`` with no endpoint at all (a session in
    this process only: a radio node's)."""
    if listen:
        return "peer"
    return "client" if connect else "peer"


def session_config(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    *,
    scouting: bool = False,
    tls: TlsFiles | None = None,
    acl_text: str | None = None,
) -> zenoh.Config:
    """A Zenoh config with explicit endpoints (``tcp/127.0.0.1:7447``) that listens
    exactly where ``listen`` says and nowhere else: Zenoh's own default for a peer is
    every address on a random port (``tcp/[::]:0``), which would let anyone who
    reaches the machine into the key space. See :func:`session_mode`. With ``tls``,
    mutual TLS (and ``acl_text``, Zenoh's access control): :mod:`swarm.runtime.keyspace.tls`."""
    cfg = zenoh.Config()
    try:
        cfg.insert_json5("mode", json.dumps(session_mode(listen, connect)))
        cfg.insert_json5("scouting/multicast/enabled", "true" if scouting else "false")
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if tls is not None:
            from swarm.runtime.keyspace import tls as zenoh_tls

            zenoh_tls.apply(cfg, tls, listening=bool(listen), acl_text=acl_text)
    except Exception as exc:  # zenoh raises its own ZError for bad JSON5 values
        raise TransportError(zenoh_config_message(str(exc))) from exc
    return cfg


def open_session(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    *,
    scouting: bool = False,
    tls: TlsFiles | None = None,
    acl: str | None = None,
    signed: bool = False,
) -> Any:
    """Open a Zenoh session. Raises TransportError (bad endpoint, port in use; with
    ``signed``, a node holding the swarm key, a plain endpoint beyond loopback:
    :func:`swarm.core.keyspace.endpoints.key_over_ip`) or CertError (``tls`` files or the
    ``acl`` file: :func:`swarm.runtime.keyspace.tls.check_tls`). Warns (one log line) of
    the key on a loopback endpoint and of TLS listening without an ACL.

    A session that only connects is a :class:`ClientSession` (Zenoh's client mode,
    opened in the background until the other side answers); otherwise Zenoh's own
    session in peer mode."""
    verdict = key_over_ip([*listen, *connect], has_key=signed)
    if verdict is not None and verdict.level == "refuse":
        raise TransportError(verdict.text)
    if verdict is not None:
        log.warning("%s", verdict.text)
    if tls is not None and listen and acl is None:
        log.warning(
            "warning: no access control: any certificate of the swarm's CA that connects to %s may publish "
            "anything (swarm certs writes acl.json5)",
            ", ".join(listen),
        )
    acl_text = None
    if tls is not None:
        from swarm.runtime.keyspace import tls as zenoh_tls

        zenoh_tls.check_tls(tls)
        acl_text = zenoh_tls.load_acl(acl) if acl is not None else None
    elif acl is not None:
        raise TransportError("Zenoh access control (an ACL file) needs TLS: certificates name who is who")
    cfg = session_config(listen, connect, scouting=scouting, tls=tls, acl_text=acl_text)
    if session_mode(listen, connect) == "client":
        return ClientSession(cfg, connect)
    try:
        return zenoh.open(cfg)
    except Exception as exc:
        raise TransportError(zenoh_open_message(str(exc), listen, connect)) from exc


#: how long one attempt of a client session to reach its router may take, ms
CLIENT_ATTEMPT_MS = 1000


class _NoInfo:
    """A client session's ``info`` before it reached anyone."""

    def peers_zid(self) -> list[Any]:
        return []

    def routers_zid(self) -> list[Any]:
        return []


#: how long closing waits for a callback still running to return, s
CALLBACK_END_S = 2.0


class _Declared:
    """A subscriber or queryable declared on a :class:`ClientSession`: declared again on
    each session it opens; :meth:`undeclare` as Zenoh's.

    Zenoh runs a Python callback on a thread of its own, started by the thread that
    declares, whose daemon flag it inherits. A client session declares from its open
    loop, a daemon thread, so those callback threads were daemons too: nothing waited
    for them at exit, and the interpreter killed one mid-callback as it shut down (the
    process aborted, "FATAL: exception not rethrown"). So a plain callable is wrapped
    with a drop hook that names its thread, and undeclaring (or closing the session)
    returns only once that thread has ended (at most :data:`CALLBACK_END_S`)."""

    def __init__(self, owner: ClientSession, method: str, args: tuple[Any, ...], kw: dict[str, Any]) -> None:
        self.owner, self.method, self.args, self.kw = owner, method, args, kw
        self.real: Any = None
        self._ends: list[tuple[threading.Event, list[threading.Thread]]] = []

    def attach(self, session: Any) -> None:
        args, kw = list(self.args), dict(self.kw)
        if len(args) > 1:
            args[1] = self._watched(args[1])
        elif "handler" in kw:
            kw["handler"] = self._watched(kw["handler"])
        self.real = getattr(session, self.method)(*args, **kw)

    def _watched(self, handler: Any) -> Any:
        if not callable(handler) or type(handler).__module__.startswith("zenoh"):
            return handler  # Zenoh's own handlers (channels, Callback) as given
        ended = threading.Event()
        thread: list[threading.Thread] = []

        def drop() -> None:
            thread.append(threading.current_thread())
            ended.set()

        self._ends.append((ended, thread))
        return zenoh.handlers.Callback(handler, drop)

    def wait_ended(self, deadline: float) -> None:
        """Wait (until ``deadline``, monotonic) for every callback thread to end."""
        ends, self._ends = self._ends, []
        for ended, thread in ends:
            if not ended.wait(max(0.0, deadline - time.monotonic())):
                log.debug("client session: a callback did not end in time")
                continue
            for t in thread:
                if t is not threading.current_thread():
                    t.join(max(0.0, deadline - time.monotonic()))

    def undeclare(self) -> None:
        self.owner.forget(self)
        real, self.real = self.real, None
        if real is not None:
            real.undeclare()
            self.wait_ended(time.monotonic() + CALLBACK_END_S)


class ClientSession:
    """A Zenoh session in client mode that never holds up its node: Zenoh's client
    refuses to open until it reaches a router or peer, so this one opens on a thread,
    trying again every :data:`CLIENT_ATTEMPT_MS` (a router started after the node, or
    down for a while, is reached when it comes), and then lets Zenoh's client keep the
    link (it reconnects by itself). Until then a put is dropped (counted in
    :attr:`dropped`), a get finds no one, ``info`` lists no peer, and subscribers and
    queryables are declared on the session once it opens. The same calls as Zenoh's
    session, as far as the swarm uses them."""

    def __init__(self, cfg: zenoh.Config, connect: Sequence[str]) -> None:
        try:
            cfg.insert_json5("connect/timeout_ms", str(CLIENT_ATTEMPT_MS))
            cfg.insert_json5("connect/exit_on_failure", "true")
        except Exception as exc:
            raise TransportError(zenoh_config_message(str(exc))) from exc
        self.cfg = cfg
        self.connect = tuple(connect)
        self.dropped = 0
        self.last_error = ""
        self._lock = threading.Lock()
        self._session: Any = None
        self._declared: list[_Declared] = []
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._open_loop, name="zenoh-client", daemon=True)
        self._thread.start()

    def _open_loop(self) -> None:
        while not self._closed.is_set():
            try:
                session = zenoh.open(self.cfg)
            except Exception as exc:  # nobody there yet (or it refused us): try again
                self.last_error = RUST_SOURCE.sub("", str(exc)).strip()
                self._closed.wait(0.2)
                continue
            with self._lock:
                if self._closed.is_set():
                    break
                self._session = session
                for d in self._declared:
                    try:
                        d.attach(session)
                    except Exception:
                        log.debug("client session: declaring again failed", exc_info=True)
                return
        else:
            return
        session.close()  # closed while it opened

    @property
    def opened(self) -> bool:
        return self._session is not None

    @property
    def info(self) -> Any:
        s = self._session
        return _NoInfo() if s is None else s.info

    def put(self, key: Any, payload: Any, **kw: Any) -> None:
        s = self._session
        if s is None:
            self.dropped += 1
            return
        s.put(key, payload, **kw)

    def get(self, *args: Any, **kw: Any) -> Any:
        s = self._session
        return [] if s is None else s.get(*args, **kw)

    def _declare(self, method: str, args: tuple[Any, ...], kw: dict[str, Any]) -> _Declared:
        d = _Declared(self, method, args, kw)
        with self._lock:
            if self._closed.is_set():
                raise TransportError("the Zenoh session is closed")
            self._declared.append(d)
            if self._session is not None:
                d.attach(self._session)
        return d

    def declare_subscriber(self, *args: Any, **kw: Any) -> _Declared:
        return self._declare("declare_subscriber", args, kw)

    def declare_queryable(self, *args: Any, **kw: Any) -> _Declared:
        return self._declare("declare_queryable", args, kw)

    def forget(self, d: _Declared) -> None:
        with self._lock:
            if d in self._declared:
                self._declared.remove(d)

    def close(self) -> None:
        """Stop trying, close the session if it opened. Safe twice."""
        with self._lock:
            self._closed.set()
            session, self._session = self._session, None
            declared, self._declared = self._declared, []
        if session is not None:
            session.close()
            deadline = time.monotonic() + CALLBACK_END_S
            for d in declared:
                d.wait_ended(deadline)
        if self._thread is not threading.current_thread():
            self._thread.join(CLIENT_ATTEMPT_MS / 1000 + 1.0)  # an attempt under way ends


def has_peer(session: Any) -> bool:
    """True when ``session`` is connected to at least one other Zenoh node (peer or
    router). Zenoh keeps retrying a ``connect`` endpoint it cannot reach, silently:
    this is how a command can tell the user."""
    info = session.info
    return any(True for _ in info.peers_zid()) or any(True for _ in info.routers_zid())


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
        self.misplaced_commands = 0  # Commands found on the inbox, dropped
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
        """A P2P message to agent ``to``'s inbox (a Command: to its command key)."""
        name = check_name(to)
        self.put(command_key(name) if isinstance(msg, Command) else inbox_key(name), msg)

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
        """Every message to this node: its inbox's (but Commands) and its command key's
        Commands (see the module docstring)."""
        self.subscribe(inbox_key(self.name), lambda _k, m: self._inbox(m, callback))
        self.subscribe(command_key(self.name), lambda _k, m: callback(m) if isinstance(m, Command) else None)

    def _inbox(self, msg: Message, callback: Callable[[Message], None]) -> None:
        if not isinstance(msg, Command):
            callback(msg)
            return
        with self._lock:
            self.misplaced_commands += 1
            first = self.misplaced_commands == 1
        if first:
            log.warning(
                "%s: a Command on its inbox %s was dropped: commands come on %s (from a station of "
                "another version, or a sender without the right to command)",
                self.name,
                inbox_key(self.name),
                command_key(self.name),
            )

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
