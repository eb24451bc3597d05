"""MAVLink 2 signing timestamps across restarts, clock steps and late joiners.

The bug these tests pin (issue 11, item 1): the frame builder set the signing timestamp
once and pymavlink added one tick (10 µs) per frame, so a sender's timestamp lagged the
wall clock by its uptime; a verifier that first heard such a stream (a restarted agent,
a late station) called it a replay when the lag passed a minute, and a signed swarm split
for good after a restart. The wall clock is monkeypatched here (``time.time``), so a
minute and a half of uptime costs nothing.
"""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from radios.errors import ConfigError
from radios.mavlink import FrameBuilder, FrameParser, SigningClock
from radios.signing import EPOCH_2015, MAX_SKEW_TICKS, Verifier, key_from_passphrase, load_key, now_ticks

KEY = key_from_passphrase("swarm key")
T0 = 1_790_000_000.0  # 2026-09, a plausible field date


class WallClock:
    """A settable stand-in for ``time.time`` (the wall clock every signer reads)."""

    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def wall(monkeypatch: pytest.MonkeyPatch) -> Iterator[WallClock]:
    clock = WallClock(T0)
    monkeypatch.setattr(time, "time", clock)
    yield clock


def parse(raw: bytes):  # type: ignore[no-untyped-def]
    frames = FrameParser().feed(raw)
    assert len(frames) == 1
    return frames[0]


def stamp(raw: bytes) -> int:
    return int.from_bytes(raw[-12:-6], "little")


def test_timestamp_follows_the_wall_clock_not_the_frame_count(wall: WallClock) -> None:
    b = FrameBuilder(7, 190, signing_key=KEY)
    for _ in range(1000):  # a busy sender: 1000 frames ...
        b.heartbeat()
    wall.t += 90.0  # ... and 90 s of uptime
    ts = stamp(b.heartbeat())
    assert abs(ts - now_ticks(wall)) <= 1000 + 1
    assert ts == pytest.approx((T0 + 90.0 - EPOCH_2015) * 100_000, abs=2000)


def test_a_verifier_started_late_accepts_a_sender_with_uptime(wall: WallClock) -> None:
    """The reported split: a member restarted after 90 s hears the others' streams."""
    sender = FrameBuilder(3, 190, signing_key=KEY)
    sender.heartbeat()
    wall.t += 90.0
    late = Verifier(KEY)  # the restarted member / the late station
    assert late.check(parse(sender.heartbeat()))
    assert late.stats.accepted == 1 and late.stats.replayed == 0


def test_a_restarted_sender_is_accepted_by_a_verifier_that_knew_it(wall: WallClock) -> None:
    v = Verifier(KEY)
    first = FrameBuilder(3, 190, signing_key=KEY)
    for _ in range(5):
        assert v.check(parse(first.heartbeat()))
    wall.t += 90.0  # kill -9, start again
    again = FrameBuilder(3, 190, signing_key=KEY)
    assert v.check(parse(again.heartbeat()))


def test_timestamps_strictly_increase_when_the_clock_steps_back(wall: WallClock) -> None:
    clock = SigningClock()
    b = FrameBuilder(3, 190, signing_key=KEY, clock=clock)
    stamps = [stamp(b.heartbeat()) for _ in range(3)]
    wall.t -= 3600.0  # NTP or GPS steps the clock an hour back
    stamps += [stamp(b.heartbeat()) for _ in range(3)]
    wall.t += 7200.0  # and an hour forward
    stamps += [stamp(b.heartbeat()) for _ in range(3)]
    assert all(a < b for a, b in itertools.pairwise(stamps))
    assert stamps[-1] >= now_ticks(wall)


def test_builders_sharing_a_clock_never_reuse_a_timestamp(wall: WallClock) -> None:
    clock = SigningClock()
    a = FrameBuilder(3, 190, signing_key=KEY, clock=clock)
    b = FrameBuilder(3, 1, signing_key=KEY, clock=clock)
    stamps = [stamp(x.heartbeat()) for _ in range(50) for x in (a, b)]
    assert len(set(stamps)) == len(stamps) and stamps == sorted(stamps)


