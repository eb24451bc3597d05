"""`swarm replay`: dump, JSON lines, statistics, damage, and re-feeding a real pty."""

from __future__ import annotations

import json
import math
import os
import re
import select
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as dialect

from radios.mavlink import FrameBuilder, FrameParser
from radios.tlog import TlogWriter
from swarm import cli
from swarm.cli.commands.replay import main

T0 = 1_700_000_000.0
TIME_RE = r"\d\d:\d\d:\d\d\.\d{3}"


def make_capture(path: Path, n: int = 6, gap: float = 0.5) -> list[bytes]:
    b1, b2 = FrameBuilder(1, 1), FrameBuilder(2, 1)
    frames = []
    for i in range(n):
        if i % 3 == 0:
            frames.append(b1.heartbeat())
        elif i % 3 == 1:
            frames.append(b2.tunnel(bytes([i]) * (10 + i)))
        else:
            frames.append(b1.build(dialect.MAVLink_attitude_message(i, math.nan, 0.1, 0, 0, 0, 0)))
    with TlogWriter(path) as w:
        for i, raw in enumerate(frames):
            w.write(raw, T0 + gap * i)
    return frames


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# -- dump ----------------------------------------------------------------------------------


def test_text_lines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "flight.tlog"
    make_capture(path)
    code, out, err = run(capsys, str(path))
    assert (code, err) == (0, "")
    lines = out.splitlines()
    assert len(lines) == 6
    assert re.fullmatch(TIME_RE + r" 1/1 HEARTBEAT \{type : 18, .*\}", lines[0])
    # bytes that are no swarm message under the swarm's payload type: said so, on one line
    assert re.fullmatch(TIME_RE + r" 2/1 TUNNEL swarm advertize 2 -> all <cannot decode: .*>", lines[1])
    assert re.fullmatch(TIME_RE + r" 1/1 ATTITUDE \{time_boot_ms : 2, roll : nan, .*\}", lines[2])


def test_json_lines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "flight.tlog"
    frames = make_capture(path)
    code, out, _ = run(capsys, str(path), "--json")
    assert code == 0
    objs = [json.loads(line) for line in out.splitlines()]
    assert len(objs) == len(frames)
    for i, o in enumerate(objs):
        assert {"t", "sysid", "compid", "msg", "seq", "fields"} <= o.keys()
        assert o["t"] == pytest.approx(T0 + 0.5 * i)
    assert [o["msg"] for o in objs] == ["HEARTBEAT", "TUNNEL", "ATTITUDE"] * 2
    assert objs[2]["fields"]["roll"] is None  # NaN is not JSON


