"""Issue 17, items 1-2: a boot-aware driver. A real ArduPilot sends GLOBAL_POSITION_INT
at 0, 0, 0 for seconds after boot, sets home at about 20 s and refuses to arm for about
40 s. The driver's pure rules (:func:`~firmware_bridge.telemetry.position_problem`,
:func:`~firmware_bridge.telemetry.arming_problems`) are fed messages built here and the
boot recorded from a real ArduCopter SITL (``tests/data/traces/``); then the recorded
autopilot side is played over a real TCP socket to the driver and to an agent, which
must publish no pose before the fix and say "waiting for position" once; and the driver
flies the vehicle simulator when asked to take off before the GPS has a fix.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port, wait_until
from pymavlink.dialects.v20 import ardupilotmega

from firmware_bridge import driver as drv
from firmware_bridge.errors import BridgeError, CommandRejected
from firmware_bridge.telemetry import (
    NO_POSITION_YET,
    TelemetryFolder,
    VehicleState,
    arming_problems,
)
from radios.tlog import read_tlog
from swarm.core.agent.node import (
    POSITION_VALID,
    WAITING_FOR_POSITION,
    AgentNode,
    EventOut,
    OwnPose,
    PositionFix,
)
from swarm.core.election.outbox import NO_POSE
from swarm.core.election.profiles import profile_by_name
from swarm.core.wire.message_types import Pose
from swarm.runtime.agent.vehicle import pose_from_state, vehicle_messages

mavlink: Any = ardupilotmega
TRACES = Path(__file__).parent / "data" / "traces"
FLIGHT, EDGES = "ardupilot-sitl-flight.tlog", "ardupilot-sitl-edges.tlog"
AUTOPILOT = (1, 1)  # the autopilot's system and component in the traces


def trace(name: str) -> list[tuple[float, bytes]]:
    """(seconds since the first record, raw frame) of the autopilot's frames."""
    out, t0 = [], None
    for rec in read_tlog(TRACES / name):
        t0 = rec.t if t0 is None else t0
        if (rec.raw[5], rec.raw[6]) == AUTOPILOT:  # MAVLink 2 header: sysid, compid
            out.append((rec.t - t0, rec.raw))
    return out


def folded(name: str) -> list[tuple[float, VehicleState]]:
    """The driver's snapshot after each of the autopilot's recorded messages."""
    f = TelemetryFolder("ardupilot", target_system=1, target_component=1, own_system=1)
    rx, out = mavlink.MAVLink(None), []
    for t, raw in trace(name):
        for msg in rx.parse_buffer(raw) or []:
            f.fold(msg, t)
            out.append((t, f.state))
    return out


def first(states: list[tuple[float, VehicleState]], pred: Any) -> float:
    return next(t for t, s in states if pred(s))


# --- the pure rules, on the recorded boot ------------------------------------------------
@pytest.mark.parametrize("name", [FLIGHT, EDGES])
def test_no_valid_position_before_the_fix_and_home_in_the_recorded_boot(name: str) -> None:
    states = folded(name)
    null_island = [t for t, s in states if s.lat == 0.0 and s.lon == 0.0]
    assert len(null_island) > 30  # the recording does hold ArduPilot's 0, 0, 0 positions ...
    assert not any(s.position_valid for t, s in states if t <= null_island[-1])  # ... none valid
    fix = first(states, lambda s: s.gps_ok)
    valid = first(states, lambda s: s.position_valid)
    home = first(states, lambda s: s.home is not None)
    assert 9.5 < fix < 11.0 and 19.5 < home < 20.5  # the trace's facts
    assert valid == home  # the position counts once the fix and the home are both there
    assert all(s.position_valid for t, s in states if t >= valid)  # and stays valid
    # what the driver said meanwhile, in order
    reasons = list(dict.fromkeys(s.position_reason for t, s in states))
    assert reasons[:2] == [NO_POSITION_YET, "the autopilot reports no position (0, 0)"]
    assert reasons[-2:] == ["no home position yet", ""]
    assert set(reasons[2:-2]) <= {"no GPS fix"}  # the fix's GPS_RAW_INT may follow its position
    # and what the agent would have sent: no pose before the fix, none at 0, 0
    poses = [(t, pose_from_state(s, t)) for t, s in states]
    assert all(p is None for t, p in poses if t < valid)
    assert not any(p is not None and p.lat == 0.0 and p.lon == 0.0 for _, p in poses)
    assert all(len(vehicle_messages(s)) == 1 for t, s in states if t < valid)  # no GLOBAL_POSITION_INT


