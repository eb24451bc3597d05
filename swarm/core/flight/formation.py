"""V-formation geometry, the follow law and the leader's route, as pure functions.

Theory of operation
-------------------
The paper's formation (section 2.4): the leader flies; each member follows one
agent, on one side, so that the swarm makes a V behind the leader, each arm a
chain. Here:

* **Assignments** (:func:`assign`, :func:`reconcile`): members are split into a
  left and a right arm; the first of each arm follows the leader, each next one
  the one before it. With known positions the split and the order follow where
  the members are (lateral offset from the leader's track, then distance behind
  it), so nobody crosses the V to reach its slot; without positions, by id. When a
  member leaves, its arm closes up (whoever followed it follows the one it
  followed); a new member goes to the tail of the shorter arm; a new leader
  assigns afresh from positions.
* **Slot** (:func:`slot_offset`): the followed agent's position plus ``back_m``
  opposite the swarm heading and ``side_m`` to the member's side (right of the
  heading for RIGHT). Altitude: the followed agent's, plus ``stagger_m`` per
  chain position (0: one common altitude).
* **Follow law** (:func:`follow_target`): the followed pose is predicted to now
  with its velocity over its age (the radio delays it by up to a TDM round), the
  slot offset is added, and the followed velocity is the setpoint's velocity
  feed-forward, so that the autopilot's position loop does not lag the slot by
  v / Kp (5 m at 5 m/s with PX4's MPC_XY_P). The followed agent's acceleration,
  estimated from its pose velocities over at least a second (:func:`estimate_accel`),
  is carried into the prediction and the feed-forward: with velocity alone members
  lagged 1.5 m while the leader sped up and led 1.5 m while it slowed down. The
  member's yaw is the swarm heading.
* **Pose age** (:class:`AgeEstimator`): a Pose carries its sample time modulo
  2.56 s in the sender's clock. Clocks differ between drones, so the age is
  estimated per sender as the delay beyond the smallest delay seen recently
  (the smallest is the radio's best case; its few tens of milliseconds are
  ignored), the smallest taken around the wrap (:func:`circular_floor`: for some
  clock offsets the delays straddle it).
* **Route** (:class:`Route`): the leader's path through waypoints at a set
  speed, corners rounded with ``turn_radius_m`` (a 90 degree corner becomes a
  quarter circle), sampled by distance: position, direction and velocity.
* **Swarm heading** (:meth:`Route.mean_heading`, :func:`turn_window_m`,
  :func:`steer_heading`): the heading a leader announces is the route's heading
  averaged over a window of route centred on the leader (straight on beyond the
  route's ends). Through a rounded corner the route's turn rate steps (0, v/r, 0);
  the average's rate ramps instead, at most ``heading_accel`` when the window is
  :func:`turn_window_m` long, starting half a window before the corner and ending
  half a window after it, with the same total turn: so the heading ends exactly
  on the route's, without the overshoot a lagging filter has. :func:`steer_heading`
  follows that target with a bounded angular acceleration (a square-root
  controller: it stops on the target without overshoot), which matters only when
  the target jumps (a route that starts off the task's heading, a waypoint added
  late, the leader arriving before the window has passed the corner).
* **Metrics** (:func:`slot_error`): a member's distance from its slot.

Coordinates: poses are geodetic (WGS-84 latitude, longitude, metres AMSL);
offsets are applied in the local north/east/up plane at the reference point with
pymap3d (exact for formation distances).
"""

from __future__ import annotations

import collections
import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import pymap3d

from swarm.core.wire.message_types import Assignment, Pose, Side, Task, TaskKind

POSE_T_WRAP = 2.56  # Pose.t crosses the air modulo this many seconds