def test_through_the_swarm_entry_point(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "flight.tlog"
    make_capture(path, n=2)
    assert cli.main(["replay", str(path), "--json"]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 2


# -- statistics ------------------------------------------------------------------------------


def test_stats_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "flight.tlog"
    frames = make_capture(path)
    code, out, _ = run(capsys, str(path), "--stats")
    assert code == 0
    assert out.startswith(f"{path}: 6 frames, {sum(map(len, frames))} bytes over 2.500 s")
    rows = {line.split()[0]: line.split() for line in out.splitlines() if re.match(r"^\s+\d", line)}
    assert set(rows) == {"1", "2"}
    assert rows["1"][1] == "4" and rows["2"][1] == "2"
    assert "HEARTBEAT 2, ATTITUDE 2" in out


def test_stats_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "flight.tlog"
    make_capture(path)
    code, out, _ = run(capsys, str(path), "--stats", "--json")
    assert code == 0
    s = json.loads(out)
    assert s["frames"] == 6 and s["damage"] is None
    assert [sy["sysid"] for sy in s["systems"]] == [1, 2]
    assert sum(sy["airtime_share"] for sy in s["systems"]) == pytest.approx(1.0)


def test_frames_of_unknown_message_ids_are_skipped_counted_and_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A real PX4 capture holds 411 (its events protocol), which the dialect here
    lacks: replay stopped there with "damaged record" and exit 2."""
    path = tmp_path / "px4.tlog"
    frames = make_capture(path, n=3)
    event_seq = bytes([0xFD, 3, 0, 0, 0, 1, 1, 0x9B, 0x01, 0x00, 7, 0, 1, 0x55, 0xAA])  # 411
    with TlogWriter(path) as w:  # the file again, with two of them between known frames
        for i, raw in enumerate([frames[0], event_seq, frames[1], event_seq, frames[2]]):
            w.write(raw, T0 + i)
    code, out, err = run(capsys, str(path))
    assert code == 0 and len(out.splitlines()) == 3
    assert err.strip() == "swarm replay: note: skipped 2 frames of message ids not known here (411 x2)"
    code, out, _ = run(capsys, str(path), "--stats", "--json")
    s = json.loads(out)
    assert code == 0 and s["frames"] == 3 and s["unknown_ids"] == {"411": 2} and s["damage"] is None


def test_a_real_px4_recording_replays_whole(capsys: pytest.CaptureFixture[str]) -> None:
    """The PX4 v1.15 SITL link recorded for the conformance tests: every frame read to
    the end, PX4's own messages (events, open drone id...) counted and said."""
    path = Path(__file__).parent / "data" / "traces" / "px4-sitl-flight.tlog"
    code, out, err = run(capsys, str(path), "--stats", "--json")
    s = json.loads(out)
    assert code == 0 and s["damage"] is None and s["frames"] > 10_000
    assert s["unknown_ids"]["410"] > 10 and s["messages"]["HEARTBEAT"] > 100
    assert "skipped" in err and "410 x" in err


# -- damage and bad input ---------------------------------------------------------------------


def damaged_capture(tmp_path: Path) -> tuple[Path, int]:
    path = tmp_path / "damaged.tlog"
    frames = make_capture(path)
    data = path.read_bytes()
    last = len(data) - 8 - len(frames[-1])
    path.write_bytes(data[:-5])
    return path, last


def test_damaged_file_prints_whole_records_then_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, last = damaged_capture(tmp_path)
    for extra in ((), ("--json",)):
        code, out, err = run(capsys, str(path), *extra)
        assert code == 2  # a damaged file is bad input
        assert len(out.splitlines()) == 5
        assert err == (
            f"swarm replay: error: {path}: damaged record at byte {last} "
            "(truncated frame) after 5 whole records\n"
        )
        assert "Traceback" not in err


def test_damaged_file_stats(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = damaged_capture(tmp_path)
    code, out, err = run(capsys, str(path), "--stats", "--json")
    assert code == 2
    s = json.loads(out)
    assert s["frames"] == 5 and "truncated frame" in s["damage"]
    assert "damaged record" in err


def test_garbage_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "garbage.tlog"
    path.write_bytes(b"definitely not a capture\n" * 20)
    code, out, err = run(capsys, str(path))
    assert (code, out) == (2, "")  # bad input, as for `swarm gcs --replay` (issue 18)
    assert "not a capture (.tlog)" in err and "damaged record at byte 0" in err


def test_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, str(tmp_path / "nope.tlog"))
    assert (code, out) == (2, "")
    assert err == f"swarm replay: error: {tmp_path / 'nope.tlog'}: no such capture file\n"


def test_pacing_options_need_to(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "flight.tlog"
    make_capture(path)
    code, out, err = run(capsys, str(path), "--speed", "2")
    assert (code, out) == (2, "")
    assert "--speed only applies with --to" in err


def test_argparse_errors_return_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(capsys, "--stats")
    assert code == 2 and "FILE" in err
    code, _, _ = run(capsys, str(tmp_path / "x.tlog"), "--stats", "--to", "loop://")
    assert code == 2


# -- re-feeding a pseudo terminal -----------------------------------------------------------


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """A pty: the master fd the test reads, and the slave's path for the command."""
    master, slave = os.openpty()
    try:
        yield master, os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


class MasterReader(threading.Thread):
    """Collects everything written to the pty slave (select-driven, no sleeps)."""

    def __init__(self, fd: int) -> None:
        super().__init__(daemon=True)
        self.fd = fd
        self.data = bytearray()
        self.cond = threading.Condition()
        self.first = threading.Event()
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.is_set():
            r, _, _ = select.select([self.fd], [], [], 0.05)  # 0.05: re-check `done`
            if not r:
                continue
            try:
                chunk = os.read(self.fd, 4096)
            except OSError:
                return
            with self.cond:
                self.data += chunk
                self.cond.notify_all()
            self.first.set()

    def wait_for(self, n: int, timeout: float = 10.0) -> bytes:
        with self.cond:
            self.cond.wait_for(lambda: len(self.data) >= n, timeout)
        return self.stop()

    def stop(self) -> bytes:
        self.done.set()
        self.join(timeout=5)
        return bytes(self.data)


def test_to_refeeds_a_real_pty(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], pty_pair: tuple[int, str]
) -> None:
    master, slave_path = pty_pair
    path = tmp_path / "flight.tlog"
    frames = make_capture(path, n=30, gap=2.0)
    reader = MasterReader(master)
    reader.start()
    code, out, err = run(capsys, str(path), "--to", slave_path, "--speed", "0", "--baud", "115200")
    data = reader.wait_for(sum(map(len, frames)))
    assert (code, err) == (0, "")
    assert [f.raw for f in FrameParser().feed(data)] == frames
    assert out.startswith(f"sent 30 frames ({sum(map(len, frames))} bytes) to {slave_path} in ")
    assert "recorded span 58.000 s, speed 0" in out


def test_to_json_summary_and_damage(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], pty_pair: tuple[int, str]
) -> None:
    master, slave_path = pty_pair
    path, last = damaged_capture(tmp_path)
    reader = MasterReader(master)
    reader.start()
    code, out, err = run(capsys, str(path), "--to", slave_path, "--speed", "0", "--json")
    data = reader.wait_for(last - 5 * 8)  # the five whole records, without timestamps
    assert code == 2
    summary = json.loads(out)
    assert summary["frames"] == 5 and summary["to"] == slave_path and not summary["stopped"]
    assert summary["bytes"] == len(data) == last - 5 * 8
    assert len(FrameParser().feed(data)) == 5
    assert "damaged record" in err


def test_to_a_receive_only_link_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "flight.tlog"
    make_capture(path)
    code, out, err = run(capsys, str(path), "--to", f"tlog:{path}")
    assert (code, out) == (2, "")
    assert "receive-only" in err


def test_to_missing_device(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "flight.tlog"
    make_capture(path)
    code, _, err = run(capsys, str(path), "--to", str(tmp_path / "radio9"))
    assert code == 2 and "no such device" in err


@pytest.mark.parametrize(("sig", "expected"), [(signal.SIGINT, 130), (signal.SIGTERM, 0)])
def test_to_stops_promptly_on_a_signal(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    pty_pair: tuple[int, str],
    sig: int,
    expected: int,
) -> None:
    master, slave_path = pty_pair
    path = tmp_path / "slow.tlog"
    with TlogWriter(path) as w:
        b = FrameBuilder(1)
        w.write(b.heartbeat(), T0)
        w.write(b.heartbeat(), T0 + 600)  # ten minutes later, uncapped below
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    reader = MasterReader(master)
    reader.start()

    def interrupt() -> None:
        if reader.first.wait(10):  # the first frame is out: the player now waits
            os.kill(os.getpid(), sig)

    killer = threading.Thread(target=interrupt, daemon=True)
    killer.start()
    started = time.monotonic()
    code, out, _ = run(capsys, str(path), "--to", slave_path, "--max-gap", "inf", "--json")
    elapsed = time.monotonic() - started
    killer.join(timeout=5)
    data = reader.stop()
    assert code == expected
    assert elapsed < 30
    summary = json.loads(out)
    assert summary["stopped"] and summary["frames"] == 1 and summary["max_gap"] is None
    assert len(FrameParser().feed(data)) == 1
    assert {s: signal.getsignal(s) for s in before} == before  # handlers restored
