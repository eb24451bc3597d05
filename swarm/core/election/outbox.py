"""What the election sends: :class:`Out` (a message and where it goes), the advertize
broadcast's address, the Advertize flags, and the pose an agent without a flight
controller acknowledges with."""

from __future__ import annotations

from dataclasses import dataclass

from swarm.core.wire.message_types import Message, Pose

ADVERTIZE = 0  # Out.to for the advertize broadcast
#: the pose an agent without a flight controller acknowledges with ("null island")
NO_POSE = Pose(0.0, 0.0, 0.0)
FLAG_HAS_FC = 0x01
FLAG_LEADER = 0x02


@dataclass(frozen=True)
class Out:
    """A message to send: ``to`` is an agent id, or ADVERTIZE for the broadcast."""

    to: int
    msg: Message
