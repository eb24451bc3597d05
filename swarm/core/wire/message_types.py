"""The swarm's messages: every type the agents and stations exchange, as data.

Theory of operation
-------------------
Every message is a frozen dataclass with a ``TYPE`` number (0..31, the low five
bits of its first byte on the air); the value types it carries (:class:`Pose`,
:class:`Task`, :class:`Assignment`) and its enums (:class:`Phase`,
:class:`CommandKind`, :class:`AckResult`...) are here too. Agents are named by
their MAVLink system id (1 byte) once Advertize has told everyone the name; only
Advertize and GSAdvertize carry names (:func:`check_name`). A pool travels as its
CRC-32 digest when unchanged (:func:`pool_digest`).

A message checks what it can when built (a :class:`Pose`'s numbers are finite);
the ranges of the air format are checked by the codec, :mod:`swarm.core.wire.messages`,
which imports this module as ``mt``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import ClassVar

import crcmod.predefined

from swarm.errors import MessageError

PROTOCOL_VERSION = 1
GCS_ID = 255
MAX_NAME = 16
NAME_RE = re.compile(r"^[A-Za-z0-9_-]{1,16}$")
REASON_MAX = 96  # a CommandAck's reason, bytes of UTF-8 (the frame holds 128)
NOTICE_MAX = 64  # an AgentNotice's text, bytes of UTF-8 (an autopilot's STATUSTEXT holds 50)
#: Advertize flag: a size byte follows (only agents with a size cap send it)
ADV_SIZE = 0x04
#: Advertize flag: the 16-bit tag of a swarm name follows (only named agents send it)
ADV_SWARM = 0x08

_crc32 = crcmod.predefined.mkCrcFun("crc-32")


def pool_digest(members: Iterable[int]) -> int:
    """CRC-32 of a pool (order-independent: the sorted ids)."""
    return int(_crc32(bytes(sorted(set(members)))))


def fit_reason(text: str) -> str:
    """``text`` cut to what a CommandAck's reason holds (whole UTF-8 characters)."""
    raw = text.encode("utf-8")[:REASON_MAX]
    return raw.decode("utf-8", errors="ignore")


def check_name(name: str) -> str:
    """Raise MessageError unless ``name`` is a valid agent name (1-16 of A-Z a-z 0-9 _ -),
    usable as a Zenoh key chunk."""
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise MessageError(f"invalid agent name {name!r}: 1 to 16 letters, digits, '_' or '-'")
    return name


def check_id(agent_id: int, *, gcs: bool = False) -> int:
    top = GCS_ID if gcs else 250
    if not isinstance(agent_id, int) or not 1 <= agent_id <= top:
        raise MessageError(f"invalid agent id {agent_id!r}: 1..250 (the GCS is {GCS_ID})")
    return agent_id


# -- value types ----------------------------------------------------------------


