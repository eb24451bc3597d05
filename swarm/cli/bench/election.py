"""``swarm bench election``: real agent processes over the emulated radios, side by side
with the deterministic simulator for the same cases.

For each case (N agents, loss, profile) a ``swarm radio-emu`` process and N
``swarm agent`` processes start; the election time is from the moment the last
agent reported ready until every agent reports the same leader (phase LEADER or
MEMBER). The simulator runs the same case over several seeds; the JSON shows the
real median next to the simulated median so the simulator's fidelity is visible.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from typing import Any

from swarm.cli.procs import Child, start_emulator
from swarm.core.election.profiles import PROFILE_NAMES
from swarm.sim.parallel import sweep
from swarm.sim.simulate import Scenario

CASES = [(5, 0.0), (5, 0.1), (10, 0.0), (10, 0.1)]
PROFILES = PROFILE_NAMES


def real_election(n: int, loss: float, profile: str, timeout: float = 120.0) -> float | None:
    """Seconds from all agents ready to all agreeing, or None if they did not."""
    with tempfile.TemporaryDirectory() as d:
        emu, links = start_emulator(n, d, "--loss", str(loss))
        agents: list[Child] = []
        try:
            for i in range(n):
                agents.append(
                    Child(
                        [
                            "agent",
                            "--name",
                            f"agent{i + 1}",
                            "--id",
                            str(i + 1),
                            "--radio",
                            links[i],
                            "--profile",
                            profile,
                            "--json",
                            # the agent cannot read the TDM round from the radio
                            "--slots",
                            str(n),
                        ],
                        name=f"agent{i + 1}",
                    )
                )
            for a in agents:
                a.wait_lines(1, 30.0)
            t0 = time.monotonic()
            while time.monotonic() - t0 < timeout:
                states = [_last_state(a) for a in agents]
                leaders = {s.get("leader") for s in states if s}
                if (
                    all(s and s.get("phase") in ("LEADER", "MEMBER") for s in states)
                    and len(leaders) == 1
                    and 0 not in leaders
                ):
                    return time.monotonic() - t0
                time.sleep(0.1)
            return None
        finally:
            for a in agents:
                a.stop()
            emu.stop()


def _last_state(child: Child) -> dict[str, Any] | None:
    for line in reversed(child.lines):
        if line.startswith("{"):
            try:
                obj: dict[str, Any] = json.loads(line)
            except ValueError:
                continue
            return obj
    return None


def run(quick: bool = False, only: tuple[str, ...] = ()) -> dict[str, Any]:
    """Every case for every profile (``only``: these profiles; quick: the paper's)."""
    cases = CASES[:2] if quick else CASES
    profiles = only or (("paper",) if quick else PROFILES)
    repeats = 1 if quick else 3
    seeds = 10 if quick else 50
    rows = []
    for profile in profiles:
        for n, loss in cases:
            real = [real_election(n, loss, profile) for _ in range(repeats)]
            ok = [r for r in real if r is not None]
            sim = sweep(Scenario(agents=n, loss=loss, profile=profile), seeds)
            sim_p50 = sim["elect_s"]["p50"]
            real_p50 = statistics.median(ok) if ok else None
            rows.append(
                {
                    "agents": n,
                    "loss": loss,
                    "profile": profile,
                    "elect_s": round(real_p50, 2) if real_p50 is not None else None,
                    "real_runs": len(real),
                    "real_converged": len(ok),
                    "sim_elect_s": {"p50": sim_p50, "p95": sim["elect_s"]["p95"]},
                    "sim_runs": sim["runs"],
                    "sim_converged": sim["converged"],
                    "round_s": sim["round_s"],
                    "elect_rounds": round(real_p50 / sim["round_s"], 2) if real_p50 is not None else None,
                    "real_vs_sim": round(real_p50 / sim_p50, 3) if real_p50 and sim_p50 else None,
                }
            )
    return {
        "cases": rows,
        "targets": {
            "real_median_within_25pct_of_sim": all(
                r["real_vs_sim"] is not None and abs(r["real_vs_sim"] - 1) <= 0.25 for r in rows
            )
        },
    }
