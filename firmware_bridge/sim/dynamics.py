"""Point-mass multicopter: a position controller, a velocity lag and ground contact.

Pure arithmetic, no I/O and no clock: :meth:`Body.step` advances the body by a fixed
step ``dt`` (simulated seconds) toward a :class:`Target`. The law is a simplified PX4
multicopter position controller (its MPC_* parameters; an approximation, not PX4's code)::

    v_cmd = v_ff + Kp * (p_sp - p)         per axis, Kp = MPC_XY_P / MPC_Z_P
    |v_cmd_xy| <= min(v_max_xy, |v_ff| + sqrt(2 a_xy |e_xy|))   (braking-distance limit)
    -v_up <= v_cmd_z <= v_down
    dv/dt = (v_cmd - v) / tau,  |dv_xy/dt| <= a_xy (g tan 45 deg), |dv_z/dt| <= a_z

An axis whose position is NaN is velocity-controlled (``v_ff``), or acceleration-
controlled (``a_ff``), or held still. Yaw turns toward ``yaw`` (or at ``yaw_rate``) at
most ``yaw_rate_max``. A body with ``z >= 0`` (NED, down positive) is on the ground:
it cannot move sideways or sink, and lifts off only when powered and commanded up. An
unpowered body in the air falls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

G = 9.80665
NAN = float("nan")


@dataclass(frozen=True)
class Limits:
    """Controller gains and limits of one autopilot profile (SI units)."""

    kp_xy: float = 0.95  # MPC_XY_P
    kp_z: float = 1.0  # MPC_Z_P
    v_xy: float = 12.0  # MPC_XY_VEL_MAX (PX4) / WPNAV_SPEED (AP)
    v_up: float = 3.0  # MPC_Z_VEL_MAX_UP / WPNAV_SPEED_UP
    v_down: float = 1.5  # MPC_Z_VEL_MAX_DN / WPNAV_SPEED_DN
    a_xy: float = G * math.tan(math.radians(45.0))  # MPC_TILTMAX_AIR 45 deg
    a_z: float = 4.0  # MPC_ACC_UP_MAX
    tau: float = 0.4  # velocity response time constant
    yaw_rate_max: float = math.radians(90.0)
    yaw_p: float = 2.8  # MC_YAW_P


@dataclass
class Target:
    """What the controller tracks; NaN = not controlled. NED metres, m/s, m/s^2, rad."""

    pos: tuple[float, float, float] = (NAN, NAN, NAN)
    vel: tuple[float, float, float] = (NAN, NAN, NAN)
    acc: tuple[float, float, float] = (NAN, NAN, NAN)
    yaw: float = NAN
    yaw_rate: float = NAN
    #: vertical speed limits override (take-off / landing speeds), m/s, NaN = profile's
    v_up: float = NAN
    v_down: float = NAN

    @staticmethod
    def hold(pos: tuple[float, float, float], yaw: float) -> Target:
        return Target(pos=pos, yaw=yaw)


def wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass
class Body:
    """Kinematic state of one vehicle in its local NED frame (origin = start point)."""

    pos: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    vel: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    acc: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    yaw: float = 0.0
    yaw_rate: float = 0.0

    @property
    def on_ground(self) -> bool:
        return self.pos[2] >= 0.0

    def step(self, target: Target | None, lim: Limits, dt: float, powered: bool) -> None:
        """Advance by ``dt``; ``target`` None or ``powered`` False means idle/free fall."""
        p, v = self.pos, self.vel
        if not powered or target is None:
            self._unpowered(dt, powered)
            return
        vc = self._velocity_command(target, lim)
        # first-order lag with acceleration limits
        ax = (vc[0] - v[0]) / lim.tau
        ay = (vc[1] - v[1]) / lim.tau
        ah = math.hypot(ax, ay)
        if ah > lim.a_xy:
            ax *= lim.a_xy / ah
            ay *= lim.a_xy / ah
        az = min(max((vc[2] - v[2]) / lim.tau, -lim.a_z), lim.a_z)
        r = self._yaw_rate_command(target, lim)
        if self.on_ground and vc[2] >= 0.0 and v[2] >= 0.0:
            # resting on the ground: motors spinning, nothing moves
            self._rest()
            return
        self.acc = [ax, ay, az]
        for i, a in enumerate((ax, ay, az)):
            v[i] += a * dt
            p[i] += v[i] * dt
        self.yaw = wrap_pi(self.yaw + r * dt)
        self.yaw_rate = r
        if p[2] >= 0.0:
            self._rest()

    def _velocity_command(self, target: Target, lim: Limits) -> list[float]:
        """The position loop: commanded NED velocity within the speed and braking limits."""
        p, v = self.pos, self.vel
        vc = [0.0, 0.0, 0.0]
        ex = target.pos[0] - p[0] if math.isfinite(target.pos[0]) else NAN
        ey = target.pos[1] - p[1] if math.isfinite(target.pos[1]) else NAN
        for i, (e, kp) in enumerate(((ex, lim.kp_xy), (ey, lim.kp_xy), (target.pos[2] - p[2], lim.kp_z))):
            ff = target.vel[i]
            if math.isfinite(e):
                vc[i] = (ff if math.isfinite(ff) else 0.0) + kp * e
            elif math.isfinite(ff):
                vc[i] = ff
            elif math.isfinite(target.acc[i]):
                vc[i] = v[i] + target.acc[i] * lim.tau
            else:
                vc[i] = 0.0
        # horizontal: speed limit and braking distance (sqrt controller)
        h = math.hypot(vc[0], vc[1])
        cap = lim.v_xy
        if math.isfinite(ex) and math.isfinite(ey):
            # braking distance: the correction term may not exceed what the tilt limit
            # can stop; a velocity feed-forward adds on top (PX4 offboard: v_ff + Kp e)
            vff = math.hypot(*(target.vel[k] if math.isfinite(target.vel[k]) else 0.0 for k in (0, 1)))
            cap = min(cap, vff + math.sqrt(2.0 * lim.a_xy * 0.8 * math.hypot(ex, ey)))
        if h > cap > 0.0:
            vc[0] *= cap / h
            vc[1] *= cap / h
        elif cap <= 0.0:
            vc[0] = vc[1] = 0.0
        v_up = target.v_up if math.isfinite(target.v_up) else lim.v_up
        v_dn = target.v_down if math.isfinite(target.v_down) else lim.v_down
        vc[2] = min(max(vc[2], -v_up), v_dn)
        return vc

    def _yaw_rate_command(self, target: Target, lim: Limits) -> float:
        if math.isfinite(target.yaw):
            r = lim.yaw_p * wrap_pi(target.yaw - self.yaw)
        elif math.isfinite(target.yaw_rate):
            r = target.yaw_rate
        else:
            r = 0.0
        return min(max(r, -lim.yaw_rate_max), lim.yaw_rate_max)

    def _unpowered(self, dt: float, powered: bool) -> None:
        p, v = self.pos, self.vel
        if self.on_ground:
            self._rest()
            return
        # motors off in the air: ballistic fall with a little drag
        v[0] -= v[0] * 0.5 * dt
        v[1] -= v[1] * 0.5 * dt
        v[2] += G * dt
        self.acc = [0.0, 0.0, G]
        for i in range(3):
            p[i] += v[i] * dt
        self.yaw_rate = 0.0
        if p[2] >= 0.0:
            self._rest()

    def _rest(self) -> None:
        self.pos[2] = 0.0
        self.vel = [0.0, 0.0, 0.0]
        self.acc = [0.0, 0.0, 0.0]
        self.yaw_rate = 0.0
