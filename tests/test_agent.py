"""The agent runtime in one process over real Zenoh on loopback TCP (no radio):
three agents elect one leader and agree on it; their state is seen on
``swarm/<name>/state`` by an observer; stop() is clean and safe twice; bad
arguments are refused before anything opens.

Nothing sleeps to hope: every wait polls for an outcome until a generous deadline.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from swarm.core.wire.message_types import AgentState, Phase
from swarm.runtime.agent.live import Agent, default_round_s
from swarm.runtime.agent.vehicle import pose_from_state, state_dict, vehicle_messages
from swarm.runtime.keyspace.transport import Transport
from swarm.runtime.options import AgentConfig, NodeOptions

pytestmark = pytest.mark.processes  # agents over Zenoh and radios, in real time

DEADLINE = 40.0  # paper profile: three 2 s windows plus discovery, with lots of margin


def agreed(states: dict[str, AgentState], names: list[str]) -> int | None:
    """The leader every agent in ``names`` reports (LEADER or MEMBER), else None."""
    if any(n not in states for n in names):
        return None
    leaders = {states[n].leader for n in names}
    phases = {states[n].phase for n in names}
    if len(leaders) != 1 or not phases <= {Phase.LEADER, Phase.MEMBER} or 0 in leaders:
        return None
    return leaders.pop()


@pytest.fixture
def trio() -> Iterator[tuple[list[Agent], dict[str, AgentState], dict[str, AgentState], float]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    lock = threading.Lock()
    own: dict[str, AgentState] = {}  # from the on_state hook
    seen: dict[str, AgentState] = {}  # from swarm/<name>/state, by an observer

    def hook(name: str) -> Callable[[AgentState], None]:
        def f(st: AgentState) -> None:
            with lock:
                own[name] = st

        return f

    def observe(name: str, st: AgentState) -> None:
        with lock:
            seen[name] = st

    agents: list[Agent] = []
    observer: Transport | None = None
    try:
        # the hub every agent connects to (as a `swarm router` over IP): a node that only
        # connects is a Zenoh client, which reaches the others through it alone, so an
        # agent as the hub would take the survivors' link with it when it stops
        observer = Transport.open("observer", listen=[ep])
        observer.on_state("*", observe)
        t0 = time.monotonic()
        for i in (1, 2, 3):
            node = NodeOptions(zenoh_connect=[ep])
            agents.append(Agent(f"agent{i}", i, node, on_state=hook(f"agent{i}")).start())
        yield agents, own, seen, t0
    finally:
        for a in agents:
            a.stop()
        if observer is not None:
            observer.close()


def test_three_agents_elect_one_leader(trio: Any) -> None:
    agents, own, seen, t0 = trio
    names = [a.name for a in agents]
    leader = wait_until(lambda: agreed(dict(own), names), "three agents to agree on a leader", DEADLINE)
    elect_s = time.monotonic() - t0
    assert leader in (1, 2, 3)
    st = {n: own[n] for n in names}
    leaders = [n for n in names if st[n].phase == Phase.LEADER]
    assert leaders == [f"agent{leader}"]
    assert st[f"agent{leader}"].members == frozenset({1, 2, 3} - {leader})
    # the same picture on the key space, seen by a fourth session
    wait_until(lambda: agreed(dict(seen), names) == leader, "the observer to see the same leader", DEADLINE)
    for a in agents:
        assert a.stats["errors"] == 0
        assert a.running
    # the paper profile cannot elect faster than its windows (lock + vote)
    assert elect_s >= 2.0
    print(f"elect_s={elect_s:.2f}")


def test_leader_stops_and_the_others_elect_again(trio: Any) -> None:
    agents, own, _seen, _t0 = trio
    names = [a.name for a in agents]
    leader = wait_until(lambda: agreed(dict(own), names), "a first leader", DEADLINE)
    gone = agents[leader - 1]
    gone.stop()
    rest = [n for n in names if n != gone.name]

    def new_leader() -> int | None:
        lead = agreed(dict(own), rest)
        return lead if lead not in (None, leader) else None

    t = time.monotonic()
    lead2 = wait_until(new_leader, "the survivors to agree on a new leader", DEADLINE)
    print(f"failover_s={time.monotonic() - t:.2f}")
    assert lead2 in {1, 2, 3} - {leader}


def test_stop_is_clean_and_safe_twice() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    before = {t.ident for t in threading.enumerate()}
    with Agent("solo", 7, NodeOptions(zenoh_listen=[ep])) as a:
        wait_until(lambda: a.state() is not None, "the first state", DEADLINE)
        assert a.running
    a.stop()
    assert not a.running
    t = time.monotonic()
    wait_until(
        lambda: (
            not [
                x for x in threading.enumerate() if x.ident not in before and x.name.startswith("agent-solo")
            ]
        ),
        "the agent's threads to end",
        timeout=5,
    )
    assert time.monotonic() - t < 5


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"name": "bad name", "agent_id": 1, "zenoh_listen": ["tcp/127.0.0.1:1"]}, "name"),
        ({"name": "a", "agent_id": 0, "zenoh_listen": ["tcp/127.0.0.1:1"]}, "id"),
        ({"name": "a", "agent_id": 251, "zenoh_listen": ["tcp/127.0.0.1:1"]}, "id"),
        ({"name": "a", "agent_id": 1}, "radio or at least one Zenoh endpoint"),
        ({"name": "a", "agent_id": 1, "radio": "x", "zenoh_listen": ["tcp/127.0.0.1:1"]}, "either"),
        ({"name": "a", "agent_id": 1, "radio": "x", "vote": "loudest"}, "vote"),
        ({"name": "a", "agent_id": 1, "radio": "x", "profile": "slow"}, "profile"),
        ({"name": "a", "agent_id": 1, "radio": "x", "round_s": 0.0}, "round_s"),
    ],
)
def test_bad_arguments(kwargs: dict[str, Any], match: str) -> None:
    """Each option in its group (where the agent meets others, how it behaves): the
    same refusals as when they were all keyword arguments of Agent."""
    name, agent_id = kwargs.pop("name"), kwargs.pop("agent_id")
    node = {k: kwargs.pop(k) for k in ("radio", "zenoh_listen") if k in kwargs}
    with pytest.raises(ValueError, match=match):
        Agent(name, agent_id, NodeOptions(**node), config=AgentConfig(**kwargs))


def test_missing_radio_raises_and_leaves_nothing_open() -> None:
    from radios.errors import LinkOpenError

    a = Agent("a1", 1, NodeOptions(radio="/nonexistent/radio0"))
    with pytest.raises(LinkOpenError):
        a.start()
    a.stop()
    assert not a.running


def test_round_and_helpers() -> None:
    assert default_round_s() == pytest.approx(0.2368)
    assert default_round_s(5) == pytest.approx(0.592)
    a = Agent("a1", 1, NodeOptions(radio="x"), config=AgentConfig(profile="fast", round_s=0.3))
    assert a.profile.name == "fast" and a.profile.vote_interval == pytest.approx(0.3)

    class S:  # the driver's VehicleState fields the agent reads
        autopilot = "px4"
        lat, lon, alt_amsl, rel_alt = 47.4, 8.5, 500.0, 10.0
        velocity = (1.0, -2.0, 0.5)
        yaw = -1.5707963
        base_mode, custom_mode, system_status, time_boot_ms = 0x81, 0x04040000, 4, 1234
        battery_remaining = 80
        position_valid = True

    p = pose_from_state(S(), 3.0)
    assert p is not None and p.heading == pytest.approx(270.0) and (p.vn, p.ve) == (1.0, -2.0)
    hb, gpi = vehicle_messages(S())
    assert hb.get_msgId() == 0 and hb.autopilot == 12
    assert gpi.get_msgId() == 33 and gpi.lat == 474_000_000 and gpi.hdg == 27000 and gpi.vy == -200
    S.position_valid = False  # the driver does not vouch for it (0, 0 before a fix): no pose, no GPI
    assert pose_from_state(S(), 3.0) is None and len(vehicle_messages(S())) == 1
    S.position_valid, S.lat = True, None  # type: ignore[assignment]
    assert pose_from_state(S(), 3.0) is None and len(vehicle_messages(S())) == 1
    d = state_dict("a1", AgentState(1, Phase.LEADER, 1, 1, 5, 9, True, frozenset({1, 2}), frozenset({2})))
    assert d == {
        "name": "a1",
        "id": 1,
        "phase": "LEADER",
        "leader": 1,
        "pool": [1, 2],
        "locked": True,
        "members": [2],
        "candidate": 1,
        "weight": 5,
        "epoch": 9,
    }


def test_two_agents_over_signed_radios_with_the_fast_profile(tmp_path: Any) -> None:
    from swarm.cli.procs import start_emulator

    key = tmp_path / "swarm.key"
    key.write_text("correct horse battery staple\n")
    emu, paths = start_emulator(2, tmp_path, "--seed", "16")  # a pair that hop-locks quickly
    own: dict[str, AgentState] = {}
    agents: list[Agent] = []
    try:
        t0 = time.monotonic()
        for i in (1, 2):
            agents.append(
                Agent(
                    f"agent{i}",
                    i,
                    NodeOptions(radio=paths[i - 1], key_file=str(key)),
                    config=AgentConfig(profile="fast", vote="link"),
                    on_state=partial(own.__setitem__, f"agent{i}"),
                ).start()
            )
        assert agents[0].profile.vote_window == pytest.approx(1.5 * default_round_s(2))
        leader = wait_until(
            lambda: agreed(dict(own), ["agent1", "agent2"]), "a leader over the radios", DEADLINE
        )
        print(f"fast profile, signed pair: leader agent{leader} after {time.monotonic() - t0:.2f} s")
        for a in agents:
            assert a.bridge is not None and a.bridge.stats.bad_signature == 0
            assert a.bridge.stats.frames_in > 0
    finally:
        for a in agents:
            a.stop()
        emu.stop()


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--name", "a b", "--id", "1", "--radio", "x"], "invalid agent name"),
        (["--name", "a1", "--id", "251", "--radio", "x"], "1..250"),
        (["--name", "a1", "--id", "1", "--radio", "/nonexistent/radio0"], "/nonexistent/radio0"),
        (
            ["--name", "a1", "--id", "1", "--radio", "/nonexistent/radio0", "--key", "/nonexistent/key"],
            "signing key",
        ),
        (["--name", "a1", "--id", "1"], "--radio"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(
    argv: list[str], match: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from swarm.cli.commands.agent import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0] and err[0].startswith("swarm agent: error:")


def test_flight_controller_pose_reaches_the_core_and_the_key_space() -> None:
    from swarm.cli.procs import Child
    from swarm.core.wire.message_types import PoseReport

    base = free_port()
    sim = Child(["sim", "--vehicles", "1", "--profile", "ardupilot", "--base-port", str(base)], name="sim")
    ep = f"tcp/127.0.0.1:{free_port()}"
    poses: list[PoseReport] = []
    try:
        url = sim.wait_lines(1, 30)[0].split(" -> ")[1].split()[0]
        with (
            Agent(
                "flyer",
                3,
                NodeOptions(zenoh_listen=[ep]),
                fc=url,
                config=AgentConfig(vote="battery", pose_hz=10),
            ) as a,
            Transport.open("observer", connect=[ep]) as obs,
        ):
            obs.on_pose("flyer", lambda _n, p: poses.append(p))
            wait_until(lambda: poses, "a pose on swarm/flyer/pose", DEADLINE)
            assert a.core is not None and a.core.has_fc
            wait_until(
                lambda: a.core is not None and a.core.pose is not None, "the pose in the core", DEADLINE
            )
            p = poses[-1].pose
            assert 47.0 < p.lat < 48.0 and 8.0 < p.lon < 9.0  # the simulator's default home
            assert 0 <= a._battery() <= 255  # noqa: SLF001 (white box: the battery byte)
    finally:
        sim.stop()


def test_agents_handed_open_links_elect_and_leave_them_open(tmp_path: Any) -> None:
    """An Agent can be handed a link its caller opened (any radios.link.Link): it
    bridges it, and on stop leaves it open for its opener to close."""
    from radios.link import open_link
    from swarm.cli.procs import start_emulator

    emu, paths = start_emulator(2, tmp_path, "--seed", "16")  # a pair that hop-locks quickly
    own: dict[str, AgentState] = {}
    agents: list[Agent] = []
    links = []
    try:
        for i in (1, 2):
            link = open_link(paths[i - 1])
            links.append(link)
            node = NodeOptions(link=link)
            assert node.radio_url == paths[i - 1] and node.on_radio
            a = Agent(f"agent{i}", i, node, config=AgentConfig(profile="fast"))
            a.on_state = partial(own.__setitem__, f"agent{i}")
            agents.append(a.start())
        assert agents[0].describe() == f"radio={paths[0]}"
        leader = wait_until(
            lambda: agreed(dict(own), ["agent1", "agent2"]), "a leader over the handed links", DEADLINE
        )
        assert leader in (1, 2)
        for a in agents:
            assert a.bridge is not None and a.bridge.stats.frames_in > 0
            a.stop()
            assert not a.running
        assert not any(link.closed for link in links)  # the opener's to close
    finally:
        for a in agents:
            a.stop()
        for link in links:
            link.close()
        emu.stop()
