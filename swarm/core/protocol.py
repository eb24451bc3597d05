"""Dynamic leader selection and swarm membership: the paper's protocol as a pure core.

Theory of operation
-------------------
:class:`Core` is one agent's protocol state machine. It does no I/O and reads no
clock: the driver feeds it messages with :meth:`Core.handle` and the passage of
time with :meth:`Core.tick`, sends what they return (:class:`Out`: a message and
its destination) and wakes it again at :meth:`Core.next_deadline`. The same core
runs in the agent (threads, Zenoh, real time) and in ``swarm simulate`` (virtual
time over the radio air model).

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
  Heartbeat (:func:`swarm.core.formation.reconcile`), so the V re-forms by itself.
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
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Protocol

from swarm.core.formation import reconcile
from swarm.core.messages import (
    Advertize,
    AgentState,
    Heartbeat,
    HeartbeatAck,
    Message,
    Phase,
    PoolStatus,
    Pose,
    Selection,
    StartPool,
    StartPoolAck,
    SyncPool,
    SyncPoolAck,
    Task,
    pool_digest,
)

ADVERTIZE = 0  # Out.to for the advertize broadcast
#: the pose an agent without a flight controller acknowledges with ("null island")
NO_POSE = Pose(0.0, 0.0, 0.0)
FLAG_HAS_FC = 0x01
FLAG_LEADER = 0x02


@dataclass(frozen=True)
class Profile:
    """Windows, rates and timeouts (seconds)."""

    name: str = "paper"
    advertize_interval: float = 1.0
    startpool_retry: float = 1.0
    sync_interval: float = 0.5
    lock_window: float = 2.0
    confirm_window: float | None = None  # locked and unchanged this long: vote (None: lock_window)
    vote_interval: float = 0.5
    vote_window: float = 2.0
    heartbeat_interval: float = 0.5
    ack_timeout: float = 3.0
    leader_timeout: float = 3.0
    alone_timeout: float = 8.0
    state_interval: float = 1.0
    vehicle_grace: float = 3.0  # a leader without its vehicle this long steps down


PAPER = Profile()
#: a member that hears its leader's poses but no Heartbeat for this many leader timeouts
#: was expelled (Heartbeats go to members only) and leaves
HB_SILENCE_FACTOR = 3.0


def fast_profile(round_s: float) -> Profile:
    """Windows derived from the link's TDM round: a message needs about one round to
    reach everyone, so every interval is one round and every window 1.5 rounds
    (2 rounds measured 20% slower with no gain in agreement; 1 round leaves no
    margin for a lost packet). No second lock window: the agent votes as soon as
    the pool locks and the lock spreads with its Selection (N=10, 10% loss: p95
    8.3 s -> 6.3 s, no violation). Timeouts: six rounds, at least 1 s."""
    r = max(round_s, 0.05)
    return Profile(
        name="fast",
        advertize_interval=r,
        startpool_retry=r,
        sync_interval=r,
        lock_window=1.5 * r,
        confirm_window=0.0,
        vote_interval=r,
        vote_window=1.5 * r,
        heartbeat_interval=r,
        ack_timeout=max(6 * r, 1.0),
        leader_timeout=max(6 * r, 1.0),
        alone_timeout=8 * r,
        state_interval=max(r, 0.5),
    )


def paper_profile(round_s: float = 0.0) -> Profile:
    """The paper's values, stretched only where the radio makes them impossible.

    The paper's 2 s windows and 0.5 s rates assume a network where a message
    reaches everyone well within a window. On a SiK radio each node speaks once
    per TDM round (multipoint: N windows per round, 2.37 s for 20 radios at
    64 kbps); a vote window shorter than a round ends before any other vote can
    arrive, and every agent elects itself (seen in simulation). So windows are
    at least 1.5 rounds, send intervals at least one round (sending faster only
    queues duplicates in the radio), and timeouts, which the paper leaves open,
    at least five rounds. With up to 8 radios at 64 kbps these are the paper's
    own values.
    """
    r = max(round_s, 0.0)
    window = max(PAPER.lock_window, 1.5 * r)
    interval = max(PAPER.sync_interval, r)
    timeout = max(PAPER.ack_timeout, 5 * r)
    return replace(
        PAPER,
        sync_interval=interval,
        vote_interval=interval,
        heartbeat_interval=interval,
        lock_window=window,
        vote_window=window,
        advertize_interval=max(PAPER.advertize_interval, r),
        startpool_retry=max(PAPER.startpool_retry, r),
        ack_timeout=timeout,
        leader_timeout=timeout,
        alone_timeout=max(PAPER.alone_timeout, 2 * timeout),
    )


def profile_by_name(name: str, round_s: float) -> Profile:
    if name == "paper":
        return paper_profile(round_s)
    if name == "fast":
        return fast_profile(round_s)
    raise ValueError(f"unknown profile {name!r}: paper or fast")


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


class VotePolicy(Protocol):
    def weight(self, rng: random.Random) -> int: ...


@dataclass
class RandomVote:
    """The paper: a random weight."""

    def weight(self, rng: random.Random) -> int:
        return rng.getrandbits(32)


@dataclass
class BatteryVote:
    """The fullest battery leads (percent in the high byte, random below)."""

    battery: Callable[[], int]

    def weight(self, rng: random.Random) -> int:
        return (max(0, min(255, self.battery())) << 24) | rng.getrandbits(24)


@dataclass
class LinkQualityVote:
    """The best-heard radio leads (RSSI in the high byte, random below)."""

    rssi: Callable[[], int]

    def weight(self, rng: random.Random) -> int:
        return (max(0, min(255, self.rssi())) << 24) | rng.getrandbits(24)


@dataclass(frozen=True)
class Out:
    """A message to send: ``to`` is an agent id, or ADVERTIZE for the broadcast."""

    to: int
    msg: Message


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
    counters: Counters = field(default_factory=Counters)
    _idle_since: float = 0.0
    _started: bool = False
    _next: dict[str, float] = field(default_factory=dict)
    _asked: dict[int, float] = field(default_factory=dict)  # StartPool sent at
    _synced_digest: dict[int, int] = field(default_factory=dict)
    _state_dirty: bool = True

    # -- driver API --------------------------------------------------------------
    def start(self, now: float) -> list[Out]:
        self._started = True
        self._idle_since = now
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
        h = _HANDLERS.get(type(msg))
        if h is None:
            self.counters.ignored_phase += 1
            return out
        h(self, msg, now, out)
        return out

    def tick(self, now: float) -> list[Out]:
        """Timers: periodic sends, windows, timeouts."""
        out: list[Out] = []
        ph = self.phase
        if ph in _TIMER_PHASES["advertize"] and self._due("advertize", now, self.profile.advertize_interval):
            fc = self.has_fc and self.vehicle_ok
            flags = (FLAG_HAS_FC if fc else 0) | (FLAG_LEADER if ph == Phase.LEADER else 0)
            out.append(Out(ADVERTIZE, Advertize(self.me, self.name or f"agent{self.me}", flags)))
        if ph == Phase.IDLE and _elapsed(now, self._idle_since, self.profile.alone_timeout) and self.can_lead:
            self._become_leader(now, set())  # a swarm of one
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
        elif ph == Phase.MEMBER and _elapsed(now, self._member_deadline(), 0.0):
            self.counters.left += 1
            self._go_idle(now)
            out += self.tick(now)
        return out

    def next_deadline(self) -> float | None:
        """When :meth:`tick` next has something to do."""
        p = self.profile
        times = [t for k, t in self._next.items() if self.phase in _TIMER_PHASES[k]]
        if self.phase == Phase.IDLE and self.can_lead:
            times.append(self._idle_since + p.alone_timeout)
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
            times.append(self._member_deadline())
        times += [t + p.startpool_retry for t in self._asked.values()]
        return min(times) if times else None

    def _member_deadline(self) -> float:
        """When a member leaves: no sign of its leader for ``leader_timeout``, or no
        Heartbeat (which only members are sent) for ``HB_SILENCE_FACTOR`` times that."""
        p = self.profile
        return min(
            max(self.last_hb, self.leader_seen) + p.leader_timeout,
            self.last_hb + HB_SILENCE_FACTOR * p.leader_timeout,
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
    def can_lead(self) -> bool:
        """False while an agent with a flight controller has lost its link to it."""
        return self.vehicle_ok or not self.has_fc

    def set_vehicle_link(self, up: bool, now: float) -> None:
        """The flight controller's link lost (``up`` false) or back. See "A leader
        that cannot fly hands over" in the module docstring."""
        if up != self.vehicle_ok:
            self.vehicle_ok = up
            self.vehicle_lost_at = now

    def set_task(self, task: Task) -> None:
        """The leader's task; it rides on the next Heartbeats."""
        self.task = task

    def take_state_changed(self) -> bool:
        """True once after the phase, leader, vote or membership changed."""
        dirty, self._state_dirty = self._state_dirty, False
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
    def _due(self, timer: str, now: float, interval: float) -> bool:
        t = self._next.get(timer)
        if t is None or now + _EPS >= t:
            self._next[timer] = now + interval
            return True
        return False

    def _set_phase(self, phase: Phase) -> None:
        if phase != self.phase:
            self.phase = phase
            self._state_dirty = True

    def _change_pool(self, add: set[int] | frozenset[int], now: float) -> bool:
        new = set(add) - self.pool
        if not new:
            return False
        self.pool |= new
        self.changed_at = now
        self.counters.merges += 1
        return True

    def _open_pool(self, other: set[int] | frozenset[int], now: float) -> None:
        self.pool = {self.me}
        self._change_pool(other, now)
        self.locked = False
        self._set_phase(Phase.POOLING)
        self._next.pop("sync", None)

    def _go_idle(self, now: float) -> None:
        self._set_phase(Phase.IDLE)
        self.pool = set()
        self.locked = False
        self.leader = 0
        self.members = {}
        self.vote = (0, 0)
        self._idle_since = now
        self._asked.clear()
        self._synced_digest.clear()
        self._next = {"advertize": now}

    def _become_leader(self, now: float, members: set[int]) -> None:
        self._set_phase(Phase.LEADER)
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
        self._go_idle(now)

    def _become_member(self, leader: int, now: float) -> None:
        self._set_phase(Phase.MEMBER)
        self.leader = leader
        self.last_hb = now
        self.members = {}
        self._next = {}
        self._asked.clear()

    def _sync_msg(self, to: int) -> SyncPool:
        d = pool_digest(self.pool)
        # members travel only when this peer has not yet seen this pool from us
        members = None if self._synced_digest.get(to) == d else frozenset(self.pool)
        self._synced_digest[to] = d
        return SyncPool(self.me, d, self.locked, members)

    def _pool_timers(self, now: float, out: list[Out]) -> None:
        p = self.profile
        if self._due("sync", now, p.sync_interval):
            for m in sorted(self.pool - {self.me}):
                out.append(Out(m, self._sync_msg(m)))
        for a, t in list(self._asked.items()):
            if a in self.pool:
                del self._asked[a]
            elif _elapsed(now, t, p.startpool_retry) and not self.locked:
                self._asked[a] = now
                out.append(Out(a, StartPool(self.me)))
        window = p.lock_window if not self.locked or p.confirm_window is None else p.confirm_window
        if _elapsed(now, self.changed_at, window):
            if not self.locked:
                self.locked = True
                self.changed_at = now  # the second window starts now
                self._set_phase(Phase.LOCKED)
                self._asked.clear()
            else:
                self._start_election(now, out)

    def _start_election(self, now: float, out: list[Out]) -> None:
        self._set_phase(Phase.ELECTING)
        self.epoch = pool_digest(self.pool) & 0xFFFF
        # an agent that cannot fly votes for itself with weight 0: anyone else wins
        self.vote = (self.policy.weight(self.rng) if self.can_lead else 0, self.me)
        self.vote_changed_at = now
        self._next["vote"] = now

    def _election_timers(self, now: float, out: list[Out]) -> None:
        p = self.profile
        if self._due("vote", now, p.vote_interval):
            sel = Selection(self.me, self.vote[1], self.vote[0], self.epoch)
            out += [Out(m, sel) for m in sorted(self.pool - {self.me})]
        if _elapsed(now, self.vote_changed_at, p.vote_window):
            if self.vote[1] == self.me:
                self._become_leader(now, self.pool - {self.me})
            else:
                self._become_member(self.vote[1], now)

    def _leader_timers(self, now: float, out: list[Out]) -> None:
        p = self.profile
        for m, t in list(self.members.items()):
            if _elapsed(now, t, p.ack_timeout):
                del self.members[m]
                self.poses.pop(m, None)
                self.pool.discard(m)
                self.counters.expelled += 1
                self._state_dirty = True
        if self._due("heartbeat", now, p.heartbeat_interval) and self.members:
            # the formation follows membership: departed members close up, newcomers
            # join an arm, a new leader assigns afresh (swarm.core.formation.reconcile)
            self.task = reconcile(self.task, self.me, self.members, self.poses, self.pose)
            self.hb_seq = (self.hb_seq + 1) & 0xFF
            hb = Heartbeat(self.me, self.epoch, self.hb_seq, frozenset(self.members), self.task)
            out += [Out(m, hb) for m in sorted(self.members)]

    # -- message handlers ------------------------------------------------------
    def _on_advertize(self, msg: Advertize, now: float, out: list[Out]) -> None:
        a = msg.sender
        if self.phase == Phase.LEADER and msg.flags & FLAG_LEADER and a not in self.members:
            # another swarm's leader: show it our swarm so the merge rule can apply
            # (Heartbeats go only to members, so leaders would never hear each other)
            out.append(
                Out(a, Heartbeat(self.me, self.epoch, self.hb_seq, frozenset(self.members), self.task))
            )
            return
        if self.phase == Phase.IDLE and msg.flags & FLAG_LEADER:
            self._idle_since = now  # not alone: a swarm is there to join (see "Alone")
        if self.phase == Phase.IDLE or (self.phase == Phase.POOLING and a not in self.pool):
            asked = self._asked.get(a)
            if asked is not None and now - asked < self.profile.startpool_retry:
                return  # asked a moment ago; each Advertize after that asks again
            self._asked[a] = now
            out.append(Out(a, StartPool(self.me)))
        else:
            self.counters.ignored_phase += 1

    def _on_start_pool(self, msg: StartPool, now: float, out: list[Out]) -> None:
        a = msg.sender
        if self.phase == Phase.IDLE:
            self._open_pool({a}, now)
            out.append(Out(a, StartPoolAck(self.me, PoolStatus.SUCCESS, False, frozenset(self.pool))))
        elif self.phase == Phase.POOLING:
            self._change_pool({a}, now)
            out.append(Out(a, StartPoolAck(self.me, PoolStatus.ALREADY_IN_POOL, False, frozenset(self.pool))))
        elif self.phase == Phase.LEADER:
            # late joiner: adopt it; our Heartbeats will list it
            if a not in self.members:
                self.members[a] = now
                self.pool.add(a)
                self._state_dirty = True
            out.append(Out(a, StartPoolAck(self.me, PoolStatus.ALREADY_IN_POOL, True, frozenset(self.pool))))
        else:
            self.counters.ignored_phase += 1  # the paper: ignored

    def _on_start_pool_ack(self, msg: StartPoolAck, now: float, out: list[Out]) -> None:
        a = msg.sender
        self._asked.pop(a, None)
        if msg.locked:
            return  # a leader adopted us: its Heartbeat will tell
        if self.phase == Phase.IDLE:
            self._open_pool(set(msg.members) | {a}, now)
        elif self.phase == Phase.POOLING:
            self._change_pool(set(msg.members) | {a}, now)
        else:
            self.counters.ignored_phase += 1

    def _on_sync_pool(self, msg: SyncPool, now: float, out: list[Out]) -> None:
        a = msg.sender
        if self.phase not in (Phase.POOLING, Phase.LOCKED, Phase.ELECTING):
            self.counters.ignored_phase += 1
            return
        if a not in self.pool:
            if self.phase == Phase.POOLING or (msg.members is not None and self.me in msg.members):
                self._change_pool({a}, now)
            else:
                self.counters.ignored_foreign += 1
                return
        if self.phase == Phase.ELECTING:
            # the election runs on a frozen pool: a peer with another pool is told ours
            # (one with ours locks on our Selection: silence)
            if msg.digest != pool_digest(self.pool):
                out.append(Out(a, SyncPoolAck(self.me, False, True, frozenset(self.pool))))
            return
        if msg.members is not None:
            self._change_pool(msg.members, now)
        mine = pool_digest(self.pool)
        if msg.digest == mine:
            if msg.locked and not self.locked:
                self._lock_from_peer(now)
            if msg.locked != self.locked:
                # only a lock state worth spreading earns an ack: with N agents an ack
                # for every agreeing SyncPool would be N^2 frames per interval
                out.append(Out(a, SyncPoolAck(self.me, True, self.locked)))
        else:
            out.append(Out(a, SyncPoolAck(self.me, False, self.locked, frozenset(self.pool))))

    def _lock_from_peer(self, now: float) -> None:
        self.locked = True
        self.changed_at = now
        self._set_phase(Phase.LOCKED)
        self._asked.clear()

    def _on_sync_pool_ack(self, msg: SyncPoolAck, now: float, out: list[Out]) -> None:
        if self.phase not in (Phase.POOLING, Phase.LOCKED):
            self.counters.ignored_phase += 1
            return
        if msg.sender not in self.pool:
            self.counters.ignored_foreign += 1
            return
        if msg.same:
            if msg.locked and not self.locked:
                self._lock_from_peer(now)
            return
        if self._change_pool(msg.members, now):
            self._synced_digest.clear()  # everyone must hear the merged pool

    def _on_selection(self, msg: Selection, now: float, out: list[Out]) -> None:
        if msg.sender not in self.pool:
            self.counters.ignored_foreign += 1
            return
        if self.phase == Phase.POOLING and msg.epoch == pool_digest(self.pool) & 0xFFFF:
            self._lock_from_peer(now)  # a vote on our very pool: it is locked
        if self.phase == Phase.LOCKED:
            self._start_election(now, out)
        if self.phase != Phase.ELECTING:
            self.counters.ignored_phase += 1
            return
        if msg.epoch != self.epoch:
            self.counters.ignored_stale += 1
            return
        if msg.candidate not in self.pool:
            self.counters.impossible += 1
            return
        theirs = (msg.weight, msg.candidate)
        if theirs > self.vote:
            self.vote = theirs
            self.vote_changed_at = now
            self._state_dirty = True

    def _on_heartbeat(self, msg: Heartbeat, now: float, out: list[Out]) -> None:
        lead = msg.sender
        if self.phase == Phase.LEADER:
            mine, theirs = (len(self.members) + 1, self.me), (len(msg.members) + 1, lead)
            if theirs > mine and self.me in msg.members:
                self._become_member(lead, now)  # absorbed by the larger swarm
            elif theirs > mine:
                self.counters.merges += 1  # it will absorb us when it hears our heartbeat
            else:
                # absorb the other swarm: its leader and members
                for m in {lead} | set(msg.members):
                    if m != self.me and m not in self.members:
                        self.members[m] = now
                        self.pool.add(m)
                self.counters.merges += 1
                self._state_dirty = True
                return
            if self.phase != Phase.MEMBER:
                return
        if self.me not in msg.members:
            if self.phase == Phase.MEMBER and lead == self.leader:
                self.counters.left += 1  # expelled: leave and start again
                self._go_idle(now)
            else:
                self.counters.ignored_foreign += 1
            return
        if self.phase != Phase.MEMBER or self.leader != lead:
            self._become_member(lead, now)
        if self.task != msg.task:
            self.task = msg.task
        self.last_hb = now
        self.epoch = msg.epoch
        out.append(Out(lead, HeartbeatAck(self.me, msg.seq, self.pose or NO_POSE)))

    def _on_heartbeat_ack(self, msg: HeartbeatAck, now: float, out: list[Out]) -> None:
        if self.phase != Phase.LEADER:
            self.counters.ignored_phase += 1
            return
        if msg.sender not in self.members:
            self.counters.ignored_foreign += 1
            return
        self.members[msg.sender] = now
        self.poses[msg.sender] = replace(msg.pose)


_HANDLERS: dict[type, Callable[[Core, Message, float, list[Out]], None]] = {
    Advertize: Core._on_advertize,  # type: ignore[dict-item]
    StartPool: Core._on_start_pool,  # type: ignore[dict-item]
    StartPoolAck: Core._on_start_pool_ack,  # type: ignore[dict-item]
    SyncPool: Core._on_sync_pool,  # type: ignore[dict-item]
    SyncPoolAck: Core._on_sync_pool_ack,  # type: ignore[dict-item]
    Selection: Core._on_selection,  # type: ignore[dict-item]
    Heartbeat: Core._on_heartbeat,  # type: ignore[dict-item]
    HeartbeatAck: Core._on_heartbeat_ack,  # type: ignore[dict-item]
}
