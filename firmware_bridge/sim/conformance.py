"""How closely the simulated autopilot answers like a recorded real one.

Theory of operation. A trace is a ``.tlog`` recorded on the link between a companion
computer (component 191) and a real ArduCopter or PX4 SITL (component 1), both
directions, read back with pymavlink; which autopilot it is comes from its HEARTBEAT
(``Trace.profile``), its system id too. :func:`replay` sends the companion's messages,
at their recorded times, into the simulator's own autopilot core of that profile
(:class:`~firmware_bridge.sim.autopilot.Autopilot`, the one ``swarm sim`` runs) on a
virtual clock stepped like the runner's, with the profile's recorded boot length;
every message it answers is packed and parsed back as MAVLink 2 bytes, and stamped
with its simulated time. :func:`compare` then reads the trace's and the
simulator's autopilot messages the same way:

* milestones: the first BOOT heartbeat, first valid position, GPS origin, home, first
  local position, accepted arm, armed heartbeat, take-off altitude reached, disarmed;
  matched when present, in the recorded order and within ``max(1.5 s, 20 %)``;
* the COMMAND_ACK result of each command (the n-th ACK of a command id with the n-th);
* STATUSTEXT texts (digits folded: "584m" and "585m" are one text), the set of message
  types and of HEARTBEAT (base_mode, custom_mode, system_status) triples;
* timings as ratios simulator / trace: take-off (accepted NAV_TAKEOFF to 95 % of its
  altitude above home; PX4's is AMSL), the 20 m move (the first LOCAL_NED position
  setpoint 5 m or more from the one before, else the first, to within 0.5 m) and the
  landing (RTL or LAND, command or mode, to the disarmed heartbeat).

:func:`replay_live` does the same through the runner (``VehicleSim``) on a real TCP
socket, ``speedup`` times faster than the recording, for the bench. Reading the files
and that live replay are the only I/O; everything else is a pure function of the
records.
"""

from __future__ import annotations

import math
import re
import stat
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.errors import BridgeError
from firmware_bridge.sim.autopilot import Autopilot
from firmware_bridge.sim.runner import REALISTIC_BOOTS
from radios.ports import free_port

COMPANION, AUTOPILOT = 191, 1
MAX_TRACE_S = 3600.0  # a longer file is refused, not replayed for hours
MAX_TRACE_BYTES = 64 * 1024 * 1024  # a larger file is refused, not read into memory
TOL_S, TOL_RATIO = 1.5, 0.2
Msg = Any


@dataclass(frozen=True)
class Record:
    t: float  # seconds since the first record
    msg: Msg


@dataclass(frozen=True)
class Trace:
    name: str
    records: tuple[Record, ...]

    def side(self, comp: int) -> list[Record]:
        return [r for r in self.records if r.msg.get_srcComponent() == comp]

    def _heartbeat(self) -> Msg | None:
        return next((r.msg for r in self.side(AUTOPILOT) if r.msg.get_type() == "HEARTBEAT"), None)

    @property
    def profile(self) -> str:
        """``px4`` or ``ardupilot``, from the autopilot's HEARTBEAT (MAV_AUTOPILOT)."""
        hb = self._heartbeat()
        return "px4" if hb is not None and hb.autopilot == 12 else "ardupilot"

    @property
    def sysid(self) -> int:
        hb = self._heartbeat()
        return int(hb.get_srcSystem()) if hb is not None else 1

    @property
    def duration(self) -> float:
        return self.records[-1].t if self.records else 0.0


