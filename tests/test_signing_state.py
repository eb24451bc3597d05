"""The signing clock kept across restarts (radios.signing_state, radios.statefile): the
start reference, the verifier's rule on it, the saving policy, and hostile or broken
state files. The wall clock is monkeypatched (``time.time``: what every signer and the
keeper read), the state folders are the tests' own."""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from radios.mavlink import FrameBuilder, FrameParser, SigningClock
from radios.signing import Verifier, key_from_passphrase
from radios.signing_state import (
    FALLBACK_TICKS,
    PERIOD_S,
    ClockKeeper,
    Saved,
    parse,
    start_reference,
    wall_ticks,
)
from radios.statefile import read_state, write_atomic

KEY = key_from_passphrase("swarm key")
T0 = 1_790_000_000.0  # 2026-09
S = 100_000  # ticks a second


class WallClock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def wall(monkeypatch: pytest.MonkeyPatch) -> Iterator[WallClock]:
    clock = WallClock(T0)
    monkeypatch.setattr(time, "time", clock)
    yield clock


def parse_one(raw: bytes):  # type: ignore[no-untyped-def]
    frames = FrameParser().feed(raw)
    assert len(frames) == 1
    return frames[0]


def node(path: Path) -> tuple[ClockKeeper, Verifier, FrameBuilder]:
    """A node as the bridge makes one: a keeper's clock shared by its verifier and builder."""
    keeper = ClockKeeper(path)
    clock = keeper.open()
    return keeper, Verifier(KEY, clock), FrameBuilder(1, 191, signing_key=KEY, clock=clock)


# -- the start reference ------------------------------------------------------------------


def test_the_start_reference() -> None:
    now = 10_000 * S
    assert start_reference(None, now) == now  # a first start: the wall clock
    # the wall clock went forward: the time the last run reached, carried forward ...
    assert start_reference(Saved(mark=now - 50 * S, wall=now - 50 * S), now) == now
    # ... and the swarm's time with it when it was ahead of this node's clock
    assert start_reference(Saved(mark=now - 50 * S + 7 * S, wall=now - 50 * S), now) == now + 7 * S
    # the wall clock went back (a Pi without a real-time clock): the mark, and the most it
    # could have moved since its last save
    booted = 1000 * S
    assert start_reference(Saved(mark=now, wall=now), booted) == now + FALLBACK_TICKS


def test_a_restarted_member_with_a_clock_behind_refuses_what_was_recorded_before(
    wall: WallClock, tmp_path: Path
) -> None:
    """The persisted mark's own case: the member's clock is 40 s behind the swarm's (it had
    taken the swarm's time from its frames); after its restart its wall clock alone would
    take a dead leader's recording of the last 40 s for live frames. The mark carries the
    swarm's time across the restart."""
    leader = FrameBuilder(2, 191, signing_key=KEY)
    recorded = [parse_one(leader.heartbeat()) for _ in range(3)]  # the swarm's time: T0
    wall.t = T0 - 40.0  # the member's own clock
    keeper, member, _b = node(tmp_path / "m.json")
    assert all(member.check(f) for f in recorded)  # live: it follows the swarm's time
    keeper.close()
    wall.t += 5.0  # the leader died; the member restarts 5 s later (by its clock)
    _k2, restarted, _b2 = node(tmp_path / "m.json")
    assert [restarted.check(f) for f in recorded] == [False] * 3
    wall.t = T0 - 40.0 + 5.0  # without the kept mark (the same wall clock): taken
    assert Verifier(KEY, SigningClock(start=wall_ticks())).check(recorded[0])


def test_what_was_accepted_after_the_last_save_is_refused_after_a_crash(
    wall: WallClock, tmp_path: Path
) -> None:
    keeper, member, _b = node(tmp_path / "m.json")
    leader = FrameBuilder(2, 191, signing_key=KEY)
    heard = []
    for _ in range(8):  # 8 s of a live leader, the keeper saving as it goes ...
        wall.t += 1.0
        f = parse_one(leader.heartbeat())
        assert member.check(f)
        heard.append(f)
        if keeper.due(wall_ticks()):
            keeper.save()
    # ... then kill -9 (no save at a stop) and a start 2 s later
    wall.t += 2.0
    _k2, restarted, _b2 = node(tmp_path / "m.json")
    assert not any(restarted.check(f) for f in heard)


