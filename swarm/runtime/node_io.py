"""A node's way into the swarm's key space: a Zenoh session, and a radio bridged to it.

Theory of operation
-------------------
An agent or a ground station meets the others either over Zenoh endpoints (its
session listens on or connects to them) or through a radio: then its Zenoh session
has no endpoints and no scouting, and a :class:`~swarm.runtime.bridge.radio_bridge.RadioBridge`
carries the key space over the radio link (captured to a file if asked, MAVLink 2
signed with the swarm key if given). :func:`open_node` opens one or the other as
``(session, link, bridge)``; :func:`open_node_io` adds the node's
:class:`~swarm.runtime.keyspace.transport.Transport` and returns them as one :class:`NodeIO`,
which closes them in the reverse order. Whatever was opened is closed again if a
later step fails.
:class:`StartOnce` is the node's ``start()``: open once, close again on failure.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Self

if TYPE_CHECKING:
    from swarm.runtime.bridge.radio_bridge import RadioBridge
    from swarm.runtime.keyspace.transport import Transport
    from swarm.runtime.options import NodeOptions, TlsFiles

log = logging.getLogger(__name__)


class StartOnce:
    """The life cycle of a node (a station, an agent): :meth:`start` runs ``_open``
    once, however often it is called; if opening fails, ``stop`` closes what was
    opened and the error goes on. Subclasses give ``_open``, ``stop`` and the
    ``_lock`` and ``_started`` attributes."""

    _lock: threading.Lock | threading.RLock
    _started: bool

    def start(self) -> Self:
        with self._lock:
            if self._started:
                return self
            self._started = True
        try:
            self._open()
        except BaseException:
            self.stop()
            raise
        return self

    def _open(self) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError


@dataclass
class NodeIO:
    """What :func:`open_node_io` opened. ``link`` and ``bridge`` are None over Zenoh
    endpoints."""

    session: Any
    link: Any
    bridge: RadioBridge | None
    transport: Transport

    def close(self) -> None:
        """Close the transport, the bridge, the link and the session, in that order;
        an error closing one is logged and the rest still closed. Safe twice."""
        for close in (self.transport.close, self.bridge and self.bridge.close, self.link and self.link.close):
            if close:
                try:
                    close()
                except Exception:
                    log.debug("node: error while closing", exc_info=True)
        try:
            self.session.close()
        except Exception:
            log.debug("node: error while closing the session", exc_info=True)


def open_node(
    name: str,
    agent_id: int,
    *,
    radio: str | None = None,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    key_file: str | None = None,
    capture: Any = None,
    link: Any = None,
    signing_state: str | None = None,
    tls: TlsFiles | None = None,
    acl: str | None = None,
) -> tuple[Any, Any, RadioBridge | None]:
    """A node's way into the key space: ``(session, link, bridge)``. With ``radio`` the
    Zenoh session has no endpoints and no scouting (only the radio), the link is
    opened (captured to ``capture`` if given) and bridged, MAVLink 2 signed with the
    key in ``key_file``; otherwise a session on the Zenoh endpoints (with ``tls``
    certificates and the ``acl`` file if given), no link or bridge.
    A ``link`` already open is bridged instead of opening ``radio``; it is not
    returned (its opener closes it). ``capture`` is a ``.tlog`` path or a capture
    sink (:class:`radios.capture.CaptureSink`: an agent's flight log); a handed link
    is captured to a sink too, through a wrapper its opener need not know of.
    ``signing_state``: the file that keeps the signing clock across restarts
    (:mod:`radios.signing_state`). Whatever was opened is closed again if a later step fails.

    Raises:
        radios.errors.ConfigError: the key file. radios.errors.LinkOpenError: the radio.
        swarm.errors.TransportError: the Zenoh endpoints. swarm.errors.CertError: the
            TLS or ACL files.
    """
    from radios.link import open_link
    from radios.signing import load_key
    from swarm.runtime.bridge.radio_bridge import BridgeConfig, RadioBridge
    from swarm.runtime.keyspace.transport import open_session

    key = load_key(key_file) if key_file is not None else None
    ours = link is None  # a handed link is closed by whoever opened it
    if link is None:
        if radio is None:
            return open_session(listen, connect, tls=tls, acl=acl, signed=key is not None), None, None
        link = open_link(radio, capture=capture)
    elif capture is not None and not isinstance(capture, str):
        from radios.capture import CaptureLink

        link = CaptureLink(link, capture)  # not closed by us: the sink outlives it, the opener closes link
    try:
        session = open_session()  # no endpoints, no scouting: only the radio
    except BaseException:
        if ours:
            link.close()
        raise
    try:
        bridge = RadioBridge(
            session,
            link,
            name=name,
            agent_id=agent_id,
            config=BridgeConfig(signing_key=key, signing_state=signing_state),
        ).start()
    except BaseException:
        if ours:
            link.close()
        session.close()
        raise
    return session, link if ours else None, bridge


def open_node_io(name: str, agent_id: int, node: NodeOptions, *, capture: Any = None) -> NodeIO:
    """:func:`open_node` for ``node`` (radio URL, open link or Zenoh endpoints, key)
    and the node's :class:`Transport` as ``name`` on its session.

    Raises:
        what :func:`open_node` raises.
    """
    from swarm.runtime.keyspace.transport import Transport

    session, link, bridge = open_node(
        name,
        agent_id,
        radio=node.radio,
        listen=node.zenoh_listen,
        connect=node.zenoh_connect,
        key_file=node.key_file,
        capture=capture,
        link=node.link,
        signing_state=node.signing_state,
        tls=node.tls,
        acl=node.acl_file,
    )
    try:
        return NodeIO(session, link, bridge, Transport(name, session))
    except BaseException:
        for close in (bridge and bridge.close, link and link.close, session.close):
            if close:
                close()
        raise
