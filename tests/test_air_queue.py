"""The radio bridge's send queue (swarm.core.bridge.air_queue): priorities, budgets, multicast,
the RADIO_STATUS back-off. A pure core: driven with a manual clock, no thread, no radio."""

from __future__ import annotations

from dataclasses import dataclass

from swarm.core.bridge.air_queue import AirItem, AirQueue, Klass
from swarm.core.bridge.radio_guard import RADIO_COMPID, RADIO_SYSID, RadioState, RadioStatusGuard
from swarm.core.wire.tunnel import TUNNEL_MAX, Kind


@dataclass
class Counts:
    queue_drops: int = 0
    throttled: int = 0
    poses_thinned: int = 0
    multicast_merged: int = 0


def make(
    *,
    rates: tuple[float, float, float] = (1e6, 1e6, 1e6),
    bursts: tuple[float, float, float] = (1e6, 1e6, 1e6),
    sizes: tuple[int, int, int] = (64, 4, 16),
    signed: bool = False,
    guard: RadioStatusGuard | None = None,
) -> tuple[AirQueue, Counts]:
    counts = Counts()
    q = AirQueue(
        rates=rates,
        bursts=bursts,
        sizes=sizes,
        coalesce_s=0.005,
        signed=signed,
        guard=guard or RadioStatusGuard(),
        stats=counts,
        now=0.0,
    )
    return q, counts


def p2p(to: int, payload: bytes = b"\x01hb") -> AirItem:
    return AirItem(Klass.PROTOCOL, Kind.P2P, [to], payload)


def drain(q: AirQueue, now: float) -> list[AirItem]:
    out = []
    while True:
        item, _ = q.next_item(now)
        if item is None:
            return out
        out.append(item)


def test_classes_go_in_priority_order_whatever_the_order_queued() -> None:
    q, _ = make()
    q.put(AirItem(Klass.TELEMETRY, Kind.STATE, [0], b"state"), 0.0)
    q.put(AirItem(Klass.POSE, Kind.POSE, [0], b"pose"), 0.0)
    q.put(AirItem(Klass.PROTOCOL, Kind.ADVERTIZE, [0], b"adv"), 0.0)
    assert [i.payload for i in drain(q, 1.0)] == [b"adv", b"pose", b"state"]


def test_a_full_queue_drops_its_oldest_item_and_counts_it() -> None:
    q, counts = make(sizes=(64, 2, 16))
    for n in range(3):
        q.put(AirItem(Klass.POSE, Kind.POSE, [0], bytes([n])), 0.0)
    assert counts.queue_drops == 1
    assert [i.payload for i in drain(q, 1.0)] == [b"\x01", b"\x02"]


def test_a_p2p_item_waits_for_identical_payloads_and_leaves_as_one_multicast() -> None:
    q, counts = make()
    for to in (3, 4, 5):
        q.put(p2p(to), 0.0)
    item, wait = q.next_item(0.001)
    assert item is None and 0 < wait <= 0.005  # still gathering
    item, _ = q.next_item(0.01)
    assert item is not None and item.kind == Kind.MULTI and sorted(item.targets) == [3, 4, 5]
    assert counts.multicast_merged == 2 and drain(q, 0.02) == []


def test_different_payloads_are_not_merged() -> None:
    q, counts = make()
    q.put(p2p(3, b"\x01a"), 0.0)
    q.put(p2p(4, b"\x01b"), 0.0)
    items = drain(q, 0.01)
    assert [(i.kind, i.targets) for i in items] == [(Kind.P2P, [3]), (Kind.P2P, [4])]
    assert counts.multicast_merged == 0


def test_multicast_stops_at_what_one_frame_holds() -> None:
    q, _ = make()
    body = b"\x01" + bytes(TUNNEL_MAX - 5)  # room for the count byte and three ids
    for to in (3, 4, 5, 6):
        q.put(p2p(to, body), 0.0)
    first, _ = q.next_item(0.01)
    assert first is not None and first.kind == Kind.P2P  # four would not fit: none merged


def test_the_budget_holds_an_item_until_its_bucket_refills() -> None:
    q, _ = make(rates=(100.0, 1e6, 1e6), bursts=(30.0, 1e6, 1e6))
    adv = AirItem(Klass.PROTOCOL, Kind.ADVERTIZE, [0], bytes(10))  # 12 + 5 + 10 = 27 bytes
    q.put(adv, 0.0)
    q.put(AirItem(Klass.PROTOCOL, Kind.ADVERTIZE, [0], bytes(10)), 0.0)
    assert q.next_item(0.0)[0] is adv  # the burst pays for one
    item, wait = q.next_item(0.0)
    assert item is None and abs(wait - 0.24) < 1e-9  # 24 more bytes at 100 B/s
    assert q.next_item(0.24)[0] is not None


def test_the_frame_size_counts_the_signature_and_the_multicast_list() -> None:
    plain, _ = make()
    signed, _ = make(signed=True)
    item = AirItem(Klass.PROTOCOL, Kind.MULTI, [3, 4], bytes(10))
    assert plain.frame_size(item) == 12 + 5 + 10 + 3
    assert signed.frame_size(item) == plain.frame_size(item) + 13
    assert plain.frame_size(AirItem(Klass.TELEMETRY, Kind.P2P, [0], b"", raw_frame=bytes(40))) == 40


def test_a_full_radio_buffer_holds_telemetry_and_thins_poses_but_never_protocol() -> None:
    guard = RadioStatusGuard()
    guard.wrote(1024, 0.0)  # the bridge wrote enough for the radio to hold this much
    guard.heartbeat_sent(0.0)
    assert guard.offer(RADIO_SYSID, RADIO_COMPID, RadioState(txbuf=10), 0.1) is None
    q, counts = make(guard=guard, sizes=(64, 64, 16))
    q.put(AirItem(Klass.TELEMETRY, Kind.STATE, [0], b"state"), 0.2)
    for n in range(20):
        q.put(AirItem(Klass.POSE, Kind.POSE, [0], bytes([n])), 0.2)
    q.put(AirItem(Klass.PROTOCOL, Kind.ADVERTIZE, [0], b"adv"), 0.2)
    assert q.next_item(0.3)[0] is not None  # protocol first
    sent = 0
    for _ in range(40):
        item, _ = q.next_item(0.3)
        sent += item is not None
    assert counts.throttled > 0  # the telemetry waited
    assert counts.poses_thinned == 3 and sent == 17  # 15% of 20 poses skipped, no more
    assert [len(x) for x in q.queues] == [0, 0, 1]


def test_clear_drops_everything_and_says_how_much() -> None:
    q, _ = make()
    q.put(p2p(3), 0.0)
    q.put(AirItem(Klass.POSE, Kind.POSE, [0], b"p"), 0.0)
    assert q.clear() == 2 and drain(q, 1.0) == []
