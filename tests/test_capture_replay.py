"""Capture wrapper, the replay link, the Player, decoding and statistics.

Pacing tests run on a manual clock whose sleep only records the request and moves
the clock: no test waits for real time.
"""

from __future__ import annotations

import json
import math
import os
import re
import select
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from net_helpers import ManualClock
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as dialect

from radios.capture import CaptureLink
from radios.errors import (
    CaptureDamagedError,
    CaptureError,
    ConfigError,
    LinkClosedError,
    LinkOpenError,
)
from radios.link import open_link
from radios.mavlink import MSG_RADIO_STATUS, FrameBuilder, FrameParser, pack_frame
from radios.replay import (
    AIRTIME_OVERHEAD_BYTES,
    Pacer,
    Player,
    TlogLink,
    capture_stats,
    decode_record,
    format_record,
    open_tlog_link,
)
from radios.seriallink import open_serial
from radios.tlog import TlogRecord, TlogWriter, read_tlog

T0 = 1_700_000_000.0


def make_capture(path: Path, times: list[float]) -> list[bytes]:
    b = FrameBuilder(1, 1)
    frames = [b.tunnel(bytes([i]) * 10) if i % 2 else b.heartbeat() for i in range(len(times))]
    with TlogWriter(path) as w:
        for raw, t in zip(frames, times, strict=True):
            w.write(raw, t)
    return frames


# -- capture ---------------------------------------------------------------------------
#
# pyserial's loop:// is opened with open_serial and wrapped by hand: open_link("loop://")
# is refused by radios/link.py's scheme check at the time of writing (reported). The
# open_link(..., capture=) wiring is exercised on a real pty below.


def loop_capture(path: Path, **kw: Any) -> CaptureLink:
    return CaptureLink(open_serial("loop://"), path, **kw)


def test_capture_link_over_loop_records_both_directions(tmp_path: Path) -> None:
    path = tmp_path / "loop.tlog"
    b = FrameBuilder(7, 1)
    sent = [b.heartbeat(), b.tunnel(b"hello"), b.tunnel(b"world" * 20)]
    before = time.time()
    link = loop_capture(path)
    with link:
        for raw in sent:
            link.send(raw)
        received: list[bytes] = []
        while len(received) < len(sent):
            frame = link.recv(timeout=5)
            assert frame is not None, "loop:// did not echo the frame"
            received.append(frame.raw)
        assert received == sent
        stats = link.stats
        assert stats is link.inner.stats
        assert (stats.frames_out, stats.frames_in) == (3, 3)
        assert stats.bytes_out == stats.bytes_in == sum(map(len, sent))
    after = time.time()
    assert link.closed and link.inner.closed
    link.close()  # safe twice
    records = list(read_tlog(path))
    assert [r.raw for r in records] == sent + sent  # all sends, then the echoes
    assert all(before <= r.t <= after for r in records)
    assert [r.t for r in records] == sorted(r.t for r in records)


def test_capture_link_stamps_with_its_clock_and_keeps_the_contract(tmp_path: Path) -> None:
    path = tmp_path / "c.tlog"
    ticks = iter([T0, T0 + 0.25])
    link = loop_capture(path, clock=lambda: next(ticks))
    b = FrameBuilder(2)
    raw = b.heartbeat()
    link.send(raw)
    frame = link.recv(timeout=5)
    assert frame is not None and frame.raw == raw
    assert link.recv(timeout=0) is None  # nothing more: nothing recorded
    assert link.can_send and link.can_recv
    assert link.path == str(path)
    link.close()
    with pytest.raises(LinkClosedError):
        link.send(raw)
    assert [(r.t, r.raw) for r in read_tlog(path)] == [(T0, raw), (T0 + 0.25, raw)]


def test_capture_link_does_not_record_what_was_not_sent(tmp_path: Path) -> None:
    path = tmp_path / "c.tlog"
    with loop_capture(path) as link, pytest.raises(ValueError):  # FrameError: not a frame
        link.send(b"not a frame")
    assert list(read_tlog(path)) == []


def test_capture_to_missing_directory_fails_at_open(tmp_path: Path) -> None:
    inner = open_serial("loop://")
    with pytest.raises(CaptureError, match="does not exist"):
        CaptureLink(inner, tmp_path / "missing" / "c.tlog")
    assert not inner.closed  # still the caller's to close
    inner.close()


def read_master(fd: int, n: int, timeout: float = 5.0) -> bytes:
    """Read ``n`` bytes from a pty master, waiting on select (never sleeping)."""
    data = b""
    deadline = time.monotonic() + timeout
    while len(data) < n:
        r, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
        if not r:
            break
        data += os.read(fd, 4096)
    return data


