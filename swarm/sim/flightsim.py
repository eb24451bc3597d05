"""The demo's flight in virtual time: protocol cores, pilots and vehicle dynamics over
the SiK air model. Used by ``swarm bench formation`` and the formation tests.

Theory of operation
-------------------
A :class:`FlightSim` is a :class:`swarm.sim.simulate.Sim` (N protocol cores behind the
air model, frames encoded exactly as the radio bridge does) with, for each agent,
a :class:`swarm.core.flight.pilot.Pilot` and a point-mass multicopter
(:class:`firmware_bridge.sim.dynamics.Body`, the vehicle simulator's own dynamics
with PX4's position-loop gains and limits, taking the setpoints' velocity
feed-forward as PX4 offboard does), in the scenario's :class:`swarm.sim.weather.Weather`
(steady wind and gusts pushing the bodies, GPS noise in what each vehicle believes
and reports; calm by default). On the air besides the protocol: every
agent's pose stream at ``pose_hz`` (PoseReport, broadcast) and its vehicle's
HEARTBEAT and GLOBAL_POSITION_INT at 1 Hz (the forwarded telemetry).

The flight: vehicles start hovering at ``alt_m`` in a line east of home,
``spacing_m`` apart; once the election has converged the leader gets a follow
command (heading north); ``settle_s`` later the route (north ``leg_m``, then
east ``leg_m``: a 90 degree right turn, rounded with the pilot's turn radius).
The run ends ``tail_s`` after the leader arrives (or at ``duration``).

Metrics, sampled every 0.1 s from the true positions (not from what the radio
delivered, nor from the GPS): each member's distance from its slot (the followed
agent's true position plus the offset for the leader's current task heading); at
the end, how far the leader's task heading is from the route's last heading
(``heading_error_after_turn_deg``). A sample is in a *turn* within
``turn_margin_s`` of a change of the task heading (one of at least
:data:`swarm.sim.tracks.TURN_MIN_DEG` from the last counted, as a capture's analysis
counts); *straight* samples are the others once the route has started (the V had
``settle_s`` to form). Air utilisation is the share of air time used between the
follow command and the end.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field, replace
from typing import Any

import pymap3d

from firmware_bridge.sim.dynamics import Body, Limits, Target
from radios.mavlink import FrameBuilder, dialect
from swarm.core.agent.node import AgentNode, NodeOut, OwnPose, PoseHeard, Send, SetpointOut
from swarm.core.election.outbox import ADVERTIZE, Out
from swarm.core.flight.formation import slot_error
from swarm.core.flight.pilot import PilotConfig, Setpoint
from swarm.core.wire.message_types import (
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    Message,
    Phase,
    Pose,
    PoseReport,
    TaskKind,
)
from swarm.core.wire.messages import encode
from swarm.core.wire.tunnel import Kind
from swarm.sim.simulate import Scenario, Sim
from swarm.sim.tracks import turn_changes
from swarm.sim.weather import Environment, Weather

HOME = (47.397742, 8.545594, 488.0)
DT = 0.02  # dynamics step, s


@dataclass
class FlightScenario:
    agents: int = 5
    loss: float = 0.1
    pose_hz: float = 4.0
    speed_mps: float = 5.0
    profile: str = "paper"
    alt_m: float = 20.0
    spacing_m: float = 8.0
    leg_m: float = 150.0
    settle_s: float = 20.0
    tail_s: float = 10.0
    duration: float = 240.0
    turn_margin_s: float = 8.0
    #: a setpoint reaches the autopilot this much after the pilot computed it (the
    #: agent's 10 Hz step and the driver's 10 Hz stream: 0.1 s on average)
    setpoint_delay_s: float = 0.1
    #: ("leader", "member" (the lowest id that is not the leader) or an agent id, seconds after
    #: the follow command)
    crash: tuple[str, float] | None = None
    pilot: PilotConfig = field(default_factory=PilotConfig)
    weather: Weather = field(default_factory=Weather)


@dataclass
class FlightResult:
    seed: int
    ok: bool
    leader: int
    elect_s: float | None
    rms_straight_m: float | None
    max_straight_m: float | None
    max_turn_m: float | None
    per_member: dict[int, dict[str, float | None]]
    air_utilisation: float
    end_s: float
    why: str = ""
    heading_error_after_turn_deg: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "ok": self.ok,
            "leader": self.leader,
            "elect_s": self.elect_s,
            "rms_straight_m": self.rms_straight_m,
            "max_straight_m": self.max_straight_m,
            "max_turn_m": self.max_turn_m,
            "heading_error_after_turn_deg": self.heading_error_after_turn_deg,
            "air_utilisation": round(self.air_utilisation, 3),
            "end_s": round(self.end_s, 1),
            "per_member": self.per_member,
            "why": self.why,
        }


class FlightSim(Sim):
    def __init__(self, fs: FlightScenario, seed: int) -> None:
        super().__init__(
            Scenario(agents=fs.agents, loss=fs.loss, profile=fs.profile, duration=fs.duration), seed
        )
        self.fs = fs
        n = fs.agents
        self.lim = Limits()
        self.bodies = [Body(pos=[0.0, i * fs.spacing_m, -fs.alt_m]) for i in range(n)]
        self.targets: list[Target | None] = [None] * n
        self.pending: list[list[tuple[float, Target]]] = [[] for _ in range(n)]
        self.env = Environment(fs.weather, n, seed ^ 0xA1B)
        self.route_end_heading: float | None = None
        cfg = replace(fs.pilot, speed_mps=fs.speed_mps)
        # each agent is the node the real agent runs, around the core (and its seed) Sim made
        self.nodes = [
            AgentNode(i + 1, c.name, c.profile, rng=c.rng, has_fc=True, pilot=cfg)
            for i, c in enumerate(self.cores)
        ]
        self.cores = [nd.core for nd in self.nodes]
        self.pilots = [nd.pilot for nd in self.nodes]
        for nd in self.nodes:
            nd.core.set_pose(self.pose_of(nd.id - 1, 0.0))
            nd.pilot.airborne = True
        self.vbuilders = [FrameBuilder(i + 1, 1) for i in range(n)]
        self.rng = random.Random(seed ^ 0x5EED)
        self.samples: list[tuple[float, int, float, float]] = []  # t, member, error, heading
        self.heading_log: list[tuple[float, float]] = []
        self.follow_at: float | None = None
        self.route_at: float | None = None
        self.arrived_at: float | None = None
        self.leader = 0
        self.elect_s: float | None = None
        self.busy_at_follow = 0.0
        self.crashed_at: float | None = None
        self.crashed = 0

    # -- poses --------------------------------------------------------------------
    def pose_of(self, i: int, t: float, *, true: bool = False) -> Pose:
        """Vehicle ``i``'s pose as it believes it (its GPS error added), or ``true``."""
        b = self.bodies[i]
        en, ee = (0.0, 0.0) if true else self.env.gps_error(i)
        lat, lon, alt = pymap3d.ned2geodetic(b.pos[0] + en, b.pos[1] + ee, b.pos[2], *HOME)
        return Pose(
            float(lat), float(lon), float(alt), math.degrees(b.yaw) % 360.0, b.vel[0], b.vel[1], t % 2.56
        )

    def _on_message(self, i: int, sender: int, kind: Kind, msg: Message, t: float) -> list[Out]:
        if kind == Kind.POSE:
            if isinstance(msg, PoseReport):
                return self._node_outs(i, self.nodes[i].handle(PoseHeard(msg.pose, sender), t), t)
            return []
        self._due[i] = t
        return self._node_outs(i, self.nodes[i].handle(msg, t), t)

    def _node_outs(self, i: int, outs: list[NodeOut], t: float) -> list[Out]:
        """What the air carries of a node's outputs (no ground station here: its
        answers stay on the ground); setpoints reach the vehicle ``setpoint_delay_s`` later."""
        air: list[Out] = []
        for o in outs:
            if isinstance(o, Send):
                if o.to == 0:
                    air.append(Out(ADVERTIZE, o.msg))
                elif o.to <= self.fs.agents:
                    air.append(Out(o.to, o.msg))
            elif isinstance(o, SetpointOut):
                self.pending[i].append((t + self.fs.setpoint_delay_s, _target(o.setpoint)))
        return air

    # -- the flight ----------------------------------------------------------------
    def run_flight(self) -> FlightResult:
        fs = self.fs
        n = fs.agents
        t = 0.0
        next_pilot = 0.0
        next_pose = [self.rng.uniform(0, 1.0 / fs.pose_hz) for _ in range(n)]
        next_vehicle = [self.rng.uniform(0, 1.0) for _ in range(n)]
        conv_since: float | None = None
        end = fs.duration
        self._start_nodes()
        while t <= end:
            self._maybe_crash(t)
            self.air.advance(t)
            for i in range(n):
                if self.alive[i]:
                    self._receive(i, t)
            pilot_due = t + 1e-9 >= next_pilot
            if pilot_due:  # each vehicle's true pose, as its pose thread would read it
                self._leader_after_crash()
                for i in range(n):
                    if self.alive[i]:
                        self.nodes[i].handle(OwnPose(self.pose_of(i, t), True, HOME), t)
            self._step_nodes(t, next_pose, next_vehicle)
            if pilot_due:
                next_pilot += 0.1
                conv_since, end = self._mission(t, conv_since, end)
            self._move_bodies(t)
            t = round(t + DT, 6)
        return self._result(t)

    def _start_nodes(self) -> None:
        for i in range(self.fs.agents):
            self.started[i] = True
            nd = self.nodes[i]
            nd.handle(OwnPose(self.pose_of(i, 0.0), True, HOME), 0.0)
            self._send(i, self._node_outs(i, nd.start(0.0), 0.0), 0.0)
            nd.pilot.hold("hovering")

    def _step_nodes(self, t: float, next_pose: list[float], next_vehicle: list[float]) -> None:
        """Each live node's timers, pose stream and forwarded vehicle frames at ``t``."""
        for i in range(self.fs.agents):
            if not self.alive[i]:
                continue
            if self._due[i] <= t + 1e-9:
                nd = self.nodes[i]
                self._send(i, self._node_outs(i, nd.tick(t), t), t)
                self._due[i] = nd.next_deadline()
            if t + 1e-9 >= next_pose[i]:
                next_pose[i] += 1.0 / self.fs.pose_hz
                self._write(i, Kind.POSE, (0,), encode(PoseReport(self.pose_of(i, t))), t)
            if t + 1e-9 >= next_vehicle[i]:
                next_vehicle[i] += 1.0
                self._forward_vehicle(i, t)

    def _mission(self, t: float, conv_since: float | None, end: float) -> tuple[float | None, float]:
        """The operator's steps (FOLLOW once agreed for 1 s, the route once settled,
        the tail once arrived) and the formation samples: (conv_since, end) updated."""
        fs = self.fs
        if self.follow_at is None:
            ok, lead = self._agreement()
            conv_since = (conv_since if conv_since is not None else t) if ok else None
            if ok and conv_since is not None and t - conv_since >= 1.0:
                self._follow(lead, t)
                self.elect_s = conv_since
        elif self.route_at is None and t - self.follow_at >= fs.settle_s:
            self._route(t)
        elif self.route_at is not None and self.arrived_at is None:
            lp = self.pilots[self.leader - 1]
            if lp.mode.value == "HOLD" and lp.hold_reason == "arrived":
                self.arrived_at = t
                end = min(end, t + fs.tail_s)
        if self.follow_at is not None:
            self._sample(t)
        return conv_since, end

    def _move_bodies(self, t: float) -> None:
        """Setpoints whose delay has passed reach their vehicles; every body moves one step:
        its autopilot flies its position estimate (true + GPS error) to the target, and the
        wind pushes it by what the autopilot has not cancelled yet."""
        env, calm = self.env, self.fs.weather.calm
        for i in range(self.fs.agents):
            q = self.pending[i]
            while q and q[0][0] <= t + 1e-9:
                self.targets[i] = q.pop(0)[1]
            b, tg = self.bodies[i], self.targets[i]
            if calm or tg is None:
                b.step(tg, self.lim, DT, True)
                continue
            en, ee = env.gps_error(i)
            b.step(replace(tg, pos=(tg.pos[0] - en, tg.pos[1] - ee, tg.pos[2])), self.lim, DT, True)
            if not b.on_ground:
                dn, de = env.push(i, b.vel, DT)
                b.vel[0] += dn
                b.vel[1] += de
        if not calm:
            env.step(DT)

    def _maybe_crash(self, t: float) -> None:
        c = self.fs.crash
        if c is None or self.follow_at is None or t < self.follow_at + c[1] or self.crashed_at is not None:
            return
        if c[0] == "leader":
            victim = self.leader
        elif c[0] == "member":
            victim = min(k for k in range(1, self.fs.agents + 1) if k != self.leader)
        else:
            victim = int(c[0])
        self.alive[victim - 1] = False
        self.dead_at[victim] = t
        self.crashed_at = t
        self.crashed = victim

    def _leader_after_crash(self) -> None:
        if self.crashed_at is not None and not self.alive[self.leader - 1]:
            ok, lead = self._agreement()
            if ok and lead:
                self.leader = lead  # the survivors' new leader carries on

    def _command(self, i: int, cmd: Command, t: float) -> tuple[AckResult, str]:
        """A ground command to agent ``i``'s node, as a station's would arrive."""
        outs = self.nodes[i].handle(cmd, t)
        self._send(i, self._node_outs(i, outs, t), t)
        ack = next(o.msg for o in outs if isinstance(o, Send) and isinstance(o.msg, CommandAck))
        assert isinstance(ack, CommandAck)
        return ack.result, ack.reason

    def _follow(self, lead: int, t: float) -> None:
        self.leader = lead
        res, why = self._command(lead - 1, Command(255, 1, 0, CommandKind.FOLLOW, heading=0.0), t)
        if res != AckResult.ACCEPTED:
            raise RuntimeError(f"follow refused: {why}")
        self.follow_at = t
        self.busy_at_follow = self.air.busy_s

    def _route(self, t: float) -> None:
        i = self.leader - 1
        o = self.pose_of(i, t)
        leg = self.fs.leg_m
        a = pymap3d.ned2geodetic(leg, 0.0, 0.0, o.lat, o.lon, o.alt)
        b = pymap3d.ned2geodetic(leg, leg, 0.0, o.lat, o.lon, o.alt)
        self.route_end_heading = 90.0  # the second leg: east
        for k, (kind, p) in enumerate(((CommandKind.GOTO, a), (CommandKind.WAYPOINT, b))):
            res, why = self._command(
                i, Command(255, 2 + k, i + 1, kind, float(p[0]), float(p[1]), o.alt - HOME[2]), t
            )
            if res != AckResult.ACCEPTED:
                raise RuntimeError(f"route refused: {why}")
        self.route_at = t

    def _forward_vehicle(self, i: int, t: float) -> None:
        p = self.pose_of(i, t)
        b = self.vbuilders[i]
        hb = dialect.MAVLink_heartbeat_message(2, 12, 217, 6 << 16, 4, 3)
        gpi = dialect.MAVLink_global_position_int_message(
            int(t * 1000) & 0xFFFFFFFF,
            round(p.lat * 1e7),
            round(p.lon * 1e7),
            round(p.alt * 1000),
            round(self.fs.alt_m * 1000),
            round(p.vn * 100),
            round(p.ve * 100),
            0,
            round(p.heading * 100) % 36000,
        )
        for m in (hb, gpi):
            self.air.host_write(i, b.build(m), t)

    def _sample(self, t: float) -> None:
        lead = self.cores[self.leader - 1]
        if not self.alive[self.leader - 1] or lead.phase != Phase.LEADER or lead.task.kind != TaskKind.FOLLOW:
            return
        task = lead.task
        self.heading_log.append((t, task.heading))
        poses = {i + 1: self.pose_of(i, t, true=True) for i in range(self.fs.agents) if self.alive[i]}
        for a in task.assignments:
            if a.member in poses and a.follows in poses:
                err = slot_error(
                    poses[a.member], poses[a.follows], task.heading, a.side, task.back_m, task.side_m
                )
                self.samples.append((t, a.member, err, task.heading))

    def _result(self, t: float) -> FlightResult:
        fs = self.fs
        heads = self.heading_log
        turning = set()
        # a sample is "in a turn" within turn_margin_s of a heading change (as a capture's)
        changes = turn_changes(heads)
        for tt, _ in heads:
            if any(abs(tt - c) <= fs.turn_margin_s for c in changes):
                turning.add(round(tt, 3))
        straight: list[float] = []
        turn: list[float] = []
        per: dict[int, list[float]] = {}
        per_turn: dict[int, list[float]] = {}
        for tt, m, err, _h in self.samples:
            if self.route_at is None or tt < self.route_at:
                continue
            if round(tt, 3) in turning:
                turn.append(err)
                per_turn.setdefault(m, []).append(err)
            else:
                straight.append(err)
                per.setdefault(m, []).append(err)
        ok = self.arrived_at is not None and bool(straight)
        why = (
            ""
            if ok
            else (
                "the election never converged"
                if self.follow_at is None
                else "the leader did not finish the route"
            )
        )
        span = max(t - (self.follow_at or 0.0), 1e-9)
        util = (self.air.busy_s - self.busy_at_follow) / span if self.follow_at is not None else 0.0
        members = sorted(set(per) | set(per_turn))
        return FlightResult(
            seed=self.seed,
            ok=ok,
            leader=self.leader,
            elect_s=self.elect_s,
            rms_straight_m=_rms(straight),
            max_straight_m=round(max(straight), 2) if straight else None,
            max_turn_m=round(max(turn), 2) if turn else None,
            per_member={
                m: {
                    "rms_straight_m": _rms(per.get(m, [])),
                    "max_m": round(max(per.get(m, []) + per_turn.get(m, [])), 2),
                }
                for m in members
            },
            air_utilisation=util,
            end_s=t,
            why=why,
            heading_error_after_turn_deg=self._heading_error(),
        )

    def _heading_error(self) -> float | None:
        """How far the leader's task heading ended from the route's last heading."""
        if self.route_end_heading is None or not self.heading_log:
            return None
        d = (self.heading_log[-1][1] - self.route_end_heading + 180.0) % 360.0 - 180.0
        return round(abs(d), 2)


def _target(sp: Setpoint) -> Target:
    n_, e_, d_ = pymap3d.geodetic2ned(sp.lat, sp.lon, sp.alt, *HOME)
    return Target(
        pos=(float(n_), float(e_), float(d_)), vel=(sp.vn, sp.ve, math.nan), yaw=math.radians(sp.yaw_deg)
    )


def _rms(v: list[float]) -> float | None:
    return round(math.sqrt(sum(x * x for x in v) / len(v)), 3) if v else None


def run(fs: FlightScenario, seed: int = 0) -> FlightResult:
    return FlightSim(fs, seed).run_flight()


__all__ = ["FlightResult", "FlightScenario", "FlightSim", "run"]
