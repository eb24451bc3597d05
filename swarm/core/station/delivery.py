"""Command delivery for the ground station: sending, retrying, matching answers.

Theory of operation
-------------------
:meth:`CommandDelivery.submit` checks a :class:`~swarm.core.station.commands.CommandSpec`
against what the station knows (unknown agent, not connected, no leader: refused
with a reason and an HTTP-like status, nothing sent) and against the station's
geofence (:mod:`swarm.core.flight.geofence`: a take-off's or a go-to's altitude above home
outside the floor and ceiling, a go-to beyond the radius from the home the station
saw the agent at, 400; with no home seen the radius is left to the agent's own
fence, and an ``alt_amsl`` cannot be converted, 409), and returns a
:class:`~swarm.core.station.commands.Request` holding one command per addressee.
Each is re-sent with the same seq after ``command_backoff`` gaps (0.5, 1, 2, 3, 4 s,
then 4 s) until its CommandAck arrives or ``command_give_up`` (12 s) has passed since
the first send. Answers are matched by seq and by the agents the command went to
(duplicates and late answers are counted and dropped). Swarm FOLLOW and STOP go to
the leader as Command(target=0), and every retry goes to the leader the station sees
*then*: a command sent just before an election reaches the new leader
(:meth:`CommandDelivery.leader_changed` retries at once). A "not the leader" or "no
leader" answer to a swarm command is not final while time remains (the agent does
not remember it, so the new leader answers for itself). Swarm STOP also goes to
every connected agent; swarm ARM/DISARM/TAKEOFF/LAND/RETURN go to every connected
agent. With several swarms (:func:`swarm.core.station.swarms.swarm_plan`) a command
goes to one swarm or to each: a swarm FOLLOW or STOP keeps its swarm's members and
every retry goes to the leader most of them follow *then*. At give-up, evidence seen
in Telemetry (:meth:`CommandDelivery.look_for_evidence`) makes the result
``CARRIED_OUT``, a swarm refusal is final, else ``NO_ANSWER``.

An IN_PROGRESS answer (the agent's vehicle is still carrying the command out: a
take-off climbs for ten seconds and more) is not a result: it is logged once, and the
command is tried on (each retry is a question the agent answers from its log, never
running the command again). If the retry window ends while the agent still says in
progress, the request is handed out as ``IN_PROGRESS`` (not done, with the agent's
words) and the station keeps asking until the agent's result comes, which is logged
as an event, or until the agent has said nothing for ``command_give_up`` or
``command_in_progress_limit`` has passed since the first send: then it ends like a
give-up (``CARRIED_OUT`` on evidence, else ``NO_ANSWER`` naming the last progress).

Owned by :class:`swarm.core.station.core.StationCore`, which shares its agents, counters
and event log with it and passes the leader it sees. Pure: no I/O, no clock.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import replace

from swarm.core.station.commands import (
    CARRIED_OUT,
    NO_ANSWER,
    CommandRefused,
    CommandSpec,
    Pending,
    Request,
    Seen,
    evidence,
)
from swarm.core.station.model import AgentView, StationConfig, StationCounters, StOut
from swarm.core.station.swarms import Addressee, SwarmBook, swarm_plan
from swarm.core.wire.codes import mode_code, short_reason
from swarm.core.wire.message_types import AckResult, Command, CommandAck, CommandKind


class CommandDelivery:
    """The station's commands in flight. See the module docstring."""

    def __init__(
        self,
        station_id: int,
        cfg: StationConfig,
        counters: StationCounters,
        agents: dict[int, AgentView],
        label: Callable[[int], str],
        event: Callable[[float, str, str], None],
        first_seq: int = 1,
        swarms: SwarmBook | None = None,
    ) -> None:
        self.id = station_id
        self.cfg = cfg
        self.counters = counters
        self.agents = agents  # the station's own dict, shared
        self._label = label
        self._event = event
        self.swarms = swarms  # the station's, shared: each swarm's leader and members
        # the runtime starts commands at a random seq: an agent remembers answers by
        # (station, seq), and a restarted station must not reuse the seqs it just used
        self._seq = itertools.count(first_seq)
        self._request_ids = itertools.count(1)
        self._pending: dict[int, Pending] = {}  # by seq
        self._answered: deque[tuple[int, int]] = deque(maxlen=256)  # (agent, seq) completed
        self._finished: list[Request] = []

    @property
    def in_flight(self) -> bool:
        """Whether a command awaits its result."""
        return bool(self._pending)

    def submit(self, spec: CommandSpec, now: float, leader: int) -> tuple[Request, list[StOut]]:
        """Start a command.

        Raises:
            CommandRefused: 404 unknown agent, 409 agent not connected, no leader
                (FOLLOW), nothing connected (a swarm fan-out).
        """
        kind = spec.kind
        plan: list[Addressee] = []
        if spec.target is not None:
            a = self.agents.get(spec.target)
            if a is None:
                raise CommandRefused(404, f"unknown agent {spec.target}")
            if not a.connected:
                raise CommandRefused(409, f"{self._label(a.id)} is not connected")
            spec = self._fenced(spec, a)
            plan.append(Addressee(a.id, a.id))
        else:
            plan = swarm_plan(spec, leader, self.agents, self.swarms)
            spec = self._fenced(spec, None)
        req = Request(next(self._request_ids), spec)
        out: list[StOut] = []
        for ad in plan:
            seq = self._next_seq()
            msg = Command(
                self.id,
                seq,
                ad.target,
                kind,
                spec.lat,
                spec.lon,
                spec.alt,
                spec.heading,
                mode_code(spec.mode),
            )
            p = Pending(
                req, ad.agent, ad.target == 0, msg, first_sent=now, group=ad.group, of_swarm=ad.of_swarm
            )
            req.pending.append(p)
            self._pending[seq] = p
            out += self._send(p, now, leader)
        return req, out

    def _fenced(self, spec: CommandSpec, a: AgentView | None) -> CommandSpec:
        """``spec`` inside the station's geofence, its ``alt_amsl`` made metres above the
        home seen for agent ``a``.

        Raises:
            CommandRefused: 400 outside the fence (the limit in the reason); 409 an
                ``alt_amsl`` for an agent whose home the station has not seen.
        """
        fence, what = self.cfg.fence, spec.kind.name.lower()
        if spec.kind == CommandKind.TAKEOFF:
            why = fence.alt_refusal(spec.alt)
            if why is None and spec.alt < 1.0:
                why = f"altitude {spec.alt:g} m: a take-off climbs 1 m at least"
        elif spec.kind in (CommandKind.GOTO, CommandKind.WAYPOINT) and a is not None:
            if spec.alt_amsl is not None:
                if a.home is None:
                    raise CommandRefused(
                        409, f"{self._label(a.id)}'s home is unknown here: give 'alt' (metres above home)"
                    )
                spec = replace(spec, alt=round(spec.alt_amsl - a.home[2], 1), alt_amsl=None)
            why = fence.refusal(spec.lat, spec.lon, spec.alt, None if a.home is None else a.home[:2])
        else:
            return spec
        if why is not None:
            raise CommandRefused(400, f"{what} refused by the station's geofence: {why}")
        return spec

    def ack(self, msg: CommandAck, now: float, leader: int) -> None:
        """A CommandAck heard (the station is not passive)."""
        msg = replace(msg, reason=short_reason(msg.reason))  # whoever sent it: one printable line
        p = self._pending.get(msg.seq)
        if p is None or msg.sender not in p.sent_to:
            if (msg.sender, msg.seq) in self._answered:
                self.counters.duplicate_acks += 1
            else:
                self.counters.late_acks += 1
            return
        if p.swarm and msg.result in (AckResult.REJECTED, AckResult.NO_LEADER):
            # "not the leader" / "no leader": not final while there is time to find the
            # leader (the agent keeps no record of it, so it will answer again)
            p.refusal = (msg.sender, msg.result.name, msg.reason)
            if now - p.first_sent < self.cfg.command_give_up:
                leader = self._lead(p, leader)
                if leader and msg.sender != leader:
                    p.next_try = min(p.next_try, now)  # it already sees another leader: go now
                return
        p.agent = msg.sender
        if msg.result == AckResult.IN_PROGRESS:
            if p.progress is None:
                self._event(now, "command", self._line(p, "IN_PROGRESS", msg.reason))
            p.progress, p.progress_at = msg.reason, now
            return
        self._complete(p, msg.result.name, msg.reason, now)

    def tick(self, now: float, leader: int) -> list[StOut]:
        """Retries due and give-ups."""
        out: list[StOut] = []
        for p in list(self._pending.values()):
            if now + 1e-9 >= self._give_up_at(p):
                self._give_up(p, now)
                continue
            if p.result is None and now + 1e-9 >= p.first_sent + self.cfg.command_give_up:
                self._still_in_progress(p, now)  # the window ended, the agent is still at it
            if now + 1e-9 >= p.next_try:
                out += self._send(p, now, leader)
        return out

    def deadlines(self) -> Iterator[float]:
        for p in self._pending.values():
            yield min(p.next_try, self._give_up_at(p))
            if p.result is None:
                yield p.first_sent + self.cfg.command_give_up

    def _give_up_at(self, p: Pending) -> float:
        """When the station stops asking: at the end of the retry window, or for a
        command the agent says is in progress ``command_give_up`` after it last said
        so, and never later than ``command_in_progress_limit`` after the first send."""
        cfg = self.cfg
        if p.progress is None:
            return p.first_sent + cfg.command_give_up
        later = max(p.first_sent + cfg.command_give_up, p.progress_at + cfg.command_give_up)
        return min(p.first_sent + max(cfg.command_in_progress_limit, cfg.command_give_up), later)

    def leader_changed(self, leader: int, now: float) -> None:
        for p in self._pending.values():
            lead = self._lead(p, leader) if p.swarm else 0
            if lead and p.agent != lead:
                p.next_try = min(p.next_try, now)  # to the new leader at the next tick

    def look_for_evidence(self, a: AgentView) -> None:
        """Telemetry from ``a``: does it show a pending command carried out?"""
        now_seen = None
        for p in self._pending.values():
            before = p.before.get(a.id)
            if before is None or p.shown is not None:
                continue
            now_seen = now_seen or self._seen(a)
            what = evidence(p.msg.kind, before, now_seen)
            if what is not None:
                p.shown = f"{a.id}:{what}"

    def take_finished(self) -> list[Request]:
        done, self._finished = self._finished, []
        return done

    # -- internals ---------------------------------------------------------------------
    def _next_seq(self) -> int:
        while True:
            seq = next(self._seq) & 0xFFFF
            if seq and seq not in self._pending:
                return seq

    def _lead(self, p: Pending, leader: int) -> int:
        """The leader a swarm command goes to now: the one its swarm's members follow
        (the station's leader for the one swarm of old); 0: none seen."""
        if p.group and self.swarms is not None:
            return self.swarms.leader_for(p.group)
        return leader

    def _send(self, p: Pending, now: float, leader: int) -> list[StOut]:
        lead = self._lead(p, leader) if p.swarm else 0
        if lead and lead in self.agents:
            p.agent = lead  # re-resolved at every try: elections happen
        if p.agent not in p.before:
            p.before[p.agent] = self._seen(self.agents[p.agent])
        p.sent_to.add(p.agent)
        p.tries += 1
        gaps = self.cfg.command_backoff
        p.next_try = now + gaps[min(p.tries, len(gaps)) - 1]
        if p.tries == 1:
            self.counters.commands_sent += 1
        else:
            self.counters.command_retries += 1
        return [StOut(p.agent, self.agents[p.agent].name, p.msg)]

    @staticmethod
    def _seen(a: AgentView) -> Seen:
        return Seen(a.mode, a.armed, a.airborne, a.holding)

    def _line(self, p: Pending, result: str, reason: str) -> str:
        what = p.msg.kind.name + (" (swarm)" if p.swarm else "")
        return (
            f"{what} -> {self._label(p.agent)}: {result}"
            + (f" ({reason})" if reason else "")
            + f" [seq {p.msg.seq}]"
        )  # the agent's own log names the same seq

    def _hand_out(self, req: Request) -> None:
        if req.done and not req.reported:
            req.reported = True
            self._finished.append(req)

    def _still_in_progress(self, p: Pending, now: float) -> None:
        """The retry window is over and the agent's vehicle is still at it: the request
        is handed out as IN_PROGRESS (not done); the result will be logged."""
        p.result, p.reason = AckResult.IN_PROGRESS.name, p.progress or ""
        secs = f"{now - p.first_sent:.0f} s"
        self._event(now, "command", self._line(p, "IN_PROGRESS", f"{p.reason}: still at it after {secs}"))
        self._hand_out(p.request)

    def _complete(self, p: Pending, result: str, reason: str, now: float) -> None:
        p.result, p.reason = result, reason
        del self._pending[p.msg.seq]
        for agent in p.sent_to:
            self._answered.append((agent, p.msg.seq))
        self._event(now, "command", self._line(p, result, reason))
        self._hand_out(p.request)

    def _give_up(self, p: Pending, now: float) -> None:
        tries = f"{p.tries} {'try' if p.tries == 1 else 'tries'} in {now - p.first_sent:.0f} s"
        last = f" (last: in progress, {p.progress})" if p.progress is not None else ""
        if p.shown is not None:
            agent, _, what = p.shown.partition(":")
            p.agent = int(agent)
            self._complete(p, CARRIED_OUT, f"no answer after {tries}, but it shows {what}", now)
        elif p.refusal is not None:
            p.agent, result, reason = p.refusal
            self._complete(p, result, reason, now)
        else:
            self._complete(p, NO_ANSWER, f"no {'result' if last else 'answer'} after {tries}{last}", now)
