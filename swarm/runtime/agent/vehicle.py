"""What the agent reads from its flight controller, in the swarm's terms: pure
conversions of a driver :class:`~firmware_bridge.driver.VehicleState` snapshot.

:func:`vehicle_info` is what Telemetry reports, :func:`pose_from_state` the
protocol's Pose (None until the driver finds the position valid, ``position_valid``:
a real autopilot sends 0, 0 before its fix; None with a non-finite field or one a
Pose cannot carry too), and
:func:`vehicle_messages` the HEARTBEAT and GLOBAL_POSITION_INT (only with a valid
position) a standard ground station expects on the radio, rebuilt from the snapshot (the driver keeps no raw
messages; the vehicle type, not in the snapshot, is sent as a quadrotor).
:func:`state_dict` is an AgentState as ``swarm agent --json`` prints it. The
snapshot is duck-typed (any object with the driver's field names): no I/O here.
"""

from __future__ import annotations

import math
from typing import Any

from firmware_bridge.session import SETPOINT_MODES
from swarm.core.agent.node import VehicleInfo
from swarm.core.wire.message_types import AgentState, Pose
from swarm.errors import MessageError


def vehicle_info(s: Any, link_ok: bool) -> VehicleInfo:
    """What Telemetry reports of a driver VehicleState."""
    speed = 0.0
    if s.velocity is not None and all(map(math.isfinite, s.velocity[:2])):
        speed = math.hypot(s.velocity[0], s.velocity[1])
    climb = None
    if s.velocity is not None and math.isfinite(s.velocity[2]):
        climb = -float(s.velocity[2])  # NED: down is positive
    return VehicleInfo(
        mode=s.mode,
        armed=bool(s.armed),
        airborne=bool(s.in_air),
        battery=int(s.battery_remaining),
        groundspeed=speed,
        link_ok=link_ok,
        controlled=(s.mode in SETPOINT_MODES) if s.mode else None,
        rel_alt=_finite(s.rel_alt),
        climb=climb,
        gps_fix=getattr(s, "gps_fix", None),
        satellites=getattr(s, "satellites", None),
        home_dist=_home_dist(s),
        ready=s.prearm_ok,
    )


def _finite(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def _home_dist(s: Any) -> float | None:
    """Metres from the autopilot's home (HOME_POSITION) to the vehicle; None unknown."""
    home = s.home
    if home is None or s.lat is None or s.lon is None or not s.position_valid:
        return None
    k = math.pi / 180.0
    x = (s.lon - home[1]) * k * math.cos((s.lat + home[0]) * k / 2)
    y = (s.lat - home[0]) * k
    d = 6_371_000.0 * math.hypot(x, y)
    return d if math.isfinite(d) else None


def pose_from_state(s: Any, t: float) -> Pose | None:
    """The protocol's Pose from a driver VehicleState (None without a valid position)."""
    if not s.position_valid or s.lat is None or s.lon is None:
        return None
    vn, ve = (s.velocity[0], s.velocity[1]) if s.velocity is not None else (0.0, 0.0)
    vals = [s.lat, s.lon, s.alt_amsl if s.alt_amsl is not None else 0.0, math.degrees(s.yaw) % 360.0, vn, ve]
    if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in vals):
        return None
    try:
        return Pose(vals[0], vals[1], vals[2], vals[3], vals[4], vals[5], t)
    except MessageError:  # beyond what a Pose carries (altitude, range): no pose, no error
        return None


_AUTOPILOT_IDS = {"px4": 12, "ardupilot": 3}
MAV_TYPE_QUADROTOR = 2


def _clamp(x: float, lo: int, hi: int) -> int:
    return max(lo, min(hi, round(x)))


def vehicle_messages(s: Any) -> list[Any]:
    """HEARTBEAT and (with a fix) GLOBAL_POSITION_INT rebuilt from a VehicleState, for
    :meth:`swarm.runtime.bridge.radio_bridge.RadioBridge.forward_vehicle` (the driver keeps no
    raw messages)."""
    from radios.mavlink import dialect

    out: list[Any] = [
        dialect.MAVLink_heartbeat_message(
            MAV_TYPE_QUADROTOR,
            _AUTOPILOT_IDS.get(s.autopilot, 0),
            s.base_mode & 0xFF,
            s.custom_mode & 0xFFFFFFFF,
            s.system_status & 0xFF,
            3,
        )
    ]
    if s.position_valid and s.lat is not None and s.lon is not None and math.isfinite(s.lat + s.lon):
        vel = s.velocity if s.velocity is not None and all(map(math.isfinite, s.velocity)) else (0, 0, 0)
        alt = s.alt_amsl if s.alt_amsl is not None and math.isfinite(s.alt_amsl) else 0.0
        rel = s.rel_alt if s.rel_alt is not None and math.isfinite(s.rel_alt) else 0.0
        hdg = _clamp(math.degrees(s.yaw) % 360.0 * 100, 0, 35999) if math.isfinite(s.yaw) else 65535
        out.append(
            dialect.MAVLink_global_position_int_message(
                s.time_boot_ms & 0xFFFFFFFF,
                _clamp(s.lat * 1e7, -900_000_000, 900_000_000),
                _clamp(s.lon * 1e7, -1_800_000_000, 1_800_000_000),
                _clamp(alt * 1000, -(2**31), 2**31 - 1),
                _clamp(rel * 1000, -(2**31), 2**31 - 1),
                _clamp(vel[0] * 100, -32768, 32767),
                _clamp(vel[1] * 100, -32768, 32767),
                _clamp(vel[2] * 100, -32768, 32767),
                hdg,
            )
        )
    return out


def state_dict(name: str, st: AgentState) -> dict[str, Any]:
    """An AgentState as the JSON object ``swarm agent --json`` prints."""
    return {
        "name": name,
        "id": st.sender,
        "phase": st.phase.name,
        "leader": st.leader,
        "pool": sorted(st.pool),
        "locked": st.locked,
        "members": sorted(st.members),
        "candidate": st.candidate,
        "weight": st.weight,
        "epoch": st.epoch,
    }


__all__ = ["pose_from_state", "state_dict", "vehicle_info", "vehicle_messages"]