@dataclass(frozen=True)
class FormationConfig:
    back_m: float = 10.0
    side_m: float = 5.0
    stagger_m: float = 0.0  # altitude step per chain position
    min_separation_m: float = 3.0
    separation_clear_m: float = 1.0  # resume when this much beyond the minimum
    stale_s: float = 2.0  # a followed pose older than this: hold
    max_predict_s: float = 1.5  # never extrapolate a pose further than this
    #: how much later the setpoint takes effect: the pilot's step (10 Hz) and the
    #: driver's stream (10 Hz) hold it 0.1 s on average before the autopilot has it
    lead_s: float = 0.1
    #: the followed acceleration is fed forward this much further ahead: the autopilot's
    #: velocity loop lags its velocity setpoint by about this (PX4's and the simulator's 0.4 s)
    accel_lead_s: float = 0.4

    def __post_init__(self) -> None:
        checks = {
            "back_m": 0 <= self.back_m <= 63.75,
            "side_m": 0 <= self.side_m <= 63.75,
            "stagger_m": -20 <= self.stagger_m <= 20,
            "min_separation_m": 0 < self.min_separation_m <= 50,
            "separation_clear_m": 0 <= self.separation_clear_m <= 50,
            "stale_s": 0 < self.stale_s <= 60,
            "max_predict_s": 0 <= self.max_predict_s <= 10,
            "lead_s": 0 <= self.lead_s <= 2,
            "accel_lead_s": 0 <= self.accel_lead_s <= 2,
        }
        for k, ok in checks.items():
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and ok):
                raise ValueError(f"formation {k}={v!r} out of range")
        if self.back_m == 0 and self.side_m == 0:
            raise ValueError(
                "formation back_m and side_m cannot both be 0: every slot would be on its leader"
            )


# -- geodesy ------------------------------------------------------------------------


def offset(lat: float, lon: float, north: float, east: float) -> tuple[float, float]:
    """The point ``north``/``east`` metres from (lat, lon)."""
    la, lo, _ = pymap3d.enu2geodetic(east, north, 0.0, lat, lon, 0.0)
    return float(la), float(lo)


def ne_between(lat0: float, lon0: float, lat: float, lon: float) -> tuple[float, float]:
    """(north, east) metres of (lat, lon) from (lat0, lon0)."""
    e, n, _ = pymap3d.geodetic2enu(lat, lon, 0.0, lat0, lon0, 0.0)
    return float(n), float(e)


def distance(a: Pose, b: Pose) -> float:
    """3-D distance in metres between two poses."""
    n, e = ne_between(a.lat, a.lon, b.lat, b.lon)
    return math.sqrt(n * n + e * e + (a.alt - b.alt) ** 2)


def heading_of(vn: float, ve: float) -> float:
    return math.degrees(math.atan2(ve, vn)) % 360.0


# -- geometry -----------------------------------------------------------------------


def slot_offset(heading_deg: float, side: Side, back_m: float, side_m: float) -> tuple[float, float]:
    """(north, east) of a slot from the agent it follows."""
    h = math.radians(heading_deg)
    fn, fe = math.cos(h), math.sin(h)  # forward
    rn, re = -math.sin(h), math.cos(h)  # right of the heading
    s = float(int(side)) * side_m
    return -back_m * fn + s * rn, -back_m * fe + s * re


def arms(assignments: Iterable[Assignment], leader: int) -> dict[Side, list[int]]:
    """The two chains, each from the leader outwards. Members whose link is broken
    (they follow someone not in their arm) are put at the end of their arm."""
    by_side: dict[Side, list[Assignment]] = {Side.LEFT: [], Side.RIGHT: []}
    for a in assignments:
        by_side[a.side].append(a)
    out: dict[Side, list[int]] = {}
    for side, items in by_side.items():
        follows = {a.follows: a.member for a in items}
        chain: list[int] = []
        cur = leader
        while cur in follows and follows[cur] not in chain:
            cur = follows[cur]
            chain.append(cur)
        chain += sorted(a.member for a in items if a.member not in chain)
        out[side] = chain
    return out


def chains_to_assignments(leader: int, left: Sequence[int], right: Sequence[int]) -> tuple[Assignment, ...]:
    out: list[Assignment] = []
    for side, chain in ((Side.LEFT, left), (Side.RIGHT, right)):
        prev = leader
        for m in chain:
            out.append(Assignment(m, prev, side))
            prev = m
    return tuple(sorted(out, key=lambda a: a.member))


