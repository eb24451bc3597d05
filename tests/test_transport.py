"""The swarm key space over Zenoh on IP: three transports on loopback TCP (one
listens, the others connect) exchanging P2P messages, advertisements, pose and
state streams; undecodable samples counted, bad names rejected, close() twice.

Nothing sleeps to hope: every wait polls for an outcome until a generous deadline.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from swarm.core.wire.message_types import (
    Advertize,
    AgentState,
    GSAdvertize,
    Message,
    Phase,
    Pose,
    PoseReport,
    Selection,
    StartPool,
)
from swarm.errors import MessageError, TransportError
from swarm.runtime.keyspace.transport import Transport, inbox_key, open_session

DEADLINE = 20.0
QUIET = 0.5  # how long "nothing else arrives" is watched after the expected did


def prime(put: Callable[[], None], seen: Callable[[], Any], what: str) -> None:
    """Zenoh propagates a new subscriber's interest asynchronously: re-send a
    sentinel every 50 ms until the new subscribers see it, so that what follows is
    counted exactly (tests ignore the sentinels)."""

    def attempt() -> Any:
        if seen():
            return True
        put()
        return False

    wait_until(attempt, what, DEADLINE, 0.05)


SENTINEL_POSE = PoseReport(Pose(0.0, 0.0, 0.0, t=0.5))
SENTINEL = StartPool(250)


class Inbox:
    """Thread-safe record of what a callback received."""

    def __init__(self) -> None:
        self.items: list[Any] = []
        self._lock = threading.Lock()

    def add(self, *item: Any) -> None:
        with self._lock:
            self.items.append(item[0] if len(item) == 1 else item)

    def snapshot(self) -> list[Any]:
        with self._lock:
            return list(self.items)

    def add_msg(self, _key: str, msg: Message) -> None:
        self.add(msg)

    def clear(self) -> None:
        with self._lock:
            self.items.clear()

    def count(self, x: Any) -> int:
        return self.snapshot().count(x)


@pytest.fixture(scope="module")
def trio() -> Iterator[list[Transport]]:
    """a1 listens on a free loopback port, a2 and a3 connect to it; returned once
    every pair delivers P2P messages both ways."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    ts: list[Transport] = []
    try:
        ts.append(Transport.open("a1", listen=[ep]))
        ts.append(Transport.open("a2", connect=[ep]))
        ts.append(Transport.open("a3", connect=[ep]))
        probes = {t.name: Inbox() for t in ts}
        for t in ts:
            t.subscribe(inbox_key(t.name), probes[t.name].add_msg)
        # connectivity: every ordered pair, probes re-sent until one arrives
        for i, src in enumerate(ts):
            for dst in ts:
                if dst is src:
                    continue
                probe = Selection(i + 1, candidate=1, weight=999_000 + i, epoch=7)

                def arrived(src: Transport = src, dst: Transport = dst, probe: Message = probe) -> bool:
                    if probes[dst.name].count(probe) > 0:
                        return True
                    src.send(dst.name, probe)
                    return False

                wait_until(arrived, f"{src.name} -> {dst.name} over Zenoh", DEADLINE, 0.05)
        yield ts
    finally:
        for t in ts:
            t.close()


def test_p2p_reaches_only_the_addressee(trio: list[Transport]) -> None:
    a1, a2, a3 = trio
    boxes = {t.name: Inbox() for t in trio}
    for t in trio:
        t.on_inbox(boxes[t.name].add)
    for t in trio:
        prime(
            partial(a1.send, t.name, SENTINEL),
            partial(boxes[t.name].count, SENTINEL),
            f"the new inbox subscriber of {t.name}",
        )
    sent = {
        (src.name, dst.name): Selection(i + 1, candidate=j + 1, weight=1000 + 10 * i + j, epoch=1)
        for i, src in enumerate(trio)
        for j, dst in enumerate(trio)
        if src is not dst
    }
    for (src, dst), msg in sent.items():
        next(t for t in trio if t.name == src).send(dst, msg)
    for (_src, dst), msg in sent.items():
        wait_until(partial(boxes[dst].count, msg), f"{msg} in {dst}'s inbox", DEADLINE)
    time.sleep(QUIET)
    for name, box in boxes.items():
        got = sorted(m.weight for m in box.snapshot() if isinstance(m, Selection) and m.epoch == 1)
        expected = sorted(m.weight for (_s, d), m in sent.items() if d == name)
        assert got == expected, f"{name}'s inbox: exactly its own messages, once each"
    assert a1.decode_errors == a2.decode_errors == a3.decode_errors == 0


