"""What the station knows of the swarm's plan: each agent's route and go-to target, the leader's task.

Theory of operation
-------------------
The page draws the plan the swarm is flying (issue 13, "plan view"); the station
keeps what it can know of it, from what it sent and what it heard:

* **Routes** (:meth:`PlanBook.command`): a GOTO to an agent replaces its route with
  one point (the go-to target), a WAYPOINT appends one (at most :data:`ROUTE_MAX`;
  the oldest dropped), whether this station sent it (:meth:`StationCore.submit
  <swarm.core.station.core.StationCore.submit>`) or it heard another station send it. A
  route ends when the agent says "arrived" (its own notice, :meth:`PlanBook.notice`),
  when it is sent STOP, LAND, RETURN or DISARM (the swarm's STOP ends every route),
  and when the agent refused the command that set the route's last point
  (:meth:`PlanBook.refused`). Earlier versions' AMSL kinds are never drawn (agents
  refuse them). A heard Command is a hostile sender's: a target outside 1..250 or a
  point that is not a finite latitude and longitude is ignored.
* **Task** (:meth:`PlanBook.heartbeat`): the leader's Heartbeat carries the
  formation task: FOLLOW with the swarm's heading, the back and side distances and
  who follows whom on which side. The newest task of each sender is kept; the state
  shows the current leader's only (:meth:`PlanBook.task_dict`,
  :meth:`PlanBook.slots_list`), as two fields so the delta pushes resend the
  (rarely changing) assignments only when they change and not at every turn of the
  heading. The page computes each slot from the followed agent's position, so no
  per-push position crosses the WebSocket for it.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import math

from swarm.core.station.rows import TaskRow
from swarm.core.wire.message_types import Command, CommandKind, Heartbeat, Task, TaskKind

#: a route keeps at most this many points (the newest)
ROUTE_MAX = 32
#: commands after which an agent flies no route
ENDS_ROUTE = frozenset({CommandKind.STOP, CommandKind.LAND, CommandKind.RETURN, CommandKind.DISARM})
#: the agent's own notice when it reached the end of its route (swarm.core.flight.pilot)
ARRIVED = "arrived"


def _point(cmd: Command) -> tuple[float, float, float] | None:
    lat, lon, alt = cmd.lat, cmd.lon, cmd.alt
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (lat, lon, alt)):
        return None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0) or (lat == 0.0 and lon == 0.0):
        return None
    return (round(lat, 7), round(lon, 7), round(alt, 1))


class PlanBook:
    """Routes by agent id, the task by sender. See the module docstring."""

    def __init__(self) -> None:
        self.routes: dict[int, list[tuple[float, float, float]]] = {}
        self._last: dict[int, tuple[int, int]] = {}  # agent -> (sender, seq) that set the route's end
        self.tasks: dict[int, Task] = {}

    def command(self, cmd: Command) -> None:
        """A Command sent (by this station or another one)."""
        to = cmd.target
        if cmd.kind in ENDS_ROUTE:
            if to == 0:
                if cmd.kind == CommandKind.STOP:
                    self.routes.clear()
                    self._last.clear()
            else:
                self.end(to)
            return
        if cmd.kind not in (CommandKind.GOTO, CommandKind.WAYPOINT) or not 1 <= to <= 250:
            return
        p = _point(cmd)
        if p is None:
            return
        route = self.routes.get(to)
        if cmd.kind == CommandKind.GOTO or route is None:
            route = self.routes[to] = []
        if route and route[-1] == p and self._last.get(to) == (cmd.sender, cmd.seq):
            return  # the same command again (a retry heard)
        route.append(p)
        del route[:-ROUTE_MAX]
        self._last[to] = (cmd.sender, cmd.seq)

    def refused(self, agent: int, cmd: Command) -> None:
        """``agent`` refused ``cmd``: the point it set is not flown to."""
        if self._last.get(agent) == (cmd.sender, cmd.seq):
            route = self.routes.get(agent, [])
            if route:
                route.pop()
            if not route:
                self.end(agent)

    def notice(self, agent: int, text: str) -> None:
        """One of ``agent``'s own notices: "arrived" ends its route."""
        if text.startswith(ARRIVED):
            self.end(agent)

    def end(self, agent: int) -> None:
        self.routes.pop(agent, None)
        self._last.pop(agent, None)

    def route_list(self, agent: int) -> list[list[float]] | None:
        """``agent``'s route as ``[[lat, lon, alt above home]...]``, the target last; None without one."""
        route = self.routes.get(agent)
        return [list(p) for p in route] if route else None

    def heartbeat(self, hb: Heartbeat) -> None:
        """A leader's Heartbeat (heard on its way to a member)."""
        if 1 <= hb.sender <= 250:
            self.tasks[hb.sender] = hb.task

    def forget(self, agent: int) -> None:
        self.tasks.pop(agent, None)

    def task_dict(self, leader: int) -> TaskRow | None:
        """The leader's FOLLOW task (heading in 0.5 degree steps, distances in metres); None otherwise."""
        t = self.tasks.get(leader)
        if t is None or t.kind != TaskKind.FOLLOW:
            return None
        return {
            "leader": leader,
            "heading": round(2.0 * (t.heading % 360.0)) / 2.0 % 360.0,
            "back": round(t.back_m, 1),
            "side": round(t.side_m, 1),
        }

    def slots_list(self, leader: int) -> list[list[int]] | None:
        """The leader's FOLLOW assignments as ``[[member, follows, side (-1 left, 1 right)]...]``."""
        t = self.tasks.get(leader)
        if t is None or t.kind != TaskKind.FOLLOW:
            return None
        return [[a.member, a.follows, int(a.side)] for a in sorted(t.assignments, key=lambda a: a.member)]