def assign(
    leader: int,
    members: Iterable[int],
    heading_deg: float,
    poses: Mapping[int, Pose] | None = None,
    leader_pose: Pose | None = None,
) -> tuple[Assignment, ...]:
    """Fresh assignments for ``members`` behind ``leader`` (see the module docstring).
    The right arm gets the extra member of an odd count."""
    ms = sorted(set(members) - {leader})
    n_left = len(ms) // 2
    if poses is not None and leader_pose is not None and all(m in poses for m in ms):
        h = math.radians(heading_deg)
        rel: dict[int, tuple[float, float]] = {}
        for m in ms:
            dn, de = ne_between(leader_pose.lat, leader_pose.lon, poses[m].lat, poses[m].lon)
            along = dn * math.cos(h) + de * math.sin(h)
            lateral = -dn * math.sin(h) + de * math.cos(h)  # + right
            rel[m] = (along, lateral)
        by_lateral = sorted(ms, key=lambda m: (rel[m][1], m))
        left = sorted(by_lateral[:n_left], key=lambda m: (-rel[m][0], m))
        right = sorted(by_lateral[n_left:], key=lambda m: (-rel[m][0], m))
    else:
        right, left = ms[0::2], ms[1::2]
    return chains_to_assignments(leader, left, right)


def reconcile(
    task: Task,
    leader: int,
    members: Iterable[int],
    poses: Mapping[int, Pose] | None = None,
    leader_pose: Pose | None = None,
) -> Task:
    """The leader's FOLLOW task kept in step with its members: departed members close
    their arm up, new ones join the tail of the shorter arm, a new leader assigns
    afresh. Other tasks are returned unchanged."""
    if task.kind != TaskKind.FOLLOW:
        return task
    ms = set(members) - {leader}
    heads = {a.follows for a in task.assignments} - {a.member for a in task.assignments}
    if task.assignments and heads != {leader}:
        # a new leader (the assignments hang from someone else): assign from positions
        return _with(task, assign(leader, ms, task.heading, poses, leader_pose))
    chains = arms(task.assignments, leader)
    left = [m for m in chains[Side.LEFT] if m in ms]
    right = [m for m in chains[Side.RIGHT] if m in ms]
    for m in sorted(ms - set(left) - set(right)):
        (left if len(left) < len(right) else right).append(m)
    new = chains_to_assignments(leader, left, right)
    return task if new == tuple(sorted(task.assignments, key=lambda a: a.member)) else _with(task, new)


def _with(task: Task, assignments: tuple[Assignment, ...]) -> Task:
    return replace(task, assignments=assignments)


def assignment_of(task: Task, me: int) -> Assignment | None:
    for a in task.assignments:
        if a.member == me:
            return a
    return None


def chain_position(task: Task, me: int) -> int:
    """1 for a member that follows the leader, 2 for the next one, ... (0: none)."""
    return chain_of(task, me)[1]


def chain_of(task: Task, me: int) -> tuple[int, int]:
    """(the agent at the head of ``me``'s chain, ``me``'s position in it: :func:`chain_position`);
    (me, 0) for an agent that follows no one; a loop's head is where it closes."""
    follows = {a.member: a.follows for a in task.assignments}
    k, cur, seen = 0, me, set()
    while cur in follows and cur not in seen:
        seen.add(cur)
        cur = follows[cur]
        k += 1
    return cur, k


# -- the follow law -------------------------------------------------------------------


@dataclass(frozen=True)
class Setpoint:
    """A position target with velocity feed-forward (AMSL altitude, degrees)."""

    lat: float
    lon: float
    alt: float
    yaw_deg: float
    vn: float = 0.0
    ve: float = 0.0


def predict(pose: Pose, age_s: float, max_s: float) -> tuple[float, float]:
    """``pose``'s position ``age_s`` seconds later at its velocity."""
    dt = max(0.0, min(age_s, max_s))
    if dt == 0.0 or (pose.vn == 0.0 and pose.ve == 0.0):
        return pose.lat, pose.lon
    return offset(pose.lat, pose.lon, pose.vn * dt, pose.ve * dt)


def rotation_motion(
    dn: float, de: float, rate_dps: float, accel_dps2: float
) -> tuple[float, float, float, float]:
    """Velocity and acceleration (vn, ve, an, ae) of the point at offset (``dn``, ``de``)
    metres from a centre, as the V turns about it (clockwise, the heading growing) at
    ``rate_dps`` with the rate changing at ``accel_dps2``: w x r, and alpha x r plus the
    centripetal -w^2 r."""
    w, al = math.radians(rate_dps), math.radians(accel_dps2)
    return -w * de, w * dn, -al * de - w * w * dn, al * dn - w * w * de


