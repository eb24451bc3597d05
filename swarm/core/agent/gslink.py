"""The agent side of the ground-station connection (the paper, section 3), as a pure core.

Theory of operation
-------------------
The protocol, both sides (the station side lives in :mod:`swarm.gcs`):

1. An agent announces itself on ``swarm/GSAdvertize`` (GSAdvertize: its id and
   name) every ``advertize_interval`` while no station is connected, and every
   ``advertize_connected_interval`` once one is (so that a second station, or one
   restarted, finds it).
2. A station announces itself on the same key with its own id (251..255; 255 by
   default) and name, so that agents (and their radio bridges) can address it.
3. A station that hears an agent it is not connected to sends GSConnect (its id,
   a sequence number) to the agent's inbox ``swarm/<agent>``, again every second
   until answered. The agent answers GSConnectAck (same sequence number, the
   heartbeat interval it will keep) to the station's inbox and is connected.
4. While connected the agent sends Telemetry to the station every
   ``hb_interval``: Telemetry is the agent's heartbeat on the connection. The
   station drops the agent after ``3 * hb_interval`` (at least 2 s) without one and
   reconnects when it hears the agent's GSAdvertize again.
5. The station sends GSHeartbeat to each connected agent every second; an agent
   that hears neither GSHeartbeat nor GSConnect from a station for
   ``station_timeout`` drops it (stops its Telemetry, advertises faster again).

Commands (Command / CommandAck) travel on the same inboxes; the agent runtime
answers them (:class:`CommandLog` keeps the answers so that a retried command,
same station, sequence number and content, gets the same answer and is not run
twice; a swarm command's "not the leader" is not kept, see :func:`remembered`).
A command carried out on the vehicle (arm, take off, land...) is answered only
with what the vehicle did (:func:`answer_command`, :meth:`CommandLog.finish`):
ACCEPTED once the flight controller's call returned, or a refusal with the
autopilot's reason (:func:`short_reason`); until then the log holds IN_PROGRESS,
which is what a retry of that command is answered with (it starts nothing).

Telemetry is also how a station learns of the agent's vehicle link: FLAG_FC_OK is
set while the flight controller is heard, and while it is not the mode is sent as
0 (unknown) rather than the last one heard.

:class:`GsLink` does no I/O and reads no clock: ``handle(msg, now)`` and
``tick(now, telemetry)`` return :class:`GsOut` (a destination id and a message);
the runtime knows which name an id has (from GSAdvertize).

Telemetry's ``mode`` is a code: the index of the mode name in :data:`MODES`
(0: unknown; names not in the table are sent as 0).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

from swarm.core.wire.codes import is_station, short_reason
from swarm.core.wire.message_types import (
    AckResult,
    Command,
    CommandAck,
    GSAdvertize,
    GSConnect,
    GSConnectAck,
    GSHeartbeat,
    Message,
    Telemetry,
)

T = TypeVar("T")


@dataclass(frozen=True)
class GsConfig:
    advertize_interval: float = 1.0
    advertize_connected_interval: float = 10.0
    #: Telemetry period while connected: 1 Hz; positions reach a station at the pose
    #: stream's rate anyway, and the air is shared with the formation
    hb_interval: float = 1.0
    station_timeout: float = 5.0

    def __post_init__(self) -> None:
        for k in ("advertize_interval", "advertize_connected_interval", "hb_interval", "station_timeout"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and 0 < v < 3600):
                raise ValueError(f"{k} {v!r}: a positive number of seconds")


@dataclass(frozen=True)
class GsOut:
    to: int  # a station id, or 0 for the swarm/GSAdvertize broadcast
    msg: Message


@dataclass
class _Station:
    name: str
    connected: bool = False
    connected_at: float = 0.0
    last_heard: float = 0.0
    next_telemetry: float = 0.0


@dataclass
class GsCounters:
    connects: int = 0
    drops: int = 0
    unknown_station: int = 0  # GSConnect from a station whose name we have not heard
    ignored: int = 0
    telemetry_sent: int = 0


@dataclass
class GsLink:
    """One agent's connections to ground stations. See the module docstring."""

    me: int
    name: str
    config: GsConfig = field(default_factory=GsConfig)
    stations: dict[int, _Station] = field(default_factory=dict)
    counters: GsCounters = field(default_factory=GsCounters)
    _next_advertize: float = 0.0

    @property
    def connected(self) -> list[int]:
        return sorted(i for i, s in self.stations.items() if s.connected)

    def station_name(self, station: int) -> str | None:
        s = self.stations.get(station)
        return s.name if s is not None else None

    def handle(self, msg: Message, now: float) -> list[GsOut]:
        sender = getattr(msg, "sender", 0)
        if isinstance(msg, GSAdvertize):
            if is_station(sender):
                st = self.stations.get(sender)
                if st is None:
                    self.stations[sender] = _Station(msg.name)
                else:
                    st.name = msg.name
            return []  # another agent's announcement: not for us
        if not is_station(sender):
            self.counters.ignored += 1
            return []
        st = self.stations.get(sender)
        if isinstance(msg, GSConnect):
            if st is None:
                self.counters.unknown_station += 1  # no name to answer to yet
                return []
            if not st.connected:
                st.connected = True
                st.connected_at = now
                st.next_telemetry = now
                self.counters.connects += 1
            st.last_heard = now
            ms = max(1, min(0xFFFF, round(self.config.hb_interval * 1000)))
            return [GsOut(sender, GSConnectAck(self.me, msg.seq, ms))]
        if isinstance(msg, GSHeartbeat):
            if st is not None and st.connected:
                st.last_heard = now
            else:
                self.counters.ignored += 1
            return []
        self.counters.ignored += 1
        return []

    def tick(self, now: float, telemetry: Callable[[], Telemetry | None]) -> list[GsOut]:
        out: list[GsOut] = []
        for st in self.stations.values():
            if st.connected and now - st.last_heard > self.config.station_timeout:
                st.connected = False
                self.counters.drops += 1
                self._next_advertize = now  # be found again quickly
        if now + 1e-9 >= self._next_advertize:
            out.append(GsOut(0, GSAdvertize(self.me, self.name)))
            period = (
                self.config.advertize_connected_interval if self.connected else self.config.advertize_interval
            )
            self._next_advertize = now + period
        due = [
            (sid, st)
            for sid, st in sorted(self.stations.items())
            if st.connected and now + 1e-9 >= st.next_telemetry
        ]
        if due:
            tm = telemetry()
            for sid, st in due:
                st.next_telemetry = now + self.config.hb_interval
                if tm is not None:
                    out.append(GsOut(sid, tm))
                    self.counters.telemetry_sent += 1
        return out

    def next_deadline(self) -> float:
        times = [self._next_advertize]
        for st in self.stations.values():
            if st.connected:
                times += [st.next_telemetry, st.last_heard + self.config.station_timeout]
        return min(times)