def test_real_replays_are_still_refused(wall: WallClock) -> None:
    v = Verifier(KEY)
    b = FrameBuilder(3, 190, signing_key=KEY)
    old = parse(b.heartbeat())
    assert v.check(old)
    assert not v.check(old)  # the same frame again
    newer = parse(b.heartbeat())
    assert v.check(newer)
    assert not v.check(old)  # an older frame of a known stream
    assert v.stats.replayed == 2


def test_a_new_stream_more_than_a_minute_old_is_a_replay(wall: WallClock) -> None:
    recorded = parse(FrameBuilder(9, 190, signing_key=KEY).heartbeat())  # captured by an attacker
    wall.t += 61.0
    v = Verifier(KEY)  # a verifier that never heard stream 9
    assert not v.check(recorded)
    assert v.stats.replayed == 1
    wall.t -= 2.0  # within a minute it is indistinguishable from a live stream (the spec's window)
    assert Verifier(KEY).check(recorded)


def test_a_dead_process_stream_replayed_to_a_restarted_verifier_is_refused(wall: WallClock) -> None:
    """The attack the fault bench caught on CI: a neighbour records agent 2 leading; agent 2
    is killed and restarts (a new link id, a new stream); then agent 1 restarts too, so its
    new verifier never heard agent 2's old stream. Replayed within the minute, the old
    stream passed as a new one and agent 1 saw agent 2 lead again. A new stream of a
    system must be newer than anything accepted from that system."""
    old = FrameBuilder(2, 191, signing_key=KEY, link_id=1)
    recorded = [parse(old.heartbeat()) for _ in range(3)]  # what the neighbour captured
    wall.t += 20.0
    successor = FrameBuilder(2, 191, signing_key=KEY, link_id=2)  # agent 2 restarted
    v = Verifier(KEY)  # agent 1 restarted: it never heard stream (2, 191, 1)
    assert v.check(parse(successor.heartbeat()))
    assert [v.check(f) for f in recorded] == [False, False, False]
    assert v.stats.replayed == 3
    # a verifier that got the recording first (before the live stream: the minute's window)
    # takes no more of it once it has heard the live stream
    early = Verifier(KEY)
    assert early.check(recorded[0])
    assert early.check(parse(successor.heartbeat()))
    assert [early.check(f) for f in recorded[1:]] == [False, False]
    # another system's stream as old is not judged by system 2's: its first frame passes
    third = FrameBuilder(3, 191, signing_key=KEY, link_id=1)
    wall.t -= 20.0
    other = parse(third.heartbeat())
    wall.t += 20.0
    assert v.check(other)
    # nor another component of system 2 (the bridge's vehicle-side builder, compid 1)
    wall.t -= 20.0
    vehicle_side = parse(FrameBuilder(2, 1, signing_key=KEY, link_id=1).heartbeat())
    wall.t += 20.0
    assert v.check(vehicle_side)


def test_a_sender_restarted_with_its_clock_behind_is_heard_at_once(wall: WallClock) -> None:
    """A Pi without a real-time clock restarts with its clock 30 s behind where its last run
    ended, 10 minutes after that run began: its frames are older than the last run's last
    ones but newer than its start, so they are no replay of it and are heard at once."""
    v = Verifier(KEY)  # a peer that heard the first run
    wall.t -= 600.0
    first_run = FrameBuilder(4, 191, signing_key=KEY)
    assert v.check(parse(first_run.heartbeat()))
    wall.t += 600.0
    assert v.check(parse(first_run.heartbeat()))
    wall.t -= 30.0  # the restarted machine's clock
    second_run = FrameBuilder(4, 191, signing_key=KEY)
    assert v.check(parse(second_run.heartbeat()))