def test_advertize_and_gs_advertize_reach_everyone(trio: list[Transport]) -> None:
    adv = {t.name: Inbox() for t in trio}
    gs = {t.name: Inbox() for t in trio}
    for t in trio:
        t.on_advertize(adv[t.name].add)
        t.on_gs_advertize(gs[t.name].add)
    sentinel_adv, sentinel_gs = Advertize(250, "sentinel"), GSAdvertize(250, "sentinel")
    for src in trio:
        prime(
            partial(src.advertise, sentinel_adv),
            lambda: all(adv[t.name].count(sentinel_adv) for t in trio),
            "advertize subscribers",
        )
        prime(
            partial(src.gs_advertise, sentinel_gs),
            lambda: all(gs[t.name].count(sentinel_gs) for t in trio),
            "GSAdvertize subscribers",
        )
    for t in trio:
        adv[t.name].clear()
        gs[t.name].clear()
    for i, t in enumerate(trio):
        t.advertise(Advertize(i + 1, t.name, flags=1))
    trio[2].gs_advertise(GSAdvertize(255, "gcs"))
    for t in trio:
        for i, other in enumerate(trio):
            wait_until(
                partial(adv[t.name].count, Advertize(i + 1, other.name, 1)),
                f"{other.name}'s Advertize at {t.name}",
                DEADLINE,
            )
        wait_until(partial(gs[t.name].count, GSAdvertize(255, "gcs")), f"GSAdvertize at {t.name}", DEADLINE)
    time.sleep(QUIET)
    for t in trio:
        # once each (its own included: same key space); late sentinels aside
        assert len([m for m in adv[t.name].snapshot() if m != sentinel_adv]) == 3
        assert len([m for m in gs[t.name].snapshot() if m != sentinel_gs]) == 1


def test_pose_and_state_streams_with_wildcards(trio: list[Transport]) -> None:
    a1, a2, a3 = trio
    poses_all, poses_a1, states = Inbox(), Inbox(), Inbox()
    a2.on_pose("*", poses_all.add)
    a3.on_pose("a1", poses_a1.add)
    a3.on_state("*", states.add)
    prime(
        lambda: a1.publish_pose(SENTINEL_POSE),
        lambda: poses_all.count(("a1", SENTINEL_POSE)) and poses_a1.count(("a1", SENTINEL_POSE)),
        "pose subscribers",
    )
    prime(
        lambda: a3.publish_pose(SENTINEL_POSE),
        lambda: poses_all.count(("a3", SENTINEL_POSE)),
        "a2's pose subscriber from a3",
    )
    sentinel_state = AgentState(250, Phase.IDLE)
    prime(
        lambda: a2.publish_state(sentinel_state),
        lambda: states.count(("a2", sentinel_state)),
        "state subscriber",
    )
    for box in (poses_all, poses_a1, states):
        box.clear()
    p1 = PoseReport(Pose(48.85, 2.35, 120.0, heading=90.0, t=1.0))
    p2 = PoseReport(Pose(48.86, 2.36, 121.0, heading=180.0, t=2.0))
    st = AgentState(2, Phase.MEMBER, leader=1, pool=frozenset({1, 2, 3}))
    a1.publish_pose(p1)
    a3.publish_pose(p2)
    a2.publish_state(st)
    wait_until(lambda: {("a1", p1), ("a3", p2)} <= set(poses_all.snapshot()), "both poses at a2", DEADLINE)
    wait_until(lambda: poses_a1.count(("a1", p1)), "a1's pose at a3", DEADLINE)
    wait_until(lambda: states.count(("a2", st)), "a2's state at a3", DEADLINE)
    time.sleep(QUIET)
    assert [x for x in poses_a1.snapshot() if x[1] != SENTINEL_POSE] == [("a1", p1)]  # not a3's
    assert [x for x in states.snapshot() if x[1] != sentinel_state] == [("a2", st)]
    # a wildcard subscription of its own: every agent's inbox
    seen = Inbox()
    a3.subscribe("swarm/*", lambda k, m: seen.add(k, m))
    prime(lambda: a1.send("a2", SENTINEL), lambda: seen.count(("swarm/a2", SENTINEL)), "swarm/* at a3")
    a1.send("a2", StartPool(1))
    wait_until(lambda: seen.count(("swarm/a2", StartPool(1))), "swarm/* sees a2's inbox", DEADLINE)


