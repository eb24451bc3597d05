"""The radio bridge's table of agent names and ids, and its name conflicts.

Theory of operation
-------------------
A radio frame names its sender by MAVLink system id only; the Zenoh keys name
agents by name. :class:`NameTable` learns the pairs from Advertize and GSAdvertize
(:meth:`NameTable.learn`), starting with the node's own, which never expires:

* a pair that agrees with what is known (or is new on both sides) is recorded
  and its time refreshed;
* a pair that clashes (the name known under another id, or the id under another
  name) is a conflict, unless every mapping it clashes with was not heard for
  ``stale_s`` (30 s): a stale mapping gives way to the new claim (an agent
  restarted under another id, a radio moved to another aircraft).

On a conflict the bridge counts and logs it, and tells the agents involved with a
NameConflict (:func:`conflict_note`): both claimants, and its own agent, which may
be one of the two. A ground station (ids 251..255) tells nobody. Pure: the caller
passes ``now``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from swarm.core.wire.message_types import NameConflict

STALE_S = 30.0


@dataclass
class Peer:
    id: int
    name: str
    seen: float


class NameTable:
    """Names <-> ids, seeded with this node's own pair. See the module docstring."""

    def __init__(self, name: str, agent_id: int, stale_s: float = STALE_S) -> None:
        self.stale_s = stale_s
        own = Peer(agent_id, name, math.inf)
        self._by_name: dict[str, Peer] = {name: own}
        self._by_id: dict[int, Peer] = {agent_id: own}

    def id_of(self, name: str) -> int | None:
        p = self._by_name.get(name)
        return None if p is None else p.id

    def name_of(self, agent_id: int) -> str | None:
        p = self._by_id.get(agent_id)
        return None if p is None else p.name

    def as_dict(self) -> dict[str, int]:
        """Every known name with its id."""
        return {n: p.id for n, p in self._by_name.items()}

    def learn(self, name: str, agent_id: int, now: float) -> int | None:
        """Record ``name`` <-> ``agent_id`` heard at ``now``: None when it is recorded,
        else the id of the other claimant (``agent_id`` itself when its id is taken
        by another name)."""
        by_name, by_id = self._by_name.get(name), self._by_id.get(agent_id)
        if (by_name is None or by_name.id == agent_id) and (by_id is None or by_id.name == name):
            peer = by_name or Peer(agent_id, name, now)
            peer.seen = now
            self._by_name[name] = self._by_id[agent_id] = peer
            return None
        # a stale mapping (not heard for stale_s) gives way to the new claim
        known = [p for p in (by_name, by_id) if p is not None]
        stale = [p for p in known if now - p.seen > self.stale_s]
        if stale and len(stale) == len(known):
            for p in stale:
                self._by_name.pop(p.name, None)
                self._by_id.pop(p.id, None)
            return self.learn(name, agent_id, now)
        if by_name is not None and by_name.id != agent_id:
            return by_name.id
        return by_id.id if by_id is not None else agent_id


def conflict_note(
    own_id: int, name: str, agent_id: int, other: int | None
) -> tuple[NameConflict, list[int]] | None:
    """The NameConflict a node with ``own_id`` sends about ``name`` claimed by
    ``agent_id`` (``other``: the other claimant's id, if known), and the agents to
    send it to over the air (the node's own agent is told besides); None when nobody
    is told (a ground station's node, an id that is no agent's)."""
    if own_id > 250 or not 1 <= agent_id <= 250:
        return None
    note = NameConflict(own_id, name, other if other is not None and 1 <= other <= 250 else agent_id)
    targets = {agent_id} | ({other} if other else set())
    return note, [t for t in sorted(targets - {own_id}) if 1 <= t <= 250]
