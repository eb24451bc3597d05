"""What one agent's vehicle does: commands, the formation, holds. A pure state machine.

Theory of operation
-------------------
:class:`Pilot` sits beside the protocol core and turns commands, the leader's task
and the poses heard on the air into what the flight controller should do. It does
no I/O and reads no clock: the runtime (``swarm.runtime.agent.live``) or the virtual-time
flight simulator (``swarm.sim.flightsim``) feeds it

* ``set_own(pose, airborne, home)``: the vehicle's own state and its home;
* ``on_pose(sender, pose, now)``: every agent's pose stream;
* ``command(cmd, role, now)``: a Command, decided at once: (result, reason, calls).
  A command with vehicle calls is only *accepted by the pilot*; its reason says what
  is being done ("arming") and the answer to the station waits for the calls'
  results (:func:`swarm.core.agent.gslink.answer_command`);
* ``step(now, role)`` at the setpoint rate (10 Hz), which returns a
  :class:`~swarm.core.flight.formation.Setpoint` to stream (or None: leave the vehicle alone)
  and the one-shot :class:`Call` s the runtime makes on the vehicle (arm, take off,
  land, return...). ``call_done`` reports how a call ended.

Modes and what they stream:

==========  ======================================================================
IDLE        nothing (on the ground, or flying before any command)
TAKEOFF     nothing: the runtime takes off (and puts the vehicle under setpoint
            control); then HOLD where it is, at the height asked for above the
            ground it last stood on (the take-off returns at 95 % of it)
HOLD        the latched hold position (stop command, swarm stop, arrival)
GOTO        a carrot moving along a :class:`~swarm.core.flight.formation.Route` at ``speed_mps``
            (never more than ``max_lead_m`` ahead of the vehicle), velocity feed-forward
FOLLOW      the slot behind the followed agent (members only)
LAND, RTL   nothing: the autopilot lands or returns
==========  ======================================================================

Rules (each stated once, here):

* **Follow** (swarm command, target 0, to the leader): refused by a member
  (REJECTED, naming the leader) and by an agent that knows no leader (NO_LEADER).
  The leader makes a FOLLOW task (new ``gen``), assignments from its members'
  positions; the core keeps it in step with membership (``formation.reconcile``).
  While it flies a route the leader's task heading is the route's heading.
* A member with an assignment in a FOLLOW task follows, unless it left that
  task's generation for an individual command (GOTO, STOP, LAND, RETURN); a
  new follow command (a new gen) brings it back. A member on the ground does not
  take off by itself.
* **Stale pose**: a followed pose older than ``stale_s`` (or none yet): hold.
* **Separation**: in GOTO or FOLLOW, an agent closer than ``min_separation_m``:
  hold, report it, resume when beyond the minimum plus ``separation_clear_m``. Both
  agents see the same distance, so both hold; a setpoint that leads away from
  every agent too close is still flown (so that two holding agents cannot lock
  each other for ever while re-forming); beside another agent (closer than
  ``CO_LOCATED_M`` across, as two copters started at one point) no direction is
  away: the higher id goes, the lower one too unless it would follow the other.
  An individual GOTO or STOP from the operator clears it (the operator is
  resolving it) and that agent is not checked again until it has been clear once
  or 10 s passed.
* **Geofence** (:mod:`swarm.core.flight.geofence`): a command's altitude is metres above
  home (the vehicle's, else where it last stood); a take-off or a go-to below the
  fence's floor, above its ceiling or beyond its radius from home is refused
  (BAD_ARGUMENT, the limit it breaks); a go-to with no home known is REJECTED.
* **Stop**: an individual STOP holds this agent; the swarm STOP makes the leader
  hold and send a HOLD task, and every member holds.
* The swarm heading a leader announces on a route is the route's heading averaged
  around the leader (``formation.Route.mean_heading``), so its rate ramps through
  a corner and it ends on the route's heading; after arriving, the leader goes on
  turning the V until it faces the route's last heading. A member uses the task's
  heading extrapolated with the task's turn rate from the Heartbeat it came on, so
  that the slots rotate smoothly between Heartbeats.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import StrEnum

from swarm.core.flight.formation import (
    AccelEstimator,
    AgeEstimator,
    FormationConfig,
    Route,
    Setpoint,
    assign,
    assignment_of,
    carried_motion,
    chain_of,
    distance,
    follow_target,
    ne_between,
    offset,
    steer_heading,
    turn_window_m,
)
from swarm.core.flight.geofence import Geofence
from swarm.core.wire.codes import SELECTABLE_MODES, mode_name
from swarm.core.wire.message_types import (
    LEGACY_KINDS,
    AckResult,
    Command,
    CommandKind,
    Phase,
    Pose,
    Task,
    TaskKind,
)

MAX_GOTO_M = 5000.0
MIN_TAKEOFF_M = 1.0
SEPARATION_WAIVER_S = 10.0
#: the swarm's turn acceleration is estimated from Heartbeats at least this far apart (the
#: turn rate on the air is in steps of 0.5 deg/s), and believed up to this (deg/s^2)
TURN_ACCEL_SPAN_S = 0.3
TURN_ACCEL_MAX = 20.0
CO_LOCATED_M = 1.0  # closer than this across, no direction is away from another agent
#: the commands that need the vehicle under setpoint control (taken back first)
TAKE_BACK = frozenset({CommandKind.GOTO, CommandKind.WAYPOINT, CommandKind.FOLLOW, CommandKind.TAKEOFF})


class Mode(StrEnum):
    IDLE = "IDLE"
    TAKEOFF = "TAKEOFF"
    HOLD = "HOLD"
    GOTO = "GOTO"
    FOLLOW = "FOLLOW"
    LAND = "LAND"
    RETURN = "RETURN"
    AUTOPILOT = "AUTOPILOT"  # the autopilot flies it in a mode the operator chose (SET_MODE)


#: the pilot's modes in which the autopilot, not our setpoints, flies the vehicle (as asked)
AUTOPILOT_FLIES = (Mode.IDLE, Mode.TAKEOFF, Mode.LAND, Mode.RETURN, Mode.AUTOPILOT)


@dataclass(frozen=True)
class Call:
    """A one-shot action on the vehicle: arm, disarm, takeoff (alt: metres above
    home), land, return. ``ticket``: the node's number for it, carried back in its
    CallDone, so that the result answers the command that asked for it."""

    kind: str
    alt: float = 0.0
    ticket: int = 0
    mode: str = ""  # "mode": the autopilot mode to switch to


@dataclass(frozen=True)
class Role:
    """The protocol's view the pilot needs: our phase, the leader, the members (leader)."""

    phase: Phase
    leader: int = 0
    members: frozenset[int] = frozenset()
    poses: dict[int, Pose] | None = None  # members' poses the leader heard in acks


