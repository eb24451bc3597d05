"""The SiK air model (radios.air.AirModel) in virtual time, against the SiK firmware's behaviour.

Every test drives the pure model with a manual clock (tests/air_helpers.py): no
sleeping, no threads, fixed seeds. Hosts write pymavlink-built frames; outputs are
parsed back with FrameParser. Tolerances are about the model being right, never
about the speed of the machine running the tests.

Where hop lock is not the subject, radios run on one channel (NUM_CHANNELS=1: locked
from boot) so that a test measures what it is about; the goodput and latency tests
use the default 50 channels and start measuring once every radio has locked.
"""

from __future__ import annotations

import functools
import math
import random
import statistics
import struct
from typing import Any

import pytest
from air_helpers import AirBench, AirPacket, saturate, sent_by, tunnel_of_length
from pymavlink.dialects.v10 import ardupilotmega as mav1

from radios.air import AirModel, RadioConfig, serial
from radios.loss import GilbertElliott, RangeLoss, UniformLoss
from radios.mavlink import (
    MSG_HEARTBEAT,
    MSG_RADIO_STATUS,
    Frame,
    FrameBuilder,
    FrameParser,
    decode,
    dialect,
    radio_status_fields,
)
from radios.sik.timing import TICK_S, TRAILER_LEN, model_goodput, model_latency_s

INF = math.inf


# -- helpers -----------------------------------------------------------------------------


def cfgs(n: int, **kw: Any) -> list[RadioConfig]:
    return [RadioConfig(**kw) for _ in range(n)]


def mp_cfgs(n: int, **kw: Any) -> list[RadioConfig]:
    return [RadioConfig(firmware="multipoint", node_id=i, node_count=n, **kw) for i in range(n)]


def numbered(fb: FrameBuilder, i: int, frame_len: int = 145) -> bytes:
    """A TUNNEL frame of ``frame_len`` bytes whose payload starts with ``i``: every
    frame of a test is distinct, so deliveries can be matched to sends."""
    k = frame_len - 17
    raw = fb.tunnel(struct.pack("<I", i) + b"\x01" * (k - 4))
    assert len(raw) == frame_len
    return raw


def ftp_frame(fb: FrameBuilder, payload_len: int, seed: int = 0) -> bytes:
    """A MAVLink 2 FILE_TRANSFER_PROTOCOL frame whose wire payload is exactly
    ``payload_len`` bytes (4..254): MAVLink 2 trims trailing zeros."""
    n = payload_len - 3
    data = [(seed + j) % 255 + 1 for j in range(n)] + [0] * (251 - n)
    raw = fb.build(dialect.MAVLink_file_transfer_protocol_message(0, 1, 1, data))
    assert raw[1] == payload_len
    return raw


def run_until_locked(b: AirBench, feed: Any = None, limit: float = 60.0) -> float:
    while b.locked_at() == INF and b.now < limit:
        b.run(b.now + 0.25, feed)
    assert b.locked_at() < INF, "radios never locked to the hopping sequence"
    return b.locked_at()


def v1_heartbeat(sysid: int = 1) -> bytes:
    mav = mav1.MAVLink(None, srcSystem=sysid, srcComponent=1)
    raw = bytes(mav.heartbeat_encode(18, 8, 0, 0, 4, 3).pack(mav))
    assert raw[0] == 0xFE and raw[1] == 9 and raw[5] == MSG_HEARTBEAT
    return raw


def periodic(node: int, make: Any, every: float, start: float = 0.0, until: float = INF) -> Any:
    """Feeder: one frame from ``make()`` every ``every`` seconds."""
    state = {"next": start}

    def feed(b: AirBench) -> None:
        if state["next"] <= b.now < until:
            b.write(node, make())
            state["next"] += every

    return feed


def feeders(*fs: Any) -> Any:
    def feed(b: AirBench) -> None:
        for f in fs:
            f(b)

    return feed


def radio_statuses(b: AirBench, node: int) -> list[Frame]:
    return [f for f in b.frames(node) if f.msgid == MSG_RADIO_STATUS]


# -- goodput of a saturated pair ---------------------------------------------------------

GOODPUT_MEASURE_S = 10.0
WARMUP_AFTER_LOCK_S = 1.0


@pytest.mark.parametrize("frame_len", [50, 145])
@pytest.mark.parametrize("air", [32, 64, 128])
def test_saturated_goodput_matches_model(air: int, frame_len: int) -> None:
    """One sender saturating a pair (flow control: the host never overruns its
    radio), MAVLink framing on: whole frames per second at the receiver, measured
    after hop lock, is the SiK model's goodput within 10%, and never above the air
    rate."""
    conf = cfgs(2, air_kbps=air, serial_baud=115200)
    b = AirBench(conf, seed=0, flow_control=True)
    fb = FrameBuilder(1, 1)
    feed = saturate(0, lambda: tunnel_of_length(fb, frame_len))
    t0 = run_until_locked(b, feed) + WARMUP_AFTER_LOCK_S
    b.run(t0 + GOODPUT_MEASURE_S, feed)
    got = sum(len(f) for f in b.frames(1, t0))
    goodput = got / GOODPUT_MEASURE_S
    model = model_goodput(conf[0].timing(), frame_len, 115200)
    assert goodput <= air * 1000 / 8
    assert goodput == pytest.approx(model, rel=0.10)
    # whole frames only: nothing corrupted or skipped on the way
    assert b.parsers[1].stats.crc_errors == 0
    assert b.parsers[1].stats.bytes_skipped == 0
    assert b.status(0)["srx"] == 0  # flow control: the host never overran the radio