def test_open_link_capture_on_a_pty_records_both_directions(tmp_path: Path) -> None:
    path = tmp_path / "pty.tlog"
    master, slave = os.openpty()
    try:
        b_local, b_remote = FrameBuilder(1), FrameBuilder(2)
        out = [b_local.heartbeat(), b_local.tunnel(b"ping")]
        inc = [b_remote.heartbeat(), b_remote.tunnel(b"pong" * 10)]
        with open_link(os.ttyname(slave), capture=path) as link:
            assert isinstance(link, CaptureLink)
            for raw in out:
                link.send(raw)
            assert read_master(master, sum(map(len, out))) == b"".join(out)
            os.write(master, b"".join(inc))
            got = [link.recv(timeout=5) for _ in inc]
            assert [f.raw for f in got if f is not None] == inc
        with pytest.raises(CaptureError, match="does not exist"):
            open_link(os.ttyname(slave), capture=tmp_path / "missing" / "c.tlog")
    finally:
        os.close(master)
        os.close(slave)
    assert [r.raw for r in read_tlog(path)] == out + inc


# -- the replay link ---------------------------------------------------------------------


def test_tlog_link_paces_with_scaled_capped_gaps(tmp_path: Path, manual_clock: ManualClock) -> None:
    path = tmp_path / "flight.tlog"
    times = [T0, T0 + 0.5, T0 + 2.0, T0 + 100.0, T0 + 99.0, T0 + 103.0]
    frames = make_capture(path, times)
    link = open_link(f"tlog:{path}?speed=2&max_gap=5", clock=manual_clock, sleep=manual_clock.sleep)
    assert isinstance(link, TlogLink)
    assert not link.can_send
    got = [link.recv().raw for _ in frames]  # type: ignore[union-attr]
    assert got == frames
    # gaps 0.5, 1.5, 98 (capped), -1 (none), 4 -> halved, capped at 5 s
    assert manual_clock.sleeps == pytest.approx([0.25, 0.75, 5.0, 2.0])
    with pytest.raises(LinkClosedError, match="end of capture"):
        link.recv()
    with pytest.raises(LinkClosedError, match="end of capture"):
        link.recv(timeout=0)  # stays ended
    assert link.ended and link.damage is None
    assert link.stats.frames_in == len(frames)
    assert link.stats.bytes_in == sum(map(len, frames))
    link.close()
    link.close()


def test_tlog_link_recv_timeout_shorter_than_the_gap(tmp_path: Path, manual_clock: ManualClock) -> None:
    path = tmp_path / "f.tlog"
    frames = make_capture(path, [T0, T0 + 3.0])
    link = open_tlog_link(str(path), clock=manual_clock, sleep=manual_clock.sleep)  # plain path, speed 1
    assert link.recv(timeout=0) is not None  # the first frame is due at once
    assert link.recv(timeout=0) is None  # poll: no sleep
    assert manual_clock.sleeps == []
    assert link.recv(timeout=1.0) is None
    assert link.recv(timeout=1.0) is None
    frame = link.recv(timeout=10.0)
    assert frame is not None and frame.raw == frames[1]
    assert manual_clock.sleeps == pytest.approx([1.0, 1.0, 1.0])


def test_tlog_link_late_consumer_catches_up_without_waiting(
    tmp_path: Path, manual_clock: ManualClock
) -> None:
    path = tmp_path / "f.tlog"
    make_capture(path, [T0, T0 + 1, T0 + 2, T0 + 3])
    link = open_tlog_link(f"tlog:{path}", clock=manual_clock, sleep=manual_clock.sleep)
    link.recv()
    manual_clock.now += 2.5  # the consumer was busy for 2.5 s
    link.recv()
    link.recv()
    assert manual_clock.sleeps == []
    link.recv()
    assert manual_clock.sleeps == pytest.approx([0.5])


def test_tlog_link_speed_zero_never_sleeps(tmp_path: Path, manual_clock: ManualClock) -> None:
    path = tmp_path / "f.tlog"
    frames = make_capture(path, [T0 + i * 10 for i in range(20)])
    link = open_link(f"{path}?speed=0", clock=manual_clock, sleep=manual_clock.sleep)
    assert [link.recv(timeout=0).raw for _ in frames] == frames  # type: ignore[union-attr]
    assert manual_clock.sleeps == []


def test_tlog_link_is_receive_only(tmp_path: Path) -> None:
    path = tmp_path / "f.tlog"
    frames = make_capture(path, [T0])
    with open_link(str(path)) as link, pytest.raises(LinkClosedError, match="receive-only"):
        link.send(frames[0])


