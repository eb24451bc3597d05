"""Command delivery in virtual time: the station's retries with back-off over 12 s,
swarm commands that follow the leader through an election, the results that say what
happened (ACCEPTED, a refusal, CARRIED_OUT, NO_ANSWER), the agent's answer log
(a repeat is answered, never run twice), and a lossy campaign (20% of messages lost
each way, an election in the middle) where no command is silently lost or wrongly
reported.

The real processes over the emulated radios at 20% loss: tests/test_command_processes.py."""

from __future__ import annotations

import random
from dataclasses import dataclass, field

import pytest

from swarm.core.agent.gslink import CommandLog, answer_command, remembered
from swarm.core.flight.pilot import Pilot, PilotConfig, Role
from swarm.core.station.commands import CARRIED_OUT, NO_ANSWER, RESULTS, CommandRefused, CommandSpec
from swarm.core.station.core import StationCore
from swarm.core.station.model import StationConfig, StOut
from swarm.core.wire.codes import FLAG_ARMED, FLAG_FC_OK, mode_code
from swarm.core.wire.message_types import (
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    GSAdvertize,
    GSConnect,
    GSConnectAck,
    Phase,
    Pose,
    Telemetry,
)

POSE = Pose(47.397, 8.545, 488.0, 90.0)


def tm(
    sender: int, *, mode: str = "POSCTL", flags: int = FLAG_FC_OK, phase: Phase = Phase.IDLE, leader: int = 0
) -> Telemetry:
    return Telemetry(sender, POSE, mode_code(mode), flags, phase, leader, 80, 180, 170, 0.0)


def commands(outs: list[StOut]) -> list[StOut]:
    return [o for o in outs if isinstance(o.msg, Command)]


def station(*ids: int, leader: int = 0, mode: str = "POSCTL", flags: int = FLAG_FC_OK) -> StationCore:
    core = StationCore()
    for i in ids:
        out = core.handle(GSAdvertize(i, f"agent{i}"), 0.0)
        (c,) = [o for o in out if isinstance(o.msg, GSConnect)]
        core.handle(GSConnectAck(i, c.msg.seq, 1000), 0.0)
        core.handle(
            tm(
                i,
                mode=mode,
                flags=flags,
                phase=Phase.LEADER if i == leader else Phase.MEMBER if leader else Phase.IDLE,
                leader=leader,
            ),
            0.0,
        )
    core.take_events()
    return core


def run(
    core: StationCore, t0: float, t1: float, step: float = 0.1, telemetry: dict[int, Telemetry] | None = None
) -> list[tuple[float, StOut]]:
    """Tick from t0 to t1 (agents keep sending ``telemetry`` every second); what was sent."""
    sent = []
    t = t0
    while t <= t1 + 1e-9:
        if telemetry and abs(t - round(t)) < 1e-6:
            for m in telemetry.values():
                core.handle(m, t)
        sent += [(round(t, 2), o) for o in commands(core.tick(t))]
        t = round(t + step, 2)
    return sent


# -- the station ----------------------------------------------------------------------


def test_retries_back_off_over_twelve_seconds_then_no_answer() -> None:
    core = station(3)
    req, out = core.submit(CommandSpec(3, CommandKind.GOTO, lat=47.4, lon=8.55, alt=20.0), 1.0)
    seq = out[0].msg.seq
    sent = run(core, 1.0, 20.0, telemetry={3: tm(3)})
    # 0.5, 1, 2, 3, 4 s apart: six tries in all, every one with the same seq
    assert [t for t, _ in sent] == [1.5, 2.5, 4.5, 7.5, 11.5]
    assert {o.msg.seq for _, o in sent} == {seq}
    assert req.done and req.status == 504
    (r,) = req.body()["results"]
    assert r["result"] == NO_ANSWER and r["reason"] == "no answer after 6 tries in 12 s"
    assert [e.text for e in core.take_events()][-1].startswith("GOTO -> agent3 (3): NO_ANSWER")


