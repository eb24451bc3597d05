"""The simulator's judge for capped runs: sub-swarms instead of one swarm per connected group.

Theory of operation
-------------------
With a size cap (:mod:`swarm.core.election.caps`, ``swarm simulate --cap N``) a connected
group of agents settles into several swarms, so the plain judge's "one leader per
connected group" cannot hold. :func:`capped_agreement` says instead whether every
live agent is in a led swarm of at most ``cap`` agents: each leader lists at most
``cap - 1`` members, every listed member is live, in the leader's connected group,
a member following that leader, and listed by no other leader; every other live
agent is such a member. :func:`split_pairs` names the pairs of leaders of one
connected group whose swarms would fit together (every pair without a cap): the
merge rule should join them, so the simulator's split check times each such pair. Pure functions of the cores'
states: the simulator calls them where it calls its own judge.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from swarm.core.election.protocol import Core
from swarm.core.wire.message_types import Phase


def capped_agreement(live: Sequence[Core], cap: int, group: Callable[[int], int]) -> tuple[bool, int]:
    """(every live agent in a led swarm of at most ``cap``, the lowest leader's id).
    ``group`` gives an agent's connected group."""
    if not live:
        return True, 0
    by_id = {c.me: c for c in live}
    leaders = [c for c in live if c.phase == Phase.LEADER]
    listed: set[int] = set()
    for lead in leaders:
        if len(lead.members) + 1 > cap:
            return False, 0
        g = group(lead.me)
        for m in lead.members:
            c = by_id.get(m)
            if c is None or m in listed or c.phase != Phase.MEMBER or c.leader != lead.me or group(m) != g:
                return False, 0
            listed.add(m)
    if len(listed) + len(leaders) != len(live):
        return False, 0  # someone is in no swarm (pooling, electing, idle or unlisted)
    return bool(leaders), min((c.me for c in leaders), default=0)


def split_pairs(live: Sequence[Core], cap: int, group: Callable[[int], int]) -> set[tuple[int, int]]:
    """The pairs of leaders (lower id first) in one connected group that the merge rule
    should join: every such pair without a cap (``cap`` 0), those whose swarms would fit
    together with one."""
    by_group: dict[int, list[Core]] = {}
    for c in live:
        if c.phase == Phase.LEADER:
            by_group.setdefault(group(c.me), []).append(c)
    out: set[tuple[int, int]] = set()
    for leads in by_group.values():
        for k, a in enumerate(leads):
            for b in leads[k + 1 :]:
                if not cap or len(a.members) + len(b.members) + 2 <= cap:
                    out.add((min(a.me, b.me), max(a.me, b.me)))
    return out


__all__ = ["capped_agreement", "split_pairs"]