def test_armable_only_when_the_recorded_autopilot_says_so() -> None:
    states = folded(FLIGHT)
    local = first(states, lambda s: s.ned is not None)
    armable = first(states, lambda s: not arming_problems(s))
    assert 41.0 < local < 42.0  # LOCAL_POSITION_NED starts when the EKF uses the GPS
    assert local <= armable < 43.5  # ... and SYS_STATUS's pre-arm bit follows within ~1 s
    assert arming_problems(states[0][1]) == [
        "autopilot still booting",
        NO_POSITION_YET,
        "no local position yet",
    ]
    at_30 = next(s for t, s in states if t >= 30.0)
    assert arming_problems(at_30) == ["no local position yet", "pre-arm checks failing"]
    # the edges trace: LAND needs no position, so its pre-arm checks pass at 23.6 s and
    # fail again a second after the switch to GUIDED (SYS_STATUS is heard from 6.6 s on)
    edges = [(t, s) for t, s in folded(EDGES) if s.prearm_ok is not None]
    no_position_needed = [t for t, s in edges if t < 41.0 and not arming_problems(s, position=False)]
    assert no_position_needed and 23.0 < no_position_needed[0] < 24.0 and no_position_needed[-1] < 25.0


# --- the pure rules, on hostile and odd messages -------------------------------------------
class Wire:
    """Builds an autopilot's (1/1) messages as real MAVLink 2 bytes and parses them back."""

    def __init__(self) -> None:
        self.mav, self.rx = mavlink.MAVLink(None, srcSystem=1, srcComponent=1), mavlink.MAVLink(None)

    def __call__(self, msg: Any) -> Any:
        (got,) = self.rx.parse_buffer(msg.pack(self.mav))
        return got

    def gpi(self, lat: float, lon: float, alt: float = 584.0) -> Any:
        return self(
            mavlink.MAVLink_global_position_int_message(
                1, round(lat * 1e7), round(lon * 1e7), round(alt * 1e3), 0, 0, 0, 0, 0
            )
        )

    def gps(self, fix: int) -> Any:
        return self(mavlink.MAVLink_gps_raw_int_message(0, fix, 0, 0, 0, 100, 100, 0, 0, 9))

    def home(self, lat: float, lon: float) -> Any:
        return self(
            mavlink.MAVLink_home_position_message(
                round(lat * 1e7), round(lon * 1e7), 584_000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0
            )
        )

    def sys_status(self, present: int, health: int) -> Any:
        return self(
            mavlink.MAVLink_sys_status_message(present, present, health, 0, 12_600, -1, 80, 0, 0, 0, 0, 0, 0)
        )

    def ekf(self, flags: int) -> Any:
        return self(mavlink.MAVLink_ekf_status_report_message(flags, 0, 0, 0, 0, 0))


def fed(*msgs: Any) -> VehicleState:
    f = TelemetryFolder("ardupilot", target_system=1, target_component=1, own_system=1)
    for i, m in enumerate(msgs):
        f.fold(m, float(i))
    return f.state


def test_a_position_needs_a_fix_a_home_and_the_ekf() -> None:
    w = Wire()
    good = (w.gps(3), w.home(-35.36, 149.16), w.gpi(-35.36, 149.16))
    assert fed(*good).position_valid and fed(*good).position_reason == ""
    assert fed(w.gpi(-35.36, 149.16)).position_reason == "no GPS report yet"
    assert fed(w.gps(2), *good[1:]).position_reason == "no GPS fix"  # a 2D fix is not enough
    assert fed(w.gps(3), w.gpi(-35.36, 149.16)).position_reason == "no home position yet"
    assert fed(w.gps(3), w.home(0, 0), w.gpi(-35.36, 149.16)).position_reason == "home is 0, 0"
    # a 3D fix and a home do not make 0, 0 a position
    assert fed(w.gps(6), w.home(-35.36, 149.16), w.gpi(0, 0, 0)).position_reason.endswith("(0, 0)")
    # the EKF, when it reports, must have an absolute horizontal position (flag 16)
    assert fed(*good, w.ekf(0x1 | 0x2 | 0x4 | 0x8 | 0x80)).position_reason == "EKF has no absolute position"
    assert fed(*good, w.ekf(0x1 | 0x2 | 0x4 | 0x8 | 0x10)).position_valid
    # GPS health from SYS_STATUS when there is no GPS_RAW_INT; the pre-arm bit when present
    gps, prearm = 32, 0x10000000
    s = fed(w.sys_status(gps | prearm, gps), *good[1:])
    assert s.position_valid and s.prearm_ok is False and "pre-arm checks failing" in arming_problems(s)
    assert fed(w.sys_status(gps, gps)).prearm_ok is None  # not reported: nothing said against it
    # a fix that is lost makes the same position invalid again
    assert not fed(*good, w.gps(0)).position_valid


