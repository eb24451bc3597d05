"""The .tlog format: writer, streaming reader, and damage detection."""

from __future__ import annotations

import contextlib
import os
import random
import struct
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from radios.errors import CaptureDamagedError, CaptureError, FrameError
from radios.mavlink import MSG_RADIO_STATUS, FrameBuilder, pack_frame, parse_one
from radios.tlog import TlogRecord, TlogWriter, read_tlog

T0 = 1_700_000_000.0


def sample_frames(n: int) -> list[bytes]:
    """A mix of frame kinds and sizes from three systems, plus MAVLink 1."""
    builders = [FrameBuilder(1, 1), FrameBuilder(2, 1), FrameBuilder(3, 191)]
    out: list[bytes] = []
    for i in range(n):
        b = builders[i % 3]
        if i % 4 == 0:
            out.append(b.heartbeat())
        elif i % 4 == 3:
            out.append(pack_frame(MSG_RADIO_STATUS, bytes(range(9)), sysid=51, compid=68, seq=i, version=1))
        else:
            out.append(b.tunnel(bytes([i % 256]) * (i % 50)))
    return out


def write_capture(path: Path, frames: list[bytes], times: list[float] | None = None) -> list[int]:
    """Write ``frames`` stamped ``times`` (default T0 + 0.1 i); return record offsets."""
    offsets = []
    pos = 0
    with TlogWriter(path) as w:
        for i, raw in enumerate(frames):
            w.write(raw, T0 + 0.1 * i if times is None else times[i])
            offsets.append(pos)
            pos += 8 + len(raw)
    return offsets


def read_all(path: Path) -> tuple[list[TlogRecord], CaptureDamagedError | None]:
    records: list[TlogRecord] = []
    try:
        for rec in read_tlog(path):
            records.append(rec)
    except CaptureDamagedError as exc:
        return records, exc
    return records, None


# -- round trip -----------------------------------------------------------------------


def test_round_trip_keeps_frames_times_and_offsets(tmp_path: Path) -> None:
    frames = sample_frames(30)
    times = [T0 + 0.123457 * i for i in range(30)]
    path = tmp_path / "flight.tlog"
    offsets = write_capture(path, frames, times)
    records, damage = read_all(path)
    assert damage is None
    assert [r.raw for r in records] == frames
    assert [r.offset for r in records] == offsets
    for rec, t in zip(records, times, strict=True):
        assert rec.t == pytest.approx(t, abs=1e-6)
        assert rec.frame.raw == rec.raw
        assert rec.size == 8 + len(rec.raw)


def test_file_layout_is_big_endian_microseconds_then_frame(tmp_path: Path) -> None:
    raw = FrameBuilder(1, 1).heartbeat()
    path = tmp_path / "one.tlog"
    with TlogWriter(path) as w:
        w.write(raw, 1_700_000_000.25)
    data = path.read_bytes()
    assert data[:8] == struct.pack(">Q", 1_700_000_000_250_000)
    assert data[8:] == raw


def test_writer_counts_and_uses_its_clock(tmp_path: Path) -> None:
    ticks = iter([T0, T0 + 1.5])
    path = tmp_path / "c.tlog"
    frames = sample_frames(2)
    w = TlogWriter(path, clock=lambda: next(ticks))
    w.write(frames[0])
    w.write(parse_one(frames[1]))  # a Frame is accepted too
    assert w.records == 2
    assert w.bytes_written == 16 + len(frames[0]) + len(frames[1])
    w.flush()
    assert os.path.getsize(path) == w.bytes_written  # written through, even before close
    w.close()
    w.close()  # safe twice
    assert w.closed
    assert [r.t for r in read_tlog(path)] == [T0, T0 + 1.5]


def test_writer_after_close_and_bad_input(tmp_path: Path) -> None:
    w = TlogWriter(tmp_path / "c.tlog")
    raw = FrameBuilder(1).heartbeat()
    with pytest.raises(FrameError):
        w.write(raw[:-1], T0)
    with pytest.raises(FrameError):
        w.write(b"hello", T0)
    for bad_t in (-1.0, float("nan"), float("inf"), 2.0**64):
        with pytest.raises(ValueError):
            w.write(raw, bad_t)
    assert w.records == 0
    w.close()
    with pytest.raises(CaptureError, match="closed"):
        w.write(raw, T0)


