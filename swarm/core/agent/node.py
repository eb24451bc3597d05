"""One swarm agent as a pure state machine: the protocol core, the pilot, the
ground-station link, the command log and the pose bookkeeping, composed once.

Theory of operation
-------------------
:class:`AgentNode` is what runs on one drone, minus the world. It is fed events
with the current time and returns what to do; it never reads a clock, opens a port
or starts a thread, so the real-time agent (:mod:`swarm.runtime.agent.live`) and the
virtual-time flight simulator (:mod:`swarm.sim.flightsim`) drive the same code:

* ``start(now)``, then ``handle(event, now)`` for each event, ``tick(now)`` at
  ``next_deadline()`` (or sooner: a tick before its time does nothing wrong).
* **Events in**: a swarm or station :class:`~swarm.core.wire.message_types.Message` received;
  :class:`PoseHeard` (another agent's pose stream); :class:`OwnPose` (this vehicle's
  pose, and whether it is airborne); :class:`VehicleInfo` (the flight controller's
  mode, arming, battery, link: what Telemetry reports); :class:`RadioInfo` (the
  local radio's RSSI); :class:`SetTask` (the task a leader carries on its
  Heartbeats); :class:`VehicleLink` (the flight controller fell silent or came back);
  :class:`PositionFix` (the flight controller's position became valid or stopped
  being one); :class:`CallDone` (a vehicle call finished); :class:`AutopilotText`
  (a STATUSTEXT of the flight controller); :class:`RadioAway` and :class:`RadioBack`
  (the radio lent or lost, and back: "Deaf" below); :class:`RadioRestored` (the radio
  guard put back a radio a rogue had moved off the swarm: a leader left with no member
  steps down and rejoins, :meth:`~swarm.core.election.protocol.Core.rejoin`).
* **Outputs**: :class:`Send` (a message to an agent or station id, with the name the
  node learnt for it, or to everyone: ``to`` 0 for Advertize and GSAdvertize);
  :class:`PublishState` (when the election state changed, and as a keep-alive:
  every ``profile.state_interval``, every 5 s once leading or following);
  :class:`SetpointOut` (the pilot's setpoint, every 0.1 s while it steers);
  :class:`CallOut` (a blocking vehicle call: arm, take-off...); :class:`EventOut`
  (a line for the operator: commands, the pilot's events, the vehicle link).

What the node decides, as the agent did before it: Advertize from our own id with
another name is an id conflict (counted, reported once); names and ids are learnt
from Advertize; a member hands every Heartbeat's task to the pilot (its heading and
turn rate); a Command is answered once per station and sequence number
(:func:`swarm.core.agent.gslink.answer_command`: a repeat is answered from the log,
never run twice; answers are sent again 0.5 and 1.5 s later; a command carried out
on the vehicle is answered when its :class:`CallDone` comes back, with the vehicle's
result and the autopilot's reason, and IN_PROGRESS to a retry meanwhile), and an accepted swarm
FOLLOW or STOP on the leader becomes the task on its Heartbeats; the leader's pilot
steers the task's heading during a FOLLOW; the vehicle link going down is told to the
core (a leader that cannot fly hands over). Without a valid position the node says
"waiting for position" once (with the reason) and "position valid" when it comes;
a fix that is lost takes the node's own pose back to none, so neither Telemetry nor
a HeartbeatAck carries the last position as if it were current.

**Deaf**: while the radio is away (:class:`RadioAway` to :class:`RadioBack`: lent to
the radio guard's check for about 2.3 s, or unplugged) the node hears no one, and that
says nothing about who is there. So the election core runs on its own clock, the
node's time less the time the radio was away, standing still while it is: no window
closes, no leader or member times out and no agent becomes a swarm of one on a
silence it could not hear, and its timers resume where they stood once the radio is
back; then a leader sends its Heartbeat and a member its HeartbeatAck at once
(:meth:`~swarm.core.election.protocol.Core.resume`), for the others' timers did not stand
still. The fault bench saw both: a member, expelled while a flood of garbage kept its
radio from sending, its radio re-checked every few seconds, was made a swarm of one
by a check that covered the gap between two of the leader's Advertizes (two leaders
for 144 s); and a periodic radio check made members drop their leader and rejoin.
The pilot, the station link and the command log keep the node's own time.

The autopilot's STATUSTEXTs at WARNING or worse and the node's own events (the
pilot's, the position fix, an id conflict) go to every connected station as
AgentNotice, through :class:`~swarm.core.agent.notices.NoticeGate` (one line, rate-limited,
repeats counted; its counters are ``notices``).

Counters are kept in ``stats`` (a dict the runtime may share with its own counters).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, replace
from typing import Any

from swarm.core.agent.gslink import CommandLog, GsLink, GsOut, answer_command
from swarm.core.agent.notices import NoticeGate, agent_severity
from swarm.core.election.outbox import ADVERTIZE, NO_POSE, Out
from swarm.core.election.profiles import Profile, RandomVote, VotePolicy
from swarm.core.election.protocol import Core
from swarm.core.flight.pilot import Call, Mode, Pilot, PilotConfig, Role, Setpoint
from swarm.core.wire.codes import (
    FLAG_AIRBORNE,
    FLAG_ARMED,
    FLAG_CONTROL_LOST,
    FLAG_FC_OK,
    FLAG_HOLDING,
    FLAG_READY,
    FLAG_READY_KNOWN,
    mode_code,
    short_reason,
)
from swarm.core.wire.message_types import (
    AckResult,
    Advertize,
    AgentNotice,
    AgentState,
    Command,
    CommandAck,
    GSAdvertize,
    GSConnect,
    GSHeartbeat,
    Message,
    NoticeSource,
    Phase,
    Pose,
    Task,
    TaskKind,
    Telemetry,
)

SETPOINT_PERIOD = 0.1  # the pilot's step: setpoints at 10 Hz
STATE_KEEPALIVE_S = 5.0  # state publication period once leading or following
#: the node's events when its flight controller falls silent and comes back
VEHICLE_LINK_LOST = "vehicle link lost"
VEHICLE_LINK_BACK = "vehicle link back"
WAITING_FOR_POSITION = "waiting for position"
POSITION_VALID = "position valid"
#: pilot modes in which the vehicle flies itself (no setpoints)
_NO_SETPOINTS = (Mode.IDLE, Mode.TAKEOFF, Mode.LAND, Mode.RETURN)


# -- events in ---------------------------------------------------------------------
@dataclass(frozen=True)
class PoseHeard:
    """Another agent's pose, by id, or by name (resolved with the Advertize table)."""

    pose: Pose
    sender: int = 0
    name: str = ""