def test_a_pi_rebooted_with_an_old_clock_refuses_what_it_had_heard(wall: WallClock, tmp_path: Path) -> None:
    keeper, member, _b = node(tmp_path / "m.json")
    leader = FrameBuilder(2, 191, signing_key=KEY)
    heard = [parse_one(leader.heartbeat()) for _ in range(3)]
    assert all(member.check(f) for f in heard)
    keeper.close()
    wall.t = 1_700_000_000.0  # 2023: a fake-hwclock's idea of the time at boot
    _keeper2, restarted, builder = node(tmp_path / "m.json")
    assert not any(restarted.check(f) for f in heard)
    # its own frames start after everything the last run saw: its peers hear them
    peer = Verifier(KEY, SigningClock(start=int((T0 - 1.0 - 1_420_070_400) * S)))
    wall.t = T0
    assert peer.check(parse_one(builder.heartbeat()))


def test_a_lagging_peer_is_heard_once_it_has_heard_us_and_two_restarts_do_not_lock(
    wall: WallClock, tmp_path: Path
) -> None:
    """b's clock is 3 s behind a's. Both restart at once: a refuses b's frames (stamped
    before a's start) until b has heard one of a's, then b stamps in a's time."""
    wall.t = T0
    _ka, va, ba = node(tmp_path / "a.json")
    wall.t = T0 - 3.0
    _kb, vb, bb = node(tmp_path / "b.json")
    wall.t = T0 + 0.5  # a few frames each, half a second later by a's clock
    from_a = parse_one(ba.heartbeat())
    wall.t = T0 - 2.5
    first_b = parse_one(bb.heartbeat())
    assert not va.check(first_b)  # stamped before a started
    assert vb.check(from_a)  # a's start is later than b's: b hears a ...
    then_b = parse_one(bb.heartbeat())  # ... and stamps in a's time from then on
    wall.t = T0 + 0.6
    assert va.check(then_b)
    assert va.check(parse_one(bb.heartbeat())) and vb.check(parse_one(ba.heartbeat()))


# -- saving -----------------------------------------------------------------------------------


def test_saved_at_start_every_period_while_it_moves_on_gain_and_at_stop(
    wall: WallClock, tmp_path: Path
) -> None:
    keeper, verifier, builder = node(tmp_path / "n.json")
    assert keeper.saves == 1  # at start, before anything is signed
    saves = []
    for second in range(1, 61):  # a minute of the node's own frames, checked every second
        wall.t = T0 + second
        builder.heartbeat()
        if keeper.due(wall_ticks()):
            keeper.save()
            saves.append(second)
    assert saves == [int(PERIOD_S) * k for k in range(1, 7)], saves  # 6 in a minute, not 60
    # a peer ahead of us by 2 s: news the extrapolation misses, saved at the next look
    wall.t += 0.5
    ahead = FrameBuilder(5, 191, signing_key=KEY)
    wall.t += 2.0
    f = parse_one(ahead.heartbeat())
    wall.t -= 2.0
    assert verifier.check(f)
    assert keeper.due(wall_ticks())
    keeper.save()
    assert not keeper.due(wall_ticks())
    keeper.close()
    assert keeper.saves == 9
    saved = read_state(tmp_path / "n.json", 4096)
    assert saved["mark"] >= int.from_bytes(f.raw[-12:-6], "little")
    assert oct(os.stat(tmp_path / "n.json").st_mode & 0o777) == "0o600"


def test_the_keeper_thread_saves_and_close_saves_once_more(tmp_path: Path) -> None:
    keeper = ClockKeeper(tmp_path / "n.json")
    clock = keeper.open()
    keeper.start()
    clock.observe(clock.mark() + 5 * S)  # a peer 5 s ahead: saved within about a second
    deadline = time.monotonic() + 10.0
    while keeper.saves < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert keeper.saves >= 2
    keeper.close()
    keeper.close()  # safe twice
    assert read_state(tmp_path / "n.json", 4096)["mark"] >= clock.mark()


# -- hostile and broken files -----------------------------------------------------------------