def test_tlog_link_damaged_capture_delivers_whole_frames_then_ends(
    tmp_path: Path, manual_clock: ManualClock
) -> None:
    path = tmp_path / "d.tlog"
    frames = make_capture(path, [T0, T0 + 0.1, T0 + 0.2])
    data = path.read_bytes()
    path.write_bytes(data[:-3])
    link = open_tlog_link(f"tlog:{path}", clock=manual_clock, sleep=manual_clock.sleep)
    assert [link.recv().raw for _ in range(2)] == frames[:2]  # type: ignore[union-attr]
    with pytest.raises(LinkClosedError, match="end of capture"):
        link.recv()
    assert link.damage is not None
    assert "truncated frame" in link.damage and "after 2 whole records" in link.damage


@pytest.mark.parametrize(
    ("suffix", "match"),
    [
        ("?speed=fast", "speed must be a number"),
        ("?speed=-1", "speed must be"),
        ("?max_gap=-2", "max_gap must be"),
        ("?sped=2", "unknown option"),
    ],
)
def test_tlog_link_bad_options(tmp_path: Path, suffix: str, match: str) -> None:
    path = tmp_path / "f.tlog"
    make_capture(path, [T0])
    with pytest.raises(LinkOpenError, match=match):
        open_link(f"tlog:{path}{suffix}")


def test_tlog_link_missing_file(tmp_path: Path) -> None:
    with pytest.raises(LinkOpenError, match="no such file"):
        open_link(f"tlog:{tmp_path / 'nope.tlog'}")
    with pytest.raises(LinkOpenError, match="no capture file path"):
        open_tlog_link("tlog:?speed=1")


def test_tlog_link_close_wakes_a_waiting_recv(tmp_path: Path) -> None:
    path = tmp_path / "f.tlog"
    make_capture(path, [T0, T0 + 10_000])
    link = open_link(f"tlog:{path}?max_gap=inf")  # real clock, default (interruptible) wait
    assert link.recv(timeout=0) is not None
    outcome: list[BaseException] = []

    def waiter() -> None:
        try:
            link.recv()
        except BaseException as exc:
            outcome.append(exc)

    t = threading.Thread(target=waiter)
    t.start()
    link.close()
    t.join(timeout=10)
    assert not t.is_alive()
    assert len(outcome) == 1 and isinstance(outcome[0], LinkClosedError)
    with pytest.raises(LinkClosedError, match="closed"):
        link.recv(timeout=0)


def test_capture_of_a_replay(tmp_path: Path) -> None:
    src = tmp_path / "src.tlog"
    frames = make_capture(src, [T0, T0 + 1, T0 + 2])
    out = tmp_path / "copy.tlog"
    with open_link(f"tlog:{src}?speed=0", capture=out) as link:
        assert not link.can_send
        for _ in frames:
            link.recv()
    assert [r.raw for r in read_tlog(out)] == frames


# -- Player -----------------------------------------------------------------------------


def test_player_writes_with_recorded_gaps(tmp_path: Path, manual_clock: ManualClock) -> None:
    path = tmp_path / "f.tlog"
    times = [T0, T0 + 0.2, T0 + 0.2, T0 + 30.0, T0 + 31.0]
    frames = make_capture(path, times)
    written: list[bytes] = []
    player = Player(read_tlog(path), speed=0.5, max_gap=10.0, clock=manual_clock, sleep=manual_clock.sleep)
    stats = player.play(written.append)
    assert written == frames
    assert manual_clock.sleeps == pytest.approx([0.4, 10.0, 2.0])
    assert stats.frames == 5 and stats.bytes == sum(map(len, frames))
    assert stats.recorded == pytest.approx(31.0)
    assert stats.elapsed == pytest.approx(12.4)
    assert not stats.stopped


def test_player_as_an_iterator(tmp_path: Path, manual_clock: ManualClock) -> None:
    path = tmp_path / "f.tlog"
    make_capture(path, [T0, T0 + 1, T0 + 3])
    due: list[float] = []
    for _rec in Player(read_tlog(path), clock=manual_clock, sleep=manual_clock.sleep):
        due.append(manual_clock.now - 1000.0)
    assert due == pytest.approx([0.0, 1.0, 3.0])