# -- latency of small frames on an idle channel ------------------------------------------

LATENCY_FRAME = 22  # bytes: a small TUNNEL frame
LATENCY_SAMPLES = 200


@functools.cache
def idle_latencies(air: int, baud: int, max_window: int) -> tuple[list[float], float, float]:
    """Send small frames at random phases on an idle, locked pair; return the
    latencies (host write of the first byte to the last byte out of the receiver),
    the fixed part (serial in + out + flight) and the TDM round."""
    conf = cfgs(2, air_kbps=air, serial_baud=baud, max_window_ms=max_window)
    b = AirBench(conf, seed=3)
    run_until_locked(b)
    b.run(b.now + 1.0)
    fb = FrameBuilder(1, 1)
    rng = random.Random(7)
    lats = []
    for i in range(LATENCY_SAMPLES):
        t_write = b.now
        frame = numbered(fb, i, LATENCY_FRAME)
        b.write(0, frame)
        b.run(t_write + rng.uniform(0.7, 1.3), max_step=0.01)
        got = [r.t for r in b.rx[1] if r.frame.raw == frame]
        assert len(got) == 1, f"frame {i} delivered {len(got)} times"
        lats.append(got[0] - t_write)
    t = conf[0].timing()
    fixed = 2 * LATENCY_FRAME * 10 / baud + t.flight_s(LATENCY_FRAME + TRAILER_LEN)
    return lats, fixed, b.model.round_s()


LATENCY_CASES = [(64, 57600, 131), (128, 57600, 131), (64, 115200, 33)]


@pytest.mark.parametrize(("air", "baud", "max_window"), LATENCY_CASES)
def test_idle_latency_bounds(air: int, baud: int, max_window: int) -> None:
    """No frame is faster than the bytes physically need (serial in, flight, serial
    out), and none waits longer than one TDM round for a transmit chance."""
    lats, fixed, rnd = idle_latencies(air, baud, max_window)
    assert min(lats) >= fixed - 1e-9
    assert max(lats) <= fixed + rnd + 0.002
    # random phases: the waits spread over the whole interval, they are not constant
    assert max(lats) - min(lats) > 0.3 * rnd


@pytest.mark.parametrize(("air", "baud", "max_window"), LATENCY_CASES)
def test_idle_latency_median_matches_model(air: int, baud: int, max_window: int) -> None:
    lats, _fixed, _rnd = idle_latencies(air, baud, max_window)
    t = RadioConfig(air_kbps=air, serial_baud=baud, max_window_ms=max_window).timing()
    model = model_latency_s(t, LATENCY_FRAME, baud)
    assert statistics.median(lats) == pytest.approx(model["p50"], rel=0.20)


def test_idle_latency_multipoint_matches_model() -> None:
    """Multipoint: the sender's chance comes in its own slot of the N-slot round."""
    n = 3
    conf = mp_cfgs(n, num_channels=1, air_kbps=64, serial_baud=57600)
    b = AirBench(conf, seed=3)
    b.run(1.0)
    fb = FrameBuilder(2, 1)
    rng = random.Random(7)
    lats = []
    for i in range(LATENCY_SAMPLES):
        t_write = b.now
        frame = numbered(fb, i, LATENCY_FRAME)
        b.write(1, frame)
        b.run(t_write + rng.uniform(0.7, 1.3), max_step=0.01)
        got = [r.t for r in b.rx[0] if r.frame.raw == frame]
        assert len(got) == 1
        lats.append(got[0] - t_write)
    model = model_latency_s(conf[0].timing(), LATENCY_FRAME, 57600, slots=n, multipoint=True)
    assert statistics.median(lats) == pytest.approx(model["p50"], rel=0.20)


# -- who hears whom ----------------------------------------------------------------------


def test_frames_never_return_to_their_sender() -> None:
    """Pair, three standard radios, multipoint broadcast: a radio never writes the
    frames its own host sent back to that host."""
    for conf in (cfgs(2, num_channels=1), cfgs(3, num_channels=1), mp_cfgs(3, num_channels=1)):
        n = len(conf)
        b = AirBench(conf, seed=1)
        fbs = [FrameBuilder(i + 1, 1) for i in range(n)]
        feed = feeders(
            *(periodic(i, lambda fb=fbs[i]: numbered(fb, 0, 40), 0.2, start=0.05 * i) for i in range(n))
        )
        b.run(6.0, feed)
        for i in range(n):
            heard = {f.sysid for f in b.frames(i)}
            assert i + 1 not in heard
            assert heard, f"node {i} of {n} heard nothing"