#: a new answer is sent again this many seconds later (see :class:`CommandLog`)
ACK_REPEATS = (0.5, 1.5)


def remembered(cmd: Command, ack: CommandAck) -> bool:
    """Whether the agent keeps ``ack`` as *the* answer to ``cmd``.

    Every answer is kept except a swarm command's "not the leader" (REJECTED) and
    "no leader" (NO_LEADER): those say "not here, not now", act on nothing, and the
    station re-sends the same command (same seq) to whoever leads when it retries,
    which may be this agent once an election made it the leader."""
    return not (cmd.target == 0 and ack.result in (AckResult.REJECTED, AckResult.NO_LEADER))


class CommandLog:
    """Answers already given, by (station, sequence number), with the command they
    answered: a retried command (same station, seq *and* content) gets the same
    answer and is not run twice. A command with a known seq but other content is
    new (a restarted station counting again) and replaces the old answer. Keeps the
    last ``size`` answers.

    A command the vehicle carries out is *open* (:meth:`begin`) until its vehicle
    calls return: a retry that arrives while a take-off is still climbing finds its
    IN_PROGRESS answer here and starts nothing; :meth:`finish` puts the vehicle's
    result in its place.

    A final answer is sent again ``repeats`` seconds later (0.5 and 1.5 s): an
    answer lost on the way is what makes a station report a command it cannot prove
    carried out, and at 20% loss the station's own retries alone left about one
    command in 500 carried out but unanswered. :meth:`due` gives the repeats. An
    IN_PROGRESS answer is not repeated: it goes only to a retry.
    """

    def __init__(self, size: int = 256, repeats: tuple[float, ...] = ACK_REPEATS) -> None:
        self.size = size
        self.repeats = repeats
        self._acks: OrderedDict[tuple[int, int], tuple[Command, CommandAck]] = OrderedDict()
        self._again: list[tuple[float, int, CommandAck]] = []  # (when, station, answer)

    def seen(self, cmd: Command) -> CommandAck | None:
        """The answer already given to this very command, or None."""
        entry = self._acks.get((cmd.sender, cmd.seq))
        if entry is None or entry[0] != cmd:
            return None
        return entry[1]

    def record(self, cmd: Command, ack: CommandAck, now: float = 0.0) -> bool:
        """Keep ``ack`` for ``cmd`` if :func:`remembered` says so (and send it again at
        ``now`` + each of ``repeats``); returns whether it did."""
        if not remembered(cmd, ack):
            return False
        self._again += [(now + d, cmd.sender, ack) for d in self.repeats]
        self._again.sort(key=lambda x: x[0])
        self._keep(cmd, ack)
        return True

    def begin(self, cmd: Command, ack: CommandAck) -> None:
        """``cmd`` is being carried out: ``ack`` (IN_PROGRESS) answers its retries."""
        self._keep(cmd, ack)

    def finish(self, cmd: Command, ack: CommandAck, now: float) -> bool:
        """The vehicle's result for an open command: kept in place of the IN_PROGRESS
        answer and repeated like any new answer. Returns whether to send it: not when
        the station has since reused the seq for another command (an answer with that
        seq would be taken for the new command's)."""
        entry = self._acks.get((cmd.sender, cmd.seq))
        if entry is not None and entry[0] != cmd:
            return False
        return self.record(cmd, ack, now)

    def _keep(self, cmd: Command, ack: CommandAck) -> None:
        key = (cmd.sender, cmd.seq)
        self._acks[key] = (cmd, ack)
        self._acks.move_to_end(key)
        while len(self._acks) > self.size:
            self._acks.popitem(last=False)

    def due(self, now: float) -> list[tuple[int, CommandAck]]:
        """The answers to send again now: (station, answer)."""
        n = 0
        while n < len(self._again) and self._again[n][0] <= now + 1e-9:
            n += 1
        out, self._again = self._again[:n], self._again[n:]
        return [(st, ack) for _, st, ack in out]

    def next_deadline(self) -> float | None:
        return self._again[0][0] if self._again else None


