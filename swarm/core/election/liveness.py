"""A member's own acknowledgement timer: liveness that survives a lossy link.

Theory of operation
-------------------
In the paper a member acknowledges only in answer to a Heartbeat, so one round of
liveness needs two frames through (the Heartbeat and its ack): at 29 % loss each
way that is half the rounds, and a 17-agent swarm lost a member to ``ack_timeout``
every few seconds somewhere (five missed rounds in a row: 0.496^5 = 3 % per member
per ack timeout), faster than the expelled ones re-joined; such swarms never held
one agreed membership for the settle time (issue 15, the fault campaign's last
family). Here a member whose leader's Heartbeat is overdue by ``OWN_ACK_SLACK``
intervals acknowledges anyway, with its pose and the last sequence number it
heard, and then every ``heartbeat_interval`` until a Heartbeat comes: a round
then needs one frame through, not two (five missed rounds: 0.29^5 = 0.2 %).

In a flying swarm the leader's pose stream, heard, restarts the timer: the member
streams its own pose, which its leader counts as its ack (swarm.core.election.protocol,
"Liveness from pose streams"), and acks on top only crowded the TDM slots the poses
need (5 agents at 10 % loss with 4 Hz poses: the formation's worst error in the turn
went from 1.6-2.4 m to up to 5.4 m over twelve seeds before this).
What it does not change: a member still answers every Heartbeat (the paper's
step), and one that hears none for ``leader_timeout`` still leaves; the leader
still expels a member silent for ``ack_timeout``. On a link that loses nothing every
Heartbeat arrives within the slack, the timer never fires, and the bytes on the air
are the paper's.

An ack can now come from an agent its leader no longer lists: one expelled by a run
of lost frames, or while cut off, that then heard a Heartbeat sent before the
expulsion (late by up to a TDM round) and took it as its leader's. Such an agent
follows this leader, so the leader takes it back at once, as it takes a late joiner
(the caps permitting): an unlucky expulsion heals within a round instead of the agent
acknowledging for a whole ``leader_timeout`` a leader that ignores it, then leaving
and re-joining. One the leader may not take is told (its Heartbeat, which does not
list it) and leaves at once. Pure: the functions read and change the core and append
what to send.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from swarm.core.election import caps
from swarm.core.election.outbox import NO_POSE, Out
from swarm.core.wire.message_types import Heartbeat, HeartbeatAck, Phase

if TYPE_CHECKING:
    from swarm.core.election.protocol import Core

#: a Heartbeat later than this many heartbeat intervals after the last ack: ack anyway
#: (above 1: a Heartbeat that is only a little late, its TDM slot drifting, is answered
#: by the paper's ack alone)
OWN_ACK_SLACK = 1.25
#: ... and the leader's pose stream silent this many heartbeat intervals (a TDM radio's
#: poses come in one burst per round, a round at most an interval: two bursts lost)
POSE_SILENCE = 3.0


def own_ack_due(core: Core) -> float:
    """When a member next acknowledges on its own (the core asks only in MEMBER); never
    for one its leader has not listed yet (with a cap, swarm.core.election.caps: an ack from an
    agent it does not list is ignored)."""
    if core.capped.unconfirmed:
        return float("inf")
    # the leader's pose stream heard restarts the timer: a flying swarm's member streams
    # its pose too, which its leader counts as its ack; acks on top only crowd the slots
    hb = core.profile.heartbeat_interval
    return max(core.acked_at + OWN_ACK_SLACK * hb, core.leader_seen + POSE_SILENCE * hb)


def own_ack(core: Core, now: float, out: list[Out]) -> None:
    """A member whose leader's Heartbeat is overdue acknowledges anyway."""
    if core.phase != Phase.MEMBER or now + 1e-9 < own_ack_due(core):
        return
    # the next one a whole interval on (the slack is for the first only)
    core.acked(now - (OWN_ACK_SLACK - 1.0) * core.profile.heartbeat_interval)
    out.append(Out(core.leader, HeartbeatAck(core.me, core.heard_seq, core.pose or NO_POSE)))


def answer_stray_ack(core: Core, msg: HeartbeatAck, now: float, out: list[Out]) -> None:
    """A leader hearing an ack from an agent it does not list: that agent takes it for
    its leader (one expelled by bad luck, or while cut off, that then heard a Heartbeat
    sent before the expulsion). It is taken back, as a late joiner would be; one the
    leader may not take (a full swarm, another swarm's name: swarm.core.election.caps) is sent
    the Heartbeat that does not list it, so it leaves at once and asks elsewhere (at
    most once per heartbeat interval per agent: forged acks get no more than that)."""
    a = msg.sender
    if core.phase != Phase.LEADER:
        return
    if not caps.refuses(core, a) and not caps.foreign(core, a, unknown=True):
        core.adopt(a, now, msg.pose)
        return
    told = core.told_at.get(a)
    if told is not None and now - told < core.profile.heartbeat_interval:
        return
    core.told(a, now)
    out.append(Out(a, Heartbeat(core.me, core.epoch, core.hb_seq, frozenset(core.members), core.task)))