def follow_target(
    followed: Pose,
    age_s: float,
    heading_deg: float,
    side: Side,
    cfg: FormationConfig,
    back_m: float | None = None,
    side_m: float | None = None,
    turn_rate_dps: float = 0.0,
    accel: tuple[float, float] = (0.0, 0.0),
    turn_accel_dps2: float = 0.0,
) -> Setpoint:
    """The member's setpoint: the followed agent predicted to now, plus the slot offset;
    velocity feed-forward: the followed velocity plus the slot's rotation about the
    followed agent when the swarm heading turns (``turn_rate_dps``). ``accel``: the
    followed agent's estimated acceleration (:func:`estimate_accel`), carried into the
    prediction and the feed-forward; ``turn_accel_dps2``: how fast the turn rate changes,
    so that the feed-forward also leads the slot's rotation as the V starts and stops
    turning (the tail of a V swings out a few metres per second in a turn: an autopilot
    that lags that change by its velocity loop's time falls metres behind)."""
    lat, lon = predict(followed, age_s + cfg.lead_s, cfg.max_predict_s)
    dt = max(0.0, min(age_s + cfg.lead_s, cfg.max_predict_s))
    an, ae = accel
    if an or ae:
        lat, lon = offset(lat, lon, 0.5 * an * dt * dt, 0.5 * ae * dt * dt)
        followed = replace(
            followed,
            vn=followed.vn + an * (dt + cfg.accel_lead_s),
            ve=followed.ve + ae * (dt + cfg.accel_lead_s),
        )
    back = cfg.back_m if back_m is None else back_m
    across = cfg.side_m if side_m is None else side_m
    lead = cfg.lead_s
    heading_deg = (heading_deg + turn_rate_dps * lead + 0.5 * turn_accel_dps2 * lead * lead) % 360.0
    dn, de = slot_offset(heading_deg, side, back, across)
    la, lo = offset(lat, lon, dn, de)
    # the slot's rotation about the followed agent, fed forward as the velocity is
    rvn, rve, ran, rae = rotation_motion(dn, de, turn_rate_dps, turn_accel_dps2)
    ahead = cfg.accel_lead_s
    vn, ve = followed.vn + rvn + ran * ahead, followed.ve + rve + rae * ahead
    return Setpoint(la, lo, followed.alt + cfg.stagger_m, heading_deg, vn, ve)