def test_the_node_says_waiting_for_position_once_and_forgets_a_lost_fix() -> None:
    node = AgentNode(5, "boot", profile_by_name("fast", 0.3), has_fc=True)
    node.start(0.0)

    def events(ev: object, t: float) -> list[str]:
        return [o.text for o in node.handle(ev, t) if isinstance(o, EventOut)]

    assert events(PositionFix(False, "no GPS fix"), 1.0) == [f"{WAITING_FOR_POSITION} (no GPS fix)"]
    assert events(PositionFix(False, "no home position yet"), 2.0) == []  # said once
    assert node.telemetry().pose == NO_POSE
    assert events(PositionFix(True), 3.0) == [POSITION_VALID]
    assert events(PositionFix(True), 3.1) == []
    node.handle(OwnPose(Pose(-35.36, 149.16, 584.0, 0.0), False), 3.2)
    assert node.telemetry().pose.lat == -35.36
    assert events(PositionFix(False, "no GPS fix"), 4.0) == [f"{WAITING_FOR_POSITION} (no GPS fix)"]
    assert node.telemetry().pose == NO_POSE  # the last fix is not sent as if it were current


# --- the recorded autopilot over a real socket ---------------------------------------------
class TracePlayer:
    """Plays a trace's autopilot frames to the first TCP client, ``speed`` times faster
    than recorded; holds at each of ``hold_at`` (trace seconds) until :meth:`go`
    (``holding`` says where it waits), and stops at ``until``. What the client sends is
    read and dropped (nothing answers it)."""

    def __init__(self, name: str, *, speed: float, hold_at: float | tuple[float, ...], until: float) -> None:
        self.frames = [(t, raw) for t, raw in trace(name) if t <= until]
        self.speed = speed
        self.holds = sorted(hold_at if isinstance(hold_at, tuple) else (hold_at,))
        self.holding: float | None = None
        self.port = free_port()
        self._srv = socket.create_server(("127.0.0.1", self.port))
        self._go, self._stop = threading.Semaphore(0), threading.Event()
        self.played_to = 0.0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def go(self) -> None:
        """Release the hold the replay is at (or the next one it reaches)."""
        self._go.release()

    def _hold(self, at: float) -> bool:
        """Wait at ``at`` for :meth:`go`; False once closed."""
        self.holding = at
        while not self._go.acquire(timeout=0.1):
            if self._stop.is_set():
                return False
        self.holding = None
        return True

    def _run(self) -> None:
        self._srv.settimeout(30.0)
        conn, _ = self._srv.accept()
        conn.setblocking(False)
        with conn:
            start = time.monotonic()
            holds = list(self.holds)
            for t, raw in self.frames:
                while holds and t > holds[0]:
                    at = holds.pop(0)
                    if not self._hold(at):
                        return
                    start = time.monotonic() - at / self.speed
                if self._stop.wait(max(0.0, start + t / self.speed - time.monotonic())):
                    return  # recorded gaps, sped up: the pacing of a replay
                try:
                    conn.sendall(raw)
                except (ConnectionResetError, BrokenPipeError):
                    return  # the driver closed its side: the replay is over
                self.played_to = t
                try:
                    conn.recv(65536)  # the driver's requests: drop them
                except BlockingIOError:
                    pass
                except OSError:
                    return  # reset by the driver closing its side: the replay is over
            self._stop.wait()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self._srv.close()


def _refusal(v: Any) -> drv.NotReady:
    """Why the vehicle is not ready now (it must not be)."""
    with pytest.raises(drv.NotReady) as err:
        v.wait_ready(0.1)
    return err.value


@pytest.fixture
def player() -> Iterator[Any]:
    made: list[TracePlayer] = []

    def make(name: str, **kw: Any) -> TracePlayer:
        made.append(TracePlayer(name, **kw))
        return made[-1]

    yield make
    for p in made:
        p.close()