def test_an_answer_on_the_fifth_try_is_accepted() -> None:
    core = station(3)
    req, out = core.submit(CommandSpec(3, CommandKind.LAND), 0.0)
    sent = run(core, 0.0, 6.6)
    assert len(sent) == 4  # 0.5, 1.5, 3.5, 6.5
    core.handle(CommandAck(3, out[0].msg.seq, AckResult.ACCEPTED), 6.7)
    assert req.done and req.body() == {
        "ok": True,
        "request": req.id,
        "results": [{"agent": 3, "result": "ACCEPTED", "reason": ""}],
    }


def test_a_return_carried_out_whose_answers_were_all_lost_is_carried_out() -> None:
    """Issue 11, item 5: a RETURN executed but whose ack was lost showed NO_ANSWER."""
    core = station(3)
    req, _ = core.submit(CommandSpec(3, CommandKind.RETURN), 0.0)
    run(core, 0.0, 2.0, telemetry={3: tm(3)})
    run(core, 2.1, 14.0, telemetry={3: tm(3, mode="AUTO.RTL")})  # it is flying home
    assert req.done and req.status == 200
    body = req.body()
    assert body["ok"] is True
    assert body["results"] == [
        {
            "agent": 3,
            "result": CARRIED_OUT,
            "reason": "no answer after 6 tries in 12 s, but it shows mode AUTO.RTL",
        }
    ]


@pytest.mark.parametrize(
    ("kind", "before", "after", "shown"),
    [
        (CommandKind.ARM, tm(3), tm(3, flags=FLAG_FC_OK | FLAG_ARMED), "armed"),
        (CommandKind.DISARM, tm(3, flags=FLAG_FC_OK | FLAG_ARMED), tm(3), "disarmed"),
        (CommandKind.LAND, tm(3), tm(3, mode="LAND"), "mode LAND"),
        (CommandKind.TAKEOFF, tm(3), tm(3, mode="AUTO.TAKEOFF"), "mode AUTO.TAKEOFF"),
    ],
)
def test_evidence_per_command(kind: CommandKind, before: Telemetry, after: Telemetry, shown: str) -> None:
    core = station(3)
    core.handle(before, 0.0)
    req, _ = core.submit(CommandSpec(3, kind, alt=10.0), 0.0)
    run(core, 0.0, 13.0, telemetry={3: after})
    assert req.body()["results"][0]["result"] == CARRIED_OUT
    assert req.body()["results"][0]["reason"].endswith("it shows " + shown)


def test_a_state_that_was_already_there_is_no_evidence() -> None:
    core = station(3, mode="AUTO.RTL", flags=FLAG_FC_OK | FLAG_ARMED)
    for kind in (CommandKind.ARM, CommandKind.RETURN):
        req, _ = core.submit(CommandSpec(3, kind), 0.0)
        run(core, 0.0, 13.0, telemetry={3: tm(3, mode="AUTO.RTL", flags=FLAG_FC_OK | FLAG_ARMED)})
        assert req.body()["results"][0]["result"] == NO_ANSWER, kind
        core = station(3, mode="AUTO.RTL", flags=FLAG_FC_OK | FLAG_ARMED)


def test_a_swarm_follow_sent_before_an_election_reaches_the_new_leader() -> None:
    """Issue 11, item 5: a FOLLOW sent just after an election got NO_ANSWER."""
    core = station(1, 2, 3, leader=2)
    req, out = core.submit(CommandSpec(None, CommandKind.FOLLOW, heading=90.0), 0.0)
    assert [(o.to, o.msg.target) for o in out] == [(2, 0)]
    seq = out[0].msg.seq
    # agent 2 lost its leadership; the others elected agent 3
    for i in (1, 2, 3):
        core.handle(tm(i, phase=Phase.LEADER if i == 3 else Phase.MEMBER, leader=3), 0.3)
    assert core.leader == 3
    sent = run(core, 0.3, 0.6)
    assert [(o.to, o.msg.seq, o.msg.target) for _, o in sent] == [(3, seq, 0)]
    core.handle(CommandAck(3, seq, AckResult.ACCEPTED), 0.7)
    assert req.done and req.body() == {
        "ok": True,
        "request": req.id,
        "results": [{"agent": 3, "result": "ACCEPTED", "reason": "", "swarm": True}],
    }