def test_undecodable_sample_counted_not_delivered(trio: list[Transport]) -> None:
    a1, a2, _ = trio
    box = Inbox()
    a2.on_inbox(box.add)
    prime(lambda: a1.send("a2", SENTINEL), lambda: box.count(SENTINEL), "a2's new inbox subscriber")
    before = a2.decode_errors
    for junk in (b"", b"\xff\x00", bytes([1 << 5 | 4, 2]), bytes([2 << 5 | 5, 1])):
        a1.session.put(inbox_key("a2"), junk)
    a1.send("a2", StartPool(9))  # a good one after the junk
    wait_until(lambda: box.count(StartPool(9)), "the valid message after the junk", DEADLINE)
    wait_until(lambda: a2.decode_errors - before >= 4, "4 decode errors counted", DEADLINE)
    assert [m for m in box.snapshot() if m not in (StartPool(9), SENTINEL)] == []
    assert a2.last_decode_error


def test_invalid_names_rejected() -> None:
    s = open_session()
    try:
        for bad in ("", "a b", "x/y", "a*", "é", "n" * 17):
            with pytest.raises(MessageError):
                Transport(bad, s)
        for reserved in ("advertize", "GSAdvertize"):
            with pytest.raises(TransportError):
                Transport(reserved, s)
        t = Transport("ok", s)
        with pytest.raises(MessageError):
            t.send("not/a/name", StartPool(1))
        with pytest.raises(MessageError):
            t.on_pose("bad name", lambda _n, _m: None)
        with pytest.raises(MessageError):
            t.on_state("**", lambda _n, _m: None)
        t.close()
    finally:
        s.close()


def test_close_twice_and_subscribe_after_close() -> None:
    t = Transport.open("solo")
    t.on_inbox(lambda _m: None)
    t.close()
    t.close()
    with pytest.raises(TransportError):
        t.on_inbox(lambda _m: None)
    with Transport.open("ctx") as c:
        c.on_advertize(lambda _m: None)
    c.close()


def test_bad_endpoint_is_a_transport_error() -> None:
    with pytest.raises(TransportError):
        open_session(listen=["nonsense-endpoint"])


def test_a_client_sessions_callback_threads_end_before_close_returns() -> None:
    """A connect-only node's subscribers are declared on the thread that opens its client
    session (a daemon thread), and Zenoh runs each Python callback on a thread of its own
    started there: a daemon too, so nothing waited for it at exit and the interpreter
    killed it mid-callback as it shut down ("FATAL: exception not rethrown", the process
    aborted: a connect-only agent stopped by systemd was reported as a core dump). Once
    close() returns, no callback of the session may still be running."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    peer = open_session(listen=[ep])
    client = open_session(connect=[ep])
    started = threading.Event()

    def slow(_sample: Any) -> None:  # still busy when close() is called
        started.set()
        time.sleep(0.5)

    try:
        others = set(threading.enumerate())  # other tests' sessions have callback threads too
        client.declare_subscriber("t/**", slow)  # before it opened: declared by the open loop
        wait_until(lambda: client.opened, "the client session opened", 30.0)

        def put_until_heard() -> bool:
            peer.put("t/x", b"x")
            return started.wait(0.1)

        wait_until(put_until_heard, "a sample at the client", 30.0)
        callback_threads = [
            t for t in set(threading.enumerate()) - others if "pyo3" in t.name
        ]  # Zenoh's name
        assert callback_threads, [t.name for t in threading.enumerate()]
        client.close()
        alive = [t.name for t in callback_threads if t.is_alive()]
        assert not alive, f"callback threads still running after close(): {alive}"
    finally:
        client.close()
        peer.close()
