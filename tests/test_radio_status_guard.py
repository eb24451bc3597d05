"""Forged RADIO_STATUS from the air must not throttle the swarm (issue 11, item 4).

A SiK radio injects RADIO_STATUS (sysid 51, compid 68, unsigned) into its host's
serial output once per HEARTBEAT from that host; a foreign radio on the same NETID
can put identical bytes on the air and ours forwards them. The pure rule
(:class:`swarm.core.bridge.radio_guard.RadioStatusGuard`) is tested on a manual clock; then end
to end: a ``swarm radio-emu`` process (real ptys, the SiK air model), three bridged
nodes streaming poses at 4 Hz, an observer measuring them, and a rogue radio on the
same NETID sending forged RADIO_STATUS at 10 Hz with txbuf 0.
"""

from __future__ import annotations

import random
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from net_helpers import wait_until

from radios.link import open_link
from radios.mavlink import pack_frame
from swarm.cli.procs import start_emulator
from swarm.core.bridge.radio_guard import RadioState, RadioStatusGuard
from swarm.core.wire.message_types import Advertize, Pose, PoseReport
from swarm.runtime.bridge.radio_bridge import RadioBridge
from swarm.runtime.keyspace.transport import Transport, open_session

pytestmark = pytest.mark.processes  # bridges on emulated radios, in real time

LOCAL = (51, 68)


def report(txbuf: int, rssi: int = 200) -> RadioState:
    return RadioState(rssi=rssi, remrssi=190, txbuf=txbuf, noise=40, remnoise=41)


def busy_guard(t: float = 0.0) -> RadioStatusGuard:
    """A guard whose bridge wrote enough lately that any txbuf is consistent."""
    g = RadioStatusGuard()
    g.wrote(4000, t)
    return g


# -- the pure rule ------------------------------------------------------------------


def test_one_report_per_heartbeat_from_the_radios_ids() -> None:
    g = busy_guard()
    assert g.offer(*LOCAL, report(30), 0.1) == "unsolicited"  # no HEARTBEAT asked for it
    g.heartbeat_sent(1.0)
    assert g.offer(51, 1, report(30), 1.1) == "wrong_source"
    assert g.offer(7, 68, report(30), 1.1) == "wrong_source"
    assert g.offer(*LOCAL, report(30), 1.2) is None
    assert g.state.txbuf == 30 and g.state.rssi == 200 and g.state.t == 1.2
    assert g.offer(*LOCAL, report(10), 1.3) == "excess"
    assert g.state.txbuf == 30, "a second report for one heartbeat changes nothing but may lift txbuf"
    g.heartbeat_sent(2.0)
    assert g.offer(*LOCAL, report(60), 5.5) == "unsolicited"  # 3.5 s later: not its answer
    s = g.stats
    assert (s.accepted, s.rejected, s.wrong_source, s.unsolicited, s.excess) == (1, 5, 2, 2, 1)


def test_each_heartbeat_into_the_radio_is_answered_once_also_two_close_together() -> None:
    """An agent puts two HEARTBEATs a second into its radio: the bridge's own and its
    vehicle's, forwarded for the ground stations. The radio answers each: both reports
    are its own (every healthy agent with a flight controller once logged a rejected
    report at start, and counted one in two as a forgery). A third is still too many."""
    g = busy_guard()
    g.heartbeat_sent(1.0)  # the bridge's
    g.heartbeat_sent(1.05)  # the vehicle's, forwarded before the radio answered the first
    assert g.offer(*LOCAL, report(30), 1.2) is None
    assert g.offer(*LOCAL, report(40), 1.3) is None
    assert g.state.txbuf == 40 and g.stats.excess == 0
    assert g.offer(*LOCAL, report(90), 1.4) == "excess"  # nobody asked for a third
    g.heartbeat_sent(1.5)  # answered ones are no credit for the next
    assert g.offer(*LOCAL, report(50), 1.6) is None
    assert g.offer(*LOCAL, report(95), 1.7) == "excess"
    # a report that never came (the radio had no room) leaves one to come, not more
    g.heartbeat_sent(2.5)
    g.heartbeat_sent(3.5)
    g.heartbeat_sent(4.5)
    assert g.offer(*LOCAL, report(50), 4.6) is None
    assert [g.offer(*LOCAL, report(50), 4.7), g.offer(*LOCAL, report(50), 4.8)].count(None) <= 1