@pytest.mark.processes
def test_wait_ready_gives_the_recorded_refusals_then_returns_when_armable(player: Any) -> None:
    p = player(FLIGHT, speed=8.0, hold_at=(1.0, 30.0), until=45.0)
    with drv.connect(f"tcp:127.0.0.1:{p.port}", timeout=15.0) as v:
        for bad in (math.nan, math.inf, -1.0, "5", True):  # a caller's mistake, refused at once
            with pytest.raises(BridgeError, match="finite number of seconds"):
                v.wait_ready(bad)
            with pytest.raises(BridgeError, match="finite number of seconds"):
                v.takeoff(5.0, ready_timeout=bad)
        with pytest.raises(drv.NotReady) as err:
            v.wait_ready(0.1)
        assert "autopilot still booting" in err.value.problems
        p.go()
        # held at 30 s (the replay would reach the fix 1.4 s later): the driver has the
        # state of 30 s once it has read what was sent
        wait_until(lambda: p.holding == 30.0, "the replay held at 30 s", 60.0)
        refused = ["no local position yet", "pre-arm checks failing"]
        wait_until(lambda: _refusal(v).problems == refused, "the refusals of 30 s", 30.0)
        err_30 = _refusal(v)
        assert "Arm: Need Position Estimate" in err_30.texts  # the autopilot's own words
        assert "Arm: Need Position Estimate" in str(err_30)
        p.go()
        s = v.wait_ready(60.0)
        assert s.position_valid and s.ned is not None and s.prearm_ok
        assert p.played_to > 41.0


@pytest.mark.processes
def test_an_agent_sends_no_pose_before_the_fix_and_says_so(player: Any) -> None:
    from swarm.core.flight.pilot import Call
    from swarm.core.wire.message_types import PoseReport
    from swarm.runtime.agent.live import Agent
    from swarm.runtime.keyspace.transport import Transport
    from swarm.runtime.options import AgentConfig, NodeOptions

    p = player(FLIGHT, speed=8.0, hold_at=1.0, until=24.0)
    ep = f"tcp/127.0.0.1:{free_port()}"
    events: list[str] = []
    poses: list[tuple[float, PoseReport]] = []  # (how far the replay was, the pose)
    with (
        Transport.open("observer", listen=[ep]) as obs,
        Agent(
            "booting",
            5,
            NodeOptions(zenoh_connect=[ep]),
            fc=f"tcp:127.0.0.1:{p.port}",
            config=AgentConfig(profile="fast", pose_hz=10),
            on_event=events.append,
        ) as a,
    ):
        states: list[Any] = []
        obs.on_pose("booting", lambda _n, r: poses.append((p.played_to, r)))
        obs.on_state("booting", lambda _n, st: states.append(st))
        wait_until(lambda: states, "the agent's state at the observer", 30.0)
        # a take-off order while the autopilot boots is refused within seconds, with why
        with pytest.raises(drv.NotReady, match="autopilot still booting"):
            a._do_call(Call("takeoff", 10.0))  # noqa: SLF001 (white box: the agent's own call)
        p.go()  # the recorded boot from here: 0, 0, 0 positions, the fix, home at 19.9 s
        wait_until(lambda: POSITION_VALID in events, "'position valid'", 60.0)
        wait_until(lambda: poses, "a pose after the fix", 30.0)
        waiting = [e for e in events if e.startswith(WAITING_FOR_POSITION)]
        assert len(waiting) == 1 and events.index(waiting[0]) < events.index(POSITION_VALID)
        assert a.stats["poses_withheld"] > 10  # every round before the fix
        assert poses[0][0] > 19.5  # no pose before home, and so none before the fix
        assert all(-36.0 < r.pose.lat < -35.0 and 149.0 < r.pose.lon < 150.0 for _, r in poses)


# --- take-off asked for before the vehicle is armable --------------------------------------
@pytest.mark.processes
@pytest.mark.parametrize("profile", ["px4", "ardupilot"])
def test_takeoff_waits_until_armable_instead_of_failing(profile: str) -> None:
    """The simulator with its GPS failed refuses to arm; takeoff() asked for then waits
    (before: CommandRejected at once) and climbs once the GPS is back."""
    from firmware_bridge import sim as sim_mod

    port = free_port("udp" if profile == "px4" else "tcp")
    sim = sim_mod.VehicleSim(
        sim_mod.SimConfig(vehicles=1, profile=profile, speedup=4.0, seed=0, base_port=port)
    )
    try:
        (endpoint,) = sim.start()
        sim.vehicle(0).fail_gps(True)
        with drv.connect(endpoint, timeout=15.0, setpoint_rate_hz=25.0) as v:
            outcome: list[BaseException | None] = []

            def fly() -> None:
                try:
                    v.takeoff(5.0, timeout=60.0, ready_timeout=60.0)
                    outcome.append(None)
                except BaseException as e:  # handed to the test thread
                    outcome.append(e)

            flyer = threading.Thread(target=fly, daemon=True)
            flyer.start()
            wait_until(lambda: v.state.gps_known and not v.state.gps_ok, "the driver told 'no fix'", 30.0)
            assert not outcome and not v.state.armed  # waiting, not refused
            sim.vehicle(0).fail_gps(False)
            flyer.join(90.0)
            assert outcome == [None]
            # PX4 ends a take-off itself within NAV_MC_ALT_RAD of it: done from there
            low = 5.0 - (drv.PX4_TAKEOFF_SHORT_M if profile == "px4" else 0.5)
            assert v.state.armed and v.state.rel_alt is not None and v.state.rel_alt > low
    finally:
        sim.stop()


