"""``swarm bench agent``'s parts that can be checked without its processes: reading the
emulator's capture as it grows (a record cut short waits for its rest), the loss
figures after a kill, the flight log's cost figures, and the area's registration.
The whole bench starts an emulator, two vehicle simulators and two agents for half a
minute: its figures are in the README, not asserted here (durations are not).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from radios.mavlink import FrameBuilder
from radios.rotating import FlightLog
from radios.tlog import TlogWriter
from swarm.cli.bench.agent import ADVERTIZE, AirTail, advertize_from, loss_of, sync_cost
from swarm.cli.commands.bench import main as bench_main

T0 = 1_795_000_000.0


def test_air_tail_reads_whole_records_as_the_file_grows(tmp_path: Path) -> None:
    b = FrameBuilder(3, 191)
    raws = [b.tunnel(bytes([i]) * i) for i in range(6)]
    path = tmp_path / "air.tlog"
    tail = AirTail(str(path))
    assert tail.poll() == []  # not there yet: nothing
    with TlogWriter(path) as w:
        for i, raw in enumerate(raws):
            w.write(raw, T0 + i)
    data = path.read_bytes()
    path.write_bytes(data[:-3])  # the last record still coming
    assert [raw for _t, raw in tail.poll()] == raws[:5]
    path.write_bytes(data)
    assert tail.poll() == [(T0 + 5, raws[5])]
    assert len(tail.records) == 6


def test_advertize_is_told_from_other_tunnels_and_senders() -> None:
    b = FrameBuilder(7, 191)
    adv = b.tunnel(b"\x01", target_system=0, payload_type=ADVERTIZE)
    assert advertize_from(adv, 7)
    assert not advertize_from(adv, 8)
    assert not advertize_from(b.tunnel(b"\x01", target_system=0, payload_type=ADVERTIZE + 2), 7)
    assert not advertize_from(b.heartbeat(), 7)


def test_loss_counts_frames_on_air_missing_from_the_flight_log(tmp_path: Path) -> None:
    b = FrameBuilder(1, 191)
    raws = [b.tunnel(bytes([i])) for i in range(10)]
    with FlightLog(str(tmp_path / "logs"), "agent1") as log:
        for i, raw in enumerate(raws[:8]):
            log.put("radio", raw, T0 + i)
    with TlogWriter(tmp_path / "air.tlog") as w:
        for i, raw in enumerate(raws):
            w.write(raw, T0 + i + 0.01)
        w.write(FrameBuilder(2, 191).heartbeat(), T0 + 9.5)  # another sender's: not counted
    got = loss_of(str(tmp_path / "logs"), str(tmp_path / "air.tlog"), T0 + 9.2)
    assert got["capture_loss_s"] == pytest.approx(2.2)
    assert got["capture_records"] == 8 and got["capture_frames_on_air"] == 10
    assert got["capture_missing_frames"] == 2 and got["capture_torn_tails"] == 0


def test_the_cost_figures_come_from_a_real_flight_log(tmp_path: Path) -> None:
    got = sync_cost(str(tmp_path), 1.2)
    assert got["syncs"] >= 1 and got["put_us"] > 0 and got["sync_ms_max"] >= got["sync_ms_mean"] > 0


def test_bench_lists_the_agent_area(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        bench_main(["--help"])
    assert "agent: one agent: start-up to first Advertize" in " ".join(capsys.readouterr().out.split())