def test_netid_separation() -> None:
    """Two pairs on NETIDs 25 and 26 share the air: each hears only its partner."""
    conf = [
        RadioConfig(netid=25, num_channels=1),
        RadioConfig(netid=25, num_channels=1),
        RadioConfig(netid=26, num_channels=1),
        RadioConfig(netid=26, num_channels=1),
    ]
    b = AirBench(conf, seed=2)
    fbs = [FrameBuilder(i + 1, 1) for i in range(4)]
    feed = feeders(
        *(periodic(i, lambda fb=fbs[i]: numbered(fb, 0, 60), 0.25, start=0.03 * i) for i in range(4))
    )
    b.run(8.0, feed)
    partner = {0: 2, 1: 1, 2: 4, 3: 3}  # node -> the sysid it should hear
    for i in range(4):
        heard = [f.sysid for f in b.frames(i)]
        assert heard, f"node {i} heard nothing from its partner"
        assert set(heard) == {partner[i]}


@pytest.mark.parametrize(
    "other", [{"air_kbps": 128}, {"netid": 26}, {"ecc": True}], ids=["air_speed", "netid", "ecc"]
)
def test_incompatible_radios_never_hear_each_other(other: dict[str, Any]) -> None:
    conf = [RadioConfig(num_channels=1), RadioConfig(num_channels=1, **other)]
    b = AirBench(conf, seed=0)
    fbs = [FrameBuilder(1, 1), FrameBuilder(2, 1)]
    feed = feeders(
        periodic(0, lambda: numbered(fbs[0], 0, 40), 0.2),
        periodic(1, lambda: numbered(fbs[1], 0, 40), 0.2, start=0.1),
    )
    b.run(5.0, feed)
    for i in (0, 1):
        st = b.status(i)
        assert b.frames(i) == []
        assert st["rx_packets"] == 0
        assert st["rx_bytes"] == 0
        assert st["tx_packets"] > 0  # they did transmit


# -- loss --------------------------------------------------------------------------------


def frame_fates(losses: list[Any], seed: int = 0, duration: float = 40.0) -> list[bool]:
    """Saturated 128 kbps pair (one 145-byte frame per air packet): for every frame
    put on air by node 0, whether node 1 delivered it."""
    conf = cfgs(2, num_channels=1, air_kbps=128, serial_baud=115200)
    b = AirBench(conf, seed=seed, losses=losses, flow_control=True)
    fb = FrameBuilder(1, 1)
    counter = iter(range(10**9))
    b.run(duration, saturate(0, lambda: numbered(fb, next(counter))))
    delivered = {f.raw for f in b.frames(1)}
    fates = []
    for p in sent_by(b, 0):
        if p.t_end > duration - 0.5:
            continue  # may still be on its way out of the receiver
        frames = FrameParser().feed(p.payload)
        assert len(frames) == 1
        fates.append(frames[0].raw in delivered)
    assert len(fates) > 1000
    return fates


def loss_runs(fates: list[bool]) -> list[int]:
    runs, r = [], 0
    for ok in fates:
        if not ok:
            r += 1
        elif r:
            runs.append(r)
            r = 0
    return runs


def test_no_loss_model_loses_nothing() -> None:
    assert all(frame_fates([], duration=20.0))


def test_uniform_loss() -> None:
    fates = frame_fates([UniformLoss(0.3)])
    n = len(fates)
    lost = fates.count(False) / n
    sd = math.sqrt(0.3 * 0.7 / n)
    assert abs(lost - 0.3) < 4 * sd
    runs = loss_runs(fates)
    assert statistics.mean(runs) < 1.6  # independent: geometric runs, mean 1/(1-p) = 1.43


def test_gilbert_elliott_bursts() -> None:
    ge = GilbertElliott(0.05, 0.3)
    fates = frame_fates([ge], duration=60.0)
    lost = fates.count(False) / len(fates)
    assert lost == pytest.approx(ge.mean_loss(), abs=0.05)
    assert statistics.mean(loss_runs(fates)) > 1.5  # bursts: mean run 1/p_bg = 3.3


def _range_bench(distance_m: float, seed: int = 0) -> tuple[AirBench, RangeLoss]:
    pos = {0: (0.0, 0.0, 0.0), 1: (distance_m, 0.0, 0.0)}
    rl = RangeLoss(lambda node, t: pos.get(node))
    b = AirBench(cfgs(2, num_channels=1), seed=seed, losses=[rl])
    return b, rl


def _range_delivery(distance_m: float) -> tuple[int, int, AirBench]:
    b, _ = _range_bench(distance_m)
    fb = FrameBuilder(1, 1)
    counter = iter(range(10**6))
    b.run(10.0, periodic(0, lambda: numbered(fb, next(counter), 40), 0.1))
    sent = sum(len(FrameParser().feed(p.payload)) for p in sent_by(b, 0) if p.t_end < 9.9)
    return sent, len(b.frames(1, 0.0, 9.9)), b


