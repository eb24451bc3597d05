"""``swarm simulate --channels``: agents over several channels, each its own air model and
TDM ring, on one virtual clock; and ``swarm bench scale``'s figures (virtual time)."""

from __future__ import annotations

import json
import shlex

import pytest

from swarm.cli.commands.bench import main as bench_main
from swarm.cli.commands.simulate import main as simulate_main
from swarm.core.wire.message_types import Phase
from swarm.sim.channels import ChannelScenario, id_ranges, parse_place, pct_none, round_robin, run_channels
from swarm.sim.parallel import sweep
from swarm.sim.relay import RelaySim
from swarm.sim.simulate import Scenario, Sim


def channel_sims(cs: ChannelScenario, seed: int) -> list[Sim]:
    return [Sim(cs.channel_scenario(c), cs.channel_seed(seed, c)) for c in range(1, cs.channels + 1)]


def test_agents_are_dealt_round_robin_or_as_placed() -> None:
    assert round_robin(7, 3) == (1, 2, 3, 1, 2, 3, 1)
    assert parse_place("1-3:2, 4:1 ,5-6:2", 6, 2) == (2, 2, 2, 1, 2, 2)
    cs = ChannelScenario.make(Scenario(agents=7), 3)
    assert [cs.members(c) for c in (1, 2, 3)] == [[1, 4, 7], [2, 5], [3, 6]]
    assert id_ranges([1, 2, 3, 7, 9, 10]) == "1-3,7,9-10"


def test_channels_never_hear_each_other_and_each_elects_its_own_leader() -> None:
    """Each channel is its own air model with only its radios: after the run, each
    channel has one leader listing exactly the other agents of its channel (two
    channels that heard each other would merge into one swarm with one leader)."""
    cs = ChannelScenario.make(Scenario(agents=9, profile="fast"), 2, "1-4:1,5-9:2")
    for c, sim in enumerate(channel_sims(cs, 3), start=1):
        n = len(cs.members(c))
        assert len(sim.air.radios) == n
        res = sim.run()
        assert res.elect_s is not None and not res.violations
        leaders = [core for core in sim.cores if core.phase == Phase.LEADER]
        assert len(leaders) == 1
        assert set(leaders[0].members) == {core.me for core in sim.cores} - {leaders[0].me}


def test_each_channel_has_the_tdm_round_of_its_own_radio_count() -> None:
    cs = ChannelScenario.make(Scenario(agents=12), 2, "1-3:1,4-12:2")
    small, big = channel_sims(cs, 0)
    assert small.round_s == Sim(Scenario(agents=3), 0).round_s
    assert big.round_s == Sim(Scenario(agents=9), 0).round_s
    assert small.round_s < big.round_s


def test_a_two_channel_run_converges_on_each_channel() -> None:
    cs = ChannelScenario.make(Scenario(agents=10, loss=0.1, profile="fast"), 2)
    r = run_channels(cs, 3, 0)
    assert r["all_led"] == 3 and r["violations"] == 0 and r["failing"] == []
    for ch in r["per_channel"]:
        assert ch["converged"] == 3 and ch["agents"] == 5
        assert ch["elect_s"]["max"] <= r["all_led_s"]["max"]
        assert 0 < ch["air_utilisation"]["max"] < 1
        assert set(ch["leaders_seen"]) <= set(cs.members(ch["channel"]))  # deployment ids
    assert r["all_led_s"]["max"] == max(ch["elect_s"]["max"] for ch in r["per_channel"])


def test_channel_one_of_a_seed_is_the_one_channel_run_of_that_seed() -> None:
    sc = Scenario(agents=6, loss=0.1)
    one = run_channels(ChannelScenario.make(sc, 1), 3, 4)
    assert one["per_channel"][0]["elect_s"] == sweep(sc, 3, 4)["elect_s"]


def test_a_run_that_never_gets_there_counts_as_slower_than_any() -> None:
    assert pct_none([1.0, None, 2.0], 0.5) == 2.0
    assert pct_none([1.0, None, 2.0], 1.0) is None
    assert pct_none([], 0.5) is None