def test_an_impossible_position_is_no_position_and_never_an_error() -> None:
    """An autopilot (or a corrupted stream) reporting 95 N, 200 E or 9 km up: the driver
    does not vouch for an impossible latitude or longitude, and the agent's pose is None,
    never an exception in its pose thread."""
    w = Wire()
    fix_home = (w.gps(3), w.home(-35.36, 149.16))
    for lat, lon in ((95.0, 149.16), (-35.36, 200.0), (-35.36, -181.0)):
        s = fed(*fix_home, w.gpi(lat, lon))
        assert not s.position_valid and s.position_reason == "position out of range"
        assert pose_from_state(s, 1.0) is None and len(vehicle_messages(s)) == 1
    s = fed(w.gps(3), w.home(95.0, 0.0), w.gpi(-35.36, 149.16))
    assert s.position_reason == "home out of range"
    high = fed(*fix_home, w.gpi(-35.36, 149.16, alt=9000.0))
    assert high.position_valid and pose_from_state(high, 1.0) is None  # beyond what a Pose carries


class ScriptedArduPilot:
    """A booted ArduCopter in a few lines: GUIDED, a 3D fix, home, local position and a
    passing pre-arm bit, refusing the first ``refusals`` arms with "Arm: Gyros
    inconsistent" (its pre-arm checks lag its reports) and accepting the next."""

    def __init__(self, port: int, refusals: int) -> None:
        from pymavlink import mavutil

        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
        )
        self.refusals, self.armed, self.arms = refusals, False, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _telemetry(self) -> None:
        mav, lat, lon = self.conn.mav, -353632610, 1491652300
        mav.heartbeat_send(2, 3, 217 if self.armed else 89, 4, 3)
        mav.sys_status_send(0x10000020, 0x10000020, 0x10000020, 0, 12_600, -1, 80, 0, 0, 0, 0, 0, 0)
        mav.gps_raw_int_send(0, 6, lat, lon, 584_000, 80, 120, 0, 0, 12)
        mav.global_position_int_send(0, lat, lon, 584_000, 0, 0, 0, 0, 0)
        mav.home_position_send(lat, lon, 584_000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0)
        mav.local_position_ned_send(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def _answer(self, m: Any) -> None:
        result = 0
        if m.command == 400 and m.param1 == 1:
            self.arms += 1
            if self.arms <= self.refusals:
                self.conn.mav.statustext_send(2, b"Arm: Gyros inconsistent")
                result = 4
            else:
                self.armed = True
        self.conn.mav.command_ack_send(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent())

    def _run(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_beat:
                self._telemetry()
                next_beat = time.monotonic() + 0.1
            self.conn.select(0.02)
            while (m := self.conn.recv_msg()) is not None:
                if m.get_type() == "COMMAND_LONG":
                    self._answer(m)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()


@pytest.mark.processes
def test_takeoff_tries_a_refused_arm_again_within_its_ready_timeout() -> None:
    port = free_port("udp")
    ap = ScriptedArduPilot(port, refusals=2)
    try:
        with drv.connect(f"udpin:127.0.0.1:{port}", timeout=10.0) as v:
            v.takeoff(10.0, wait=False, ready_timeout=30.0)
            assert ap.arms == 3 and v.state.armed  # refused twice, then armed and took off
        ap.arms, ap.armed = 0, False
        with drv.connect(f"udpin:127.0.0.1:{port}", timeout=10.0) as v:
            with pytest.raises(CommandRejected, match="Gyros inconsistent"):
                v.takeoff(10.0, wait=False, ready_timeout=1.0)  # no time left to try again
            assert ap.arms == 1
    finally:
        ap.close()