def test_range_loss_close_loses_nothing() -> None:
    sent, got, b = _range_delivery(10.0)
    assert sent > 50
    assert got == sent
    assert b.status(1)["lost"] == 0


def test_range_loss_very_far_loses_everything() -> None:
    sent, got, b = _range_delivery(5_000_000.0)  # 5000 km: beyond any radio
    assert sent > 50
    assert got == 0
    assert b.status(1)["lost"] > 0


def test_range_loss_50km_loses_everything() -> None:
    """A 100 mW SiK radio with its whips reaches "better than 300 m out of the box,
    several km with a patch antenna on the ground" (Holybro SiK V3 docs), not 50 km.
    The model must not be kinder than the real radio."""
    sent, got, _b = _range_delivery(50_000.0)
    assert sent > 50
    assert got <= 0.01 * sent, f"{got}/{sent} frames delivered over 50 km"


def test_rssi_falls_with_distance() -> None:
    rssi = []
    for d in (50.0, 500.0, 5000.0):
        b, _ = _range_bench(d)
        b.run(8.0)
        b.write(1, FrameBuilder(2, 1).heartbeat())
        b.run(9.0)
        (rs,) = radio_statuses(b, 1)
        fields = radio_status_fields(rs)
        rssi.append((fields["rssi"], fields["remrssi"]))
    assert rssi[0][0] > rssi[1][0] > rssi[2][0]
    assert rssi[0][1] > rssi[1][1] > rssi[2][1]


# -- RADIO_STATUS ------------------------------------------------------------------------


def test_heartbeat_v2_gets_one_radio_status_v2() -> None:
    b = AirBench(cfgs(2, num_channels=1), seed=0)
    fb = FrameBuilder(1, 1)
    writes = iter([1.0, 2.5, 4.0])
    nxt = {"t": next(writes)}

    def feed(bench: AirBench) -> None:
        if bench.now >= nxt["t"]:
            bench.write(0, fb.heartbeat())
            nxt["t"] = next(writes, INF)

    b.run(6.0, feed)
    out = b.frames(0)
    assert [f.msgid for f in out] == [MSG_RADIO_STATUS] * 3  # one per heartbeat, nothing else
    for seq, f in enumerate(out):
        assert (f.version, f.sysid, f.compid, f.seq) == (2, 51, 68, seq)
        assert not f.signed
        msg = decode(f)
        assert msg.get_type() == "RADIO_STATUS"
        assert msg.txbuf == 100  # idle: the input buffer is empty
        assert msg.rssi > 0 and msg.remrssi > 0
    # the heartbeats went over the air; the reports stayed local
    assert [f.msgid for f in b.frames(1)] == [MSG_HEARTBEAT] * 3
    assert b.status(0)["radio_status"] == 3
    assert b.status(1)["radio_status"] == 0


def test_heartbeat_v1_gets_radio_status_v1() -> None:
    b = AirBench(cfgs(2, num_channels=1), seed=0)
    b.run(1.0)
    b.write(0, v1_heartbeat())
    b.run(3.0)
    (rs,) = b.frames(0)
    assert (rs.version, rs.msgid, rs.sysid, rs.compid) == (1, MSG_RADIO_STATUS, 51, 68)
    assert rs.payload_len == 9  # MAVLink 1 never trims the payload
    assert decode(rs).get_type() == "RADIO_STATUS"
    assert [f.version for f in b.frames(1)] == [1]


def test_radio_status_txbuf_falls_when_the_input_buffer_fills() -> None:
    """A saturating host (flow control on) keeps the radio's 1850-byte input buffer
    nearly full: txbuf (% free) in its RADIO_STATUS reports drops below 20, the
    level where ArduPilot slows its streams down."""
    b = AirBench(cfgs(2, num_channels=1, serial_baud=115200), seed=0, flow_control=True)
    fb = FrameBuilder(1, 1)
    count = iter(range(1, 10**9))
    b.run(15.0, saturate(0, lambda: fb.heartbeat() if next(count) % 40 == 0 else tunnel_of_length(fb, 145)))
    reports = [radio_status_fields(f)["txbuf"] for f in radio_statuses(b, 0)]
    assert len(reports) >= 5
    assert max(reports[1:]) < 20
    assert b.status(0)["txbuf"] < 20
    assert b.status(1)["txbuf"] == 100


def test_no_radio_status_without_mavlink_framing() -> None:
    b = AirBench(cfgs(2, num_channels=1, mavlink=0), seed=0)
    fb = FrameBuilder(1, 1)
    b.run(1.0)
    b.write(0, fb.heartbeat())
    b.write(0, v1_heartbeat())
    b.run(4.0)
    assert b.frames(0) == []
    assert b.status(0)["radio_status"] == 0
    assert [f.msgid for f in b.frames(1)] == [MSG_HEARTBEAT, MSG_HEARTBEAT]  # still relayed