def test_an_unconverged_channel_is_failing_with_both_replays(capsys: pytest.CaptureFixture[str]) -> None:
    """A run too short to elect: each channel fails, named with the deployment's replay
    command and the channel's own one-channel replay, which give the same outcome."""
    argv = [
        "--agents",
        "6",
        "--channels",
        "2",
        "--seeds",
        "1",
        "--seed",
        "7",
        "--duration",
        "1",
        "--json",
        "--jobs",
        "1",
    ]
    assert simulate_main(argv) == 1
    out = capsys.readouterr()
    r = json.loads(out.out)
    assert r["all_led"] == 0 and r["all_led_s"]["p95"] is None
    f = r["failing"][1]
    assert f["channel"] == 2 and f["seed"] == 7
    assert "--channels 2" in f["replay"] and "--channels" not in f["replay_channel"]
    assert "replay failing seed 7 (channel 2)" in out.err
    assert simulate_main([*shlex.split(f["replay"])[2:], "--json", "--jobs", "1"]) == 1
    assert json.loads(capsys.readouterr().out) == r
    assert simulate_main([*shlex.split(f["replay_channel"])[2:], "--json", "--jobs", "1"]) == 1
    assert json.loads(capsys.readouterr().out)["converged"] == 0


def test_a_swarm_command_relayed_between_stations_reaches_every_channels_leader() -> None:
    """The operator gives channel 1's station a swarm FOLLOW at 20 s; channel 2's station
    gets it 0.5 s later over the stations' network: each channel's station (the real
    StationCore, its radio in the channel's ring) connects its agents, sends it to the
    leader it sees, and that leader accepts it."""
    cs = ChannelScenario.make(Scenario(agents=8, profile="fast", command_at=20.0), 2, latency=0.5)
    for c in (1, 2):
        sim = RelaySim(cs.channel_scenario(c), cs.channel_seed(4, c))
        assert sim.round_s == Sim(Scenario(agents=5), 0).round_s  # 4 agents and a station
        res = sim.run()
        assert res.elect_s is not None and not res.violations
        assert res.command_s == pytest.approx(20.0 + (0.5 if c == 2 else 0.0), abs=0.1)
        assert res.ack_result == "ACCEPTED" and res.ack_s is not None and res.ack_s > res.command_s
        assert res.ack_by == res.leader
        assert sim.station.station.leader == res.leader
        assert all(a.connected for a in sim.station.station.agents.values())
    r = run_channels(cs, 2, 4)["relay"]
    assert r["answered"] == r["accepted"] == {"min": 2, "max": 2} and r["all_answered"] == 2
    assert 0.5 < r["all_answered_s"]["max"] < 10
    assert "--command-at 20.0" in cs.command(4) and "--relay-latency 0.5" in cs.command(4)


def test_a_swarm_command_before_any_leader_is_refused_by_the_station() -> None:
    r = run_channels(ChannelScenario.make(Scenario(agents=6, command_at=1.0), 2), 1, 0)
    assert r["relay"]["answered"] == {"min": 0, "max": 0}
    assert r["relay"]["refused_at_once"] == {"no leader elected yet": 2}
    assert r["all_led"] == 1  # the elections go on


