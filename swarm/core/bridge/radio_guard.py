"""Which RADIO_STATUS reports come from our own radio, and what they may hold back.

Theory of operation
-------------------
A SiK radio injects one RADIO_STATUS (sysid 51, compid 68, unsigned) into its host's
serial output each time it puts a HEARTBEAT from that host on the air: about once
a second, since the bridge sends one HEARTBEAT a second. Its ``txbuf`` is the free
share of the radio's serial input buffer, the only flow control a SiK radio
offers. But the same bytes can come from the air: a foreign radio on the NETID
sends a forged RADIO_STATUS as data and ours forwards it, unsigned and identical.
Nothing in the frame tells the two apart, so :class:`RadioStatusGuard` judges
plausibility and bounds the effect:

* **Source**: only msgid 109 from sysid 51, compid 68 (what the firmware sends).
* **Cadence**: each HEARTBEAT the bridge sent opens a window (until the next one,
  at most ``window_s``) that may hold one report: reports with no window are
  rejected. The bridge puts two HEARTBEATs a second into its radio on an agent with
  a flight controller (its own, and the vehicle's forwarded for the ground
  stations): one sent before the radio answered the last adds one report to the
  window (at most two outstanding). A report beyond those proves a forgery: it is rejected, the
  window is *contested*, and the most favourable ``txbuf`` seen in it counts (our
  radio's true report is among them) while RSSI and noise keep the values from
  before the window.
* **Consistency**: the radio's input buffer holds only bytes the bridge wrote. A
  report of ``100 - txbuf`` % occupied (of at least ``buffer_bytes``, the smallest
  SiK input buffer) when the bridge wrote fewer bytes in the last ``history_s``
  contradicts what the bridge saw, and is rejected.
* **Bounded effect**: protocol traffic is never held; telemetry waits while
  ``txbuf`` < 50 %; poses are never held, only thinned: below 50 % one in 20 is
  skipped, below 20 % at most ``max_pose_thin`` (15 %), never two in a row. So an
  accepted stream of ``txbuf`` 0 costs at most 15 % of the pose rate. Reports older
  than ``stale_s`` are ignored, as ArduPilot and PX4 ignore old txbuf.

Pure: fed with reports, bytes written, heartbeats sent and ``now``; no I/O, no clock.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

RADIO_SYSID = 51  # '3'
RADIO_COMPID = 68  # 'D'
TELEMETRY_MIN_TXBUF = 50
POSE_THIN = ((20, 0.15), (50, 0.05))  # (txbuf below, share of poses skipped)


@dataclass
class RadioState:
    """The last plausible RADIO_STATUS of the local radio (``t``: when accepted)."""

    rssi: int = 0
    remrssi: int = 0
    txbuf: int = 100
    noise: int = 0
    remnoise: int = 0
    rxerrors: int = 0
    t: float = -1e9


@dataclass
class GuardStats:
    accepted: int = 0
    rejected: int = 0  # every report not taken as the radio's (sum of the reasons below)
    wrong_source: int = 0
    unsolicited: int = 0  # no HEARTBEAT of ours asked for it
    excess: int = 0  # a second report for one HEARTBEAT
    contradiction: int = 0  # claims more bytes waiting than the bridge wrote
    poses_thinned: int = 0


@dataclass
class _Window:
    t: float  # the last HEARTBEAT into it
    asked: int = 1  # HEARTBEATs the radio may still answer in it (at most two)
    answered: int = 0
    contested: bool = False


class RadioStatusGuard:
    """See the module docstring. Not thread-safe: the bridge calls it under its lock."""

    def __init__(
        self,
        *,
        window_s: float = 3.0,
        history_s: float = 5.0,
        buffer_bytes: int = 1024,
        slack_bytes: int = 64,
        stale_s: float = 5.0,
        max_pose_thin: float = 0.15,
    ) -> None:
        if not 0.0 <= max_pose_thin < 0.5:
            raise ValueError("max_pose_thin: a share below one half (never two poses in a row)")
        self.window_s = window_s
        self.history_s = history_s
        self.buffer_bytes = buffer_bytes
        self.slack_bytes = slack_bytes
        self.stale_s = stale_s
        self.max_pose_thin = max_pose_thin
        self.stats = GuardStats()
        self.state = RadioState()
        self._before = RadioState()
        self._window: _Window | None = None
        self._written: deque[tuple[float, int]] = deque()
        self._written_sum = 0
        self._debt = 0.0

    # -- what the bridge did --------------------------------------------------------
    def heartbeat_sent(self, now: float) -> None:
        """A HEARTBEAT went to the local radio (the bridge's own, or its vehicle's
        forwarded): it will answer with one report. One sent before the radio answered
        the last adds one answer to the window (at most two outstanding: a report the
        radio never sent is no credit for more)."""
        w = self._window
        if w is not None and now <= w.t + self.window_s and w.answered < w.asked:
            w.asked = min(w.asked + 1, w.answered + 2)
            w.t = now
        else:
            self._window = _Window(now)

    def wrote(self, nbytes: int, now: float) -> None:
        """``nbytes`` went to the local radio."""
        self._written.append((now, nbytes))
        self._written_sum += nbytes
        self._forget(now)

    def reset(self) -> None:
        """The radio was replaced (unplugged and back): forget what it said."""
        self.state = RadioState()
        self._before = RadioState()
        self._window = None
        self._written.clear()
        self._written_sum = 0
        self._debt = 0.0

    # -- a report -------------------------------------------------------------------
    def offer(self, sysid: int, compid: int, report: RadioState, now: float) -> str | None:
        """Judge one RADIO_STATUS (``report.t`` is ignored). Returns None if taken as
        the local radio's, else why not (the report then changes nothing, except that
        in a contested window its ``txbuf`` may lift the back-off)."""
        reason = self._judge(sysid, compid, report, now)
        if reason is None:
            self.stats.accepted += 1
        else:
            self.stats.rejected += 1
            setattr(self.stats, reason, getattr(self.stats, reason) + 1)
        return reason

    def _judge(self, sysid: int, compid: int, r: RadioState, now: float) -> str | None:
        if (sysid, compid) != (RADIO_SYSID, RADIO_COMPID):
            return "wrong_source"
        w = self._window
        if w is None or not w.t <= now <= w.t + self.window_s:
            return "unsolicited"
        if w.answered >= w.asked:
            if not w.contested:
                w.contested = True
                b = self._before
                self.state = RadioState(
                    b.rssi, b.remrssi, self.state.txbuf, b.noise, b.remnoise, b.rxerrors, self.state.t
                )
            if r.txbuf > self.state.txbuf and not self._contradicts(r, now):
                self.state.txbuf = r.txbuf
            return "excess"
        if self._contradicts(r, now):
            return "contradiction"
        if not w.answered:
            self._before = self.state  # what the window restores if it turns out contested
        w.answered += 1
        self.state = RadioState(r.rssi, r.remrssi, r.txbuf, r.noise, r.remnoise, r.rxerrors, now)
        return None

    def _contradicts(self, r: RadioState, now: float) -> bool:
        self._forget(now)
        waiting = (100 - min(100, max(0, r.txbuf))) * self.buffer_bytes // 100
        return waiting > self._written_sum + self.slack_bytes

    def _forget(self, now: float) -> None:
        while self._written and self._written[0][0] < now - self.history_s:
            self._written_sum -= self._written.popleft()[1]

    # -- what the bridge may send -----------------------------------------------------
    def txbuf(self, now: float) -> int:
        """The free share of the radio's input buffer to act on (100 when stale)."""
        return self.state.txbuf if now - self.state.t <= self.stale_s else 100

    def telemetry_allowed(self, now: float) -> bool:
        return self.txbuf(now) >= TELEMETRY_MIN_TXBUF

    def pose_thin(self, now: float) -> float:
        """The share of poses to skip now (0 .. ``max_pose_thin``)."""
        txbuf = self.txbuf(now)
        for below, share in POSE_THIN:
            if txbuf < below:
                return min(share, self.max_pose_thin)
        return 0.0

    def take_pose(self, now: float) -> bool:
        """A pose is about to leave: False if it is to be skipped (counted)."""
        share = self.pose_thin(now)
        if share <= 0.0:
            self._debt = 0.0
            return True
        self._debt += share
        if self._debt >= 1.0:
            self._debt -= 1.0
            self.stats.poses_thinned += 1
            return False
        return True
