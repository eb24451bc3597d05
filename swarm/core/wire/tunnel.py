"""The swarm's messages in MAVLink 2 TUNNEL payloads: the one codec the radio bridge,
both simulators, the tracks and the station replay use.

Theory of operation
-------------------
A compact message (:mod:`swarm.core.wire.messages`) crosses the air in the payload of a
TUNNEL frame (id 385). The frame's ``payload_type`` is ``PAYLOAD_TYPE_BASE + kind``
(:class:`Kind`: advertize, GSAdvertize, P2P, pose, state, multicast P2P), its
``target_system`` the addressee's id (0 for everyone), its payload the message's
bytes. A *multicast* frame carries one P2P message to several addressees:
``[n][id_1 .. id_n][message]`` with target 0, so a leader's heartbeat to its members
costs one frame.

:func:`pack` gives the three fields of one frame; :func:`group` turns what a node
sends at one moment (``(addressee, bytes)`` pairs) into frames, merging identical
P2P messages into multicast ones when they fit; :func:`fits_multicast` is the rule
the radio bridge applies to its queue; :func:`unpack_tunnel` reads a received
payload back. Building the MAVLink frame itself (sequence, signing) is the caller's:
:class:`radios.mavlink.FrameBuilder`. Pure: no I/O, no clock.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from enum import IntEnum

from swarm.errors import DecodeError

PAYLOAD_TYPE_BASE = 32768
TUNNEL_MAX = 128
COMP_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER: the component id of every swarm frame


class Kind(IntEnum):
    ADVERTIZE = 0
    GS_ADVERTIZE = 1
    P2P = 2
    POSE = 3
    STATE = 4
    MULTI = 5  # P2P to several peers: [n][ids...][message]


def fits_multicast(body_len: int, addressees: int) -> bool:
    """Whether a message of ``body_len`` bytes to ``addressees`` peers fits one
    multicast payload (count byte, the ids, the message)."""
    return body_len + 1 + addressees <= TUNNEL_MAX


def pack(kind: Kind, targets: Sequence[int], body: bytes) -> tuple[int, int, bytes]:
    """``(target_system, payload_type, payload)`` of the TUNNEL frame carrying ``body``
    to ``targets`` (one id, or ``[0]`` for everyone; MULTI: the addressees, sorted
    and without repeats on the air)."""
    if kind == Kind.MULTI:
        ids = sorted(set(targets))
        return 0, PAYLOAD_TYPE_BASE + int(kind), bytes([len(ids), *ids]) + body
    return targets[0], PAYLOAD_TYPE_BASE + int(kind), body


def group(outs: Iterable[tuple[int, bytes]]) -> list[tuple[Kind, tuple[int, ...], bytes]]:
    """P2P messages sent together, as frames: ``(kind, targets, body)`` in the order
    each message first appears; one message to several peers becomes one MULTI frame
    when it fits (else one P2P frame per peer, in id order)."""
    groups: dict[bytes, list[int]] = {}
    for to, data in outs:
        groups.setdefault(data, []).append(to)
    frames: list[tuple[Kind, tuple[int, ...], bytes]] = []
    for data, tos in groups.items():
        targets = tuple(sorted(set(tos)))
        if len(targets) > 1 and fits_multicast(len(data), len(targets)):
            frames.append((Kind.MULTI, targets, data))
        else:
            frames += [(Kind.P2P, (t,), data) for t in targets]
    return frames


def unpack_tunnel(payload: bytes) -> tuple[Kind, int, bytes, bytes] | None:
    """A TUNNEL payload as the bridge puts it on the air: (kind, target system,
    addressees (MULTI only, else empty), the compact message's bytes). None for a
    payload type that is not the swarm's. MULTI is returned as is: the caller checks
    whether it is among the addressees.

    Raises:
        DecodeError: a MULTI payload whose addressee list does not fit.
    """
    p = payload.ljust(5 + TUNNEL_MAX, b"\0")
    ptype = p[0] | (p[1] << 8)
    if not PAYLOAD_TYPE_BASE <= ptype < PAYLOAD_TYPE_BASE + len(Kind):
        return None
    kind = Kind(ptype - PAYLOAD_TYPE_BASE)
    data = p[5 : 5 + min(p[4], TUNNEL_MAX)]
    if kind == Kind.MULTI:
        if not data or len(data) < 1 + data[0]:
            raise DecodeError("multicast addressee list does not fit its payload")
        return kind, p[2], data[1 : 1 + data[0]], data[1 + data[0] :]
    return kind, p[2], b"", data


__all__ = [
    "COMP_ID",
    "PAYLOAD_TYPE_BASE",
    "TUNNEL_MAX",
    "Kind",
    "fits_multicast",
    "group",
    "pack",
    "unpack_tunnel",
]