def answer_command(
    log: CommandLog,
    cmd: Command,
    me: int,
    has_fc: bool,
    decide: Callable[[Command], tuple[AckResult, str, list[T]]],
    now: float = 0.0,
) -> tuple[CommandAck, list[T], bool]:
    """The agent's answer to ``cmd``: (the CommandAck, what to start, whether it is a
    repeat answered from ``log``). ``decide`` (the pilot) is asked only for a command
    not answered before and addressed to this agent (``target`` ``me``, or 0 for the
    swarm); a repeat starts nothing. Every answer goes through ``log``.

    A command ``decide`` accepts *with* vehicle calls is not answered yet: the answer
    is IN_PROGRESS (with ``decide``'s reason, what is being done), kept open in
    ``log`` for retries, and the caller sends the vehicle's result when the calls
    return (:meth:`CommandLog.finish`)."""
    ack = log.seen(cmd)
    if ack is not None:
        return ack, [], True
    calls: list[T] = []
    if cmd.target not in (0, me):
        result, why = AckResult.UNKNOWN_AGENT, f"this is agent {me}, not {cmd.target}"
    elif not has_fc and cmd.target != 0:
        result, why = AckResult.FAILED, "no flight controller on this agent"
    else:
        result, why, calls = decide(cmd)
    if result == AckResult.ACCEPTED and calls:
        ack = CommandAck(me, cmd.seq, AckResult.IN_PROGRESS, short_reason(why or "on the flight controller"))
        log.begin(cmd, ack)
        return ack, calls, False
    ack = CommandAck(me, cmd.seq, result, short_reason(why))
    log.record(cmd, ack, now)
    return ack, calls, False


__all__ = [
    "ACK_REPEATS",
    "CommandLog",
    "GsConfig",
    "GsCounters",
    "GsLink",
    "GsOut",
    "answer_command",
    "remembered",
]
