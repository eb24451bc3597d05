"""The picture of a formation flight, read at a glance: a map and the slot error over time.

Theory of operation
-------------------
:func:`plot` takes an :class:`swarm.sim.tracks.Analysis` (tracks, tasks, slot errors and
the counted interval, all from the capture) and draws two panels with matplotlib's Agg
backend (no display needed), one colour per agent in both:

* the **map** (east, north in metres from the leader's first pose): each agent's track
  during the counted interval (from the route's start to the end of the follow task);
  what came before and after (take-off, the V forming, landing) thin and grey, apart
  from the route; the leader's track thick with arrows along it, its turn stretches
  (within the turn margin of a heading change) shaded; a start (circle) and an end
  (star) marker, both in the legend; the slots every ``slot_every_s`` seconds (crosses,
  with a thin line to the agent followed);
* the **slot error over time**: each member's error at its pose samples, seconds from
  the route's start, the turns shaded and the target as a dashed line.

The title names the figures with their legs and interval (:data:`swarm.sim.tracks.FIGURES`).
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from swarm.core.flight.formation import ne_between, slot_offset
from swarm.core.wire.message_types import TaskKind

if TYPE_CHECKING:
    from swarm.sim.tracks import Analysis

NE = Callable[[tuple[float, float]], tuple[float, float]]
GREY = "#9a9a9a"
TURN = "#f4b183"


def _colour(agent: int) -> str:
    return f"C{(agent - 1) % 10}"


def _in_turn(t: float, windows: list[tuple[float, float]]) -> bool:
    return any(a <= t <= b for a, b in windows)


def _tracks(ax: Any, an: Analysis, ne: NE, t0: float, t1: float) -> None:
    """Each agent's track: the counted interval in its colour, the rest thin and grey."""
    grey_said = False
    leader_route: list[tuple[float, float, float]] = []
    for agent, track in sorted(an.tracks.items()):
        lead = agent == an.leader
        pts = [(t, *ne((p.lat, p.lon))) for t, p in track]
        for part in ([x for x in pts if x[0] < t0], [x for x in pts if x[0] > t1]):
            if part:
                label = None if grey_said else "take-off, V forming, landing"
                grey_said = True
                ax.plot([e for _t, _n, e in part], [n for _t, n, _e in part], color=GREY, lw=0.6, label=label)
        route = [x for x in pts if t0 <= x[0] <= t1]
        if not route:
            continue
        xs, ys = [e for _t, _n, e in route], [n for _t, n, _e in route]
        name = f"agent {agent}" + (" (leader)" if lead else "")
        ax.plot(xs, ys, lw=2.5 if lead else 1.2, color=_colour(agent), label=name)
        if lead:
            leader_route = route
    if leader_route:  # after every track: the legend lists the agents first
        _leader_marks(ax, leader_route, an.turn_windows)


def _leader_marks(
    ax: Any, route: list[tuple[float, float, float]], windows: list[tuple[float, float]]
) -> None:
    """Turn shading, direction arrows every 20 m, start and end markers on the leader's route."""
    turn = [(e, n) for t, n, e in route if _in_turn(t, windows)]
    if turn:
        ax.scatter([e for e, _n in turn], [n for _e, n in turn], s=90, color=TURN, alpha=0.5, lw=0, zorder=1)
        ax.scatter([], [], s=90, color=TURN, label="turn (leader shaded)")
    run = 0.0
    for (_ta, na, ea), (_tb, nb, eb) in itertools.pairwise(route):
        run += math.hypot(nb - na, eb - ea)
        if run >= 20.0 and math.hypot(nb - na, eb - ea) > 0.05:
            run = 0.0
            ax.annotate(
                "",
                xy=(eb, nb),
                xytext=(ea, na),
                arrowprops={"arrowstyle": "-|>", "color": "black", "lw": 1.2},
            )
    ax.plot(route[0][2], route[0][1], marker="o", ms=11, color="green", ls="", label="start of route")
    ax.plot(route[-1][2], route[-1][1], marker="*", ms=16, color="black", ls="", label="end")


