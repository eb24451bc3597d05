"""The election's message rules: what each message does to a :class:`~swarm.core.election.protocol.Core`.

Theory of operation
-------------------
:data:`HANDLERS` maps each message type to one function ``(core, msg, now, out)``
that reads and changes the core's state through its transitions (``open_pool``,
``change_pool``, ``lock_from_peer``, ``start_election``, ``become_member``,
``go_idle``) and appends what to send to ``out`` (:class:`Out`: a message and its
destination, ADVERTIZE for the broadcast). Together with the timers in
:meth:`swarm.core.election.protocol.Core.tick` these are the whole machine; the rules they
follow (the paper's steps and what goes beyond the paper) are written once, in
:mod:`swarm.core.election.protocol`'s docstring. A message that means nothing in the core's
phase, or comes from outside its pool or swarm, is counted and dropped: a peer's
message never raises. Pure: no I/O, no clock.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from swarm.core.election import caps, liveness
from swarm.core.election.outbox import FLAG_LEADER, NO_POSE, Out
from swarm.core.wire.message_types import (
    Advertize,
    Heartbeat,
    HeartbeatAck,
    Phase,
    PoolStatus,
    Selection,
    StartPool,
    StartPoolAck,
    SyncPool,
    SyncPoolAck,
    pool_digest,
)

if TYPE_CHECKING:
    from swarm.core.election.protocol import Core


def on_advertize(core: Core, msg: Advertize, now: float, out: list[Out]) -> None:
    a = msg.sender
    caps.note_leader_advert(core, msg, now)
    if caps.skip_advert(core, msg, now):
        core.counters.refused += 1  # it could not take us, or we could not merge
        return
    if core.phase == Phase.LEADER and msg.flags & FLAG_LEADER and a not in core.members:
        # another swarm's leader: show it our swarm so the merge rule can apply
        # (Heartbeats go only to members, so leaders would never hear each other)
        out.append(Out(a, Heartbeat(core.me, core.epoch, core.hb_seq, frozenset(core.members), core.task)))
        return
    if core.phase == Phase.IDLE and msg.flags & FLAG_LEADER:
        core.not_alone(now)  # not alone: a swarm is there to join (see "Alone")
    if core.phase == Phase.IDLE or (core.phase == Phase.POOLING and a not in core.pool):
        asked = core.asked.get(a)
        if asked is not None and now - asked < core.profile.startpool_retry:
            return  # asked a moment ago; each Advertize after that asks again
        core.ask(a, now)
        out.append(Out(a, StartPool(core.me)))
    else:
        core.counters.ignored_phase += 1


def on_start_pool(core: Core, msg: StartPool, now: float, out: list[Out]) -> None:
    a = msg.sender
    if caps.foreign(core, a, unknown=True):
        core.counters.ignored_foreign += 1  # another swarm name's (or one not heard yet)
        return
    if caps.refuses(core, a):
        core.counters.refused += 1  # full: the asker pools with others
        lead = core.phase == Phase.LEADER
        out.append(Out(a, StartPoolAck(core.me, PoolStatus.FULL, lead, frozenset(core.pool))))
        return
    if core.phase == Phase.IDLE:
        core.open_pool({a}, now)
        caps.founded(core)
        out.append(Out(a, StartPoolAck(core.me, PoolStatus.SUCCESS, False, frozenset(core.pool))))
    elif core.phase == Phase.POOLING:
        core.change_pool({a}, now)
        out.append(Out(a, StartPoolAck(core.me, PoolStatus.ALREADY_IN_POOL, False, frozenset(core.pool))))
    elif core.phase == Phase.LEADER:
        # late joiner: adopt it; our Heartbeats will list it
        core.adopt(a, now)
        out.append(Out(a, StartPoolAck(core.me, PoolStatus.ALREADY_IN_POOL, True, frozenset(core.pool))))
    else:
        core.counters.ignored_phase += 1  # the paper: ignored


def on_start_pool_ack(core: Core, msg: StartPoolAck, now: float, out: list[Out]) -> None:
    a = msg.sender
    core.answered(a)
    if msg.status == PoolStatus.FULL:
        caps.note_refusal(core, a, msg.members, now)
        return
    if msg.locked:
        return  # a leader adopted us: its Heartbeat will tell
    if core.phase == Phase.IDLE and not caps.fits(len(msg.members | {a, core.me}), core.cap):
        core.counters.refused += 1
    elif core.phase == Phase.IDLE:
        core.open_pool(set(msg.members) | {a}, now)
    elif core.phase == Phase.POOLING:
        core.change_pool(set(msg.members) | {a}, now)
    else:
        core.counters.ignored_phase += 1


def on_sync_pool(core: Core, msg: SyncPool, now: float, out: list[Out]) -> None:
    a = msg.sender
    if core.phase not in (Phase.POOLING, Phase.LOCKED, Phase.ELECTING):
        core.counters.ignored_phase += 1
        return
    if a not in core.pool:
        pooling = core.phase == Phase.POOLING or (msg.members is not None and core.me in msg.members)
        if pooling and not caps.foreign(core, a, unknown=True):
            core.change_pool({a}, now)
        if a not in core.pool:  # not ours, or a full pool (swarm.core.election.caps)
            core.counters.ignored_foreign += 1
            return
    if core.phase == Phase.ELECTING:
        # the election runs on a frozen pool: a peer with another pool is told ours
        # (one with ours locks on our Selection: silence)
        if msg.digest != pool_digest(core.pool):
            out.append(Out(a, SyncPoolAck(core.me, False, True, frozenset(core.pool))))
        return
    if msg.members is not None:
        core.change_pool(msg.members, now)
        if core.phase == Phase.IDLE:
            return  # the cap left us out of the merged pool (swarm.core.election.caps.trim)
    mine = pool_digest(core.pool)
    if msg.digest == mine:
        if msg.locked and not core.locked:
            core.lock_from_peer(now)
        if msg.locked != core.locked:
            # only a lock state worth spreading earns an ack: with N agents an ack
            # for every agreeing SyncPool would be N^2 frames per interval
            out.append(Out(a, SyncPoolAck(core.me, True, core.locked)))
    else:
        out.append(Out(a, SyncPoolAck(core.me, False, core.locked, frozenset(core.pool))))


def on_sync_pool_ack(core: Core, msg: SyncPoolAck, now: float, out: list[Out]) -> None:
    if caps.release(core, msg):
        return
    if core.phase not in (Phase.POOLING, Phase.LOCKED):
        core.counters.ignored_phase += 1
        return
    if msg.sender not in core.pool:
        core.counters.ignored_foreign += 1
        return
    if msg.same:
        if msg.locked and not core.locked:
            core.lock_from_peer(now)
        return
    if core.change_pool(msg.members, now):
        core.resync_all()  # everyone must hear the merged pool


def on_selection(core: Core, msg: Selection, now: float, out: list[Out]) -> None:
    if msg.sender not in core.pool:
        core.counters.ignored_foreign += 1
        return
    if core.phase == Phase.POOLING and msg.epoch == pool_digest(core.pool) & 0xFFFF:
        core.lock_from_peer(now)  # a vote on our very pool: it is locked
    if core.phase == Phase.LOCKED:
        core.start_election(now, out)
    if core.phase != Phase.ELECTING:
        core.counters.ignored_phase += 1
        return
    if msg.epoch != core.epoch:
        core.counters.ignored_stale += 1
        return
    if msg.candidate not in core.pool:
        core.counters.impossible += 1
        return
    theirs = (msg.weight, msg.candidate)
    if theirs > core.vote:
        core.adopt_vote(theirs, now)


def on_heartbeat(core: Core, msg: Heartbeat, now: float, out: list[Out]) -> None:
    lead = msg.sender
    caps.note_leader_heartbeat(core, msg, now)
    if core.phase == Phase.LEADER:
        mine, theirs = (len(core.members) + 1, core.me), (len(msg.members) + 1, lead)
        if theirs > mine and core.me in msg.members:
            core.become_member(lead, now)  # absorbed by the larger swarm
        elif theirs > mine:
            core.counters.merges += 1  # it will absorb us when it hears our heartbeat
        elif not caps.may_absorb(core, msg):
            core.counters.refused += 1  # both swarms would not fit under the cap: stay apart
            return
        else:
            # absorb the other swarm: its leader and members
            for m in {lead} | set(msg.members):
                core.adopt(m, now)
            core.counters.merges += 1
            core.changed()
            return
        if core.phase != Phase.MEMBER:
            return
    if core.me not in msg.members:
        if core.phase == Phase.MEMBER and lead == core.leader:
            core.counters.left += 1  # expelled: leave and start again
            core.go_idle(now)
        else:
            core.counters.ignored_foreign += 1
        return
    if core.phase == Phase.MEMBER and core.leader != lead and not caps.may_switch(core, msg):
        core.counters.ignored_foreign += 1  # with a cap, a member stays with its leader...
        out.append(Out(lead, SyncPoolAck(core.me, False, True, frozenset({core.me, core.leader}))))
        return  # ...and tells the other one so (swarm.core.election.caps.release)
    if core.phase != Phase.MEMBER or core.leader != lead:
        core.become_member(lead, now)
    core.heard_heartbeat(msg, now)
    caps.confirmed(core)
    out.append(Out(lead, HeartbeatAck(core.me, msg.seq, core.pose or NO_POSE)))


def on_heartbeat_ack(core: Core, msg: HeartbeatAck, now: float, out: list[Out]) -> None:
    if core.phase != Phase.LEADER:
        core.counters.ignored_phase += 1
        return
    if msg.sender not in core.members:
        core.counters.ignored_foreign += 1
        liveness.answer_stray_ack(core, msg, now, out)  # it takes us for its leader
        return
    core.heard_ack(msg.sender, replace(msg.pose), now)


#: a message rule: what one message does to the core, and what it sends
Handler = Callable[["Core", Any, float, list[Out]], None]

HANDLERS: dict[type, Handler] = {
    Advertize: on_advertize,
    StartPool: on_start_pool,
    StartPoolAck: on_start_pool_ack,
    SyncPool: on_sync_pool,
    SyncPoolAck: on_sync_pool_ack,
    Selection: on_selection,
    Heartbeat: on_heartbeat,
    HeartbeatAck: on_heartbeat_ack,
}
