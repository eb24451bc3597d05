"""The agent side of the ground-station connection: the pure core (virtual time), then a
real agent over Zenoh answering a scripted station (connect, telemetry as heartbeat,
drop when the station goes silent, reconnect)."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest
from net_helpers import free_port, wait_until

from swarm.core.agent.gslink import CommandLog, GsConfig, GsLink
from swarm.core.wire.codes import MODES, mode_code, mode_name
from swarm.core.wire.message_types import (
    AckResult,
    CommandAck,
    GSAdvertize,
    GSConnect,
    GSConnectAck,
    GSHeartbeat,
    Heartbeat,
    Message,
    Phase,
    Pose,
    Telemetry,
)
from swarm.runtime.agent.live import Agent
from swarm.runtime.keyspace.transport import Transport
from swarm.runtime.options import AgentConfig, NodeOptions

pytestmark = pytest.mark.processes  # a real agent and its station link, in real time

POSE = Pose(47.0, 8.0, 500.0)


def tm() -> Telemetry:
    return Telemetry(3, POSE, phase=Phase.MEMBER, leader=1)


def test_advertises_until_connected_then_slowly() -> None:
    g = GsLink(3, "agent3", GsConfig(advertize_interval=1.0, advertize_connected_interval=10.0))
    ads = [t for t in range(0, 5) if any(isinstance(o.msg, GSAdvertize) for o in g.tick(float(t), tm))]
    assert ads == [0, 1, 2, 3, 4]
    assert g.handle(GSAdvertize(255, "gcs"), 5.0) == []
    out = g.handle(GSConnect(255, 7), 5.0)
    assert [(o.to, o.msg) for o in out] == [(255, GSConnectAck(3, 7, 1000))]
    assert g.connected == [255]
    ads = []
    for k in range(12, 40):
        g.handle(GSHeartbeat(255, 1), k / 2)
        if any(isinstance(o.msg, GSAdvertize) for o in g.tick(k / 2, tm)):
            ads.append(k / 2)
    assert ads == [6.0, 16.0]  # once connected, every 10 s


def test_telemetry_is_the_heartbeat_and_silence_drops_the_station() -> None:
    g = GsLink(3, "agent3", GsConfig(hb_interval=0.5, station_timeout=5.0))
    g.handle(GSAdvertize(255, "gcs"), 0.0)
    g.handle(GSConnect(255, 1), 0.0)
    sent = []
    t = 0.0
    while t < 3.0:
        sent += [o for o in g.tick(t, tm) if isinstance(o.msg, Telemetry)]
        g.handle(GSHeartbeat(255, 1), t)
        t += 0.1
    assert 5 <= len(sent) <= 7 and all(o.to == 255 for o in sent)  # 2 Hz
    dropped_at = advertised_at = None
    while t < 9.0:  # the station falls silent
        out = g.tick(t, tm)
        if dropped_at is None and not g.connected:
            dropped_at = t
        if (
            dropped_at is not None
            and advertised_at is None
            and any(isinstance(o.msg, GSAdvertize) for o in out)
        ):
            advertised_at = t
        t += 0.1
    assert g.connected == [] and g.counters.drops == 1
    assert dropped_at is not None and 7.8 < dropped_at < 8.2  # last heard at 2.9 + 5 s
    assert advertised_at == dropped_at, "advertises again at once"
    assert [o for o in g.tick(t + 1, tm) if isinstance(o.msg, Telemetry)] == []


def test_bad_peers_are_ignored_never_raised() -> None:
    g = GsLink(3, "agent3")
    assert g.handle(GSConnect(255, 1), 0.0) == []  # name unknown: cannot answer yet
    assert g.counters.unknown_station == 1
    assert g.handle(GSConnect(12, 1), 0.0) == []  # an agent id is not a station
    assert g.handle(GSAdvertize(12, "agent12"), 0.0) == []  # another agent announcing itself
    assert g.station_name(12) is None
    assert g.handle(GSHeartbeat(255, 1), 0.0) == []  # not connected
    assert g.handle(Heartbeat(1, 0, 0), 0.0) == []
    assert g.connected == []
    with pytest.raises(ValueError):
        GsConfig(hb_interval=0)


def test_mode_codes_round_trip() -> None:
    for name in MODES[1:]:
        assert mode_name(mode_code(name)) == name
    assert mode_code("NO_SUCH_MODE") == 0 and mode_name(200) == ""


def test_command_log_replays_answers_and_sends_new_ones_again() -> None:
    from swarm.core.wire.message_types import Command, CommandKind

    log = CommandLog(size=2)
    c1, c2, c3 = (Command(255, s, 3, CommandKind.ARM) for s in (1, 2, 3))
    a = CommandAck(3, 1, AckResult.ACCEPTED)
    assert log.record(c1, a, 10.0)
    assert log.seen(c1) is a and log.seen(Command(254, 1, 3, CommandKind.ARM)) is None
    assert log.next_deadline() == 10.5
    assert log.due(10.4) == [] and log.due(10.5) == [(255, a)] and log.due(11.5) == [(255, a)]
    assert log.next_deadline() is None
    log.record(c2, a)
    log.record(c3, a)
    assert log.seen(c1) is None  # oldest forgotten


# -- a real agent over Zenoh ---------------------------------------------------------


@pytest.fixture
def agent_and_station() -> Iterator[tuple[Agent, Transport, list[Message]]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    agent = Agent("agent3", 3, NodeOptions(zenoh_listen=[ep]), config=AgentConfig(seed=3)).start()
    station = Transport.open("gcs", connect=[ep])
    got: list[Message] = []
    lock = threading.Lock()

    def keep(m: Message) -> None:
        with lock:
            got.append(m)

    station.on_inbox(keep)
    station.on_gs_advertize(keep)
    try:
        yield agent, station, got
    finally:
        station.close()
        agent.stop()


def test_real_agent_connects_sends_telemetry_and_drops_a_silent_station(
    agent_and_station: tuple[Agent, Transport, list[Message]],
) -> None:
    agent, station, got = agent_and_station
    wait_until(
        lambda: any(isinstance(m, GSAdvertize) and m.sender == 3 and m.name == "agent3" for m in got),
        "the agent's GSAdvertize",
        20,
    )

    def connect(seq: int) -> None:
        def acked() -> bool:
            station.gs_advertise(GSAdvertize(255, "gcs"))
            station.send("agent3", GSConnect(255, seq))
            return any(isinstance(m, GSConnectAck) and m.seq == seq for m in got)

        wait_until(acked, f"GSConnectAck {seq}", 20, 0.5)

    connect(1)
    ack = next(m for m in got if isinstance(m, GSConnectAck))
    assert ack.sender == 3 and ack.hb_interval_ms == 1000

    def telemetry() -> list[Telemetry]:
        return [m for m in list(got) if isinstance(m, Telemetry)]

    stop_hb = threading.Event()

    def heartbeats() -> None:
        while not stop_hb.wait(0.5):
            station.send("agent3", GSHeartbeat(255, 1))

    hb = threading.Thread(target=heartbeats, daemon=True)
    hb.start()
    try:
        wait_until(lambda: len(telemetry()) >= 4, "telemetry at 1 Hz", 20)
        t0 = telemetry()[0]
        assert t0.sender == 3 and t0.phase in set(Phase)
        assert agent.gs.connected == [255]
    finally:
        stop_hb.set()
        hb.join(2)
    wait_until(lambda: agent.gs.connected == [], "the agent drops the silent station", 20)
    n = len(telemetry())
    connect(2)  # the station comes back
    wait_until(lambda: len(telemetry()) > n, "telemetry again after reconnecting", 20)


def test_real_agent_answers_commands_with_reasons_once_per_sequence_number(
    agent_and_station: tuple[Agent, Transport, list[Message]],
) -> None:
    from swarm.core.wire.message_types import Command, CommandKind

    agent, station, got = agent_and_station

    def ask(cmd: Command) -> CommandAck:
        def answered() -> CommandAck | None:
            station.gs_advertise(GSAdvertize(255, "gcs"))  # the agent learns whom to answer
            station.send("agent3", cmd)
            return next((m for m in list(got) if isinstance(m, CommandAck) and m.seq == cmd.seq), None)

        ack: CommandAck = wait_until(answered, f"an answer to {cmd.kind.name}", 20, 0.5)
        return ack

    follow = ask(Command(255, 101, 0, CommandKind.FOLLOW, heading=90.0))
    # a lone agent leads a swarm of one after its alone timeout; before that there is no leader
    assert follow.result in (AckResult.NO_LEADER, AckResult.ACCEPTED)
    if follow.result == AckResult.NO_LEADER:
        assert follow.reason == "no leader elected yet"
    wrong = ask(Command(255, 102, 7, CommandKind.LAND))
    assert wrong.result == AckResult.UNKNOWN_AGENT and "agent 3" in wrong.reason
    no_fc = ask(Command(255, 103, 3, CommandKind.TAKEOFF, alt=10.0))
    assert no_fc.result == AckResult.FAILED and "flight controller" in no_fc.reason
    # the station retries (same sequence number): the same answer, not run again
    replays = agent.stats["command_replays"]
    station.send("agent3", Command(255, 103, 3, CommandKind.TAKEOFF, alt=10.0))
    wait_until(lambda: agent.stats["command_replays"] > replays, "the retry answered from the log", 20)
    acks = {m for m in list(got) if isinstance(m, CommandAck) and m.seq == 103}
    assert acks == {no_fc}  # every answer the same
