"""What a radio's output holds for its host: the next frame an agent must see on time.

Theory of operation
-------------------
In the simulator a radio's serial output reaches its host byte by byte at the serial
rate, and the host's MAVLink parser yields a frame when its last byte has arrived.
Most of those frames change nothing for the agent behind the radio: on a multipoint
channel every radio hears every P2P frame, and the agent drops the ones addressed to
others. So the simulator need not wake for them: it wakes when the first frame the
agent must handle has arrived, and feeds the parser everything that has arrived by
then (the frames it skipped included). The core sees the same messages at the same
virtual times as when it is woken for every frame.

:func:`frames_in` walks a stream as the parser would (it skips bytes that are not a
start byte, and one byte on a frame whose CRC fails; a frame whose CRC checks is
added to the ``trusted`` set the simulator's parsers share, as the parser would add
it) and gives each frame the offset of the byte that makes the parser yield it;
:func:`due_end` finds the first frame an agent wants among them. Both are pure.

:class:`HostStreams` is the simulator's side of it: per radio, when its host next
gets a frame it handles (``due``, from the air model's closed-form serial clock
:func:`radios.air.serial.drain_time`), the steps that serve those hosts
(:meth:`HostStreams.serve_due`), and the air's own events between two steps, run at
their own times (:meth:`HostStreams.run_air`): only an event that gives a host
output can bring the next step forward. Every receiver of a broadcast holds the same
stream: it is walked once (a cache keyed by the bytes).

:class:`HostStreams` names :class:`~swarm.sim.simulate.Sim` in its annotations only
(an import under ``TYPE_CHECKING``): the simulator makes its host streams and hands
itself to them, so the two modules name each other, and nothing of either runs at
import time.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from radios.air.serial import drain, drain_time
from radios.mavlink import STX_V1, STX_V2, frame_length, frame_problem
from swarm.core.wire.tunnel import Kind

if TYPE_CHECKING:
    from radios.mavlink import FrameParser
    from swarm.sim.simulate import Sim

_INF = float("inf")
_NONE = 1 << 62  # no frame due
_CACHE_MAX = 4096  # walks kept per run (a cache: its size changes no result)
#: (frames as (offset, target, MULTI addressees or None), where the parser then waits)
Walk = tuple[list[tuple[int, int, bytes | None]], int]

#: a host backlog of frames nobody needs is handed over anyway past this many bytes
BACKLOG_CAP = 4096


def frames_in(stream: bytes, trusted: set[bytes]) -> tuple[list[tuple[int, bytes]], int]:
    """``([(offset, frame)...], rest)``: the whole frames the host's parser will yield
    from ``stream``, in order, each with the offset of the byte whose arrival yields it,
    and where the bytes it must keep waiting on begin. A frame after a candidate whose
    CRC failed is yielded only once the whole candidate has arrived (the parser waits
    for it before it can skip it), so its offset may lie past its own end."""
    out: list[tuple[int, bytes]] = []
    off = 0
    high = 0  # the furthest byte a failed candidate needed
    n = len(stream)
    while n - off >= 3:
        b = stream[off]
        if b != STX_V2 and b != STX_V1:
            j = stream.find(STX_V2, off + 1)
            k = stream.find(STX_V1, off + 1)
            if k != -1 and (j == -1 or k < j):
                j = k
            if j == -1:
                return out, n
            off = j
            continue
        flen = frame_length(stream, off)
        assert flen is not None  # a start byte and a whole header
        end = off + flen
        if end > n:
            break
        raw = stream[off:end]
        if raw not in trusted:
            if frame_problem(raw) is not None:
                off += 1  # the parser skips a byte and looks again
                high = max(high, end)
                continue
            trusted.add(raw)
        out.append((max(end, high), raw))
        off = end
    return out, off


def due_end(
    frames: list[tuple[int, bytes]],
    wanted: Callable[[bytes], bool],
    cap: int = BACKLOG_CAP,
) -> int | None:
    """The end offset of the first of ``frames`` (:func:`frames_in`) that ``wanted``
    accepts (or the first one ending at or past ``cap``), or None."""
    for end, raw in frames:
        if end >= cap or wanted(raw):
            return end
    return None


class HostStreams:
    """When each of a simulation's hosts next gets a frame its agent handles, and the
    serving of those hosts (see the module docstring)."""

    def __init__(self, sim: Sim) -> None:
        n = len(sim.air.radios)
        self.sim = sim
        self.air = sim.air
        self.due = [_INF] * n  # when each host next gets a frame it handles
        self.walks: dict[bytes, Walk] = {}
        self.walked = [0] * n  # host stream bytes walked and not the agent's (see serve)
        self.walked_by: list[FrameParser | None] = [None] * n  # ... for this parser
        self.touched: list[int] = []  # radios whose output grew since they were served

    def start(self) -> None:
        """From now on the air model lists the radios whose output grows."""
        self.air.touched = self.touched

    def next_due(self) -> float:
        """When the next host gets a frame it handles (infinite: none waits)."""
        return min(self.due)

    def serve_due(self, t: float) -> None:
        """Each radio whose host gets a frame it handles by ``t`` (``due``), or whose
        output grew, serves its host (:meth:`serve`), in radio order."""
        due = self.due
        touched = self.touched
        if min(due) <= t:
            todo = touched + [i for i, d in enumerate(due) if d <= t]
        elif touched:
            todo = touched[:]
        else:
            return
        touched.clear()
        for i in sorted(set(todo)) if len(todo) > 1 else todo:
            due[i] = self.serve(i, t)

    def serve(self, i: int, t: float, deliver: bool = True) -> float:
        """Radio ``i``'s output to its host at ``t``: once the first frame its agent
        handles has arrived (:meth:`walk`), what has arrived goes to the parser and the
        core (``Sim.deliver``). Returns when the next such frame will have arrived
        (infinite if none waits), from the closed-form serial clock, so the answer does
        not depend on when it is asked. Without ``deliver`` a frame already complete is
        left for a step at ``t``."""
        r = self.air.radios[i]
        ob = r.outbuf
        if ob:
            drain(r, t)
        parser = self.sim.parsers[i]
        while True:
            hr = r.host_ready
            if not ob and not hr:
                return _INF
            pend = parser.held
            head = len(pend) + len(hr)
            # the stream: the parser's bytes, those not yet fed, then the radio's output;
            # frames before ``seen`` were walked and are not the agent's: walk on from there
            seen = self.walked[i] if self.walked_by[i] is parser else 0
            if seen >= head:
                stream = bytes(ob[seen - head :])
            else:
                stream = bytes((pend + hr)[seen:] + ob)
            walk = self.walks.get(stream)
            if walk is None:
                walk = self.walk(stream)
            me = i + 1
            end = _NONE
            for fend, target, ids in walk[0]:  # the first frame agent ``me`` handles
                if ((target == 0 or target == me) and (ids is None or me in ids)) or fend >= BACKLOG_CAP:
                    end = seen + fend
                    break
            if end == _NONE:
                self.walked[i] = seen + walk[1]
                self.walked_by[i] = parser
                return _INF
            if end > head:
                return drain_time(r, end - head) + 1e-9
            if not deliver:
                return t
            if not hr:
                return _INF  # never loop: the walk mirrors the parser (tests/test_sim_events.py)
            self.sim.deliver(i, t)
            self.walked[i] = 0

    def walk(self, stream: bytes) -> Walk:
        """The frames a host's parser will yield from ``stream`` and where it then waits
        (:func:`frames_in`), each frame as ``(offset, target,
        the addressees of a MULTI frame or None)``; target -1: no swarm message. Every
        receiver of a broadcast holds the same stream: it is walked once."""
        frames, rest = frames_in(stream, self.sim.trusted)
        out: list[tuple[int, int, bytes | None]] = []
        for end, raw in frames:
            tun = self.sim.tunnel_of(raw)
            if tun is None:
                out.append((end, -1, None))
            else:
                out.append((end, tun[1], tun[2] if tun[0] == Kind.MULTI else None))
        if len(self.walks) > _CACHE_MAX:
            self.walks.clear()
        walk = self.walks[stream] = (out, rest)
        return walk

    def run_air(self, t: float, nxt: float) -> float:
        """Run the air's events after ``t`` and before ``nxt``, each at its own time;
        returns ``nxt``, or earlier when an event gave a host output that completes a
        frame before it."""
        air = self.air
        ev = air.queue
        thr = t + 1e-9
        while ev and ev[0][0] < nxt:
            te = ev[0][0]
            if te <= thr:
                break  # left for the next step's advance (the old loop's order)
            air.advance(te)
            touched = self.touched
            if touched:
                todo = sorted(set(touched)) if len(touched) > 1 else touched[:]
                touched.clear()
                due = self.due
                for i in todo:
                    d = self.serve(i, te, deliver=False)
                    due[i] = d
                    if d < nxt:
                        nxt = d
        return nxt


__all__ = ["BACKLOG_CAP", "HostStreams", "Walk", "due_end", "frames_in"]
