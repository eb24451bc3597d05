"""The event-driven simulator (issue 15): it wakes only for what can change a core.

The simulator no longer steps for every air event and every frame a radio outputs:
it wakes when the first frame an agent handles has reached its host
(swarm.sim.hoststream). These tests pin what that must not change: the frames the
host's parser yields (the walk mirrors FrameParser on any stream, garbage, bad CRCs
and cut frames included), and what each core receives and when (the same as waking
for every frame). In-process and in virtual time.
"""

from __future__ import annotations

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from radios.mavlink import FrameBuilder, FrameParser
from swarm.sim.hoststream import BACKLOG_CAP, Walk, due_end, frames_in
from swarm.sim.simulate import Scenario, Sim


def _stream(pieces: list[tuple[int, int]], seed: int) -> bytes:
    """Frames of several lengths and senders, garbage, frames with a flipped bit and
    frames cut short, in the order ``pieces`` says."""
    rng = random.Random(seed)
    fbs = [FrameBuilder(s, 191) for s in (1, 2, 3)]
    out = bytearray()
    for what, n in pieces:
        frame = fbs[n % 3].tunnel(rng.randbytes(n % 120), target_system=n % 4)
        if what == 0:
            out += frame
        elif what == 1:
            out += rng.randbytes(1 + n % 7)  # garbage, maybe with start bytes in it
        elif what == 2:
            bad = bytearray(frame)
            bad[rng.randrange(len(bad))] ^= 1 << rng.randrange(8)
            out += bad
        else:
            out += frame[: 1 + n % (len(frame) - 1)]  # cut short
    return bytes(out)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 3), st.integers(0, 255)), max_size=30),
    st.integers(0, 2**32),
    st.integers(0, 40),
)
def test_the_walk_yields_what_the_parser_yields(pieces: list[tuple[int, int]], seed: int, cut: int) -> None:
    """frames_in finds exactly the frames FrameParser yields from the same bytes, and
    a parser fed the stream in two parts at any frame boundary agrees."""
    data = _stream(pieces, seed)
    want = [f.raw for f in FrameParser().feed(data)]
    trusted: set[bytes] = set()
    frames, rest = frames_in(data, trusted)
    assert [raw for _, raw in frames] == want
    assert set(want) <= trusted
    # resuming where the walk stopped finds the rest (the simulator walks on from there)
    more = data + _stream([(0, cut)], seed)
    again, _ = frames_in(more[rest:], set())
    assert [raw for _, raw in frames] + [raw for _, raw in again] == [f.raw for f in FrameParser().feed(more)]


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 255)), max_size=12), st.integers(0, 2**32))
def test_each_frame_is_yielded_when_the_walk_says(pieces: list[tuple[int, int]], seed: int) -> None:
    """Fed one byte at a time, the parser yields each frame on the byte at the offset
    the walk gives it (a frame after a bad candidate waits for the whole candidate):
    the simulator wakes when the frame reaches the host, not before, not after."""
    data = _stream(pieces, seed)
    frames, _ = frames_in(data, set())
    parser = FrameParser()
    yielded: list[tuple[int, bytes]] = []
    for k in range(len(data)):
        yielded += [(k + 1, f.raw) for f in parser.feed(data[k : k + 1])]
    assert yielded == frames


def test_due_end_picks_the_first_wanted_frame_or_the_backlog_cap() -> None:
    fb = FrameBuilder(1, 191)
    a, b, c = (fb.tunnel(bytes([k]) * 20, target_system=k) for k in (1, 2, 3))
    frames, _ = frames_in(a + b + c, set())
    assert due_end(frames, lambda raw: raw == b) == len(a) + len(b)
    assert due_end(frames, lambda raw: False) is None
    assert due_end(frames, lambda raw: False, cap=len(a) + 1) == len(a) + len(b)
    assert BACKLOG_CAP >= 4 * 280  # a few of the largest frames fit before it


class _EveryFrame(Sim):
    """The same run, woken for every frame a radio outputs (nothing skipped)."""

    def __init__(self, sc: Scenario, seed: int) -> None:
        super().__init__(sc, seed)
        walk = self.hosts.walk

        def every(stream: bytes) -> Walk:
            frames, rest = walk(stream)
            return [(end, 0, None) for end, _, _ in frames], rest

        self.hosts.walk = every  # type: ignore[method-assign]


def _trace(sim: Sim) -> tuple[list[tuple[float, int, str]], dict[str, object]]:
    seen: list[tuple[float, int, str]] = []
    handle = sim._on_message  # noqa: SLF001 (white box: every message the simulator hands a core)

    def record(i: int, sender: int, kind: object, msg: object, t: float) -> list[object]:
        seen.append((t, i, repr(msg)))
        return handle(i, sender, kind, msg, t)  # type: ignore[arg-type]

    sim._on_message = record  # type: ignore[assignment,method-assign]  # noqa: SLF001 (white box: every message the simulator hands a core)
    res = sim.run()
    return seen, {"elect_s": res.elect_s, "leader": res.leader, "violations": res.violations}


def test_skipping_frames_nobody_handles_changes_nothing_a_core_sees() -> None:
    """Waking only for the frames an agent handles gives every core the same
    messages at the same virtual times as waking for every frame (faults included)."""
    for sc, seed in (
        (Scenario(agents=8, loss=0.1), 3),
        (Scenario(agents=5, loss=0.05, partitions=["4-9:1,2|3,4,5"], crashes=["leader@14"], duration=30), 1),
    ):
        fast, every = _trace(Sim(sc, seed)), _trace(_EveryFrame(sc, seed))
        assert len(fast[0]) > 300
        assert fast == every
