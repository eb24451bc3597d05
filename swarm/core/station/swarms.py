"""The swarms as the ground station sees them: each leader, its members, its colour.

Theory of operation
-------------------
A swarm is a leader and the agents that follow it. The station learns who follows
whom from each agent's own words: its AgentState or Telemetry names its phase and its
leader. :meth:`SwarmBook.update` (called by :class:`swarm.core.station.core.StationCore`
whenever a connection, a phase or a leader changed) groups the connected agents in
phase LEADER or MEMBER by the leader they name; each group whose leader is itself a
connected agent the station knows is a swarm. The leader's own Heartbeat list (heard on
its way to the members) adds the agents it names that say nothing else: an agent's own
AgentState wins over another agent's list, so no agent is in two swarms.

* ``leader`` (:attr:`SwarmBook.leader`): the swarm most connected agents follow (ties:
  the highest id; none when the most followed leader is not connected), the one
  leader of the station's state before there were several. Its computation is the
  station's of old, unchanged, so a one-swarm deployment reads as before.
* ``swarms`` (:meth:`SwarmBook.as_list`): one entry per leader, sorted by leader id:
  ``{"leader", "members" (the leader included), "colour"}``; each other swarm's
  FOLLOW task and slots in ``swarm_tasks`` and ``swarm_slots`` (:meth:`SwarmBook.plans`),
  apart, so a turning heading resends a task and not every member list. The
  colour is a small integer, stable while the swarm lives: a new swarm takes the
  colour of a swarm that just vanished and shared most of its members (a re-election
  keeps the colour), else the lowest free one. The page maps it to its palette.
* :func:`fleet_colours`: one colour per swarm across stations. Each station numbers
  its swarms' colours from 0 (above), so on a page that merges several stations' swarms
  two of them could share a colour, and one swarm could show different colours on two
  pages. The merged view's colour is a pure function of what every page is given, the
  swarms' ``(station, colour)`` (the station's own, stable through re-elections): each
  swarm prefers ``(h(station) + colour) % PALETTE`` (``h``: the first byte of the name's
  SHA-256, the same in every process); in the order ``(colour, station, leader)`` (a
  station's first swarms choose first, so a new swarm rarely moves an old one), each
  takes its preferred colour if it is free, else the next free one around the
  :data:`PALETTE` colours, else the lowest free one beyond (the page makes more). Every
  page that shows the same swarms shows them in the same colours, all distinct.
* :meth:`SwarmBook.leader_for` names the leader a group of agents follows now (the swarm
  holding most of them): a swarm command in flight follows its members' new leader.
* :func:`swarm_plan`: the Commands a swarm command becomes, to one swarm (its leader
  id) or to all; FOLLOW to all is refused while there are several swarms (they would
  fly one heading from near each other and meet). :meth:`SwarmBook.take_news` is the
  log's line when the leaders change while there are several swarms.

Hostile input is bounded by construction: a leader must be a known, connected agent
(ids 1..250, at most one swarm per agent), members are agents the station knows, and a
Heartbeat list keeps ids 1..250 only. Pure: no I/O, no clock.
"""

from __future__ import annotations

import hashlib
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

from swarm.core.station.commands import CommandRefused, CommandSpec
from swarm.core.station.rows import SwarmRow, SwarmsPart, TaskRow
from swarm.core.wire.message_types import CommandKind, Heartbeat, Phase


class _Agent(Protocol):
    """What the book reads of an agent (:class:`swarm.core.station.model.AgentView`)."""

    id: int
    connected: bool
    phase: Phase | None
    leader: int


class _Plan(Protocol):
    """The plan's per-leader task (:class:`swarm.core.station.plan.PlanBook`)."""

    def task_dict(self, leader: int) -> TaskRow | None: ...

    def slots_list(self, leader: int) -> list[list[int]] | None: ...


_LED = (Phase.LEADER, Phase.MEMBER)
#: the page's palette of swarm colours (static/swarms.js: the same count; beyond, it makes more)
PALETTE = 8


