"""Issue 27: station Commands travel on a key of their own, ``swarm/<name>/command``.

Zenoh's access control decides by key, and agents put election messages on each
other's inboxes ``swarm/<name>``: a Command sharing that key could not be refused to an
agent's certificate. So a Command goes to ``swarm/<name>/command`` (only stations may
put there), an agent takes Commands from there only, and one found on an inbox is
dropped, counted and logged once. Over a radio nothing changes on the air: the bridge
sends a command key's sample as the P2P frame it always was (the same bytes) and puts
a received P2P Command back on the addressee's command key.

Real Zenoh sessions in this process and a real bridge on an in-process radio link.
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from radios.link import open_link
from radios.mavlink import MSG_TUNNEL, FrameBuilder, parse_one
from swarm.core.wire.message_types import Advertize, Command, CommandKind, Heartbeat, StartPool
from swarm.core.wire.messages import decode, encode
from swarm.core.wire.tunnel import COMP_ID, PAYLOAD_TYPE_BASE, Kind, unpack_tunnel
from swarm.runtime.bridge.radio_bridge import BridgeConfig, RadioBridge
from swarm.runtime.keyspace.transport import Transport, command_key, inbox_key, open_session

DEADLINE = 20.0
ARM = Command(255, 7, 2, CommandKind.ARM)


class Keys:
    """Every (key, payload, from the radio) a session sees on ``swarm/**``."""

    def __init__(self, session: Any) -> None:
        self.seen: list[tuple[str, bytes, bool]] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber("swarm/**", self._on)

    def _on(self, sample: Any) -> None:
        with self._lock:
            self.seen.append((str(sample.key_expr), sample.payload.to_bytes(), sample.attachment is not None))

    def radio(self) -> list[tuple[str, bytes]]:
        with self._lock:
            return [(k, p) for k, p, radio in self.seen if radio]


def test_a_command_goes_on_the_command_key_and_only_there_reaches_the_agent(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ExitStack() as stack:
        agent = stack.enter_context(Transport.open("agent2", listen=[ep]))
        station = stack.enter_context(Transport.open("gcs", connect=[ep]))
        got: list[Any] = []
        agent.on_inbox(got.append)
        keys = Keys(agent.session)

        def delivered(msg: Any) -> bool:  # a client's first puts race its subscriptions
            if msg in got:
                return True
            station.send("agent2", msg)
            return False

        wait_until(lambda: delivered(StartPool(9)), "a P2P message in the inbox", DEADLINE, 0.1)
        wait_until(lambda: delivered(ARM), "the station's Command", DEADLINE, 0.1)
        assert ("swarm/agent2/command", encode(ARM), False) in keys.seen
        assert all(k != "swarm/agent2" for k, p, _r in keys.seen if p == encode(ARM)), "never on the inbox"
        # a Command put on the inbox (an agent's certificate may put there) is dropped,
        # counted, and logged once
        forged = Command(255, 8, 2, CommandKind.TAKEOFF, alt=10.0)
        with caplog.at_level(logging.WARNING, logger="swarm.runtime.keyspace.transport"):
            for _ in range(3):
                station.session.put(inbox_key("agent2"), encode(forged))
            wait_until(lambda: agent.misplaced_commands == 3, "three misplaced Commands counted", DEADLINE)
        assert forged not in got
        assert [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()] == [
            "agent2: a Command on its inbox swarm/agent2 was dropped: commands come on "
            "swarm/agent2/command (from a station of another version, or a sender without the right "
            "to command)"
        ]
        # and only Commands are taken from the command key
        station.session.put(command_key("agent2"), encode(Heartbeat(3, 1, 1, frozenset({2}))))
        station.send("agent2", StartPool(10))
        wait_until(lambda: StartPool(10) in got, "a later message", DEADLINE)
        assert not any(isinstance(m, Heartbeat) for m in got)


@pytest.fixture
def bridge() -> Iterator[tuple[RadioBridge, Any, Keys, Transport]]:
    """Agent a1 (id 1) bridged to an in-process radio link; a tap on the same bus."""
    url = f"virtual://cmdkey-{uuid.uuid4().hex}"
    with ExitStack() as stack:
        session = open_session()
        stack.callback(session.close)
        link = open_link(url)
        stack.callback(link.close)
        tap = open_link(url)
        stack.callback(tap.close)
        b = RadioBridge(session, link, name="a1", agent_id=1, config=BridgeConfig()).start()
        stack.callback(b.close)
        tr = Transport("a1", session)
        stack.callback(tr.close)
        keys = Keys(session)
        b.handle_frame(tunnel(2, Kind.ADVERTIZE, encode(Advertize(2, "a2"))))
        assert b.peers() == {"a1": 1, "a2": 2}
        yield b, tap, keys, tr


def tunnel(sysid: int, kind: Kind, payload: bytes, target: int = 0) -> Any:
    return parse_one(
        FrameBuilder(sysid, COMP_ID).tunnel(
            payload, target_system=target, payload_type=PAYLOAD_TYPE_BASE + int(kind)
        )
    )


def test_the_bridge_keeps_the_air_bytes_and_maps_the_command_key(
    bridge: tuple[RadioBridge, Any, Keys, Transport],
) -> None:
    b, tap, keys, tr = bridge
    # out: a Command for a2 leaves as the P2P frame to a2 it always was
    tr.send("a2", ARM)

    def on_air() -> list[Any]:
        frames = []
        while (f := tap.recv(0.05)) is not None:
            if f.msgid == MSG_TUNNEL:
                frames.append(unpack_tunnel(f.payload))
        return [t for t in frames if t is not None and t[3] == encode(ARM)]

    sent = wait_until(on_air, "the Command on the air", DEADLINE)
    assert [(kind, target, data) for kind, target, _ids, data in sent] == [(Kind.P2P, 2, encode(ARM))]
    # in: a P2P frame carrying a Command lands on our command key, anything else on the inbox
    cmd = Command(255, 9, 1, CommandKind.LAND)
    b.handle_frame(tunnel(255, Kind.P2P, encode(cmd), target=1))
    b.handle_frame(tunnel(2, Kind.P2P, encode(StartPool(2)), target=1))

    def p2p() -> list[tuple[str, bytes]]:
        return [(k, p) for k, p in keys.radio() if k != "swarm/advertize"]

    wait_until(lambda: len(p2p()) >= 2, "both frames published", DEADLINE)
    assert p2p() == [("swarm/a1/command", encode(cmd)), ("swarm/a1", encode(StartPool(2)))]
    assert decode(p2p()[0][1]) == cmd
