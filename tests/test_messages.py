"""The compact codec: round trips of every message type, sizes against the issue's
targets, and decode() on arbitrary bytes raising only DecodeError."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.core.wire.message_types import (
    ADV_SIZE,
    ADV_SWARM,
    AckResult,
    Advertize,
    AgentNotice,
    AgentState,
    Assignment,
    Command,
    CommandAck,
    CommandKind,
    GSAdvertize,
    GSConnect,
    GSConnectAck,
    GSHeartbeat,
    Heartbeat,
    HeartbeatAck,
    NameConflict,
    NoticeSource,
    Phase,
    PoolStatus,
    Pose,
    PoseReport,
    Selection,
    Side,
    StartPool,
    StartPoolAck,
    SyncPool,
    SyncPoolAck,
    Task,
    TaskKind,
    Telemetry,
    pool_digest,
)
from swarm.core.wire.messages import decode, encode, message_types
from swarm.errors import DecodeError, MessageError, VersionMismatch

ids = st.integers(1, 250)
pools = st.frozensets(ids, max_size=60)
names = st.from_regex(r"[A-Za-z0-9_-]{1,16}", fullmatch=True)
# poses on the codec's grid, so a round trip is exact
poses = st.builds(
    Pose,
    lat=st.integers(-900_000_000, 900_000_000).map(lambda v: v / 1e7),
    lon=st.integers(-1_800_000_000, 1_800_000_000).map(lambda v: v / 1e7),
    alt=st.integers(0, 65535).map(lambda v: v / 10.0 - 1000.0),
    heading=st.integers(0, 35999).map(lambda v: v / 100.0),
    vn=st.integers(-128, 127).map(lambda v: v / 4.0),
    ve=st.integers(-128, 127).map(lambda v: v / 4.0),
    t=st.integers(0, 255).map(lambda v: v / 100.0),
)
tasks = st.one_of(
    st.builds(Task, kind=st.sampled_from([TaskKind.NONE, TaskKind.HOLD])),
    st.builds(
        Task,
        kind=st.just(TaskKind.FOLLOW),
        heading=st.integers(0, 35999).map(lambda v: v / 100.0),
        back_m=st.integers(0, 255).map(lambda v: v / 4.0),
        side_m=st.integers(0, 255).map(lambda v: v / 4.0),
        assignments=st.lists(st.builds(Assignment, ids, ids, st.sampled_from(Side)), max_size=20).map(tuple),
        gen=st.integers(0, 255),
        turn_rate=st.integers(-127, 127).map(lambda v: v / 2.0),
    ),
)
headings = st.integers(0, 35999).map(lambda v: v / 100.0)
commands = st.one_of(
    st.builds(
        Command,
        st.integers(1, 255),
        st.integers(0, 65535),
        st.integers(0, 250),
        st.sampled_from(
            [CommandKind.ARM, CommandKind.DISARM, CommandKind.LAND, CommandKind.RETURN, CommandKind.STOP]
        ),
    ),
    st.builds(
        Command,
        st.integers(1, 255),
        st.integers(0, 65535),
        st.integers(0, 250),
        st.just(CommandKind.TAKEOFF),
        alt=st.integers(0, 65535).map(lambda v: v / 10.0),
    ),
    st.builds(
        Command,
        st.integers(1, 255),
        st.integers(0, 65535),
        st.integers(0, 250),
        st.just(CommandKind.FOLLOW),
        heading=headings,
    ),
    st.builds(
        Command,
        st.integers(1, 255),
        st.integers(0, 65535),
        st.integers(0, 250),
        st.just(CommandKind.GOTO),
        lat=st.integers(-900_000_000, 900_000_000).map(lambda v: v / 1e7),
        lon=st.integers(-1_800_000_000, 1_800_000_000).map(lambda v: v / 1e7),
        alt=st.integers(0, 65535).map(lambda v: v / 10.0 - 1000.0),
    ),
)
messages = st.one_of(
    st.builds(Advertize, ids, names, st.integers(0, 255).map(lambda f: f & ~(ADV_SIZE | ADV_SWARM))),
    st.builds(Advertize, ids, names, st.integers(0, 255).map(lambda f: f & ~ADV_SWARM | ADV_SIZE), ids),
    st.builds(  # capped and named
        Advertize,
        ids,
        names,
        st.integers(0, 255).map(lambda f: f | ADV_SIZE | ADV_SWARM),
        ids,
        st.integers(1, 65535),
    ),
    st.builds(GSAdvertize, st.integers(1, 255), names),
    st.builds(Heartbeat, ids, st.integers(0, 65535), st.integers(0, 255), pools, tasks),
    st.builds(HeartbeatAck, ids, st.integers(0, 255), poses),
    st.builds(StartPool, ids),
    st.builds(StartPoolAck, ids, st.sampled_from(PoolStatus), st.booleans(), pools),
    st.builds(SyncPool, ids, st.integers(0, 2**32 - 1), st.booleans(), st.one_of(st.none(), pools)),
    st.builds(SyncPoolAck, ids, st.booleans(), st.booleans(), pools),
    st.builds(Selection, ids, ids, st.integers(0, 2**32 - 1), st.integers(0, 65535)),
    st.builds(PoseReport, poses),
    st.builds(
        AgentState,
        ids,
        st.sampled_from(Phase),
        st.integers(0, 250),
        st.integers(0, 250),
        st.integers(0, 2**32 - 1),
        st.integers(0, 65535),
        st.booleans(),
        pools,
        pools,
    ),
    st.builds(GSConnect, st.integers(1, 255), st.integers(0, 65535)),
    st.builds(GSConnectAck, ids, st.integers(0, 65535), st.integers(0, 65535)),
    st.builds(
        Telemetry,
        ids,
        poses,
        st.integers(0, 255),
        st.integers(0, 255),
        st.sampled_from(Phase),
        st.integers(0, 250),
        st.integers(0, 255),
        st.integers(0, 255),
        st.integers(0, 255),
        st.integers(0, 255).map(lambda v: v / 4.0),
    ),
    st.builds(GSHeartbeat, st.integers(1, 255), st.integers(0, 255)),
    commands,
    st.builds(CommandAck, ids, st.integers(0, 65535), st.sampled_from(AckResult), st.text(max_size=8)),
    st.builds(NameConflict, ids, names, ids),
    st.builds(
        AgentNotice,
        ids,
        st.sampled_from(NoticeSource),
        st.integers(0, 7),
        st.text(st.characters(codec="utf-8", categories=("L", "N", "P", "S")), min_size=1, max_size=16),
        st.integers(0, 255),
    ),
)


@given(messages)
@settings(max_examples=400)
def test_round_trip(msg: object) -> None:
    assert decode(encode(msg)) == msg  # type: ignore[arg-type]


@given(st.binary(max_size=80))
@settings(max_examples=2000)
def test_decode_any_bytes_returns_message_or_decode_error(data: bytes) -> None:
    try:
        msg = decode(data)
    except DecodeError:
        return
    assert encode(msg) == data  # a decoded message re-encodes to the same bytes


@given(messages, st.data())
@settings(max_examples=300)
def test_truncated_or_extended_messages_are_rejected(msg: object, data: st.DataObject) -> None:
    raw = encode(msg)  # type: ignore[arg-type]
    cut = data.draw(st.integers(0, len(raw) - 1))
    with pytest.raises(DecodeError):
        decode(raw[:cut])
    with pytest.raises(DecodeError):
        decode(raw + b"\x00")


# -- canonical encoding: one message, one byte string ---------------------------------


@given(messages, st.data())
@settings(max_examples=1500, deadline=None)  # a loaded machine takes 250 ms for one example
def test_mutated_messages_decode_only_to_their_own_bytes(msg: object, data: st.DataObject) -> None:
    """Valid messages with a byte changed, inserted or removed: whatever still decodes must
    re-encode to exactly the bytes received (a decoder that accepts two spellings of one
    message lets a signed frame be altered in meaning-preserving ways, and hides bugs)."""
    raw = bytearray(encode(msg))  # type: ignore[arg-type]
    for _ in range(data.draw(st.integers(1, 3))):
        at = data.draw(st.integers(0, len(raw)))
        op = data.draw(st.sampled_from(["set", "insert", "delete"]))
        value = data.draw(st.integers(0, 255))
        if op == "set" and at < len(raw):
            raw[at] = value
        elif op == "insert":
            raw.insert(at, value)
        elif op == "delete" and at < len(raw) and len(raw) > 1:
            del raw[at]
    try:
        got = decode(bytes(raw))
    except DecodeError:
        return
    assert encode(got) == bytes(raw)


def _start_pool_ack(pool_bytes: bytes) -> bytes:
    return encode(StartPoolAck(1, PoolStatus.SUCCESS, False, frozenset()))[:-1] + pool_bytes


def _bitmap(ids: list[int]) -> bytes:
    bits = bytearray(32)
    for i in ids:
        bits[i >> 3] |= 1 << (i & 7)
    return b"\x80" + bytes(bits)


@pytest.mark.parametrize(
    ("what", "raw"),
    [
        ("a small pool sent as a bitmap", _start_pool_ack(_bitmap([1, 2, 3]))),
        ("a bitmap pool holding id 0", _start_pool_ack(_bitmap([0, *range(1, 40)]))),
        ("a bitmap pool holding id 251", _start_pool_ack(_bitmap([*range(1, 40), 251]))),
        ("a bitmap pool holding the station's 255", _start_pool_ack(_bitmap([*range(1, 40), 255]))),
        ("a list pool holding id 0", _start_pool_ack(bytes([2, 0, 5]))),
        ("a list pool holding id 253", _start_pool_ack(bytes([2, 5, 253]))),
        (
            "a leader id of 252 in AgentState",
            encode(AgentState(3, Phase.MEMBER, 1, 0, 0, 0, False, frozenset(), frozenset()))[:3]
            + bytes([252])
            + encode(AgentState(3, Phase.MEMBER, 1, 0, 0, 0, False, frozenset(), frozenset()))[4:],
        ),
        (
            "a command to the station's own id",
            encode(Command(255, 1, 7, CommandKind.LAND))[:4]
            + bytes([255])
            + encode(Command(255, 1, 7, CommandKind.LAND))[5:],
        ),
        (
            "a turn rate of -128 (the encoder writes -127..127)",
            encode(Heartbeat(1, 2, 3, frozenset({1}), Task(TaskKind.FOLLOW)))[:-2] + b"\x80\x00",
        ),
        (
            "a formation slot following agent 0",
            encode(
                Heartbeat(
                    1, 2, 3, frozenset({1}), Task(TaskKind.FOLLOW, assignments=(Assignment(2, 1, Side.LEFT),))
                )
            )[:-2]
            + b"\x00\xff",
        ),
    ],
)
def test_non_canonical_or_out_of_range_ids_are_refused(what: str, raw: bytes) -> None:
    with pytest.raises(DecodeError):
        decode(raw)


def test_pools_hold_agent_ids_only() -> None:
    for bad in (0, 251, 255):
        with pytest.raises(MessageError):
            encode(StartPoolAck(1, PoolStatus.SUCCESS, False, frozenset({1, bad})))
    with pytest.raises(MessageError):
        encode(AgentState(3, Phase.MEMBER, 251, 0, 0, 0, False, frozenset(), frozenset()))


def test_every_type_is_covered_by_the_strategies() -> None:
    built = {b.target for b in _builds(messages)}  # every `builds(Cls, ...)` in the strategy
    assert set(message_types()) <= built


def _builds(strategy: object) -> list[object]:
    """The builds() strategies inside a one_of tree (hypothesis internals kept out of
    the assertion: only their target classes are read)."""
    out: list[object] = []
    stack = [strategy]
    while stack:
        s = stack.pop()
        s = getattr(s, "wrapped_strategy", s)
        if hasattr(s, "original_strategies"):
            stack.extend(s.original_strategies)
        elif hasattr(s, "target"):
            out.append(s)
    return out


POSE = Pose(47.3977419, 8.5455939, 503.4, 271.5, 3.25, -1.5, 1.23)


def test_sizes_meet_the_targets() -> None:
    assert len(encode(PoseReport(POSE))) <= 16
    assert len(encode(HeartbeatAck(2, 17, POSE))) <= 18
    assert len(encode(SyncPool(3, pool_digest({1, 2, 3}), locked=True))) <= 8
    assert len(encode(StartPool(3))) == 2


def test_pose_quantisation_is_centimetric() -> None:
    d = decode(encode(PoseReport(POSE)))
    assert isinstance(d, PoseReport)
    assert abs(d.pose.lat - POSE.lat) < 1e-7 and abs(d.pose.lon - POSE.lon) < 1e-7
    assert abs(d.pose.alt - POSE.alt) <= 0.05
    assert d.pose.heading == POSE.heading and d.pose.vn == 3.25 and d.pose.ve == -1.5


def test_large_pools_use_the_bitmap_and_small_pools_the_list() -> None:
    small = encode(StartPoolAck(1, PoolStatus.SUCCESS, False, frozenset(range(1, 11))))
    big = encode(StartPoolAck(1, PoolStatus.SUCCESS, False, frozenset(range(1, 101))))
    assert len(small) == 1 + 1 + 1 + 1 + 1 + 10
    assert len(big) == 1 + 1 + 1 + 1 + 1 + 32


def test_digest_ignores_order_and_duplicates() -> None:
    assert pool_digest([3, 1, 2, 2]) == pool_digest({1, 2, 3}) != pool_digest({1, 2})


def test_version_mismatch_is_clear() -> None:
    raw = bytearray(encode(StartPool(3)))
    raw[0] = (2 << 5) | (raw[0] & 0x1F)
    with pytest.raises(VersionMismatch, match=r"v2.*v1"):
        decode(bytes(raw))


@pytest.mark.parametrize(
    "bad",
    [
        lambda: encode(Advertize(3, "bad/name")),
        lambda: encode(Advertize(0, "agent")),
        lambda: encode(Advertize(251, "agent")),
        lambda: Pose(math.nan, 0.0, 0.0),
        lambda: Pose(91.0, 0.0, 0.0),
        lambda: encode(Command(255, 1, 0, CommandKind.FOLLOW, heading=400.0)),
        lambda: encode(Command(255, 1, 0, CommandKind.FOLLOW, heading=math.inf)),
        lambda: encode(CommandAck(3, 1, AckResult.REJECTED, "x" * 97)),
    ],
)
def test_our_own_bad_messages_raise_message_error(bad: object) -> None:
    with pytest.raises(MessageError):
        bad()  # type: ignore[operator]
