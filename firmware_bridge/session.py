"""One connected autopilot's threads and I/O, around the driver's pure cores.

Theory of operation. A :class:`Session` is made by :func:`~firmware_bridge.driver.connect`
with an open pymavlink connection and the autopilot's first HEARTBEAT; the
:class:`~firmware_bridge.driver.Vehicle` facade adds the flight API on top. The
pure cores (:mod:`firmware_bridge.telemetry`, :mod:`firmware_bridge.commands`) are
used only under the session's lock; the threads feed them ``time.monotonic()``.

* the *receiver* reads every message, folds it
  (:class:`~firmware_bridge.telemetry.TelemetryFolder`: only the autopilot's, into
  an immutable :class:`VehicleState`), hands a COMMAND_ACK or STATUSTEXT to the
  command in flight, and wakes whoever waits on the condition; a TCP link that
  ends is reconnected once a second;
* the *housekeeper* sends the companion HEARTBEAT at 1 Hz (type ONBOARD_CONTROLLER,
  component 191), asks :class:`~firmware_bridge.telemetry.LinkWatch` whether the
  link is lost (no autopilot message for ``link_timeout`` -> ``on_link_lost`` once,
  then ``on_link_restored``) and, while the link is up, re-requests the telemetry
  :class:`~firmware_bridge.telemetry.StreamRequests` names (ArduPilot streams
  nothing until asked; UDP loses requests);
* the *streamer* (:class:`~firmware_bridge.streamer.SetpointStreamer`, only while a
  target is set) sends the current position target at a fixed rate.

Both threads note ``time.monotonic()`` at every round (:meth:`Session.beats`): a
supervisor (the service watchdog) sees one that hangs, such as the housekeeper in a
serial write to an autopilot whose USB port stopped taking bytes.

Commands go out one at a time: :meth:`Session.command` makes a
:class:`~firmware_bridge.commands.CommandExchange`, sends what it returns and
sleeps on the condition until its next deadline or an answer; the exchange's
outcome becomes the return value or a :class:`CommandRejected` /
:class:`CommandTimeout`. :meth:`Session.wait_for` waits for a condition on the
telemetry snapshot; :meth:`Session.wait_ready` for "armable" as the autopilot reports
it (:func:`~firmware_bridge.telemetry.arming_problems`), or :class:`NotReady` with
what was missing and the autopilot's latest "PreArm:"/"Arm:" texts.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Self

from firmware_bridge.commands import (
    ARMING_TEXTS,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_RESULT_ACCEPTED,
    CommandExchange,
    command_long,
)
from firmware_bridge.connection import (
    COMPANION_COMPONENT,
    Endpoint,
    close_link,
    companion_heartbeat,
    signing_timestamp,
)
from firmware_bridge.errors import BridgeError, FlightInterrupted
from firmware_bridge.modes import autopilot_name
from firmware_bridge.px4_events import EventCatalog
from firmware_bridge.setpoints import GlobalTarget, LocalTarget, setpoint_message
from firmware_bridge.streamer import SetpointStreamer
from firmware_bridge.telemetry import (
    MSG_ATTITUDE,
    MSG_EKF_STATUS_REPORT,
    MSG_EXTENDED_SYS_STATE,
    MSG_GLOBAL_POSITION_INT,
    MSG_GPS_RAW_INT,
    MSG_HOME_POSITION,
    MSG_LOCAL_POSITION_NED,
    MSG_SYS_STATUS,
    LinkWatch,
    StatusText,
    StreamRequests,
    TelemetryFolder,
    VehicleState,
    arming_problems,
    interruption,
)

log = logging.getLogger("firmware_bridge.driver")  # one logger for the driver, as before the split

__all__ = ["NotReady", "Session", "WaitTimeout"]

TEXT_FRESH_S = 5.0  # an arming text older than this is quoted with its age

#: the modes in which the vehicle follows the companion's setpoints
SETPOINT_MODES = frozenset({"OFFBOARD", "GUIDED"})


def check_timeout(value: float, what: str) -> float:
    """``value`` if it is a finite number of seconds >= 0, else BridgeError."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value < math.inf:
        raise BridgeError(f"{what} {value!r} must be a finite number of seconds >= 0")
    return float(value)


class WaitTimeout(BridgeError, TimeoutError):
    """A :meth:`Session.wait_for` condition did not come true in time."""