def test_not_the_leader_is_not_final_while_time_remains() -> None:
    core = station(1, 2, leader=2)
    req, out = core.submit(CommandSpec(None, CommandKind.FOLLOW, heading=90.0), 0.0)
    seq = out[0].msg.seq
    # 2 lost the lead and says so; the station does not see the new leader yet
    core.handle(CommandAck(2, seq, AckResult.REJECTED, "not the leader: send it to agent 1"), 0.2)
    assert not req.done
    for i in (1, 2):
        core.handle(tm(i, phase=Phase.LEADER if i == 1 else Phase.MEMBER, leader=1), 0.3)
    sent = run(core, 0.3, 0.3)
    assert [(o.to, o.msg.seq) for _, o in sent] == [(1, seq)]  # at once, not at the next back-off
    core.handle(CommandAck(1, seq, AckResult.ACCEPTED), 0.4)
    assert req.body()["results"] == [{"agent": 1, "result": "ACCEPTED", "reason": "", "swarm": True}]


def test_a_refusal_that_stays_is_the_result_at_give_up() -> None:
    core = station(1, 2, leader=2)
    req, out = core.submit(CommandSpec(None, CommandKind.FOLLOW, heading=90.0), 0.0)
    for t, o in [(0.0, out[0]), *run(core, 0.0, 11.9)]:
        core.handle(CommandAck(2, o.msg.seq, AckResult.NO_LEADER, "no leader elected yet"), t + 0.05)
    assert not req.done
    run(core, 12.0, 12.0)
    assert req.body()["results"] == [
        {"agent": 2, "result": "NO_LEADER", "reason": "no leader elected yet", "swarm": True}
    ]


def test_the_old_leaders_late_accept_counts_and_later_answers_are_duplicates() -> None:
    core = station(1, 2, leader=2)
    req, out = core.submit(CommandSpec(None, CommandKind.STOP), 0.0)
    to_leader = out[0].msg.seq
    for i in (1, 2):
        core.handle(tm(i, phase=Phase.LEADER if i == 1 else Phase.MEMBER, leader=1), 0.2)
    run(core, 0.2, 0.6)  # the retry went to 1
    core.handle(CommandAck(2, to_leader, AckResult.ACCEPTED), 0.7)  # 2 did carry it out
    core.handle(CommandAck(1, to_leader, AckResult.ACCEPTED), 0.8)
    assert req.pending[0].as_dict() == {"agent": 2, "result": "ACCEPTED", "reason": "", "swarm": True}
    assert core.counters.duplicate_acks == 1 and core.counters.late_acks == 0
    core.handle(CommandAck(3, to_leader, AckResult.ACCEPTED), 0.9)  # never sent to 3
    assert core.counters.late_acks == 1


def test_config_refuses_a_bad_back_off() -> None:
    for bad in ((), (0.5, -1.0), (float("nan"),), [0.5]):
        with pytest.raises(ValueError, match="command_backoff"):
            StationConfig(command_backoff=bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="command_give_up"):
        StationConfig(command_give_up=0)


def test_result_names_are_stable() -> None:
    assert RESULTS == (
        "ACCEPTED",
        "REJECTED",
        "UNKNOWN_AGENT",
        "NOT_CONNECTED",
        "NO_LEADER",
        "BAD_ARGUMENT",
        "FAILED",
        "IN_PROGRESS",
        "CARRIED_OUT",
        "NO_ANSWER",
    )


def test_a_restarted_station_does_not_reuse_its_seqs() -> None:
    a, b = StationCore(first_seq=1), StationCore(first_seq=40000)
    for core in (a, b):
        core.handle(GSAdvertize(3, "agent3"), 0.0)
        core.handle(GSConnectAck(3, core.agents[3].connect_seq or 0, 1000), 0.0)
    assert a.submit(CommandSpec(3, CommandKind.ARM), 0.0)[1][0].msg.seq == 1
    assert b.submit(CommandSpec(3, CommandKind.ARM), 0.0)[1][0].msg.seq == 40000


# -- the agent's answers ------------------------------------------------------------------


def decide_counting(runs: list[Command]):  # type: ignore[no-untyped-def]
    def decide(c: Command) -> tuple[AckResult, str, list[str]]:
        runs.append(c)
        return AckResult.ACCEPTED, "", ["takeoff"]

    return decide