def read_trace(path: Path) -> Trace:
    """All MAVLink messages of a ``.tlog``; BridgeError for a file that is not one."""
    try:
        st = path.stat()  # before opening: a FIFO or a device is never opened
    except OSError as exc:
        raise BridgeError(f"cannot read trace {path}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise BridgeError(f"trace {path} is not a regular file")
    if st.st_size > MAX_TRACE_BYTES:
        raise BridgeError(f"trace {path} is larger than {MAX_TRACE_BYTES // 2**20} MiB")
    try:
        conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    except OSError as exc:
        raise BridgeError(f"cannot read trace {path}: {exc.strerror or exc}") from None
    recs: list[Record] = []
    t0: float | None = None
    try:
        while (m := conn.recv_match()) is not None:
            if m.get_type() == "BAD_DATA":
                continue
            t0 = m._timestamp if t0 is None else t0  # noqa: SLF001 (pymavlink's receive time has no public name)
            t = m._timestamp - t0  # noqa: SLF001 (pymavlink's receive time has no public name)
            if not (math.isfinite(t) and 0.0 <= t <= MAX_TRACE_S):
                raise BridgeError(f"trace {path}: timestamps out of order or beyond {MAX_TRACE_S:.0f} s")
            recs.append(Record(t, m))
    finally:
        conn.close()
    if not any(r.msg.get_srcComponent() == COMPANION for r in recs):
        raise BridgeError(f"trace {path}: no message from a companion (component {COMPANION})")
    return Trace(path.stem, tuple(recs))


def _origin(trace: Trace) -> tuple[float, float, float]:
    """The EKF origin (GPS_GLOBAL_ORIGIN), else the first home (PX4 sends no origin unasked)."""
    for kind in ("GPS_GLOBAL_ORIGIN", "HOME_POSITION"):
        for r in trace.records:
            if r.msg.get_type() == kind:
                return r.msg.latitude / 1e7, r.msg.longitude / 1e7, r.msg.altitude / 1000.0
    raise BridgeError(f"trace {trace.name}: no GPS_GLOBAL_ORIGIN or HOME_POSITION")


def replay(trace: Trace, boot_time: float | None = None, dt: float = 0.02) -> list[Record]:
    """The simulated autopilot's answers to the trace's companion messages (its profile's
    recorded boot unless ``boot_time`` is given)."""
    profile = trace.profile
    boot = REALISTIC_BOOTS[profile] if boot_time is None else boot_time
    ap = Autopilot(profile, trace.sysid, _origin(trace), boot_time=boot, dt=dt, noise=0.0)
    # its 1 Hz heartbeat in the recorded one's phase: the companion answers what it saw
    # (an arm undone at the next armed heartbeat), so the replay must show it then too
    beats = [r.t for r in trace.side(AUTOPILOT) if r.msg.get_type() == "HEARTBEAT"]
    if beats:
        ap.next_hb = beats[0] % 1.0
    enc, rx = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 0, 0)
    out: list[Record] = []

    def keep(msgs: list[Msg], t: float) -> None:
        for m in msgs:
            out.extend(Record(t, p) for p in rx.parse_buffer(m.pack(enc)) or [])

    inputs = trace.side(COMPANION)
    i, step, end = 0, 0, trace.duration
    while step * dt <= end + 1e-9:
        now = step * dt
        while i < len(inputs) and inputs[i].t <= now:
            keep(ap.handle(inputs[i].msg, inputs[i].t), inputs[i].t)
            i += 1
        keep(ap.tick(now), now)
        step += 1
    return out


# ------------------------------------------------------------------ milestones
def _first(recs: Iterable[Record], kind: str, ok: Callable[[Msg], bool], after: float = -1.0) -> float | None:
    return next((r.t for r in recs if r.t > after and r.msg.get_type() == kind and ok(r.msg)), None)


def _takeoff_alt(companion: list[Record], accepted: float, recs: list[Record]) -> float | None:
    """The altitude above home of the NAV_TAKEOFF that was accepted at ``accepted`` (PX4's
    is AMSL: home's altitude, from the last HOME_POSITION before, taken off)."""
    cmd = next((r.msg for r in reversed(companion) if _command(r.msg) == 22 and r.t <= accepted), None)
    if cmd is None:
        return None
    alt = float(cmd.param7 if cmd.get_type() == "COMMAND_LONG" else cmd.z)
    hb = next((r.msg for r in recs if r.msg.get_type() == "HEARTBEAT"), None)
    if hb is not None and hb.autopilot == 12:
        homes = [r.msg for r in recs if r.t <= accepted and r.msg.get_type() == "HOME_POSITION"]
        home = homes[-1] if homes else None
        alt = alt - home.altitude / 1000.0 if home is not None else math.nan
    return alt if math.isfinite(alt) else None


def _command(m: Msg) -> int | None:
    return int(m.command) if m.get_type() in ("COMMAND_LONG", "COMMAND_INT") else None


def milestones(recs: list[Record], companion: list[Record]) -> dict[str, float | None]:
    """When each milestone first happened in ``recs`` (autopilot messages), or None."""
    armed = _first(recs, "HEARTBEAT", lambda m: m.base_mode & 128)
    took = _first(recs, "COMMAND_ACK", lambda m: m.command == 22 and m.result == 0)
    alt = None if took is None else _takeoff_alt(companion, took, recs)
    reached = None
    if alt is not None and took is not None:
        reached = _first(recs, "GLOBAL_POSITION_INT", lambda m: m.relative_alt >= 950 * alt - 10, took)
    return {
        "boot_heartbeat": _first(recs, "HEARTBEAT", lambda m: m.system_status == 1),
        "position_valid": _first(recs, "GLOBAL_POSITION_INT", lambda m: m.lat != 0),
        "gps_origin": _first(recs, "GPS_GLOBAL_ORIGIN", lambda m: True),
        "home": _first(recs, "HOME_POSITION", lambda m: True),
        "local_position": _first(recs, "LOCAL_POSITION_NED", lambda m: True),
        "arm_accepted": _first(recs, "COMMAND_ACK", lambda m: m.command == 400 and m.result == 0),
        "armed": armed,
        "takeoff_reached": reached,
        # the disarm that ends the flight (an arm tried and undone before it is not it)
        "disarmed": None
        if armed is None
        else _first(recs, "HEARTBEAT", lambda m: not m.base_mode & 128, reached or armed),
    }


