"""Formation tracks and metrics from a radio capture, and their picture.

Theory of operation
-------------------
Everything the swarm puts on the air is in the capture (``.tlog``): each agent's
pose stream (PoseReport in TUNNEL frames) and the leader's Heartbeats with the
swarm task (heading, assignments). :func:`analyse` rebuilds from it:

* each agent's **track**: its poses at their sample times. A pose carries its
  sample time modulo 2.56 s in the sender's clock; the capture stamps the air
  time. Per sender, the delay (air time - sample time) modulo 2.56 s is smallest
  (taken around the wrap: :func:`swarm.core.flight.formation.circular_floor`) for the pose
  that waited least; the sample time of every pose is its air time
  minus its delay beyond that smallest one (the smallest, a few tens of
  milliseconds of serial and air time, is ignored);
* the **task timeline**: which leader, heading and assignments held when;
* each member's **slot error** at each of its pose samples: the distance from
  the slot (the followed agent's position, interpolated at the same instant,
  plus the slot offset for the task heading then), counted over one interval:
  from the **route's start** (the leader's first pose faster than
  ``MOVING_MPS`` after the first follow task: it hovers while the V forms; when
  it never moves, the first follow task + ``settle_s``) to the **end of the
  follow task** (the swarm STOP after the leader's arrival + tail). A sample is
  in a *turn* when the task heading changed within ``turn_margin_s`` of it; the
  others are *straight* (a change counts once the heading is :data:`TURN_MIN_DEG`
  from the last counted: settling by hundredths of a degree is not turning).
  :data:`FIGURES` names each figure with its legs and interval, in the words every
  report uses (``swarm demo``, ``swarm replay --plot``; ``swarm bench formation``
  measures the same figures in virtual time);
* the **heading error after the turn** (when the task heading turned): the last
  follow task's heading against the leader's course over ground on its last
  straight stretch (its last ``course_s`` seconds faster than 1 m/s), which is the
  route's last heading whatever the route was.

:func:`swarm.sim.trackplot.plot` draws two panels with matplotlib's Agg backend (no display needed).
Left, the map (local metres from the leader's first pose): each agent's track
during the counted interval (take-off, the V forming and landing drawn thin and
grey, apart from it), the leader's thick with arrows along it, its straight legs
and turns told apart (turn stretches shaded), a start (circle) and end (star)
marker, both in the legend, and the slots every ``slot_every_s`` seconds (crosses,
with a thin line to the agent followed). Right, each member's slot error over
time (seconds from the route's start) with the target line and the turns shaded.

Nothing here raises for a damaged capture: the whole records before the damage
are used and ``damaged`` says where it stopped.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from typing import Any

from radios.errors import CaptureError
from radios.mavlink import MSG_TUNNEL
from radios.tlog import read_tlog
from swarm.core.flight.formation import POSE_T_WRAP, circular_floor, ne_between, slot_error
from swarm.core.wire.message_types import Heartbeat, Pose, PoseReport, Task, TaskKind
from swarm.core.wire.messages import decode
from swarm.core.wire.tunnel import Kind, unpack_tunnel
from swarm.errors import DecodeError

KIND_P2P, KIND_POSE, KIND_MULTI = Kind.P2P, Kind.POSE, Kind.MULTI

#: the leader moves faster than this once the route has started (it hovers while the V forms)
MOVING_MPS = 1.0
#: a change of the task heading counts as turning once it is this far from the heading last
#: counted: the leader's heading settling by hundredths of a degree after a turn (or a
#: 0.01 degree step at the route's start) is not a turn, and counted as one it turned a
#: whole route into "turns" and left only the hover after arrival as "straight legs"
TURN_MIN_DEG = 1.0


def turn_changes(headings: list[tuple[float, float]]) -> list[float]:
    """The times (ascending) at which a heading timeline ``(t, degrees)`` has turned by
    :data:`TURN_MIN_DEG` or more since the last such time (or its start)."""
    out: list[float] = []
    ref: float | None = None
    for t, h in headings:
        if ref is None:
            ref = h
        elif abs((h - ref + 180.0) % 360.0 - 180.0) >= TURN_MIN_DEG:
            out.append(t)
            ref = h
    return out


#: each formation figure: which legs, which interval (the same words in every report)
INTERVAL = "from the route's start to the end of the follow task (the leader's arrival + tail)"
FIGURES = {
    "formation_rms_m": f"RMS slot error on the straight legs, {INTERVAL}",
    "formation_max_m": f"largest slot error on the straight legs, {INTERVAL}",
    "turn_max_m": f"largest slot error in the turns (within 8 s of a heading change), {INTERVAL}",
    "route_rms_m": f"RMS slot error on the whole route, turns included, {INTERVAL}",
    "heading_error_after_turn_deg": "the last follow heading against the leader's course on its last "
    "straight stretch",
}

#: the same figures in a few words, for a line that names the interval once
LEGS = {
    "formation_rms_m": "RMS on the straight legs",
    "formation_max_m": "largest on the straight legs",
    "turn_max_m": "largest in the turns",
    "route_rms_m": "RMS on the whole route",
}


def fmt(v: float | None, unit: str = " m") -> str:
    """A figure for people: ``1.27 m``, or ``n/a`` when there was nothing to measure."""
    return "n/a" if v is None else f"{v:g}{unit}"


@dataclass
class Analysis:
    tracks: dict[int, list[tuple[float, Pose]]] = field(default_factory=dict)
    tasks: list[tuple[float, int, Task]] = field(default_factory=list)  # (t, leader, task)
    errors: list[tuple[float, int, float, bool]] = field(default_factory=list)  # t, member, m, turn
    records: int = 0
    damaged: str = ""
    follow_at: float | None = None
    heading_error_after_turn_deg: float | None = None
    #: the counted interval's start (capture time) and what it is ("route start" or "settled")
    t_from: float | None = None
    from_what: str = ""
    #: (from, to) capture times within the turn margin of a task heading change
    turn_windows: list[tuple[float, float]] = field(default_factory=list)

    @property
    def leader(self) -> int:
        return self.tasks[-1][1] if self.tasks else 0

    def summary(self) -> dict[str, Any]:
        straight = [e for _t, _m, e, turn in self.errors if not turn]
        turns = [e for _t, _m, e, turn in self.errors if turn]
        members = sorted({m for _t, m, _e, _turn in self.errors})
        per = {}
        for m in members:
            s = [e for _t, mm, e, turn in self.errors if mm == m and not turn]
            a = [e for _t, mm, e, _turn in self.errors if mm == m]
            per[str(m)] = {"rms_m": _rms(s), "max_m": round(max(a), 2) if a else None, "samples": len(a)}
        ends = [t for t, _m, _e, _turn in self.errors]
        return {
            "leader": self.leader,
            "agents": sorted(self.tracks),
            "records": self.records,
            "formation_rms_m": _rms(straight),
            "formation_max_m": round(max(straight), 2) if straight else None,
            "turn_max_m": round(max(turns), 2) if turns else None,
            "route_rms_m": _rms(straight + turns),
            "heading_error_after_turn_deg": self.heading_error_after_turn_deg,
            "samples": len(self.errors),
            "straight_samples": len(straight),
            "interval": {
                "from": self.from_what or None,
                "duration_s": round(ends[-1] - self.t_from, 1) if ends and self.t_from is not None else None,
            },
            "figures": FIGURES,
            "per_member": per,
            **({"damaged": self.damaged} if self.damaged else {}),
        }


def _rms(v: list[float]) -> float | None:
    return round(math.sqrt(sum(x * x for x in v) / len(v)), 3) if v else None


def read_capture(path: str) -> Analysis:
    """Tracks and tasks from a capture (no metrics yet).

    Raises:
        CaptureError: the file cannot be opened.
    """
    an = Analysis()
    raw: dict[int, list[tuple[float, Pose]]] = {}
    reader = read_tlog(path)
    try:
        for rec in reader:
            an.records += 1
            f = rec.frame
            if f.msgid != MSG_TUNNEL:
                continue
            try:
                tun = unpack_tunnel(f.payload)
                if tun is None:
                    continue
                kind, _target, _ids, body = tun
                if kind not in (KIND_POSE, KIND_P2P, KIND_MULTI):
                    continue
                msg = decode(body)
            except DecodeError:
                continue
            if kind == KIND_POSE and isinstance(msg, PoseReport):
                raw.setdefault(f.sysid, []).append((rec.t, msg.pose))
            elif isinstance(msg, Heartbeat) and msg.task.kind != TaskKind.NONE:
                if not an.tasks or an.tasks[-1][1:] != (msg.sender, msg.task):
                    an.tasks.append((rec.t, msg.sender, msg.task))
    except CaptureError as exc:
        an.damaged = str(exc)
    finally:
        reader.close()
    for sender, samples in raw.items():
        delays = [(t - pose.t) % POSE_T_WRAP for t, pose in samples]
        base = circular_floor(delays, POSE_T_WRAP)  # around the wrap: they may straddle it
        extra = [(d - base) % POSE_T_WRAP for d in delays]
        pairs = zip(samples, extra, strict=True)
        track = [(t - (x if x < POSE_T_WRAP / 2 else 0.0), pose) for (t, pose), x in pairs]
        track.sort(key=lambda x: x[0])
        an.tracks[sender] = track
    follows = [t for t, _l, task in an.tasks if task.kind == TaskKind.FOLLOW]
    an.follow_at = follows[0] if follows else None
    return an


def position_at(
    track: list[tuple[float, Pose]], t: float, times: list[float] | None = None, max_gap: float = 2.0
) -> tuple[float, float] | None:
    """(lat, lon) interpolated at ``t`` (None outside the track or across a gap)."""
    ts = times if times is not None else [x[0] for x in track]
    k = bisect.bisect_left(ts, t)
    if k == 0 or k >= len(ts):
        return None
    (t0, a), (t1, b) = track[k - 1], track[k]
    if t1 - t0 > max_gap:
        return None
    w = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
    return a.lat + (b.lat - a.lat) * w, a.lon + (b.lon - a.lon) * w


def analyse(
    path: str, *, settle_s: float = 15.0, turn_margin_s: float = 8.0, start: float | None = None
) -> Analysis:
    """Tracks, tasks and slot errors (see the module docstring). ``start``: count
    samples from this capture time (default: the route's start, :func:`route_start`)."""
    an = read_capture(path)
    if an.follow_at is None:
        return an
    if start is not None:
        an.t_from, an.from_what = start, "given time"
    else:
        rs = route_start(an)
        an.t_from, an.from_what = (
            (rs, "route start") if rs is not None else (an.follow_at + settle_s, "settled")
        )
    t_from = an.t_from
    times = {a: [x[0] for x in tr] for a, tr in an.tracks.items()}
    task_t = [t for t, _l, _task in an.tasks]
    changes: list[float] = []
    run: list[tuple[float, float]] = []  # one unbroken run of follow tasks
    for t, _l, task in [*an.tasks, (math.inf, 0, Task())]:
        if task.kind == TaskKind.FOLLOW:
            run.append((t, task.heading))
            continue
        changes += turn_changes(run)
        run = []
    for c in changes:  # merged: one window per turn
        if an.turn_windows and c - turn_margin_s <= an.turn_windows[-1][1]:
            an.turn_windows[-1] = (an.turn_windows[-1][0], c + turn_margin_s)
        else:
            an.turn_windows.append((c - turn_margin_s, c + turn_margin_s))
    for member, track in an.tracks.items():
        for t, pose in track:
            if t < t_from:
                continue
            k = bisect.bisect_right(task_t, t) - 1
            if k < 0:
                continue
            _t0, _leader, task = an.tasks[k]
            if task.kind != TaskKind.FOLLOW:
                continue
            a = next((x for x in task.assignments if x.member == member), None)
            if a is None or a.follows not in an.tracks:
                continue
            fp = position_at(an.tracks[a.follows], t, times[a.follows])
            if fp is None:
                continue
            followed = Pose(fp[0], fp[1], pose.alt)
            err = slot_error(pose, followed, task.heading, a.side, task.back_m, task.side_m)
            j = bisect.bisect_left(changes, t - turn_margin_s)
            turn = j < len(changes) and changes[j] <= t + turn_margin_s
            an.errors.append((t, member, err, turn))
    an.errors.sort()
    if changes:
        an.heading_error_after_turn_deg = heading_error(an)
    return an


def route_start(an: Analysis) -> float | None:
    """The route's start: the leader's first pose faster than ``MOVING_MPS`` after the
    first follow task (None: no follow task, or the leader never moved)."""
    if an.follow_at is None:
        return None
    return next(
        (
            t
            for t, p in an.tracks.get(an.leader, [])
            if t > an.follow_at and math.hypot(p.vn, p.ve) > MOVING_MPS
        ),
        None,
    )


def heading_error(an: Analysis, course_s: float = 5.0) -> float | None:
    """The last follow task's heading minus the leader's last course (module docstring),
    in degrees (absolute); None without a follow task or a straight stretch of 2 m."""
    follows = [task for _t, _l, task in an.tasks if task.kind == TaskKind.FOLLOW]
    moving = [(t, p) for t, p in an.tracks.get(an.leader, []) if math.hypot(p.vn, p.ve) > 1.0]
    if not follows or not moving:
        return None
    t_end, last = moving[-1]
    first = next(p for t, p in moving if t >= t_end - course_s)
    dn, de = ne_between(first.lat, first.lon, last.lat, last.lon)
    if math.hypot(dn, de) < 2.0:
        return None
    course = math.degrees(math.atan2(de, dn))
    return round(abs((follows[-1].heading - course + 180.0) % 360.0 - 180.0), 2)


__all__ = [
    "FIGURES",
    "INTERVAL",
    "LEGS",
    "Analysis",
    "analyse",
    "fmt",
    "heading_error",
    "position_at",
    "read_capture",
    "route_start",
    "turn_changes",
]