def test_a_repeat_is_answered_the_same_and_starts_nothing() -> None:
    log, runs = CommandLog(), []  # type: ignore[var-annotated]
    cmd = Command(255, 7, 3, CommandKind.TAKEOFF, alt=10.0)
    ack, calls, repeat = answer_command(log, cmd, 3, True, decide_counting(runs))
    progress = CommandAck(3, 7, AckResult.IN_PROGRESS, "on the flight controller")
    assert (ack, calls, repeat) == (progress, ["takeoff"], False)
    # the take-off is still climbing when the station's retry arrives: answered from the log
    assert answer_command(log, cmd, 3, True, decide_counting(runs)) == (ack, [], True)
    # climbed: the vehicle's result answers it, and every retry from now on
    assert log.finish(cmd, CommandAck(3, 7, AckResult.ACCEPTED), 9.0)
    assert answer_command(log, cmd, 3, True, decide_counting(runs)) == (
        CommandAck(3, 7, AckResult.ACCEPTED),
        [],
        True,
    )
    assert len(runs) == 1


def test_same_seq_other_content_is_a_new_command() -> None:
    """A restarted station counting from the same seq must not get an old answer."""
    log, runs = CommandLog(), []  # type: ignore[var-annotated]
    answer_command(log, Command(255, 1, 3, CommandKind.ARM), 3, True, decide_counting(runs))
    repeat = answer_command(log, Command(255, 1, 3, CommandKind.LAND), 3, True, decide_counting(runs))[2]
    assert not repeat and len(runs) == 2 and runs[-1].kind == CommandKind.LAND
    # another station's seq 1 is another command too
    assert not answer_command(log, Command(254, 1, 3, CommandKind.LAND), 3, True, decide_counting(runs))[2]


def test_a_swarm_not_the_leader_is_not_remembered() -> None:
    follow = Command(255, 9, 0, CommandKind.FOLLOW, heading=90.0)
    assert not remembered(follow, CommandAck(3, 9, AckResult.REJECTED, "not the leader"))
    assert not remembered(follow, CommandAck(3, 9, AckResult.NO_LEADER))
    assert remembered(follow, CommandAck(3, 9, AckResult.BAD_ARGUMENT))
    assert remembered(Command(255, 9, 3, CommandKind.GOTO), CommandAck(3, 9, AckResult.REJECTED))
    log = CommandLog()
    pilot = Pilot(3, PilotConfig())
    member, leader = Role(Phase.MEMBER, 2, frozenset(), {}), Role(Phase.LEADER, 3, frozenset({1}), {})
    ack, _, _ = answer_command(log, follow, 3, False, lambda c: pilot.command(c, member, 0.0))
    assert ack.result == AckResult.REJECTED
    # an election later this agent leads: the same command (same seq) is now its own
    ack, _, repeat = answer_command(log, follow, 3, False, lambda c: pilot.command(c, leader, 1.0))
    assert ack.result == AckResult.ACCEPTED and not repeat
    assert answer_command(log, follow, 3, False, lambda c: pilot.command(c, leader, 2.0))[2]


def test_the_log_forgets_the_oldest() -> None:
    log = CommandLog(size=2)
    cmds = [Command(255, s, 3, CommandKind.ARM) for s in (1, 2, 3)]
    for c in cmds:
        log.record(c, CommandAck(3, c.seq, AckResult.ACCEPTED))
    assert log.seen(cmds[0]) is None and log.seen(cmds[2]) is not None


# -- a lossy campaign ---------------------------------------------------------------------


@dataclass
class SimAgent:
    """The agent side as the runtime has it: the answer log and a real pilot."""

    id: int
    log: CommandLog = field(default_factory=CommandLog)
    pilot: Pilot | None = None
    carried_out: list[tuple[int, int]] = field(default_factory=list)  # (seq, heading) of ACCEPTED

    def __post_init__(self) -> None:
        self.pilot = Pilot(self.id, PilotConfig())


