"""The agent runtime: one agent node driven in real time over Zenoh (and a radio).

Theory of operation
-------------------
:class:`Agent` wires one :class:`~swarm.core.agent.node.AgentNode` (the pure agent: protocol
core, pilot, station link, command log) to the world, with threads and queues as
the paper has it (section 2.2: one thread per protocol or link, queues between them):

* **Zenoh**: one session per agent. With a radio the session has no endpoints and
  no scouting, so agents meet only through the radio; with Zenoh endpoints (listen
  and/or connect) they meet over IP. Which of the two is the agent's
  :class:`~swarm.runtime.options.NodeOptions`; how it behaves (profile, vote, pose
  rate, pilot) its :class:`~swarm.runtime.options.AgentConfig`. A
  :class:`~swarm.runtime.keyspace.transport.Transport` gives the key space: the agent
  listens on its inbox ``swarm/<name>`` and on ``swarm/advertize``, and publishes its
  state on ``swarm/<name>/state``.
* **Radio** (optional): :func:`radios.link.open_link` (or a link handed in already
  open, which the agent bridges but leaves to its opener to close) and a
  :class:`~swarm.runtime.bridge.radio_bridge.RadioBridge` (its own tx and rx threads) carry the key space
  over the air, MAVLink 2 signed when a key file is given.
* **Protocol thread** (:class:`~swarm.runtime.loop.EventLoop`): the only thread that
  touches the node. Zenoh callbacks only put what they receive on its queue (so do
  the pose and vehicle threads and :meth:`Agent.set_task`); it feeds the node with
  the monotonic clock at its deadlines and carries out what the node returns:
  ``Send`` to everyone (Advertize on ``swarm/advertize``, GSAdvertize on
  ``swarm/GSAdvertize``) or to ``swarm/<name>`` with the name the node learnt (an id
  not yet heard of is counted in ``stats['unknown_destination']`` and skipped: every
  agent advertises while it looks for a swarm and leaders keep advertising, so
  names arrive before anyone needs them); ``PublishState`` on ``swarm/<name>/state``;
  setpoints to the flight controller; vehicle calls to the vehicle thread; events
  to the log and ``on_event``. What the node decides (ground-station connections,
  commands answered once, the pilot) is in :mod:`swarm.core.agent.node`.
* **Pose thread** (only with a flight controller): at ``pose_hz`` reads the
  driver's :class:`~firmware_bridge.driver.VehicleState` snapshot, hands the node the
  pose and what Telemetry reports (through the queue), publishes it on ``swarm/<name>/pose`` and, with
  a radio, gives the bridge a HEARTBEAT and a GLOBAL_POSITION_INT for standard
  ground stations, rebuilt from the snapshot by :mod:`swarm.runtime.agent.vehicle` (the
  driver keeps no raw messages); the bridge rate-limits them to 1 Hz. While the
  driver reports the vehicle link lost the thread publishes nothing (a stale
  position would look alive to the swarm). Until the driver finds the position
  valid (``position_valid``: a real autopilot sends 0, 0 for seconds after boot)
  no pose and no GLOBAL_POSITION_INT leaves the agent (each withheld round is
  counted in ``stats['poses_withheld']``) and the node is told once
  (:class:`~swarm.core.agent.node.PositionFix`): it says "waiting for position" and then
  "position valid".
* **Autopilot texts**: each STATUSTEXT goes from the driver's receiver thread to the node,
  which forwards the warnings to the stations, rate-limited (:mod:`swarm.core.agent.notices`).
* **Vehicle link**: the driver's link-lost / link-restored callbacks come through
  the queue to the node (an event, a leader that cannot fly hands over, Telemetry
  without FLAG_FC_OK and with the mode unknown).
* **Vehicle thread**: runs the pilot's blocking calls (arm, take-off, land...) and
  queues each result back (:func:`call_result`: the driver's error as the refusal the
  station is told, REJECTED with the autopilot's own text for a refusal, FAILED
  otherwise); the node answers the command with it; a take-off waits at most
  :data:`TAKEOFF_READY_S` for the vehicle to become armable, then fails with the
  autopilot's reasons.
* **Flight log** (optional, a :class:`radios.rotating.FlightLog` handed in): the radio
  link is wrapped for capture (:class:`radios.capture.CaptureLink`: every frame the
  bridge writes and reads, raw, so signatures and RADIO_STATUS are in it) and the
  flight controller's key messages (:data:`FC_LOG_MESSAGES`) are queued from the
  driver's receiver thread, each source to its own files. Queuing never waits for
  the disk; the log's writer thread does the writing. :meth:`Agent.stop` closes it
  last, after the radio and the vehicle, so their last frames are in it.

:meth:`Agent.loop_beats` names every loop that must keep going round (the protocol
loop, the bridge's two threads, the flight-controller session's receiver and
housekeeper, the pose thread) with its last round: the service watchdog's input
(:mod:`swarm.runtime.notify`). The vehicle thread is not among them: a take-off
legitimately blocks it for up to a minute.

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
from collections.abc import Callable
from typing import Any

from swarm.core.agent.node import (
    AgentNode,
    AutopilotText,
    CallDone,
    CallOut,
    EventOut,
    NodeOut,
    OwnPose,
    PoseHeard,
    PositionFix,
    PublishState,
    RadioAway,
    RadioBack,
    RadioInfo,
    RadioRestored,
    Send,
    SetpointOut,
    SetTask,
    VehicleLink,
)
from swarm.core.election.profiles import (
    BatteryVote,
    LinkQualityVote,
    Profile,
    RandomVote,
    VotePolicy,
    profile_by_name,
)
from swarm.core.flight.pilot import Call, Setpoint
from swarm.core.wire.message_types import (
    AckResult,
    Advertize,
    AgentState,
    GSAdvertize,
    PoseReport,
    Task,
    check_id,
    check_name,
)
from swarm.runtime.agent.vehicle import pose_from_state, vehicle_info, vehicle_messages
from swarm.runtime.loop import EventLoop
from swarm.runtime.node_io import NodeIO, StartOnce, open_node_io
from swarm.runtime.options import AgentConfig, NodeOptions

log = logging.getLogger(__name__)

DEFAULT_AIR_KBPS = 64
#: how long a take-off order waits for the vehicle to become armable before it is refused
#: (with the autopilot's reasons): an order must not start the motors long after it was given
TAKEOFF_READY_S = 5.0

#: the flight controller's messages a flight log keeps (by message id): HEARTBEAT,
#: SYS_STATUS, GPS_RAW_INT, GLOBAL_POSITION_INT, COMMAND_ACK, BATTERY_STATUS,
#: HOME_POSITION, EXTENDED_SYS_STATE, STATUSTEXT
FC_LOG_MESSAGES = frozenset({0, 1, 24, 33, 77, 147, 242, 245, 253})


def call_result(exc: BaseException) -> tuple[AckResult, str]:
    """What a vehicle call's error means for the station: (result, reason).

    The autopilot refused (:class:`~firmware_bridge.errors.CommandRejected` with a
    refusal code): REJECTED, with its STATUSTEXT ("Arm: Mode not armable") or, when it
    gave none, the driver's line naming the command and code. Accepted but the vehicle
    never showed the state (armed, the mode), no answer at all, or the altitude not
    reached: FAILED, with the driver's line. Anything else: FAILED, its text."""
    from firmware_bridge.commands import MAV_RESULT_ACCEPTED
    from firmware_bridge.errors import CommandRejected

    text = str(exc) or type(exc).__name__
    if isinstance(exc, CommandRejected) and exc.result != MAV_RESULT_ACCEPTED:
        return AckResult.REJECTED, exc.text or text
    if isinstance(exc, CommandRejected) and exc.text:
        return AckResult.FAILED, f"{text.split(' (')[0]}: {exc.text}"
    return AckResult.FAILED, text


