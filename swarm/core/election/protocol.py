"""Dynamic leader selection and swarm membership: the paper's protocol as a pure core.

Theory of operation
-------------------
:class:`Core` is one agent's protocol state machine. It does no I/O and reads no
clock: the driver feeds it messages with :meth:`Core.handle` and the passage of
time with :meth:`Core.tick`, sends what they return (:class:`Out`: a message and
its destination) and wakes it again at :meth:`Core.next_deadline`. The same core
runs in the agent (threads, Zenoh, real time) and in ``swarm simulate`` (virtual
time over the radio air model).

This module is the election's one state: :class:`Core` holds every field, runs the
timers (:meth:`Core.tick`) and owns every transition. The strategies decide, and ask
the core for a transition by name (:meth:`Core.adopt`, :meth:`Core.adopt_vote`,
:meth:`Core.heard_heartbeat`, ...); they read its fields but never write them:
:mod:`swarm.core.election.rules` (what each message does, one handler per message
type, in one table), :mod:`swarm.core.election.tdm` (under the ``tdm`` profile: the
pooling timers and three of the message rules, votes exchanged while pooling),
:mod:`swarm.core.election.caps` (a size cap and a swarm name, with their own
:class:`~swarm.core.election.caps.CapState`) and :mod:`swarm.core.election.liveness`
(a member's own ack timer). The profile chooses the rules and the pooling timers once,
when the core is made. :mod:`swarm.core.election.profiles` holds the timing profiles
and vote policies, :mod:`swarm.core.election.outbox` what the election sends.

The strategies name :class:`Core` in their type annotations only (an import under
``TYPE_CHECKING``): that is the one import circle of the election, and it is right:
the state calls its strategies, the strategies are handed the state, and nothing of
either runs at import time.

Phases and the paper's steps (section 2.3):

* IDLE: advertise on ``swarm/advertize``. Hearing an Advertize, send StartPool
  (retried until answered). A StartPool makes a free agent answer Success and
  open a pool with the sender; an agent whose pool is open answers
  AlreadyInPool (with its members) and adds the sender; any other agent ignores
  it.
* POOLING: StartPool to new advertisers, SyncPool (CRC-32 digest, members when the
  pool changed since the last sync) to every member at ``sync_interval``;
  differing pools merge (SyncPoolAck Different carries the receiver's members);
  an agreeing SyncPool is answered only when the lock states differ (silence
  means agreement: saves N^2 acks per interval); every change restamps
  ``changed_at``. A pool unchanged
  for ``lock_window`` locks; SyncPool/SyncPoolAck carry the lock flag and an agent
  with the same pool as a locked peer locks too, as does one that hears a
  Selection from a pool member whose epoch is its own pool's (that vote proves the
  pool locked with these very members).
* LOCKED: merges still happen (and restamp the time). Unchanged for another
  ``confirm_window`` (the paper: ``lock_window`` again; ``fast``: none, the agent
  votes as soon as it locks), or on the first vote from a pool member, the agent votes.
* While ELECTING, a SyncPool is answered only when its pool differs (SyncPoolAck
  with our members); an agreeing one gets silence (its sender locks on our
  Selection): acking every SyncPool was a quarter of the air time for N=20.
* ELECTING: vote for itself with a weight from the vote policy; exchange votes
  at ``vote_interval``; adopt any heavier vote (weight, then candidate id: ties
  break deterministically towards the higher id). A vote unchanged for
  ``vote_window`` ends the election: the candidate leads, the others follow.
* LEADER: Heartbeat (members, task) every ``heartbeat_interval``; members answer
  HeartbeatAck with their pose; a member silent for ``ack_timeout`` is expelled.
  A FOLLOW task's assignments are reconciled with the members before each
  Heartbeat (:func:`swarm.core.flight.formation.reconcile`), so the V re-forms by itself.
* MEMBER: a member that hears no Heartbeat for ``leader_timeout``, or one that no
  longer lists it, leaves: back to IDLE, to join another swarm or start a pool.

Beyond the paper (each rule stated once, here):

* **Late joiner**: a leader answers StartPool from a free agent with
  AlreadyInPool(locked) and adds it to its members; the newcomer becomes a
  member when a Heartbeat lists it. Leaders keep advertising for that reason.
* **Swarms that meet merge**: a leader hearing another leader's Advertize sends
  it its Heartbeat; a leader hearing another leader's Heartbeat compares
  (swarm size, leader id): the larger swarm (ties: higher id) absorbs
  the smaller: its leader adds the other leader and all its members; the smaller
  leader becomes a member of the larger. A member follows whichever leader lists
  it in a Heartbeat (conflicting claims are settled by the leaders' rule).
* **Liveness from pose streams**: a flying swarm's agents publish their pose
  several times a second. A member's pose heard by its leader counts as a
  HeartbeatAck, the leader's pose heard by a member as a Heartbeat, for the
  timeouts only (membership and tasks still come from Heartbeats). At 20% loss a
  member whose acks alone were counted was expelled every minute or so, and each
  expulsion re-formed the V. But poses alone keep a member for at most
  ``HB_SILENCE_FACTOR`` leader timeouts: an expelled member is no longer sent
  Heartbeats, and would otherwise stay the member of a swarm that does not have it.
* **A member acknowledges on its own timer** (:mod:`swarm.core.election.liveness`): a member
  whose leader's Heartbeat is overdue by a quarter interval sends its HeartbeatAck
  anyway, then every ``heartbeat_interval`` until one comes. An answered ack needs two
  frames through, an own ack one: at 29 % loss a 17-agent swarm lost a member to
  ``ack_timeout`` every few seconds and never settled. Without loss it never fires. A
  leader that hears an ack from an agent it does not list (expelled by bad luck, it
  still follows this leader) takes it back as a late joiner, the cap permitting.
* **Alone**: an agent that found nobody for ``alone_timeout`` forms a swarm of one
  (and absorbs others later by the rules above). An agent that hears a leader
  advertise is not alone: it keeps asking that leader (StartPool) instead. One that
  can hear the swarm but not be heard (its radio flooded, a one-way link) would
  otherwise lead a swarm of one beside the real leader for as long as that lasts.
* **Votes** come from a pluggable :class:`VotePolicy`: random (the paper),
  battery, or link quality, each in the high byte with random low bits.
* **Elections are named** by ``epoch`` = the pool digest's low 16 bits: votes
  from another pool (an older election) are ignored and counted.
* **A leader that cannot fly hands over** (:meth:`Core.set_vehicle_link`): an
  agent with a flight controller whose link to it is lost does not lead. A
  leader whose vehicle link has been lost for ``vehicle_grace`` sends its members
  a last Heartbeat listing nobody (so they leave at once, by the rule above,
  instead of after ``leader_timeout``) and goes IDLE; until the link is back the
  agent votes with weight 0 (any agent that can fly outweighs it), does not form
  a swarm of one, and advertises without FLAG_HAS_FC. A member whose vehicle is
  lost stays a member (it holds; the station marks it). A shorter loss changes
  nothing: the driver already waits 2 s before it calls a link lost.
* **Sub-swarms** (``cap``, the agent's ``--swarm-cap``): no pool or swarm grows past
  ``cap`` agents. The cap's rules (who asks whom, FULL answers, merges only when they
  fit, a member listed by two leaders) are :mod:`swarm.core.election.caps`'s, called from small
  hooks here and in :mod:`swarm.core.election.rules`; with ``cap`` 0 they change nothing.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, field

from swarm.core.election import caps, liveness
from swarm.core.election.outbox import ADVERTIZE, FLAG_HAS_FC, FLAG_LEADER, NO_POSE, Out
from swarm.core.election.profiles import (
    PAPER,
    Profile,
    RandomVote,
    VotePolicy,
)
from swarm.core.election.rules import HANDLERS, Handler
from swarm.core.election.tdm import TDM_HANDLERS
from swarm.core.election.tdm import news_at as tdm_news_at
from swarm.core.election.tdm import pool_timers as tdm_pool_timers
from swarm.core.flight.formation import reconcile
from swarm.core.wire.message_types import (
    AgentState,
    Heartbeat,
    HeartbeatAck,
    Message,
    Phase,
    Pose,
    Selection,
    StartPool,
    SyncPool,
    Task,
    pool_digest,
)

#: a member that hears its leader's poses but no Heartbeat for this many leader timeouts
#: was expelled (Heartbeats go to members only) and leaves
HB_SILENCE_FACTOR = 3.0


_EPS = 1e-9  # times are sums of floats: a deadline reached is reached, not 1 ulp short


def _elapsed(now: float, since: float, span: float) -> bool:
    """``span`` has passed since ``since``: true at the very time :meth:`Core.next_deadline`
    names, so a driver that ticks at the deadline always moves on."""
    return now + _EPS >= since + span


#: the phases in which :meth:`Core.tick` runs each periodic timer (a timer left from
#: an earlier phase is no deadline: ticking for it would do nothing, for ever)
_TIMER_PHASES: dict[str, frozenset[Phase]] = {
    "advertize": frozenset({Phase.IDLE, Phase.POOLING, Phase.LEADER}),
    "sync": frozenset({Phase.POOLING, Phase.LOCKED}),
    "vote": frozenset({Phase.ELECTING}),
    "heartbeat": frozenset({Phase.LEADER}),
}


@dataclass
class Counters:
    handled: int = 0
    ignored_foreign: int = 0  # from agents not in our pool/swarm
    ignored_stale: int = 0  # older election, duplicate or out-of-order
    ignored_phase: int = 0  # not meaningful in our phase
    impossible: int = 0  # contents that cannot be right
    expelled: int = 0
    left: int = 0
    elections: int = 0
    merges: int = 0
    step_downs: int = 0  # leaderships handed over for a lost vehicle link
    refused: int = 0  # joins and merges a size cap refused (swarm.core.election.caps)


@dataclass
class Core:
    """One agent's protocol core. See the module docstring."""

    me: int
    name: str = ""
    profile: Profile = PAPER
    policy: VotePolicy = field(default_factory=RandomVote)
    rng: random.Random = field(default_factory=random.Random)
    has_fc: bool = False
    vehicle_ok: bool = True  # the flight controller heard (see set_vehicle_link)
    vehicle_lost_at: float = 0.0

    phase: Phase = Phase.IDLE
    pool: set[int] = field(default_factory=set)
    locked: bool = False
    changed_at: float = 0.0
    vote: tuple[int, int] = (0, 0)  # (weight, candidate)
    vote_changed_at: float = 0.0
    epoch: int = 0
    leader: int = 0
    members: dict[int, float] = field(default_factory=dict)  # member -> last ack
    poses: dict[int, Pose] = field(default_factory=dict)
    task: Task = field(default_factory=Task)
    pose: Pose | None = None
    last_hb: float = 0.0
    leader_seen: float = 0.0  # the leader's pose stream last heard
    hb_seq: int = 0
    acked_at: float = 0.0  # a member's last HeartbeatAck sent (swarm.core.election.liveness)
    heard_seq: int = 0  # the sequence number of the last Heartbeat heard
    told_at: dict[int, float] = field(
        default_factory=dict
    )  # stray acks answered (swarm.core.election.liveness)
    counters: Counters = field(default_factory=Counters)
    idle_since: float = 0.0
    _started: bool = False
    _next: dict[str, float] = field(default_factory=dict)
    _handlers: dict[type, Handler] = field(default_factory=dict, init=False, repr=False, compare=False)
    _pooling: Callable[[Core, float, list[Out]], None] = field(
        default=lambda core, now, out: None, init=False, repr=False, compare=False
    )
    asked: dict[int, float] = field(default_factory=dict)  # StartPool sent at
    synced_digest: dict[int, int] = field(default_factory=dict)
    heard: set[int] = field(default_factory=set)  # tdm: pool members whose vote was heard
    state_dirty: bool = True
    cap: int = 0  # the most agents in a pool or swarm; 0: no cap (swarm.core.election.caps)
    swarm_name: str = ""  # pools and swarms only with agents of this name; "": any unnamed
    capped: caps.CapState = field(default_factory=caps.CapState)  # the cap's own state
    other_leaders: caps.LeaderTable = field(default_factory=caps.LeaderTable)

    def __post_init__(self) -> None:
        self.cap = caps.check_cap(self.cap or 0)
        self.capped.tag = caps.tag_of(self.swarm_name)
        # the strategies, chosen once: the paper's message rules, three of them replaced
        # under the tdm profile, and the pooling timers of one or the other
        self._handlers = {**HANDLERS, **TDM_HANDLERS} if self.profile.tdm else dict(HANDLERS)
        self._pooling = tdm_pool_timers if self.profile.tdm else Core._paper_pool_timers

    # -- driver API --------------------------------------------------------------
    def start(self, now: float) -> list[Out]:
        self._started = True
        self.idle_since = self.capped.free_since = now
        self._next = {"advertize": now}
        return self.tick(now)

    def handle(self, msg: Message, now: float) -> list[Out]:
        """Process one received message. Never raises for peer input. The driver
        calls :meth:`tick` when :meth:`next_deadline` (which may now be ``now``) comes."""
        out: list[Out] = []
        sender = getattr(msg, "sender", None)
        if sender == self.me:
            self.counters.impossible += 1  # our own id from elsewhere: ignore
            return out
        self.counters.handled += 1
        h = self._handlers.get(type(msg))
        if h is None:
            self.counters.ignored_phase += 1
            return out
        h(self, msg, now, out)
        return out

    def tick(self, now: float) -> list[Out]:
        """Timers: periodic sends, windows, timeouts."""
        out: list[Out] = []
        ph = self.phase
        if ph in _TIMER_PHASES["advertize"] and self.due("advertize", now, self.profile.advertize_interval):
            fc = self.has_fc and self.vehicle_ok
            flags = (FLAG_HAS_FC if fc else 0) | (FLAG_LEADER if ph == Phase.LEADER else 0)
            ad = caps.advert(self, flags, self.name or f"agent{self.me}")
            out += [Out(ADVERTIZE, ad)] if ad is not None else []
        if ph == Phase.IDLE and _elapsed(now, self.idle_since, self.profile.alone_timeout) and self.can_lead:
            self.become_leader(now, set())  # a swarm of one
            ph = self.phase
        if ph in (Phase.POOLING, Phase.LOCKED):
            self._pool_timers(now, out)
            ph = self.phase
        if ph == Phase.ELECTING:
            self._election_timers(now, out)
            ph = self.phase
        grounded = not self.can_lead and _elapsed(now, self.vehicle_lost_at, self.profile.vehicle_grace)
        if ph == Phase.LEADER and grounded:
            self._step_down(now, out)
        elif ph == Phase.LEADER:
            self._leader_timers(now, out)
        elif ph == Phase.MEMBER and not _elapsed(now, self._member_deadline(), 0.0):
            liveness.own_ack(self, now, out)  # a Heartbeat overdue: ack anyway
        elif ph == Phase.MEMBER:
            self.counters.left += 1
            rejoin = caps.rejoin(self, now)  # None without a cap
            self.go_idle(now)
            out += self.tick(now)
            if rejoin is not None:
                self.asked[rejoin] = now
                out.append(Out(rejoin, StartPool(self.me)))
        return out

    def next_deadline(self) -> float | None:
        """When :meth:`tick` next has something to do."""
        p = self.profile
        times = [t for k, t in self._next.items() if self.phase in _TIMER_PHASES[k]]
        if self.phase == Phase.IDLE and self.can_lead:
            times.append(self.idle_since + p.alone_timeout)
        elif self.phase == Phase.POOLING:
            times.append(self.changed_at + p.lock_window)
        elif self.phase == Phase.LOCKED:
            times.append(self.changed_at + (p.lock_window if p.confirm_window is None else p.confirm_window))
        elif self.phase == Phase.ELECTING:
            times.append(self.vote_changed_at + p.vote_window)
        elif self.phase == Phase.LEADER:
            times += [t + p.ack_timeout for t in self.members.values()]
            if not self.can_lead:
                times.append(self.vehicle_lost_at + p.vehicle_grace)
        elif self.phase == Phase.MEMBER:
            times += [self._member_deadline(), liveness.own_ack_due(self)]
        times += [t + p.startpool_retry for t in self.asked.values()]
        if self.tdm and (news := tdm_news_at(self)) is not None:
            times.append(news)
        return min(times) if times else None

    def _member_deadline(self) -> float:
        """When a member leaves: no sign of its leader for ``leader_timeout``, or no
        Heartbeat (which only members are sent) for ``HB_SILENCE_FACTOR`` times that."""
        p = self.profile
        return min(
            max(self.last_hb, self.leader_seen) + p.leader_timeout,
            self.last_hb + HB_SILENCE_FACTOR * p.leader_timeout,
            caps.unconfirmed_deadline(self),
        )

    def set_pose(self, pose: Pose) -> None:
        self.pose = pose

    def note_pose(self, agent: int, pose: Pose, now: float | None = None) -> None:
        """A pose heard on an agent's pose stream: the formation's assignments use the
        freshest positions (a new leader has no HeartbeatAck yet). With ``now``, the
        pose also shows the sender alive: a member's pose counts as its ack, the
        leader's as its heartbeat (see "Liveness" in the module docstring)."""
        if agent == self.me:
            return
        self.poses[agent] = pose
        if now is None:
            return
        if self.phase == Phase.LEADER and agent in self.members:
            self.members[agent] = max(self.members[agent], now)
        elif self.phase == Phase.MEMBER and agent == self.leader:
            self.leader_seen = max(self.leader_seen, now)

    @property
    def tdm(self) -> bool:
        """The tdm profile's rules (swarm.core.election.tdm), with a size cap too (the
        cap's rules apply within them: "With a size cap" in that module)."""
        return self.profile.tdm

    @property
    def can_lead(self) -> bool:
        """False while an agent with a flight controller has lost its link to it."""
        return self.vehicle_ok or not self.has_fc

    def set_vehicle_link(self, up: bool, now: float) -> None:
        """The flight controller's link lost (``up`` false) or back. See "A leader
        that cannot fly hands over" in the module docstring."""
        if up != self.vehicle_ok:
            self.vehicle_ok = up
            self.vehicle_lost_at = now

    def resume(self, now: float) -> list[Out]:
        """The node's radio is back after a time away, during which this core's time
        stood still (see "Deaf" in :mod:`swarm.core.agent.node`) but the others' did not: a
        leader sends its Heartbeat and a member its HeartbeatAck at once, so the others
        hear from it before their own timeouts, without waiting for its next interval."""
        out: list[Out] = []
        if self.phase == Phase.LEADER:
            self._next["heartbeat"] = now
            self._leader_timers(now, out)
        elif self.phase == Phase.MEMBER and self.leader:
            self.acked_at = now
            out.append(Out(self.leader, HeartbeatAck(self.me, self.heard_seq, self.pose or NO_POSE)))
        return out

    def rejoin(self, now: float) -> list[Out]:
        """The node's radio had been moved off the swarm's network (a rogue radio's RT
        commands) and was put back by the radio guard: it was cut off, and the swarm went
        on without it. A leader left with no member (all expelled while it was cut off)
        leads nobody the others can hear: it steps down and asks to join (IDLE: it asks
        the leaders it hears, and leads a swarm of one again only after a whole alone
        timeout of hearing none), instead of claiming to lead beside the swarm's new
        leader until the merge rule absorbs it (the fault bench: two leaders for 2-5 s
        after each isolating attack was undone). A leader that kept members stays."""
        if self.phase != Phase.LEADER or self.members:
            return []
        self.counters.step_downs += 1
        self.go_idle(now)
        return self.tick(now)  # its Advertize at once

    def set_task(self, task: Task) -> None:
        """The leader's task; it rides on the next Heartbeats."""
        self.task = task

    def take_state_changed(self) -> bool:
        """True once after the phase, leader, vote or membership changed."""
        dirty, self.state_dirty = self.state_dirty, False
        return dirty

    def state(self) -> AgentState:
        return AgentState(
            self.me,
            self.phase,
            self.leader if self.phase in (Phase.LEADER, Phase.MEMBER) else 0,
            self.vote[1],
            self.vote[0],
            self.epoch,
            self.locked,
            frozenset(self.pool),
            frozenset(self.members) if self.phase == Phase.LEADER else frozenset(),
        )

    # -- helpers ------------------------------------------------------------------
    def due(self, timer: str, now: float, interval: float) -> bool:
        t = self._next.get(timer)
        if t is None or now + _EPS >= t:
            self._next[timer] = now + interval
            return True
        return False

    def set_phase(self, phase: Phase) -> None:
        if phase != self.phase:
            self.phase = phase
            self.state_dirty = True

    def change_pool(self, add: set[int] | frozenset[int], now: float) -> bool:
        new = set(add) - self.pool
        if not new:
            return False
        if self.cap and not caps.fits(len(self.pool) + len(new), self.cap):
            return caps.trim(self, new, now)  # the cap's lowest ids stay (or we leave)
        self.pool |= new
        self.changed_at = now
        self.counters.merges += 1
        return True

    def open_pool(self, other: set[int] | frozenset[int], now: float) -> None:
        self.pool = {self.me}
        self.capped.founder = False
        self.change_pool(other, now)
        self.locked = False
        self.set_phase(Phase.POOLING)
        self._next.pop("sync", None)

    def go_idle(self, now: float) -> None:
        self.set_phase(Phase.IDLE)
        self.pool = set()
        self.locked = False
        self.leader = 0
        self.members = {}
        self.vote = (0, 0)
        self.idle_since = self.capped.free_since = now
        self.asked.clear()
        self.synced_digest.clear()
        self._next = {"advertize": now}

    def become_leader(self, now: float, members: set[int]) -> None:
        self.set_phase(Phase.LEADER)
        self.leader = self.me
        self.members = {m: now for m in members if m != self.me}
        self.pool = {self.me} | set(self.members)
        self.epoch = pool_digest(self.pool) & 0xFFFF
        self._next = {"advertize": now, "heartbeat": now}
        self.counters.elections += 1

    def _step_down(self, now: float, out: list[Out]) -> None:
        """Hand over: a last Heartbeat that lists nobody releases every member now."""
        self.hb_seq = (self.hb_seq + 1) & 0xFF
        hb = Heartbeat(self.me, self.epoch, self.hb_seq, frozenset(), self.task)
        out += [Out(m, hb) for m in sorted(self.members)]
        self.counters.step_downs += 1
        self.go_idle(now)

    def become_member(self, leader: int, now: float) -> None:
        self.set_phase(Phase.MEMBER)
        self.leader = leader
        self.last_hb = self.acked_at = now
        self.members = {}
        self._next = {}
        self.asked.clear()

    def _sync_msg(self, to: int) -> SyncPool:
        d = pool_digest(self.pool)
        # members travel only when this peer has not yet seen this pool from us
        members = None if self.synced_digest.get(to) == d else frozenset(self.pool)
        self.synced_digest[to] = d
        return SyncPool(self.me, d, self.locked, members)

    def _pool_timers(self, now: float, out: list[Out]) -> None:
        self._pooling(self, now, out)

    def _paper_pool_timers(self, now: float, out: list[Out]) -> None:
        p = self.profile
        if self.due("sync", now, p.sync_interval):
            for m in sorted(self.pool - {self.me}):
                out.append(Out(m, self._sync_msg(m)))
        for a, t in list(self.asked.items()):
            if a in self.pool:
                del self.asked[a]
            elif _elapsed(now, t, p.startpool_retry) and not self.locked:
                self.asked[a] = now
                out.append(Out(a, StartPool(self.me)))
        window = p.lock_window if not self.locked or p.confirm_window is None else p.confirm_window
        if _elapsed(now, self.changed_at, window):
            if not self.locked:
                self.locked = True
                self.changed_at = now  # the second window starts now
                self.set_phase(Phase.LOCKED)
                self.asked.clear()
            else:
                self.start_election(now, out)

    def start_election(self, now: float, out: list[Out]) -> None:
        self.set_phase(Phase.ELECTING)
        self.epoch = pool_digest(self.pool) & 0xFFFF
        # an agent that cannot fly votes for itself with weight 0: anyone else wins
        self.vote = (self.policy.weight(self.rng) if self.can_lead else 0, self.me)
        self.vote_changed_at = now
        self._next["vote"] = now

    def _election_timers(self, now: float, out: list[Out]) -> None:
        p = self.profile
        if self.due("vote", now, p.vote_interval):
            sel = Selection(self.me, self.vote[1], self.vote[0], self.epoch)
            out += [Out(m, sel) for m in sorted(self.pool - {self.me})]
        if _elapsed(now, self.vote_changed_at, p.vote_window):
            self.end_election(now, out)

    def end_election(self, now: float, out: list[Out]) -> None:
        """The vote's candidate leads, the others follow it (the window ran out, or under
        the ``tdm`` profile every vote was heard)."""
        if self.vote[1] == self.me:
            self.become_leader(now, self.pool - {self.me})
        else:
            self.become_member(self.vote[1], now)
            if self.cap:  # not listed if our pools differed: a StartPool gets us adopted
                out += [Out(to, StartPool(self.me)) for to in caps.ask_after_vote(self, now)]

    def _leader_timers(self, now: float, out: list[Out]) -> None:
        p = self.profile
        for m, t in list(self.members.items()):
            if _elapsed(now, t, p.ack_timeout):
                self.expel(m)
        if self.due("heartbeat", now, p.heartbeat_interval) and self.members:
            # the formation follows membership: departed members close up, newcomers
            # join an arm, a new leader assigns afresh (swarm.core.flight.formation.reconcile)
            self.task = reconcile(self.task, self.me, self.members, self.poses, self.pose)
            self.hb_seq = (self.hb_seq + 1) & 0xFF
            hb = Heartbeat(self.me, self.epoch, self.hb_seq, frozenset(self.members), self.task)
            # ...and to the leaders that would absorb us (caps.courted: the merge rule)
            out += [Out(m, hb) for m in sorted(self.members) + caps.courted(self, now)]

    def lock_from_peer(self, now: float) -> None:
        self.locked = True
        self.changed_at = now
        self.set_phase(Phase.LOCKED)
        self.asked.clear()

    # -- transitions the strategies ask for (rules, tdm, caps, liveness) ------------
    # They read this state freely; every change goes through a method here.
    def ask(self, agent: int, now: float) -> None:
        """A StartPool sent to ``agent`` now (retried until answered)."""
        self.asked[agent] = now

    def answered(self, agent: int) -> None:
        """``agent`` answered our StartPool (or refused it): stop asking."""
        self.asked.pop(agent, None)

    def not_alone(self, now: float) -> None:
        """A swarm is there to join: the alone timeout starts again."""
        self.idle_since = now

    def adopt(self, agent: int, now: float, pose: Pose | None = None) -> None:
        """A leader takes ``agent`` into its swarm (a late joiner, an absorbed swarm's
        agent): listed by the next Heartbeat."""
        if agent == self.me or agent in self.members:
            return
        self.members[agent] = now
        self.pool.add(agent)
        if pose is not None:
            self.poses[agent] = pose
        self.state_dirty = True

    def expel(self, agent: int) -> None:
        """A leader lets ``agent`` go (silent past the ack timeout, or following another)."""
        del self.members[agent]
        self.poses.pop(agent, None)
        self.pool.discard(agent)
        self.counters.expelled += 1
        self.state_dirty = True

    def heard_ack(self, agent: int, pose: Pose, now: float) -> None:
        """A member's HeartbeatAck: alive now, and where it is."""
        self.members[agent] = now
        self.poses[agent] = pose

    def heard_heartbeat(self, hb: Heartbeat, now: float) -> None:
        """A member's leader's Heartbeat: its task, its election, and the member's own-ack
        timer restarts (swarm.core.election.liveness)."""
        self.task = hb.task
        self.last_hb = now
        self.epoch = hb.epoch
        self.acked_at, self.heard_seq = now, hb.seq

    def told(self, agent: int, now: float) -> None:
        """A leader sent a stray ack's sender the Heartbeat that does not list it."""
        self.told_at[agent] = now

    def acked(self, at: float) -> None:
        """A member's own HeartbeatAck counted as sent at ``at``."""
        self.acked_at = at

    def changed(self) -> None:
        """The phase, leader, vote or membership changed: say so (take_state_changed)."""
        self.state_dirty = True

    def resync_all(self) -> None:
        """Every pool member must hear the whole pool again (it changed by a merge)."""
        self.synced_digest.clear()

    def replace_pool(self, pool: set[int], now: float) -> None:
        """The pool becomes ``pool`` (a capped merge kept the cap's lowest ids)."""
        self.pool = pool
        self.changed_at = now
        self.counters.merges += 1

    def adopt_vote(self, vote: tuple[int, int], now: float) -> None:
        """A heavier vote heard: ours now."""
        self.vote = vote
        self.vote_changed_at = now
        self.state_dirty = True

    def draw_vote(self, now: float) -> None:
        """Our own vote, once per pool (the tdm profile votes while pooling)."""
        if self.vote[1] == 0:
            self.vote = (self.policy.weight(self.rng) if self.can_lead else 0, self.me)
            self.vote_changed_at = now
            self.heard.clear()
            self.state_dirty = True

    def heard_vote(self, agent: int) -> None:
        """The tdm profile: ``agent``'s vote heard."""
        self.heard.add(agent)

    def send_sync_now(self) -> None:
        """News: the next SyncPool leaves in this round's slot, not the next."""
        self._next.pop("sync", None)

    def next_send(self, timer: str) -> float | None:
        """When the periodic ``timer`` ("advertize", "sync", "vote", "heartbeat") next sends."""
        return self._next.get(timer)

    def elect_on_locked_pool(self, now: float) -> None:
        """The tdm profile: the pool locks and elects at once, keeping the vote gathered
        while pooling; without every vote heard the vote window also runs from the
        pool's last change (a member added late may hold a heavier vote not yet heard)."""
        self.locked = True
        self.asked.clear()
        self.set_phase(Phase.ELECTING)
        self.epoch = pool_digest(self.pool) & 0xFFFF
        self.draw_vote(now)
        self.vote_changed_at = max(self.vote_changed_at, self.changed_at)
        self._next["vote"] = now


__all__ = ["HB_SILENCE_FACTOR", "Core", "Counters"]
