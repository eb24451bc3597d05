"""The fault campaign (``swarm simulate --campaign``, ``swarm bench campaign``): its new
fault kinds do what they say, its continuous invariants catch what they name, a
failing scenario shrinks to a small one whose replay command fails the same way, a
bounded campaign has no violation, and serial and ``--jobs`` campaigns agree."""

from __future__ import annotations

import json
import shlex

import pytest

from swarm.cli.bench import campaign as bench_campaign
from swarm.cli.commands.simulate import main
from swarm.core.wire.message_types import Phase
from swarm.core.wire.tunnel import Kind
from swarm.sim.campaign import draw, run_campaign
from swarm.sim.faultsim import DriftCore, FaultSim, make_sim
from swarm.sim.scenario import Link, Scenario
from swarm.sim.shrink import fewer_agents, kinds, shrink
from swarm.sim.simulate import Sim


def test_plain_scenarios_run_on_the_plain_simulator() -> None:
    assert type(make_sim(Scenario(agents=3, loss=0.1, links=["1>2:0.3"]), 0)) is Sim
    assert type(make_sim(Scenario(agents=3, strict=True), 0)) is FaultSim


def test_a_restarted_leader_comes_back_without_state_and_rejoins() -> None:
    sc = Scenario(agents=4, restarts=["1@20-25", "2@20-25", "3@20-25", "4@20-25"], strict=True)
    sim = FaultSim(sc, 3)
    before = list(sim.cores)
    res = sim.run()
    assert res.violations == [] and res.converged
    assert all(a is not b for a, b in zip(before, sim.cores, strict=True))  # fresh cores
    assert res.end_s >= 25
    assert sum(c.phase == Phase.LEADER for c in sim.cores) == 1


def _settles(sc: Scenario, seed: int) -> Sim:
    """A scenario the campaign once failed, run again: no violation, settled at the end."""
    sim = make_sim(sc, seed)
    res = sim.run()
    assert res.violations == [] and res.stable_at_end
    return sim


def test_a_multipoint_base_cut_off_for_long_still_hears_its_nodes_after_the_heal() -> None:
    # found by the 10,000-scenario campaign: agent 1's radio (node 0, the multipoint base)
    # heard nobody for 79 s, the air model unlocked it like any node, and after the heal
    # it heard the others only by chance (1 packet in NUM_CHANNELS): its leader and
    # leader 3 stayed apart for 30 s. The base is the network's clock: it never unlocks.
    sc = Scenario(
        agents=3,
        profile="fast",
        loss=0.18,
        partitions=["33.2-84.6:1|2,3", "5.3-50.1:2,3|1"],
        links=["2>3:0.07", "1>3:0.08"],
        restarts=["1@47.7-61.3"],
        pauses=["2@70.4-79.8"],
        duration=121.9,
        strict=True,
    )
    sim = _settles(sc, 450402140)
    assert sim.air.radios[0].cfg.node_id == 0 and sim.air.radios[0].locked


def test_two_splits_one_after_the_other_are_timed_apart() -> None:
    # found by the 10,000-scenario campaign: leaders 7 and 9 shared a group for 11 s,
    # then a partition ended and 9 and 20 shared another for 11 s; the check timed
    # "some group has two leaders" and called it one split of 22 s. Each pair is timed.
    sc = Scenario(
        agents=20,
        profile="tdm",
        loss=0.28,
        partitions=[
            "31.7-71.8:1,4,7,8,9,10,11,17,20|2,3,5,6,12,13,14,15,16,18,19",
            "11.8-62.2:1,4,5,6,10,11,12,13,16,17,20|2,3,7,8,9,14,15,18,19",
        ],
        duration=191.8,
        strict=True,
    )
    _settles(sc, 1532974364)


def test_after_a_heal_under_loss_the_smaller_leader_is_absorbed_within_the_split_bound() -> None:
    # found by the 10,000-scenario campaign: after the heal at 105.3 s the larger
    # leader's frames reached the smaller one 3 times in 18 s, and each time the
    # smaller one's single reply Heartbeat was lost: two leaders shared a group for 23 s.
    # Now each of its periodic Heartbeats also goes to the larger one (caps.courted).
    sc = Scenario(
        agents=18,
        profile="fast",
        loss=0.25,
        partitions=[
            "72.6-105.3:1,2,3,5,7,8,9,10,12,13,17|4,6,11,14,15,16,18",
            "62.0-74.1:1,5,6,10,12,15,18|2,3,4,7,8,9,11,13,14,16,17",
        ],
        crashes=["leader@26.6"],
        duration=244.1,
        strict=True,
    )
    sim = _settles(sc, 1278781733)
    assert sum(c.phase == Phase.LEADER for c, up in zip(sim.cores, sim.alive, strict=True) if up) == 1


