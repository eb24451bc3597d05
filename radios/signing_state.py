"""The signing clock kept across restarts, so nothing recorded before a restart is taken after it.

Theory of operation
-------------------
MAVLink 2 signing refuses a frame that is not newer than the last one of its stream,
but a verifier that restarts forgets every stream: a recording of a sender it never
heard since (a dead leader, recorded from the air less than a minute ago) passed for
a live stream, and the restarted member followed the dead leader. The MAVLink
specification asks that the timestamp be kept across restarts; a node keeps one
number, its clock's *mark* (:meth:`radios.mavlink.SigningClock.mark`: the latest time
it issued or accepted), with the wall clock at which it was saved, in a small file of
its state folder (one per node: ``agent-NAME-ID.signing.json``...).

At start (:meth:`ClockKeeper.open`) the node's *start reference* is
(:func:`start_reference`)::

    R = max(wall now, mark + (wall now - wall at save))    the wall clock went forward
    R = max(wall now, mark + FALLBACK)                     it went back (unknown downtime)
    R = wall now                                           no file, or one not believed

The first line carries the swarm's time across the restart (a node whose clock lags
the swarm's resumes at the swarm's time, not its own) and covers everything accepted
since the last save as long as it was not ahead of that extrapolation (see below). The
second is a Raspberry Pi without a real-time clock booted with an old wall clock: the
mark is what protects it. The clock starts at R (it never issues less) and the verifier
refuses every frame stamped before R (:class:`radios.signing.Verifier`): such a frame
was on the air before this run began, whether the node heard it or not.

Saving (:meth:`ClockKeeper.start`, a thread looking once a second) writes the file
atomically (:func:`radios.statefile.write_atomic`) at start (so a crash right after
still starts the next run later), when the mark has gone more than 0.1 s beyond the
extrapolation of the last save (a peer whose clock is ahead of ours: news the next
start could not work out), at least every :data:`PERIOD_S` while the mark moves (it
does all the time: the node's own frames), and at stop. That is about 6 writes a
minute on an SD card, not 60; the extrapolation makes saving every second unneeded
while the wall clock holds.

What a file may not do: a missing one is a first start (no word); an unreadable,
corrupt or hostile one (a symbolic link, a FIFO, too large, not JSON, wrong types, a
mark beyond the 48-bit field or more than a day ahead of a plausible wall clock) is
one warning line and the start from the wall clock alone; a save that fails (the disk
full, the folder gone read-only) is one warning line, retried each second, and one
line when it works again. Nothing here raises into the bridge.

What is left: a node without a trustworthy clock at start (a Pi without a real-time
clock rebooted while the swarm flew on) cannot know how long it was down, so a
recording made while it was down, after its last save, is still taken until the live
stream of that sender takes over.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from radios.mavlink import SIGNING_EPOCH, SigningClock
from radios.statefile import read_state, write_atomic

log = logging.getLogger(__name__)

FORMAT = "uav-swarm signing clock"
VERSION = 1
FILE_LIMIT = 4096  # bytes: the file is under 100
TICKS_PER_S = 100_000
CHECK_S = 1.0  # the keeper looks this often
PERIOD_S = 10.0  # a moving mark is saved at least this often
GAIN_TICKS = TICKS_PER_S // 10  # 0.1 s beyond the extrapolation: saved at the next look
#: the mark may have moved this far since its last save when the clock went back
FALLBACK_TICKS = int((PERIOD_S + 2 * CHECK_S) * TICKS_PER_S)
MAX_TICKS = (1 << 48) - 1  # the signature's 48-bit timestamp: year 2104
#: a wall clock after this (2026-01-01) is trusted to judge a mark too far ahead of it
PLAUSIBLE_WALL_TICKS = (1_767_225_600 - SIGNING_EPOCH) * TICKS_PER_S
AHEAD_LIMIT_TICKS = 86_400 * TICKS_PER_S  # a day


def wall_ticks() -> int:
    """The wall clock in signing ticks (10 µs since 2015), read now."""
    return int((time.time() - SIGNING_EPOCH) * TICKS_PER_S)


@dataclass(frozen=True)
class Saved:
    """What the file holds: the node's time (its clock's mark, or the wall clock if
    later) and the wall clock, both in ticks, when it was saved."""

    mark: int
    wall: int

    def dump(self) -> bytes:
        return json.dumps(
            {"format": FORMAT, "version": VERSION, "mark": self.mark, "wall": self.wall}
        ).encode()


def _ticks(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= MAX_TICKS:
        raise ValueError("its times are not 48-bit signing timestamps")
    return v


def parse(obj: dict[str, Any], wall_now: int) -> Saved:
    """The :class:`Saved` in a state file's JSON object, if it is believable at
    ``wall_now``. Raises ValueError (one line: why)."""
    if obj.get("format") != FORMAT or obj.get("version") != VERSION:
        raise ValueError("not a signing clock state of this version")
    saved = Saved(_ticks(obj.get("mark")), _ticks(obj.get("wall")))
    ahead = saved.mark - wall_now
    if wall_now >= PLAUSIBLE_WALL_TICKS and ahead > AHEAD_LIMIT_TICKS:
        raise ValueError(f"its time is {ahead / TICKS_PER_S / 86_400:.1f} days ahead of this clock")
    return saved


def start_reference(saved: Saved | None, wall_now: int) -> int:
    """The start reference R (module docstring) for ``saved`` at ``wall_now``."""
    if saved is None:
        return wall_now
    if wall_now >= saved.wall:
        return min(MAX_TICKS, max(wall_now, saved.mark + (wall_now - saved.wall)))
    return min(MAX_TICKS, max(wall_now, saved.mark + FALLBACK_TICKS))


class ClockKeeper:
    """One node's signing clock, started from and saved to ``path`` (module docstring).

    :meth:`open` (once, before any frame is signed or checked) returns the clock;
    :meth:`start` saves it as it goes, :meth:`close` saves it once more and stops.
    """

    def __init__(self, path: str | Path, name: str = "") -> None:
        self.path = Path(path)
        self.name = name or self.path.name
        self.clock = SigningClock()
        self.saves = 0  # files written (for the tests and the figures)
        self.problem = ""  # why the file was not used at start ("" if it was, or there was none)
        self._saved: Saved | None = None
        self._raw_mark = 0  # the clock's mark at the last save
        self._failing = False
        self._opened = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._io = threading.Lock()

    def open(self) -> SigningClock:
        wall_now = wall_ticks()
        saved = None
        try:
            saved = parse(read_state(self.path, FILE_LIMIT), wall_now)
        except FileNotFoundError:
            log.info("signing state %s: none yet (a first start)", self.path)
        except ValueError as exc:
            self.problem = str(exc)
            log.warning(
                "signing state %s ignored (%s): replays are refused from the wall clock's time only",
                self.path,
                exc,
            )
        self.clock = SigningClock(start=start_reference(saved, wall_now))
        self._opened = True
        self.save()
        return self.clock

    def due(self, wall_now: int) -> bool:
        """Whether the mark should be saved now (module docstring)."""
        mark = self.clock.mark()
        s = self._saved
        if s is None or self._failing:
            return True
        if mark > s.mark + max(0, wall_now - s.wall) + GAIN_TICKS:
            return True
        return mark > self._raw_mark and wall_now - s.wall >= PERIOD_S * TICKS_PER_S

    def save(self) -> bool:
        """Write the mark now; False (one warning line, not raised) if it cannot be."""
        with self._io:
            mark, wall = self.clock.mark(), wall_ticks()
            saved = Saved(min(MAX_TICKS, max(mark, wall)), wall)
            try:
                write_atomic(self.path, saved.dump())
            except OSError as exc:
                if not self._failing:
                    log.warning(
                        "signing state %s not saved (%s): frames recorded before a restart "
                        "may be taken after it until it can be",
                        self.path,
                        exc.strerror or exc,
                    )
                self._failing = True
                return False
            if self._failing:
                log.warning("signing state %s saved again", self.path)
            self._failing = False
            self._saved, self._raw_mark = saved, mark
            self.saves += 1
            return True

    def start(self) -> ClockKeeper:
        self._thread = threading.Thread(target=self._run, name=f"signing-state-{self.name}", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(CHECK_S):
            try:
                if self.due(wall_ticks()):
                    self.save()
            except Exception:  # a bug here must not stop the node
                log.exception("signing state %s: saving failed", self.path)

    def close(self) -> None:
        """Stop saving, after one last save (none if never opened). Safe twice."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        if self._opened:
            self.save()


__all__ = [
    "CHECK_S",
    "FALLBACK_TICKS",
    "PERIOD_S",
    "ClockKeeper",
    "Saved",
    "parse",
    "start_reference",
    "wall_ticks",
]