def test_writer_is_thread_safe(tmp_path: Path) -> None:
    path = tmp_path / "threads.tlog"
    per_thread = 300

    def work(w: TlogWriter, sysid: int) -> None:
        b = FrameBuilder(sysid)
        for i in range(per_thread):
            w.write(b.tunnel(bytes([sysid]) * (i % 100)), T0 + i * 1e-3)

    with TlogWriter(path) as w:
        threads = [threading.Thread(target=work, args=(w, s)) for s in range(1, 9)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    records, damage = read_all(path)
    assert damage is None
    assert len(records) == 8 * per_thread
    for sysid in range(1, 9):
        mine = [r for r in records if r.frame.sysid == sysid]
        assert [r.frame.seq for r in mine] == [i % 256 for i in range(per_thread)]


def test_empty_file_has_no_records(tmp_path: Path) -> None:
    path = tmp_path / "empty.tlog"
    path.write_bytes(b"")
    assert list(read_tlog(path)) == []


def test_reader_is_a_context_manager_and_closes(tmp_path: Path) -> None:
    path = tmp_path / "c.tlog"
    write_capture(path, sample_frames(5))
    with read_tlog(path) as reader:
        first = next(reader)
        assert reader.records == 1
        assert reader.offset == first.size
    assert list(reader) == []  # closed: iteration simply ends
    reader.close()


# -- open errors ----------------------------------------------------------------------


def test_missing_file_raises_capture_error_at_open(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="no such file") as info:
        read_tlog(tmp_path / "nope.tlog")
    assert not isinstance(info.value, CaptureDamagedError)


def test_directory_is_not_a_capture(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="directory"):
        read_tlog(tmp_path)


def test_writer_missing_directory_fails_at_open(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such" / "dir"
    with pytest.raises(CaptureError, match="does not exist") as info:
        TlogWriter(missing / "c.tlog")
    assert str(missing) in str(info.value)


def test_writer_unwritable_paths_fail_at_open(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="is a directory"):
        TlogWriter(tmp_path)
    plain = tmp_path / "plain-file"
    plain.write_text("x")
    with pytest.raises(CaptureError, match="not a directory"):
        TlogWriter(plain / "c.tlog")


# -- damage -----------------------------------------------------------------------------


def test_truncated_at_every_byte_of_the_last_record(tmp_path: Path) -> None:
    frames = sample_frames(6)
    full = tmp_path / "full.tlog"
    offsets = write_capture(full, frames)
    data = full.read_bytes()
    last = offsets[-1]
    cut_path = tmp_path / "cut.tlog"
    # cutting exactly at the record boundary leaves a clean, shorter file
    cut_path.write_bytes(data[:last])
    records, damage = read_all(cut_path)
    assert damage is None and len(records) == 5
    for cut in range(last + 1, len(data)):
        cut_path.write_bytes(data[:cut])
        records, damage = read_all(cut_path)
        assert [r.raw for r in records] == frames[:5], cut
        assert damage is not None, cut
        assert damage.offset == last
        assert damage.records == 5
        reason = "truncated timestamp" if cut - last < 8 else "truncated frame"
        assert str(damage) == (f"{cut_path}: damaged record at byte {last} ({reason}) after 5 whole records")


def test_every_flipped_frame_byte_in_the_middle_is_caught(tmp_path: Path) -> None:
    frames = sample_frames(9)
    full = tmp_path / "full.tlog"
    offsets = write_capture(full, frames)
    data = full.read_bytes()
    k = 4
    start, end = offsets[k], offsets[k + 1]
    bad = tmp_path / "bad.tlog"
    # the frame bytes, and the high timestamp bytes (a change of a day or more)
    positions = list(range(start + 8, end)) + list(range(start, start + 4))
    msgid_bytes = range(start + 8 + 7, start + 8 + 10)
    for pos in positions:
        corrupt = bytearray(data)
        corrupt[pos] ^= 0xFF
        bad.write_bytes(bytes(corrupt))
        reader = read_tlog(bad)
        records, damage = read_all(bad)
        if pos in msgid_bytes and damage is None:  # now an id nobody knows: skipped, counted
            rest = list(reader)
            assert [r.raw for r in rest] == frames[:k] + frames[k + 1 :], pos
            assert sum(reader.unknown.values()) == 1, pos
            continue
        assert [r.raw for r in records] == frames[:k], pos
        assert damage is not None, pos
        assert (damage.offset, damage.records) == (start, k), pos


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda raw: raw[:-1] + bytes([raw[-1] ^ 0x01]), "bad frame CRC"),
        (lambda raw: b"\x42" + raw[1:], "no MAVLink start byte (0x42)"),
    ],
)
def test_damage_reasons(tmp_path: Path, mutate: Callable[[bytes], bytes], reason: str) -> None:
    frames = sample_frames(3)
    path = tmp_path / "d.tlog"
    with TlogWriter(path) as w:
        w.write(frames[0], T0)
        w.write(frames[1], T0 + 1)
    with open(path, "ab") as f:
        f.write(struct.pack(">Q", int((T0 + 2) * 1e6)) + mutate(frames[2]))
    records, damage = read_all(path)
    assert len(records) == 2
    assert damage is not None
    assert f"({reason})" in str(damage)
    assert damage.records == 2