@dataclass(frozen=True)
class PilotConfig:
    speed_mps: float = 5.0
    accel_mps2: float = 1.0
    turn_radius_m: float = 25.0
    heading_accel_dps2: float = 3.0
    max_lead_m: float = 8.0
    arrive_m: float = 1.0
    formation: FormationConfig = field(default_factory=FormationConfig)
    fence: Geofence = field(default_factory=Geofence)

    def __post_init__(self) -> None:
        for k, lo, hi in (
            ("speed_mps", 0.1, 20.0),
            ("accel_mps2", 0.1, 10.0),
            ("turn_radius_m", 0.0, 200.0),
            ("max_lead_m", 1.0, 100.0),
            ("arrive_m", 0.1, 20.0),
            ("heading_accel_dps2", 0.5, 100.0),
        ):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"pilot {k}={v!r}: {lo:g}..{hi:g}")


@dataclass
class _Heard:
    pose: Pose
    rx: float
    age: float  # estimated age at reception
    acc: tuple[float, float] = (0.0, 0.0)  # estimated acceleration (north, east m/s^2)

    def age_at(self, now: float) -> float:
        return self.age + max(0.0, now - self.rx)


@dataclass
class Pilot:
    me: int
    cfg: PilotConfig = field(default_factory=PilotConfig)

    mode: Mode = Mode.IDLE
    own: Pose | None = None
    airborne: bool = False
    hold_at: Setpoint | None = None
    hold_reason: str = ""
    task: Task = field(default_factory=Task)  # the swarm task (leader: ours; member: heard)
    events: list[str] = field(default_factory=list)  # for the runtime to log / report
    too_close: dict[int, float] = field(default_factory=dict)  # agent -> distance, while holding for it
    last_setpoint: Setpoint | None = None
    stale_hold: Setpoint | None = None  # holding in FOLLOW: the followed pose is stale
    sep_hold: Setpoint | None = None  # holding: another agent too close
    _heard: dict[int, _Heard] = field(default_factory=dict)
    _accels: AccelEstimator = field(default_factory=AccelEstimator)
    _ages: AgeEstimator = field(default_factory=AgeEstimator)
    _route: Route | None = None
    _route_pts: list[tuple[float, float]] = field(default_factory=list)
    _route_origin: tuple[float, float] = (0.0, 0.0)
    route_alt: float = 0.0
    _route_s: float = 0.0
    _route_v: float = 0.0
    _swarm_h: float | None = None  # the leader's announced swarm heading (smoothed)
    _swarm_rate: float = 0.0
    _ground_alt: float | None = None  # AMSL altitude last seen on the ground (take-off height base)
    home: tuple[float, float, float] | None = None  # lat, lon, metres AMSL: what altitudes are above
    control_lost: str = ""  # the mode the autopilot took by itself, in the air ("": none)
    _uncontrolled: int = 0  # vehicle reports in a row not under setpoint control
    _last_step: float | None = None
    _left_gen: int | None = None  # the FOLLOW gen we left for an individual command
    _applied_task: tuple[TaskKind, int] = (TaskKind.NONE, -1)
    _heading: tuple[float, float, float] | None = None  # (heading, at, rate deg/s)
    _rate_ref: tuple[float, float] | None = None  # (at, turn rate) the turn's acceleration is from
    turn_accel: float = 0.0  # deg/s^2, from the turn rates of successive Heartbeats
    _waived: dict[int, float] = field(default_factory=dict)  # separation waived until
    _gen: int = 0

    # -- inputs -------------------------------------------------------------------
    def set_own(
        self, pose: Pose | None, airborne: bool, home: tuple[float, float, float] | None = None
    ) -> None:
        """The vehicle's pose, whether it flies, and its home (lat, lon, metres AMSL) when
        the autopilot told it; without one, home is where the vehicle last stood."""
        self.own = pose
        self.airborne = airborne
        if pose is not None and not airborne:
            self._ground_alt = pose.alt
        if home is not None:
            self.home = home
        elif pose is not None and not airborne:
            self.home = (pose.lat, pose.lon, pose.alt)

    def set_control(self, controlled: bool | None, mode: str) -> None:
        """Whether the vehicle follows the companion's setpoints (its autopilot in
        OFFBOARD or GUIDED), from its heartbeat; None: not known. In the air, in a mode
        that streams setpoints, a vehicle its autopilot let go of (PX4's setpoint-loss
        failsafe, an RC switch) is said once (two reports in a row: one may predate a
        mode switch just made) and kept in :attr:`control_lost`, which a go-to, stop,
        take-off or follow then takes back (a ``control`` call)."""
        if controlled is None:
            return
        if controlled:
            self._uncontrolled = 0
            if self.control_lost:
                self.events.append(f"back under setpoint control ({mode})")
                self.control_lost = ""
            return
        if not self.airborne or self.mode in AUTOPILOT_FLIES:
            self._uncontrolled = 0
            if self.control_lost and not self.airborne:  # it landed by itself: nothing left to take back
                self.events.append(f"landed under the autopilot's control ({mode or 'unknown'})")
                self.control_lost = ""
            return
        self._uncontrolled += 1
        if self._uncontrolled < 2:
            return
        if not self.control_lost:
            self.events.append(
                f"the autopilot left setpoint control by itself (now {mode or 'unknown'}): not following "
                "the swarm; a go-to, stop, take-off or follow takes control back"
            )
        self.control_lost = mode or "unknown"

    def _take_back(self, result: AckResult, why: str, calls: list[Call]) -> tuple[AckResult, str, list[Call]]:
        """An accepted command that needs the vehicle under setpoint control: take it
        back first when its autopilot let go (the station hears the vehicle's result)."""
        if result != AckResult.ACCEPTED or not self.control_lost or not self.airborne:
            return result, why, calls
        back = f"taking control back from {self.control_lost}"
        return result, f"{why}: {back}" if why else back, [*calls, Call("control")]

    def on_pose(self, sender: int, pose: Pose, now: float) -> None:
        if sender == self.me:
            return
        age = self._ages.age(sender, pose.t, now)
        self._heard[sender] = _Heard(pose, now, age, self._accels.add(sender, now - age, pose.vn, pose.ve))

    def on_task(self, task: Task, now: float) -> None:
        """The swarm task as a member heard it, on every Heartbeat: the heading and its
        turn rate, extrapolated from ``now`` until the next one."""
        if task.kind == TaskKind.FOLLOW:
            ref = self._rate_ref
            if ref is None or not 0.0 <= now - ref[0] <= 2.0:  # nothing recent to tell it from
                self.turn_accel, self._rate_ref = 0.0, (now, task.turn_rate)
            elif now - ref[0] >= TURN_ACCEL_SPAN_S:  # (a Heartbeat closer than that: kept as it is)
                acc = (task.turn_rate - ref[1]) / (now - ref[0])
                self.turn_accel = max(-TURN_ACCEL_MAX, min(TURN_ACCEL_MAX, acc))
                self._rate_ref = (now, task.turn_rate)
            self._heading = (task.heading, now, task.turn_rate)
        else:
            self._rate_ref, self.turn_accel = None, 0.0
        self.task = task

    def call_done(self, call: Call, ok: bool, error: str = "") -> None:
        if call.kind == "control":
            self.events.append("took control back: holding" if ok else f"taking control back failed: {error}")
            return
        if call.kind == "mode":
            if ok and self.mode == Mode.AUTOPILOT:
                self.control_lost = (
                    call.mode
                )  # not following: a go-to, stop, take-off or follow takes it back
                self.events.append(
                    f"in {call.mode} at the operator's request: not following the swarm; a go-to, stop, "
                    "take-off or follow takes control back"
                )
            elif not ok and self.mode == Mode.AUTOPILOT:
                self.hold(f"mode {call.mode} refused")
                self.events.append(f"mode {call.mode} failed: {error}")
            return
        if not ok:
            self.events.append(f"{call.kind} failed: {error}")
            if call.kind == "takeoff" and self.mode == Mode.TAKEOFF:
                self.mode = Mode.IDLE
            return
        if call.kind == "takeoff" and self.mode == Mode.TAKEOFF:
            self.airborne = True
            self.hold("took off")
            want = None if self._ground_alt is None else self._ground_alt + call.alt
            # the height asked for, unless the ground we saw is far off it (a pose before the fix)
            if (
                self.hold_at is not None
                and want is not None
                and abs(want - self.hold_at.alt) <= max(2.0, 0.2 * call.alt)
            ):
                self.hold_at = replace(self.hold_at, alt=want)
            self.events.append("took off: holding")

    # -- commands -------------------------------------------------------------------
    def command(self, cmd: Command, role: Role, now: float) -> tuple[AckResult, str, list[Call]]:
        """Answer a command: (result, reason, vehicle calls to make now). A go-to,
        waypoint, stop, follow or take-off in the air takes control back first when the
        autopilot let go of the vehicle (:meth:`set_control`)."""
        if cmd.kind == CommandKind.SET_MODE:
            return self._set_mode(cmd, role, now)
        result, why, calls = self._decide(cmd, role, now)
        if cmd.kind in (CommandKind.LAND, CommandKind.RETURN):
            self.control_lost, self._uncontrolled = "", 0  # the autopilot flies it now, as asked
            return result, why, calls
        if cmd.kind in TAKE_BACK or (cmd.kind == CommandKind.STOP and cmd.target != 0):
            return self._take_back(result, why, calls)
        if cmd.kind == CommandKind.STOP and self.control_lost and result == AckResult.ACCEPTED:
            return self._take_back(result, why, calls)  # the swarm stop: the leader holds too
        return result, why, calls

    def _set_mode(self, cmd: Command, role: Role, now: float) -> tuple[AckResult, str, list[Call]]:
        """The operator's mode selector: a landing or return mode is LAND or RETURN, the
        setpoint mode (OFFBOARD, GUIDED) this agent's STOP (take control back, hold);
        a hold mode (AUTO.LOITER, BRAKE) hands the vehicle to its autopilot, in the air
        only: the agent leaves the formation and stops its setpoints, and says it is not
        following (``control_lost``) until a go-to, stop, take-off or follow."""
        name = mode_name(cmd.mode)
        what = SELECTABLE_MODES.get(name)
        if cmd.target == 0:
            return AckResult.BAD_ARGUMENT, "SET_MODE is sent to each agent, not to the swarm", []
        if what is None:
            shown = name or repr(cmd.mode)
            return (
                AckResult.BAD_ARGUMENT,
                f"mode {shown} is not one to select: {', '.join(SELECTABLE_MODES)}",
                [],
            )
        if what in ("land", "return", "swarm"):
            kind = {"land": CommandKind.LAND, "return": CommandKind.RETURN, "swarm": CommandKind.STOP}[what]
            return self.command(replace(cmd, kind=kind), role, now)
        if not self.airborne:
            return AckResult.REJECTED, f"on the ground: {name} is for a vehicle in the air", []
        self._leave_formation()
        self._waive(now)
        self.mode = Mode.AUTOPILOT
        return AckResult.ACCEPTED, f"switching to {name}", [Call("mode", mode=name)]

    def _decide(self, cmd: Command, role: Role, now: float) -> tuple[AckResult, str, list[Call]]:
        k = cmd.kind
        swarm = cmd.target == 0
        if swarm and k not in (CommandKind.FOLLOW, CommandKind.STOP):
            return AckResult.BAD_ARGUMENT, f"{k.name} is sent to each agent, not to the swarm", []
        if k == CommandKind.FOLLOW or (swarm and k == CommandKind.STOP):
            if role.phase != Phase.LEADER:
                if role.phase == Phase.MEMBER and role.leader:
                    return AckResult.REJECTED, f"not the leader: send it to agent {role.leader}", []
                return AckResult.NO_LEADER, "no leader elected yet", []
            self._gen = (max(self._gen, self.task.gen) + 1) & 0xFF
            if k == CommandKind.STOP:
                self.task = Task(TaskKind.HOLD, gen=self._gen)
                self.hold("swarm stop")
                return AckResult.ACCEPTED, "", []
            if not (math.isfinite(cmd.heading) and 0.0 <= cmd.heading < 360.0):
                return AckResult.BAD_ARGUMENT, f"heading {cmd.heading!r} outside 0..360", []
            f = self.cfg.formation
            assignments = assign(self.me, role.members, cmd.heading, role.poses, self.own)
            self.task = Task(TaskKind.FOLLOW, cmd.heading, f.back_m, f.side_m, assignments, self._gen)
            self._heading = (cmd.heading, now, 0.0)
            return AckResult.ACCEPTED, "", []
        if k == CommandKind.ARM:
            return AckResult.ACCEPTED, "arming", [Call("arm")]
        if k == CommandKind.DISARM:
            if self.airborne:
                return AckResult.REJECTED, "in the air: land first", []
            return AckResult.ACCEPTED, "disarming", [Call("disarm")]
        if k == CommandKind.TAKEOFF:
            why = self.cfg.fence.alt_refusal(cmd.alt)
            if why is None and not cmd.alt >= MIN_TAKEOFF_M:
                why = f"altitude {cmd.alt:g} m: a take-off climbs {MIN_TAKEOFF_M:g} m at least"
            if why is not None:
                return AckResult.BAD_ARGUMENT, "take-off " + why, []
            if self.airborne and self.mode not in (Mode.IDLE, Mode.LAND, Mode.RETURN):
                return AckResult.ACCEPTED, "already flying", []
            self._leave_formation()
            self.mode = Mode.TAKEOFF
            return AckResult.ACCEPTED, f"taking off to {cmd.alt:g} m", [Call("takeoff", cmd.alt)]
        if k == CommandKind.LAND:
            self._leave_formation()
            self.mode = Mode.LAND
            return AckResult.ACCEPTED, "switching to land", [Call("land")]
        if k == CommandKind.RETURN:
            self._leave_formation()
            self.mode = Mode.RETURN
            return AckResult.ACCEPTED, "switching to return", [Call("return")]
        if k == CommandKind.STOP:
            self._leave_formation()
            self._waive(now)
            self.hold("stop command")
            return AckResult.ACCEPTED, "", []
        if k in (CommandKind.GOTO, CommandKind.WAYPOINT):
            return self._goto(cmd, now, append=k == CommandKind.WAYPOINT)
        if k in LEGACY_KINDS:  # its altitude is AMSL: never guess which a sender meant
            return AckResult.REJECTED, "an older station's go-to (altitude AMSL): update the station", []
        return AckResult.BAD_ARGUMENT, f"unknown command {k!r}", []

    def _goto(self, cmd: Command, now: float, *, append: bool) -> tuple[AckResult, str, list[Call]]:
        home = self.home
        why = self.cfg.fence.refusal(cmd.lat, cmd.lon, cmd.alt, None if home is None else home[:2])
        if why is not None:
            return AckResult.BAD_ARGUMENT, why, []
        if self.own is None or not self.airborne or self.mode in (Mode.TAKEOFF, Mode.LAND, Mode.RETURN):
            return AckResult.REJECTED, "not flying under setpoint control: take off first", []
        if home is None:
            return AckResult.REJECTED, "home unknown: the geofence cannot be checked", []
        alt = home[2] + cmd.alt  # the setpoints are AMSL
        if append and self.mode == Mode.GOTO and self._route is not None:
            o = self._route_origin
            n, e = ne_between(o[0], o[1], cmd.lat, cmd.lon)
            if math.hypot(n - self._route_pts[-1][0], e - self._route_pts[-1][1]) > MAX_GOTO_M:
                return AckResult.BAD_ARGUMENT, f"waypoint more than {MAX_GOTO_M:g} m from the last", []
            self._route_pts.append((n, e))
            self._route = Route(self._route_pts, self.cfg.turn_radius_m)
            return AckResult.ACCEPTED, "", []
        n, e = ne_between(self.own.lat, self.own.lon, cmd.lat, cmd.lon)
        if math.hypot(n, e) > MAX_GOTO_M:
            why = f"target {math.hypot(n, e):.0f} m away (at most {MAX_GOTO_M:g})"
            return AckResult.BAD_ARGUMENT, why, []
        if self.mode == Mode.FOLLOW:
            self._leave_formation()
        self._waive(now)
        start = self.last_setpoint if self.mode in (Mode.HOLD, Mode.GOTO) and self.last_setpoint else None
        o = (start.lat, start.lon) if start is not None else (self.own.lat, self.own.lon)
        self._route_origin = o
        self.route_alt = alt
        tn, te = ne_between(o[0], o[1], cmd.lat, cmd.lon)
        if math.hypot(tn, te) < 0.5:
            self.mode, self.hold_reason = Mode.HOLD, "at the target"
            self.hold_at = Setpoint(cmd.lat, cmd.lon, alt, self._yaw())
            return AckResult.ACCEPTED, "", []
        self._route_pts = [(0.0, 0.0), (tn, te)]
        self._route = Route(self._route_pts, self.cfg.turn_radius_m)
        self._route_s = 0.0
        self._route_v = 0.0
        self._swarm_h = self.task.heading if self.task.kind == TaskKind.FOLLOW else None
        self._swarm_rate = 0.0
        self.mode = Mode.GOTO
        return AckResult.ACCEPTED, "", []

    def _leave_formation(self) -> None:
        if self.task.kind == TaskKind.FOLLOW:
            self._left_gen = self.task.gen

    def _waive(self, now: float) -> None:
        for a in list(self.too_close):
            self._waived[a] = now + SEPARATION_WAIVER_S
        self.too_close.clear()

    def _yaw(self) -> float:
        return self.own.heading if self.own is not None else 0.0

    def hold(self, why: str) -> None:
        """Hold where the vehicle is (where it was sent, when it has just arrived) for ``why``."""
        self.mode = Mode.HOLD
        self.hold_reason = why
        if self.own is not None:
            base = self.last_setpoint if self.last_setpoint is not None and why == "arrived" else None
            p = base or Setpoint(self.own.lat, self.own.lon, self.own.alt, self._yaw())
            self.hold_at = Setpoint(p.lat, p.lon, p.alt, p.yaw_deg)
        else:
            self.hold_at = None

    # -- the 10 Hz step -------------------------------------------------------------------
    def step(self, now: float, role: Role) -> tuple[Setpoint | None, tuple[float, float] | None]:
        """The setpoint to stream now (None: none), and for a leader flying a route in
        FOLLOW (or arrived, still turning the V) a new (heading, turn rate) for its task
        when it changed (:meth:`_steer_swarm`; else None)."""
        dt = 0.0 if self._last_step is None else max(0.0, min(now - self._last_step, 1.0))
        self._last_step = now
        self._apply_task(role)
        new_heading: tuple[float, float] | None = None
        sp: Setpoint | None = None
        leading = role.phase == Phase.LEADER and self.task.kind == TaskKind.FOLLOW
        # a leader steers the V's heading on its route, and once arrived until it faces the route's end
        steering = leading and (
            self.mode == Mode.GOTO or (self.mode == Mode.HOLD and self.hold_reason == "arrived")
        )
        if self.mode == Mode.HOLD:
            sp = self.hold_at
        elif self.mode == Mode.GOTO:
            sp = self._carrot(dt)
        elif self.mode == Mode.FOLLOW:
            sp = self._follow(now, role)
        if steering and sp is not None:
            new_heading = self._steer_swarm(dt)
        elif leading and self.task.turn_rate != 0.0:
            # stopped turning (held, or off the route): the V stops turning too
            new_heading = (self.task.heading, 0.0)
            self.task = replace(self.task, turn_rate=0.0)
            self._swarm_rate = 0.0
        if sp is not None and self.mode in (Mode.GOTO, Mode.FOLLOW):
            sp = self._separation(now, sp)
        self.last_setpoint = sp
        return sp, new_heading

    def _apply_task(self, role: Role) -> None:
        t = self.task
        if role.phase == Phase.LEADER:
            if self.mode == Mode.FOLLOW:
                self.hold("leading now")
            return
        if role.phase != Phase.MEMBER:
            if self.mode == Mode.FOLLOW:
                self.hold("no leader")
            return
        key = (t.kind, t.gen)
        if t.kind == TaskKind.HOLD and key != self._applied_task:
            self._applied_task = key
            if self.mode in (Mode.GOTO, Mode.FOLLOW, Mode.HOLD):
                self.hold("swarm stop")
        elif t.kind == TaskKind.FOLLOW:
            self._applied_task = key
            if (
                assignment_of(t, self.me) is not None
                and self._left_gen != t.gen
                and self.airborne
                and self.mode in (Mode.IDLE, Mode.HOLD, Mode.FOLLOW)
            ):
                if self.mode != Mode.FOLLOW:
                    self.events.append(f"following (task {t.gen})")
                self.mode = Mode.FOLLOW
            elif self.mode == Mode.FOLLOW and assignment_of(t, self.me) is None:
                self.hold("not in the formation")

    def _carrot(self, dt: float) -> Setpoint | None:
        r = self._route
        if r is None or self.own is None:
            return self.hold_at
        o = self._route_origin
        here_n, here_e = ne_between(o[0], o[1], self.own.lat, self.own.lon)
        p = r.at(self._route_s)
        # the carrot's speed: ramps up and down at accel_mps2 (the formation follows the
        # leader's velocity; a step would throw every slot), and waits for a lagging vehicle
        left = r.length - self._route_s
        want = min(self.cfg.speed_mps, math.sqrt(2.0 * self.cfg.accel_mps2 * max(left, 0.0)))
        if math.hypot(p.n - here_n, p.e - here_e) >= self.cfg.max_lead_m:
            want = 0.0
        dv = self.cfg.accel_mps2 * dt
        v0 = self._route_v
        self._route_v = max(want, v0 - dv) if want < v0 else min(want, v0 + dv)
        self._route_s = min(r.length, self._route_s + self._route_v * dt)
        p = r.at(self._route_s)
        v = self._route_v
        lat, lon = offset(o[0], o[1], p.n, p.e)
        h = math.radians(p.heading_deg)
        if self._route_s >= r.length:
            end = Setpoint(lat, lon, self.route_alt, p.heading_deg)
            if math.hypot(p.n - here_n, p.e - here_e) < self.cfg.arrive_m:
                self.last_setpoint = end
                self.hold("arrived")
                self.events.append("arrived: holding")
            return end
        return Setpoint(lat, lon, self.route_alt, p.heading_deg, v * math.cos(h), v * math.sin(h))

    def _steer_swarm(self, dt: float) -> tuple[float, float] | None:
        """A leader's swarm heading one step on (module docstring): toward the route's
        heading averaged around where the carrot is, or, arrived, the route's last
        heading. Returns (heading, rate) for the task when the heading moved by 0.5
        degree, the rate changed or, turning no more, it is not exactly the target."""
        r, cfg = self._route, self.cfg
        if r is None:
            return None
        half = turn_window_m(cfg.speed_mps, cfg.turn_radius_m, cfg.heading_accel_dps2)
        going = self.mode == Mode.GOTO
        target, per_m = r.mean_heading(self._route_s if going else r.length + half, half)
        if self._swarm_h is None:
            self._swarm_h, self._swarm_rate = target, 0.0
        ff = per_m * self._route_v if going else 0.0
        h, rate = steer_heading(self._swarm_h, self._swarm_rate, target, ff, cfg.heading_accel_dps2, dt)
        if not going and abs((target - h + 180.0) % 360.0 - 180.0) < 0.05 and abs(rate) < 0.1:
            h, rate = target, 0.0  # arrived and turned: exactly the route's heading
        self._swarm_h, self._swarm_rate = h, rate
        d = (h - self.task.heading + 180.0) % 360.0 - 180.0
        wire = max(-63.5, min(63.5, round(rate * 2) / 2))
        if abs(d) >= 0.5 or wire != self.task.turn_rate or (wire == 0.0 and abs(d) >= 0.01):
            self.task = replace(self.task, heading=round(h % 360.0, 2) % 360.0, turn_rate=wire)
            return self.task.heading, wire
        return None

    def _swarm_heading(self, now: float) -> tuple[float, float]:
        if self._heading is None:
            return self.task.heading, 0.0
        h, t0, rate = self._heading
        dt = now - t0
        if dt > 2.0:  # heartbeats lost for long: stop turning the slots
            return h, 0.0
        return (h + rate * max(0.0, dt)) % 360.0, rate

    def swarm_turn_accel(self, rate: float) -> float:
        """How fast the swarm's turn rate changes (deg/s^2), for the feed-forward: 0 while
        the rate heard is 0 (a turn starting shows in the next Heartbeat's rate), and a
        slowing turn never fed forward past a rate of 0 (the leader's rate stops there)."""
        acc = self.turn_accel
        if rate == 0.0 or self._heading is None:
            return 0.0
        if rate * acc < 0.0:
            cap = abs(rate) / max(self.cfg.formation.accel_lead_s, 0.1)
            acc = max(-cap, min(cap, acc))
        return acc

    def _follow(self, now: float, role: Role) -> Setpoint | None:
        a = assignment_of(self.task, self.me)
        if a is None:
            return self.hold_at
        heard = self._heard.get(a.follows)
        stale = self.cfg.formation.stale_s
        if heard is None or heard.age_at(now) > stale:
            if self.stale_hold is None:
                self.events.append(f"holding: no fresh pose of agent {a.follows} (over {stale:g} s)")
                o = self.own
                self.stale_hold = Setpoint(o.lat, o.lon, o.alt, self._yaw()) if o is not None else None
            return self.stale_hold
        if self.stale_hold is not None:
            self.events.append(f"pose of agent {a.follows} back: following")
            self.stale_hold = None
        heading, rate = self._swarm_heading(now)
        turn_acc = self.swarm_turn_accel(rate)
        followed, acc = heard.pose, heard.acc
        head, k = chain_of(self.task, self.me)
        lead = self._heard.get(head)
        if k > 1 and lead is not None and lead.age_at(now) <= stale:
            # further down an arm: the leader's motion, carried to the agent followed
            t = self.task
            (vn, ve), acc = carried_motion(
                lead.pose, lead.acc, heading, rate, turn_acc, a.side, t.back_m, t.side_m, k - 1
            )
            followed = replace(followed, vn=vn, ve=ve)
        return follow_target(
            followed,
            heard.age_at(now),
            heading,
            a.side,
            self.cfg.formation,
            self.task.back_m,
            self.task.side_m,
            rate,
            acc,
            turn_acc,
        )

    def _separation(self, now: float, sp: Setpoint) -> Setpoint | None:
        """Hold while another agent is too close, except for a setpoint that takes us
        away from every agent too close (so two holding agents cannot lock each other
        for ever: whichever is going away from the other goes on)."""
        if self.own is None or not self.airborne:
            return sp
        f = self.cfg.formation
        close: dict[int, float] = {}
        near: list[tuple[int, Pose]] = []
        for a, h in self._heard.items():
            if h.age_at(now) > f.stale_s:
                continue
            d = distance(self.own, h.pose)
            waived = self._waived.get(a)
            if waived is not None:
                if now < waived and d < f.min_separation_m + f.separation_clear_m:
                    continue
                del self._waived[a]
            limit = f.min_separation_m + (f.separation_clear_m if a in self.too_close else 0.0)
            if d < limit:
                close[a] = round(d, 1)
                near.append((a, h.pose))
        if close and not self.too_close:
            self.events.append(
                "holding: too close to "
                + ", ".join(f"agent {a} ({d:.1f} m)" for a, d in sorted(close.items()))
            )
            self.sep_hold = Setpoint(self.own.lat, self.own.lon, self.own.alt, self._yaw())
        elif not close and self.too_close:
            self.events.append("separation restored: resuming")
        self.too_close = close
        if not close:
            return sp
        gn, ge = ne_between(self.own.lat, self.own.lon, sp.lat, sp.lon)
        if math.hypot(gn, ge) > 0.5 and all(self._leads_away(gn, ge, a, q) for a, q in near):
            return sp  # moving away from all of them
        return self.sep_hold

    def _leads_away(self, gn: float, ge: float, other: int, q: Pose) -> bool:
        """Whether going (``gn``, ``ge``) from here parts us from agent ``other`` at
        ``q``. Beside it (within :data:`CO_LOCATED_M` across: two copters started at
        one point) no direction is away from it: the higher id goes, and the lower
        one too unless that would follow the other's own motion."""
        assert self.own is not None
        dn, de = ne_between(self.own.lat, self.own.lon, q.lat, q.lon)
        if math.hypot(dn, de) >= CO_LOCATED_M:
            return gn * -dn + ge * -de > 0
        return self.me > other or gn * q.vn + ge * q.ve <= 0

    # -- reporting -----------------------------------------------------------------------
    @property
    def holding(self) -> bool:
        return (
            bool(self.too_close)
            or self.mode == Mode.HOLD
            or (self.mode == Mode.FOLLOW and self.stale_hold is not None)
        )

    def take_events(self) -> list[str]:
        ev, self.events = self.events, []
        return ev

    def status(self) -> dict[str, object]:
        a = assignment_of(self.task, self.me)
        return {
            "mode": self.mode.value,
            "holding": self.holding,
            "hold_reason": self.hold_reason,
            "too_close": dict(self.too_close),
            "control_lost": self.control_lost,
            "follows": a.follows if a else 0,
            "side": a.side.name if a else "",
            "task": self.task.kind.name,
            "gen": self.task.gen,
        }


__all__ = ["Call", "Mode", "Pilot", "PilotConfig", "Role"]
