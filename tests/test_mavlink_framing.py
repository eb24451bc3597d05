"""MAVLink framing: FrameParser fed whole, byte by byte, split at every index, with
garbage around and between frames (STYLE.md point 4), plus parse_one, pack_frame and
the frame builders, checked against pymavlink as an independent implementation."""

from __future__ import annotations

import itertools
import struct

import pytest
from emu_helpers import garbage
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v10 import ardupilotmega as v1
from pymavlink.dialects.v20 import ardupilotmega as v2

from radios.errors import FrameError
from radios.mavlink import (
    MAX_FRAME_LEN,
    MSG_RADIO_STATUS,
    MSG_TUNNEL,
    SIGNATURE_LEN,
    STX_V1,
    STX_V2,
    Frame,
    FrameBuilder,
    FrameParser,
    decode,
    frame_length,
    pack_frame,
    parse_one,
    radio_status_fields,
    x25_crc,
)

# -- sample frames ------------------------------------------------------------------------


def _hb_v2(sysid: int = 1, seq: int = 0) -> bytes:
    b = FrameBuilder(sysid, 1)
    b.mav.seq = seq
    return b.heartbeat()


def _hb_v1(sysid: int = 2) -> bytes:
    mav = v1.MAVLink(None, srcSystem=sysid, srcComponent=1)
    return bytes(v1.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3).pack(mav))


def _signed(sysid: int = 3) -> bytes:
    mav = v2.MAVLink(None, srcSystem=sysid, srcComponent=1)
    mav.signing.secret_key = bytes(range(32))
    mav.signing.sign_outgoing = True
    mav.signing.link_id = 1
    mav.signing.timestamp = 1_000_000
    return bytes(v2.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3).pack(mav))


def _largest(signed: bool = False) -> bytes:
    """ENCAPSULATED_DATA with a non-zero last byte: a 255-byte payload."""
    mav = v2.MAVLink(None, srcSystem=4, srcComponent=1)
    if signed:
        mav.signing.secret_key = bytes(32)
        mav.signing.sign_outgoing = True
    data = bytes((STX_V2, 0xFF, STX_V1) * 84) + b"\x01"  # false starts inside the payload
    return bytes(v2.MAVLink_encapsulated_data_message(7, data).pack(mav))


HB = _hb_v2()
TUN = FrameBuilder(5).tunnel(bytes((STX_V2, 0xFF)) * 20)  # start bytes inside the payload
HB1 = _hb_v1()
SIGNED = _signed()
LARGE = _largest()
LARGE_SIGNED = _largest(signed=True)
RS1 = pack_frame(
    MSG_RADIO_STATUS,
    struct.pack("<HHBBBBB", 3, 0, 180, 170, 90, 40, 41),
    sysid=51,
    compid=68,
    seq=9,
    version=1,
)
SAMPLES = [HB, TUN, HB1, SIGNED, LARGE, RS1, LARGE_SIGNED]
STREAM = b"".join(SAMPLES)


def feed_all(parser: FrameParser, chunks: list[bytes]) -> list[bytes]:
    return [f.raw for chunk in chunks for f in parser.feed(chunk)]


def accounted(p: FrameParser, out: list[bytes]) -> bool:
    """Every byte fed is in a frame, skipped, or still pending."""
    return sum(map(len, out)) + p.stats.bytes_skipped + p.pending == p.stats.bytes


# -- the samples themselves -----------------------------------------------------------------


def test_sample_frames_are_what_they_claim() -> None:
    assert frame_length(LARGE) == len(LARGE) == 10 + 255 + 2
    assert frame_length(LARGE_SIGNED) == len(LARGE_SIGNED) == MAX_FRAME_LEN
    assert frame_length(SIGNED) == len(SIGNED) == 10 + 9 + 2 + SIGNATURE_LEN
    assert frame_length(HB1) == len(HB1) == 6 + 9 + 2
    assert frame_length(b"\x00\x09\x00") is None  # not a start byte
    assert frame_length(b"\xfd\x09") is None  # header incomplete
    for raw in SAMPLES:
        assert decode(raw) is not None


# -- whole input, byte by byte, split everywhere ---------------------------------------------