def campaign(seed: int, n: int, loss: float) -> dict[str, int]:
    """n swarm commands (FOLLOW with changing headings, STOP) from a station core to three
    agents over a channel losing ``loss`` of the messages each way and delaying them
    0.05..0.4 s; the leader changes every 7 commands. Counts as the bench does."""
    rng = random.Random(seed)
    core = station(1, 2, 3, leader=3)
    agents = {i: SimAgent(i) for i in (1, 2, 3)}
    leader = 3
    t = 0.0
    air: list[tuple[float, int, object]] = []  # (arrival time, to: agent id or 0 station, msg)
    reports: list[tuple[int, str, int]] = []  # (seq, result, agent)
    refused_here = 0

    def send(to: int, msg: object) -> None:
        if rng.random() >= loss:
            air.append((t + rng.uniform(0.05, 0.4), to, msg))

    for k in range(n):
        if k % 7 == 6:  # an election: the lead moves, the station hears of it a bit later
            leader = leader % 3 + 1
        spec = (
            CommandSpec(None, CommandKind.FOLLOW, heading=float(k % 360))
            if k % 2 == 0
            else CommandSpec(None, CommandKind.STOP)
        )
        try:
            req, out = core.submit(spec, t)
        except CommandRefused:  # no leader or nobody connected this instant: nothing sent
            refused_here += 1
            t = round(t + 0.5, 2)
            continue
        for o in out:
            send(o.to, o.msg)
        while not req.done:
            t = round(t + 0.05, 2)
            if abs(t - round(t)) < 1e-6:  # 1 Hz telemetry from each agent
                for i in agents:
                    send(0, tm(i, phase=Phase.LEADER if i == leader else Phase.MEMBER, leader=leader))
            now, air[:] = [m for m in air if m[0] <= t], [m for m in air if m[0] > t]
            for _, to, msg in sorted(now, key=lambda m: m[0]):
                if to == 0:
                    assert isinstance(msg, (Telemetry, CommandAck, GSConnectAck))
                    core.handle(msg, t)
                    continue
                if isinstance(msg, GSConnect):  # the station lost us for a while: answer
                    send(0, GSConnectAck(to, msg.seq, 1000))
                    continue
                if not isinstance(msg, Command):
                    continue  # GSHeartbeat
                ag = agents[to]
                pilot = ag.pilot
                assert pilot is not None
                role = Role(
                    Phase.LEADER if to == leader else Phase.MEMBER,
                    leader,
                    frozenset(agents) - {to} if to == leader else frozenset(),
                    {},
                )
                now_t = t
                ack, _, repeat = answer_command(
                    ag.log, msg, to, False, lambda c, r=role, p=pilot, n=now_t: p.command(c, r, n), t
                )
                if not repeat and ack.result == AckResult.ACCEPTED:
                    ag.carried_out.append((msg.seq, ag.id))
                send(0, ack)
            for o in core.tick(t):
                if o.to:
                    send(o.to, o.msg)
            for ag in agents.values():
                for _, again in ag.log.due(t):
                    send(0, again)
        reports += [(p.msg.seq, p.result or "", p.agent) for p in req.pending]
    done = {seq for a in agents.values() for seq, _ in a.carried_out}
    out = {
        "sent": len(reports),
        "refused_at_station": refused_here,
        "accepted": 0,
        "carried_out_unacked": 0,
        "refused": 0,
        "no_answer": 0,
        "silently_lost": 0,
        "wrongly_reported": 0,
    }
    for seq, result, agent in reports:
        if result == "ACCEPTED":
            out["accepted"] += 1
            ok = (seq, agent) in {(s, a.id) for a in agents.values() for s, _ in a.carried_out}
            out["silently_lost"] += 0 if ok else 1
        elif result == CARRIED_OUT:
            out["carried_out_unacked"] += 1
            out["wrongly_reported"] += 0 if seq in done else 1
        elif result == NO_ANSWER:
            out["no_answer"] += 1
            out["wrongly_reported"] += 1 if seq in done else 0
        else:
            out["refused"] += 1
            out["wrongly_reported"] += 1 if seq in done else 0
    return out


def test_at_20_percent_loss_with_elections_nothing_is_lost_or_misreported() -> None:
    figures = campaign(seed=11, n=200, loss=0.2)
    assert figures["sent"] > 200
    assert figures["silently_lost"] == 0 and figures["wrongly_reported"] == 0, figures
    assert figures["no_answer"] <= 2, figures
