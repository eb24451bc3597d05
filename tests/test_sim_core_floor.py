"""The simulator's CPU floor (``swarm bench simulate``'s ``core_floor``): the share of a
run spent in the agents' own protocol cores and the codec, timed without changing the run."""

from __future__ import annotations

import swarm.sim.simulate as simulate
from swarm.cli.bench.simulate import core_share
from swarm.sim.parallel import run_one
from swarm.sim.simulate import Scenario


def test_timing_the_cores_changes_no_run_and_is_undone() -> None:
    sc = Scenario(agents=6, loss=0.1)
    encode, decode = simulate.encode, simulate.decode
    share, timed = core_share(sc, 3)
    plain = [run_one((sc, seed)) for seed in range(3)]
    assert timed == plain  # same elections, times, leaders and message counts
    assert all(r.elect_s is not None for r in timed)
    assert 0.0 < share < 1.0
    assert simulate.encode is encode and simulate.decode is decode  # the codec is unwrapped
