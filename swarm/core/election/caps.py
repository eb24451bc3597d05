"""Sub-swarms with a size cap or a swarm name: their decisions for the protocol core, and the leaders' table.

Theory of operation
-------------------
An agent given a cap (``Core(..., cap=N)``, the agent's ``--swarm-cap N``) never lets
its pool or its swarm hold more than N agents; the agents beyond it form further
swarms, each electing its own leader with the paper's protocol. ``cap`` 0 is no cap:
every function here then answers as the paper does, and the core sends the same
bytes as without this module. The rules, each decided here and called from one hook
in :mod:`swarm.core.election.rules` or :class:`swarm.core.election.protocol.Core`:

* **A capped agent says how big it is**: its Advertize carries its pool's or swarm's
  size while it pools (as the pool's founder) or leads (:func:`advert`).
* **Free agents pool by blocks of ids** (:func:`skip_advert`, :func:`block`): a free
  agent asks (StartPool) only the lower ids of its block (1..cap, cap+1..2*cap, ...)
  and leaders with room, so blocks pool side by side and any mixing within a block
  fits; one free for FALLBACK_INTERVALS advertise intervals (:func:`late`) asks anyone
  with room. Capped pooling agents ask nobody (pools do not merge; swarms may later).
* **One admitter per pool** (:func:`refuses`): only the pool's founder (the agent that
  answered Success) admits; the other members answer FULL and do not advertise.
* **Nobody asks a full pool or swarm**: an advertiser it would not fit in is not
  asked, and a leader sends its Heartbeat to another leader (the merge rule's first
  step) only if both swarms would fit. A full leader's Advertize does not count against
  the "Alone" rule, so an agent hearing only full swarms pools with the other free
  agents or leads a swarm of one.
* **Admission is refused when full**: a pool or swarm at the cap answers StartPool
  with StartPoolAck FULL and its members; the asker does not ask it again until an
  Advertize shows it smaller or REFUSAL_RETRIES retry intervals pass
  (:func:`note_refusal`): it never asks a full leader forever.
* **Pools merge only when the union fits** (:meth:`Core.change_pool`); a union that
  would not fit (two admissions at once, a late agent) keeps the cap's lowest ids
  (:func:`trim`), a function of the union alone, so every agent that sees it decides
  the same; an agent left out goes back to IDLE.
* **Swarms merge only when the sum fits** (:func:`may_absorb`): today's rule (the
  larger (size, id) absorbs the smaller) applies only when the union of both swarms
  fits; otherwise both swarms stay as they are.
* **A member stays with its leader** (:func:`may_switch`): with a cap, a member
  listed by another leader's Heartbeat follows it only when that Heartbeat also
  lists its own leader (the two swarms merged); otherwise it stays and acknowledges
  only its own leader, and answers the other one with a SyncPoolAck naming its own
  swarm, on which that leader lets it go (:func:`release`). Without the cap a member
  follows whichever leader lists it (the paper's merge).
* **A member by its vote** asks its candidate (StartPool) to be listed, and a leader
  of its block with room it heard if that is another (:func:`ask_after_vote`); it
  follows the first leader whose Heartbeat lists it; if no
  Heartbeat lists it within CONFIRM_INTERVALS heartbeat intervals
  (:func:`unconfirmed_deadline`: the candidate does not lead, or leads another pool)
  it leaves and asks at once a leader with room it heard (:func:`rejoin`).
* **Leaders know of each other**: :class:`LeaderTable` keeps every other leader
  heard (id, size, last heard) from Advertizes (FLAG_LEADER) and Heartbeats, kept
  with or without a cap; entries not heard for ``forget_s`` are dropped. A command
  for every swarm is sent by a station to each leader it sees (docs/design/election.md),
  not through a leader of leaders.
* **Leaders court the larger** (:func:`courted`): a leader's periodic Heartbeat also
  goes (one more addressee in the same frame) to every other leader it heard within
  one leader timeout that would absorb it (at most COURT_MAX, the largest known first:
  forged Advertizes cannot grow the frame), until that leader's Heartbeat lists it. The
  merge then needs one of those Heartbeats to reach the larger leader, not a reply
  timed to the one Advertize it happened to hear: over a lossy one-way leg a merge
  waited for the smaller leader to hear the larger twice (a campaign run at 25 % loss
  kept two leaders in one group 23 s).
* **Names** (``Core(..., swarm_name=NAME)``, the agent's ``--swarm-name``): a named
  agent's Advertize carries its name's 16-bit tag (:func:`swarm.core.wire.message_types.swarm_tag`,
  flag ADV_SWARM); an agent asks, courts, absorbs or follows only agents that advertised
  its own tag (none for an agent without a name), and a named agent takes into its pool
  only agents it heard advertise its tag (:func:`foreign`). Agents of different names
  never pool or merge, with or without a cap.

* **Under the tdm profile** (:mod:`swarm.core.election.tdm`) the rules above apply
  to tdm's exchanges (its "With a size cap"): admission by SyncPool within the cap and
  the founder rule, and a full pool that heard every vote decides without its lock
  window (:func:`full`).

Pure: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from swarm.core.wire.message_types import (
    ADV_SIZE,
    ADV_SWARM,
    Advertize,
    Heartbeat,
    Phase,
    SyncPoolAck,
    swarm_tag,
)

if TYPE_CHECKING:
    from swarm.core.election.protocol import Core

FLAG_LEADER = 0x02  # as swarm.core.election.rules.FLAG_LEADER (that module imports this one)
MAX_CAP = 250
#: other leaders a leader's periodic Heartbeat courts at most (:func:`courted`)
COURT_MAX = 3


def check_cap(cap: object) -> int:
    """``cap`` as a size cap: 0 (none) or 2..250 agents.

    Raises:
        ValueError: anything else (the caller's misuse or a bad setting).
    """
    if not isinstance(cap, int) or isinstance(cap, bool) or not (cap == 0 or 2 <= cap <= MAX_CAP):
        raise ValueError(f"a swarm cap is 0 (no cap) or 2..{MAX_CAP} agents, not {cap!r}")
    return cap


def tag_of(swarm_name: str) -> int:
    """The tag a swarm name travels as (0: no name).

    Raises:
        MessageError: not a valid name (1-16 of A-Z a-z 0-9 _ -).
    """
    return swarm_tag(swarm_name) if swarm_name else 0


def fits(total: int, cap: int) -> bool:
    """Whether ``total`` agents fit under ``cap`` (0: no cap)."""
    return cap <= 0 or total <= cap


def size_of(core: Core) -> int:
    """The agent's pool or swarm size as it advertises it (a free agent: 1)."""
    if core.phase == Phase.LEADER:
        return len(core.members) + 1
    if core.phase == Phase.MEMBER:
        return 1
    return max(len(core.pool), 1)


def advert(core: Core, flags: int, name: str) -> Advertize | None:
    """The Advertize the core sends (None: none): with a cap, its size while pooling or
    leading, and none from a pooling agent that does not admit (not its pool's founder)."""
    tag = core.capped.tag
    flags |= ADV_SWARM if tag else 0
    if not core.cap or core.phase == Phase.IDLE:
        return Advertize(core.me, name, flags, 0, tag)
    if core.phase == Phase.POOLING and not core.capped.founder:
        return None
    return Advertize(core.me, name, flags | ADV_SIZE, size_of(core), tag)


def skip_advert(core: Core, msg: Advertize, now: float) -> bool:
    """Whether a capped core ignores this Advertize (see "Nobody asks a full pool" and
    "Free agents pool by blocks of ids"), or one of another swarm name ("Names")."""
    if core.capped.tag:
        core.capped.tags[msg.sender] = msg.swarm
    if msg.swarm != core.capped.tag:
        return True  # another swarm's (or a named agent heard by one without a name)
    if not core.cap or core.phase not in (Phase.IDLE, Phase.POOLING, Phase.LEADER):
        return False
    if core.phase == Phase.POOLING:
        return True  # capped pools grow by free agents only; swarms merge later
    a, refused = msg.sender, core.capped.refused.get(msg.sender)
    if refused is not None:
        size, when = refused
        if (msg.size and msg.size < size) or now - when >= REFUSAL_RETRIES * core.profile.startpool_retry:
            del core.capped.refused[a]  # it has room again, or it is long ago
        else:
            return True
    if msg.size and not fits(size_of(core) + msg.size, core.cap):
        return True
    if core.phase == Phase.IDLE and msg.flags & FLAG_LEADER:
        asked = core.asked.get(a)
        if asked is not None and now - asked >= RETRY_SLACK * core.profile.startpool_retry:
            core.answered(a)  # Advertizes come once a round, give or take: ask at each
    if core.phase == Phase.LEADER or msg.flags & FLAG_LEADER or late(core, now):
        return False  # a leader admits alone; a free agent late in finding a pool asks anyone
    return block(a, core.cap) != block(core.me, core.cap) or a > core.me


def block(agent: int, cap: int) -> int:
    """The block of ids ``agent`` pools with first: ids 1..cap, cap+1..2*cap, ..."""
    return (agent - 1) // cap


def founded(core: Core) -> None:
    """The core opened its pool on a StartPool: it is the pool's one admitter."""
    core.capped.founder = True


def confirmed(core: Core) -> None:
    """A Heartbeat of its leader listed the member: it is no longer a member by its vote
    alone (see "A member by its vote")."""
    core.capped.unconfirmed = False


def late(core: Core, now: float) -> bool:
    """Whether a capped free agent has been free for FALLBACK_INTERVALS advertise
    intervals: it then asks anyone with room, as the paper's agents do (within the cap)."""
    return now - core.capped.free_since >= FALLBACK_INTERVALS * core.profile.advertize_interval


def refuses(core: Core, asker: int) -> bool:
    """Whether the core answers a StartPool from ``asker`` with FULL: a capped pool or
    swarm at its cap, or a pooling agent that is not its pool's founder (one admitter
    per pool: two admitting at once would overfill it). An agent already in it is
    never refused."""
    if not core.cap or asker in core.pool or core.phase not in (Phase.POOLING, Phase.LEADER):
        return False
    if core.phase == Phase.POOLING and not core.capped.founder:
        return True
    return not fits(size_of(core) + 1, core.cap)


def note_refusal(core: Core, sender: int, members: frozenset[int], now: float) -> None:
    """A StartPoolAck FULL: stop asking ``sender`` until it advertises a smaller size or
    an alone timeout has passed."""
    core.answered(sender)
    core.capped.refused[sender] = (max(len(members), 1), now)


def trim(core: Core, new: set[int], now: float) -> bool:
    """Merge ``new`` into a capped pool that cannot hold them all: the pool keeps the
    ``cap`` lowest ids of the union (every agent that sees the same union keeps the
    same pool); an agent left out goes back to IDLE, free to join another. Returns
    whether the pool changed."""
    core.counters.refused += 1
    keep = set(sorted(core.pool | new)[: core.cap])
    if core.me not in keep:
        core.go_idle(now)
        return True
    if keep == core.pool:
        return False
    core.replace_pool(keep, now)
    return True


def unconfirmed_deadline(core: Core) -> float:
    """When a capped member that no Heartbeat has listed since its election leaves (see
    "A member by its vote"); infinity otherwise. Under the ``tdm`` profile a member that
    heard every vote decides at once while its candidate may still wait out its vote
    window: the deadline counts that window too."""
    if not core.capped.unconfirmed:
        return float("inf")
    p = core.profile
    return core.last_hb + CONFIRM_INTERVALS * p.heartbeat_interval + (p.vote_window if p.tdm else 0.0)


def full(core: Core) -> bool:
    """Whether the core's pool is at its cap (never without a cap): no agent can join it
    (see "With a size cap" in :mod:`swarm.core.election.tdm`)."""
    return bool(core.cap) and len(core.pool) >= core.cap


def rejoin(core: Core, now: float) -> int | None:
    """The leader a capped member asks at once when it leaves unconfirmed: one heard
    within two advertise intervals with room for it, its own block's first, then the
    largest; None if none (or no cap, or the member was confirmed)."""
    if not core.cap or not core.capped.unconfirmed:
        return None
    core.capped.unconfirmed = False
    return _leader_with_room(core, now, own_block=False)


def ask_after_vote(core: Core, now: float) -> list[int]:
    """Whom a capped agent that ends its election as a member asks to list it (StartPool):
    its candidate, and a leader of its block with room heard lately if that is another
    (the candidate may lead nothing: its pool elected differently). The first to list
    it is its leader (see "A member by its vote")."""
    core.capped.unconfirmed = True
    other = _leader_with_room(core, now, own_block=True)
    return [core.leader] + ([other] if other is not None and other != core.leader else [])


def _leader_with_room(core: Core, now: float, *, own_block: bool) -> int | None:
    """A leader heard within two advertise intervals with room for one more, of our
    name: of our block first, then the largest (only of our block if ``own_block``)."""
    known = core.other_leaders.current(now, 2 * core.profile.advertize_interval)
    mine = block(core.me, core.cap)
    room = [
        (block(k, core.cap) == mine, v.size, k)
        for k, v in known.items()
        if v.size and v.size < core.cap and not foreign(core, k, unknown=True)
    ]
    if own_block:
        room = [r for r in room if r[0]]
    return max(room)[2] if room else None


def release(core: Core, msg: SyncPoolAck) -> bool:
    """A capped or named leader told by one of its members that it follows another leader (a
    SyncPoolAck naming a swarm without us, see "A member stays with its leader") lets
    it go at once instead of after the ack timeout. Returns whether it did."""
    named_or_capped = core.cap or core.capped.tag
    if not named_or_capped or core.phase != Phase.LEADER or msg.sender not in core.members:
        return False
    if core.me in msg.members:
        return False
    core.expel(msg.sender)
    return True


def foreign(core: Core, agent: int, *, unknown: bool) -> bool:
    """Whether a named core keeps ``agent`` out: it advertised another name (or, when it
    has not been heard yet, ``unknown``). An agent without a name keeps nobody out."""
    if not core.capped.tag:
        return False
    theirs = core.capped.tags.get(agent)
    return unknown if theirs is None else theirs != core.capped.tag


def may_absorb(core: Core, msg: Heartbeat) -> bool:
    """Whether a leader may absorb the swarm of the leader of ``msg`` (the larger absorbs
    the smaller: the caller decides who is larger): the union of both swarms fits, and
    a named leader absorbs only a leader it heard advertise its name."""
    if foreign(core, msg.sender, unknown=True):
        return False
    if not core.cap:
        return True
    union = {core.me, msg.sender} | set(core.members) | set(msg.members)
    return fits(len(union), core.cap)


def courted(core: Core, now: float) -> list[int]:
    """The other leaders a leader's periodic Heartbeat also goes to (see "Leaders court
    the larger"): each heard within one leader timeout, not a member, not of another
    name, that would absorb us by the merge rule (a larger (size, id), or a size not
    heard yet) and, with a cap, whose swarm and ours fit together; at most COURT_MAX,
    the largest known first (forged leader Advertizes must not grow the frame: past
    what one TUNNEL frame holds, a Heartbeat would go as one frame per addressee)."""
    mine = (size_of(core), core.me)
    out: list[tuple[int, int]] = []
    for leader, info in core.other_leaders.current(now, core.profile.leader_timeout).items():
        if leader in core.members or foreign(core, leader, unknown=True):
            continue  # (never our own id: Core.handle drops what claims it)
        if info.size and ((info.size, leader) < mine or not fits(info.size + mine[0], core.cap)):
            continue
        out.append((info.size, leader))
    return [leader for _, leader in sorted(out, reverse=True)[:COURT_MAX]]


def may_switch(core: Core, msg: Heartbeat) -> bool:
    """Whether a member listed by another leader's Heartbeat follows it (see "A member
    stays with its leader"; a named member never follows a leader of another name)."""
    if foreign(core, msg.sender, unknown=False):
        return False
    return not core.cap or core.capped.unconfirmed or core.leader in msg.members


@dataclass(frozen=True)
class LeaderInfo:
    """Another leader as last heard: its swarm's size (0: not said) and when."""

    size: int
    heard: float


#: a free agent asks anyone with room (not only its chunk's seed) after this many
#: advertise intervals without a pool of its own
FALLBACK_INTERVALS = 4.0


@dataclass
class CapState:
    """What a capped core keeps for the cap's rules (unused without a cap)."""

    founder: bool = False  # opened its pool (answered Success): the pool's admitter
    refused: dict[int, tuple[int, float]] = field(default_factory=dict)  # FULL: (size, when)
    free_since: float = 0.0  # free (IDLE) since
    tag: int = 0  # our swarm name's tag (swarm_tag); 0: no name
    tags: dict[int, int] = field(default_factory=dict)  # named: the tags other agents advertise
    unconfirmed: bool = False  # a member by its vote, not yet listed by a Heartbeat


#: a refusal (StartPoolAck FULL) keeps an agent from asking again for this many
#: StartPool retry intervals, unless the refuser advertises a smaller size first
REFUSAL_RETRIES = 3.0

#: a capped member by its vote that no Heartbeat has listed within this many heartbeat
#: intervals leaves (its candidate does not lead, or leads without it)
CONFIRM_INTERVALS = 2.0
#: a capped free agent asks a leader again at its next Advertize heard this share of a
#: StartPool retry interval after the last question (Advertizes come once a TDM round,
#: give or take a little: "a full interval" skipped every other one)
RETRY_SLACK = 0.75

#: a leader not heard for this many leader timeouts is forgotten
FORGET_TIMEOUTS = 3.0


@dataclass
class LeaderTable:
    """The other leaders on the channel (id -> :class:`LeaderInfo`); an entry not heard
    for ``forget_s`` seconds is dropped."""

    leaders: dict[int, LeaderInfo] = field(default_factory=dict)

    def note(self, leader: int, size: int, now: float, forget_s: float) -> None:
        """``leader`` heard at ``now`` leading ``size`` agents (0: size unknown: the last
        known size is kept)."""
        old = self.leaders.get(leader)
        if size == 0 and old is not None:
            size = old.size
        self.leaders[leader] = LeaderInfo(size, now)
        if len(self.leaders) > 1:
            self.leaders = {k: v for k, v in self.leaders.items() if now - v.heard <= forget_s}

    def drop(self, leader: int) -> None:
        self.leaders.pop(leader, None)

    def current(self, now: float, forget_s: float) -> dict[int, LeaderInfo]:
        """The leaders heard within ``forget_s`` of ``now``, by id."""
        return {k: v for k, v in sorted(self.leaders.items()) if now - v.heard <= forget_s}


def forget_s(core: Core) -> float:
    return FORGET_TIMEOUTS * core.profile.leader_timeout


def note_leader_advert(core: Core, msg: Advertize, now: float) -> None:
    if msg.flags & FLAG_LEADER:
        core.other_leaders.note(msg.sender, msg.size, now, forget_s(core))
    else:
        core.other_leaders.drop(msg.sender)  # no longer leads


def note_leader_heartbeat(core: Core, msg: Heartbeat, now: float) -> None:
    core.other_leaders.note(msg.sender, len(msg.members) + 1, now, forget_s(core))


__all__ = [
    "CONFIRM_INTERVALS",
    "COURT_MAX",
    "FALLBACK_INTERVALS",
    "FORGET_TIMEOUTS",
    "MAX_CAP",
    "REFUSAL_RETRIES",
    "RETRY_SLACK",
    "CapState",
    "LeaderInfo",
    "LeaderTable",
    "advert",
    "ask_after_vote",
    "block",
    "check_cap",
    "confirmed",
    "courted",
    "fits",
    "foreign",
    "forget_s",
    "founded",
    "full",
    "late",
    "may_absorb",
    "may_switch",
    "note_leader_advert",
    "note_leader_heartbeat",
    "note_refusal",
    "refuses",
    "rejoin",
    "release",
    "size_of",
    "skip_advert",
    "tag_of",
    "trim",
    "unconfirmed_deadline",
]