def _match_milestones(real: dict[str, float | None], sim: dict[str, float | None]) -> dict[str, Any]:
    present = [k for k, v in real.items() if v is not None]
    order_real = sorted(present, key=lambda k: (real[k], present.index(k)))
    in_sim = [k for k in present if sim.get(k) is not None]
    order_sim = sorted(in_sim, key=lambda k: (sim[k], order_real.index(k)))
    rank = {k: i for i, k in enumerate(k for k in order_real if k in in_sim)}
    matched, detail = 0, {}
    for k in present:
        t_real, t_sim = real[k], sim.get(k)
        assert t_real is not None
        ok = (
            t_sim is not None
            and order_sim.index(k) == rank[k]
            and abs(t_sim - t_real) <= max(TOL_S, TOL_RATIO * t_real)
        )
        matched += ok
        detail[k] = {
            "trace_s": round(t_real, 2),
            "sim_s": None if t_sim is None else round(t_sim, 2),
            "ok": ok,
        }
    return {"matched": matched, "total": len(present), "detail": detail}


# ----------------------------------------------------------------- acks, texts
def ack_results(companion: list[Record], autopilot: list[Record]) -> list[tuple[int, int | None]]:
    """(command, result of its ACK or None) for each command the companion sent, in order."""
    acks: dict[int, list[int]] = {}
    for r in autopilot:
        if r.msg.get_type() == "COMMAND_ACK":
            acks.setdefault(int(r.msg.command), []).append(int(r.msg.result))
    seen: Counter[int] = Counter()
    out = []
    for r in companion:
        cmd = _command(r.msg)
        if cmd is None:
            continue
        got = acks.get(cmd, [])
        out.append((cmd, got[seen[cmd]] if seen[cmd] < len(got) else None))
        seen[cmd] += 1
    return out


def _fold(text: str) -> str:
    return re.sub(r"[0-9]+(\.[0-9]+)?", "#", text)


def texts(recs: list[Record]) -> set[str]:
    return {_fold(str(r.msg.text)) for r in recs if r.msg.get_type() == "STATUSTEXT"}


def heartbeats(recs: list[Record]) -> set[tuple[int, int, int]]:
    return {
        (r.msg.base_mode, r.msg.custom_mode, r.msg.system_status)
        for r in recs
        if r.msg.get_type() == "HEARTBEAT"
    }


def _set_score(real: set[Any], sim: set[Any]) -> dict[str, Any]:
    return {
        "matched": len(real & sim),
        "total": len(real),
        "missing": sorted(str(x) for x in real - sim),
        "extra": sorted(str(x) for x in sim - real),
    }


# --------------------------------------------------------------------- timings
def _step_start(companion: list[Record]) -> tuple[float, float, float] | None:
    """(time, north, east) of the first LOCAL_NED position setpoint 5 m or more from the
    one before it (a step after a hold stream), else of the first one."""
    first: tuple[float, float, float] | None = None
    prev: tuple[float, float] | None = None
    for r in companion:
        m = r.msg
        local = m.get_type() == "SET_POSITION_TARGET_LOCAL_NED" and m.coordinate_frame == 1
        if local and not m.type_mask & 7:
            here = (float(m.x), float(m.y))
            if prev is not None and math.dist(here, prev) >= 5.0:
                return r.t, here[0], here[1]
            first = first or (r.t, here[0], here[1])
            prev = here
    return first


def _landing_start(companion: list[Record], armed: float | None) -> float | None:
    """The first RTL or LAND (command or mode) after arming."""
    for r in companion:
        cmd = _command(r.msg)
        land_mode = cmd == 176 and (
            int(r.msg.param2) in (6, 9) or (int(r.msg.param2) == 4 and int(r.msg.param3) in (5, 6))
        )  # ArduCopter RTL, LAND; PX4 AUTO.RTL, AUTO.LAND
        if armed is not None and r.t > armed and (cmd in (20, 21) or land_mode):
            return r.t
    return None