class SwarmBook:
    """The station's swarms. See the module docstring."""

    def __init__(self) -> None:
        self.leader = 0
        self.members: dict[int, frozenset[int]] = {}  # by leader id, the leader included
        self.colours: dict[int, int] = {}  # by leader id
        self._listed: dict[int, frozenset[int]] = {}  # each sender's latest Heartbeat list
        self._told: frozenset[int] = frozenset()  # the leaders the log last named

    def heartbeat(self, hb: Heartbeat) -> bool:
        """A leader's Heartbeat: its member list. True when the list changed."""
        if not 1 <= hb.sender <= 250:
            return False
        listed = frozenset(i for i in hb.members if isinstance(i, int) and 1 <= i <= 250)
        if self._listed.get(hb.sender) == listed:
            return False
        self._listed[hb.sender] = listed
        return True

    def update(self, agents: Mapping[int, _Agent]) -> bool:
        """Recompute the swarms and the leader from ``agents``. True when anything changed."""
        votes: Counter[int] = Counter()
        groups: dict[int, set[int]] = {}
        for a in agents.values():
            if a.connected and a.phase in _LED and a.leader:
                votes[a.leader] += 1
                groups.setdefault(a.leader, set()).add(a.id)
        leader = 0
        if votes:  # the station's one leader, as it always was
            best = max(votes.values())
            top = [i for i, n in votes.items() if n == best and i in agents and agents[i].connected]
            leader = max(top) if top else 0
        leads = sorted(x for x in groups if x in agents and agents[x].connected)
        taken = set(leads)  # a leader is in its own swarm (whatever its last words say)
        for lead in leads:
            groups[lead] = {lead} | (groups[lead] - taken)
        for group in groups.values():
            taken |= group
        members: dict[int, frozenset[int]] = {}
        for lead in leads:  # the Heartbeat lists add only agents that name no other leader
            extra = {i for i in self._listed.get(lead, ()) if i in agents and not agents[i].leader} - taken
            taken |= extra
            members[lead] = frozenset(groups[lead] | extra)
        changed = leader != self.leader or members != self.members
        self.colours = _colours(members, self.members, self.colours)
        self.leader, self.members = leader, members
        return changed

    def take_news(self, label: Callable[[int], str]) -> list[str]:
        """A line for the log when the set of leaders changed while there are (or were)
        several swarms: "2 swarms: agent3 (3) with 3 agents, agent6 (6) with 3"."""
        leads = frozenset(self.members)
        if leads == self._told:
            return []
        told, self._told = self._told, leads
        if len(leads) < 2 and len(told) < 2:
            return []  # one swarm: the leader's own event says it
        ids = sorted(leads, key=lambda x: (-len(self.members[x]), x))
        shown = ", ".join(f"{label(x)} with {len(self.members[x])}" for x in ids[:8])
        more = f" and {len(ids) - 8} more" if len(ids) > 8 else ""
        return [f"{len(ids)} swarm{'' if len(ids) == 1 else 's'}: {shown or 'none'}{more}"]

    def swarm_of(self, agent: int) -> int:
        """The leader of the swarm ``agent`` is in; 0 for none."""
        for lead, group in self.members.items():
            if agent in group:
                return lead
        return 0

    def leader_for(self, group: Iterable[int]) -> int:
        """The leader most of ``group`` follows now (ties: the station's leader, then the
        highest id); 0 when none of them is in a swarm."""
        ids = set(group)
        best = (0, False, 0)
        for lead, members in self.members.items():
            n = len(ids & members)
            if n:
                best = max(best, (n, lead == self.leader, lead))
        return best[2]

    def as_list(self) -> list[SwarmRow]:
        """The state's ``swarms``: one entry per leader, by leader id."""
        return [
            {"leader": lead, "members": sorted(self.members[lead]), "colour": self.colours[lead]}
            for lead in sorted(self.members)
        ]

    def state(self, plan: _Plan) -> SwarmsPart:
        """The state's ``swarms``, ``swarm_tasks`` and ``swarm_slots``."""
        tasks, slots = self.plans(plan)
        return {"swarms": self.as_list(), "swarm_tasks": tasks, "swarm_slots": slots}

    def plans(self, plan: _Plan) -> tuple[dict[str, TaskRow], dict[str, list[list[int]] | None]]:
        """The state's ``swarm_tasks`` and ``swarm_slots``: the FOLLOW task and slots of
        each swarm but the leader's (those are ``task`` and ``slots``), by leader id as text."""
        tasks: dict[str, TaskRow] = {}
        slots: dict[str, list[list[int]] | None] = {}
        for lead in sorted(self.members):
            t = plan.task_dict(lead) if lead != self.leader else None
            if t is not None:
                tasks[str(lead)], slots[str(lead)] = t, plan.slots_list(lead)
        return tasks, slots


def _colours(
    new: dict[int, frozenset[int]], old: dict[int, frozenset[int]], colours: dict[int, int]
) -> dict[int, int]:
    """Each swarm's colour: the colour of the old swarm it shares most members with (the
    largest overlaps first, the same leader first on a tie), so a swarm keeps its colour
    through new members and a re-election; a swarm of new agents the lowest free one."""
    old_of = {m: o for o, members in old.items() if o in colours for m in members}
    pairs = []  # (shared members, same leader, -new leader, old leader): at most one per agent
    for lead, members in new.items():
        shared = Counter(old_of[m] for m in members if m in old_of)
        pairs += [(n, lead == o, -lead, o) for o, n in shared.items()]
    pairs.sort(reverse=True)
    out: dict[int, int] = {}
    for n, _, neg, o in pairs:
        if n and -neg not in out and colours[o] not in out.values():
            out[-neg] = colours[o]
    for lead in sorted(new):
        if lead not in out:
            used = set(out.values())
            out[lead] = next(c for c in range(len(new) + 1) if c not in used)
    return out