def test_contested_window_takes_the_most_favourable_txbuf_and_keeps_rssi() -> None:
    g = busy_guard()
    g.heartbeat_sent(0.0)
    assert g.offer(*LOCAL, report(90, rssi=150), 0.2) is None
    g.heartbeat_sent(1.0)
    assert g.offer(*LOCAL, report(0, rssi=255), 1.05) is None  # a forgery came first
    assert g.state.txbuf == 0
    assert g.offer(*LOCAL, report(95, rssi=140), 1.2) == "excess"  # the radio's own
    assert g.state.txbuf == 95, "the radio's true report is among them: the highest counts"
    assert g.state.rssi == 150, "RSSI from a contested window is not trusted"
    assert g.offer(*LOCAL, report(0, rssi=255), 1.3) == "excess"
    assert g.state.txbuf == 95


def test_report_contradicting_the_bytes_written_is_rejected() -> None:
    g = RadioStatusGuard()
    g.wrote(21, 0.0)  # one HEARTBEAT: the radio's buffer cannot be full
    g.heartbeat_sent(0.0)
    assert g.offer(*LOCAL, report(0), 0.1) == "contradiction"
    assert g.offer(*LOCAL, report(97), 0.2) is None
    g.wrote(900, 0.5)
    g.heartbeat_sent(1.0)
    assert g.offer(*LOCAL, report(20), 1.1) is None  # 80 % of 1024 B < 921 B + slack
    g.heartbeat_sent(7.0)  # what was written 6.5 s ago has long gone on air
    assert g.offer(*LOCAL, report(20), 7.1) == "contradiction"


def test_backoff_is_bounded_and_goes_stale() -> None:
    g = busy_guard()
    g.heartbeat_sent(0.0)
    g.offer(*LOCAL, report(0), 0.1)
    assert not g.telemetry_allowed(0.2)
    taken = [g.take_pose(0.2 + k * 0.01) for k in range(100)]
    assert taken.count(False) <= 15, "at most 15 % of poses skipped"
    assert all(taken[k] or taken[k + 1] for k in range(99)), "never two poses in a row"
    assert g.telemetry_allowed(5.2) and g.take_pose(5.2) and g.pose_thin(5.2) == 0.0  # stale
    g.wrote(4000, 6.0)
    g.heartbeat_sent(6.0)
    assert g.offer(*LOCAL, report(40), 6.1) is None
    assert not g.telemetry_allowed(6.2) and g.pose_thin(6.2) == 0.05
    g.reset()
    assert g.txbuf(6.2) == 100 and g.state.rssi == 0


def test_forged_stream_at_any_rate_costs_at_most_a_fifth_of_the_poses() -> None:
    """Model time: the bridge's HEARTBEAT each second answered by the radio 0.15 s
    later (txbuf 100), forged txbuf 0 reports at 10 Hz and 50 Hz, poses at 4 Hz."""
    for forged_hz in (10.0, 50.0):
        g = busy_guard()
        rng = random.Random(3)
        events: list[tuple[float, str]] = []
        for k in range(120):
            events += [(k + 0.0, "hb"), (k + 0.15, "radio")]
        events += [(k / forged_hz + rng.random() / forged_hz, "forged") for k in range(int(120 * forged_hz))]
        events += [(k / 4 + 0.001, "pose") for k in range(480)]
        sent = 0
        for t, what in sorted(events):
            if what == "hb":
                g.heartbeat_sent(t)
                g.wrote(4000, t)
            elif what == "radio":
                g.offer(*LOCAL, report(100), t)
            elif what == "forged":
                g.offer(*LOCAL, report(0, rssi=rng.randrange(256)), t)
            else:
                sent += g.take_pose(t)
        assert sent >= 0.8 * 480, f"{forged_hz} Hz forgeries: {sent}/480 poses"
        assert g.stats.rejected >= 0.8 * 120 * forged_hz


