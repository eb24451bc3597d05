"""The agent runtime: one protocol core driven in real time over Zenoh (and a radio).

Theory of operation
-------------------
:class:`Agent` wires one :class:`~swarm.protocol.Core` (the pure state machine) to
the world, with threads and queues as the paper has it (section 2.2: one thread per
protocol or link, queues between them):

* **Zenoh**: one session per agent. With a radio the session has no endpoints and
  no scouting, so agents meet only through the radio; with ``zenoh_listen`` /
  ``zenoh_connect`` endpoints they meet over IP. A :class:`~swarm.transport.Transport`
  gives the key space: the agent listens on its inbox ``swarm/<name>`` and on
  ``swarm/advertize``, and publishes its state on ``swarm/<name>/state``.
* **Radio** (optional): :func:`radios.link.open_link` and a
  :class:`~swarm.bridge.RadioBridge` (its own tx and rx threads) carry the key space
  over the air, MAVLink 2 signed when a key file is given.
* **Protocol thread**: the only thread that touches the core. Zenoh callbacks only
  put what they receive on a :class:`queue.Queue` (so do the pose thread and
  :meth:`Agent.set_task`); the thread waits on the queue until the core's
  :meth:`~swarm.protocol.Core.next_deadline` (or the next state publication),
  feeds ``handle`` / ``tick`` with the monotonic clock and sends every
  :class:`~swarm.protocol.Out`: ``ADVERTIZE`` on ``swarm/advertize``, an agent id
  to ``swarm/<name>`` using the id -> name table learnt from Advertize (an id not
  yet heard of is counted in ``stats['unknown_destination']`` and skipped: every
  agent advertises while it looks for a swarm and leaders keep advertising, so
  names arrive before anyone needs them). The state is published whenever it
  changed and at least every ``profile.state_interval`` (every 5 s once the agent
  leads or follows: the air is shared with the pose streams).
* **Ground stations** (:mod:`swarm.gslink`, the paper's section 3): the agent
  announces itself on ``swarm/GSAdvertize``, answers a station's GSConnect, sends
  it Telemetry every ``hb_interval`` (the connection's heartbeat) and drops it when
  its GSHeartbeats stop. This runs on the protocol thread beside the core.
* **Pose thread** (only with a flight controller): at ``pose_hz`` reads the
  driver's :class:`~firmware_bridge.driver.VehicleState` snapshot, hands the pose
  to the core (through the queue), publishes it on ``swarm/<name>/pose`` and, with
  a radio, gives the bridge a HEARTBEAT and a GLOBAL_POSITION_INT for standard
  ground stations. The driver does not expose raw pymavlink messages, so those two
  are rebuilt from the snapshot (same fields; the vehicle type, not in the
  snapshot, is sent as a quadrotor); the bridge rate-limits them to 1 Hz. While the
  driver reports the vehicle link lost the thread publishes nothing (a stale
  position would look alive to the swarm).
* **Vehicle link**: the driver's link-lost / link-restored callbacks come through
  the queue: an event (``vehicle link lost`` / ``vehicle link back``), the core told
  (:meth:`~swarm.protocol.Core.set_vehicle_link`: a leader that cannot fly hands
  over), and Telemetry without FLAG_FC_OK and with the mode unknown.
* **Commands** from a station are answered on the protocol thread through
  :func:`swarm.gslink.answer_command` (a repeat is answered from the log and never
  run twice; new answers are sent again 0.5 and 1.5 s later); vehicle calls run
  on their own thread.

Profiles: ``paper`` (the default) or ``fast``, whose windows follow the radio
network's TDM round (``round_s``). The round is not read from the radio: pass it,
or it defaults to a SiK pair at 64 kbit/s (0.2368 s); a multipoint network of N
radios has ``radios.sik.timing.tdm_timing(air_kbps).round_s(N)``.

Vote policies: ``random`` (the paper), ``battery`` (the flight controller's
remaining battery percent; 255 when unknown or without a flight controller), and
``link`` (the local radio's RSSI from RADIO_STATUS; 0 without a radio).

:meth:`Agent.stop` stops every thread and closes the bridge, the link, the vehicle
and the session; it is safe twice, and the agent is a context manager.
"""

from __future__ import annotations