@dataclass(frozen=True)
class OwnPose:
    pose: Pose
    airborne: bool
    home: tuple[float, float, float] | None = None  # the autopilot's: lat, lon, metres AMSL


@dataclass(frozen=True)
class VehicleInfo:
    """What the flight controller last said, for Telemetry."""

    mode: str = ""
    armed: bool = False
    airborne: bool = False
    battery: int = -1  # percent, -1 unknown
    groundspeed: float = 0.0
    link_ok: bool = True
    controlled: bool | None = None  # under the companion's setpoints (OFFBOARD, GUIDED); None: unknown
    # what an operator's table shows beside (None: unknown; Telemetry's detail block)
    rel_alt: float | None = None  # metres above the autopilot's home
    climb: float | None = None  # m/s, up
    gps_fix: int | None = None  # GPS_FIX_TYPE
    satellites: int | None = None
    home_dist: float | None = None  # metres from the autopilot's home
    ready: bool | None = None  # the autopilot's pre-arm checks pass


@dataclass(frozen=True)
class RadioInfo:
    rssi: int
    remrssi: int


@dataclass(frozen=True)
class SetTask:
    task: Task


@dataclass(frozen=True)
class VehicleLink:
    up: bool


@dataclass(frozen=True)
class RadioAway:
    """The radio link went away (lent to the radio guard's check, unplugged)."""


@dataclass(frozen=True)
class RadioBack:
    """The radio link is back after :class:`RadioAway`."""


@dataclass(frozen=True)
class RadioRestored:
    """The radio guard found the radio off the swarm's settings (a rogue's RT commands)
    and put it back: the agent was cut off from the swarm meanwhile."""