@dataclass(frozen=True)
class Pose:
    """A sampled vehicle pose. ``t`` is the sample time in seconds (only t mod 2.56 s
    crosses the air; receivers unwrap it against their clock)."""

    lat: float
    lon: float
    alt: float  # metres AMSL
    heading: float = 0.0  # degrees, 0..360
    vn: float = 0.0  # m/s north
    ve: float = 0.0  # m/s east
    t: float = 0.0

    def __post_init__(self) -> None:
        for name in ("lat", "lon", "alt", "heading", "vn", "ve", "t"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise MessageError(f"pose {name}={v!r} is not a finite number")
        if not -90 <= self.lat <= 90 or not -180 <= self.lon <= 180:
            raise MessageError(f"pose lat/lon {self.lat}, {self.lon} out of range")
        if not -1000 <= self.alt <= 5553.5:
            raise MessageError(f"pose alt {self.alt} m outside -1000..5553.5 m AMSL")


class Side(IntEnum):
    LEFT = -1
    RIGHT = 1


@dataclass(frozen=True)
class Assignment:
    """Formation slot of one member: follow ``follows`` on ``side``."""

    member: int
    follows: int
    side: Side


class TaskKind(IntEnum):
    NONE = 0
    FOLLOW = 1
    HOLD = 2


@dataclass(frozen=True)
class Task:
    """What the leader asks of the swarm, riding on its Heartbeats."""

    kind: TaskKind = TaskKind.NONE
    heading: float = 0.0  # degrees, FOLLOW: the swarm's heading (the leader's course)
    back_m: float = 10.0
    side_m: float = 5.0
    assignments: tuple[Assignment, ...] = ()
    #: FOLLOW: which follow command this is (mod 256); a member that left the formation
    #: for an individual command rejoins on a new generation
    gen: int = 0
    #: FOLLOW: how fast the swarm heading turns, degrees/s (+: clockwise), so members
    #: turn their slots between Heartbeats; 0.5 deg/s steps, -63.5..63.5
    turn_rate: float = 0.0


class Phase(IntEnum):
    IDLE = 0
    POOLING = 1
    LOCKED = 2
    ELECTING = 3
    LEADER = 4
    MEMBER = 5


class CommandKind(IntEnum):
    """What a Command asks. Every ``alt`` a Command carries is metres above the
    vehicle's home (as MAVLink's GLOBAL_RELATIVE_ALT frame), never AMSL: the agent adds
    its own home, so the station need not know it (:mod:`swarm.core.flight.geofence`)."""

    ARM = 1
    DISARM = 2
    TAKEOFF = 3  # alt: metres above home
    LAND = 4
    RETURN = 5
    FOLLOW = 7  # heading degrees
    STOP = 8
    GOTO = 10  # lat, lon, alt (metres above home)
    WAYPOINT = 11  # lat, lon, alt (above home): append to the route being flown (GOTO replaces it)
    #: an earlier version's GOTO and WAYPOINT, whose altitude was AMSL: decoded (captures
    #: replay) and refused by an agent, never sent. The kinds above home took new numbers
    #: so that an agent of that version drops them (an unknown kind) instead of reading
    #: 20 m above home as 20 m above the sea.
    GOTO_AMSL = 6
    WAYPOINT_AMSL = 9
    #: mode: an autopilot mode's code (swarm.core.wire.codes.mode_code), one of
    #: SELECTABLE_MODES: the operator's mode selector
    SET_MODE = 12


#: the kinds only an earlier version sends (see :class:`CommandKind`)
LEGACY_KINDS = frozenset({CommandKind.GOTO_AMSL, CommandKind.WAYPOINT_AMSL})


class AckResult(IntEnum):
    ACCEPTED = 0
    REJECTED = 1
    UNKNOWN_AGENT = 2
    NOT_CONNECTED = 3
    NO_LEADER = 4
    BAD_ARGUMENT = 5
    FAILED = 6
    IN_PROGRESS = 7


class NoticeSource(IntEnum):
    """Who an :class:`AgentNotice` speaks for."""

    AUTOPILOT = 0  # a STATUSTEXT of the agent's flight controller
    AGENT = 1  # the agent's own event (took off, arrived, holding...)


class PoolStatus(IntEnum):
    SUCCESS = 0
    ALREADY_IN_POOL = 1
    FULL = 2  # a capped pool or swarm refuses the asker (never sent without a cap)


# -- messages -------------------------------------------------------------------


@dataclass(frozen=True)
class Message:
    TYPE: ClassVar[int] = 0


@dataclass(frozen=True)
class Advertize(Message):
    """An agent announces itself on ``swarm/advertize``."""

    TYPE: ClassVar[int] = 1
    sender: int
    name: str
    flags: int = 0  # bit 0: has a flight controller
    #: a capped agent's pool or swarm size (1..250), sent only by agents with a size cap
    #: (:mod:`swarm.core.election.caps`); flag ADV_SIZE says it follows. 0: not sent
    size: int = 0
    #: the tag of the agent's swarm name (1..65535, :func:`swarm_tag`), sent only by agents
    #: given a swarm name; flag ADV_SWARM says it follows. 0: not sent
    swarm: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.size, int) and 0 <= self.size <= 250):
            raise MessageError(f"advertised size {self.size!r} outside 0..250")
        if bool(self.flags & ADV_SIZE) != bool(self.size):
            raise MessageError("an Advertize carries a size exactly when its flag ADV_SIZE is set")
        if not (isinstance(self.swarm, int) and 0 <= self.swarm <= 0xFFFF):
            raise MessageError(f"swarm tag {self.swarm!r} outside 0..65535")
        if bool(self.flags & ADV_SWARM) != bool(self.swarm):
            raise MessageError("an Advertize carries a swarm tag exactly when its flag ADV_SWARM is set")