# -- a host flooding its radio without flow control --------------------------------------


def test_flooding_host_loses_only_its_own_bytes_multipoint() -> None:
    """Node 0's host writes at 115200 baud into a 64 kbps radio with no flow control:
    its input buffer overflows (srx), nobody else's does, and node 2's traffic still
    reaches everyone in its own slot."""
    conf = mp_cfgs(3, num_channels=1, air_kbps=64, serial_baud=115200)
    b = AirBench(conf, seed=0)
    f0, f2 = FrameBuilder(1, 1), FrameBuilder(3, 1)
    sent2: list[bytes] = []

    def from2() -> bytes:
        sent2.append(numbered(f2, len(sent2), 40))
        return sent2[-1]

    b.run(
        15.0,
        feeders(
            saturate(0, lambda: tunnel_of_length(f0, 145)), periodic(2, from2, 0.5, start=0.5, until=14.0)
        ),
    )
    assert b.status(0)["srx"] > 10_000
    assert b.status(1)["srx"] == 0
    assert b.status(2)["srx"] == 0
    assert len(sent2) >= 25
    for node in (0, 1):
        assert [f.raw for f in b.frames(node) if f.sysid == 3] == sent2
    # and the flood's own frames still go out (those that survived the overflow)
    assert any(f.sysid == 1 for f in b.frames(1))


def test_flooding_host_loses_only_its_own_bytes_pair() -> None:
    conf = cfgs(2, num_channels=1, air_kbps=64, serial_baud=115200)
    b = AirBench(conf, seed=0)
    f0, f1 = FrameBuilder(1, 1), FrameBuilder(2, 1)
    sent1: list[bytes] = []

    def from1() -> bytes:
        sent1.append(numbered(f1, len(sent1), 40))
        return sent1[-1]

    b.run(
        12.0,
        feeders(
            saturate(0, lambda: tunnel_of_length(f0, 145)), periodic(1, from1, 0.3, start=0.5, until=11.0)
        ),
    )
    assert b.status(0)["srx"] > 0
    assert b.status(1)["srx"] == 0
    assert [f.raw for f in b.frames(0) if f.sysid == 2] == sent1


# -- the radio's serial output buffer ----------------------------------------------------


def test_host_that_never_reads_does_not_break_the_model() -> None:
    conf = cfgs(2, num_channels=1, serial_baud=115200)
    b = AirBench(conf, seed=0, flow_control=True, take_output=[True, False])
    f0, f1 = FrameBuilder(1, 1), FrameBuilder(2, 1)
    b.run(
        10.0,
        feeders(
            saturate(0, lambda: tunnel_of_length(f0, 145)), periodic(1, lambda: numbered(f1, 0, 40), 0.5)
        ),
    )
    assert b.status(1)["rx_bytes"] > 10_000
    assert len([f for f in b.frames(0) if f.sysid == 2]) >= 15  # the other way still works


def test_next_deadline_is_in_the_future_when_a_host_does_not_read() -> None:
    """A driver that sleeps until next_deadline() must never be told a time it has
    already reached, also when one host never reads its port (a crashed agent)."""
    m = AirModel(cfgs(2, num_channels=1), seed=0)
    fb = FrameBuilder(1, 1)
    for i in range(10):
        m.host_write(0, numbered(fb, i, 60), 0.0)
    now, past = 0.0, []
    for _ in range(20_000):
        m.advance(now)
        m.take_output(0, now)  # node 0's host reads; node 1's never does
        dl = m.next_deadline()
        assert dl is not None
        if dl <= now:
            past.append(now)
            dl = now + 0.001
        now = dl
        if now > 3.0:
            break
    assert past == [], f"next_deadline() <= now at {len(past)} steps, first at t={past[0]:.3f}"


def test_output_overflow_counts_stx() -> None:
    """The receiver's serial port runs at 1200 baud (120 B/s) while the air brings
    ~5 kB/s: its 645-byte output buffer overflows, the radio truncates (stx) and
    never waits; every byte it received is either delivered or counted."""
    conf = [RadioConfig(num_channels=1, serial_baud=115200), RadioConfig(num_channels=1, serial_baud=1200)]
    b = AirBench(conf, seed=0, flow_control=True)
    fb = FrameBuilder(1, 1)
    b.run(10.0, saturate(0, lambda: tunnel_of_length(fb, 145)))
    st = b.status(1)
    assert st["stx"] > 10_000
    assert len(b.raw[1]) <= 120 * 10.0 + 1
    b.run(20.0)  # no more input: the buffer drains at 120 B/s
    st = b.status(1)
    assert st["serial_out"] + st["stx"] == st["rx_bytes"]
    assert st["serial_out"] == len(b.raw[1])
    assert b.status(0)["stx"] == 0


# -- MAVLink framing ---------------------------------------------------------------------

MIXED_SIZES = [22, 40, 50, 97, 120, 145]