def _slots(ax: Any, an: Analysis, ne: NE, t0: float, t1: float, every_s: float) -> None:
    """Every ``every_s`` in the interval: each member's slot (a red x) and the line from the
    agent it follows to it."""
    times = {a: [x[0] for x in tr] for a, tr in an.tracks.items()}
    task_t = [t for t, _l, _task in an.tasks]
    t, said = t0, False
    while t <= t1:
        k = bisect.bisect_right(task_t, t) - 1
        task = an.tasks[max(k, 0)][2]
        for a in task.assignments if k >= 0 and task.kind == TaskKind.FOLLOW else ():
            if a.follows not in an.tracks:
                continue
            fp = _position_at(an, a.follows, t, times[a.follows])
            if fp is None:
                continue
            fn, fe = ne(fp)
            dn, de = slot_offset(task.heading, a.side, task.back_m, task.side_m)
            ax.plot([fe, fe + de], [fn, fn + dn], color="grey", lw=0.5)
            label = None if said else f"slot (every {every_s:g} s)"
            said = True
            ax.plot(fe + de, fn + dn, marker="x", color="red", ms=5, ls="", label=label)
        t += every_s


def _position_at(an: Analysis, agent: int, t: float, times: list[float]) -> tuple[float, float] | None:
    from swarm.sim.tracks import position_at

    return position_at(an.tracks[agent], t, times)


def _errors(ax: Any, an: Analysis, t0: float, target_m: float | None) -> None:
    """Each member's slot error over time, turns shaded, the target dashed."""
    for m in sorted({m for _t, m, _e, _turn in an.errors}):
        pts = [(t - t0, e) for t, mm, e, _turn in an.errors if mm == m]
        ax.plot([t for t, _e in pts], [e for _t, e in pts], lw=0.9, color=_colour(m), label=f"agent {m}")
    for k, (a, b) in enumerate(an.turn_windows):
        ax.axvspan(a - t0, b - t0, color=TURN, alpha=0.35, lw=0, label=None if k else "turn")
    if target_m is not None:
        ax.axhline(target_m, color="black", ls="--", lw=1.0, label=f"target RMS {target_m:g} m")
    ax.set_xlabel("time from the route's start (s)")
    ax.set_ylabel("slot error (m)")
    ax.set_ylim(bottom=0)
    ax.grid(True, lw=0.3)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("slot error over time, per member", fontsize=9)


def figure(an: Analysis, *, slot_every_s: float = 10.0, title: str = "", target_m: float | None = 1.5) -> Any:
    """The two panels as a matplotlib figure (Agg; the caller saves and closes it).

    Raises:
        ValueError: nothing to draw (no pose in the capture).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from swarm.sim.tracks import fmt

    if not an.tracks:
        raise ValueError("no pose stream in the capture: nothing to draw")
    ref_track = an.tracks.get(an.leader) or next(iter(an.tracks.values()))
    lat0, lon0 = ref_track[0][1].lat, ref_track[0][1].lon

    def ne(p: tuple[float, float]) -> tuple[float, float]:
        return ne_between(lat0, lon0, p[0], p[1])

    t_all = [t for tr in an.tracks.values() for t, _p in tr]
    t0 = an.t_from if an.t_from is not None else min(t_all)
    t1 = an.errors[-1][0] if an.errors else max(t_all)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 6.2), dpi=80, width_ratios=(1.0, 1.1))
    _tracks(ax, an, ne, t0, t1)
    if an.follow_at is not None and an.tasks:
        _slots(ax, an, ne, t0, t1, slot_every_s)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("tracks (colour: the route; grey: before and after)", fontsize=9)
    _errors(ax2, an, t0, target_m)
    s = an.summary()
    default = (
        f"leader agent {an.leader}; slot error from the route's start to the end of the follow task "
        f"({fmt(s['interval']['duration_s'], ' s')}): straight legs RMS {fmt(s['formation_rms_m'])} "
        f"(formation_rms_m), max {fmt(s['formation_max_m'])}; turns max {fmt(s['turn_max_m'])}"
    )
    fig.suptitle(title or default, fontsize=10)
    fig.tight_layout()
    return fig


def plot(
    an: Analysis, out: str, *, slot_every_s: float = 10.0, title: str = "", target_m: float | None = 1.5
) -> str:
    """Draw :func:`figure` to ``out`` (PNG). Returns ``out``.

    Raises:
        OSError: the file cannot be written.
        ValueError: nothing to draw (no pose in the capture).
    """
    fig = figure(an, slot_every_s=slot_every_s, title=title, target_m=target_m)
    import matplotlib.pyplot as plt  # after figure() chose the Agg backend

    try:
        fig.savefig(out)
    finally:
        plt.close(fig)
    return out


__all__ = ["figure", "plot"]