def carried_motion(
    head: Pose,
    head_accel: tuple[float, float],
    heading_deg: float,
    turn_rate_dps: float,
    turn_accel_dps2: float,
    side: Side,
    back_m: float,
    side_m: float,
    k: int,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """The velocity and acceleration ((vn, ve), (an, ae)) of the point ``k`` slots down
    one arm of the V from ``head`` (the leader) if the V moved as one rigid body: the
    head's motion plus the rotation of that point about it (:func:`rotation_motion`).

    A member further down an arm than the first takes this as its followed agent's motion
    instead of that agent's own reported velocity and acceleration (predecessor-leader
    following): the position it flies to is still its slot behind the agent it follows,
    but what it feeds forward is the leader's smooth motion, not the corrections of the
    members between them. Fed the followed agent's own motion, every member passed on the
    corrections of the one ahead, and an autopilot whose response overshoots its input
    amplified them down the arm (a string instability: on real ArduCopters the second of
    an arm flew 8.5 m/s behind a leader at 5.25 m/s; the simulator's well-damped vehicles
    hid it)."""
    dn, de = slot_offset(heading_deg, side, back_m, side_m)
    vn, ve, an, ae = rotation_motion(dn * k, de * k, turn_rate_dps, turn_accel_dps2)
    return (head.vn + vn, head.ve + ve), (head_accel[0] + an, head_accel[1] + ae)


def slot_error(
    member: Pose, followed: Pose, heading_deg: float, side: Side, back_m: float, side_m: float
) -> float:
    """Horizontal distance in metres between a member and its slot (both at one instant)."""
    dn, de = slot_offset(heading_deg, side, back_m, side_m)
    fn, fe = ne_between(followed.lat, followed.lon, member.lat, member.lon)
    return math.hypot(fn - dn, fe - de)


#: the shortest span of pose velocities an acceleration is estimated over (a pose's velocity
#: is quantised to 0.25 m/s: over 1 s that is 0.25 m/s^2), the largest believed, and the
#: smallest acted on
ACCEL_SPAN_S = 1.0
ACCEL_MAX = 4.0
ACCEL_DEADBAND = 0.15


def estimate_accel(history: Sequence[tuple[float, float, float]]) -> tuple[float, float]:
    """A followed agent's acceleration (north, east m/s^2) from its recent pose velocities,
    ``(sample time, vn, ve)`` oldest first: the newest against the newest at least
    ``ACCEL_SPAN_S`` older; (0, 0) without such a pair, below ``ACCEL_DEADBAND`` or beyond
    ``ACCEL_MAX`` (a velocity that jumped: not believed)."""
    if len(history) < 2:
        return 0.0, 0.0
    t1, vn1, ve1 = history[-1]
    old = [h for h in history[:-1] if t1 - h[0] >= ACCEL_SPAN_S]
    if not old:
        return 0.0, 0.0
    t0, vn0, ve0 = old[-1]
    an, ae = (vn1 - vn0) / (t1 - t0), (ve1 - ve0) / (t1 - t0)
    mag = math.hypot(an, ae)
    if mag < ACCEL_DEADBAND or mag > ACCEL_MAX:
        return 0.0, 0.0
    return an, ae


@dataclass
class AccelEstimator:
    """Each sender's acceleration from its last ``keep_s`` of pose velocities (:func:`estimate_accel`)."""

    keep_s: float = 2.0
    _hist: dict[int, list[tuple[float, float, float]]] = field(default_factory=dict)

    def add(self, sender: int, t: float, vn: float, ve: float) -> tuple[float, float]:
        """Note a pose velocity sampled at ``t``; the acceleration estimated now."""
        hist = [h for h in self._hist.get(sender, []) if t - h[0] <= self.keep_s] + [(t, vn, ve)]
        self._hist[sender] = hist
        return estimate_accel(hist)


def circular_floor(values: Sequence[float], wrap: float) -> float:
    """The smallest of ``values`` (each in ``[0, wrap)``) taken around a circle of
    circumference ``wrap``: the value just after the widest empty arc. Delays measured
    modulo the wrap straddle it for some clock offsets (2.45, 2.50, then 0.14, 0.39...):
    there the plain minimum (0.14) is not the smallest delay (2.45)."""
    v = sorted(values)
    if not v:
        raise ValueError("circular_floor of nothing")
    best, floor = v[0] + wrap - v[-1], v[0]  # the arc across the wrap
    for a, b in itertools.pairwise(v):
        if b - a > best:
            best, floor = b - a, b
    return floor


@dataclass
class AgeEstimator:
    """Age of a sender's pose from its wrapped sample time (see the module docstring):
    its delay (modulo the wrap) beyond the smallest of the last ``window_s``, the
    smallest taken around the wrap (:func:`circular_floor`)."""

    window_s: float = 30.0
    _seen: dict[int, collections.deque[tuple[float, float]]] = field(default_factory=dict)

    def age(self, sender: int, t_wrapped: float, now: float) -> float:
        d = (now - t_wrapped) % POSE_T_WRAP
        hist = self._seen.setdefault(sender, collections.deque())
        hist.append((now, d))
        while hist[0][0] < now - self.window_s:
            hist.popleft()
        age = (d - circular_floor([x[1] for x in hist], POSE_T_WRAP)) % POSE_T_WRAP
        return age if age < POSE_T_WRAP / 2 else 0.0  # a wrap we cannot tell: trust it fresh


# -- the leader's route -------------------------------------------------------------


@dataclass(frozen=True)
class RoutePoint:
    n: float
    e: float
    heading_deg: float
    curvature: float = 0.0  # degrees of heading per metre along the route (+: turning right)


@dataclass(frozen=True)
class _Seg:
    length: float
    # line: start (n, e), unit direction; arc: centre, radius, start angle, turn sign
    kind: str
    a: tuple[float, float]
    b: tuple[float, float]
    r: float = 0.0
    sign: float = 0.0
    h0: float = 0.0  # heading at the start, unwrapped along the route (degrees)
    k: float = 0.0  # heading change per metre (degrees, +: turning right)


class Route:
    """A path through waypoints (local north/east metres from an origin), corners
    rounded with ``turn_radius_m``, sampled by distance along it."""

    def __init__(self, points: Sequence[tuple[float, float]], turn_radius_m: float = 10.0) -> None:
        pts = [p for i, p in enumerate(points) if i == 0 or math.dist(p, points[i - 1]) > 1e-6]
        if len(pts) < 2:
            raise ValueError("a route needs at least two distinct points")
        if not (math.isfinite(turn_radius_m) and turn_radius_m >= 0):
            raise ValueError(f"turn radius {turn_radius_m!r} must be >= 0")
        self.segments: list[_Seg] = []
        start = pts[0]
        for i in range(1, len(pts)):
            p, q = pts[i], pts[i + 1] if i + 1 < len(pts) else None
            d1 = _unit(pts[i - 1], p)
            if q is None:
                self._line(start, p)
                break
            d2 = _unit(p, q)
            turn = math.atan2(d1[0] * d2[1] - d1[1] * d2[0], d1[0] * d2[0] + d1[1] * d2[1])
            if abs(turn) < 1e-6 or turn_radius_m == 0:
                self._line(start, p)
                start = p
                continue
            t = turn_radius_m * math.tan(abs(turn) / 2)
            t = min(t, 0.5 * math.dist(pts[i - 1], p), 0.5 * math.dist(p, q))
            r = t / math.tan(abs(turn) / 2)
            a = (p[0] - d1[0] * t, p[1] - d1[1] * t)
            self._line(start, a)
            sign = 1.0 if turn > 0 else -1.0  # +: turning right (clockwise, seen from above, n/e axes)
            # centre: to the right of d1 for a right turn
            right = (-d1[1], d1[0])
            c = (a[0] + sign * right[0] * r, a[1] + sign * right[1] * r)
            ang0 = math.atan2(a[1] - c[1], a[0] - c[0])
            self.segments.append(_Seg(r * abs(turn), "arc", c, (ang0, turn), r, sign))
            start = (p[0] + d2[0] * t, p[1] + d2[1] * t)
        self.length = sum(s.length for s in self.segments)
        self._unwrap()

    def _unwrap(self) -> None:
        """Each segment's start heading, unwrapped from the one before (no 360 jumps), and
        its heading change per metre."""
        out: list[_Seg] = []
        end: float | None = None
        for seg in self.segments:
            if seg.kind == "line":
                raw, k = heading_of(*seg.b), 0.0
            else:
                ang0, turn = seg.b
                sgn = math.copysign(1.0, turn)
                raw, k = (
                    heading_of(-math.sin(ang0) * sgn, math.cos(ang0) * sgn),
                    sgn * math.degrees(1 / seg.r),
                )
            h0 = raw if end is None else end + (raw - end + 180.0) % 360.0 - 180.0
            out.append(replace(seg, h0=h0, k=k))
            end = h0 + k * seg.length
        self.segments = out

    def _heading(self, s: float) -> float:
        """The unwrapped heading ``s`` metres along (straight on beyond both ends)."""
        for seg in self.segments:
            if s <= seg.length or seg is self.segments[-1]:
                return seg.h0 + seg.k * max(0.0, min(s, seg.length))
            s -= seg.length
        raise AssertionError("unreachable")  # pragma: no cover

    def _heading_integral(self, s: float) -> float:
        """The integral of the unwrapped heading from 0 to ``s`` (degree-metres)."""
        if s <= 0.0:
            return self.segments[0].h0 * s
        total = 0.0
        for seg in self.segments:
            x = min(s, seg.length)
            total += seg.h0 * x + 0.5 * seg.k * x * x
            s -= seg.length
            if s <= 0.0:
                return total
        last = self.segments[-1]
        return total + (last.h0 + last.k * last.length) * s

    def mean_heading(self, s: float, half_m: float) -> tuple[float, float]:
        """The route's heading averaged over ``s - half_m .. s + half_m`` (0..360) and how
        fast that average changes, in degrees per metre of ``s`` (see the module docstring)."""
        if half_m <= 0.0:
            return self._heading(s) % 360.0, 0.0
        lo, hi = s - half_m, s + half_m
        mean = (self._heading_integral(hi) - self._heading_integral(lo)) / (2.0 * half_m)
        return mean % 360.0, (self._heading(hi) - self._heading(lo)) / (2.0 * half_m)

    def _line(self, a: tuple[float, float], b: tuple[float, float]) -> None:
        length = math.dist(a, b)
        if length > 1e-9:
            self.segments.append(_Seg(length, "line", a, _unit(a, b)))

    def at(self, s: float) -> RoutePoint:
        """Where the route is ``s`` metres from its start (clamped to its ends)."""
        s = max(0.0, min(s, self.length))
        for seg in self.segments:
            if s <= seg.length or seg is self.segments[-1]:
                s = min(s, seg.length)
                if seg.kind == "line":
                    (n0, e0), (dn, de) = seg.a, seg.b
                    return RoutePoint(n0 + dn * s, e0 + de * s, heading_of(dn, de))
                ang0, turn = seg.b
                ang = ang0 + math.copysign(s / seg.r, turn)
                n = seg.a[0] + seg.r * math.cos(ang)
                e = seg.a[1] + seg.r * math.sin(ang)
                # tangent: derivative of the position along the turn's direction
                tn, te = -math.sin(ang) * math.copysign(1, turn), math.cos(ang) * math.copysign(1, turn)
                return RoutePoint(n, e, heading_of(tn, te), math.copysign(math.degrees(1.0 / seg.r), turn))
            s -= seg.length
        raise AssertionError("unreachable")  # pragma: no cover


def turn_window_m(speed_mps: float, turn_radius_m: float, accel_dps2: float) -> float:
    """Half the window :meth:`Route.mean_heading` averages over, so that at ``speed_mps``
    the heading's rate ramps into a corner of ``turn_radius_m`` at ``accel_dps2``:
    the rate steps by v/r (degrees/s) and the average spreads the step over the window,
    ``2 half / v`` seconds. Sharp corners (radius under 1 m) count as 1 m; at most 100 m."""
    step_dps = math.degrees(speed_mps / max(turn_radius_m, 1.0))
    return min(100.0, speed_mps * step_dps / (2.0 * accel_dps2))


def steer_heading(
    heading: float, rate: float, target: float, target_rate: float, accel_dps2: float, dt: float
) -> tuple[float, float]:
    """One step of ``dt`` of a heading (and its rate, degrees/s) toward ``target`` moving at
    ``target_rate``: the rate wanted is the target's plus a square-root controller on the
    error (proportional with a gain of 1/s near it, so that braking at ``accel_dps2``
    stops on it), reached at most at ``accel_dps2``. Returns (heading 0..360, rate)."""
    err = (target - heading + 180.0) % 360.0 - 180.0
    linear = accel_dps2  # the error below which the controller is proportional (gain 1/s)
    if abs(err) <= linear:
        fix = err
    else:
        fix = math.copysign(math.sqrt(2.0 * accel_dps2 * (abs(err) - linear / 2.0)), err)
    step = accel_dps2 * dt
    rate = max(rate - step, min(rate + step, target_rate + fix))
    return (heading + rate * dt) % 360.0, rate


def _unit(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
    d = math.dist(a, b)
    return (b[0] - a[0]) / d, (b[1] - a[1]) / d


__all__ = [
    "AccelEstimator",
    "AgeEstimator",
    "FormationConfig",
    "Route",
    "RoutePoint",
    "Setpoint",
    "arms",
    "assign",
    "assignment_of",
    "carried_motion",
    "chain_of",
    "chain_position",
    "chains_to_assignments",
    "circular_floor",
    "distance",
    "estimate_accel",
    "follow_target",
    "heading_of",
    "ne_between",
    "offset",
    "predict",
    "reconcile",
    "rotation_motion",
    "slot_error",
    "slot_offset",
    "steer_heading",
    "turn_window_m",
]