def _framing_run(mavlink: int, seed: int = 0) -> tuple[AirBench, list[bytes]]:
    conf = cfgs(2, num_channels=1, serial_baud=115200, mavlink=mavlink)
    b = AirBench(conf, seed=seed, flow_control=True)
    fb = FrameBuilder(1, 1)
    rng = random.Random(seed)
    sent: list[bytes] = []

    def make() -> bytes:
        sent.append(numbered(fb, len(sent), rng.choice(MIXED_SIZES)))
        return sent[-1]

    b.run(10.0, saturate(0, make))
    b.run(11.0)
    return b, sent


def _packet_is_whole_frames(p: AirPacket) -> bool:
    parser = FrameParser()
    frames = parser.feed(p.payload)
    return (
        parser.pending == 0
        and parser.stats.bytes_skipped == 0
        and sum(len(f) for f in frames) == len(p.payload)
    )


def test_mavlink_framing_keeps_frames_whole_per_packet() -> None:
    b, sent = _framing_run(mavlink=1)
    data = sent_by(b, 0)
    assert len(data) > 200
    assert all(_packet_is_whole_frames(p) for p in data)
    # several small frames share a packet
    assert max(len(FrameParser().feed(p.payload)) for p in data) >= 3
    got = [f.raw for f in b.frames(1)]
    assert got == sent[: len(got)]
    assert len(got) >= len(sent) - 20  # the rest still buffered when the run ended


def test_raw_mode_splits_frames_across_packets() -> None:
    b, sent = _framing_run(mavlink=0)
    data = sent_by(b, 0)
    split = [p for p in data if not _packet_is_whole_frames(p)]
    assert len(split) > len(data) // 2
    # nothing lost on a clean link: the byte stream arrives intact
    got = [f.raw for f in b.frames(1)]
    assert got == sent[: len(got)]
    assert len(got) >= len(sent) - 20


def test_frames_too_large_for_a_packet_arrive_whole() -> None:
    """payload + 25 > 250: the radio splits the frame over packets unframed; the
    receiver's host still gets the frame whole. payload 225 still fits one packet."""
    b = AirBench(cfgs(2, num_channels=1, serial_baud=115200), seed=0, flow_control=True)
    fb = FrameBuilder(1, 1)
    b.run(1.0)
    fits = [ftp_frame(fb, 225, seed=i) for i in range(5)]
    big = [ftp_frame(fb, 254, seed=i) for i in range(5)] + [ftp_frame(fb, 226, seed=9)]
    for f in fits:
        b.write(0, f)
    b.run(4.0)
    n_fit_packets = len(sent_by(b, 0))
    for f in big:
        b.write(0, f)
    b.run(8.0)
    assert [f.raw for f in b.frames(1)] == fits + big
    assert b.parsers[1].stats.bytes_skipped == 0
    packets = sent_by(b, 0)
    assert all(_packet_is_whole_frames(p) for p in packets[:n_fit_packets])
    assert {len(p.payload) for p in packets[:n_fit_packets]} == {237}
    # no packet carries a whole oversized frame
    for p in packets[n_fit_packets:]:
        assert not any(len(f) > 237 for f in FrameParser().feed(p.payload))
    assert sum(len(p.payload) for p in packets[n_fit_packets:]) == sum(len(f) for f in big)


# -- multipoint --------------------------------------------------------------------------


@pytest.mark.parametrize("n", [3, 5])
def test_multipoint_slots(n: int) -> None:
    """Each node transmits only inside its own window of the N-slot round, and
    round_s is N*(W+S)."""
    conf = mp_cfgs(n, num_channels=1, serial_baud=115200)
    b = AirBench(conf, seed=0, flow_control=True)
    fbs = [FrameBuilder(i + 1, 1) for i in range(n)]
    feed = feeders(
        saturate(0, lambda: tunnel_of_length(fbs[0], 145)),
        *(periodic(i, lambda fb=fbs[i]: numbered(fb, 0, 60), 0.13 * i, start=0.01 * i) for i in range(1, n)),
    )
    b.run(8.0, feed)
    t = conf[0].timing()
    w, s = t.tx_window_width, t.silence_period
    assert b.model.round_s() == pytest.approx(n * (w + s) * TICK_S)
    assert all(b.model.round_s(i) == b.model.round_s() for i in range(n))
    slot = (w + s) * TICK_S
    rnd = n * slot
    senders = set()
    for p in b.air:
        k = math.floor((p.t_start - p.sender * slot) / rnd + 1e-9)
        start = k * rnd + p.sender * slot
        assert start - 1e-9 <= p.t_start, p
        assert p.t_end <= start + w * TICK_S + 1e-9, p
        senders.add(p.sender)
    assert senders == set(range(n))
    assert b.status(0)["collisions"] == 0


