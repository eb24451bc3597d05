"""The simulated ArduCopter against recorded real ArduCopter SITL traces (tests/data/traces).

The companion's side of each trace is replayed at its recorded times into the simulator's
autopilot core with the recorded boot (virtual time: the whole trace in about a second),
and what comes back is compared with what the real autopilot sent. Then the boot itself
on real sockets through the runner, the hostile trace files, and the CLI flags.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mav_helpers import command, wait_msg
from net_helpers import free_port_range
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.errors import BridgeError, ConnectError
from firmware_bridge.sim import REALISTIC_BOOT, Autopilot, SimConfig, VehicleSim
from firmware_bridge.sim.boot import BootTimeline
from firmware_bridge.sim.conformance import (
    MAX_TRACE_BYTES,
    Trace,
    compare,
    conformance,
    read_trace,
    replay_live,
)
from swarm.errors import SwarmError
from tools.bench import conformance as bench

ROOT = Path(__file__).resolve().parents[1]
TRACES = Path(__file__).parent / "data" / "traces"
FLIGHT, EDGES = TRACES / "ardupilot-sitl-flight.tlog", TRACES / "ardupilot-sitl-edges.tlog"
STABILIZE, PX4 = TRACES / "ardupilot-sitl-stabilize.tlog", TRACES / "px4-sitl-flight.tlog"


@pytest.mark.parametrize("trace", [FLIGHT, EDGES], ids=["flight", "edges"])
def test_replayed_trace_conforms(trace: Path) -> None:
    r = conformance(trace)
    ms = r["milestones"]
    assert ms["matched"] == ms["total"] >= 8, ms["detail"]
    assert r["acks"]["matched"] == r["acks"]["total"] >= 40, r["acks"]["mismatches"]
    assert r["message_types"]["matched"] == r["message_types"]["total"], r["message_types"]
    assert not r["message_types"]["extra"]
    assert r["texts"]["matched"] >= r["texts"]["total"] - 4, r["texts"]["missing"]
    assert not r["texts"]["extra"] or r["texts"]["extra"] == ["Arm: AHRS: waiting for home"]
    assert r["heartbeats"]["matched"] >= r["heartbeats"]["total"] - 1, r["heartbeats"]
    ratios = {k: v["ratio"] for k, v in r["timings"].items() if v["trace_s"] is not None}
    assert ratios and all(x is not None and 0.8 <= x <= 1.2 for x in ratios.values()), r["timings"]


def test_fresh_ardupilot_trace_arms_in_stabilize_before_its_position() -> None:
    """Recorded 2026-11-29: arms tried in STABILIZE every 2 s from the connection; the real
    ArduCopter accepted one at 23 s, 19 s before its position: so does the simulator."""
    r = conformance(STABILIZE)
    ms = r["milestones"]
    assert ms["matched"] == ms["total"] >= 9, ms["detail"]
    assert ms["detail"]["arm_accepted"]["trace_s"] < ms["detail"]["local_position"]["trace_s"] - 15
    assert r["acks"]["matched"] == r["acks"]["total"] >= 40, r["acks"]["mismatches"]
    assert r["heartbeats"]["matched"] == r["heartbeats"]["total"], r["heartbeats"]
    assert r["message_types"]["matched"] == r["message_types"]["total"], r[
        "message_types"
    ]  # EKF_STATUS_REPORT
    ratios = {k: v["ratio"] for k, v in r["timings"].items()}
    assert all(x is not None and 0.8 <= x <= 1.2 for x in ratios.values()), r["timings"]


def test_px4_trace_conforms_boot_acks_heartbeats_and_events() -> None:
    """A real PX4 v1.15.4 SITL recorded 2026-11-29 (boot with arms every 2 s, take-off,
    20 m offboard step, setpoints stopped, control taken back, landing): the simulated
    PX4 answers every command alike, reaches every milestone in time and in order, shows
    the same HEARTBEATs, says nothing in STATUSTEXT, and no EVENT the real one did not."""
    from firmware_bridge.px4_events import parse_event
    from firmware_bridge.sim.conformance import read_trace, replay

    trace = read_trace(PX4)
    assert trace.profile == "px4" and trace.sysid == 1
    r = conformance(PX4)
    ms = r["milestones"]
    assert ms["matched"] == ms["total"] >= 8, ms["detail"]
    assert r["acks"]["matched"] == r["acks"]["total"] >= 40, r["acks"]["mismatches"]
    assert r["heartbeats"]["matched"] == r["heartbeats"]["total"] >= 8, r["heartbeats"]
    assert r["texts"]["total"] == 0 and not r["texts"]["extra"]  # PX4 says it in events
    t = r["timings"]
    assert 0.8 <= t["takeoff"]["ratio"] <= 1.2 and 0.8 <= t["move_20m"]["ratio"] <= 1.2, t
    assert t["land"]["ratio"] is not None  # measured, not matched: see the README (SIH's drift)

    def events(recs: list[Any]) -> set[int]:
        evs = (parse_event(bytes(x.msg.data)) for x in recs if x.msg.get_type() == "UNKNOWN_410")
        return {e.id for e in evs if e is not None}

    real, sim = events(list(trace.records)), events(replay(trace))  # (an unknown frame has no parsed header)
    assert sim and sim <= real, {hex(e) for e in sim - real}


def test_flight_trace_times_take_off_move_and_landing() -> None:
    timings = conformance(FLIGHT)["timings"]
    assert set(timings) == {"takeoff", "move_20m", "land"}
    assert all(v["ratio"] is not None for v in timings.values()), timings


def test_boot_timeline_as_recorded_and_scaled() -> None:
    real = BootTimeline(REALISTIC_BOOT)
    assert real.booting(1.0) and not real.booting(3.0)
    assert real.arm_refusal(1.98) == ("Arm: System not initialised",)
    assert real.arm_refusal(14.0) == ("Arm: Gyros inconsistent", "Arm: AHRS: waiting for home")
    assert real.arm_refusal(30.0) == ("Arm: Need Position Estimate",)
    assert real.arm_refusal(REALISTIC_BOOT) == ()
    assert not real.position_valid(9.0) and real.position_valid(10.0)
    assert not real.origin_set(19.0) and real.origin_set(20.0) and not real.using_gps(41.0)
    short = BootTimeline(4.0)  # the same phases, in 4 s
    assert short.arm_refusal(0.1) == ("Arm: System not initialised",) and short.arm_refusal(4.0) == ()
    booted = BootTimeline(0.0)
    assert not booted.booting(0.0) and booted.arm_refusal(0.0) == () and booted.position_valid(0.0)
    for bad in (-1.0, 601.0, math.nan):
        with pytest.raises(ValueError):
            BootTimeline(bad)


# ----------------------------------------------------------------- attack tests
def test_hostile_trace_files_give_one_clear_error(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.tlog"
    garbage.write_bytes(bytes(range(256)) * 40)
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    autopilot_only = tmp_path / "one-side.tlog"  # the autopilot's frames only: nothing to replay
    with open(FLIGHT, "rb") as f:
        autopilot_only.write_bytes(f.read(4000))
    backwards = tmp_path / "backwards.tlog"  # a companion frame stamped an hour before the first
    ap, companion = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 1, 191)
    t0 = 1_700_000_000_000_000
    backwards.write_bytes(
        (t0).to_bytes(8, "big")
        + ap.heartbeat_encode(2, 3, 81, 0, 3).pack(ap)
        + (t0 - 3_600_000_000).to_bytes(8, "big")
        + companion.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(companion)
    )
    for path in (garbage, empty, autopilot_only, tmp_path / "missing.tlog", tmp_path):
        with pytest.raises(BridgeError) as info:
            conformance(path)
        assert "\n" not in str(info.value)
    with pytest.raises(BridgeError, match="out of order"):
        read_trace(backwards)


def test_bench_without_traces_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(SwarmError, match="no recorded traces"):
        bench.run(traces=tmp_path)
    (tmp_path / "bad.tlog").write_bytes(b"\xfd" * 300)
    with pytest.raises(SwarmError, match=r"bad\.tlog"):
        bench.run(traces=tmp_path)


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, 601.0])
def test_sim_config_refuses_impossible_boot_times(bad: float) -> None:
    with pytest.raises(ConnectError, match="boot_time"):
        SimConfig(profile="ardupilot", boot_time=bad).validate()


# ----------------------------------------------------------- real sockets, CLI
@pytest.fixture
def booting(request: pytest.FixtureRequest) -> Iterator[mavutil.mavfile]:
    """A vehicle on a real TCP socket whose boot lasts ``request.param`` = (boot_time, speedup)."""
    boot_time, speedup = request.param
    sim = VehicleSim(
        SimConfig(
            profile="ardupilot",
            speedup=speedup,
            home=(-35.363261, 149.165230, 584.0),
            base_port=free_port_range(1, "tcp", step=10),
            boot_time=boot_time,
        )
    )
    sim.start()
    c = mavutil.mavlink_connection(sim.endpoints[0], source_system=255)
    c.target_system = 1
    try:
        yield c
    finally:
        c.close()
        sim.stop()


@pytest.mark.processes
@pytest.mark.parametrize("booting", [(600.0, 1.0)], indirect=True)
def test_a_booting_vehicle_on_its_socket(booting: mavutil.mavfile) -> None:
    """A 600 s boot (BOOT for its first 34 s, no GPS for 140 s, so a loaded machine cannot
    outrun it): BOOT heartbeats, Null Island positions, arms refused with their reasons."""
    c = booting
    hb = wait_msg(c, "HEARTBEAT", timeout=20)
    assert hb.system_status == 1 and hb.base_mode == 89  # type: ignore[attr-defined]
    assert command(c, 511, 33, 100000) == 0
    pos = wait_msg(c, "GLOBAL_POSITION_INT", timeout=20)
    assert (pos.lat, pos.lon, pos.alt) == (0, 0, 0)  # type: ignore[attr-defined]
    texts: list[str] = []
    assert command(c, 400, 1, texts=texts) == 4
    assert texts and all(t.startswith("Arm: ") for t in texts), texts


@pytest.mark.processes
@pytest.mark.parametrize("booting", [(4.0, 2.0)], indirect=True)
def test_a_vehicle_arms_once_its_boot_is_over(booting: mavutil.mavfile) -> None:
    """A 4 s boot at speedup 2: LOCAL_POSITION_NED flows only once the EKF uses GPS (the
    boot's end, whenever this test got to ask), then GUIDED and the arm are accepted."""
    c = booting
    assert command(c, 511, 32, 100000) == 0
    wait_msg(c, "LOCAL_POSITION_NED", timeout=20)
    assert command(c, 176, 1, 4) == 0  # GUIDED
    assert command(c, 400, 1) == 0
    assert command(c, 511, 33, 100000) == 0
    assert wait_msg(c, "GLOBAL_POSITION_INT", lambda m: m.lat != 0, timeout=20)  # type: ignore[attr-defined]


def _swarm(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "swarm.cli", *args], capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.processes
def test_bench_conformance_json_meets_the_target() -> None:
    p = subprocess.run(
        [sys.executable, "-m", "tools.bench", "conformance", "--json", "--quick"],
        capture_output=True,
        text=True,
        timeout=120.0,
        cwd=ROOT,
    )
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    for name in (
        "ardupilot-sitl-flight",
        "ardupilot-sitl-edges",
        "ardupilot-sitl-stabilize",
        "px4-sitl-flight",
    ):
        done, total = out[name]["milestones"].split("/")
        assert done == total
        assert set(out[name]["timing_ratios"]) >= {"takeoff", "land"}
        # every ArduCopter trace meets every target; PX4's landing is the known miss (its
        # SIH altitude drifts: README), which the bench reports, not hides
        assert out[name]["met"] is name.startswith("ardupilot"), out[name]
    assert out["target_met"] is False


@pytest.mark.slow
@pytest.mark.processes
@pytest.mark.parametrize("trace", [FLIGHT, EDGES], ids=["flight", "edges"])
def test_live_replay_through_the_runner_conforms(trace: Path) -> None:
    """The whole trace through VehicleSim on a real TCP socket at speedup 5 (about 25 s)."""
    tr = read_trace(trace)
    r = compare(tr, replay_live(tr, speedup=5.0))
    assert r["milestones"]["matched"] == r["milestones"]["total"], r["milestones"]["detail"]
    assert r["acks"]["matched"] == r["acks"]["total"], r["acks"]["mismatches"]
    ratios = [v["ratio"] for v in r["timings"].values() if v["trace_s"] is not None]
    assert ratios and all(x is not None and 0.8 <= x <= 1.2 for x in ratios), r["timings"]


@pytest.mark.timing  # a live replay at 10x matched ack for ack
@pytest.mark.processes
def test_live_replay_of_the_boot_through_the_runner() -> None:
    """The flight trace's first 25 s (boot and refused arms) live at speedup 10: about 3 s."""
    full = read_trace(FLIGHT)
    tr = Trace(full.name, tuple(r for r in full.records if r.t <= 25.0))
    r = compare(tr, replay_live(tr, speedup=10.0))
    assert r["acks"]["matched"] >= r["acks"]["total"] - 1, r["acks"][
        "mismatches"
    ]  # a loaded machine may drop one
    done = {k for k, v in r["milestones"]["detail"].items() if v["ok"]}
    assert {"boot_heartbeat", "position_valid", "gps_origin", "home"} <= done, r["milestones"]["detail"]


@pytest.mark.processes
@pytest.mark.parametrize("flags", [["--boot-time", "nan"], ["--boot-time", "-3"], ["--boot-time", "1e9"]])
def test_sim_boot_time_bad_values_exit_2(flags: list[str]) -> None:
    p = _swarm("sim", "--vehicles", "1", "--profile", "ardupilot", *flags, timeout=30)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.startswith("swarm sim: error:") and len(p.stderr.strip().splitlines()) == 1, p.stderr


@pytest.mark.processes
@pytest.mark.parametrize("flags", [["--profile", "px4"], ["--profile", "ardupilot", "--serial", "pty"]])
def test_sim_wait_for_client_only_where_a_client_connects(flags: list[str]) -> None:
    """PX4's link sends first (a udpin client never talks first) and a serial line has no
    connection: waiting there would wait for ever, so it is refused at once."""
    p = _swarm("sim", "--vehicles", "1", *flags, "--wait-for-client", timeout=30)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.startswith("swarm sim: error: --wait-for-client needs"), p.stderr
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr


@pytest.mark.processes
def test_sim_boot_flags_are_exclusive() -> None:
    p = _swarm("sim", "--vehicles", "1", "--realistic-boot", "--boot-time", "3", timeout=30)
    assert p.returncode == 2 and "Traceback" not in p.stderr


def test_a_fifo_or_an_oversized_trace_is_refused_not_read(tmp_path: Path) -> None:
    """A FIFO named as a trace would block the reader for ever; a huge file would fill memory."""
    fifo = tmp_path / "fifo.tlog"
    os.mkfifo(fifo)
    with pytest.raises(BridgeError, match="not a regular file"):
        read_trace(fifo)
    big = tmp_path / "big.tlog"
    with open(big, "wb") as f:
        f.truncate(MAX_TRACE_BYTES + 1)
    with pytest.raises(BridgeError, match="larger than"):
        read_trace(big)


def test_sys_status_reports_the_prearm_check_and_gps_health_while_booting() -> None:
    """ArduPilot's pre-arm bit (0x10000000) and the GPS bit stay unhealthy until the boot allows them."""
    ap = Autopilot("ardupilot", 1, (-35.363261, 149.16523, 584.0), boot_time=4.0)
    gcs = mavlink.MAVLink(None, 255, 190)

    def sys_status(t: float) -> tuple[int, int]:
        req = mavlink.MAVLink(None, 0, 0).parse_buffer(
            gcs.command_long_encode(1, 1, 512, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs)
        )
        assert req
        [m] = [m for m in ap.handle(req[0], t) if m.get_type() == "SYS_STATUS"]
        return m.onboard_control_sensors_present, m.onboard_control_sensors_health

    present, health = sys_status(0.5)
    assert present & 0x10000000 and not health & 0x10000000 and not health & 32
    present, health = sys_status(2.0)  # GPS found (9.94 of 41.52 s), arming still refused
    assert health & 32 and not health & 0x10000000
    present, health = sys_status(4.1)
    assert health & 0x10000000 and health & 32
    assert Autopilot("px4", 1, (47.4, 8.5, 488.0)).flavour.prearm_ok(ap) is None  # PX4: not reported
