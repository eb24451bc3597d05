"""Telemetry of the simulated autopilot: one encoder per MAVLink message id.

Theory of operation. :func:`message` builds the message ``mid`` from an
:class:`~firmware_bridge.sim.autopilot.Autopilot`'s state at its physics time, for a
stream that fell due or a REQUEST_MESSAGE; None when it has nothing to say (no
position without GPS, no target echo where the flavour sends none). Pure: positions go
through pymap3d around the vehicle's origin, the only randomness is the autopilot's
seeded generator (position noise, drawn north, east, then down in the air), and the
flavour gives the heartbeat, the version, the target-echo rule and, while an ArduPilot
boots, which positions exist yet (all-zero GLOBAL_POSITION_INT, no LOCAL_POSITION_NED,
no HOME_POSITION).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

from firmware_bridge.sim.dynamics import G
from firmware_bridge.sim.flavour import Msg, finite

if TYPE_CHECKING:
    from firmware_bridge.sim.autopilot import Autopilot

#: message ids a stream may carry (SET_MESSAGE_INTERVAL), and what REQUEST_MESSAGE answers
STREAMABLE = frozenset({1, 24, 30, 32, 33, 49, 74, 85, 147, 193, 242, 245})
REQUESTABLE = STREAMABLE | {0, 148}


def message(ap: Autopilot, mid: int) -> Msg | None:
    """Message ``mid`` as the autopilot would send it now, or None."""
    encode = ENCODERS.get(mid)
    return encode(ap) if encode is not None else None


def _boot_ms(ap: Autopilot) -> int:
    return round(ap.t * 1000.0) & 0xFFFFFFFF


def _noisy_pos(ap: Autopilot) -> tuple[float, float, float]:
    b = ap.body
    s = ap.noise
    if s <= 0:
        return b.pos[0], b.pos[1], b.pos[2]
    dz = 0.0 if b.on_ground else ap.rng.gauss(0.0, s)
    return b.pos[0] + ap.rng.gauss(0.0, s), b.pos[1] + ap.rng.gauss(0.0, s), b.pos[2] + dz


def _battery_vi(ap: Autopilot) -> tuple[float, float]:
    volt = 14.0 + 2.8 * ap.battery / 100.0
    if not ap.armed:
        cur = 0.5
    elif ap.body.on_ground:
        cur = 3.0
    else:
        cur = 18.0
    return volt, cur


def _heartbeat(ap: Autopilot) -> Msg:
    return ap.flavour.heartbeat(ap)


def _extended_sys_state(ap: Autopilot) -> Msg:
    return ap.mav.extended_sys_state_encode(0, ap.landed_state)


def _global_position_int(ap: Autopilot) -> Msg | None:
    if not ap.gps_ok:
        return None
    if not ap.flavour.position_valid(ap):  # booting ArduPilot: all zeros ("Null Island"); PX4: none
        if not ap.flavour.zero_position_before_fix:
            return None
        return ap.mav.global_position_int_encode(_boot_ms(ap), 0, 0, 0, 0, 0, 0, 0, 0)
    b = ap.body
    n, e, d = _noisy_pos(ap)
    lat, lon, alt = ap.geo(n, e, d)
    rel = alt - ap.geo(*ap.home)[2]
    hdg = round(math.degrees(b.yaw) * 100.0) % 36000
    return ap.mav.global_position_int_encode(
        _boot_ms(ap),
        round(lat * 1e7),
        round(lon * 1e7),
        round(alt * 1000),
        round(rel * 1000),
        round(b.vel[0] * 100),
        round(b.vel[1] * 100),
        round(b.vel[2] * 100),
        hdg,
    )


def _local_position_ned(ap: Autopilot) -> Msg | None:
    if not ap.gps_ok or not ap.flavour.local_valid(ap):
        return None
    b = ap.body
    n, e, d = _noisy_pos(ap)
    return ap.mav.local_position_ned_encode(_boot_ms(ap), n, e, d, b.vel[0], b.vel[1], b.vel[2])


def _attitude(ap: Autopilot) -> Msg:
    b = ap.body
    a = b.acc
    c, s = math.cos(b.yaw), math.sin(b.yaw)
    fwd, right = a[0] * c + a[1] * s, -a[0] * s + a[1] * c
    return ap.mav.attitude_encode(
        _boot_ms(ap), math.atan2(right, G), -math.atan2(fwd, G), b.yaw, 0.0, 0.0, b.yaw_rate
    )


PREARM = 0x10000000  # MAV_SYS_STATUS_PREARM_CHECK


def _sys_status(ap: Autopilot) -> Msg:
    sensors = 32 | 1 | 2 | 4 | 8  # GPS, gyro, accel, mag, baro
    health = sensors if ap.gps_ok and ap.flavour.gps_detected(ap) else sensors & ~32
    prearm = ap.flavour.prearm_ok(ap)
    if prearm is not None:  # the autopilot reports its pre-arm checks
        sensors |= PREARM
        health |= PREARM if prearm else 0
    volt, cur = _battery_vi(ap)
    load, pct = 250, int(ap.battery)
    return ap.mav.sys_status_encode(
        sensors, sensors, health, load, int(volt * 1000), int(cur * 100), pct, 0, 0, 0, 0, 0, 0
    )


def _gps_raw_int(ap: Autopilot) -> Msg:
    b = ap.body
    ok = ap.gps_ok and ap.flavour.gps_detected(ap)
    fix = ap.flavour.gps_fix_type if ok else 0
    lat, lon, alt = ap.geo(b.pos[0], b.pos[1], b.pos[2]) if ok else (0.0, 0.0, 0.0)
    return ap.mav.gps_raw_int_encode(
        int(ap.t * 1e6),
        fix,
        round(lat * 1e7),
        round(lon * 1e7),
        round(alt * 1000),
        80 if fix else 9999,
        120 if fix else 9999,
        int(math.hypot(b.vel[0], b.vel[1]) * 100),
        0,
        12 if fix else 0,
    )


def _battery_status(ap: Autopilot) -> Msg:
    volt, cur = _battery_vi(ap)
    cells = [int(volt * 250)] * 4 + [65535] * 6
    return ap.mav.battery_status_encode(0, 1, 3, 32767, cells, int(cur * 100), -1, -1, int(ap.battery))


def _ekf_status_report(ap: Autopilot) -> Msg | None:
    flags = ap.flavour.ekf_flags(ap)
    if flags is None:
        return None
    return ap.mav.ekf_status_report_encode(flags, 0.02, 0.05, 0.03, 0.04, 0.0, 0.0)


def _home_position(ap: Autopilot) -> Msg | None:
    if not ap.flavour.home_set(ap):
        return None
    lat, lon, alt = ap.geo(*ap.home)
    h = ap.home
    return ap.mav.home_position_encode(
        round(lat * 1e7),
        round(lon * 1e7),
        round(alt * 1000),
        h[0],
        h[1],
        h[2],
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
        int(ap.t * 1e6),
    )


def _gps_global_origin(ap: Autopilot) -> Msg:
    lat, lon, alt = ap.origin
    return ap.mav.gps_global_origin_encode(
        round(lat * 1e7), round(lon * 1e7), round(alt * 1000), int(ap.t * 1e6)
    )


def _vfr_hud(ap: Autopilot) -> Msg:
    b = ap.body
    _, _, alt = ap.geo(*b.pos)
    hdg = round(math.degrees(b.yaw)) % 360
    return ap.mav.vfr_hud_encode(
        0.0, math.hypot(b.vel[0], b.vel[1]), hdg, 0 if not ap.armed else 50, alt, -b.vel[2]
    )


def _autopilot_version(ap: Autopilot) -> Msg:
    caps = 4 | 8 | 128 | 256 | 8192  # MISSION_INT, COMMAND_INT, SET_POS_TARGET_*, MAVLINK2
    ver = ap.flavour.version
    return ap.mav.autopilot_version_encode(caps, ver, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, ap.sysid)


def _target_echo(ap: Autopilot) -> Msg | None:
    extra = ap.flavour.echo_mask(ap)
    if extra is None:
        return None
    tg = ap.target if ap.target is not None else ap.hold_target()
    fields = (*tg.pos, *tg.vel, *tg.acc, tg.yaw, tg.yaw_rate)
    bits = (1, 2, 4, 8, 16, 32, 64, 128, 256, 1024, 2048)
    mask = 0
    vals = []
    for bit, v in zip(bits, fields, strict=True):
        if not finite(v):
            mask |= bit
            vals.append(0.0)
        else:
            vals.append(v)
    return ap.mav.position_target_local_ned_encode(_boot_ms(ap), 1, mask | extra, *vals)


ENCODERS: dict[int, Callable[[Autopilot], Msg | None]] = {
    0: _heartbeat,
    1: _sys_status,
    24: _gps_raw_int,
    30: _attitude,
    32: _local_position_ned,
    33: _global_position_int,
    49: _gps_global_origin,
    74: _vfr_hud,
    85: _target_echo,
    147: _battery_status,
    193: _ekf_status_report,
    148: _autopilot_version,
    242: _home_position,
    245: _extended_sys_state,
}