import logging
import math
import queue
import random
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from swarm.gslink import (
    FLAG_AIRBORNE,
    FLAG_ARMED,
    FLAG_FC_OK,
    FLAG_HOLDING,
    CommandLog,
    GsLink,
    GsOut,
    answer_command,
    mode_code,
)
from swarm.messages import (
    AckResult,
    Advertize,
    AgentState,
    Command,
    CommandAck,
    GSAdvertize,
    GSConnect,
    GSHeartbeat,
    Message,
    Phase,
    Pose,
    PoseReport,
    Task,
    TaskKind,
    Telemetry,
    check_id,
    check_name,
)
from swarm.pilot import Call, Mode, Pilot, PilotConfig, Role
from swarm.protocol import (
    ADVERTIZE,
    NO_POSE,
    BatteryVote,
    Core,
    LinkQualityVote,
    Out,
    Profile,
    RandomVote,
    VotePolicy,
    profile_by_name,
)

log = logging.getLogger(__name__)

VOTES = ("random", "battery", "link")
PROFILES = ("paper", "fast")
DEFAULT_AIR_KBPS = 64


def default_round_s(slots: int = 2, air_kbps: int = DEFAULT_AIR_KBPS) -> float:
    """The SiK TDM round for ``slots`` radios at ``air_kbps`` (2: a standard pair)."""
    from radios.sik.timing import tdm_timing

    return tdm_timing(air_kbps).round_s(slots)


@dataclass(frozen=True)
class _Pose:
    pose: Pose


@dataclass(frozen=True)
class _Task:
    task: Task


@dataclass(frozen=True)
class _PoseIn:
    name: str
    pose: Pose


@dataclass(frozen=True)
class _VehicleLink:
    up: bool  # the driver's link-lost / link-restored callbacks


@dataclass(frozen=True)
class _CallDone:
    call: Call
    ok: bool
    error: str


_STOP = object()
#: the agent's events (``on_event``) when its flight controller falls silent and comes back
VEHICLE_LINK_LOST = "vehicle link lost"
VEHICLE_LINK_BACK = "vehicle link back"
SETPOINT_PERIOD = 0.1  # the pilot's step: setpoints at 10 Hz
STATE_KEEPALIVE_S = 5.0  # state publication period once leading or following