def test_two_live_senders_with_one_id_are_both_heard(wall: WallClock) -> None:
    """Two stations left at the default id on one net that do not hear each other, b's clock
    2 s behind a's: a's stream began at T0+1, so b's frames stamped before that look like
    an earlier run; from then on each stream began before the other's frames and both are
    heard (the rule on the newest frame of the sender dropped b's frames for good)."""
    v = Verifier(KEY)
    a = FrameBuilder(255, 191, signing_key=KEY, link_id=1)
    wall.t -= 2.0
    b = FrameBuilder(255, 191, signing_key=KEY, link_id=2)
    wall.t += 2.0
    results = []
    for _ in range(10):
        wall.t += 1.0
        results.append(v.check(parse(a.heartbeat())))
        wall.t -= 2.0
        results.append(v.check(parse(b.heartbeat())))
        wall.t += 2.0
    assert results[0::2] == [True] * 10, results  # a
    assert results[1::2] == [False, False] + [True] * 8, results  # b


def test_a_recording_played_back_slowly_ages_out(wall: WallClock) -> None:
    """A dead leader's recording, one frame every 20 s, to a verifier restarted after it
    died: only a stream's first frame was held to the minute, so the recording kept the
    dead leader alive for as long as it lasted. Every frame must be within the minute."""
    old = FrameBuilder(2, 191, signing_key=KEY)
    recorded = [parse(old.heartbeat()) for _ in range(25)]  # 25 frames, a few ms apart
    wall.t += 10.0
    v = Verifier(KEY)
    accepted = []
    for f in recorded:
        accepted.append(v.check(f))
        wall.t += 20.0
    assert accepted == [True] * 3 + [False] * 22, accepted  # ages 10, 30, 50 s; then 70 s...


def test_a_verifier_with_a_slow_clock_adopts_the_swarm_time(wall: WallClock) -> None:
    """A Pi without a real-time clock booted an hour behind: it accepts current streams (they are
    not old) and from then on stamps its own frames with the swarm's time, as the MAVLink signing
    specification asks, so the others accept it too."""
    swarm_sender = FrameBuilder(3, 190, signing_key=KEY)
    frame = parse(swarm_sender.heartbeat())
    wall.t -= 3600.0  # this machine's clock
    clock = SigningClock()
    v = Verifier(KEY, clock=clock)
    mine = FrameBuilder(4, 190, signing_key=KEY, clock=clock)
    behind = parse(mine.heartbeat())
    assert v.check(frame)
    caught_up = parse(mine.heartbeat())
    wall.t += 3600.0
    other = Verifier(KEY)
    assert not other.check(behind)  # an hour old: refused as a new stream
    assert other.check(caught_up)  # after hearing the swarm, current
    assert MAX_SKEW_TICKS == 60 * 100_000


def test_forged_and_unsigned_frames_do_not_move_the_clock(wall: WallClock) -> None:
    clock = SigningClock()
    v = Verifier(KEY, clock=clock)
    wall.t += 10_000.0
    future = parse(FrameBuilder(5, 190, signing_key=key_from_passphrase("intruder")).heartbeat())
    wall.t -= 10_000.0
    assert not v.check(future)
    assert clock.reference() == now_ticks(wall)


def test_default_link_id_differs_between_starts() -> None:
    """A restarted sender opens a new stream (link id), so a clock stepped back by less than a
    minute between the runs cannot make the new run's frames look like replays."""
    ids = {FrameBuilder(3, 190, signing_key=KEY).heartbeat()[-13] for _ in range(40)}
    assert len(ids) > 1
    fixed = FrameBuilder(3, 190, signing_key=KEY, link_id=7).heartbeat()
    assert fixed[-13] == 7


# -- hostile key files -------------------------------------------------------------------


@pytest.mark.parametrize("path", ["/dev/zero", "/dev/urandom", "/"])
def test_a_key_path_that_is_no_regular_file_is_refused_at_once(path: str) -> None:
    """An endless device was read for ever (a hang, then memory); a folder is refused."""
    with pytest.raises(ConfigError, match="not a regular file"):
        load_key(path)


def test_a_fifo_as_key_file_does_not_block(tmp_path: Path) -> None:
    fifo = tmp_path / "key"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="not a regular file"):
        load_key(fifo)  # nobody writes to it: a blocking open would wait for ever


def test_a_huge_key_file_is_refused(tmp_path: Path) -> None:
    big = tmp_path / "key"
    big.write_bytes(b"x" * 100_000)
    with pytest.raises(ConfigError, match="larger than"):
        load_key(big)