def default_round_s(slots: int = 2, air_kbps: int = DEFAULT_AIR_KBPS) -> float:
    """The SiK TDM round for ``slots`` radios at ``air_kbps`` (2: a standard pair)."""
    from radios.sik.timing import tdm_timing

    return tdm_timing(air_kbps).round_s(slots)


_STOP = object()

#: the counters in :attr:`Agent.stats` (the node counts most of them)
STATS = (
    "received",
    "sent",
    "advertized",
    "unknown_destination",
    "send_errors",
    "state_published",
    "own_echo",
    "id_conflicts",
    "errors",
    "poses",
    "poses_withheld",
    "vehicle_forwarded",
    "gs_sent",
    "commands",
    "command_replays",
    "setpoints",
    "setpoint_errors",
    "poses_heard",
    "vehicle_link_lost",
    "vehicle_link_back",
)


class Agent(StartOnce):
    """One swarm agent: a protocol core, its threads, Zenoh, optionally a radio and a
    flight controller. See the module docstring.

    ``node``: where it meets the others (a radio URL, an open link, or Zenoh
    endpoints); ``fc``: the flight controller's URL (optional); ``config``: how it
    behaves; ``on_state`` / ``on_event``: hooks called on the protocol thread with
    each new state and each event's text.

    Construction only checks the arguments (ValueError); :meth:`start` (or ``with``)
    opens everything and may raise the errors of the parts it opens:
    :class:`radios.errors.ConfigError` (key file), :class:`radios.errors.LinkOpenError`
    (radio), :class:`swarm.errors.TransportError` (Zenoh endpoints),
    :class:`firmware_bridge.errors.BridgeError` (flight controller).

    ``flight_log``: an open :class:`radios.rotating.FlightLog` the agent writes its
    radio traffic and its flight controller's key messages to; the agent closes it.
    """

    def __init__(
        self,
        name: str,
        agent_id: int,
        node: NodeOptions,
        *,
        fc: str | None = None,
        config: AgentConfig | None = None,
        on_state: Callable[[AgentState], None] | None = None,
        on_event: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        flight_log: Any = None,
    ) -> None:
        check_name(name)
        check_id(agent_id)
        self.name = name
        self.id = agent_id
        self.options = node
        self.config = cfg = config if config is not None else AgentConfig()
        self.fc_url = fc
        self.round_s = cfg.round_s if cfg.round_s is not None else default_round_s()
        self.profile: Profile = profile_by_name(cfg.profile, self.round_s)
        self.on_state = on_state
        self.on_event = on_event
        self.clock = clock
        self._calls: queue.Queue[object] = queue.Queue()
        self.stats: dict[str, int] = dict.fromkeys(STATS, 0)
        self.node: AgentNode | None = None
        self.session: Any = None
        self.transport: Any = None
        self.link: Any = None
        self.bridge: Any = None
        self.io: NodeIO | None = None  # what start() opened
        self.vehicle: Any = None
        self.flight_log = flight_log
        self.started_at = 0.0
        self.loop = EventLoop(
            f"agent-{name}-protocol",
            handle=self._handle,
            tick=self._tick,
            next_deadline=self._next_deadline,
            on_error=self._count_error,
            clock=clock,
        )
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._state: AgentState | None = None
        self._started = False
        self._stopped = False
        self._radio_seen = (0, 0)
        self._pose_beat = time.monotonic()  # the pose thread's last round
        self._fix_told: bool | None = None  # the pose thread's last PositionFix

    # -- the node's parts (None before start) ---------------------------------------
    @property
    def core(self) -> Any:
        return self.node.core if self.node is not None else None

    @property
    def gs(self) -> Any:
        return self.node.gs if self.node is not None else None

    @property
    def names(self) -> dict[int, str]:
        return self.node.names if self.node is not None else {}

    # -- life cycle -------------------------------------------------------------
    def _open(self) -> None:
        """Open the session, radio (unless handed a link), bridge and flight controller
        and start the threads (:meth:`start`, from :class:`StartOnce`)."""
        sink = self.flight_log.sink("radio") if self.flight_log is not None else None
        self.io = io = open_node_io(self.name, self.id, self.options, capture=sink)
        self.session, self.link, self.bridge, self.transport = io.session, io.link, io.bridge, io.transport
        if self.fc_url is not None:
            from firmware_bridge.driver import connect

            self.vehicle = connect(
                self.fc_url,
                timeout=self.config.fc_timeout,
                on_link_lost=lambda: self.loop.put(VehicleLink(False)),
                on_link_restored=lambda: self.loop.put(VehicleLink(True)),
            )
            self.vehicle.add_message_hook(self._fc_text)
            if self.flight_log is not None:
                self.vehicle.add_message_hook(self._log_fc)
        self.node = AgentNode(
            self.id,
            self.name,
            self.profile,
            policy=self._policy(),
            rng=random.Random(self.config.seed),
            has_fc=self.vehicle is not None,
            pilot=self.config.pilot,
            stats=self.stats,
            cap=self.config.swarm_cap,
            swarm_name=self.config.swarm_name,
        )
        if self.bridge is not None:  # the election core stands still while the radio is away
            self.bridge.add_listener(self._radio_event)
        self.transport.on_inbox(self.loop.put)
        self.transport.on_advertize(self.loop.put)
        self.transport.on_gs_advertize(self.loop.put)
        self.transport.on_pose(
            "*",
            lambda name, rep: self.loop.put(PoseHeard(rep.pose, name=name)) if name != self.name else None,
        )
        self.started_at = self.clock()
        self._execute(self.node.start(self.clock()))
        self.loop.start()
        if self.vehicle is not None:
            self._spawn(self._pose_loop, "pose")
            self._spawn(self._vehicle_loop, "vehicle")

    def radio_restored(self) -> None:
        """The radio guard found the radio off the swarm's settings and put it back: it
        was cut off from the swarm (:class:`swarm.core.agent.node.RadioRestored`)."""
        self.loop.put(RadioRestored())

    def _radio_event(self, what: str, _text: str) -> None:
        """The bridge's radio events: the election core stands still while the radio is
        away (:class:`swarm.core.agent.node.RadioAway`)."""
        if what in ("lost", "paused"):
            self.loop.put(RadioAway())
        elif what == "back":
            self.loop.put(RadioBack())

    def _spawn(self, target: Callable[[], None], what: str) -> None:
        t = threading.Thread(target=target, name=f"agent-{self.name}-{what}", daemon=True)
        self._threads.append(t)
        t.start()

    def _policy(self) -> VotePolicy:
        if self.config.vote == "battery":
            return BatteryVote(self._battery)
        if self.config.vote == "link":
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
        self.loop.stop()
        self._calls.put(_STOP)
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(2.0)
        if self.vehicle is not None:
            try:
                self.vehicle.close()
            except Exception:  # every part gets its chance to close
                log.debug("agent %s: error while closing the vehicle", self.name, exc_info=True)
        if self.io is not None:
            self.io.close()  # transport, bridge, link (unless handed), session
        if self.flight_log is not None:
            self.flight_log.close()  # last: the frames of the closing are in it

    close = stop

    def __enter__(self) -> Agent:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- public helpers -----------------------------------------------------------
    @property
    def running(self) -> bool:
        radio_ok = self.bridge is None or not self.bridge.link_lost
        return (
            self._started
            and not self._stopped
            and radio_ok
            and self.loop.alive
            and all(t.is_alive() for t in self._threads)
        )

    def loop_beats(self) -> dict[str, tuple[float, float]]:
        """Each loop's last round (``time.monotonic()``) and the longest it waits between
        rounds (see the module docstring); the vehicle thread is left out."""
        beats = {"protocol": (self.loop.beat, self.loop.max_wait)}
        if self.bridge is not None:
            beats.update(self.bridge.beats())
        if self.vehicle is not None:
            beats.update(self.vehicle.beats())
            beats["pose"] = (self._pose_beat, 1.0 / self.config.pose_hz)
        return beats

    def state(self) -> AgentState | None:
        """The last state the protocol thread published (None before the first)."""
        return self._state

    def set_task(self, task: Task) -> None:
        """The task a leader sends on its Heartbeats (applied on the protocol thread)."""
        self.loop.put(SetTask(task))

    def describe(self) -> str:
        """Where the agent meets others, for the ready line."""
        return self.options.describe()

    # -- protocol thread: the node and what it asks for ------------------------------
    def _handle(self, item: object, now: float) -> None:
        assert self.node is not None
        self._execute(self.node.handle(item, now))

    def _tick(self, now: float) -> None:
        node = self.node
        assert node is not None
        if self.bridge is not None:
            radio = (self.bridge.radio.rssi, self.bridge.radio.remrssi)
            if radio != self._radio_seen:
                self._radio_seen = radio
                node.handle(RadioInfo(*radio), now)
        self._execute(node.tick(now))

    def _next_deadline(self) -> float:
        return self.node.next_deadline() if self.node is not None else self.clock() + 1.0

    def _count_error(self) -> None:
        self.stats["errors"] += 1

    def _execute(self, outs: list[NodeOut]) -> None:
        for o in outs:
            if isinstance(o, Send):
                self._send(o)
            elif isinstance(o, PublishState):
                self._publish_state(o.state)
            elif isinstance(o, SetpointOut):
                self._setpoint(o.setpoint)
            elif isinstance(o, CallOut):
                self._calls.put(o.call)
            elif isinstance(o, EventOut):
                self._event(o.text)

    def _send(self, o: Send) -> None:
        tr = self.transport
        try:
            if o.to == 0:
                if isinstance(o.msg, Advertize):
                    tr.advertise(o.msg)
                    self.stats["advertized"] += 1
                elif isinstance(o.msg, GSAdvertize):
                    tr.gs_advertise(o.msg)
                return
            if o.name is None:
                self.stats["unknown_destination"] += 1
                return
            tr.send(o.name, o.msg)
            self.stats["gs_sent" if o.to > 250 else "sent"] += 1
        except Exception:  # the session closing under us, or a bad peer name
            self.stats["send_errors"] += 1
            log.debug("agent %s: send failed", self.name, exc_info=True)

    def _event(self, text: str) -> None:
        log.info("agent %s: %s", self.name, text)
        if self.on_event is not None:
            try:
                self.on_event(text)
            except Exception:
                log.exception("agent %s: on_event callback failed", self.name)

    def _setpoint(self, sp: Setpoint) -> None:
        v = self.vehicle
        if v is None:
            return
        s = v.state
        if s.home is not None:
            home_amsl = s.home[2]
        elif s.position_valid and s.alt_amsl is not None and s.rel_alt is not None:
            home_amsl = s.alt_amsl - s.rel_alt
        else:
            return
        try:
            v.set_target_global(
                sp.lat, sp.lon, sp.alt - home_amsl, math.radians(sp.yaw_deg), velocity=(sp.vn, sp.ve, 0.0)
            )
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
                self.loop.put(CallDone(item, True, ""))
            except Exception as exc:
                result, reason = call_result(exc)
                self.loop.put(CallDone(item, False, str(exc) or type(exc).__name__, result, reason))

    def _do_call(self, c: Call) -> None:
        v = self.vehicle
        if c.kind == "arm":
            v.arm()
        elif c.kind == "disarm":
            v.disarm()
        elif c.kind == "takeoff":  # not armable within seconds: refused with the reasons, never late
            v.takeoff(c.alt, wait=True, timeout=60.0, ready_timeout=TAKEOFF_READY_S)
            v.start_offboard()  # hold here under setpoint control
        elif c.kind == "control":  # the autopilot let go (a failsafe, RC): hold here under setpoints
            v.take_control()
        elif c.kind == "land":
            v.land()
        elif c.kind == "return":
            v.return_to_launch()
        elif c.kind == "mode":  # the operator's choice: the autopilot flies it (AUTO.LOITER, BRAKE)
            v.stop_setpoints()
            v.set_mode(c.mode)
        else:
            raise ValueError(f"unknown vehicle call {c.kind!r}")

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

    def _log_fc(self, msg: Any) -> None:
        """The driver's receiver thread: queue a key message for the flight log."""
        if msg.get_msgId() in FC_LOG_MESSAGES:
            self.flight_log.put("fc", msg.get_msgbuf())

    def _fc_text(self, msg: Any) -> None:
        """The driver's receiver thread: the autopilot's STATUSTEXT to the node (its notices)."""
        if msg.get_type() == "STATUSTEXT" and msg.get_srcSystem() == self.vehicle.state.system_id:
            self.loop.put(AutopilotText(int(msg.severity), msg.text))

    # -- pose thread -------------------------------------------------------------------
    def _pose_loop(self) -> None:
        period = 1.0 / self.config.pose_hz
        while not self._stop.wait(period):
            self._pose_beat = time.monotonic()
            try:
                self._pose_once()
            except Exception:
                self.stats["errors"] += 1
                log.exception("agent %s: pose error", self.name)

    def _pose_once(self) -> None:
        v = self.vehicle
        s = v.state
        link_ok = bool(getattr(v, "link_ok", True))
        self.loop.put(vehicle_info(s, link_ok))
        if not link_ok:
            return  # no fresh position: a stale one would look alive to the swarm
        if self.bridge is not None:
            for msg in vehicle_messages(s):
                self.bridge.forward_vehicle(msg)
                self.stats["vehicle_forwarded"] += 1
        # the pose's sample time is when the position arrived, not when we read it
        t = s.position_time if s.position_time and self.clock is time.monotonic else self.clock()
        pose = pose_from_state(s, t)
        if (pose is not None) != self._fix_told:
            self._fix_told = pose is not None
            self.loop.put(PositionFix(pose is not None, s.position_reason or "position not finite"))
        if pose is None:
            self.stats["poses_withheld"] += 1
            return
        home = s.home if s.home is not None and s.home[:2] != (0.0, 0.0) else None
        self.loop.put(OwnPose(pose, bool(s.in_air), home))
        self.transport.publish_pose(PoseReport(pose))
        self.stats["poses"] += 1


__all__ = ["FC_LOG_MESSAGES", "STATS", "Agent", "call_result", "default_round_s"]