def test_whole_input() -> None:
    p = FrameParser()
    out = p.feed(STREAM)
    assert [f.raw for f in out] == SAMPLES
    assert (p.stats.frames, p.stats.bytes, p.stats.bytes_skipped, p.pending) == (
        len(SAMPLES),
        len(STREAM),
        0,
        0,
    )
    assert (p.stats.crc_errors, p.stats.unknown_msgid) == (0, 0)


def test_one_byte_at_a_time() -> None:
    p = FrameParser()
    out = []
    for k in range(len(STREAM)):
        got = feed_all(p, [STREAM[k : k + 1]])
        out += got
        # a frame comes out exactly when its last byte arrives
        if got:
            assert sum(map(len, out)) == k + 1
    assert out == SAMPLES
    assert p.stats.bytes_skipped == 0 and p.pending == 0


def test_split_at_every_index() -> None:
    for k in range(len(STREAM) + 1):
        p = FrameParser()
        assert feed_all(p, [STREAM[:k], STREAM[k:]]) == SAMPLES, f"split at {k}"
        assert p.pending == 0


def test_empty_feed() -> None:
    p = FrameParser()
    assert p.feed(b"") == []
    assert p.stats.bytes == 0


# -- garbage ----------------------------------------------------------------------------------


def test_garbage_before_between_and_after_without_start_bytes() -> None:
    g = [garbage(n, seed, with_stx=False) for seed, n in enumerate((50, 1, 300, 7, 40))]
    frames = [HB, TUN, SIGNED, HB1]
    data = g[0] + frames[0] + g[1] + frames[1] + g[2] + frames[2] + g[3] + frames[3] + g[4]
    for chunks in ([data], [data[k : k + 1] for k in range(len(data))]):
        p = FrameParser()
        assert feed_all(p, chunks) == frames
        assert p.stats.bytes_skipped == sum(map(len, g))
        assert p.pending == 0  # trailing garbage with no start byte is not held
        assert (p.stats.crc_errors, p.stats.unknown_msgid) == (0, 0)


def test_garbage_with_false_starts_does_not_swallow_real_frames() -> None:
    g = garbage(600, seed=1)
    assert g.count(STX_V2) > 3 and g.count(STX_V1) > 3
    # the last false starts claim up to 280 bytes: what follows the garbage must be
    # at least that long to prove them false (LARGE alone is 267 bytes)
    frames = [HB, LARGE, TUN, HB1, SIGNED]
    data = g + b"".join(frames)
    for chunks in (
        [data],
        [data[k : k + 1] for k in range(len(data))],
        [data[k : k + 61] for k in range(0, len(data), 61)],
    ):
        p = FrameParser()
        out = feed_all(p, chunks)
        assert out == frames
        assert p.stats.bytes_skipped == len(g)
        assert p.pending == 0
        assert p.stats.crc_errors + p.stats.unknown_msgid >= g.count(STX_V2)


def test_false_start_with_large_length_right_before_a_frame() -> None:
    """0xFD 0xFF claims a 267-byte frame: the heartbeat behind it is held until the
    claim is disproved by enough bytes, then comes out whole and unharmed."""
    p = FrameParser()
    assert p.feed(b"\xfd\xff" + HB) == []
    assert p.pending == 2 + len(HB)  # nothing lost while waiting
    more = [TUN, LARGE]
    out = feed_all(p, more)
    assert out == [HB, *more]
    assert p.stats.bytes_skipped == 2
    assert p.stats.crc_errors + p.stats.unknown_msgid >= 1
    assert accounted(p, out)


def test_false_v1_start_inside_garbage_between_frames() -> None:
    data = HB + b"\x00\xfe\x40\x01\x02" + TUN + b"\xfe" + SIGNED + LARGE
    p = FrameParser()
    assert feed_all(p, [data]) == [HB, TUN, SIGNED, LARGE]
    assert p.stats.bytes_skipped == 6


def test_start_byte_alone_at_the_end_is_pending_not_emitted() -> None:
    p = FrameParser()
    assert [f.raw for f in p.feed(HB + b"\xfd")] == [HB]
    assert p.pending == 1
    assert p.feed(HB[1:2]) == []  # header still incomplete
    assert p.pending == 2
    assert [f.raw for f in p.feed(HB[2:])] == [HB]  # the held start byte began a frame
    assert p.pending == 0 and p.stats.bytes_skipped == 0