def test_signing_lets_only_the_radios_own_ids_through_unsigned() -> None:
    from radios.mavlink import parse_one
    from radios.signing import Verifier

    v = Verifier(b"\0" * 32)
    payload = struct.pack("<HHBBBBB", 0, 0, 200, 190, 0, 40, 41)
    assert v.check(parse_one(pack_frame(109, payload, sysid=51, compid=68, seq=0)))
    assert not v.check(parse_one(pack_frame(109, payload, sysid=51, compid=1, seq=0)))
    assert not v.check(parse_one(pack_frame(109, payload, sysid=9, compid=68, seq=0)))


# -- end to end: a rogue radio on the emulator ---------------------------------------

AGENTS = ("a1", "a2", "a3")
POSE_HZ = 4.0
PHASE_S = 15.0
LOCK_DEADLINE = 90.0
POSE = Pose(48.8566, 2.3522, 135.0, heading=90.0, vn=1.0, ve=-0.5, t=1.0)


class PoseRecorder:
    """Arrival times of every agent's pose at the observer."""

    def __init__(self, session: Any) -> None:
        self.times: dict[str, list[float]] = {n: [] for n in AGENTS}
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber("swarm/*/pose", self._on)

    def _on(self, sample: Any) -> None:
        name = str(sample.key_expr).split("/")[1]
        with self._lock:
            if name in self.times:
                self.times[name].append(time.monotonic())

    def measure(self, t0: float, t1: float) -> tuple[float, float]:
        """(poses per second over all agents, longest gap of any agent) in [t0, t1]."""
        with self._lock:
            series = {n: [t for t in ts if t0 <= t <= t1] for n, ts in self.times.items()}
        count = sum(len(ts) for ts in series.values())
        gap = max(max(b - a for a, b in zip([t0, *ts], [*ts, t1], strict=True)) for ts in series.values())
        return count / (t1 - t0), gap

    def close(self) -> None:
        self._sub.undeclare()


def forged_status(rng: random.Random, seq: int, txbuf: int) -> bytes:
    payload = struct.pack(
        "<HHBBBBB",
        0,
        0,
        rng.randrange(256),
        rng.randrange(256),
        txbuf,
        rng.randrange(256),
        rng.randrange(256),
    )
    return pack_frame(109, payload, sysid=51, compid=68, seq=seq & 0xFF)


def _published(times: list[float], t0: float, t1: float) -> tuple[float, float]:
    """(poses published per second over all agents, the publisher's longest gap) in [t0, t1]."""
    ts = [t for t in times if t0 <= t <= t1]
    gap = max(b - a for a, b in zip([t0, *ts], [*ts, t1], strict=True))
    return len(ts) * len(AGENTS) / (t1 - t0), gap


@pytest.fixture
def swarm(tmp_path: Path) -> Iterator[tuple[list[RadioBridge], PoseRecorder, Any, list[Transport]]]:
    with ExitStack() as stack:
        emu, paths = start_emulator(5, tmp_path, "--seed", "16")
        stack.callback(emu.stop)
        bridges, transports = [], []
        for i, name in enumerate([*AGENTS, "observer"]):
            session = open_session()
            stack.callback(session.close)
            link = open_link(paths[i])
            stack.callback(link.close)
            bridge = RadioBridge(session, link, name=name, agent_id=i + 1 if i < 3 else 99).start()
            stack.callback(bridge.close)
            bridges.append(bridge)
            t = Transport(name, session)
            stack.callback(t.close)
            transports.append(t)
            if name == "observer":
                rec = PoseRecorder(session)
                stack.callback(rec.close)
        rogue = open_link(paths[4])
        stack.callback(rogue.close)

        def known() -> bool:
            if set(AGENTS) <= set(bridges[3].peers()):
                return True
            for i, name in enumerate(AGENTS):
                transports[i].advertise(Advertize(i + 1, name))
            return False

        wait_until(known, "the observer to learn every agent's name", LOCK_DEADLINE, 0.5)
        yield bridges[:3], rec, rogue, transports[:3]


