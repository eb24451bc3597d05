"""The ``tdm`` profile's election: pooling and voting in the same rounds of a TDM channel.

Theory of operation
-------------------
On a SiK multipoint network every radio speaks once per TDM round and every radio in
range hears it. The paper's steps run one after the other (pool, lock window, vote,
vote window), each a round or more. The ``tdm`` profile
(:func:`swarm.core.election.profiles.tdm_profile`, ``Profile.tdm``) keeps the paper's messages,
phases and guarantees but overlaps the steps, so an agent's one slot per round carries
everything it knows:

* **News leaves in the next slot**: a frame a core queues waits for the radio's slot,
  so what changed (the pool, the vote) is sent at once rather than at the next
  periodic sync (:func:`news_at`: at most :data:`NEWS_PER_ROUND` / pool size times a
  round, so a slot does not overflow and delay the rest a round).
* **One SyncPool per round, with its members**: every sync interval (one round) an
  agent sends the same SyncPool, members included, to all its pool members: one
  multicast frame instead of one per member, and a member that lost a round's frame
  learns the pool from the next one. A StartPool is answered by that SyncPool (an
  idle agent listed in one joins the pool) instead of one StartPoolAck per asker.
* **The vote rides with the pool**: an agent draws its vote (weight, itself) when it
  first syncs a pool, and sends its best vote beside each SyncPool. A vote is a
  token "candidate C has weight W": it does not depend on the pool it was sent in,
  so votes flood while the pool still grows. A receiver adopts a heavier vote whose
  candidate is in its pool (weight, then candidate id, as the paper's rule); the
  sender's SyncPool, which travels in the same slot just before the vote, brings
  the candidate into the pool.
* **Lock, then decide as soon as everyone is heard**: a pool unchanged for
  ``lock_window`` (a round and a margin for a lost frame) locks, and the agent goes
  straight to ELECTING with the vote it gathered. An agent that has heard a vote
  from every other member decides at once (:func:`complete`): each vote is at least
  its sender's own weight, so the heaviest heard is the pool's heaviest, and agents
  that heard everyone on one pool name the same leader. Otherwise the paper's vote
  window decides, counted from the later of the vote's and the pool's last change
  (a member added late may hold a heavier vote): a member silent that long is
  presumed gone.
* **A member that decides sends its vote once more**: it stops voting when it
  follows, but a member that missed its vote would not hear everyone and would wait
  out the windows: the vote goes to the pool once more, in the member's next slot.
* **The leader's Heartbeat ends it for the others**: an agent that hears a Heartbeat
  listing it becomes a member at once (the paper's rule), so members need not wait
  out their own windows.

With a size cap (``Core(..., cap=N)``) these rules run with the cap's
(:mod:`swarm.core.election.caps`): a StartPool that a capped pool refuses (full, or we are not
its founder) or that comes from another swarm name gets the paper's answer
(StartPoolAck FULL, or none); a free agent that takes an asker in is its pool's
founder; a leader adopts the agents a member's SyncPool names only while the cap
leaves room (lowest ids first); a member by its vote asks its candidate to list it and
leaves if no Heartbeat does (the cap's "A member by its vote", its deadline counting
the candidate's vote window: the member may decide before it). And **a full pool that
heard every vote decides at once** (:func:`settled`): nobody can join a pool at its
cap, so the lock window has nothing to wait for. On one channel of 50 radios (a round
of 5.92 s, cap 10) a block pooled in round 1 is led about a round later, where the
lock and vote windows and a Heartbeat took the fast profile three rounds more.

The guarantees are the paper's: votes are adopted only for pool members, ties break on
the candidate id, and two leaders that a lost vote left in one connected pool hear each
other's Heartbeats (each lists the other as a member) and merge by the swarm rule
(the larger, then the higher id, absorbs the other). Pure: no I/O, no clock.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from swarm.core.election import caps
from swarm.core.election.outbox import Out
from swarm.core.election.rules import Handler
from swarm.core.election.rules import on_start_pool as on_start_pool_paper
from swarm.core.election.rules import on_sync_pool as on_sync_pool_paper
from swarm.core.wire.message_types import Phase, Selection, StartPool, SyncPool, pool_digest

if TYPE_CHECKING:
    from swarm.core.election.protocol import Core


#: news (a pool or vote change) is sent at once, but an agent sends at most this many news
#: frames per round divided by its pool's size (at most 8 and at least 1 a round): every
#: frame queued before its slot leaves in it and a full slot delays the rest, so the
#: whole swarm sends about as many news frames per round whatever its size
NEWS_PER_ROUND = 40


def _elapsed(now: float, since: float, span: float) -> bool:
    return now + 1e-9 >= since + span


def pool_timers(core: Core, now: float, out: list[Out]) -> None:
    """POOLING and LOCKED under the ``tdm`` profile: the round's SyncPool and vote to
    every member, StartPool retries, and the lock that starts the election."""
    p = core.profile
    core.draw_vote(now)
    others = sorted(core.pool - {core.me})
    news = news_at(core)
    if news is not None and now + 1e-9 >= news:
        core.send_sync_now()  # news: it leaves in this round's slot, not the next
    if core.due("sync", now, p.sync_interval) and others:
        digest = pool_digest(core.pool)
        sync = SyncPool(core.me, digest, core.locked, frozenset(core.pool))
        sel = Selection(core.me, core.vote[1], core.vote[0], digest & 0xFFFF)
        out += [Out(m, sync) for m in others]
        out += [Out(m, sel) for m in others]
    for a, t in list(core.asked.items()):
        if a in core.pool:
            core.answered(a)
        elif _elapsed(now, t, p.startpool_retry) and not core.locked:
            core.ask(a, now)
            out.append(Out(a, StartPool(core.me)))
    if core.locked or _elapsed(now, core.changed_at, p.lock_window) or settled(core):
        start_election(core, now, out)


def settled(core: Core) -> bool:
    """A capped pool at its cap whose every vote is heard: nobody can join it, so the
    lock window has nothing to wait for (see "With a size cap")."""
    return caps.full(core) and complete(core)


def news_at(core: Core) -> float | None:
    """When the pool or vote changed since the last SyncPool can be sent (None: no news)."""
    p = core.profile
    sync = core.next_send("sync")
    if sync is None or core.phase not in (Phase.POOLING, Phase.LOCKED):
        return None
    last = sync - p.sync_interval  # when the last SyncPool was sent
    if max(core.changed_at, core.vote_changed_at) <= last + 1e-9:
        return None
    return last + p.sync_interval * min(max(len(core.pool) / NEWS_PER_ROUND, 0.125), 1.0)


def start_election(core: Core, now: float, out: list[Out]) -> None:
    """Locked: elect on this pool, keeping the vote gathered while pooling."""
    core.elect_on_locked_pool(now)
    if complete(core):
        decide(core, now, out)


def complete(core: Core) -> bool:
    """Every other pool member's vote heard: each vote is at least its sender's own
    weight, so the heaviest vote heard is the pool's heaviest."""
    return core.heard >= core.pool - {core.me}