def test_a_paused_agent_resumes_with_its_state() -> None:
    sim = FaultSim(Scenario(agents=3, pauses=["2@15-16"], strict=True), 1)
    core = sim.cores[1]
    res = sim.run()
    assert res.violations == [] and sim.cores[1] is core and res.end_s >= 16


def test_an_agent_that_crashes_while_paused_stays_down() -> None:
    sim = FaultSim(Scenario(agents=4, pauses=["2@10-30"], crashes=["2@20"], strict=True), 2)
    res = sim.run()
    assert res.violations == [] and not sim.alive[1] and res.end_s >= 30


def test_drift_runs_an_agents_clock_fast() -> None:
    sim = FaultSim(Scenario(agents=2, drift=["2:1000"]), 0)
    assert isinstance(sim.cores[1], DriftCore) and sim.cores[1].rate == pytest.approx(1.001)
    sim.cores[1].start(100.0)
    assert sim.cores[1].idle_since == pytest.approx(100.1)
    assert sim.run().violations == []


def test_a_one_way_link_drops_one_direction_only() -> None:
    k = Link.parse("3>1:1@5-40")
    assert (k.src, k.dst, k.p, k.t0, k.t1) == (3, 1, 1.0, 5.0, 40.0)
    assert Link.parse(k.spec()) == k
    for bad in ("3>3:1", "1>2:2", "1>2", "1>2:0.5@9-3", "a>b:1"):
        with pytest.raises(ValueError):
            Link.parse(bad)


def test_a_message_that_does_not_decode_is_a_violation() -> None:
    sim = FaultSim(Scenario(agents=2, strict=True), 0)
    sim._write(0, Kind.ADVERTIZE, (0,), b"\xff\x00garbage", 1.0)  # noqa: SLF001 (white box: garbage on the air)
    assert any("does not decode" in v for v in sim.violations)


