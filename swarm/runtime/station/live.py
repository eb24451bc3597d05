"""The ground station's runtime: one :class:`~swarm.core.station.core.StationCore` on a thread.

:class:`Station` runs the core on a thread over a Zenoh session, optionally bridged
to a radio (exactly as :class:`swarm.runtime.agent.live.Agent` does), and gives the
server thread-safe snapshots, command futures and an event feed. On a radio, the
bridge's ``id_collision`` (a frame with the station's system id that it did not send:
MAVProxy or QGroundControl left at their default 255) becomes one ``radio`` event.
The agents' inboxes are heard too, for the plan (:mod:`swarm.core.station.plan`):
the leader's Heartbeats (one per round: the copies to each member are dropped
before the core's queue), and their command keys for other stations' Commands; other
messages there, and the station's own keys, are passed over on their first byte,
undecoded.
:class:`CoreStation` is the part of the live and the replayed station that reads their
:class:`StationCore` for the server (its :class:`~swarm.runtime.station.served.ServedStation`).
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any, cast

from swarm.core.flight.geofence import Geofence
from swarm.core.station.commands import CommandRefused, CommandSpec, outcome
from swarm.core.station.core import StationCore
from swarm.core.station.model import Event, StationConfig, StOut
from swarm.core.station.rows import AgentRow, AlertRow, Snapshot, StationInfo
from swarm.core.wire.message_types import GCS_ID, Command, GSAdvertize, Heartbeat, Message
from swarm.runtime.keyspace.transport import command_key, inbox_key
from swarm.runtime.loop import EventLoop
from swarm.runtime.node_io import NodeIO, StartOnce, open_node_io
from swarm.runtime.options import NodeOptions
from swarm.runtime.station.served import Listener

log = logging.getLogger(__name__)

TICK_S = 0.05
#: the message types overheard for the plan (the first byte's low bits): the leader's
#: Heartbeats on the agents' inboxes, other stations' Commands on their command keys
HB_TYPE, CMD_TYPE = Heartbeat.TYPE, Command.TYPE


class CoreStation:
    """A station as the server reads it, live or replayed: both keep a
    :class:`StationCore` under a lock and say what time it is for it (``_now``)."""

    core: StationCore
    name: str
    id: int
    _lock: threading.Lock | threading.RLock

    def _now(self) -> float:
        raise NotImplementedError  # each station knows its own time

    def describe(self) -> str:
        raise NotImplementedError

    @property
    def fence(self) -> Geofence:
        """The station's geofence (the page checks it before asking, the core before sending)."""
        return self.core.cfg.fence

    def snapshot(self) -> Snapshot:
        with self._lock:
            body = self.core.snapshot(self._now())
        body["station"] = {"name": self.name, "id": self.id, "link": self.describe()}
        return body

    def snapshot_json(self) -> str:
        """:meth:`snapshot` as JSON text (what the server sends)."""
        station: StationInfo = {"name": self.name, "id": self.id, "link": self.describe()}
        with self._lock:
            return self.core.snapshot_json(self._now(), station)

    def agent(self, agent_id: int) -> AgentRow | None:
        with self._lock:
            a = self.core.agents.get(agent_id)
            return a.as_dict(self._now()) if a is not None else None

    def ack_alert(self, alert_id: Any) -> AlertRow:
        """Acknowledge an alert (CommandRefused: 400 a bad id, 404 no such alert)."""
        with self._lock:
            return self.core.ack_alert(alert_id)

    def shelve_alert(self, alert_id: Any, seconds: Any) -> AlertRow:
        """Shelve an alarm for ``seconds`` (0: unshelve; CommandRefused: 400, 404)."""
        with self._lock:
            return self.core.shelve_alert(alert_id, seconds, self._now())