@dataclass(frozen=True)
class PositionFix:
    """Whether the flight controller's position is valid now, and if not why."""

    valid: bool
    reason: str = ""


@dataclass(frozen=True)
class AutopilotText:
    """A STATUSTEXT of the flight controller (MAVLink severity, its text as received:
    str, or bytes from some dialects)."""

    severity: int
    text: str | bytes


@dataclass(frozen=True)
class CallDone:
    """A vehicle call returned: ``ok``, else ``error`` (for the log), ``result`` the
    refusal it means for the station (REJECTED: the autopilot refused; FAILED: it
    did not happen, e.g. no answer) and ``reason`` the autopilot's own words
    ("Arm: Mode not armable"; ``error`` when empty)."""

    call: Call
    ok: bool
    error: str = ""
    result: AckResult = AckResult.FAILED
    reason: str = ""


# -- outputs -----------------------------------------------------------------------
@dataclass(frozen=True)
class Send:
    """``msg`` to agent or station ``to`` (0: to everyone, Advertize or GSAdvertize);
    ``name`` the one learnt for ``to`` (None if not known yet)."""

    to: int
    msg: Message
    name: str | None = None


@dataclass(frozen=True)
class PublishState:
    state: AgentState


@dataclass(frozen=True)
class SetpointOut:
    setpoint: Setpoint


@dataclass(frozen=True)
class CallOut:
    call: Call


@dataclass(frozen=True)
class EventOut:
    text: str


NodeOut = Send | PublishState | SetpointOut | CallOut | EventOut
NODE_STATS = (
    "received",
    "own_echo",
    "id_conflicts",
    "commands",
    "command_replays",
    "poses_heard",
    "vehicle_link_lost",
    "vehicle_link_back",
)