def _hostile(path: Path, what: str) -> None:
    if what == "symlink":
        target = path.with_name("elsewhere.json")
        target.write_text(
            json.dumps({"format": "uav-swarm signing clock", "version": 1, "mark": 1, "wall": 1})
        )
        path.symlink_to(target)
    elif what == "fifo":
        os.mkfifo(path)
    elif what == "folder":
        path.mkdir()
    elif what == "huge":
        path.write_bytes(b" " * 100_000)
    elif what == "garbage":
        path.write_bytes(os.urandom(200))
    elif what == "not an object":
        path.write_text("[1, 2, 3]")
    else:
        value: object = {
            "a string": "12345",
            "a boolean": True,
            "negative": -5,
            "beyond 48 bits": 1 << 48,
            "a float": 1.5e12,
            "2100": (4_102_444_800 - 1_420_070_400) * S,
        }[what]
        path.write_text(
            json.dumps({"format": "uav-swarm signing clock", "version": 1, "mark": value, "wall": 5})
        )


@pytest.mark.parametrize(
    "what",
    [
        "symlink",
        "fifo",
        "folder",
        "huge",
        "garbage",
        "not an object",
        "a string",
        "a boolean",
        "negative",
        "beyond 48 bits",
        "a float",
        "2100",
    ],
)
def test_a_hostile_state_file_is_one_warning_and_the_wall_clock(
    what: str, wall: WallClock, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "n.json"
    _hostile(path, what)
    caplog.set_level(logging.WARNING, "radios.signing_state")
    keeper = ClockKeeper(path)
    clock = keeper.open()  # never raises, never blocks (the FIFO)
    assert clock.start == wall_ticks()
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 + (what == "folder"), warnings  # a folder cannot be replaced either
    assert "ignored" in warnings[0] and "\n" not in warnings[0], warnings
    if what not in ("folder",):  # the next save replaces it with a good file (a link itself, not its target)
        assert not path.is_symlink() and read_state(path, 4096)["mark"] >= clock.start
    if what == "symlink":
        assert json.loads(path.with_name("elsewhere.json").read_text())["mark"] == 1


def test_a_power_cut_mid_write_leaves_the_old_file(
    wall: WallClock, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "n.json"
    keeper = ClockKeeper(path)
    clock = keeper.open()
    before = path.read_bytes()
    real_fsync = os.fsync

    def cut(fd: int) -> None:
        raise OSError(5, "Input/output error")  # the write never reaches the disk

    monkeypatch.setattr(os, "fsync", cut)
    wall.t += 100.0
    clock.issue()
    assert not keeper.save()
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert path.read_bytes() == before and not list(tmp_path.glob(".*.tmp"))
    # a temporary file a cut left behind is neither read nor in the way
    (tmp_path / ".n.json.tmp").write_bytes(b'{"format": "half a fi')
    assert ClockKeeper(path).open().start >= json.loads(before)["mark"]
    assert keeper.save()


def test_a_folder_gone_is_one_warning_and_the_node_goes_on(
    wall: WallClock, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A save that fails (here the folder removed under the node: as a full disk or an SD
    card gone read-only would) is one warning line, retried each second, one line when it
    works again; the clock goes on (the tests run as root: no mode keeps root out)."""
    folder = tmp_path / "state"
    folder.mkdir()
    caplog.set_level(logging.WARNING, "radios.signing_state")
    keeper = ClockKeeper(folder / "n.json")
    clock = keeper.open()
    (folder / "n.json").unlink()
    folder.rmdir()
    wall.t += 1.0
    clock.issue()
    assert not keeper.save()
    for _ in range(3):  # retried at every look
        wall.t += 1.0
        assert keeper.due(wall_ticks()) and not keeper.save()
    folder.mkdir()
    assert keeper.save()
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 2 and "not saved" in msgs[0] and "saved again" in msgs[1], msgs


def test_write_atomic_replaces_and_read_state_refuses_what_is_not_a_state(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    write_atomic(path, b'{"a": 1}')
    write_atomic(path, b'{"a": 2}')
    assert read_state(path, 100) == {"a": 2}
    with pytest.raises(FileNotFoundError):
        read_state(tmp_path / "none.json", 100)
    path.write_bytes(b"\xff\xfe")
    with pytest.raises(ValueError, match="not JSON"):
        read_state(path, 100)
    with pytest.raises(ValueError, match="not a signing clock state"):
        parse({"format": "other"}, 0)