@pytest.mark.parametrize(
    "args,says",
    [
        (["--channels", "0"], "--channels: 1..8"),
        (["--channels", "9"], "--channels: 1..8"),
        (["--channels", "99999999999999999999"], "--channels: 1..8"),
        (["--channels", "2", "--place", "1-9:1"], "agents are 1..8"),
        (["--channels", "2", "--place", "0-4:1,5-8:2"], "agents are 1..8"),
        (["--channels", "2", "--place", "5-4:1"], "A <= B"),
        (["--channels", "2", "--place", "1-4:1,4-8:2"], "agent 4 is placed twice"),
        (["--channels", "2", "--place", "1-4:1"], "agent 5 is on no channel"),
        (["--channels", "2", "--place", "1-8:1"], "channel 2 has no agent"),
        (["--channels", "2", "--place", "1-4:1,5-8:3"], "channels are 1..2"),
        (["--channels", "2", "--place", "1-4:1,,5-8:2"], "expected A-B:CHANNEL"),
        (["--channels", "2", "--place", "1-99999999999:1"], "expected A-B:CHANNEL"),
        (["--channels", "2", "--place", "\u0661-4:1,5-8:2"], "expected A-B:CHANNEL"),
        (["--channels", "2", "--place", "1-4:1;rm -rf /"], "expected A-B:CHANNEL"),
        (["--channels", "2", "--place", "1:1," * 3000], "at most 2000 characters"),
        (["--channels", "2", "--crash", "1@5"], "one-channel only"),
        (["--channels", "2", "--campaign", "3"], "one-channel only"),
        (["--command-at", "-1"], "--command-at: virtual seconds"),
        (["--command-at", "nan"], "--command-at: virtual seconds"),
        (["--command-at", "1e400"], "--command-at: virtual seconds"),
        (["--command-at", "5", "--strict"], "not with --strict"),
        (["--command-at", "5", "--relay-latency", "-0.1"], "--relay-latency: 0..60"),
        (["--command-at", "5", "--relay-latency", "nan"], "--relay-latency: 0..60"),
        (["--relay-latency", "1"], "only with --command-at"),
    ],
)
def test_bad_channel_input_is_one_line_and_exit_2(
    args: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert simulate_main(["--agents", "8", "--seeds", "1", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err and "Traceback" not in err


@pytest.mark.processes  # worker processes
def test_the_same_seed_gives_the_same_json_serial_and_over_two_jobs(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["--agents", "9", "--channels", "3", "--seeds", "3", "--seed", "11", "--loss", "0.1", "--json"]
    assert simulate_main([*argv, "--jobs", "1"]) == 0
    serial = capsys.readouterr().out
    assert simulate_main([*argv, "--jobs", "2"]) == 0
    assert capsys.readouterr().out == serial
    assert simulate_main([*argv, "--jobs", "1"]) == 0
    assert capsys.readouterr().out == serial
    assert json.loads(serial)["channels"] == 3


@pytest.mark.processes  # worker processes for the seeds; emulators, agents, stations, a router
def test_bench_scale_quick_json_has_its_figures(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench_main(["scale", "--quick", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["quick"] is True and r["targets"]["all_led_p95_s"] == 30.0
    one, four = r["one_channel_n50"], r["four_channels_n200"]
    assert one["channels"] == 1 and one["cap"] > 0 and four["channels"] == 4
    assert one["profile"] == four["profile"] == "tdm"
    for part in (one, four):
        assert part["all_led"] == part["runs"] > 0
        assert part["all_led_s"]["p95"] is not None and part["air_utilisation_max"] > 0
        assert set(part["met"]) >= {"all_led_p95_s", "all_led_share"}
        assert len(part["per_channel"]) == part["channels"]
    assert set(one["met"]) == {"all_led_p95_s", "all_led_share", "air_utilisation"}
    relay = r["relay_four_channels"]["relay"]
    assert (
        relay["swarms"] == 4 and relay["answered"]["max"] == 4 and relay["all_answered_s"]["p50"] is not None
    )
    # the real-process part: 2 emulators x 2 agents, 2 stations, a router
    procs = r["processes"]
    assert procs["agents"] == 4 and procs["command"]["acked_by_leader_on"] == "c1"
    assert procs["survivors"] == {"swarms": 1, "agents": 2}
    # what the stations' states cost on the router: counted there, and modelled in flight
    fed = procs["federation"]
    assert set(fed["measured"]["stations"]) == {"st0", "st1"}
    assert all(s["states_per_s"] > 0 and s["bytes_per_s"] > 0 for s in fed["measured"]["stations"].values())
    big = fed["model_200"]
    assert big["agents"] == 200 and 0 < big["bytes_per_s"] < big["before_bytes_per_s"]
    assert big["json_bytes"] > big["state_bytes"]  # deflated
