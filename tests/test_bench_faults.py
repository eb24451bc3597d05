"""The fault bench, bounded: a real signed swarm (radio emulator, one simulated vehicle per
agent, four agents with the swarm key, a signed station) flying a V, then faults in turn.
The whole campaign is ``swarm bench faults --json``; this runs the faults that guard the
fixes of issue 11 in the time the suite can afford (about three minutes)."""

from __future__ import annotations

import pytest

from swarm.bench.faults import run_faults

SUITE_FAULTS = ("rogue_unsigned", "rogue_wrong_key", "station_restart", "garbage_small", "leader_kill",
                "member_restart", "rogue_replay")


@pytest.mark.timeout(900)
def test_signed_swarm_survives_the_bounded_fault_campaign() -> None:
    lines: list[str] = []
    result = run_faults(SUITE_FAULTS, log=lines.append, member_uptime_s=75.0)
    faults = {f["fault"]: f for f in result["faults"]}
    assert result["total"] == len(SUITE_FAULTS)
    failed = [f for f in result["faults"] if not f["survived"] or f["frames_accepted_from_rogue"]]
    assert not failed, "\n".join(lines)
    # a member restarted after more than a minute of everyone's uptime joins the signed swarm
    # again (its verifier used to call every other stream a replay: a swarm of one for good)
    restart = next(f for name, f in faults.items() if name.startswith("member kill -9 and restart"))
    assert restart["recovery_s"] is not None
    assert all(f["dual_leader_s"] <= result["leader_timeout_s"] for f in result["faults"]), "\n".join(lines)
    replay = next(f for name, f in faults.items() if "replayed" in name)
    assert replay["rogue_frames"] > 100  # the replay really sent the recorded election