def swarm_tag(name: str) -> int:
    """A swarm name's 16-bit tag (1..65535): the low bits of its CRC-32, 0 taken as 1.
    Two names share a tag once in 65,535: agents of different names then pool together."""
    check_name(name)
    return (int(_crc32(name.encode("ascii"))) & 0xFFFF) or 1


@dataclass(frozen=True)
class GSAdvertize(Message):
    """On ``swarm/GSAdvertize``: an agent announces itself to ground stations (the
    paper, section 3), and a station (id 255) announces its name, so that agents can
    answer it."""

    TYPE: ClassVar[int] = 2
    sender: int
    name: str


@dataclass(frozen=True)
class Heartbeat(Message):
    """Leader -> members: I lead ``members``; the current task rides along."""

    TYPE: ClassVar[int] = 3
    sender: int
    epoch: int
    seq: int
    members: frozenset[int] = frozenset()
    task: Task = field(default_factory=Task)


@dataclass(frozen=True)
class HeartbeatAck(Message):
    """Member -> leader: alive, with its pose (18 bytes; battery travels in Telemetry)."""

    TYPE: ClassVar[int] = 4
    sender: int
    seq: int
    pose: Pose


@dataclass(frozen=True)
class StartPool(Message):
    TYPE: ClassVar[int] = 5
    sender: int


@dataclass(frozen=True)
class StartPoolAck(Message):
    TYPE: ClassVar[int] = 6
    sender: int
    status: PoolStatus
    locked: bool = False
    members: frozenset[int] = frozenset()


@dataclass(frozen=True)
class SyncPool(Message):
    """Pool state by digest; ``members`` only when the sender chooses to send them."""

    TYPE: ClassVar[int] = 7
    sender: int
    digest: int
    locked: bool = False
    members: frozenset[int] | None = None


@dataclass(frozen=True)
class SyncPoolAck(Message):
    """Same digest, or Different with the receiver's members and lock state."""

    TYPE: ClassVar[int] = 8
    sender: int
    same: bool
    locked: bool = False
    members: frozenset[int] = frozenset()


@dataclass(frozen=True)
class Selection(Message):
    """A vote: ``candidate`` with ``weight`` in election ``epoch``."""

    TYPE: ClassVar[int] = 9
    sender: int
    candidate: int
    weight: int
    epoch: int = 0


@dataclass(frozen=True)
class PoseReport(Message):
    """The pose stream ``swarm/<name>/pose`` (the key names the sender)."""

    TYPE: ClassVar[int] = 10
    pose: Pose


@dataclass(frozen=True)
class AgentState(Message):
    """An agent's protocol state on ``swarm/<name>/state``."""

    TYPE: ClassVar[int] = 11
    sender: int
    phase: Phase
    leader: int = 0  # 0: none
    candidate: int = 0
    weight: int = 0
    epoch: int = 0
    locked: bool = False
    pool: frozenset[int] = frozenset()
    members: frozenset[int] = frozenset()


@dataclass(frozen=True)
class GSConnect(Message):
    """Ground station -> agent: connection request (also re-sent to keep it)."""

    TYPE: ClassVar[int] = 12
    sender: int
    seq: int


@dataclass(frozen=True)
class GSConnectAck(Message):
    TYPE: ClassVar[int] = 13
    sender: int
    seq: int
    hb_interval_ms: int = 1000