def test_multipoint_broadcast_and_unicast() -> None:
    n = 4
    conf = [
        RadioConfig(
            firmware="multipoint",
            node_id=i,
            node_count=n,
            num_channels=1,
            node_destination=2 if i == 0 else 0xFFFF,
        )
        for i in range(n)
    ]
    b = AirBench(conf, seed=0)
    fbs = [FrameBuilder(i + 1, 1) for i in range(n)]
    feed = feeders(
        *(
            periodic(i, lambda fb=fbs[i]: numbered(fb, 0, 40), 1.0, start=0.5 + 0.1 * i, until=5.5)
            for i in range(n)
        )
    )
    b.run(8.0, feed)
    heard = [sorted({f.sysid for f in b.frames(i)}) for i in range(n)]
    counts = [[f.sysid for f in b.frames(i)].count for i in range(n)]
    # node 0 sends to node 2 only; the others broadcast
    assert heard[0] == [2, 3, 4]
    assert heard[1] == [3, 4]
    assert heard[2] == [1, 2, 4]
    assert heard[3] == [2, 3]
    for i in range(n):
        for sysid in heard[i]:
            assert counts[i](sysid) == 5


# -- three standard radios on one NETID --------------------------------------------------


def _standard_goodput(n: int) -> tuple[float, int]:
    conf = cfgs(n, num_channels=1, serial_baud=115200)
    b = AirBench(conf, seed=0, flow_control=True)
    fb = FrameBuilder(1, 1)
    b.run(20.0, saturate(0, lambda: tunnel_of_length(fb, 145)))
    goodput = sum(len(f) for f in b.frames(1, 5.0)) / 15.0
    collisions = sum(b.status(i)["collisions"] for i in range(n))
    return goodput, collisions


def test_three_standard_radios_collide() -> None:
    """SiK's TDM (tdm.c) assumes two radios; with three every radio re-syncs to whatever
    it heard last, so windows overlap and packets collide."""
    pair, pair_collisions = _standard_goodput(2)
    three, collisions = _standard_goodput(3)
    assert pair_collisions == 0
    assert collisions > 0
    assert three < 0.75 * pair


# -- determinism -------------------------------------------------------------------------


def _scenario(seed: int) -> tuple[list[bytes], list[dict[str, Any]], list[AirPacket]]:
    conf = cfgs(3, serial_baud=115200)
    b = AirBench(conf, seed=seed, losses=[UniformLoss(0.1), GilbertElliott(0.02, 0.4)], flow_control=True)
    fbs = [FrameBuilder(i + 1, 1) for i in range(3)]
    b.run(
        12.0,
        feeders(
            saturate(0, lambda: tunnel_of_length(fbs[0], 97)),
            periodic(1, fbs[1].heartbeat, 1.0),
            periodic(2, lambda: numbered(fbs[2], 0, 50), 0.3),
        ),
    )
    return [bytes(r) for r in b.raw], [b.status(i) for i in range(3)], b.air


def test_same_seed_same_run() -> None:
    a, b = _scenario(5), _scenario(5)
    assert a[0] == b[0]
    assert a[1] == b[1]
    assert a[2] == b[2]
    assert sum(len(x) for x in a[0]) > 10_000


def test_other_seed_other_timing() -> None:
    a, b = _scenario(5), _scenario(6)
    assert [p.t_start for p in a[2]] != [p.t_start for p in b[2]]


# -- utilisation -------------------------------------------------------------------------


def test_utilisation_idle_and_saturated() -> None:
    idle = AirBench(cfgs(2, num_channels=1), seed=0)
    for t in (1.0, 5.0, 20.0):
        idle.run(t)
        u = idle.model.utilisation()
        # only zero-length yields (two per radio per round) and statistics packets
        assert 0.0 <= u < 0.1
    busy = AirBench(cfgs(2, num_channels=1, serial_baud=115200), seed=0, flow_control=True)
    fb = FrameBuilder(1, 1)
    feed = saturate(0, lambda: tunnel_of_length(fb, 145))
    for t in (1.0, 5.0, 20.0):
        busy.run(t, feed)
        u = busy.model.utilisation()
        assert 0.0 <= u <= 1.0
    assert busy.model.utilisation() > 0.8
    # the channel cannot be busier than the packets put on it
    airtime = sum(busy.status(i)["tx_airtime_s"] for i in range(2))
    assert busy.model.utilisation() * 20.0 <= airtime + 1e-9


# -- closed-form timing (the event-driven simulator skips steps) ---------------------------


def test_a_long_drain_in_one_step_equals_many_small_steps() -> None:
    """The serial output's clock is closed form (byte n of a busy spell leaves at
    drain_base + n * byte_s): draining once, or at thousands of uneven steps, or
    while more output arrives, hands the host the same bytes at the same instants,
    to the last bit."""
    rng = random.Random(15)
    chunks = [(0.01 * k + rng.random() * 0.004, rng.randbytes(rng.randrange(1, 90))) for k in range(40)]
    chunks.sort()
    one, many = (AirModel(cfgs(2, num_channels=1), seed=0).radios[1] for _ in range(2))
    times = sorted(rng.uniform(0.0, 1.2) for _ in range(5000))
    steps = iter(times)
    for when, data in chunks:
        for t in steps:  # many: drain at every step before the next chunk arrives
            if t >= when:
                break
            serial.drain(many, t)
        serial.output(one, data, when)
        serial.output(many, data, when)
    for t in steps:
        serial.drain(many, t)
    serial.drain(many, 1.2)
    serial.drain(one, 1.2)
    assert bytes(one.host_ready) == bytes(many.host_ready)
    assert one.drain_clock == many.drain_clock and one.stats.stx == many.stats.stx
    assert (one.drain_base, one.drained) == (many.drain_base, many.drained)