class Station(StartOnce, CoreStation):
    """One :class:`StationCore` on its own thread, over Zenoh (endpoints) or a radio.

    Construction checks arguments (ValueError); :meth:`start` opens everything and may
    raise :class:`radios.errors.ConfigError` (key file),
    :class:`radios.errors.LinkOpenError` (radio), :class:`radios.errors.CaptureError`
    (capture file), :class:`swarm.errors.TransportError` (Zenoh endpoints).
    """

    def __init__(
        self,
        name: str = "gcs",
        station_id: int = GCS_ID,
        *,
        radio: str | None = None,
        zenoh_listen: Sequence[str] = (),
        zenoh_connect: Sequence[str] = (),
        key_file: str | None = None,
        node: NodeOptions | None = None,
        capture: str | None = None,
        config: StationConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        if node is None:  # NodeOptions checks the way in (ValueError)
            node = NodeOptions(radio, None, zenoh_listen, zenoh_connect, key_file)
        if capture is not None and node.radio is None:
            raise ValueError("a capture records the radio's traffic: it needs a radio")
        self.core = StationCore(
            name, station_id, config, wall_offset=wall() - clock(), first_seq=random.randrange(1, 0x10000)
        )
        self.name = name
        self.id = station_id
        self.node = node
        self.capture = capture
        self.clock = clock
        self.replay = None
        self.session: Any = None
        self.transport: Any = None
        self.link: Any = None
        self.bridge: Any = None
        self.io: NodeIO | None = None  # what start() opened
        self.stats = {"send_errors": 0, "errors": 0}
        self._lock = threading.Lock()
        self._futures: dict[int, Future[tuple[int, dict[str, Any]]]] = {}
        self._listeners: list[Listener] = []
        # ticks at the core's deadlines and at most every TICK_S otherwise: at hundreds
        # of messages a second, ticking after every batch cost more than the messages
        # (every timer is a second or more, so 50 ms is invisible)
        self.loop = EventLoop(
            f"gcs-{name}",
            handle=self._handle,
            tick=self._tick,
            next_deadline=self.core.next_deadline,
            after=self._after,
            on_error=self._count_error,
            clock=clock,
            min_tick_gap=TICK_S,
        )
        self._started = self._stopped = False
        self._hb_round: tuple[int, int, int] | None = None  # the last Heartbeat round passed on

    def _open(self) -> None:
        self.io = io = open_node_io(self.name, self.id, self.node, capture=self.capture)
        self.session, self.link, self.bridge, self.transport = io.session, io.link, io.bridge, io.transport
        tr = io.transport
        tr.on_inbox(lambda m: self.loop.put((m, "")))
        tr.on_gs_advertize(lambda m: self.loop.put((m, "")))
        tr.on_pose("*", lambda n, m: self.loop.put((m, n)))
        tr.on_state("*", lambda n, m: self.loop.put((m, n)))
        own = inbox_key(self.name)
        tr.subscribe(
            "swarm/*", self._on_inboxes, lambda k, b: k != own and bool(b) and b[0] & 0x1F == HB_TYPE
        )
        mine = command_key(self.name)  # other stations' Commands, on the agents' command keys
        tr.subscribe(
            command_key("*"), self._on_inboxes, lambda k, b: k != mine and bool(b) and b[0] & 0x1F == CMD_TYPE
        )
        if io.bridge is not None:
            io.bridge.add_listener(self._on_radio)
        self.loop.start()

    def _on_inboxes(self, _key: str, msg: Message) -> None:
        """A message to any agent: the plan's (a Heartbeat once per round, a Command)."""
        if isinstance(msg, Heartbeat):
            round_ = (msg.sender, msg.epoch, msg.seq)
            if round_ == self._hb_round:
                return
            self._hb_round = round_
        elif not isinstance(msg, Command):
            return
        self.loop.put((msg, ""))

    def _on_radio(self, what: str, text: str) -> None:
        """The bridge heard our system id from another sender: say so (once, as the bridge does)."""
        if what == "id_collision":
            hint = "; give one of them another id (swarm gcs --id 254, or MAVProxy --source-system)"
            ev = Event(self.core.wall_offset + self.clock(), "radio", text + hint)
            with self._lock:
                self.core.events.append(ev)  # in the history a page opened later reads
            self._notify([ev])

    def stop(self) -> None:
        """Stop the thread, then close bridge, link and session. Safe twice."""
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
        self.loop.stop()
        if self.io is not None:
            self.io.close()
        with self._lock:
            futures, self._futures = self._futures, {}
        for f in futures.values():
            if not f.done():
                f.set_result((503, {"error": "the station stopped"}))

    close = stop

    def __enter__(self) -> Station:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def loop_beats(self) -> dict[str, tuple[float, float]]:
        """The protocol loop's and the bridge's last rounds (``time.monotonic()``) and
        longest waits: the service watchdog's input (:mod:`swarm.runtime.notify`)."""
        beats = {"protocol": (self.loop.beat, self.loop.max_wait)}
        if self.bridge is not None:
            beats.update(self.bridge.beats())
        return beats

    @property
    def running(self) -> bool:
        radio_ok = self.bridge is None or not self.bridge.link_lost
        return self._started and not self._stopped and radio_ok and self.loop.alive

    def describe(self) -> str:
        return self.node.describe()

    # -- for the server (any thread): snapshot, snapshot_json, agent from CoreStation --
    def _now(self) -> float:
        return self.clock()

    def center(self) -> list[float] | None:
        with self._lock:
            for a in self.core.agents.values():
                if a.pose is not None:
                    return [a.pose.lat, a.pose.lon]
        return None

    def submit(self, spec: CommandSpec) -> Future[tuple[int, dict[str, Any]]]:
        """Send a command; the future gives (status, body) once every addressee
        answered or ran out of tries.

        Raises:
            CommandRefused: see :meth:`StationCore.submit`.
        """
        fut: Future[tuple[int, dict[str, Any]]] = Future()
        with self._lock:
            if self._stopped:
                raise CommandRefused(503, "the station is stopping")
            req, outs = self.core.submit(spec, self.clock())
            self._futures[req.id] = fut
            events = self.core.take_events()
        self._send(outs)
        self._notify(events)
        self.loop.wake()  # its next deadline moved
        return fut

    def add_listener(self, fn: Listener) -> None:
        """``fn(event_dict)`` for every new event (called on the station's thread)."""
        with self._lock:
            self._listeners.append(fn)

    def remove_listener(self, fn: Listener) -> None:
        with self._lock:
            if fn in self._listeners:
                self._listeners.remove(fn)

    # -- the station thread -------------------------------------------------------------
    def _handle(self, item: object, now: float) -> None:
        msg, name = cast(tuple[Message, str], item)
        with self._lock:
            outs = self.core.handle(msg, now, name)
        self._send(outs)

    def _tick(self, now: float) -> None:
        radio = self.bridge.radio if self.bridge is not None else None
        with self._lock:
            if radio is not None and radio.t > -1e9:  # a RADIO_STATUS was heard (at radio.t, bridge clock)
                age = self.bridge.clock() - radio.t
                self.core.observe_radio(radio.rssi, radio.noise, radio.remrssi, radio.remnoise, now - age)
            outs = self.core.tick(now)
        self._send(outs)

    def _after(self) -> None:
        with self._lock:
            events = self.core.take_events()
            finished = self.core.take_finished()
            futures = [self._futures.pop(r.id, None) for r in finished]
        self._notify(events)
        for r, f in zip(finished, futures, strict=True):
            if f is not None and not f.done():
                f.set_result(outcome(r))

    def _count_error(self) -> None:
        self.stats["errors"] += 1

    def _send(self, outs: list[StOut]) -> None:
        tr = self.transport
        for o in outs:
            try:
                if o.to == 0:
                    if isinstance(o.msg, GSAdvertize):
                        tr.gs_advertise(o.msg)
                else:
                    tr.send(o.name, o.msg)
            except Exception:
                self.stats["send_errors"] += 1
                log.debug("station: send failed", exc_info=True)

    def _notify(self, events: list[Event]) -> None:
        if not events:
            return
        with self._lock:
            listeners = list(self._listeners)
        for e in events:
            d = e.as_dict()
            for fn in listeners:
                try:
                    fn(d)
                except Exception:
                    log.exception("station: event listener failed")


__all__ = ["CoreStation", "Station"]