class Agent:
    """One swarm agent: a protocol core, its threads, Zenoh, optionally a radio and a
    flight controller. See the module docstring.

    Construction only checks the arguments (ValueError); :meth:`start` (or ``with``)
    opens everything and may raise the errors of the parts it opens:
    :class:`radios.errors.ConfigError` (key file), :class:`radios.errors.LinkOpenError`
    (radio), :class:`swarm.errors.TransportError` (Zenoh endpoints),
    :class:`firmware_bridge.errors.BridgeError` (flight controller).
    """

    def __init__(self, name: str, agent_id: int, *, radio: str | None = None,
                 zenoh_listen: Sequence[str] = (), zenoh_connect: Sequence[str] = (),
                 fc: str | None = None, profile: str = "paper", round_s: float | None = None,
                 key_file: str | None = None, vote: str = "random", pose_hz: float = 4.0,
                 fc_timeout: float = 10.0, seed: int | None = None,
                 pilot: PilotConfig | None = None,
                 on_state: Callable[[AgentState], None] | None = None,
                 on_event: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        check_name(name)
        check_id(agent_id)
        if vote not in VOTES:
            raise ValueError(f"unknown vote policy {vote!r}: {', '.join(VOTES)}")
        if profile not in PROFILES:
            raise ValueError(f"unknown profile {profile!r}: {', '.join(PROFILES)}")
        if radio is not None and (zenoh_listen or zenoh_connect):
            raise ValueError("an agent meets others either through a radio or over Zenoh endpoints")
        if radio is None and not (zenoh_listen or zenoh_connect):
            raise ValueError("give a radio or at least one Zenoh endpoint (listen or connect)")
        if round_s is not None and not (math.isfinite(round_s) and round_s > 0):
            raise ValueError(f"round_s {round_s!r} must be a positive number of seconds")
        if not (math.isfinite(pose_hz) and 0 < pose_hz <= 50):
            raise ValueError(f"pose_hz {pose_hz!r} must be in (0, 50]")
        self.name = name
        self.id = agent_id
        self.radio_url = radio
        self.zenoh_listen = list(zenoh_listen)
        self.zenoh_connect = list(zenoh_connect)
        self.fc_url = fc
        self.round_s = round_s if round_s is not None else default_round_s()
        self.profile: Profile = profile_by_name(profile, self.round_s)
        self.key_file = key_file
        self.vote = vote
        self.pose_hz = pose_hz
        self.fc_timeout = fc_timeout
        self.on_state = on_state
        self.on_event = on_event
        self.clock = clock
        self.pilot = Pilot(agent_id, pilot or PilotConfig())
        self.commands = CommandLog()
        self._calls: queue.Queue[object] = queue.Queue()
        self._rng = random.Random(seed)
        self.stats: dict[str, int] = {
            "received": 0, "sent": 0, "advertized": 0, "unknown_destination": 0,
            "send_errors": 0, "state_published": 0, "own_echo": 0, "id_conflicts": 0,
            "errors": 0, "poses": 0, "vehicle_forwarded": 0, "gs_sent": 0,
            "commands": 0, "command_replays": 0, "setpoints": 0, "setpoint_errors": 0, "poses_heard": 0,
            "vehicle_link_lost": 0, "vehicle_link_back": 0,
        }
        self.names: dict[int, str] = {}  # agent id -> name, from Advertize
        self._ids: dict[str, int] = {}  # name -> agent id
        self.core: Core | None = None
        self.gs = GsLink(agent_id, name)
        self.session: Any = None
        self.transport: Any = None
        self.link: Any = None
        self.bridge: Any = None
        self.vehicle: Any = None
        self.started_at = 0.0
        self._q: queue.Queue[object] = queue.Queue()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._state: AgentState | None = None
        self._started = False
        self._stopped = False
        self._conflicts_logged: set[tuple[int, str]] = set()

    # -- life cycle -------------------------------------------------------------
    def start(self) -> Agent:
        """Open the session, radio, bridge and flight controller and start the threads."""
        with self._lock:
            if self._started:
                return self
            self._started = True
        try:
            self._open()
        except BaseException:
            self.stop()
            raise
        return self

    def _open(self) -> None:
        from swarm.bridge import open_node
        from swarm.transport import Transport

        self.session, self.link, self.bridge = open_node(
            self.name, self.id, radio=self.radio_url, listen=self.zenoh_listen,
            connect=self.zenoh_connect, key_file=self.key_file)
        if self.fc_url is not None:
            from firmware_bridge.driver import connect

            self.vehicle = connect(self.fc_url, timeout=self.fc_timeout,
                                   on_link_lost=lambda: self._q.put(_VehicleLink(False)),
                                   on_link_restored=lambda: self._q.put(_VehicleLink(True)))
        self.core = Core(self.id, self.name, self.profile, self._policy(), rng=self._rng,
                         has_fc=self.vehicle is not None)
        self.transport = Transport(self.name, self.session)
        self.transport.on_inbox(self._q.put)
        self.transport.on_advertize(self._q.put)
        self.transport.on_gs_advertize(self._q.put)
        self.transport.on_pose("*", lambda name, rep: self._q.put(_PoseIn(name, rep.pose))
                               if name != self.name else None)
        self.started_at = self.clock()
        self._spawn(self._protocol_loop, "protocol")
        if self.vehicle is not None:
            self._spawn(self._pose_loop, "pose")
            self._spawn(self._vehicle_loop, "vehicle")

    def _spawn(self, target: Callable[[], None], what: str) -> None:
        t = threading.Thread(target=target, name=f"agent-{self.name}-{what}", daemon=True)
        self._threads.append(t)
        t.start()

    def _policy(self) -> VotePolicy:
        if self.vote == "battery":
            return BatteryVote(self._battery)
        if self.vote == "link":
            return LinkQualityVote(lambda: self.bridge.radio.rssi if self.bridge is not None else 0)
        return RandomVote()

    def _battery(self) -> int:
        # an unknown battery must not win a battery vote
        if self.vehicle is None:
            return 0
        pct = int(self.vehicle.state.battery_remaining)
        return pct if 0 <= pct <= 100 else 0

    def stop(self) -> None:
        """Stop every thread, then close bridge, link, vehicle and session. Safe twice."""
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
        self._stop.set()
        self._q.put(_STOP)
        self._calls.put(_STOP)
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(2.0)
        for close in (self.transport and self.transport.close, self.bridge and self.bridge.close,
                      self.link and self.link.close, self.vehicle and self.vehicle.close,
                      self.session and self.session.close):
            if close:
                try:
                    close()
                except Exception:  # every part gets its chance to close
                    log.debug("agent %s: error while closing", self.name, exc_info=True)

    close = stop

    def __enter__(self) -> Agent:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- public helpers -----------------------------------------------------------
    @property
    def running(self) -> bool:
        radio_ok = self.bridge is None or not self.bridge.link_lost
        return (self._started and not self._stopped and radio_ok
                and all(t.is_alive() for t in self._threads))

    def state(self) -> AgentState | None:
        """The last state the protocol thread published (None before the first)."""
        return self._state

    def set_task(self, task: Task) -> None:
        """The task a leader sends on its Heartbeats (applied on the protocol thread)."""
        self._q.put(_Task(task))

    def describe(self) -> str:
        """Where the agent meets others, for the ready line."""
        if self.radio_url is not None:
            return f"radio={self.radio_url}"
        parts = []
        if self.zenoh_listen:
            parts.append("listen=" + ",".join(self.zenoh_listen))
        if self.zenoh_connect:
            parts.append("connect=" + ",".join(self.zenoh_connect))
        return "zenoh " + " ".join(parts)

    # -- protocol thread ------------------------------------------------------------
    def _protocol_loop(self) -> None:
        core = self.core
        assert core is not None
        now = self.clock()
        self._send(core.start(now))
        next_publish = now
        next_step = now
        while not self._stop.is_set():
            now = self.clock()
            if core.take_state_changed() or now >= next_publish:
                self._publish_state(core.state())
                # settled (leading or following): a change is published at once anyway,
                # so the keep-alive can be slow; the air is shared with poses
                settled = core.phase in (Phase.LEADER, Phase.MEMBER)
                next_publish = now + (STATE_KEEPALIVE_S if settled else self.profile.state_interval)
            deadline = core.next_deadline()
            wake = min(next_publish, self.gs.next_deadline(), next_step)
            again = self.commands.next_deadline()
            if again is not None:
                wake = min(wake, again)
            if deadline is not None:
                wake = min(wake, deadline)
            try:
                item = self._q.get(timeout=max(0.0, wake - now))
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            try:
                outs: list[Out] = []
                while item is not None:
                    if item is _STOP:
                        self._stop.set()
                        break
                    outs += self._feed(core, item, self.clock())
                    try:
                        item = self._q.get_nowait()
                    except queue.Empty:
                        item = None
                outs += core.tick(self.clock())
                self._send(outs)
                self._send_gs(self.gs.tick(self.clock(), self._telemetry))
                for station, ack in self.commands.due(self.clock()):
                    self._reply(station, ack)  # answers are sent three times
                now = self.clock()
                if now >= next_step:
                    next_step = max(next_step + SETPOINT_PERIOD, now - SETPOINT_PERIOD)
                    self._pilot_step(core, now)
            except Exception:  # a bug must not silence the agent: log, count, go on
                self.stats["errors"] += 1
                log.exception("agent %s: protocol error", self.name)

    def _feed(self, core: Core, item: object, now: float) -> list[Out]:
        if isinstance(item, _Pose):
            core.set_pose(item.pose)
            v = self.vehicle
            self.pilot.set_own(item.pose, bool(v is not None and v.state.in_air))
            return []
        if isinstance(item, _PoseIn):
            sender = self._ids.get(item.name)
            if sender is not None:
                self.pilot.on_pose(sender, item.pose, now)
                core.note_pose(sender, item.pose, now)
                self.stats["poses_heard"] += 1
            return []
        if isinstance(item, _CallDone):
            self.pilot.call_done(item.call, item.ok, item.error)
            return []
        if isinstance(item, _Task):
            core.set_task(item.task)
            return []
        if isinstance(item, _VehicleLink):
            self.stats["vehicle_link_lost" if not item.up else "vehicle_link_back"] += 1
            self._event(VEHICLE_LINK_BACK if item.up else VEHICLE_LINK_LOST)
            core.set_vehicle_link(item.up, now)  # a leader that cannot fly hands over
            return []
        if not isinstance(item, Message):
            return []
        self.stats["received"] += 1
        if isinstance(item, (GSAdvertize, GSConnect, GSHeartbeat)):
            self._send_gs(self.gs.handle(item, now))
            return []
        if isinstance(item, Command):
            self._command(core, item, now)
            return []
        if isinstance(item, Advertize):
            if item.sender == self.id:
                if item.name == self.name:
                    self.stats["own_echo"] += 1  # our own advertisement, delivered locally
                else:
                    self._id_conflict(item)
                return []
            self.names[item.sender] = item.name
            self._ids[item.name] = item.sender
        hb = core.last_hb
        outs = core.handle(item, now)
        if core.last_hb != hb and core.phase == Phase.MEMBER:
            self.pilot.on_task(core.task, now)  # every heartbeat (the heading's rate)
        return outs

    def _id_conflict(self, msg: Advertize) -> None:
        self.stats["id_conflicts"] += 1
        k = (msg.sender, msg.name)
        if k not in self._conflicts_logged:
            self._conflicts_logged.add(k)
            log.warning("agent %s: %r advertises our id %d", self.name, msg.name, msg.sender)

    def _send(self, outs: list[Out]) -> None:
        tr = self.transport
        for o in outs:
            try:
                if o.to == ADVERTIZE:
                    if isinstance(o.msg, Advertize):
                        tr.advertise(o.msg)
                        self.stats["advertized"] += 1
                    continue
                name = self.names.get(o.to)
                if name is None:
                    self.stats["unknown_destination"] += 1
                    continue
                tr.send(name, o.msg)
                self.stats["sent"] += 1
            except Exception:  # the session closing under us, or a bad peer name
                self.stats["send_errors"] += 1
                log.debug("agent %s: send failed", self.name, exc_info=True)

    # -- commands and the pilot ---------------------------------------------------------
    def _role(self, core: Core) -> Role:
        return Role(core.phase, core.leader if core.phase in (Phase.LEADER, Phase.MEMBER) else 0,
                    frozenset(core.members) if core.phase == Phase.LEADER else frozenset(),
                    dict(core.poses))

    def _command(self, core: Core, cmd: Command, now: float) -> None:
        """Answer a Command (once per station and sequence number) and act on it."""
        self.stats["commands"] += 1
        ack, calls, repeat = answer_command(
            self.commands, cmd, self.id, self.vehicle is not None,
            lambda c: self.pilot.command(c, self._role(core), now), now)
        if repeat:  # a retry: the same answer, nothing run again
            self.stats["command_replays"] += 1
            self._reply(cmd.sender, ack)
            return
        result, why = ack.result, ack.reason
        if result == AckResult.ACCEPTED and cmd.target == 0 and core.phase == Phase.LEADER:
            core.set_task(self.pilot.task)  # FOLLOW or HOLD rides on the next heartbeats
        self._reply(cmd.sender, ack)
        self._event(f"command {cmd.kind.name} seq {cmd.seq} from {cmd.sender}: {result.name}"
                    + (f" ({why})" if why else ""))
        for c in calls:
            self._calls.put(c)

    def _reply(self, to: int, ack: CommandAck) -> None:
        name = self.gs.station_name(to) or self.names.get(to)
        if name is None:
            self.stats["unknown_destination"] += 1
            return
        try:
            self.transport.send(name, ack)
            self.stats["sent"] += 1
        except Exception:
            self.stats["send_errors"] += 1

    def _event(self, text: str) -> None:
        log.info("agent %s: %s", self.name, text)
        if self.on_event is not None:
            try:
                self.on_event(text)
            except Exception:
                log.exception("agent %s: on_event callback failed", self.name)

    def _pilot_step(self, core: Core, now: float) -> None:
        sp, heading = self.pilot.step(now, self._role(core))
        if heading is not None and core.phase == Phase.LEADER and core.task.kind == TaskKind.FOLLOW:
            core.set_task(replace(core.task, heading=heading[0], turn_rate=heading[1]))
        for ev in self.pilot.take_events():
            self._event(ev)
        v = self.vehicle
        if sp is None or v is None or self.pilot.mode in (Mode.IDLE, Mode.TAKEOFF, Mode.LAND, Mode.RETURN):
            return
        s = v.state
        if s.home is not None:
            home_amsl = s.home[2]
        elif s.alt_amsl is not None and s.rel_alt is not None:
            home_amsl = s.alt_amsl - s.rel_alt
        else:
            return
        try:
            v.set_target_global(sp.lat, sp.lon, sp.alt - home_amsl, math.radians(sp.yaw_deg),
                                velocity=(sp.vn, sp.ve, 0.0))
            self.stats["setpoints"] += 1
        except Exception as exc:  # a bad setpoint is refused by the driver: count, hold on
            self.stats["setpoint_errors"] += 1
            log.debug("agent %s: setpoint refused: %s", self.name, exc)

    def _vehicle_loop(self) -> None:
        """Runs the pilot's one-shot calls (they block: take-off waits for altitude)."""
        while not self._stop.is_set():
            item = self._calls.get()
            if item is _STOP or not isinstance(item, Call):
                break
            try:
                self._do_call(item)
                self._q.put(_CallDone(item, True, ""))
            except Exception as exc:
                self._q.put(_CallDone(item, False, str(exc)))

    def _do_call(self, c: Call) -> None:
        v = self.vehicle
        if c.kind == "arm":
            v.arm()
        elif c.kind == "disarm":
            v.disarm()
        elif c.kind == "takeoff":
            v.takeoff(c.alt, wait=True, timeout=60.0)
            v.start_offboard()  # hold here under setpoint control
        elif c.kind == "land":
            v.land()
        elif c.kind == "return":
            v.return_to_launch()
        else:
            raise ValueError(f"unknown vehicle call {c.kind!r}")

    def _send_gs(self, outs: list[GsOut]) -> None:
        tr = self.transport
        for o in outs:
            try:
                if o.to == 0:
                    if isinstance(o.msg, GSAdvertize):
                        tr.gs_advertise(o.msg)
                    continue
                name = self.gs.station_name(o.to)
                if name is None:
                    self.stats["unknown_destination"] += 1
                    continue
                tr.send(name, o.msg)
                self.stats["gs_sent"] += 1
            except Exception:
                self.stats["send_errors"] += 1
                log.debug("agent %s: send to station failed", self.name, exc_info=True)

    def _telemetry(self) -> Telemetry:
        """This agent's Telemetry for connected ground stations (its connection heartbeat)."""
        core = self.core
        assert core is not None
        pose = core.pose or NO_POSE
        mode = flags = 0
        battery, groundspeed = 255, 0.0
        v = self.vehicle
        if v is not None:
            s = v.state
            link_ok = bool(getattr(v, "link_ok", True))
            mode = mode_code(s.mode) if link_ok else 0  # not the last mode heard: unknown
            flags |= (FLAG_ARMED if s.armed else 0) | (FLAG_AIRBORNE if s.in_air else 0)
            flags |= FLAG_FC_OK if link_ok else 0
            flags |= FLAG_HOLDING if self.pilot.holding else 0
            if 0 <= s.battery_remaining <= 100:
                battery = s.battery_remaining
            if s.velocity is not None and all(map(math.isfinite, s.velocity[:2])):
                groundspeed = min(63.75, math.hypot(s.velocity[0], s.velocity[1]))
        rssi = remrssi = 0
        if self.bridge is not None:
            rssi, remrssi = self.bridge.radio.rssi & 0xFF, self.bridge.radio.remrssi & 0xFF
        leader = core.leader if core.phase in (Phase.LEADER, Phase.MEMBER) else 0
        return Telemetry(self.id, pose, mode, flags, core.phase, leader, battery, rssi, remrssi,
                         groundspeed)

    def _publish_state(self, st: AgentState) -> None:
        try:
            self.transport.publish_state(st)
            self.stats["state_published"] += 1
        except Exception:
            self.stats["send_errors"] += 1
        if st != self._state:
            self._state = st
            if self.on_state is not None:
                try:
                    self.on_state(st)
                except Exception:
                    log.exception("agent %s: on_state callback failed", self.name)

    # -- pose thread -------------------------------------------------------------------
    def _pose_loop(self) -> None:
        period = 1.0 / self.pose_hz
        while not self._stop.wait(period):
            try:
                self._pose_once()
            except Exception:
                self.stats["errors"] += 1
                log.exception("agent %s: pose error", self.name)

    def _pose_once(self) -> None:
        v = self.vehicle
        if not getattr(v, "link_ok", True):
            return  # no fresh position: a stale one would look alive to the swarm
        s = v.state
        if self.bridge is not None and getattr(v, "link_ok", True):
            for msg in vehicle_messages(s):
                self.bridge.forward_vehicle(msg)
                self.stats["vehicle_forwarded"] += 1
        # the pose's sample time is when the position arrived, not when we read it
        t = s.position_time if s.position_time and self.clock is time.monotonic else self.clock()
        pose = pose_from_state(s, t)
        if pose is None:
            return
        self._q.put(_Pose(pose))
        self.transport.publish_pose(PoseReport(pose))
        self.stats["poses"] += 1


def pose_from_state(s: Any, t: float) -> Pose | None:
    """The protocol's Pose from a driver VehicleState (None before a position fix)."""
    if s.lat is None or s.lon is None:
        return None
    vn, ve = (s.velocity[0], s.velocity[1]) if s.velocity is not None else (0.0, 0.0)
    vals = [s.lat, s.lon, s.alt_amsl if s.alt_amsl is not None else 0.0,
            math.degrees(s.yaw) % 360.0, vn, ve]
    if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in vals):
        return None
    return Pose(vals[0], vals[1], vals[2], vals[3], vals[4], vals[5], t)