def _station_hue(station: str) -> int:
    return hashlib.sha256(station.encode()).digest()[0] % PALETTE


def fleet_colours(swarms: list[SwarmRow]) -> list[SwarmRow]:
    """``swarms`` (each with ``station``, ``leader`` and the station's own ``colour``,
    or none) with ``colour`` made one per swarm on the merged view (module docstring);
    the station's own is kept as ``station_colour``. Pure: the same list, the same
    colours, on every page."""

    def own(s: SwarmRow) -> int:
        c = s.get("colour")
        return c if isinstance(c, int) and not isinstance(c, bool) and c >= 0 else int(s["leader"])

    out: list[SwarmRow] = [{**s, "station_colour": s.get("colour")} for s in swarms]
    taken: set[int] = set()
    for s in sorted(out, key=lambda s: (own(s), str(s.get("station", "")), s["leader"])):
        pref = (_station_hue(str(s.get("station", ""))) + own(s)) % PALETTE
        ring = [(pref + k) % PALETTE for k in range(PALETTE)]
        free = next((c for c in ring if c not in taken), None)
        if free is None:
            free = next(c for c in range(PALETTE, PALETTE + len(out) + 1) if c not in taken)
        s["colour"] = free
        taken.add(free)
    return out


@dataclass(frozen=True)
class Addressee:
    """One Command of a request: to ``agent`` (``target`` 0: the swarm, through its
    leader), for the swarm led by ``of_swarm`` (0: an agent in none; None: an agent's
    command, or the one swarm of a station that sees one and was not asked to name it),
    whose leader is looked up among ``group`` at each try (empty: the station's leader)."""

    agent: int
    target: int
    of_swarm: int | None = None
    group: frozenset[int] = frozenset()


def swarm_plan(
    spec: CommandSpec, leader: int, agents: Mapping[int, _Agent], book: SwarmBook | None
) -> list[Addressee]:
    """The Commands a swarm command (``spec.target`` None) becomes.

    ``spec.swarm`` names one swarm by its leader: FOLLOW and STOP go to that leader,
    the rest (and STOP too) to its connected members. Without it the command is for
    every swarm: STOP to each leader and every connected agent, the fan-out kinds to
    every connected agent, FOLLOW to the one swarm only (several swarms sent the same
    way from near each other would meet: the operator names one).

    Raises:
        CommandRefused: 400 no swarm led by ``spec.swarm``; 409 FOLLOW with several
            swarms and none named, no leader (FOLLOW), nothing connected.
    """
    kind = spec.kind
    swarms = dict(book.members) if book is not None else {}
    connected = sorted(i for i, a in agents.items() if a.connected)
    group: frozenset[int] = frozenset()
    if spec.swarm is not None:
        if spec.swarm not in swarms:
            raise CommandRefused(400, f"no swarm led by agent {spec.swarm} now ({_led_by(swarms)})")
        leads, group = [spec.swarm], swarms[spec.swarm]
        connected = [i for i in connected if i in group]
    elif kind == CommandKind.FOLLOW and len(swarms) > 1:
        raise CommandRefused(
            409,
            f'follow goes to one swarm ({_led_by(swarms)}): name it with "swarm": <leader id>;'
            " several swarms sent one way would meet",
        )
    elif len(swarms) > 1:
        leads = sorted(swarms)
    else:
        leads = [leader] if leader else []
    several = spec.swarm is not None or len(swarms) > 1  # else the one swarm of old: its answer as it was
    plan: list[Addressee] = []
    if kind in (CommandKind.FOLLOW, CommandKind.STOP):
        if not leads and kind == CommandKind.FOLLOW:
            raise CommandRefused(409, "no leader elected yet")
        for lead in leads:
            g = group or (swarms[lead] if several else frozenset())
            plan.append(Addressee(lead, 0, lead if several else None, g))
    if kind != CommandKind.FOLLOW:
        plan += [Addressee(i, i, book.swarm_of(i) if several and book else None) for i in connected]
    if not plan:
        raise CommandRefused(409, "no connected agents" + (" in that swarm" if spec.swarm else ""))
    return plan


def _led_by(swarms: Mapping[int, frozenset[int]]) -> str:
    """ "swarms led by 1, 6" (at most 8 named), or "no swarm"."""
    if not swarms:
        return "no swarm"
    ids = sorted(swarms)
    more = f" and {len(ids) - 8} more" if len(ids) > 8 else ""
    return f"{len(ids)} swarm{'s' if len(ids) > 1 else ''} led by " + ", ".join(map(str, ids[:8])) + more