def timings(recs: list[Record], companion: list[Record]) -> dict[str, float | None]:
    """Seconds of the take-off, the 20 m move and the landing in ``recs`` (None: not seen)."""
    ms = milestones(recs, companion)
    took = _first(recs, "COMMAND_ACK", lambda m: m.command == 22 and m.result == 0)
    takeoff = None if ms["takeoff_reached"] is None or took is None else ms["takeoff_reached"] - took
    move = None
    step = _step_start(companion)
    if step is not None:
        t0, n, e = step
        hit = _first(recs, "LOCAL_POSITION_NED", lambda m: math.hypot(m.x - n, m.y - e) < 0.5, t0)
        move = None if hit is None else hit - t0
    land = None
    start = _landing_start(companion, ms["armed"])
    if start is not None:
        down = _first(recs, "HEARTBEAT", lambda m: not m.base_mode & 128, start)
        land = None if down is None else down - start
    return {"takeoff_s": takeoff, "move_20m_s": move, "land_s": land}


def _ratios(real: dict[str, float | None], sim: dict[str, float | None]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in real.items():
        s = sim.get(k)
        name = k.removesuffix("_s")
        out[name] = {
            "trace_s": None if v is None else round(v, 2),
            "sim_s": None if s is None else round(s, 2),
            "ratio": None if v is None or s is None or v <= 0 else round(s / v, 3),
        }
    return out


# --------------------------------------------------------------------- compare
def compare(trace: Trace, sim: list[Record]) -> dict[str, Any]:
    """The simulator's answers ``sim`` against the trace (see the module docstring)."""
    companion, real = trace.side(COMPANION), trace.side(AUTOPILOT)
    acks_real, acks_sim = ack_results(companion, real), ack_results(companion, sim)
    ack_detail = [
        {"command": c, "trace": a, "sim": b}
        for (c, a), (_, b) in zip(acks_real, acks_sim, strict=True)
        if a != b
    ]
    return {
        "milestones": _match_milestones(milestones(real, companion), milestones(sim, companion)),
        "acks": {
            "matched": len(acks_real) - len(ack_detail),
            "total": len(acks_real),
            "mismatches": ack_detail,
        },
        "texts": _set_score(texts(real), texts(sim)),
        "message_types": _set_score({r.msg.get_type() for r in real}, {r.msg.get_type() for r in sim}),
        "heartbeats": _set_score(heartbeats(real), heartbeats(sim)),
        "timings": _ratios(timings(real, companion), timings(sim, companion)),
    }


def conformance(path: Path, boot_time: float | None = None) -> dict[str, Any]:
    """Read, replay and compare one trace."""
    trace = read_trace(path)
    return compare(trace, replay(trace, boot_time))


# ------------------------------------------------------- live, on real sockets
def replay_live(trace: Trace, speedup: float = 10.0, boot_time: float | None = None) -> list[Record]:
    """Like :func:`replay`, but through a :class:`VehicleSim` (``swarm sim``) on a real
    socket (ArduCopter: TCP, its clock held until we connect; PX4: UDP, booting from its
    start), the companion's frames sent at their recorded times ``speedup`` times faster;
    answers stamped in simulated seconds. The simulated vehicle is system 1: so must the
    recorded one be."""
    from firmware_bridge.sim.runner import SimConfig, VehicleSim

    profile = trace.profile
    if trace.sysid != 1:
        raise BridgeError(f"trace {trace.name}: system {trace.sysid}; a live replay needs system 1")
    lat, lon, alt = _origin(trace)
    cfg = SimConfig(
        profile=profile,
        home=(lat, lon, alt),
        speedup=speedup,
        boot_time=REALISTIC_BOOTS[profile] if boot_time is None else boot_time,
        base_port=free_port("tcp" if profile == "ardupilot" else "udp"),
        wait_for_client=profile == "ardupilot",  # the boot starts at our connection, however late
    )
    out: list[Record] = []
    with VehicleSim(cfg) as sim:
        conn = mavutil.mavlink_connection(sim.endpoints[0], source_system=1, source_component=COMPANION)
        t0 = time.monotonic()  # about when the simulator accepted us: its time 0
        try:
            now = lambda: (time.monotonic() - t0) * speedup  # noqa: E731
            for r in [*trace.side(COMPANION), Record(trace.duration, None)]:
                while now() < r.t:
                    m = conn.recv_match(blocking=True, timeout=min(0.05, max(0.001, (r.t - now()) / speedup)))
                    if m is not None and m.get_type() != "BAD_DATA":
                        out.append(Record(now(), m))
                if r.msg is not None:
                    conn.write(r.msg.get_msgbuf())
        finally:
            conn.close()
    return out
