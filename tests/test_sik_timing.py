"""The firmware's TDM formulas (radios.sik.timing) against a table worked by hand.

The table below was computed by hand from the SiK firmware's tdm.c; these
tests pin tdm_timing() to it, then check the analytic goodput and latency models
for the properties every caller relies on (never faster than the serial port or
the air, latency never below the time the bytes physically need).
"""

from __future__ import annotations

import pytest

from radios.sik.timing import (
    MAX_PACKET_LENGTH,
    TICK_S,
    TRAILER_LEN,
    WINDOW_BITS_MAX,
    fill_window,
    max_xmit,
    model_goodput,
    model_latency_s,
    serial_bytes_per_s,
    tdm_timing,
)

AIR_RATES = [2, 4, 8, 16, 19, 24, 32, 48, 64, 96, 128, 192, 250]
BAUDS = [9600, 19200, 38400, 57600, 115200, 230400]


# -- the table worked by hand from tdm.c -------------------------------------------------


@pytest.mark.parametrize(
    ("air", "ecc", "max_window", "window", "silence", "round_ms"),
    [
        (64, False, 131, 7140, 260, 237),
        (64, True, 131, 6978, 404, 236),
        (64, False, 33, 2046, 260, 74),
        (128, False, 131, 3984, 156, 133),
        (250, False, 131, 2406, 104, 80),
    ],
)
def test_table(air: int, ecc: bool, max_window: int, window: int, silence: int, round_ms: int) -> None:
    t = tdm_timing(air, ecc=ecc, max_window_ms=max_window)
    assert t.tx_window_width == window
    assert t.silence_period == silence
    assert t.round_s() == pytest.approx(2 * (window + silence) * TICK_S)
    assert t.round_s() * 1000 == pytest.approx(round_ms, abs=1.0)  # the table rounds to 1 ms
    assert t.window_s == pytest.approx(window * 16e-6)
    assert t.silence_s == pytest.approx(silence * 16e-6)


@pytest.mark.parametrize("air", [2, 4, 8, 16, 19, 24, 32, 48])
def test_slow_rates_cap_the_window_at_max_window(air: int) -> None:
    """<= 48 kbps: three full packets would exceed MAX_WINDOW=131 ms, so W = 131*62."""
    t = tdm_timing(air)
    assert t.tx_window_width == 8122
    assert 0.269 <= t.round_s() <= 0.470  # "270-470 ms"


def test_slowest_and_fastest_round() -> None:
    assert tdm_timing(48).round_s() == pytest.approx(0.2699, abs=5e-4)
    assert tdm_timing(2).round_s() == pytest.approx(0.4696, abs=5e-4)