def test_bad_crc_is_counted_and_skipped() -> None:
    bad = bytearray(HB)
    bad[-1] ^= 0x55
    data = TUN + bytes(bad) + SIGNED + LARGE
    for chunks in ([data], [data[k : k + 1] for k in range(len(data))]):
        p = FrameParser()
        assert feed_all(p, chunks) == [TUN, SIGNED, LARGE]
        assert p.stats.crc_errors == 1
        assert p.stats.bytes_skipped == len(bad)
        assert p.stats.frames == 3


def test_corrupted_payload_is_a_crc_error() -> None:
    bad = bytearray(TUN)
    bad[20] ^= 0x01
    p = FrameParser()
    out = feed_all(p, [bytes(bad), HB, LARGE])
    assert out == [HB, LARGE]
    assert p.stats.crc_errors >= 1
    assert accounted(p, out)


def test_unknown_msgid_is_counted_and_skipped() -> None:
    msgid = 0xABCDE
    assert msgid not in v2.mavlink_map
    hdr = struct.pack("<BBBBBBBHB", STX_V2, 4, 0, 0, 0, 1, 1, msgid & 0xFFFF, msgid >> 16)
    body = b"\x01\x02\x03\x04"
    unknown = hdr + body + struct.pack("<H", x25_crc(hdr[1:] + body, 0))
    p = FrameParser()
    assert feed_all(p, [unknown + HB + TUN]) == [HB, TUN]
    assert p.stats.unknown_msgid == 1
    assert p.stats.crc_errors == 0
    assert p.stats.bytes_skipped == len(unknown)


def test_truncated_frame_at_end_is_held_then_completed() -> None:
    p = FrameParser()
    cut = len(LARGE) - 5
    out = feed_all(p, [HB + LARGE[:cut]])
    assert out == [HB]
    assert p.pending == cut
    assert p.stats.bytes_skipped == 0
    assert feed_all(p, [LARGE[cut:]]) == [LARGE]
    assert p.pending == 0


def test_reset_forgets_a_pending_frame() -> None:
    p = FrameParser()
    p.feed(HB1[:10])
    p.reset()
    assert p.pending == 0
    assert feed_all(p, [HB1[10:] + HB]) == [HB]


# -- MAVLink 1 and signed frames ---------------------------------------------------------------


def test_mavlink1_frames() -> None:
    p = FrameParser()
    out = p.feed(HB1 + RS1)
    assert [f.raw for f in out] == [HB1, RS1]
    hb, rs = out
    assert (hb.version, hb.sysid, hb.compid, hb.msgid, hb.name, hb.payload_len) == (
        1,
        2,
        1,
        0,
        "HEARTBEAT",
        9,
    )
    assert not hb.signed
    assert (rs.version, rs.sysid, rs.compid, rs.seq, rs.msgid) == (1, 51, 68, 9, MSG_RADIO_STATUS)


def test_mavlink1_frames_rejected_when_not_accepted() -> None:
    p = FrameParser(accept_v1=False)
    assert feed_all(p, [HB1 + HB + RS1 + TUN]) == [HB, TUN]
    assert p.stats.bytes_skipped == len(HB1) + len(RS1)


def test_signed_frame_is_whole_with_its_13_signature_bytes() -> None:
    assert SIGNED[2] & 0x01  # incompat flags: signed
    assert frame_length(SIGNED) == len(SIGNED) == 10 + SIGNED[1] + 2 + 13
    for k in range(len(SIGNED) + 1):
        p = FrameParser()
        out = p.feed(SIGNED[:k]) + p.feed(SIGNED[k:] + HB)
        assert [f.raw for f in out] == [SIGNED, HB], f"split at {k}"
    f = parse_one(SIGNED)
    assert f.signed and f.version == 2 and f.sysid == 3 and len(f) == len(SIGNED)
    # pymavlink, holding the key, accepts the signature we carried through
    mav = v2.MAVLink(None)
    mav.signing.secret_key = bytes(range(32))
    assert mav.decode(bytearray(f.raw)).get_type() == "HEARTBEAT"