def test_player_stops_before_the_next_record(tmp_path: Path, manual_clock: ManualClock) -> None:
    path = tmp_path / "f.tlog"
    make_capture(path, [T0 + i for i in range(10)])
    stop = threading.Event()
    written: list[bytes] = []

    def write(raw: bytes) -> None:
        written.append(raw)
        if len(written) == 3:
            stop.set()  # as a SIGINT handler would

    player = Player(read_tlog(path), clock=manual_clock, sleep=manual_clock.sleep, stop=stop)
    stats = player.play(write)
    assert len(written) == 3 and stats.frames == 3 and stats.stopped


def test_player_default_wait_ends_at_once_when_stopped(tmp_path: Path) -> None:
    path = tmp_path / "f.tlog"
    make_capture(path, [T0, T0 + 10_000])
    player = Player(read_tlog(path), max_gap=math.inf)  # real clock, interruptible wait
    written: list[bytes] = []
    done = threading.Event()

    def run() -> None:
        player.play(written.append)
        done.set()

    t = threading.Thread(target=run)
    t.start()
    player.stop()
    t.join(timeout=10)
    assert done.is_set()
    assert player.stats.stopped and len(written) <= 1


def test_player_into_a_link(tmp_path: Path) -> None:
    path = tmp_path / "f.tlog"
    frames = make_capture(path, [T0 + i for i in range(5)])
    with open_serial("loop://") as link:
        stats = Player(read_tlog(path), speed=0).play(link)
        assert stats.frames == 5
        got: list[bytes] = []
        while len(got) < 5:
            frame = link.recv(timeout=5)
            assert frame is not None
            got.append(frame.raw)
    assert got == frames


def test_player_on_damaged_capture_writes_whole_frames_then_raises(
    tmp_path: Path, manual_clock: ManualClock
) -> None:
    path = tmp_path / "f.tlog"
    frames = make_capture(path, [T0 + i for i in range(4)])
    path.write_bytes(path.read_bytes()[:-1])
    written: list[bytes] = []
    player = Player(read_tlog(path), clock=manual_clock, sleep=manual_clock.sleep)
    with pytest.raises(CaptureDamagedError) as info:
        player.play(written.append)
    assert written == frames[:3]
    assert player.stats.frames == 3 and info.value.records == 3


@pytest.mark.parametrize(("speed", "max_gap"), [(-1.0, 5.0), (math.nan, 5.0), (1.0, -1.0)])
def test_player_rejects_bad_pacing(speed: float, max_gap: float) -> None:
    with pytest.raises(ConfigError):
        Player([], speed=speed, max_gap=max_gap)


def test_pacer_steps() -> None:
    p = Pacer(speed=4, max_gap=2, clock=lambda: 50.0)
    assert p.due(T0) == 50.0
    assert p.due(T0 + 1) == 50.25
    assert p.due(T0 + 101) == 52.25
    assert p.due(T0 + 100) == 52.25
    assert p.step(0.4) == pytest.approx(0.1)


# -- decoding and statistics -----------------------------------------------------------


def mixed_capture(path: Path) -> list[bytes]:
    b1, b2 = FrameBuilder(1, 1), FrameBuilder(2, 1)
    frames = [
        b1.heartbeat(),
        b2.tunnel(b"\x01\x02payload"),
        b1.build(dialect.MAVLink_attitude_message(1234, math.nan, 0.5, -0.25, 0, 0, 0)),
        b2.build(dialect.MAVLink_statustext_message(4, b"low battery")),
        pack_frame(
            MSG_RADIO_STATUS, bytes([1, 0, 0, 0, 200, 190, 80, 40, 35]), sysid=51, compid=68, seq=9, version=1
        ),
        b2.heartbeat(),
    ]
    with TlogWriter(path) as w:
        for i, raw in enumerate(frames):
            w.write(raw, T0 + 0.5 * i)
    return frames


def test_decode_record_fields_and_json(tmp_path: Path) -> None:
    path = tmp_path / "m.tlog"
    mixed_capture(path)
    decoded = [decode_record(r) for r in read_tlog(path)]
    for d in decoded:
        json.dumps(d, allow_nan=False)  # strict JSON: no NaN
        assert {"t", "sysid", "compid", "msg", "seq", "fields"} <= d.keys()
    hb, tun, att, text, radio, hb2 = decoded
    assert (hb["t"], hb["sysid"], hb["compid"], hb["msg"], hb["seq"]) == (T0, 1, 1, "HEARTBEAT", 0)
    assert hb["fields"]["type"] == 18 and "mavpackettype" not in hb["fields"]
    assert tun["msg"] == "TUNNEL" and tun["fields"]["payload_length"] == 9
    assert tun["fields"]["payload"][:9] == list(b"\x01\x02payload")
    assert att["fields"]["roll"] is None and att["fields"]["pitch"] == 0.5
    assert text["fields"]["text"] == "low battery"
    assert (radio["msg"], radio["sysid"], radio["compid"]) == ("RADIO_STATUS", 51, 68)
    assert radio["fields"]["rssi"] == 200
    assert hb2["seq"] == 2 and hb2["t"] == T0 + 2.5