class NotReady(WaitTimeout):
    """:meth:`Session.wait_ready`: the vehicle did not become armable in time; the
    message names what was missing and the autopilot's latest pre-arm texts."""

    def __init__(self, message: str, problems: Sequence[str] = (), texts: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.problems = list(problems)
        self.texts = list(texts)


@dataclass
class Options:
    """What :func:`~firmware_bridge.driver.connect` was asked for (checked there)."""

    link_timeout: float = 2.0
    on_link_lost: Callable[[], object] | None = None
    on_link_restored: Callable[[], object] | None = None
    setpoint_rate_hz: float = 10.0
    command_retries: int = 3
    command_timeout: float = 1.0
    telemetry_rate_hz: float = 10.0
    mode_timeout: float = 3.0
    interval_history: int = 2000
    events: EventCatalog | None = None  # PX4's event metadata (px4_events), if any


# --- the session ---------------------------------------------------------------------
class Session:
    """The threads and I/O of a connected autopilot (see the module header); a context manager."""

    def __init__(
        self,
        conn: Any,
        endpoint: Endpoint,
        heartbeat: Any,
        opts: Options,
        source_system: int | None,
        source_component: int = COMPANION_COMPONENT,
    ) -> None:
        self._conn = conn
        self.endpoint = endpoint
        self._opts = opts
        self.target_system: int = heartbeat.get_srcSystem()
        self.target_component: int = heartbeat.get_srcComponent()
        self.autopilot: str = autopilot_name(heartbeat.autopilot)
        conn.mav.srcSystem = source_system if source_system is not None else self.target_system
        conn.mav.srcComponent = source_component
        conn.target_system, conn.target_component = self.target_system, self.target_component
        self._t0 = time.monotonic()
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._send_lock = threading.Lock()
        self._cmd_lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        # the pure cores, used under self._lock
        self._telemetry = TelemetryFolder(
            self.autopilot,
            self.target_system,
            self.target_component,
            own_system=conn.mav.srcSystem,
            events=opts.events,
        )
        self._exchange: CommandExchange | None = None
        self._link = LinkWatch(opts.link_timeout)
        self._requests = StreamRequests()
        self._streamer = SetpointStreamer(
            self._send,
            self._setpoint_message,
            rate_hz=opts.setpoint_rate_hz,
            history=opts.interval_history,
            cond=self._cond,
            closing=self._stop,
        )
        self._handle(heartbeat, time.monotonic())
        self._beat_rx = self._beat_hk = time.monotonic()  # each thread's last round
        self._threads = [
            threading.Thread(target=self._receive_loop, name="fb-receiver", daemon=True),
            threading.Thread(target=self._housekeeping_loop, name="fb-housekeeping", daemon=True),
        ]
        for t in self._threads:
            t.start()

    # -- context manager / lifetime
    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the threads and close the link. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self._streamer.stop()
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(2.0)
        with self._send_lock:
            close_link(self._conn)
        with self._cond:
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def beats(self) -> dict[str, tuple[float, float]]:
        """The receiver's and the housekeeper's last round (``time.monotonic()``) and the
        longest each waits between rounds (a TCP reconnect takes up to a second)."""
        return {"fc-receive": (self._beat_rx, 1.1), "fc-housekeeping": (self._beat_hk, 0.1)}

    @property
    def link_ok(self) -> bool:
        """False while the autopilot is silent for longer than ``link_timeout``."""
        return self._link.ok

    def add_message_hook(self, fn: Callable[[Any], object]) -> None:
        """Call ``fn(msg)`` with every message received on the autopilot's link (a
        pymavlink message: ``get_msgbuf()`` is the frame as received), on the receiver
        thread, so ``fn`` must not block (a flight log queues the frame). An error in
        ``fn`` is logged, never raised into the receiver."""

        def hook(_conn: Any, msg: Any) -> None:
            try:
                fn(msg)
            except Exception:
                log.debug("%s: message hook failed", self.endpoint, exc_info=True)

        self._conn.message_hooks.append(hook)

    # -- state access
    @property
    def state(self) -> VehicleState:
        """The latest telemetry snapshot (immutable)."""
        with self._lock:
            return self._telemetry.state

    def statustexts(self) -> list[StatusText]:
        """The last STATUSTEXTs from the autopilot, oldest first."""
        with self._lock:
            return list(self._telemetry.texts)

    def setpoint_intervals(self) -> list[float]:
        """Measured gaps between consecutive setpoint sends, in seconds (last N)."""
        return self._streamer.intervals()

    @property
    def setpoints_sent(self) -> int:
        """How many setpoints the streamer has sent."""
        return self._streamer.sent

    def wait_for(
        self,
        predicate: Callable[[VehicleState], bool],
        timeout: float,
        what: str = "condition",
        *,
        interrupt: Callable[[VehicleState], str | None] | None = None,
    ) -> VehicleState:
        """Wait until ``predicate(state)`` is true; return that state. ``interrupt``
        says why it never will (a reason, else None): then the wait ends at once.

        Raises:
            WaitTimeout: not true within ``timeout`` s.
            FlightInterrupted: ``interrupt`` gave a reason.
            BridgeError: the vehicle was closed meanwhile.
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                s = self._telemetry.state
                if predicate(s):
                    return s
                why = interrupt(s) if interrupt is not None else None
                if why is not None:
                    raise FlightInterrupted(f"{what} not reached: {why}", state=s)
                if self._closed:
                    raise BridgeError("vehicle connection closed")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise WaitTimeout(
                        f"{what} not reached within {timeout:g} s "
                        f"(mode {s.mode}, armed {s.armed}, rel_alt {s.rel_alt})"
                    )
                self._cond.wait(min(left, 0.5))

    def wait_ready(self, timeout: float = 60.0, *, position: bool = True) -> VehicleState:
        """Wait until the vehicle is armable as its autopilot reports it
        (:func:`~firmware_bridge.telemetry.arming_problems`: booted, with ``position``
        a valid position and a local position, and the pre-arm check bit of SYS_STATUS
        set when the autopilot sends it). A real ArduPilot takes about 40 s after boot.

        Raises:
            NotReady: not armable within ``timeout`` s (what was missing, and the
                autopilot's latest "PreArm:"/"Arm:" texts).
            BridgeError: the vehicle was closed meanwhile, or ``timeout`` is not a
                finite number of seconds >= 0.
        """
        check_timeout(timeout, "wait_ready timeout")
        started = time.monotonic()
        try:
            return self.wait_for(lambda s: not arming_problems(s, position=position), timeout, "armable")
        except WaitTimeout:
            problems = arming_problems(self.state, position=position)
            texts = self.arming_texts(since=started - 30.0)
            # the autopilot's own words first: a reason cut to fit a radio message keeps them
            parts = [f"autopilot: {'; '.join(texts)}"] if texts else []
            if problems:
                parts.append(", ".join(problems))
            raise NotReady(
                f"not armable after {timeout:.3g} s: {'; '.join(parts) or 'refused'}", problems, texts
            ) from None

    def arming_texts(self, since: float, most: int = 4) -> list[str]:
        """The autopilot's latest distinct pre-arm/arm refusal texts heard at ``since``
        or later (newest last, at most ``most``); one older than :data:`TEXT_FRESH_S`
        says how old it is ("... (25 s ago)": ArduPilot repeats its PreArm texts only
        every 30 s, so an old one may no longer hold)."""
        now = time.monotonic()
        with self._lock:
            texts = [t for t in self._telemetry.texts if t.time >= since and t.text.startswith(ARMING_TEXTS)]
        out: list[str] = []
        seen: set[str] = set()
        for t in reversed(texts):
            if t.text in seen:
                continue
            seen.add(t.text)
            age = now - t.time
            out.append(t.text if age <= TEXT_FRESH_S else f"{t.text} ({age:.0f} s ago)")
            if len(out) == most:
                break
        return out[::-1]

    def wait_altitude(self, rel_alt: float, *, tolerance: float = 0.5, timeout: float = 60.0) -> VehicleState:
        """Wait until the altitude above home is within ``tolerance`` of ``rel_alt``.

        Raises:
            WaitTimeout: not within ``timeout`` s.
            FlightInterrupted: the vehicle disarmed or left the setpoint mode it was in.
        """
        return self.wait_for(
            lambda s: s.rel_alt is not None and abs(s.rel_alt - rel_alt) <= tolerance,
            timeout,
            f"altitude {rel_alt:g} m",
            interrupt=self._held(),
        )

    def _held(self) -> Callable[[VehicleState], str | None]:
        """What ends a wait for a point: the vehicle disarms, or leaves the setpoint
        mode (OFFBOARD, GUIDED) it is in now."""
        before = self.state
        hold = before.mode if before.mode in SETPOINT_MODES else None
        return lambda s: interruption(before, s, hold)

    def wait_ned(
        self,
        north: float,
        east: float,
        down: float | None = None,
        *,
        tolerance: float = 0.5,
        timeout: float = 60.0,
    ) -> VehicleState:
        """Wait until the local position is within ``tolerance`` m of the point.

        Raises:
            WaitTimeout: not within ``timeout`` s.
            FlightInterrupted: the vehicle disarmed or left the setpoint mode it was in.
        """

        def near(s: VehicleState) -> bool:
            if s.ned is None:
                return False
            dz = 0.0 if down is None else s.ned[2] - down
            return math.hypot(s.ned[0] - north, s.ned[1] - east, dz) <= tolerance

        return self.wait_for(near, timeout, f"position ({north:g}, {east:g})", interrupt=self._held())

    # -- sending
    def _send(self, msg: Any) -> None:
        with self._send_lock:
            if self._closed and msg.get_type() != "HEARTBEAT":
                raise BridgeError("vehicle connection closed")
            signing = self._conn.mav.signing
            if signing.sign_outgoing:  # pymavlink adds 10 µs a frame: keep up with the wall clock
                signing.timestamp = max(signing.timestamp, signing_timestamp())
            try:
                self._conn.mav.send(msg)
            except OSError as e:
                log.debug("send failed: %s", e)

    def _setpoint_message(self, target: LocalTarget | GlobalTarget) -> Any:
        boot_ms = int((time.monotonic() - self._t0) * 1000)
        return setpoint_message(
            target,
            time_boot_ms=boot_ms,
            target_system=self.target_system,
            target_component=self.target_component,
        )

    def send_command_nowait(self, command: int, params: Sequence[float] = ()) -> None:
        """Send a COMMAND_LONG without waiting for its ACK."""
        self._send(
            command_long(
                command, params, 0, target_system=self.target_system, target_component=self.target_component
            )
        )

    def command(
        self,
        command: int,
        params: Sequence[float] = (),
        *,
        retries: int | None = None,
        timeout: float | None = None,
        in_progress_timeout: float = 30.0,
    ) -> int:
        """Send COMMAND_LONG ``command`` and wait for its ACCEPTED COMMAND_ACK.

        Each try waits ``timeout`` s (default ``command_timeout``); IN_PROGRESS keeps
        waiting (up to ``in_progress_timeout``). Returns MAV_RESULT_ACCEPTED.

        Raises:
            CommandRejected: any other result (with the autopilot's STATUSTEXT).
            CommandTimeout: no ACK after ``retries`` tries.
            BridgeError: the vehicle was closed meanwhile.
        """
        with self._cmd_lock:
            with self._lock:
                ex = self._exchange = CommandExchange(
                    command,
                    params,
                    time.monotonic(),
                    target_system=self.target_system,
                    target_component=self.target_component,
                    tries=self._opts.command_retries if retries is None else retries,
                    per_try=self._opts.command_timeout if timeout is None else timeout,
                    in_progress_timeout=in_progress_timeout,
                    texts=self._telemetry.texts,
                )
            try:
                sends = [ex.start()]
                while sends:
                    for msg in sends:
                        self._send(msg)
                    sends = self._exchange_sends(ex)
            finally:
                with self._lock:
                    self._exchange = None
        error = ex.error(self.autopilot)
        if error is not None:
            raise error
        return MAV_RESULT_ACCEPTED

    def _exchange_sends(self, ex: CommandExchange) -> list[Any]:
        """Wait until ``ex`` is done (-> []) or has a retry to send (-> it)."""
        with self._cond:
            while (deadline := ex.next_deadline()) is not None:
                now = time.monotonic()
                if self._closed:  # no ACK will come: act on the deadline at once
                    now = max(now, deadline)
                if now >= deadline:
                    sends = ex.tick(now)
                    if sends:
                        return sends
                else:
                    self._cond.wait(deadline - now)
        return []

    def _texts_since(self, since: float) -> str:
        """The autopilot's STATUSTEXTs from half a second before ``since`` on."""
        with self._lock:
            return "; ".join(self._telemetry.texts_since(since - 0.5))

    # -- telemetry requests
    def request_message_interval(self, msg_id: int, rate_hz: float) -> None:
        """Ask for ``msg_id`` at ``rate_hz`` (SET_MESSAGE_INTERVAL, ACK not awaited;
        re-sent by the housekeeper while the message does not arrive)."""
        with self._lock:
            self._requests.asked(msg_id, rate_hz, time.monotonic())
        self.send_command_nowait(MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, 1e6 / rate_hz))

    def request_telemetry(self) -> None:
        fast = self._opts.telemetry_rate_hz
        for msg_id, rate in (
            (MSG_GLOBAL_POSITION_INT, fast),
            (MSG_LOCAL_POSITION_NED, fast),
            (MSG_ATTITUDE, fast),
            (MSG_EXTENDED_SYS_STATE, 2.0),
            (MSG_SYS_STATUS, 1.0),
            (MSG_GPS_RAW_INT, 1.0),
            (MSG_HOME_POSITION, 1.0),
        ):
            self.request_message_interval(msg_id, rate)
        if self.autopilot == "ardupilot":  # its EKF's flags say when its position is absolute
            self.request_message_interval(MSG_EKF_STATUS_REPORT, 1.0)
        self.send_command_nowait(MAV_CMD_REQUEST_MESSAGE, (MSG_HOME_POSITION,))

    def _rerequest(self, now: float) -> None:
        with self._lock:
            due = self._requests.due(self._telemetry.seen, now)
        for msg_id, rate in due:
            self.request_message_interval(msg_id, rate)
        with self._lock:
            home = self._requests.home_due(self._telemetry.state.home is not None, now)
        if home:
            self.send_command_nowait(MAV_CMD_REQUEST_MESSAGE, (MSG_HOME_POSITION,))

    # -- threads
    def _receive_loop(self) -> None:
        conn = self._conn
        last_reconnect = 0.0
        while not self._stop.is_set():
            self._beat_rx = time.monotonic()
            try:
                if getattr(conn, "eof", False):
                    now = time.monotonic()
                    if now - last_reconnect >= 1.0:
                        last_reconnect = now
                        if conn.try_reconnect():
                            log.info("%s: TCP reconnected", self.endpoint)
                            continue
                    self._stop.wait(0.1)
                    continue
                conn.select(0.05)
                while not self._stop.is_set():
                    msg = conn.recv_msg()
                    if msg is None:
                        break
                    self._beat_rx = time.monotonic()
                    self._handle(msg, time.monotonic())
            except Exception as e:  # a dying link must not kill the thread silently
                if self._stop.is_set():
                    break
                log.debug("receive error on %s: %s", self.endpoint, e)
                self._stop.wait(0.1)

    def _handle(self, msg: Any, now: float) -> None:
        with self._cond:
            heard = self._telemetry.fold(msg, now)
            ex = self._exchange
            if ex is not None:
                for event in (heard.ack, heard.text):
                    if event is not None:
                        ex.handle(event, now)
            self._cond.notify_all()

    def _housekeeping_loop(self) -> None:
        next_hb = time.monotonic()
        next_check = next_hb + 1.0
        while not self._stop.wait(0.05):
            now = self._beat_hk = time.monotonic()
            if now >= next_hb:
                with contextlib.suppress(BridgeError):
                    self._send(companion_heartbeat())
                next_hb = max(next_hb + 1.0, now + 0.5)
            self._watch_link(now)
            if now >= next_check:
                next_check = now + 1.0
                if self.link_ok:
                    with contextlib.suppress(BridgeError):
                        self._rerequest(now)

    def _watch_link(self, now: float) -> None:
        last = self.state.last_message_time
        change = self._link.check(last, now)
        if change == "lost":
            log.warning("%s: autopilot link lost (%.1f s silent)", self.endpoint, now - last)
            self._callback(self._opts.on_link_lost)
            with self._cond:
                self._cond.notify_all()
        elif change == "restored":
            log.info("%s: autopilot link restored", self.endpoint)
            self._callback(self._opts.on_link_restored)

    @staticmethod
    def _callback(cb: Callable[[], object] | None) -> None:
        if cb is None:
            return
        try:
            cb()
        except Exception:
            log.exception("link callback failed")
