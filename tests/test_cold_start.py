"""Issue 17's acceptance, on real processes: an agent and a simulated ArduCopter powered
on together, the autopilot with the boot a real one was recorded to have (41.5 s:
positions at 0, 0, 0 for seconds, home late, arming refused). The radio emulator
captures the air; a ground station asks for a take-off every few seconds from the
moment the agent is connected (the bench figure ``python -m tools.bench conformance``'s
``cold_start`` is this run).

The agent must send no pose before the autopilot's fix and none at Null Island, must
refuse the early take-offs with the autopilot's reasons, and take off once it can.
"""

from __future__ import annotations

import pytest

from tools.bench import cold_start

pytestmark = pytest.mark.processes  # emulator, swarm sim, swarm agent, a station: real time


def test_a_cold_start_sends_no_pose_before_the_fix_and_reports_the_refusals_it_met() -> None:
    r = cold_start.run(quick=False)
    assert r["boot_s"] > 40.0  # the recorded boot, not a shortened one
    assert r["poses_sent"] > 10, r  # it did fly and report where it was
    assert r["null_poses_sent"] == 0, r
    assert r["poses_before_fix"] == 0, r
    # the early take-offs were refused with the autopilot's words, the later one flew
    assert r["takeoff_refusals"], r
    assert all("not armable" in why for why in r["takeoff_refusals"]), r
    assert any("Arm" in why for why in r["takeoff_refusals"]), r  # "PreArm: ..." / "Arm: ..."
    assert r["takeoff_accepted_s"] is not None and r["takeoff_accepted_s"] > 20.0, r
    assert r["airborne"], r
    assert any("waiting for position" in line for line in r["agent_said"]), r
