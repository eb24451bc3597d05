"""Issue 17, item 3: a station's command is answered with what the vehicle did.

A pure agent node and a pure station talk in virtual time (every message delivered
20 ms later, in both directions: GSAdvertize, connect, Telemetry, commands and
answers). The vehicle is the driver's outcome as an event: each vehicle call the
node starts ends, after the time the scenario gives it, with the :class:`CallDone`
the agent runtime would queue (the runtime's own mapping of the driver's errors,
:func:`swarm.runtime.agent.live.call_result`, is tested on the driver's real error
classes at the end). The same refusal through the real simulator, a real agent and a
real station: tests/test_command_results_processes.py.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, field

from firmware_bridge.commands import MAV_RESULT_ACCEPTED
from firmware_bridge.errors import CommandRejected, CommandTimeout
from firmware_bridge.session import WaitTimeout
from swarm.core.agent.gslink import CommandLog
from swarm.core.agent.node import AgentNode, CallDone, CallOut, NodeOut, Send, VehicleInfo
from swarm.core.election.profiles import profile_by_name
from swarm.core.flight.pilot import Call
from swarm.core.station.commands import CARRIED_OUT, NO_ANSWER, CommandSpec, Request
from swarm.core.station.core import StationCore
from swarm.core.station.model import StationConfig, StOut
from swarm.core.wire.codes import short_reason
from swarm.core.wire.message_types import REASON_MAX, AckResult, Command, CommandAck, CommandKind, Message
from swarm.core.wire.messages import decode, encode
from swarm.runtime.agent.live import call_result

AGENT = 3
STATION = 255
LATENCY = 0.02
STEP = 0.05

#: how a vehicle call ends: (seconds it takes, ok, result, reason)
Outcome = tuple[float, bool, AckResult, str]


def refused(reason: str, after: float = 0.3) -> Callable[[Call], Outcome]:
    return lambda _c: (after, False, AckResult.REJECTED, reason)


def done(after: float) -> Callable[[Call], Outcome]:
    return lambda _c: (after, True, AckResult.ACCEPTED, "")


@dataclass
class Bench:
    """One agent node with a flight controller and one station, in virtual time."""

    vehicle: Callable[[Call], Outcome]
    config: StationConfig = field(default_factory=StationConfig)
    agent_down: bool = False  # the agent's answers are lost (it keeps running)
    now: float = 0.0
    node: AgentNode = field(init=False)
    station: StationCore = field(init=False)
    calls: list[Call] = field(default_factory=list)
    acks: list[CommandAck] = field(default_factory=list)  # every answer the agent sent
    finished: list[Request] = field(default_factory=list)
    events: list[str] = field(default_factory=list)
    _air: list[tuple[float, str, Message]] = field(default_factory=list)  # (due, to, msg)
    _vehicle: list[tuple[float, CallDone]] = field(default_factory=list)

    def __post_init__(self) -> None:
        profile = profile_by_name("fast", 0.25)
        self.node = AgentNode(AGENT, "agent3", profile, rng=random.Random(1), has_fc=True)
        self.station = StationCore(config=self.config)
        self.from_node(self.node.start(0.0))
        self.run(5.0)
        assert self.station.agents[AGENT].connected

    def from_node(self, outs: list[NodeOut]) -> None:
        for o in outs:
            if isinstance(o, Send) and o.to in (0, STATION):
                if isinstance(o.msg, CommandAck):
                    self.acks.append(o.msg)
                if not self.agent_down:
                    self._air.append((self.now + LATENCY, "station", o.msg))
            elif isinstance(o, CallOut):
                self.calls.append(o.call)
                after, ok, result, reason = self.vehicle(o.call)
                error = "" if ok else f"{o.call.kind} failed ({reason})"
                self._vehicle.append((self.now + after, CallDone(o.call, ok, error, result, reason)))

    def _from_station(self, outs: list[StOut]) -> None:
        for o in outs:
            self._air.append((self.now + LATENCY, "agent", o.msg))

    def run(self, until: float) -> None:
        while self.now < until - 1e-9:
            self.now = round(self.now + STEP, 6)
            due = [x for x in self._air if x[0] <= self.now]
            self._air = [x for x in self._air if x[0] > self.now]
            for _t, to, msg in due:
                if to == "agent":
                    self.from_node(self.node.handle(msg, self.now))
                else:
                    self._from_station(self.station.handle(msg, self.now))
            for when, ev in [x for x in self._vehicle if x[0] <= self.now]:
                self._vehicle.remove((when, ev))
                self.from_node(self.node.handle(ev, self.now))
            self.from_node(self.node.tick(self.now))
            self._from_station(self.station.tick(self.now))
            self.finished += self.station.take_finished()
            self.events += [e.text for e in self.station.take_events() if e.kind == "command"]

    def submit(self, kind: CommandKind, **args: float) -> tuple[Request, int]:
        req, outs = self.station.submit(CommandSpec(AGENT, kind, **args), self.now)
        self._from_station(outs)
        return req, outs[0].msg.seq  # type: ignore[attr-defined]

    def answers(self, seq: int) -> list[tuple[str, str]]:
        return [(a.result.name, a.reason) for a in self.acks if a.seq == seq]


# -- the attack: the autopilot refuses, the station must not say ACCEPTED ------------------


def test_an_arm_the_autopilot_refuses_is_reported_refused_with_its_reason() -> None:
    b = Bench(refused("Arm: Mode not armable"))
    req, seq = b.submit(CommandKind.ARM)
    b.run(b.now + 15.0)
    assert [c.kind for c in b.calls] == ["arm"]
    assert b.finished == [req]
    assert req.body() == {
        "ok": False,
        "request": req.id,
        "results": [{"agent": AGENT, "result": "REJECTED", "reason": "Arm: Mode not armable"}],
    }
    # the agent never said ACCEPTED for it, not even before the flight controller answered
    assert {r for r, _ in b.answers(seq)} == {"REJECTED"}
    assert any("ARM -> agent3 (3): REJECTED (Arm: Mode not armable)" in e for e in b.events), b.events


def test_a_take_off_whose_arming_fails_is_reported_with_the_autopilots_text() -> None:
    b = Bench(refused("Arm: Gyros inconsistent", after=1.2))
    req, seq = b.submit(CommandKind.TAKEOFF, alt=10.0)
    b.run(b.now + 15.0)
    assert req.body()["results"][0]["result"] == "REJECTED"
    assert req.body()["results"][0]["reason"] == "Arm: Gyros inconsistent"
    assert "ACCEPTED" not in {r for r, _ in b.answers(seq)}
    assert b.node.pilot.mode.value == "IDLE"  # the pilot knows the take-off did not happen


def test_an_arm_the_vehicle_carries_out_is_accepted_once_it_is_done() -> None:
    b = Bench(done(0.2))
    req, seq = b.submit(CommandKind.ARM)
    b.run(b.now + 3.0)
    assert req.body()["ok"] is True and req.body()["results"][0]["result"] == "ACCEPTED"
    assert b.answers(seq)[0] == ("ACCEPTED", "")  # the first answer is the vehicle's


# -- the vehicle takes its time ------------------------------------------------------------


def test_retries_while_the_vehicle_is_at_it_get_in_progress_and_start_nothing() -> None:
    b = Bench(done(5.0))
    req, seq = b.submit(CommandKind.TAKEOFF, alt=10.0)
    b.run(b.now + 4.0)
    assert b.finished == []  # not done: the station does not count IN_PROGRESS as an answer
    assert b.station.commands.in_flight
    assert {r for r, _ in b.answers(seq)} == {"IN_PROGRESS"}
    assert ("IN_PROGRESS", "taking off to 10 m") in b.answers(seq)
    b.run(b.now + 4.0)
    assert len(b.calls) == 1  # every retry was answered from the log, none ran it again
    assert req.body()["ok"] is True and req.body()["results"][0]["result"] == "ACCEPTED"
    # the operator saw it was under way, once, then the result
    assert sum("IN_PROGRESS" in e for e in b.events) == 1, b.events
    assert any("TAKEOFF -> agent3 (3): ACCEPTED" in e for e in b.events), b.events


def test_a_call_longer_than_the_retry_window_is_handed_out_in_progress_then_logged() -> None:
    b = Bench(lambda c: (30.0, False, AckResult.REJECTED, "Takeoff failed: altitude not reached"))
    req, _seq = b.submit(CommandKind.TAKEOFF, alt=10.0)
    b.run(b.now + 13.0)
    assert b.finished == [req]  # the API answers at the end of the window: not done yet
    assert req.body() == {
        "ok": False,
        "request": req.id,
        "results": [{"agent": AGENT, "result": "IN_PROGRESS", "reason": "taking off to 10 m"}],
    }
    assert any("still at it after 12 s" in e for e in b.events), b.events
    b.run(b.now + 20.0)
    assert b.finished == [req]  # handed out once
    assert req.pending[0].result == "REJECTED"
    assert any(
        "TAKEOFF -> agent3 (3): REJECTED (Takeoff failed: altitude not reached)" in e for e in b.events
    )
    assert not b.station.commands.in_flight and len(b.calls) == 1


def test_an_agent_silent_after_in_progress_ends_no_answer_naming_what_it_said() -> None:
    b = Bench(done(60.0))
    req, _ = b.submit(CommandKind.TAKEOFF, alt=10.0)
    b.run(b.now + 2.0)
    b.agent_down = True
    b.run(b.now + 30.0)
    p = req.pending[0]
    assert p.result == NO_ANSWER and "last: in progress, taking off to 10 m" in p.reason, p.reason


def test_a_command_in_progress_for_ever_is_given_up_at_the_limit() -> None:
    b = Bench(done(1000.0), config=StationConfig(command_in_progress_limit=40.0))
    req, _ = b.submit(CommandKind.TAKEOFF, alt=10.0)
    b.run(b.now + 39.0)
    assert b.station.commands.in_flight
    b.run(b.now + 2.0)
    assert not b.station.commands.in_flight
    assert req.pending[0].result == NO_ANSWER


def test_evidence_still_counts_for_a_command_in_progress() -> None:
    """The vehicle shows the take-off (airborne in Telemetry) but the result never
    arrives: CARRIED_OUT, as for an unanswered command."""
    b = Bench(done(1000.0), config=StationConfig(command_in_progress_limit=30.0))
    req, _ = b.submit(CommandKind.TAKEOFF, alt=10.0)
    b.run(b.now + 2.0)
    b.from_node(b.node.handle(VehicleInfo("GUIDED", True, True, 90), b.now))
    b.run(b.now + 40.0)
    assert req.pending[0].result == CARRIED_OUT


# -- after a failsafe: "accepted" must not mean "nothing will happen" -----------------------


def flying_after_a_failsafe(b: Bench) -> None:
    """The vehicle flies 20 m up under setpoint control, then its autopilot lets go
    (PX4's setpoint-loss failsafe: AUTO.LOITER)."""
    from swarm.core.agent.node import OwnPose
    from swarm.core.wire.message_types import Pose

    here = Pose(47.397742, 8.545594, 508.0)
    b.from_node(b.node.handle(OwnPose(here, False), b.now))  # home: where it stood
    b.from_node(b.node.handle(OwnPose(Pose(here.lat, here.lon, 528.0), True), b.now))
    b.node.pilot.hold("test")
    b.from_node(b.node.handle(VehicleInfo("OFFBOARD", True, True, 80, controlled=True), b.now))
    for _ in range(2):
        b.from_node(b.node.handle(VehicleInfo("AUTO.LOITER", True, True, 80, controlled=False), b.now))
    assert b.node.pilot.control_lost == "AUTO.LOITER"


def test_a_go_to_after_a_failsafe_takes_control_back_and_is_answered_with_what_the_vehicle_did() -> None:
    """After PX4's failsafe a Go from the station was answered ACCEPTED and the vehicle
    moved 0 m. Now the agent takes control back first and the station hears the
    vehicle's result: the refusal with its reason, or ACCEPTED once it is back."""
    b = Bench(refused("mode OFFBOARD refused: no position", after=1.0))
    flying_after_a_failsafe(b)
    b.run(b.now + 3.0)  # the station sees it in the agent's Telemetry (and its API state)
    assert b.station.agents[AGENT].control_lost is True
    assert b.station.agents[AGENT].as_dict(b.now)["control_lost"] is True
    req, seq = b.submit(CommandKind.GOTO, lat=47.3979, lon=8.5456, alt=20.0)
    b.run(b.now + 10.0)
    assert [c.kind for c in b.calls] == ["control"]
    assert (
        b.answers(seq)[0][0] == "IN_PROGRESS"
        and "taking control back from AUTO.LOITER" in b.answers(seq)[0][1]
    )
    assert "ACCEPTED" not in {r for r, _ in b.answers(seq)}
    assert req.body()["results"][0]["result"] == "REJECTED"
    assert "OFFBOARD refused" in req.body()["results"][0]["reason"]
    # the vehicle lets the companion take over: the same go-to is accepted once it is back
    b.vehicle = done(0.5)
    req, seq = b.submit(CommandKind.GOTO, lat=47.3979, lon=8.5456, alt=20.0)
    b.run(b.now + 5.0)
    assert req.body()["ok"] is True and b.answers(seq)[-1] == ("ACCEPTED", "")
    b.from_node(b.node.handle(VehicleInfo("OFFBOARD", True, True, 80, controlled=True), b.now))
    assert b.node.pilot.control_lost == ""
    b.run(b.now + 3.0)
    assert b.station.agents[AGENT].control_lost is False


# -- hostile or odd results ----------------------------------------------------------------


def test_a_long_multi_line_reason_is_one_line_that_fits_the_frame() -> None:
    text = "PreArm: Gyros inconsistent\nPreArm: Accels inconsistent\x00; " + "é" * 200
    b = Bench(refused(text))
    req, seq = b.submit(CommandKind.ARM)
    b.run(b.now + 5.0)
    reason = req.pending[0].reason
    assert reason.startswith("PreArm: Gyros inconsistent PreArm: Accels inconsistent ;")
    assert reason.endswith("...") and len(reason.encode()) <= REASON_MAX
    assert all(c.isprintable() for c in reason)
    ack = CommandAck(AGENT, seq, AckResult.REJECTED, reason)
    assert decode(encode(ack)) == ack  # what the radio carries


def test_a_failed_call_is_never_answered_accepted_or_in_progress() -> None:
    for said in (AckResult.ACCEPTED, AckResult.IN_PROGRESS):
        b = Bench(lambda c, r=said: (0.2, False, r, ""))  # type: ignore[misc]
        req, seq = b.submit(CommandKind.DISARM)
        b.run(b.now + 3.0)
        assert req.pending[0].result == "FAILED"
        assert req.pending[0].reason == "disarm failed ()"  # the error line stands in
        assert "ACCEPTED" not in {r for r, _ in b.answers(seq)}


def test_a_call_result_nobody_asked_for_sends_nothing() -> None:
    b = Bench(done(0.1))
    for call in (Call("arm"), Call("arm", ticket=99)):
        assert b.node.handle(CallDone(call, True), b.now) == []


def test_a_result_for_a_seq_the_station_reused_is_not_sent() -> None:
    log = CommandLog()
    old, new = (
        Command(STATION, 5, AGENT, CommandKind.TAKEOFF, alt=10.0),
        Command(STATION, 5, AGENT, CommandKind.LAND),
    )
    log.begin(old, CommandAck(AGENT, 5, AckResult.IN_PROGRESS))
    log.record(new, CommandAck(AGENT, 5, AckResult.ACCEPTED))
    assert not log.finish(old, CommandAck(AGENT, 5, AckResult.ACCEPTED), 1.0)
    assert log.seen(new) == CommandAck(AGENT, 5, AckResult.ACCEPTED)


def test_short_reason() -> None:
    assert short_reason("  Arm:\tMode   not armable\r\n") == "Arm: Mode not armable"
    assert short_reason("x" * 200) == "x" * (REASON_MAX - 3) + "..."
    assert short_reason("") == ""
    # the driver's texts since just before the command: the last refusal's is often among them
    assert short_reason("Arm: Mode not armable; Arm: Mode not armable") == "Arm: Mode not armable"
    assert short_reason("PreArm: A; PreArm: B; PreArm: A") == "PreArm: A; PreArm: B"


# -- the runtime's reading of the driver's errors ------------------------------------------


def test_call_result_names_the_autopilots_refusal() -> None:
    denied = CommandRejected(
        "COMPONENT_ARM_DISARM rejected by ardupilot: FAILED (Arm: Mode not armable)",
        command=400,
        result=4,
        text="Arm: Mode not armable",
    )
    assert call_result(denied) == (AckResult.REJECTED, "Arm: Mode not armable")
    silent = CommandRejected("NAV_TAKEOFF rejected by ardupilot: FAILED", command=22, result=4)
    assert call_result(silent) == (AckResult.REJECTED, "NAV_TAKEOFF rejected by ardupilot: FAILED")
    not_armed = CommandRejected(
        "COMPONENT_ARM_DISARM accepted but the vehicle is not armed",
        command=400,
        result=MAV_RESULT_ACCEPTED,
        text="PreArm: Throttle below failsafe",
    )
    assert call_result(not_armed) == (
        AckResult.FAILED,
        "COMPONENT_ARM_DISARM accepted but the vehicle is not armed: PreArm: Throttle below failsafe",
    )
    timeout = CommandTimeout("COMPONENT_ARM_DISARM: no COMMAND_ACK from ardupilot after 3 tries of 1 s")
    assert call_result(timeout) == (AckResult.FAILED, str(timeout))
    assert call_result(WaitTimeout("takeoff altitude 10 m not reached"))[0] == AckResult.FAILED
    assert call_result(RuntimeError()) == (AckResult.FAILED, "RuntimeError")


def test_a_hostile_agents_reason_reaches_the_station_log_as_one_printable_line() -> None:
    """An agent (or anyone on the air with its id) can put anything in a reason: a
    terminal escape or a line break must not reach the station's log or the page."""
    b = Bench(done(0.1))
    req, seq = b.submit(CommandKind.ARM)
    evil = "Arm: ok\n2026-11-24 agent9 ACCEPTED everything\x1b[31m"
    b.station.handle(CommandAck(AGENT, seq, AckResult.REJECTED, evil), b.now)
    b.events += [e.text for e in b.station.take_events()]
    assert req.pending[0].reason == "Arm: ok 2026-11-24 agent9 ACCEPTED everything [31m"
    assert all(c.isprintable() for e in b.events for c in e), b.events


def test_a_replayed_capture_cannot_put_a_line_break_in_the_station_log() -> None:
    core = StationCore(passive=True)
    core.handle(CommandAck(AGENT, 4, AckResult.REJECTED, "no\nagent9 ACCEPTED\x07"), 1.0)
    (e,) = [e for e in core.take_events() if e.kind == "command"]
    assert e.text.endswith("answered seq 4: REJECTED (no agent9 ACCEPTED)"), e.text
