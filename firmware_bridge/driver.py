"""Companion-side driver of a PX4 or ArduPilot flight controller over MAVLink 2.

Theory of operation. :func:`connect` checks its arguments, parses the connection
string and opens the link (:mod:`firmware_bridge.connection`: our own deadlines
instead of pymavlink's blocking TCP connect and heartbeat wait; GCS and companion
heartbeats are ignored) and returns a :class:`Vehicle`, the public facade. Its
threads and I/O live in :class:`~firmware_bridge.session.Session` (receiver,
housekeeper, setpoint streamer, one command at a time), around the pure cores:
:mod:`firmware_bridge.telemetry` (messages -> :class:`VehicleState`, link lost or
back, stream re-requests), :mod:`firmware_bridge.commands` (COMMAND_LONG, ACK,
retries) and :mod:`firmware_bridge.setpoints` (validation, SET_POSITION_TARGET_*).

:class:`Vehicle` adds the flight API: modes by name, arming, takeoff, landing,
return, hold, and position targets. A real autopilot refuses to arm for about 40 s
after boot: :meth:`Vehicle.takeoff` first waits until the vehicle is armable
(:meth:`~firmware_bridge.session.Session.wait_ready`, up to ``ready_timeout``) and
tries a refused arm again within that time. Mode changes, arming and OFFBOARD are verified
on the next heartbeats, not only by the ACK (PX4 accepts OFFBOARD while disarmed
without a stream); a refusal raises :class:`CommandRejected` with the autopilot's
STATUSTEXT. Facts from the autopilots' sources: PX4's commander (UserModeIntention,
offboard checks) and mavlink_receiver, ArduCopter's GCS_MAVLink_Copter and mode_guided.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import time
from collections.abc import Callable, Sequence

from firmware_bridge.commands import (
    FORCE_ARM_ARDUPILOT,
    FORCE_MAGIC_PX4,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_RESULT_ACCEPTED,
    command_name,
)
from firmware_bridge.connection import COMPANION_COMPONENT, Endpoint, open_link, parse_url, signing_timestamp
from firmware_bridge.errors import (
    BridgeError,
    CommandRejected,
    ConnectError,
    FlightInterrupted,
    SetpointError,
)
from firmware_bridge.modes import canonical_mode, encode_mode
from firmware_bridge.px4_metadata import find_metadata, load_catalog
from firmware_bridge.session import NotReady, Options, Session, WaitTimeout, check_timeout
from firmware_bridge.setpoints import (
    GlobalTarget,
    LocalTarget,
    setpoint_message,
    validate_global,
    validate_local,
    validate_takeoff_altitude,
)
from firmware_bridge.telemetry import LANDED_ON_GROUND, StatusText, VehicleState, interruption

__all__ = [  # the public names stay importable from here (swarm and the README use them)
    "COMPANION_COMPONENT",
    "MAV_CMD_COMPONENT_ARM_DISARM",
    "MAV_CMD_DO_SET_MODE",
    "MAV_CMD_NAV_TAKEOFF",
    "MAV_CMD_REQUEST_MESSAGE",
    "MAV_CMD_SET_MESSAGE_INTERVAL",
    "Endpoint",
    "GlobalTarget",
    "LocalTarget",
    "NotReady",
    "SetpointError",
    "StatusText",
    "Vehicle",
    "VehicleState",
    "WaitTimeout",
    "connect",
    "parse_url",
    "setpoint_message",
    "signing_timestamp",
    "validate_global",
    "validate_local",
]


ARM_RETRY_S = 2.0  # the least time between two tries of a refused arm (takeoff)
ON_GROUND_M = 1.0  # below this height above home a vehicle not reported in the air is on the ground
PX4_TAKEOFF_SHORT_M = 1.5  # PX4 may end a take-off this far below its altitude (NAV_MC_ALT_RAD + its drift)

log = logging.getLogger("firmware_bridge.driver")


# --- the vehicle -----------------------------------------------------------------------
class Vehicle(Session):
    """A connected flight controller. Made by :func:`connect`; a context manager.

    The telemetry, waits, commands and lifetime come from
    :class:`~firmware_bridge.session.Session`; this class is the flight API.
    """

    # -- modes
    def set_mode(self, name: str) -> None:
        """Switch flight mode by name (PX4 ``OFFBOARD``, ``AUTO.LOITER``...; ArduPilot
        ``GUIDED``, ``LOITER``...; aliases HOLD, RTL, LAND) and verify it on the heartbeat.

        Raises:
            UnknownMode: no such mode on this autopilot.
            CommandRejected: refused, or accepted but the heartbeat never shows it.
            CommandTimeout: never acknowledged.
        """
        key = canonical_mode(self.autopilot, name)
        self.command(MAV_CMD_DO_SET_MODE, encode_mode(self.autopilot, key))
        try:
            self.wait_for(lambda s: s.mode == key, self._opts.mode_timeout, f"mode {key}")
        except WaitTimeout:
            text = self._texts_since(time.monotonic() - self._opts.mode_timeout)
            raise CommandRejected(
                f"mode {key} accepted but the heartbeat still shows "
                f"{self.state.mode}" + (f" ({text})" if text else ""),
                command=MAV_CMD_DO_SET_MODE,
                result=MAV_RESULT_ACCEPTED,
                text=text,
            ) from None

    # -- arming, takeoff, landing
    def arm(self, force: bool = False) -> None:
        """Arm and wait until the heartbeat shows it.

        Raises:
            CommandRejected: arming refused (text says why), or not armed after the ACK.
            CommandTimeout: never acknowledged.
        """
        magic = 0 if not force else (FORCE_MAGIC_PX4 if self.autopilot == "px4" else FORCE_ARM_ARDUPILOT)
        try:
            self.command(MAV_CMD_COMPONENT_ARM_DISARM, (1, magic))
        except CommandRejected as e:
            said = e.text.split("; ") if e.text else []
            checks = tuple(c for c in self.state.checks if c not in said)
            if not checks or e.result == MAV_RESULT_ACCEPTED:
                raise
            # PX4's refusal says only "Resolve system health failures first": the
            # failing checks are in its latest arming check report (its events)
            raise CommandRejected(
                f"{e} [arming checks: {', '.join(checks)}]",
                command=e.command,
                result=e.result,
                text="; ".join([*said, *checks]),
            ) from None
        self._verify(lambda s: s.armed, "armed", MAV_CMD_COMPONENT_ARM_DISARM)

    def disarm(self, force: bool = False) -> None:
        """Disarm (``force`` also in the air: the motors stop!) and verify it."""
        self.command(MAV_CMD_COMPONENT_ARM_DISARM, (0, FORCE_MAGIC_PX4 if force else 0))
        self._verify(lambda s: not s.armed, "disarmed", MAV_CMD_COMPONENT_ARM_DISARM)

    def _verify(self, pred: Callable[[VehicleState], bool], what: str, command: int) -> None:
        try:
            self.wait_for(pred, self._opts.mode_timeout, what)
        except WaitTimeout:
            raise CommandRejected(
                f"{command_name(command)} accepted but the vehicle is not {what}",
                command=command,
                result=MAV_RESULT_ACCEPTED,
                text=self._texts_since(time.monotonic() - 3.0),
            ) from None

    def home_amsl(self, timeout: float = 3.0) -> float:
        """Home altitude AMSL: HOME_POSITION, else GLOBAL_POSITION_INT alt - relative_alt
        once that position is valid (before its fix ArduPilot reports 0 for both).

        Raises:
            WaitTimeout: neither known within ``timeout``.
        """
        s = self.wait_for(
            lambda s: (
                s.home is not None or (s.position_valid and s.alt_amsl is not None and s.rel_alt is not None)
            ),
            timeout,
            "home position",
        )
        if s.home is not None:
            return s.home[2]
        assert s.alt_amsl is not None and s.rel_alt is not None
        return s.alt_amsl - s.rel_alt

    def takeoff(
        self, rel_alt_m: float, *, wait: bool = True, timeout: float = 60.0, ready_timeout: float = 90.0
    ) -> None:
        """Take off to ``rel_alt_m`` above home, arming first if needed.

        Unless armed already, waits first (up to ``ready_timeout`` s) until the vehicle
        is armable (:meth:`wait_ready`: a real autopilot refuses for about 40 s after
        boot) and tries arming again while the autopilot refuses it within that time.
        PX4: MAV_CMD_NAV_TAKEOFF with param7 AMSL (home + rel). ArduPilot: GUIDED,
        arm, NAV_TAKEOFF with param7 relative. ``wait`` waits for the altitude.

        Raises:
            SetpointError: altitude not finite or out of 0.5..MAX_ALT_M.
            BridgeError: ``ready_timeout`` not a finite number of seconds >= 0.
            NotReady: not armable within ``ready_timeout``.
            CommandRejected, CommandTimeout: from the mode change, arming or takeoff.
            WaitTimeout: the altitude is not reached in ``timeout``.
            FlightInterrupted: the vehicle disarmed in the air, or twice on the ground
                (once is tried again: PX4 disarms by itself just after a landing).
        """
        alt = validate_takeoff_altitude(rel_alt_m)
        ready_by = time.monotonic() + check_timeout(ready_timeout, "ready_timeout")
        self._takeoff_once(alt, ready_by)
        if not wait:
            return
        for again in (False, True):
            before = self.state  # armed: the take-off was accepted
            try:
                self.wait_for(
                    _TakeoffDone(self.autopilot, alt),
                    timeout,
                    f"takeoff altitude {alt:g} m",
                    interrupt=functools.partial(interruption, before),
                )
                return
            except FlightInterrupted as e:
                s = e.state if isinstance(e.state, VehicleState) else self.state
                on_ground = not s.in_air and (s.rel_alt is None or s.rel_alt < ON_GROUND_M)
                if again or s.armed or not on_ground:
                    raise
                # PX4 disarms by itself about a second after a landing (COM_DISARM_LAND):
                # a take-off sent in that second is accepted, then the motors stop.
                log.info("takeoff: %s before leaving the ground; arming again", e)
                self._takeoff_once(alt, ready_by)

    def _takeoff_once(self, alt: float, ready_by: float) -> None:
        """Arm if needed (waiting until armable, until ``ready_by``) and send the take-off."""
        if not self.state.armed:
            self.wait_ready(max(0.0, ready_by - time.monotonic()))
        if self.autopilot == "ardupilot":
            self.set_mode("GUIDED")
            if not self.state.armed:
                self._arm_by(ready_by)
            self.command(MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, alt))
        else:
            amsl = self.home_amsl() + alt
            if not self.state.armed:
                self._arm_by(ready_by)
            nan = math.nan
            self.command(MAV_CMD_NAV_TAKEOFF, (0, 0, 0, nan, nan, nan, amsl))

    def _arm_by(self, deadline: float) -> None:
        """Arm; while the autopilot refuses (its pre-arm checks lag its reports by up to
        a second or two) and ``deadline`` is more than a retry away, wait until it looks
        armable again and try once more (every ``ARM_RETRY_S`` at most)."""
        while True:
            tried = time.monotonic()
            try:
                self.arm()
                return
            except CommandRejected as e:
                if e.result == MAV_RESULT_ACCEPTED or deadline - time.monotonic() < ARM_RETRY_S:
                    raise
            with contextlib.suppress(WaitTimeout):  # a pause between tries, woken early by closing
                self.wait_for(lambda s: self._closed, max(0.0, tried + ARM_RETRY_S - time.monotonic()))
            self.wait_ready(max(0.0, deadline - time.monotonic()))

    def land(self, *, wait: bool = False, timeout: float = 120.0) -> None:
        """Stop the setpoints and land where the vehicle is (PX4 AUTO.LAND, AP LAND)."""
        self._streamer.stop()
        self.set_mode("LAND")
        if wait:
            self.wait_for(lambda s: s.landed_state == LANDED_ON_GROUND or not s.armed, timeout, "landed")

    def return_to_launch(self) -> None:
        """Stop the setpoints and return home (PX4 AUTO.RTL, ArduPilot RTL)."""
        self._streamer.stop()
        self.set_mode("RTL")

    def hold(self) -> None:
        """Hold position: PX4 AUTO.LOITER; ArduPilot GUIDED at the current position
        (LOITER needs RC throttle, which a companion-only vehicle lacks)."""
        if self.autopilot == "ardupilot":
            s = self.state
            if s.mode != "GUIDED":
                self.set_mode("GUIDED")
            if s.ned is not None and s.in_air:
                self.set_target_ned(*s.ned, yaw=s.yaw)
            return
        self._streamer.stop()
        self.set_mode("AUTO.LOITER")

    # -- position control
    def set_target_ned(
        self,
        north: float,
        east: float,
        down: float,
        yaw: float | None = None,
        velocity: Sequence[float] | None = None,
    ) -> None:
        """Stream SET_POSITION_TARGET_LOCAL_NED to this point (z down, EKF origin);
        yaw defaults to the current heading. Starts the streamer if needed.

        Raises:
            SetpointError: NaN, inf or out of range; nothing is sent.
        """
        target = validate_local(north, east, down, self.state.yaw if yaw is None else yaw, velocity)
        self._set_target(target)

    def set_target_global(
        self,
        lat: float,
        lon: float,
        rel_alt: float,
        yaw: float | None = None,
        velocity: Sequence[float] | None = None,
    ) -> None:
        """Stream SET_POSITION_TARGET_GLOBAL_INT (altitude above home) to this point,
        with an optional NED velocity feed-forward (m/s) for a moving target.

        Raises:
            SetpointError: NaN, inf or out of range; nothing is sent.
        """
        target = validate_global(lat, lon, rel_alt, self.state.yaw if yaw is None else yaw, velocity)
        self._set_target(target)

    @property
    def target(self) -> LocalTarget | GlobalTarget | None:
        return self._streamer.target

    @property
    def streaming(self) -> bool:
        return self._streamer.streaming

    def _set_target(self, target: LocalTarget | GlobalTarget) -> None:
        if self._closed:
            raise BridgeError("vehicle connection closed")
        self._streamer.set(target)

    def stop_setpoints(self) -> None:
        """Stop the setpoint stream (PX4 then leaves OFFBOARD after COM_OF_LOSS_T)."""
        self._streamer.stop()

    def take_control(self, *, stream_first: float = 1.0) -> None:
        """Take the vehicle back under setpoint control after its autopilot left it by
        itself (PX4's setpoint-loss failsafe: AUTO.LOITER or AUTO.LAND; RC; a landing):
        hold where it is now (a fresh setpoint stream at its current position, never an
        older target), then OFFBOARD (PX4, after ``stream_first`` s of stream) or GUIDED
        (ArduPilot), verified on the heartbeat.

        Raises:
            FlightInterrupted: on the ground or disarmed (take off instead), or no local
                position to hold.
            CommandRejected, CommandTimeout: the autopilot refused the mode.
        """
        s = self.state
        if not s.armed or not s.in_air:
            raise FlightInterrupted("cannot take control back: the vehicle is not flying (take off)", state=s)
        if s.ned is None:
            raise FlightInterrupted("cannot take control back: no local position to hold", state=s)
        self.set_target_ned(*s.ned, yaw=s.yaw)  # here, now: not a target from before the failsafe
        if self.autopilot == "px4":
            started = time.monotonic()
            sent = self.setpoints_sent
            self.wait_for(
                lambda _s: time.monotonic() - started >= stream_first and self.setpoints_sent >= sent + 3,
                stream_first + 5.0,
                "setpoint stream",
            )
            self.set_mode("OFFBOARD")
        else:
            self.set_mode("GUIDED")

    def start_offboard(
        self, *, takeoff_alt: float = 2.5, stream_first: float = 1.0, timeout: float = 60.0
    ) -> None:
        """Put the vehicle under setpoint control.

        Takes off first if on the ground (to ``takeoff_alt``); holds the current
        position if no target is set. PX4: streams ``stream_first`` s, then OFFBOARD
        (verified on the heartbeat). ArduPilot: GUIDED.

        Raises:
            CommandRejected, CommandTimeout, WaitTimeout: as the steps it takes.
        """
        if not self.state.in_air:
            self.takeoff(takeoff_alt, wait=True, timeout=timeout)
        if self.target is None:  # ArduPilot sends it only once its EKF uses the GPS
            s = self.wait_for(lambda s: s.ned is not None, timeout, "local position")
            assert s.ned is not None
            self.set_target_ned(*s.ned, yaw=s.yaw)
        if self.autopilot == "px4":
            self.wait_for(
                lambda s: (
                    time.monotonic() - self._streamer.started >= stream_first and self.setpoints_sent >= 3
                ),
                stream_first + 5.0,
                "setpoint stream",
            )
            self.set_mode("OFFBOARD")
        else:
            self.set_mode("GUIDED")


# --- connect ---------------------------------------------------------------------------
class _TakeoffDone:
    """When a take-off to ``alt`` m is done: within 5 % (at least 0.5 m) of it; or, on
    PX4, when PX4 itself ends its take-off (AUTO.TAKEOFF, then its hold mode on its own)
    within PX4_TAKEOFF_SHORT_M of it. PX4 ends a take-off within NAV_MC_ALT_RAD (0.8 m)
    of the altitude by its own estimate and holds there: measured on PX4 v1.15 SITL,
    8.99 m of 10 for good (the 0.5 m rule waited out its timeout)."""

    def __init__(self, autopilot: str, alt: float) -> None:
        self.px4, self.alt = autopilot == "px4", alt
        self.climbing = False  # PX4 was seen in AUTO.TAKEOFF

    def __call__(self, s: VehicleState) -> bool:
        if s.rel_alt is None:
            return False
        if s.rel_alt >= self.alt - max(0.5, 0.05 * self.alt):
            return True
        if not self.px4:
            return False
        if s.mode == "AUTO.TAKEOFF":
            self.climbing = True
            return False
        return self.climbing and s.mode == "AUTO.LOITER" and s.rel_alt >= self.alt - PX4_TAKEOFF_SHORT_M


def connect(
    url: str,
    *,
    timeout: float = 10.0,
    source_system: int | None = None,
    source_component: int = COMPANION_COMPONENT,
    signing_key: bytes | None = None,
    link_timeout: float = 2.0,
    on_link_lost: Callable[[], object] | None = None,
    on_link_restored: Callable[[], object] | None = None,
    setpoint_rate_hz: float = 10.0,
    command_retries: int = 3,
    command_timeout: float = 1.0,
    telemetry_rate_hz: float = 10.0,
    mode_timeout: float = 3.0,
    request_telemetry: bool = True,
    px4_events: str | os.PathLike[str] | None = None,
) -> Vehicle:
    """Open ``url``, wait for the autopilot's heartbeat and return the :class:`Vehicle`.

    The companion's own messages use ``source_system`` (default: the vehicle's sysid)
    and ``source_component`` (191). ``signing_key`` (32 bytes) signs everything sent
    and accepts only signed messages (and unsigned RADIO_STATUS). With
    ``request_telemetry`` false the vehicle's own stream rates are left alone
    (ArduPilot then sends nothing but heartbeats). ``px4_events`` is PX4's event
    metadata (``all_events.json[.xz]``; else ``$PX4_EVENTS``, else the SITL folder's:
    :mod:`firmware_bridge.px4_metadata`): PX4's reasons, sent as events, in words.

    Raises:
        ConnectError: malformed URL, missing device, unresolvable host, bad arguments,
            an unreadable ``px4_events`` file.
        HeartbeatTimeout: no autopilot heartbeat within ``timeout`` s.
    """
    ep = parse_url(url)
    _check_arguments(signing_key, setpoint_rate_hz, timeout, link_timeout)
    metadata = find_metadata(px4_events)
    events = load_catalog(metadata) if metadata is not None else None  # before anything is opened
    conn, hb = open_link(
        ep,
        timeout=timeout,
        source_system=source_system if source_system is not None else 1,  # provisional
        source_component=source_component,
        signing_key=signing_key,
    )
    opts = Options(
        link_timeout=link_timeout,
        on_link_lost=on_link_lost,
        on_link_restored=on_link_restored,
        setpoint_rate_hz=setpoint_rate_hz,
        command_retries=max(1, command_retries),
        command_timeout=command_timeout,
        telemetry_rate_hz=telemetry_rate_hz,
        mode_timeout=mode_timeout,
        events=events,
    )
    vehicle = Vehicle(conn, ep, hb, opts, source_system, source_component)
    try:
        if request_telemetry:
            vehicle.request_telemetry()
    except BaseException:
        vehicle.close()
        raise
    return vehicle


def _check_arguments(
    signing_key: bytes | None, setpoint_rate_hz: float, timeout: float, link_timeout: float
) -> None:
    """Raises ConnectError for a bad argument of :func:`connect` (nothing is opened yet)."""
    if signing_key is not None and (not isinstance(signing_key, bytes | bytearray) or len(signing_key) != 32):
        raise ConnectError("signing_key must be 32 bytes")
    if not 1.0 <= setpoint_rate_hz <= 200.0:
        raise ConnectError(f"setpoint_rate_hz {setpoint_rate_hz} outside 1..200 Hz")
    if timeout <= 0 or link_timeout <= 0:
        raise ConnectError("timeout and link_timeout must be positive")