# txbuf 45 (reports rejected only as second reports) takes another 34 s: with the slow ones
@pytest.mark.timing  # pose rates over 15 s windows
@pytest.mark.parametrize("txbuf", [0, pytest.param(45, marks=pytest.mark.slow)])
def test_rogue_radio_status_stream_slows_poses_by_at_most_a_fifth(
    swarm: tuple[list[RadioBridge], PoseRecorder, Any, list[Transport]], txbuf: int
) -> None:
    """txbuf 0 claims more bytes waiting than a node streaming poses writes; 45 does
    not, so those forgeries meet the radio's own reports in contested windows."""
    bridges, rec, rogue, transports = swarm
    stop = threading.Event()

    published: list[float] = []  # when each round of poses left (a stall of this process shows)

    def publish() -> None:
        next_t = time.monotonic()
        while not stop.is_set():
            for t in transports:
                t.publish_pose(PoseReport(POSE))
            published.append(time.monotonic())
            next_t += 1.0 / POSE_HZ
            stop.wait(max(0.0, next_t - time.monotonic()))

    def attack() -> None:
        rng, seq = random.Random(11), 0
        next_t = time.monotonic()
        while not stop.is_set():
            rogue.send(forged_status(rng, seq, txbuf))
            seq += 1
            next_t += 0.1
            stop.wait(max(0.0, next_t - time.monotonic()))

    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    attacker = threading.Thread(target=attack, daemon=True)
    try:
        time.sleep(2.0)  # streams settle (not a synchronisation: the window starts later)
        t0 = time.monotonic()
        time.sleep(PHASE_S)
        t1 = time.monotonic()
        attacker.start()
        time.sleep(2.0)
        t2 = time.monotonic()
        time.sleep(PHASE_S)
        t3 = time.monotonic()
    finally:
        stop.set()
        publisher.join(5)
        if attacker.is_alive():
            attacker.join(5)
    rate0, gap0 = rec.measure(t0, t1)
    rate1, gap1 = rec.measure(t2, t3)
    # the two windows follow each other: a loaded machine may stall this process in one
    # of them, and then the poses are not even published. Each window is judged on what
    # was published in it (the rate as a share of it; the gap beyond the publisher's own)
    sent0, pub_gap0 = _published(published, t0, t1)
    sent1, pub_gap1 = _published(published, t2, t3)
    rejected = [b.stats.radio_status_rejected for b in bridges]
    print(
        f"\nposes without the rogue: {rate0:.2f}/s, longest gap {gap0:.2f} s; with forged "
        f"RADIO_STATUS at 10 Hz, txbuf {txbuf}: {rate1:.2f}/s, longest gap {gap1:.2f} s; "
        f"published {sent0:.2f}/s and {sent1:.2f}/s (longest gaps {pub_gap0:.2f} s, {pub_gap1:.2f} s); "
        f"rejected {rejected}, "
        f"accepted {[b.stats.radio_status_accepted for b in bridges]}, "
        f"thinned {[b.stats.poses_thinned for b in bridges]}; why rejected (a1): "
        f"{ {k: v for k, v in vars(bridges[0].guard.stats).items() if k not in ('accepted', 'rejected')} }"
    )
    share0, share1 = rate0 / sent0, rate1 / sent1
    assert share0 > 0.5, f"the baseline itself carried the poses ({share0:.2f} of them)"
    assert share1 >= 0.8 * share0, f"share of poses delivered fell from {share0:.2f} to {share1:.2f}"
    # held poses arrive late in a burst (the count alone hides it: 11.4/s against 12/s
    # before the fix, with the longest gap 0.60 s -> 1.76 s). The bridge may skip at most
    # one pose in a row: one pose period, and one more for a loaded machine
    extra0, extra1 = gap0 - pub_gap0, gap1 - pub_gap1
    assert extra1 <= max(extra0, 0.0) + 2.0 / POSE_HZ, (
        f"longest pose gap beyond the publisher's grew from {extra0:.2f} s to {extra1:.2f} s"
    )
    assert all(r >= 50 for r in rejected), f"forged RADIO_STATUS counted as rejected: {rejected}"