@dataclass(frozen=True)
class Telemetry(Message):
    """Agent -> ground station at the connection's heartbeat rate: doubles as the
    agent's heartbeat on that connection."""

    TYPE: ClassVar[int] = 14
    sender: int
    pose: Pose
    mode: int = 0
    flags: int = 0  # bit0 armed, bit1 airborne, bit2 fc link ok, bit3 holding, bit4 control lost
    phase: Phase = Phase.IDLE
    leader: int = 0
    battery: int = 255
    rssi: int = 0
    remrssi: int = 0
    groundspeed: float = 0.0  # m/s
    # the detail block (an agent before it sends none; None: unknown)
    rel_alt: float | None = None  # metres above the autopilot's home, -3276.7..3276.7
    climb: float | None = None  # m/s up, -31.75..31.75
    gps_fix: int | None = None  # GPS_FIX_TYPE 0..8
    satellites: int | None = None  # 0..254
    home_dist: float | None = None  # metres from the autopilot's home, 0..65534

    @property
    def has_detail(self) -> bool:
        detail = (self.rel_alt, self.climb, self.gps_fix, self.satellites, self.home_dist)
        return any(v is not None for v in detail)


@dataclass(frozen=True)
class GSHeartbeat(Message):
    TYPE: ClassVar[int] = 15
    sender: int
    seq: int


@dataclass(frozen=True)
class Command(Message):
    """A command to one agent (``target``) or to the swarm (``target`` 0)."""

    TYPE: ClassVar[int] = 16
    sender: int
    seq: int
    target: int
    kind: CommandKind
    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0
    heading: float = 0.0
    mode: int = 0  # SET_MODE: the mode's code


@dataclass(frozen=True)
class CommandAck(Message):
    TYPE: ClassVar[int] = 17
    sender: int
    seq: int
    result: AckResult
    reason: str = ""


@dataclass(frozen=True)
class NameConflict(Message):
    """Sent to both agents when two use the same name or the same id."""

    TYPE: ClassVar[int] = 18
    sender: int
    name: str
    other_id: int


@dataclass(frozen=True)
class AgentNotice(Message):
    """Agent -> ground station: one line for the operator, rate-limited by the agent
    (:mod:`swarm.core.agent.notices`). ``severity`` is MAVLink's (0 emergency .. 7 debug);
    ``repeats`` how many more times the same line came since it was last sent."""

    TYPE: ClassVar[int] = 19
    sender: int
    source: NoticeSource
    severity: int
    text: str
    repeats: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.severity, int) and 0 <= self.severity <= 7):
            raise MessageError(f"notice severity {self.severity!r} outside 0..7")
        if not (isinstance(self.repeats, int) and 0 <= self.repeats <= 255):
            raise MessageError(f"notice repeats {self.repeats!r} outside 0..255")
        if not isinstance(self.text, str) or not self.text.isprintable() or not self.text:
            raise MessageError("a notice's text is one non-empty printable line")


__all__ = [
    "ADV_SIZE",
    "ADV_SWARM",
    "GCS_ID",
    "LEGACY_KINDS",
    "MAX_NAME",
    "NAME_RE",
    "NOTICE_MAX",
    "PROTOCOL_VERSION",
    "REASON_MAX",
    "AckResult",
    "Advertize",
    "AgentNotice",
    "AgentState",
    "Assignment",
    "Command",
    "CommandAck",
    "CommandKind",
    "GSAdvertize",
    "GSConnect",
    "GSConnectAck",
    "GSHeartbeat",
    "Heartbeat",
    "HeartbeatAck",
    "Message",
    "NameConflict",
    "NoticeSource",
    "Phase",
    "PoolStatus",
    "Pose",
    "PoseReport",
    "Selection",
    "Side",
    "StartPool",
    "StartPoolAck",
    "SyncPool",
    "SyncPoolAck",
    "Task",
    "TaskKind",
    "Telemetry",
    "check_id",
    "check_name",
    "fit_reason",
    "pool_digest",
    "swarm_tag",
]
