"""Figures of the simulator's conformance to recorded ArduCopter and PX4 traces.

Each ``.tlog`` in the project's recorded traces (``tests/data/traces``: a real
ArduCopter 4.7.0-dev or PX4 v1.15.4 SITL and a companion, both directions) is replayed
into the simulated autopilot of its kind with the recorded boot length, on a virtual clock, by
:mod:`firmware_bridge.sim.conformance`; the figures are, per trace, milestones, ACK
results, texts, message types and HEARTBEAT triples matched / total, and the take-off,
20 m move and landing times as ratios simulator / trace. The target: every milestone
and ACK matched, every timing ratio within 0.8..1.2. Without ``--quick`` each trace is
also replayed live, through ``VehicleSim`` on a real TCP socket at ``LIVE_SPEEDUP``
(about 25 s of wall time per trace): the same figures under ``live``.

``cold_start`` (:mod:`tools.bench.cold_start`): a real agent and ``swarm sim``
with the recorded boot powered on together: poses sent before the fix and at Null
Island (target 0), the take-off refusals met while the autopilot booted, and when a
take-off was accepted (``--quick``: the boot scaled to 10 s).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from firmware_bridge.errors import BridgeError
from firmware_bridge.sim.conformance import compare, conformance, read_trace, replay_live
from swarm.errors import SwarmError

TRACES = Path(__file__).resolve().parents[2] / "tests" / "data" / "traces"
RATIO_RANGE = (0.8, 1.2)
LIVE_SPEEDUP = 5.0


def _summary(r: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {k: f"{v['matched']}/{v['total']}" for k, v in r.items() if "matched" in v}
    out["timing_ratios"] = {k: v["ratio"] for k, v in r["timings"].items() if v["ratio"] is not None}
    out["milestones_missed"] = [k for k, v in r["milestones"]["detail"].items() if not v["ok"]]
    out["ack_mismatches"] = r["acks"]["mismatches"]
    out["texts_missing"] = r["texts"]["missing"]
    out["heartbeats_missing"] = r["heartbeats"]["missing"]
    return out


def _met(r: dict[str, Any]) -> bool:
    lo, hi = RATIO_RANGE
    whole = all(r[k]["matched"] == r[k]["total"] for k in ("milestones", "acks"))
    ratios = [v["ratio"] for v in r["timings"].values() if v["ratio"] is not None]
    return whole and all(lo <= x <= hi for x in ratios)


def run(quick: bool = False, traces: Path = TRACES, real: bool = False) -> dict[str, Any]:
    if real:  # the simulator against the real autopilots, live (conformance_real)
        from tools.bench.conformance_real import run_real

        return run_real(quick)
    files = sorted(traces.glob("*.tlog")) if traces.is_dir() else []
    if not files:
        raise SwarmError(f"no recorded traces (*.tlog) in {traces}: run from a source checkout")
    t0 = time.process_time()
    out: dict[str, Any] = {"note": "recorded boot length, virtual time; ratios are simulator / trace"}
    met, live_met, live = True, True, {}
    for f in files:
        try:
            r = conformance(f)
            lr = None if quick else compare(read_trace(f), replay_live(read_trace(f), LIVE_SPEEDUP))
        except BridgeError as exc:
            raise SwarmError(str(exc)) from None
        out[f.stem] = {**_summary(r), "met": _met(r)}
        met = met and _met(r)
        if lr is not None:
            live[f.stem] = _summary(lr)
            live_met = live_met and _met(lr)
    out["target_met"] = met
    if live:
        out["live"] = {"speedup": LIVE_SPEEDUP, **live, "target_met": live_met}
    out["cpu_s"] = round(time.process_time() - t0, 1)
    from tools.bench import cold_start

    cs = cold_start.run(quick)
    out["cold_start"] = cs
    out["null_poses_sent"] = cs["null_poses_sent"]
    out["cold_start_target_met"] = bool(
        cs["null_poses_sent"] == 0 and cs["poses_before_fix"] == 0 and cs["airborne"]
    )
    return out
