"""Replay: a captured flight (``.tlog``) played into the station's core, for the page.

Theory of operation
-------------------
:func:`load_capture` reads a whole capture (radios.tlog: every record checked; a
damaged file raises) and turns its frames into timed inputs for a passive
:class:`~swarm.core.station.core.StationCore`, keying TUNNEL payloads exactly as the radio
bridge does (:mod:`swarm.runtime.bridge.radio_bridge`: ``payload_type`` 32768 + kind, the sender's
system id, names learnt from Advertize and GSAdvertize, multicast address lists
stripped). The vehicles' own frames that agents forward (HEARTBEAT: mode and
arming; GLOBAL_POSITION_INT: position, heading, speed) count too, so a capture of
agents with no station in the air still shows them on the map.

:class:`ReplayStation` plays those inputs with the recorded timing: a position on
the capture's time line advanced by ``speed`` times the elapsed clock while
playing; pause, seek (backwards re-feeds a fresh core from the start, quickly,
without announcing the events again) and speed. :meth:`ReplayStation.step` does
the work and takes its time from the injected ``clock``, so tests drive it
without real time passing; :meth:`ReplayStation.start` calls it from a thread.
It offers the server the same view as the live station, in the capture's time (the
state's ``time`` and the events' times are the capture's; an agent counts as
connected if heard within ``passive_timeout`` of that time); commands are refused
(409). :meth:`ReplayStation.status` adds the capture's time at the play position
(``time``, ``start``) for the page's "REPLAY" header, ``seeks``, which counts
seeks (the page rebuilds its event log from the state when it changes), and
``radio``: the station radio's last RADIO_STATUS by then (a capture made on the
station's radio holds them: rssi, remrssi, noise, remnoise, txbuf, rxerrors), so a
replay shows the link's quality.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, cast

from firmware_bridge.modes import autopilot_name, decode_mode
from radios.errors import FrameError
from radios.mavlink import MSG_HEARTBEAT, MSG_RADIO_STATUS, MSG_TUNNEL, radio_status_fields
from radios.mavlink import decode as decode_frame
from radios.tlog import read_tlog
from swarm.core.station.commands import CommandRefused, CommandSpec
from swarm.core.station.core import StationCore
from swarm.core.station.model import StationConfig
from swarm.core.station.rows import CapturedRadio, EventRow, ReplayStatus
from swarm.core.wire.codes import is_station
from swarm.core.wire.message_types import Advertize, GSAdvertize, Message, Pose, check_name
from swarm.core.wire.messages import decode as decode_msg
from swarm.core.wire.tunnel import COMP_ID, Kind, unpack_tunnel
from swarm.errors import DecodeError
from swarm.runtime.station.live import CoreStation
from swarm.runtime.station.served import Listener

log = logging.getLogger(__name__)

MSG_GLOBAL_POSITION_INT = 33
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAX_SPEED = 100.0
RADIO_STATUS_IDS = (51, 68)  # the ids a SiK radio gives its own RADIO_STATUS
STEP_S = 0.05


@dataclass(frozen=True)
class Item:
    """One timed input: ``op`` is msg (a swarm message, ``arg`` the key's agent name),
    learn (``arg`` a name), pose (``arg`` a Pose), vehicle (``arg`` (mode, armed)) or
    radio (the station radio's RADIO_STATUS, ``arg`` its fields)."""

    t: float
    op: str
    agent: int
    msg: Message | None = None
    arg: Any = None


@dataclass
class Capture:
    path: str
    items: list[Item] = field(default_factory=list)
    records: int = 0
    swarm_messages: int = 0
    vehicle_frames: int = 0
    decode_errors: int = 0
    t0: float = 0.0
    t1: float = 0.0
    station_name: str | None = None
    center: list[float] | None = None

    @property
    def duration(self) -> float:
        return max(0.0, self.t1 - self.t0)


def load_capture(path: str) -> Capture:
    """Read and decode a whole capture.

    Raises:
        CaptureError: the file cannot be read; CaptureDamagedError (a subclass) when
            it is truncated or corrupted (offset and record count in the message).
    """
    cap = Capture(path)
    names: dict[int, str] = {}
    for rec in read_tlog(path):
        if cap.records == 0:
            cap.t0 = rec.t
        cap.records += 1
        cap.t1 = max(cap.t1, rec.t)
        frame = rec.frame
        sysid = frame.sysid
        if frame.msgid == MSG_TUNNEL:
            _tunnel(cap, names, rec.t, sysid, frame.payload)
        elif frame.msgid == MSG_RADIO_STATUS and (sysid, frame.compid) == RADIO_STATUS_IDS:
            cap.items.append(Item(rec.t, "radio", 0, arg=radio_status_fields(frame)))
        elif (
            frame.msgid in (MSG_HEARTBEAT, MSG_GLOBAL_POSITION_INT)
            and frame.compid != COMP_ID
            and 1 <= sysid <= 250
        ):
            try:
                m = decode_frame(frame)
            except FrameError:
                cap.decode_errors += 1
                continue
            _vehicle(cap, names, rec.t, sysid, m)
    cap.items.sort(key=lambda it: it.t)  # stable: records stamped out of order play in time order
    return cap


def _ensure(cap: Capture, names: dict[int, str], t: float, agent: int) -> None:
    if agent not in names:
        names[agent] = f"agent{agent}"
        cap.items.append(Item(t, "learn", agent, arg=names[agent]))


def _tunnel(cap: Capture, names: dict[int, str], t: float, sender: int, payload: bytes) -> None:
    try:
        tun = unpack_tunnel(payload)
    except DecodeError:
        cap.decode_errors += 1
        return
    if tun is None:
        return
    kind, _target, _ids, data = tun
    if kind == Kind.MULTI:
        kind = Kind.P2P
    try:
        msg = decode_msg(data)
    except DecodeError:
        cap.decode_errors += 1
        return
    cap.swarm_messages += 1
    if kind in (Kind.ADVERTIZE, Kind.GS_ADVERTIZE) and isinstance(msg, (Advertize, GSAdvertize)):
        if is_station(msg.sender):
            cap.station_name = cap.station_name or msg.name
        elif names.get(msg.sender) != msg.name:
            names[msg.sender] = msg.name
            cap.items.append(Item(t, "learn", msg.sender, arg=msg.name))
        if isinstance(msg, GSAdvertize):
            cap.items.append(Item(t, "msg", msg.sender, msg, ""))
    elif kind == Kind.P2P:
        cap.items.append(Item(t, "msg", sender, msg, ""))
    elif 1 <= sender <= 250:  # pose, state: the key names the sender
        _ensure(cap, names, t, sender)
        pose = getattr(msg, "pose", None)
        if kind == Kind.POSE and isinstance(pose, Pose):
            cap.items.append(Item(t, "pose", sender, arg=pose))
            _center(cap, pose)
        elif kind == Kind.STATE:
            cap.items.append(Item(t, "msg", sender, msg, names[sender]))


def _center(cap: Capture, pose: Pose) -> None:
    if cap.center is None and not (pose.lat == 0.0 and pose.lon == 0.0):
        cap.center = [pose.lat, pose.lon]


def _vehicle(cap: Capture, names: dict[int, str], t: float, sysid: int, m: Any) -> None:
    if m.get_msgId() == MSG_HEARTBEAT:
        if m.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER):
            return  # a ground station or a companion computer, not a vehicle
        mode = decode_mode(autopilot_name(m.autopilot), m.custom_mode, m.base_mode)
        _ensure(cap, names, t, sysid)
        cap.items.append(Item(t, "vehicle", sysid, arg=(mode, bool(m.base_mode & 0x80))))
        cap.vehicle_frames += 1
        return
    if m.lat == 0 and m.lon == 0:
        return
    hdg = m.hdg / 100.0 if m.hdg != 65535 else 0.0
    try:
        pose = Pose(m.lat / 1e7, m.lon / 1e7, m.alt / 1000.0, hdg % 360.0, m.vx / 100.0, m.vy / 100.0, t)
    except ValueError:
        cap.decode_errors += 1
        return
    _ensure(cap, names, t, sysid)
    cap.items.append(Item(t, "pose", sysid, arg=pose))
    cap.vehicle_frames += 1
    _center(cap, pose)


class ReplayStation(CoreStation):
    """A capture played into a passive station core; the server's view of it."""

    id = 255

    def __init__(
        self,
        capture: Capture,
        *,
        speed: float = 1.0,
        name: str | None = None,
        config: StationConfig | None = None,
        playing: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        _check_speed(speed)
        self.capture = capture
        self.name = name or capture.station_name or "replay"
        check_name(self.name)
        self.cfg = config
        self.clock = clock
        self.speed = float(speed)
        self.playing = playing
        self.position = 0.0
        self.seeks = 0
        self.radio: CapturedRadio | None = None  # the station radio's last RADIO_STATUS
        self.core = self._new_core()
        self._index = 0
        self._last = clock()
        self._lock = threading.RLock()
        self._listeners: list[Listener] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._advance(0.0, announce=False)

    def _new_core(self) -> StationCore:
        return StationCore(self.name, self.id, self.cfg, passive=True)

    @property
    def replay(self) -> ReplayStation:
        return self

    # -- life cycle -------------------------------------------------------------
    def start(self) -> ReplayStation:
        self._last = self.clock()
        self._thread = threading.Thread(target=self._run, name="gcs-replay", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)

    close = stop

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        while not self._stop.wait(STEP_S):
            try:
                self.step()
            except Exception:
                log.exception("replay: step failed")

    def step(self) -> None:
        """Advance the play position by the clock time since the last step."""
        with self._lock:
            now = self.clock()
            dt, self._last = max(0.0, now - self._last), now
            if self.playing:
                self._advance(min(self.capture.duration, self.position + dt * self.speed), announce=True)
                if self.position >= self.capture.duration:
                    self.playing = False

    def _advance(self, position: float, *, announce: bool) -> None:
        items, core = self.capture.items, self.core
        target = self.capture.t0 + position
        while self._index < len(items) and items[self._index].t <= target:
            it = items[self._index]
            if core.next_deadline() <= it.t:
                core.tick(it.t)
            self._apply(it)
            self._index += 1
        core.tick(target)
        self.position = position
        events = core.take_events()
        if announce:
            self._notify([e.as_dict() for e in events])

    def _apply(self, it: Item) -> None:
        core = self.core
        if it.op == "msg" and it.msg is not None:
            core.handle(it.msg, it.t, it.arg or "")
        elif it.op == "learn":
            core.learn(it.agent, it.arg, it.t)
        elif it.op == "pose":
            core.observe_pose(it.agent, it.arg, it.t)
        elif it.op == "radio":
            self.radio = cast(CapturedRadio, {**it.arg, "t": round(it.t, 3)})  # radio_status_fields
        elif it.op == "vehicle":
            mode, armed = it.arg
            core.observe_vehicle(it.agent, it.t, mode=mode, armed=armed)

    # -- controls ----------------------------------------------------------------------
    def status(self) -> ReplayStatus:
        with self._lock:
            return {
                "playing": self.playing,
                "speed": self.speed,
                "position_s": round(self.position, 3),
                "duration_s": round(self.capture.duration, 3),
                "time": round(self.capture.t0 + self.position, 3),
                "start": round(self.capture.t0, 3),
                "seeks": self.seeks,
                "radio": self.radio,
            }

    def control(self, action: Any, value: Any = None) -> ReplayStatus:
        """play | pause | seek (value: seconds from the start) | speed (value: factor).

        Raises:
            CommandRefused: (400) unknown action or bad value.
        """
        with self._lock:
            self.step()
            if action == "play":
                if self.position >= self.capture.duration:
                    self.seek(0.0)
                self.playing = True
            elif action == "pause":
                self.playing = False
            elif action == "seek":
                v = _number(value, "seek")
                if not 0 <= v <= self.capture.duration:
                    raise CommandRefused(400, f"seek {v}: 0..{self.capture.duration:.3f} s")
                self.seek(v)
            elif action == "speed":
                v = _number(value, "speed")
                try:
                    _check_speed(v)
                except ValueError as exc:
                    raise CommandRefused(400, str(exc)) from None
                self.speed = v
            else:
                raise CommandRefused(400, f"unknown replay action {action!r}: play, pause, seek or speed")
            return self.status()

    def seek(self, position: float) -> None:
        with self._lock:
            self.seeks += 1
            if position < self.position:
                self.core = self._new_core()
                self.radio = None
                self._index = 0
            self._advance(position, announce=False)

    # -- the station view --------------------------------------------------------------
    def describe(self) -> str:
        return f"replay={self.capture.path}"

    def _now(self) -> float:
        return self.capture.t0 + self.position

    def center(self) -> list[float] | None:
        return self.capture.center

    def submit(self, spec: CommandSpec) -> Future[tuple[int, dict[str, Any]]]:
        raise CommandRefused(409, "replay: commands are disabled while a capture plays")

    def add_listener(self, fn: Listener) -> None:
        with self._lock:
            self._listeners.append(fn)

    def remove_listener(self, fn: Listener) -> None:
        with self._lock:
            if fn in self._listeners:
                self._listeners.remove(fn)

    def _notify(self, events: list[EventRow]) -> None:
        for e in events:
            for fn in list(self._listeners):
                try:
                    fn(e)
                except Exception:
                    log.exception("replay: event listener failed")


def _number(value: Any, what: str) -> float:
    """A finite number; integers too large for a float are refused, never converted."""
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or (isinstance(value, int) and abs(value) > 2**53)
        or (isinstance(value, float) and not math.isfinite(value))
    ):
        raise CommandRefused(400, f"{what} needs a number 'value', not {str(value)[:40]}")
    return float(value)


def _check_speed(speed: float) -> None:
    if not (math.isfinite(speed) and 0 < speed <= MAX_SPEED):
        raise ValueError(f"speed {speed}: a factor in (0, {MAX_SPEED:g}]")


__all__ = ["Capture", "Item", "ReplayStation", "load_capture"]