def test_a_message_id_nobody_here_knows_is_skipped_and_counted(tmp_path: Path) -> None:
    """A real PX4 capture holds message ids the dialect here lacks (411, its events
    protocol): reading stopped at the first one as if the file were damaged."""
    frames = sample_frames(3)
    # well-formed MAVLink 2 frames naming ids no dialect here knows (411, and 0x0F1234)
    px4 = bytes([0xFD, 1, 0, 0, 0, 1, 1, 0x9B, 0x01, 0x00, 7, 0x55, 0xAA])
    odd = bytes([0xFD, 1, 0, 0, 0, 1, 1, 0x34, 0x12, 0x0F, 0, 0, 0])
    path = tmp_path / "u.tlog"
    with TlogWriter(path) as w:
        for i, raw in enumerate([frames[0], px4, px4, frames[1], odd, frames[2]]):
            w.write(raw, T0 + i)
    reader = read_tlog(path)
    assert [r.raw for r in reader] == frames
    assert reader.unknown == {411: 2, 0x0F1234: 1}


@pytest.mark.parametrize(
    ("times", "good", "reason"),
    [
        ([T0, 12.5], 1, "implausible timestamp 1970-01-01"),
        ([T0, 4_200_000_000.0], 1, "implausible timestamp"),
        ([T0, T0 + 1, T0 + 1 + 90_000], 2, "+90000 s from the previous record"),
        ([T0, T0 + 1, T0 + 1 - 90_000], 2, "-90000 s from the previous record"),
    ],
)
def test_implausible_timestamps(tmp_path: Path, times: list[float], good: int, reason: str) -> None:
    path = tmp_path / "t.tlog"
    write_capture(path, sample_frames(len(times)), times)
    records, damage = read_all(path)
    assert len(records) == good
    assert damage is not None and reason in str(damage)


def test_small_steps_backwards_are_fine(tmp_path: Path) -> None:
    # two threads stamping one capture may be a little out of order
    path = tmp_path / "t.tlog"
    write_capture(path, sample_frames(3), [T0, T0 - 0.001, T0 + 0.5])
    records, damage = read_all(path)
    assert damage is None and len(records) == 3


@pytest.mark.parametrize(
    "content",
    [
        b"this is not a tlog, just some text\n" * 10,
        random.Random(7).randbytes(4096),
        b"\x00" * 100,
    ],
)
def test_garbage_file(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "garbage.tlog"
    path.write_bytes(content)
    records, damage = read_all(path)
    assert records == []
    assert damage is not None
    assert (damage.offset, damage.records) == (0, 0)
    assert "after 0 whole records" in str(damage)


def test_large_capture_streams(tmp_path: Path) -> None:
    path = tmp_path / "big.tlog"
    raw = FrameBuilder(1).tunnel(b"x" * 100)
    n = 50_000
    with TlogWriter(path) as w:
        for i in range(n):
            w.write(raw, T0 + i * 0.01)
    count = 0
    last = None
    reader = read_tlog(path)
    for rec in reader:
        count += 1
        last = rec
    assert count == n
    assert last is not None and last.offset == (n - 1) * (8 + len(raw))


_GOOD = sample_frames(8)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    cut=st.integers(min_value=0, max_value=2000),
    flips=st.lists(st.tuples(st.integers(0, 2000), st.integers(1, 255)), max_size=4),
    tail=st.binary(max_size=40),
)
def test_only_damage_errors_escape(
    tmp_path: Path, cut: int, flips: list[tuple[int, int]], tail: bytes
) -> None:
    path = tmp_path / "fuzz.tlog"
    write_capture(path, _GOOD)
    data = bytearray(path.read_bytes())
    for pos, x in flips:
        if pos < len(data):
            data[pos] ^= x
    data = data[: cut + 1] + tail if cut < len(data) else data + tail
    path.write_bytes(bytes(data))
    records, damage = read_all(path)  # anything but CaptureDamagedError fails the test
    for rec in records:
        assert parse_one(rec.raw).raw == rec.raw  # every yielded frame is whole and valid
    if damage is not None:
        assert damage.records == len(records)
        skipped = read_tlog(path)
        with contextlib.suppress(CaptureDamagedError):
            list(skipped)
        if not skipped.unknown:  # else frames of unknown ids were skipped before it
            assert damage.offset == sum(r.size for r in records)