def test_format_record_is_one_mavproxy_like_line(tmp_path: Path) -> None:
    path = tmp_path / "m.tlog"
    mixed_capture(path)
    lines = [format_record(r) for r in read_tlog(path)]
    assert all("\n" not in line for line in lines)
    clock_part = time.strftime("%H:%M:%S", time.localtime(T0)) + ".000"
    assert lines[0] == (
        f"{clock_part} 1/1 HEARTBEAT {{type : 18, autopilot : 8, base_mode : 0, custom_mode : 0,"
        " system_status : 4, mavlink_version : 3}"
    )
    assert re.match(r"^\d\d:\d\d:\d\d\.500 2/1 TUNNEL \{target_system : 0, ", lines[1])
    assert " 51/68 RADIO_STATUS {rssi : 200, remrssi : 190, " in lines[4]


def test_pymavlink_reads_the_same_capture(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An independent reader (pymavlink's own .tlog reader) agrees with ours."""
    path = tmp_path / "m.tlog"
    mixed_capture(path)
    # pymavlink switches itself to MAVLink 2 by setting this; keep it test-local
    monkeypatch.setenv("MAVLINK20", "1")
    theirs = []
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    try:
        while True:
            msg = conn.recv_msg()
            if msg is None:
                break
            theirs.append(msg)
    finally:
        conn.close()
    ours = [decode_record(r) for r in read_tlog(path)]
    assert len(theirs) == len(ours) == 6
    assert [m.get_type() for m in theirs] == [d["msg"] for d in ours]
    assert [m.get_srcSystem() for m in theirs] == [d["sysid"] for d in ours]
    assert [m._timestamp for m in theirs] == pytest.approx([d["t"] for d in ours])  # noqa: SLF001 (pymavlink's receive time)


def test_pymavlink_reads_a_capture_link_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "loop.tlog"
    b = FrameBuilder(9, 1)
    with loop_capture(path) as link:
        for i in range(4):
            link.send(b.tunnel(bytes([i]) * 5))
        for _ in range(4):
            assert link.recv(timeout=5) is not None
    monkeypatch.setenv("MAVLINK20", "1")
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    types = []
    while (msg := conn.recv_msg()) is not None:
        types.append(msg.get_type())
    conn.close()
    assert types == ["TUNNEL"] * 8


def test_capture_stats(tmp_path: Path) -> None:
    path = tmp_path / "m.tlog"
    frames = mixed_capture(path)
    s = capture_stats(read_tlog(path))
    json.dumps(s, allow_nan=False)
    assert s["frames"] == 6 and s["bytes"] == sum(map(len, frames))
    assert s["duration"] == pytest.approx(2.5)
    assert s["messages"] == {"HEARTBEAT": 2, "TUNNEL": 1, "ATTITUDE": 1, "STATUSTEXT": 1, "RADIO_STATUS": 1}
    by_id = {sy["sysid"]: sy for sy in s["systems"]}
    assert sorted(by_id) == [1, 2, 51]
    assert by_id[2]["frames"] == 3
    assert by_id[2]["messages"] == {"TUNNEL": 1, "STATUSTEXT": 1, "HEARTBEAT": 1}
    assert by_id[1]["bytes"] == len(frames[0]) + len(frames[2])
    # the radio's RADIO_STATUS to its host never went on air: no share of it
    air_total = s["bytes"] - by_id[51]["bytes"] + AIRTIME_OVERHEAD_BYTES * 5
    assert by_id[51]["airtime_share"] == 0.0
    expected = (by_id[1]["bytes"] + 2 * AIRTIME_OVERHEAD_BYTES) / air_total
    assert by_id[1]["airtime_share"] == pytest.approx(expected)
    assert sum(sy["airtime_share"] for sy in s["systems"]) == pytest.approx(1.0)


def test_capture_stats_empty() -> None:
    s = capture_stats([])
    assert s["frames"] == 0 and s["systems"] == [] and s["duration"] == 0.0


def test_records_can_be_built_by_hand() -> None:
    raw = FrameBuilder(4).heartbeat()
    rec = TlogRecord(T0, raw)
    assert decode_record(rec)["sysid"] == 4
    assert FrameParser().feed(rec.raw)[0].raw == raw