def test_drain_time_is_when_the_byte_has_left() -> None:
    """serial.drain_time(r, n) is the instant the n-th byte waiting leaves: a hair
    before it n-1 bytes have reached the host, at it all n."""
    r = AirModel(cfgs(2, num_channels=1), seed=0).radios[1]
    serial.output(r, bytes(range(100)), 0.25)
    for n in (1, 2, 37, 100):
        at = serial.drain_time(r, n)
        assert at == pytest.approx(0.25 + n * r.byte_s, abs=1e-12)
        probe = AirModel(cfgs(2, num_channels=1), seed=0).radios[1]
        serial.output(probe, bytes(range(100)), 0.25)
        serial.drain(probe, at - 1e-7)
        assert len(probe.host_ready) == n - 1
        serial.drain(probe, at)
        assert len(probe.host_ready) == n


def test_an_idle_line_starts_where_new_output_arrives() -> None:
    """Output that finds the line idle (drained, even if nobody asked until now)
    starts leaving when it arrives, not where the last spell ended."""
    r = AirModel(cfgs(2, num_channels=1), seed=0).radios[1]
    serial.output(r, b"x" * 10, 0.0)
    serial.output(r, b"y" * 10, 1.0)  # the first ten left by 1.7 ms: an idle line
    assert serial.drain_time(r, 1) == pytest.approx(1.0 + r.byte_s, abs=1e-12)
    serial.drain(r, 2.0)
    assert bytes(r.host_ready) == b"x" * 10 + b"y" * 10


def test_a_frames_delivery_time() -> None:
    """A frame a host writes reaches the other host whole at the end of its packet on
    the air plus its length at the serial rate (the receiver's line was idle)."""
    m = AirModel(cfgs(2, num_channels=1), seed=3)
    packets: list[tuple[int, bytes, float, float, str]] = []
    m.on_air = lambda *p: packets.append(p)
    frame = numbered(FrameBuilder(1, 1), 7, 60)
    m.host_write(0, frame, 0.5)
    while not any(k == "data" for *_, k in packets):
        dl = m.next_deadline()
        assert dl is not None and dl < 5.0
        m.advance(dl)
    _, payload, _, t_end, _ = next(p for p in packets if p[4] == "data")
    assert payload == frame
    m.advance(t_end)
    r = m.radios[1]
    due = serial.drain_time(r, len(frame))
    assert due == pytest.approx(t_end + len(frame) * r.byte_s, abs=1e-12)
    assert m.take_output(1, due - 1e-7) == frame[:-1]
    assert m.take_output(1, due) == frame[-1:]


def test_a_multipoint_node_with_queued_bytes_speaks_at_its_slot_boundary() -> None:
    """Bytes waiting in node k's radio go on the air at the first instant of node k's
    window (rounds counted from the model's start, on whole ticks)."""
    n = 3
    conf = mp_cfgs(n, num_channels=1)
    t = conf[0].timing()
    slot = (t.tx_window_width + t.silence_period) * TICK_S
    for k in range(1, n):
        m = AirModel(conf, seed=1)
        starts: list[float] = []

        def on_air(
            s: int, p: bytes, t0: float, t1: float, kind: str, k: int = k, out: list[float] = starts
        ) -> None:
            if s == k and kind == "data":
                out.append(t0)

        m.on_air = on_air
        m.host_write(k, numbered(FrameBuilder(k + 1, 1), 0, 40), 0.0)
        while not starts:
            dl = m.next_deadline()
            assert dl is not None and dl < 10.0
            m.advance(dl)
        assert starts[0] == pytest.approx(k * slot, abs=1e-9)


def test_a_new_serial_rate_applies_from_the_reboot_on() -> None:
    """Output waiting when a radio is reconfigured leaves at the old rate until the
    reboot and at the new one after it, also when nobody read it before (the drain
    is lazy: the model drains at the reboot)."""
    m = AirModel(cfgs(2, num_channels=1), seed=0)
    r = m.radios[1]
    serial.output(r, b"z" * 600, 0.0)
    old_byte = r.byte_s
    m.reconfigure(1, RadioConfig(num_channels=1, serial_baud=115200), 0.05)
    left = int(0.05 / old_byte + 1e-9)
    assert len(r.host_ready) == left
    assert serial.drain_time(r, 1) == pytest.approx(left * old_byte + r.byte_s, abs=1e-12)