_AUTOPILOT_IDS = {"px4": 12, "ardupilot": 3}
MAV_TYPE_QUADROTOR = 2


def _clamp(x: float, lo: int, hi: int) -> int:
    return max(lo, min(hi, round(x)))


def vehicle_messages(s: Any) -> list[Any]:
    """HEARTBEAT and (with a fix) GLOBAL_POSITION_INT rebuilt from a VehicleState, for
    :meth:`swarm.bridge.RadioBridge.forward_vehicle` (the driver keeps no raw messages)."""
    from radios.mavlink import dialect

    out: list[Any] = [dialect.MAVLink_heartbeat_message(
        MAV_TYPE_QUADROTOR, _AUTOPILOT_IDS.get(s.autopilot, 0), s.base_mode & 0xFF,
        s.custom_mode & 0xFFFFFFFF, s.system_status & 0xFF, 3)]
    if s.lat is not None and s.lon is not None and math.isfinite(s.lat) and math.isfinite(s.lon):
        vel = s.velocity if s.velocity is not None and all(map(math.isfinite, s.velocity)) else (0, 0, 0)
        alt = s.alt_amsl if s.alt_amsl is not None and math.isfinite(s.alt_amsl) else 0.0
        rel = s.rel_alt if s.rel_alt is not None and math.isfinite(s.rel_alt) else 0.0
        hdg = _clamp(math.degrees(s.yaw) % 360.0 * 100, 0, 35999) if math.isfinite(s.yaw) else 65535
        out.append(dialect.MAVLink_global_position_int_message(
            s.time_boot_ms & 0xFFFFFFFF, _clamp(s.lat * 1e7, -900_000_000, 900_000_000),
            _clamp(s.lon * 1e7, -1_800_000_000, 1_800_000_000), _clamp(alt * 1000, -2**31, 2**31 - 1),
            _clamp(rel * 1000, -2**31, 2**31 - 1), _clamp(vel[0] * 100, -32768, 32767),
            _clamp(vel[1] * 100, -32768, 32767), _clamp(vel[2] * 100, -32768, 32767), hdg))
    return out


def state_dict(name: str, st: AgentState) -> dict[str, Any]:
    """An AgentState as the JSON object ``swarm agent --json`` prints."""
    return {"name": name, "id": st.sender, "phase": st.phase.name, "leader": st.leader,
            "pool": sorted(st.pool), "locked": st.locked, "members": sorted(st.members),
            "candidate": st.candidate, "weight": st.weight, "epoch": st.epoch}


__all__ = ["PROFILES", "VEHICLE_LINK_BACK", "VEHICLE_LINK_LOST", "VOTES", "Agent", "default_round_s",
           "pose_from_state", "state_dict", "vehicle_messages"]
