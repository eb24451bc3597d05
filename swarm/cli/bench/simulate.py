"""Figures of the deterministic simulator for the election targets (virtual time)."""

from __future__ import annotations

import time
from typing import Any

from swarm.sim.simulate import Scenario, campaign


def run(quick: bool = False) -> dict[str, Any]:
    k = 20 if quick else 500
    out: dict[str, Any] = {}
    t0 = time.process_time()
    out["paper_n10_loss10"] = campaign(Scenario(agents=10, loss=0.1), k)
    cpu = time.process_time() - t0
    out["cpu_s_per_seed_n10"] = round(cpu / k, 4)
    out["cpu_s_for_1000_seeds_n10"] = round(1000 * cpu / k, 1)
    out["fast_n10_loss10"] = campaign(Scenario(agents=10, loss=0.1, profile="fast"), max(k // 5, 10))
    out["paper_n20_64kbps"] = campaign(Scenario(agents=20, loss=0.1), 5 if quick else 30)
    out["fast_n20_64kbps"] = campaign(Scenario(agents=20, loss=0.1, profile="fast"), 5 if quick else 30)
    out["paper_n5_leader_crash"] = campaign(
        Scenario(agents=5, crashes=["leader@15"], duration=80), 10 if quick else 100
    )
    if not quick:
        out["paper_n50_loss10"] = campaign(Scenario(agents=50, loss=0.1, duration=120), 20)
    for v in out.values():
        if isinstance(v, dict):
            v.pop("failing", None) if not v.get("failing") else None
    return out