@pytest.mark.parametrize("air", AIR_RATES)
@pytest.mark.parametrize("ecc", [False, True])
def test_formulas(air: int, ecc: bool) -> None:
    """tdm_init() step by step, for every air rate the firmware rounds to."""
    t = tdm_timing(air, ecc=ecc)
    tpb = (8 + 8000 // air) // 16 + 1
    latency = 13 * tpb + 13
    payload = 250
    if ecc:
        payload = 118
        tpb *= 2
        latency += 4 * tpb
    assert t.ticks_per_byte == tpb
    assert t.silence_period == 2 * latency
    assert t.tx_window_width == min(3 * (latency + payload * tpb), 25000, 131 * 62, WINDOW_BITS_MAX)
    assert t.max_data_packet_length == payload
    # the preamble adjustment lengthens the flight-time estimate, not the round
    assert t.packet_latency == latency + 3 * tpb
    assert t.flight_ticks(0) == t.packet_latency
    assert t.flight_ticks(10) == t.packet_latency + 10 * tpb
    assert t.flight_s(10) == pytest.approx(t.flight_ticks(10) * TICK_S)
    assert t.mav_max_xmit == min((t.tx_window_width - t.packet_latency) // tpb, payload)


def test_max_packet_lengths() -> None:
    assert tdm_timing(64).max_data_packet_length == MAX_PACKET_LENGTH - TRAILER_LEN == 250
    assert tdm_timing(64, ecc=True).max_data_packet_length == 118


def test_window_limits() -> None:
    # 13-bit trailer: never more than 8191 ticks, even without MAX_WINDOW on one channel
    t = tdm_timing(2, max_window_ms=None, num_channels=1)
    assert t.tx_window_width == WINDOW_BITS_MAX
    # multipoint (no MAX_WINDOW) at 64 kbps: the three-packet window
    assert tdm_timing(64, max_window_ms=None).tx_window_width == 7140
    # MAX_WINDOW 33 shrinks the largest MAVLink frame the packetiser keeps whole
    assert tdm_timing(64, max_window_ms=33).mav_max_xmit == (2046 - 157) // 9 == 209
    for air in AIR_RATES:
        for ecc in (False, True):
            t = tdm_timing(air, ecc=ecc)
            assert t.tx_window_width <= min(25000, WINDOW_BITS_MAX)


def test_round_slots() -> None:
    t = tdm_timing(128)
    assert t.round_s(2) == pytest.approx(2 * (3984 + 156) * TICK_S)
    assert t.round_s(5) == pytest.approx(5 * (3984 + 156) * TICK_S)


def test_bad_air_rate() -> None:
    with pytest.raises(ValueError):
        tdm_timing(0)


# -- max_xmit: how much fits in what is left of a window ----------------------------------


def test_max_xmit_edges() -> None:
    t = tdm_timing(64)  # L = 157, tpb = 9
    L, tpb = t.packet_latency, t.ticks_per_byte
    assert max_xmit(t, 0) == 0
    assert max_xmit(t, L - 1) == 0
    assert max_xmit(t, L) == 0
    # room for the 2-byte trailer and one spare byte only: nothing to carry
    assert max_xmit(t, L + 3 * tpb) == 0
    assert max_xmit(t, L + 4 * tpb - 1) == 0
    assert max_xmit(t, L + 4 * tpb) == 1
    assert max_xmit(t, L + 103 * tpb) == 100
    # capped at the largest packet
    assert max_xmit(t, L + 253 * tpb) == 250
    assert max_xmit(t, t.tx_window_width) == 250
    assert max_xmit(t, 10**6) == 250
    assert max_xmit(tdm_timing(64, ecc=True), 10**6) == 118


def test_max_xmit_never_overruns_the_window() -> None:
    """A packet of max_xmit bytes plus trailer always ends inside the window."""
    for air in (2, 32, 64, 128, 250):
        for ecc in (False, True):
            t = tdm_timing(air, ecc=ecc)
            prev = 0
            for remaining in range(0, t.tx_window_width + 1, 7):
                n = max_xmit(t, remaining)
                assert n >= prev  # monotonic in the time left
                prev = n
                if n:
                    assert t.flight_ticks(n + TRAILER_LEN) <= remaining


# -- fill_window -------------------------------------------------------------------------


@pytest.mark.parametrize("frame_len", [21, 50, 97, 145, 250])
@pytest.mark.parametrize("air", [32, 64, 128, 250])
def test_fill_window_packs_whole_frames(air: int, frame_len: int) -> None:
    t = tdm_timing(air)
    w = t.tx_window_width
    sent, used = fill_window(t, w, frame_len)
    assert sent > 0
    assert sent % frame_len == 0
    assert used <= w
    # not one more frame would fit in what is left
    assert max_xmit(t, w - used) < frame_len
    # packets hold at most max_data_packet_length bytes each: count them
    per_packet = t.max_data_packet_length // frame_len * frame_len
    packets = -(-sent // per_packet)
    assert used >= packets * t.packet_latency + (sent + packets * TRAILER_LEN) * t.ticks_per_byte


def test_fill_window_edge_cases() -> None:
    t = tdm_timing(64)
    assert fill_window(t, t.tx_window_width, 251) == (0, 0)  # never fits in one packet
    assert fill_window(t, 0, 50) == (0, 0)
    assert fill_window(t, t.packet_latency + 52 * t.ticks_per_byte, 50) == (0, 0)
    sent, used = fill_window(t, t.packet_latency + 53 * t.ticks_per_byte, 50)
    assert (sent, used) == (50, t.flight_ticks(52))
    # 64 kbps, 250-byte frames: 2 full packets fit in 7140 ticks (each 157 + 252*9 = 2425)
    assert fill_window(t, t.tx_window_width, 250) == (500, 2 * 2425)


# -- the analytic models -----------------------------------------------------------------


@pytest.mark.parametrize("air", AIR_RATES)
@pytest.mark.parametrize("ecc", [False, True])
def test_model_goodput_bounded_by_serial_and_air(air: int, ecc: bool) -> None:
    t = tdm_timing(air, ecc=ecc)
    for frame_len in (21, 50, 97, 145, 200):
        for baud in BAUDS:
            g = model_goodput(t, frame_len, baud)
            assert g >= 0
            assert g <= serial_bytes_per_s(baud) + 1e-9
            assert g <= air * 1000 / 8
            # one way, with the peer's window yielded: never more than 100% of the air time
            assert g <= air * 1000 / 8 * t.max_data_packet_length / (t.max_data_packet_length + 2)


def test_model_goodput_shape() -> None:
    t = tdm_timing(64)
    # serial-limited: 9600 baud carries 960 B/s, far below what the air moves
    assert model_goodput(t, 50, 9600) == pytest.approx(960.0)
    # air-limited at 115200: bigger air rate, more goodput
    g = [model_goodput(tdm_timing(a), 145, 115200) for a in (32, 64, 128, 250)]
    assert g == sorted(g)
    assert len(set(g)) == 4
    # ECC halves the byte rate: well under the plain rate
    assert model_goodput(tdm_timing(64, ecc=True), 50, 115200) < 0.6 * model_goodput(t, 50, 115200)
    # about 5-6 kB/s at 64 kbps (ArduPilot's SiK documentation: ~90 % of the air rate one way)
    assert 5000 < model_goodput(t, 50, 115200) < 6500


@pytest.mark.parametrize(("air", "baud", "frame_len"), [(64, 57600, 22), (128, 115200, 30), (32, 19200, 50)])
def test_model_latency_parts(air: int, baud: int, frame_len: int) -> None:
    """Serial in and out + flight is the floor; the wait for a transmit chance is
    uniform (p50 = mean) and bounded by one TDM round."""
    t = tdm_timing(air)
    lat = model_latency_s(t, frame_len, baud)
    fixed = 2 * frame_len * 10 / baud + t.flight_s(frame_len + TRAILER_LEN)
    wait50 = lat["p50"] - fixed
    wait99 = lat["p99"] - fixed
    assert 0 < wait50 < wait99 <= 0.99 * t.round_s() + 1e-12
    assert wait99 == pytest.approx(wait50 * 0.99 / 0.5)  # uniform wait
    assert lat["mean"] == pytest.approx(lat["p50"])
    # half of the interval between transmit chances, which is at most one round
    # and at least half a round (a radio gets its own window and, when the peer is
    # idle, the peer's yielded window)
    assert 0.25 * t.round_s() - 1e-12 <= wait50 <= 0.5 * t.round_s() + 1e-12


def test_model_latency_multipoint_grows_with_slots() -> None:
    t = tdm_timing(64, max_window_ms=None)
    p = [model_latency_s(t, 22, 57600, slots=n, multipoint=True)["p50"] for n in (3, 4, 6, 10)]
    assert p == sorted(p)
    assert p[-1] - p[0] == pytest.approx(0.5 * (t.round_s(10) - t.round_s(3)), rel=1e-6)
