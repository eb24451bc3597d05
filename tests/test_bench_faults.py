"""The fault bench, bounded: a real signed swarm (radio emulator, one simulated vehicle per
agent, four agents with the swarm key, a signed station) flying a V, then faults in turn.
The whole campaign is ``swarm bench faults --json``; this runs the faults that guard the
fixes of issue 11 in the time the suite can afford (about three minutes)."""

from __future__ import annotations

import os
import signal

import pytest
from net_helpers import wait_until

from swarm.cli.bench.faults import FAULTS_QUICK, run_faults
from swarm.cli.procs import Child

# timing: dual-leader seconds within the leader timeout, replays within the minute
pytestmark = [pytest.mark.processes, pytest.mark.timing]  # the bench's processes through a fault campaign


@pytest.mark.timeout(900)
def test_signed_swarm_survives_the_bounded_fault_campaign() -> None:
    lines: list[str] = []
    result = run_faults(FAULTS_QUICK, log=lines.append, member_uptime_s=75.0)
    faults = {f["fault"]: f for f in result["faults"]}
    assert result["total"] == len(FAULTS_QUICK)
    failed = [f for f in result["faults"] if not f["survived"] or f["frames_accepted_from_rogue"]]
    assert not failed, "\n".join(lines)
    # a member restarted after more than a minute of everyone's uptime joins the signed swarm
    # again (its verifier used to call every other stream a replay: a swarm of one for good)
    restart = next(f for name, f in faults.items() if name.startswith("member kill -9 and restart"))
    assert restart["recovery_s"] is not None
    assert all(f["dual_leader_s"] <= result["leader_timeout_s"] for f in result["faults"]), "\n".join(lines)
    replay = next(f for name, f in faults.items() if "replayed" in name)
    assert replay["rogue_frames"] > 100  # the replay really sent the recorded election


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="ascii") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid:
            out.append(int(entry))
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.timeout(300)
def test_sigterm_stops_the_bench_and_every_process_it_started() -> None:
    bench = Child(["bench", "faults", "--json"], name="bench")
    try:
        # the emulator, the vehicles, the agents: wait until a few are running
        started = wait_until(
            lambda: len(_children(bench.pid)) >= 3 and _children(bench.pid),
            "the bench to start its processes",
            120.0,
            0.2,
        )
        bench.proc.send_signal(signal.SIGTERM)
        assert bench.proc.wait(60) == 130
        wait_until(lambda: not any(_alive(p) for p in started), "its processes gone", 30.0, 0.2)
        assert not any("Traceback" in line for line in bench.errors), bench.errors
    finally:
        bench.stop()