def test_a_failing_scenario_shrinks_and_its_replay_fails_the_same_way(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # agent 1 is never heard by agent 2: the swarm cannot settle before the link heals,
    # and it never heals; the rest is noise the shrinker removes
    sc = Scenario(
        agents=6, loss=0.05, links=["1>2:1.0"], late=["5@3"], drift=["4:200"], duration=90, strict=True
    )
    small, res = shrink(sc, 7)
    assert res.violations
    assert small.agents <= 3 and small.links == ["1>2:1.0"]
    assert not (small.late or small.drift or small.loss)
    argv = shlex.split(small.command(7))[2:]
    assert main([*argv, "--json", "--jobs", "1"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["failing"][0]["violations"] == res.violations


def test_a_shrink_keeps_only_variants_that_fail_the_same_way() -> None:
    # the full campaign shrank a 48-agent split to 2 agents whose leaders all crashed:
    # "membership did not converge", another kind, printed as the failure's replay
    split = "two leaders in one connected group for over 34 s (their swarms fit under the cap)"
    other = "membership did not converge after the last fault (t=0.0 s) by the end of the run (t=75.2 s)"
    assert kinds([split]) == kinds([split.replace("34", "20")]) != kinds([other])
    later = other.replace("0.0", "9.5").replace("75.2", "1.0")
    assert kinds([other]) == kinds([later])


def test_the_split_bound_is_20_s_or_six_tdm_rounds_whichever_is_longer() -> None:
    # the merge rule is three one-way steps of at least a round each; 20 s was 3.5
    # rounds on a channel of 48 radios, barely above the loss-free three
    small, big = Sim(Scenario(agents=10), 0), Sim(Scenario(agents=48), 0)
    assert small.split_limit_s == 20.0 and 6 * small.round_s < 20.0
    assert big.split_limit_s == pytest.approx(6 * big.round_s) and big.split_limit_s > 30.0


def test_fewer_agents_drops_faults_naming_agents_no_longer_there() -> None:
    sc = Scenario(
        agents=5,
        links=["5>1:0.3", "1>2:0.3"],
        crashes=["leader@9", "4@3"],
        partitions=["1-9:1,4|5", "1-9:1,2|3"],
        drift=["5:9"],
    )
    small = fewer_agents(sc, 3)
    assert small.links == ["1>2:0.3"] and small.crashes == ["leader@9"] and small.drift == []
    assert small.partitions == ["1-9:1,2|3"]  # the first one is left with a single group


def test_the_draws_depend_only_on_seed_and_index() -> None:
    assert draw(4, 17) == draw(4, 17)
    assert [draw(4, k)[1] for k in range(5)] != [draw(5, k)[1] for k in range(5)]
    sizes = [draw(0, k)[0].agents for k in range(400)]
    assert min(sizes) == 2 and max(sizes) > 20 and sum(n <= 8 for n in sizes) > 250


def test_the_draws_cover_every_profile_and_capped_sub_swarms() -> None:
    drawn = [draw(0, k)[0] for k in range(600)]
    profiles = [sc.profile for sc in drawn]
    assert {p: profiles.count(p) > 100 for p in ("paper", "fast", "tdm")} == dict.fromkeys(
        ("paper", "fast", "tdm"), True
    )
    capped = [(sc.agents, sc.cap) for sc in drawn if sc.cap]
    assert len(capped) > 50 and all(2 <= cap < n for n, cap in capped)
    assert all("cap" in kinds for sc, _, kinds in map(lambda k: draw(0, k), range(200)) if sc.cap)
    # a profile given for all replaces the drawn one, tdm included
    assert {draw(0, k, profile="paper")[0].profile for k in range(60)} == {"paper"}


def test_a_capped_scenario_replays_from_its_command() -> None:
    sc = next(sc for sc, _, _ in (draw(0, k, max_agents=8) for k in range(200)) if sc.cap)
    assert f"--cap {sc.cap}" in sc.command(1)


@pytest.mark.parametrize(
    "argv",
    [
        ["--link", "1>9:0.5"],
        ["--link", "1>2:1.5"],
        ["--link", "x"],
        ["--restart", "2@30-10"],
        ["--restart", "7@1-2"],
        ["--pause", "2"],
        ["--drift", "1:1e9"],
        ["--drift", "nan:3"],
        ["--campaign", "0"],
        ["--campaign", "-5"],
    ],
)
def test_bad_fault_flags_exit_2_with_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--agents", "3", "--jobs", "1", *argv]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_campaign_flag_prints_the_campaign(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--campaign", "4", "--seed", "4", "--jobs", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scenarios"] == 4 and out["violations"] == 0 and out["failing"] == []


@pytest.mark.processes  # worker processes
def test_serial_and_jobs_campaigns_are_identical() -> None:
    assert run_campaign(16, 11, jobs=1, max_agents=10) == run_campaign(16, 11, jobs=2, max_agents=10)


@pytest.mark.processes  # worker processes
# about 35 s of CPU: on a busy machine (two busy loops beside the suite) its wall time
# passed the session's 180 s; the outcome is judged, not the time
@pytest.mark.timeout(900)
def test_bounded_campaign_has_no_violation() -> None:
    # 200 of `swarm bench campaign --quick`'s 300 scenarios (N <= 12): about 35 s of CPU
    res = bench_campaign.run(quick=True, scenarios=200)
    assert set(res) >= {
        "scenarios",
        "violations",
        "failing",
        "wall_s",
        "cpu_s",
        "scenarios_per_cpu_s",
        "reference_cpu_s",
        "reference_cpu_s_before_after",
        "cpu_in_reference_units",
        "by_kind",
    }
    # 200 drawn scenarios cost more than the 40 plain runs of the reference; the
    # reference is the mean of one taken before the campaign and one after
    assert res["reference_cpu_s"] > 0 and res["cpu_in_reference_units"] > 1
    before, after = res["reference_cpu_s_before_after"]
    assert (
        before > 0 and after > 0 and res["reference_cpu_s"] == pytest.approx((before + after) / 2, abs=0.01)
    )
    assert res["scenarios"] == 200 and res["agents_max"] <= bench_campaign.QUICK_AGENTS
    assert res["violations"] == 0, res["failing"]
    assert res["by_kind"]["restart"]["scenarios"] > 0 and res["by_kind"]["one_way"]["scenarios"] > 0