def test_frame_fields_of_a_mavlink2_frame() -> None:
    b = FrameBuilder(200, 7)
    b.mav.seq = 254
    raw = b.tunnel(b"abc", target_system=9)
    f = parse_one(raw)
    assert (f.version, f.sysid, f.compid, f.seq, f.msgid, f.name) == (2, 200, 7, 254, MSG_TUNNEL, "TUNNEL")
    assert f.payload == raw[10 : 10 + raw[1]]
    assert decode(f).payload_length == 3
    assert Frame(raw[:7] + b"\x01\x02\x03" + raw[10:]).name == "UNKNOWN_197121"


# -- property tests --------------------------------------------------------------------------

FRAME = st.sampled_from(SAMPLES)
NO_STX = st.binary(max_size=200).map(lambda b: bytes(x for x in b if x not in (STX_V1, STX_V2)))
SETTINGS = settings(deadline=None, max_examples=150, suppress_health_check=[HealthCheck.too_slow])


def _split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    edges = [0, *points, len(data)]
    return [data[a:b] for a, b in itertools.pairwise(edges)]


@SETTINGS
@given(data=st.binary(max_size=2000), cuts=st.lists(st.integers(0, 4000), max_size=20))
def test_arbitrary_bytes_never_raise_and_chunking_does_not_matter(data: bytes, cuts: list[int]) -> None:
    whole = FrameParser()
    out = [f.raw for f in whole.feed(data)]
    p = FrameParser()
    chunked = feed_all(p, _split(data, cuts))
    assert chunked == out
    assert accounted(p, chunked) and accounted(whole, out)
    assert p.pending < MAX_FRAME_LEN  # nothing is held beyond the longest frame


@SETTINGS
@given(
    parts=st.lists(st.tuples(NO_STX, FRAME), max_size=8),
    tail=NO_STX,
    cuts=st.lists(st.integers(0, 4000), max_size=10),
)
def test_frames_between_garbage_without_start_bytes_are_all_recovered(
    parts: list[tuple[bytes, bytes]], tail: bytes, cuts: list[int]
) -> None:
    data = b"".join(g + f for g, f in parts) + tail
    p = FrameParser()
    assert feed_all(p, _split(data, cuts)) == [f for _, f in parts]
    assert p.stats.bytes_skipped == sum(len(g) for g, _ in parts) + len(tail)
    assert p.pending == 0


@SETTINGS
@given(
    parts=st.lists(st.tuples(st.binary(max_size=400), FRAME), min_size=1, max_size=5),
    cuts=st.lists(st.integers(0, 4000), max_size=10),
)
def test_arbitrary_garbage_cannot_swallow_frames_it_cannot_reach(
    parts: list[tuple[bytes, bytes]], cuts: list[int]
) -> None:
    """No frame is longer than 280 bytes, so a false start inside garbage followed by
    280 bytes with no start byte is resolved before the next real frame begins: that
    frame must come out. (Garbage may itself hold valid frames; those come out too.)"""
    pad = bytes(MAX_FRAME_LEN)
    data = b"".join(g + pad + f for g, f in parts)
    expected: list[bytes] = []
    for g, f in parts:
        expected += [x.raw for x in FrameParser().feed(g + pad)] + [f]
    p = FrameParser()
    assert feed_all(p, _split(data, cuts)) == expected
    assert p.pending == 0


@SETTINGS
@given(data=st.binary(max_size=400))
def test_parse_one_and_decode_raise_only_frame_error(data: bytes) -> None:
    try:
        f = parse_one(data)
    except FrameError:
        pass
    else:
        assert f.raw == data
    try:
        decode(data)
    except FrameError:
        pass


# -- parse_one -------------------------------------------------------------------------------


def test_parse_one_accepts_exactly_one_valid_frame() -> None:
    for raw in SAMPLES:
        assert parse_one(raw).raw == raw


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (bytes(MAX_FRAME_LEN + 1), "larger than any MAVLink frame"),
        (LARGE_SIGNED + b"\x00", "larger than any MAVLink frame"),
        (HB + HB, "not exactly one"),
        (HB + b"\x00", "not exactly one"),
        (HB[:-1], "not exactly one"),
        (b"", "not exactly one"),
        (b"\x00" + HB[1:], "not exactly one"),
        (HB[:-1] + bytes((HB[-1] ^ 1,)), "bad CRC"),
    ],
    ids=[
        "oversize",
        "oversize-by-one",
        "two-frames",
        "trailing-byte",
        "truncated",
        "empty",
        "no-start-byte",
        "bad-crc",
    ],
)
def test_parse_one_errors(data: bytes, message: str) -> None:
    with pytest.raises(FrameError, match=message):
        parse_one(data)