class AgentNode:
    """One agent's parts composed (see the module docstring). ``has_fc``: a flight
    controller is attached (without one, commands to this agent fail and the
    protocol does not wait for a pose)."""

    def __init__(
        self,
        agent_id: int,
        name: str,
        profile: Profile,
        *,
        policy: VotePolicy | None = None,
        rng: random.Random | None = None,
        has_fc: bool = False,
        pilot: PilotConfig | None = None,
        stats: dict[str, int] | None = None,
        cap: int = 0,
        swarm_name: str = "",
    ) -> None:
        self.id = agent_id
        self.name = name
        self.profile = profile
        self.has_fc = has_fc
        self.core = Core(
            agent_id,
            name,
            profile,
            policy or RandomVote(),
            rng=rng or random.Random(),
            has_fc=has_fc,
            cap=cap,
            swarm_name=swarm_name,
        )
        self.pilot = Pilot(agent_id, pilot or PilotConfig())
        self.gs = GsLink(agent_id, name)
        self.commands = CommandLog()
        self._awaiting: dict[int, Command] = {}  # a vehicle call's ticket -> the command it answers
        self._tickets = 0
        self.stats = stats if stats is not None else {}
        for k in NODE_STATS:
            self.stats.setdefault(k, 0)
        self.names: dict[int, str] = {}  # agent id -> name, from Advertize
        self.ids: dict[str, int] = {}  # name -> agent id
        self.vehicle: VehicleInfo | None = None
        self.position_ok: bool | None = None  # None: not told yet
        self.radio = RadioInfo(0, 0)
        self.reported_conflicts: set[tuple[int, str]] = set()
        self._next_publish = 0.0
        self._next_step = 0.0
        self.notices = NoticeGate()
        # the election core's time: ours less the time the radio was away (see "Deaf")
        self._deaf_since: float | None = None
        self._deaf_total = 0.0

    # -- driving ---------------------------------------------------------------------
    def start(self, now: float) -> list[NodeOut]:
        self._next_publish = self._next_step = now
        return self._outs(self.core.start(self._core_time(now)))

    def _core_time(self, now: float) -> float:
        """The election core's clock: ``now`` less the time the radio was away, held
        still while it is away (see "Deaf" in the module docstring)."""
        return (self._deaf_since if self._deaf_since is not None else now) - self._deaf_total

    @property
    def deaf(self) -> bool:
        """The radio is away: the election core's time stands still."""
        return self._deaf_since is not None

    def next_deadline(self) -> float:
        d = min(self._next_publish, self._next_step, self.gs.next_deadline())
        if self.gs.connected:
            d = min(d, self.notices.next_deadline())
        core_due = None if self.deaf else self.core.next_deadline()
        for x in (None if core_due is None else core_due + self._deaf_total, self.commands.next_deadline()):
            if x is not None:
                d = min(d, x)
        return d

    def tick(self, now: float) -> list[NodeOut]:
        core = self.core
        out: list[NodeOut] = []
        if core.take_state_changed() or now >= self._next_publish:
            out.append(PublishState(core.state()))
            # settled (leading or following): a change is published at once anyway,
            # so the keep-alive can be slow; the air is shared with poses
            settled = core.phase in (Phase.LEADER, Phase.MEMBER)
            self._next_publish = now + (STATE_KEEPALIVE_S if settled else self.profile.state_interval)
        if not self.deaf:
            out += self._outs(core.tick(self._core_time(now)))
        out += self._gs_outs(self.gs.tick(now, self.telemetry))
        out += [self._send(station, ack) for station, ack in self.commands.due(now)]
        if now >= self._next_step:
            self._next_step = max(self._next_step + SETPOINT_PERIOD, now - SETPOINT_PERIOD)
            out += self._tell(self._pilot_step(now), now)
        stations = self.gs.connected
        if stations:
            for n in self.notices.take(now):
                note = AgentNotice(self.id, n.source, n.severity, n.text, n.repeats)
                out += [self._send(st, note) for st in stations]
        return out

    def _tell(self, outs: list[NodeOut], now: float) -> list[NodeOut]:
        """Offer the events among ``outs`` to the stations (as notices); ``outs`` unchanged."""
        for o in outs:
            if isinstance(o, EventOut):
                self.notices.offer(NoticeSource.AGENT, agent_severity(o.text), o.text, now)
        return outs

    def handle(self, ev: object, now: float) -> list[NodeOut]:
        if isinstance(ev, Message):
            return self._message(ev, now)
        core = self.core
        if isinstance(ev, PoseHeard):
            sender = ev.sender or self.ids.get(ev.name, 0)
            if sender and sender != self.id:
                self.pilot.on_pose(sender, ev.pose, now)
                core.note_pose(sender, ev.pose, self._core_time(now))
                self.stats["poses_heard"] += 1
        elif isinstance(ev, OwnPose):
            core.set_pose(ev.pose)
            self.pilot.set_own(ev.pose, ev.airborne, ev.home)
        elif isinstance(ev, VehicleInfo):
            self.vehicle = ev
            self.pilot.set_control(ev.controlled, ev.mode)
        elif isinstance(ev, RadioInfo):
            self.radio = ev
        elif isinstance(ev, SetTask):
            core.set_task(ev.task)
        elif isinstance(ev, CallDone):
            self.pilot.call_done(ev.call, ev.ok, ev.error)
            return self._call_done(ev, now)
        elif isinstance(ev, VehicleLink):
            self.stats["vehicle_link_back" if ev.up else "vehicle_link_lost"] += 1
            core.set_vehicle_link(ev.up, self._core_time(now))  # a leader that cannot fly hands over
            return [EventOut(VEHICLE_LINK_BACK if ev.up else VEHICLE_LINK_LOST)]
        elif isinstance(ev, RadioAway):
            if self._deaf_since is None:
                self._deaf_since = now
        elif isinstance(ev, RadioBack):
            if self._deaf_since is not None:
                self._deaf_total += max(0.0, now - self._deaf_since)
                self._deaf_since = None
                return self._outs(core.resume(self._core_time(now)))  # heard from at once
        elif isinstance(ev, RadioRestored):
            return self._outs(core.rejoin(self._core_time(now)))  # cut off: no swarm of one to lead
        elif isinstance(ev, PositionFix):
            return self._tell(self._position_fix(ev), now)
        elif isinstance(ev, AutopilotText):
            self.notices.offer(NoticeSource.AUTOPILOT, ev.severity, ev.text, now)
        return []

    def _position_fix(self, ev: PositionFix) -> list[NodeOut]:
        """Say "waiting for position" once and "position valid" when it comes."""
        was, self.position_ok = self.position_ok, ev.valid
        if ev.valid == was:
            return []
        if ev.valid:
            return [EventOut(POSITION_VALID)]
        if was:
            self.core.set_pose(NO_POSE)  # the last fix is not where we are now
        return [EventOut(f"{WAITING_FOR_POSITION} ({ev.reason})" if ev.reason else WAITING_FOR_POSITION)]

    # -- messages ----------------------------------------------------------------------
    def _message(self, msg: Message, now: float) -> list[NodeOut]:
        self.stats["received"] += 1
        if isinstance(msg, (GSAdvertize, GSConnect, GSHeartbeat)):
            return self._gs_outs(self.gs.handle(msg, now))
        if isinstance(msg, Command):
            return self._command(msg, now)
        core = self.core
        if isinstance(msg, Advertize):
            if msg.sender == self.id:
                if msg.name == self.name:
                    self.stats["own_echo"] += 1  # our own advertisement, delivered locally
                    return []
                return self._tell(self._id_conflict(msg), now)
            self.names[msg.sender] = msg.name
            self.ids[msg.name] = msg.sender
        hb = core.last_hb
        outs = self._outs(core.handle(msg, self._core_time(now)))
        if core.last_hb != hb and core.phase == Phase.MEMBER:
            self.pilot.on_task(core.task, now)  # every heartbeat (the heading's rate)
        return outs

    def _id_conflict(self, msg: Advertize) -> list[NodeOut]:
        self.stats["id_conflicts"] += 1
        k = (msg.sender, msg.name)
        if k in self.reported_conflicts:
            return []
        self.reported_conflicts.add(k)
        return [EventOut(f"{msg.name!r} advertises our id {msg.sender}")]

    def role(self) -> Role:
        core = self.core
        settled = core.phase in (Phase.LEADER, Phase.MEMBER)
        return Role(
            core.phase,
            core.leader if settled else 0,
            frozenset(core.members) if core.phase == Phase.LEADER else frozenset(),
            dict(core.poses),
        )

    def _command(self, cmd: Command, now: float) -> list[NodeOut]:
        """Answer a Command (once per station and sequence number) and act on it."""
        self.stats["commands"] += 1
        core = self.core
        ack, calls, repeat = answer_command(
            self.commands, cmd, self.id, self.has_fc, lambda c: self.pilot.command(c, self.role(), now), now
        )
        if repeat:  # a retry: the same answer, nothing run again
            self.stats["command_replays"] += 1
            return [self._send(cmd.sender, ack)]
        if ack.result == AckResult.ACCEPTED and cmd.target == 0 and core.phase == Phase.LEADER:
            core.set_task(self.pilot.task)  # FOLLOW or HOLD rides on the next heartbeats
        text = f"command {cmd.kind.name} seq {cmd.seq} from {cmd.sender}: {ack.result.name}" + (
            f" ({ack.reason})" if ack.reason else ""
        )
        if ack.result == AckResult.IN_PROGRESS:  # answered when the vehicle has done it
            return [EventOut(text), *(CallOut(self._ticket(c, cmd)) for c in calls)]
        return [self._send(cmd.sender, ack), EventOut(text), *(CallOut(c) for c in calls)]

    def _ticket(self, call: Call, cmd: Command) -> Call:
        self._tickets += 1
        self._awaiting[self._tickets] = cmd
        return replace(call, ticket=self._tickets)

    def _call_done(self, ev: CallDone, now: float) -> list[NodeOut]:
        """The vehicle's result answers the command that asked for the call: ACCEPTED,
        or the refusal with the autopilot's reason (never IN_PROGRESS or ACCEPTED for a
        call that failed)."""
        cmd = self._awaiting.pop(ev.call.ticket, None)
        if cmd is None:
            return []
        if ev.ok:
            result, why = AckResult.ACCEPTED, ""
        else:
            refusals = (AckResult.ACCEPTED, AckResult.IN_PROGRESS)
            result = AckResult.FAILED if ev.result in refusals else ev.result
            why = ev.reason or ev.error or f"{ev.call.kind} failed"
        ack = CommandAck(self.id, cmd.seq, result, short_reason(why))
        text = f"command {cmd.kind.name} seq {cmd.seq} from {cmd.sender}: {result.name}" + (
            f" ({ack.reason})" if ack.reason else ""
        )
        if not self.commands.finish(cmd, ack, now):
            return [EventOut(text + ": not sent, the station reused its seq")]
        return [self._send(cmd.sender, ack), EventOut(text)]

    def _pilot_step(self, now: float) -> list[NodeOut]:
        core = self.core
        sp, heading = self.pilot.step(now, self.role())
        if heading is not None and core.phase == Phase.LEADER and core.task.kind == TaskKind.FOLLOW:
            core.set_task(replace(core.task, heading=heading[0], turn_rate=heading[1]))
        out: list[NodeOut] = [EventOut(e) for e in self.pilot.take_events()]
        if sp is not None and self.pilot.mode not in _NO_SETPOINTS:
            out.append(SetpointOut(sp))
        return out

    # -- outputs -----------------------------------------------------------------------
    def _send(self, to: int, msg: Message) -> Send:
        return Send(to, msg, self.gs.station_name(to) or self.names.get(to))

    def _outs(self, outs: list[Out]) -> list[NodeOut]:
        return [
            Send(0, o.msg, None) if o.to == ADVERTIZE else Send(o.to, o.msg, self.names.get(o.to))
            for o in outs
        ]

    def _gs_outs(self, outs: list[GsOut]) -> list[NodeOut]:
        return [Send(o.to, o.msg, None if o.to == 0 else self.gs.station_name(o.to)) for o in outs]

    def telemetry(self) -> Telemetry:
        """This agent's Telemetry for connected ground stations (its connection heartbeat)."""
        core = self.core
        pose = core.pose or NO_POSE
        mode = flags = 0
        battery, groundspeed = 255, 0.0
        detail: dict[str, Any] = {}
        v = self.vehicle
        if v is not None and v.link_ok:  # the last values heard are not what it is now
            detail = {
                "rel_alt": v.rel_alt,
                "climb": v.climb,
                "gps_fix": v.gps_fix,
                "satellites": v.satellites,
                "home_dist": v.home_dist,
            }
            if v.ready is not None:
                flags |= FLAG_READY_KNOWN | (FLAG_READY if v.ready else 0)
        if v is not None:
            mode = mode_code(v.mode) if v.link_ok else 0  # not the last mode heard: unknown
            flags |= (FLAG_ARMED if v.armed else 0) | (FLAG_AIRBORNE if v.airborne else 0)
            flags |= FLAG_FC_OK if v.link_ok else 0
            if 0 <= v.battery <= 100:
                battery = v.battery
            if math.isfinite(v.groundspeed):
                groundspeed = max(0.0, min(63.75, v.groundspeed))
            flags |= FLAG_HOLDING if self.pilot.holding else 0
            flags |= FLAG_CONTROL_LOST if self.pilot.control_lost else 0
        leader = core.leader if core.phase in (Phase.LEADER, Phase.MEMBER) else 0
        return Telemetry(
            self.id,
            pose,
            mode,
            flags,
            core.phase,
            leader,
            battery,
            self.radio.rssi & 0xFF,
            self.radio.remrssi & 0xFF,
            groundspeed,
            **detail,
        )


__all__ = [
    "NODE_STATS",
    "POSITION_VALID",
    "SETPOINT_PERIOD",
    "VEHICLE_LINK_BACK",
    "VEHICLE_LINK_LOST",
    "WAITING_FOR_POSITION",
    "AgentNode",
    "AutopilotText",
    "CallDone",
    "CallOut",
    "EventOut",
    "NodeOut",
    "OwnPose",
    "PoseHeard",
    "PositionFix",
    "PublishState",
    "RadioAway",
    "RadioBack",
    "RadioInfo",
    "RadioRestored",
    "Send",
    "SetTask",
    "SetpointOut",
    "VehicleInfo",
    "VehicleLink",
]