def decide(core: Core, now: float, out: list[Out]) -> None:
    """The election's end: the vote's candidate leads, the others follow it (with a cap,
    a member asks its candidate to list it: :meth:`swarm.core.election.protocol.Core.end_election`)."""
    core.end_election(now, out)
    if core.phase == Phase.MEMBER:
        # we stop voting now, but members that missed our vote would wait for it:
        # it goes once more, in our next slot
        sel = Selection(core.me, core.vote[1], core.vote[0], core.epoch)
        out += [Out(m, sel) for m in sorted(core.pool - {core.me})]


def on_selection(core: Core, msg: Selection, now: float, out: list[Out]) -> None:
    """A vote under the ``tdm`` profile: adopted while pooling or electing when it is
    heavier and names a pool member (its epoch names the sender's pool: not checked)."""
    if msg.sender not in core.pool:
        core.counters.ignored_foreign += 1
        return
    if core.phase not in (Phase.POOLING, Phase.LOCKED, Phase.ELECTING):
        core.counters.ignored_phase += 1
        return
    if msg.candidate not in core.pool:
        core.counters.ignored_stale += 1  # our pool has not caught up: its SyncPool will bring it
        return
    core.draw_vote(now)
    core.heard_vote(msg.sender)
    theirs = (msg.weight, msg.candidate)
    if theirs > core.vote:
        core.adopt_vote(theirs, now)
    if core.phase == Phase.ELECTING and complete(core):
        decide(core, now, out)
    elif core.phase in (Phase.POOLING, Phase.LOCKED) and settled(core):
        start_election(core, now, out)  # decides at once: every vote is heard


def on_start_pool(core: Core, msg: StartPool, now: float, out: list[Out]) -> None:
    """A free or pooling agent takes the asker into its pool without a StartPoolAck:
    its next SyncPool (news: at once) carries the pool to every member, the asker
    included, in one frame, where the paper's acks were one frame per asker. An asker
    of another swarm name, and one a capped pool refuses (full, or we do not admit),
    get the paper's answer (none, or StartPoolAck FULL)."""
    if caps.foreign(core, msg.sender, unknown=True) or caps.refuses(core, msg.sender):
        on_start_pool_paper(core, msg, now, out)
    elif core.phase == Phase.IDLE:
        core.open_pool({msg.sender}, now)
        caps.founded(core)  # the pool's admitter (swarm.core.election.caps)
    elif core.phase == Phase.POOLING:
        core.change_pool({msg.sender}, now)
    else:
        on_start_pool_paper(core, msg, now, out)


def on_sync_pool(core: Core, msg: SyncPool, now: float, out: list[Out]) -> None:
    """A free agent listed in a SyncPool's members joins that pool (the answer to its
    StartPool); anything else follows the paper's rule."""
    if core.phase == Phase.IDLE and msg.members is not None and core.me in msg.members:
        core.open_pool(set(msg.members) | {msg.sender}, now)
    if core.phase == Phase.LEADER and msg.members is not None and msg.sender in core.members:
        # a member still electing knows agents our pool locked without: they are
        # electing us too; adopt them as late joiners (our Heartbeats will list them),
        # the lowest ids first while the cap leaves room
        for m in sorted(msg.members - set(core.members) - {core.me}):
            if not caps.fits(len(core.members) + 2, core.cap):
                core.counters.refused += 1
                break
            core.adopt(m, now)
        return
    on_sync_pool_paper(core, msg, now, out)


#: the message rules the ``tdm`` profile replaces (:meth:`swarm.core.election.protocol.Core.handle`)
TDM_HANDLERS: dict[type, Handler] = {
    Selection: on_selection,
    StartPool: on_start_pool,
    SyncPool: on_sync_pool,
}


__all__ = [
    "NEWS_PER_ROUND",
    "TDM_HANDLERS",
    "complete",
    "decide",
    "news_at",
    "on_selection",
    "on_start_pool",
    "on_sync_pool",
    "pool_timers",
    "settled",
    "start_election",
]