def test_frame_error_is_a_value_error() -> None:
    with pytest.raises(ValueError):
        parse_one(b"nope")


# -- pack_frame and RADIO_STATUS --------------------------------------------------------------

FIELDS = {"rxerrors": 513, "fixed": 7, "rssi": 180, "remrssi": 175, "txbuf": 93, "noise": 41, "remnoise": 39}


def _rs_payload(fields: dict[str, int]) -> bytes:
    f = fields
    return struct.pack(
        "<HHBBBBB", f["rxerrors"], f["fixed"], f["rssi"], f["remrssi"], f["txbuf"], f["noise"], f["remnoise"]
    )


@pytest.mark.parametrize("version", [1, 2])
def test_pack_frame_radio_status_decodes_with_pymavlink(version: int) -> None:
    raw = pack_frame(MSG_RADIO_STATUS, _rs_payload(FIELDS), sysid=51, compid=68, seq=300, version=version)
    dialect = v1 if version == 1 else v2
    msg = dialect.MAVLink(None).decode(bytearray(raw))
    assert msg.get_type() == "RADIO_STATUS"
    assert {k: getattr(msg, k) for k in FIELDS} == FIELDS
    assert (msg.get_srcSystem(), msg.get_srcComponent(), msg.get_seq()) == (51, 68, 300 & 0xFF)
    f = parse_one(raw)
    assert f.version == version
    assert radio_status_fields(f) == FIELDS


def test_pack_frame_v2_truncates_trailing_zeros_as_pymavlink_does() -> None:
    fields = dict(FIELDS, noise=0, remnoise=0)
    raw = pack_frame(MSG_RADIO_STATUS, _rs_payload(fields), sysid=51, compid=68, seq=1)
    mav = v2.MAVLink(None, srcSystem=51, srcComponent=68)
    mav.seq = 1
    ref = bytes(
        v2.MAVLink_radio_status_message(
            fields["rssi"],
            fields["remrssi"],
            fields["txbuf"],
            fields["noise"],
            fields["remnoise"],
            fields["rxerrors"],
            fields["fixed"],
        ).pack(mav)
    )
    assert raw == ref
    assert raw[1] == 7
    assert radio_status_fields(parse_one(raw)) == fields


def test_pack_frame_all_zero_payload_keeps_one_byte() -> None:
    raw = pack_frame(MSG_RADIO_STATUS, bytes(9), sysid=51, compid=68, seq=0)
    assert raw[1] == 1
    assert radio_status_fields(parse_one(raw)) == dict.fromkeys(FIELDS, 0)


# -- builders and CRC --------------------------------------------------------------------------


def test_frame_builder_sequence_wraps() -> None:
    b = FrameBuilder(9)
    seqs = [parse_one(b.heartbeat()).seq for _ in range(258)]
    assert seqs[:3] == [0, 1, 2]
    assert seqs[255:] == [255, 0, 1]


@pytest.mark.parametrize(("sysid", "compid"), [(0, 0), (256, 0), (1, -1), (1, 256)])
def test_frame_builder_rejects_bad_ids(sysid: int, compid: int) -> None:
    with pytest.raises(FrameError):
        FrameBuilder(sysid, compid)


def test_tunnel_payload_limit() -> None:
    b = FrameBuilder(1)
    f = parse_one(b.tunnel(bytes(range(1, 129))))
    assert decode(f).payload[:128] == list(range(1, 129))
    with pytest.raises(FrameError, match="exceeds 128"):
        b.tunnel(bytes(129))


def test_decode_errors_are_frame_errors() -> None:
    with pytest.raises(FrameError, match="cannot decode"):
        decode(HB[:-1] + bytes((HB[-1] ^ 1,)))


def test_crc_matches_pymavlink() -> None:
    for raw in SAMPLES:
        f = parse_one(raw)
        end = (10 if f.version == 2 else 6) + f.payload_len
        extra = v2.mavlink_map[f.msgid].crc_extra
        ref = v2.x25crc(raw[1:end])
        ref.accumulate(bytes((extra,)))
        assert x25_crc(raw[1:end], extra) == ref.crc == struct.unpack("<H", raw[end : end + 2])[0]
