"""SiK TDM timing: the firmware's formulas, and what they predict.

Theory of operation
-------------------
The SiK firmware (tdm.c, ``tdm_init``) derives every timing from the air data
rate, in 16 µs timer ticks:

* ``ticks_per_byte`` = (8 + 8000/kbps) / 16 + 1 (integer division);
* ``packet_latency`` L = 13·tpb + 13, the cost of a zero-length packet
  (preamble, sync word, header, CRC, turn-around). With ECC (Golay) tpb doubles
  and L grows by 4·tpb;
* ``silence_period`` S = 2·L, ``tx_window_width`` W = 3·(L + maxpayload·tpb)
  capped at 25000 (more than one channel), MAX_WINDOW·62 and 8191 (13 bits);
* after the window is fixed, L grows by 3·tpb for the real preamble length and
  is the flight-time estimate used thereafter: flight(n) = L + n·tpb.

A radio pair cycles TRANSMIT(W), SILENCE(S), RECEIVE(W), SILENCE(S): the round
is 2·(W+S). The multipoint firmware gives every node id a window in turn:
NODECOUNT·(W+S).

The ``model_*`` functions predict goodput and latency from the same formulas,
analytically, so the emulator's measured figures can be checked against them
(``swarm bench radio``).
"""

from __future__ import annotations

from dataclasses import dataclass

TICK_S = 16e-6
MAX_PACKET_LENGTH = 252
TRAILER_LEN = 2
STATS_LEN = 4  # rssi, remrssi... the firmware's statistics struct
REGULATORY_MAX_WINDOW = 25000
WINDOW_BITS_MAX = 0x1FFF


@dataclass(frozen=True)
class TdmTiming:
    air_kbps: int
    ecc: bool
    ticks_per_byte: int
    packet_latency: int  # flight-time overhead (after the preamble adjustment)
    silence_period: int
    tx_window_width: int
    max_data_packet_length: int
    mav_max_xmit: int  # largest packet the MAVLink framer plans for

    def flight_ticks(self, nbytes: int) -> int:
        """Air time of a packet carrying ``nbytes`` (payload + trailer)."""
        return self.packet_latency + nbytes * self.ticks_per_byte

    def flight_s(self, nbytes: int) -> float:
        return self.flight_ticks(nbytes) * TICK_S

    @property
    def window_s(self) -> float:
        return self.tx_window_width * TICK_S

    @property
    def silence_s(self) -> float:
        return self.silence_period * TICK_S

    def round_s(self, slots: int = 2) -> float:
        """TDM round: every slot (2 for a pair, NODECOUNT for multipoint) gets a
        window and a silence period."""
        return slots * (self.tx_window_width + self.silence_period) * TICK_S


def tdm_timing(
    air_kbps: int,
    *,
    ecc: bool = False,
    max_window_ms: int | None = 131,
    num_channels: int = 50,
    preamble_length: int = 16,
) -> TdmTiming:
    """The firmware's timings for an air rate (already rounded as at boot).

    ``max_window_ms`` None means no MAX_WINDOW parameter (multipoint firmware).
    """
    if air_kbps <= 0:
        raise ValueError("air rate must be positive")
    tpb = (8 + 8000 // air_kbps) // 16 + 1
    latency = (8 + 10 // 2) * tpb + 13
    if ecc:
        max_payload = MAX_PACKET_LENGTH // 2 - (6 + TRAILER_LEN)
        tpb *= 2
        latency += 4 * tpb
    else:
        max_payload = MAX_PACKET_LENGTH - TRAILER_LEN
    silence = 2 * latency
    window = 3 * (latency + max_payload * tpb)
    if num_channels > 1:
        window = min(window, REGULATORY_MAX_WINDOW)
    if max_window_ms is not None:
        window = min(window, max_window_ms * 62)
    window = min(window, WINDOW_BITS_MAX)
    latency += ((preamble_length - 10) // 2) * tpb
    mav_max = min((window - latency) // tpb, max_payload)
    return TdmTiming(
        air_kbps=air_kbps,
        ecc=ecc,
        ticks_per_byte=tpb,
        packet_latency=latency,
        silence_period=silence,
        tx_window_width=window,
        max_data_packet_length=max_payload,
        mav_max_xmit=mav_max,
    )


def max_xmit(t: TdmTiming, remaining_ticks: int) -> int:
    """How many payload bytes the firmware lets a packet carry with
    ``remaining_ticks`` left in its window (0: nothing fits)."""
    if remaining_ticks < t.packet_latency:
        return 0
    n = (remaining_ticks - t.packet_latency) // t.ticks_per_byte
    if n < TRAILER_LEN + 1:
        return 0
    return min(n - (TRAILER_LEN + 1), t.max_data_packet_length)


def fill_window(t: TdmTiming, remaining_ticks: int, frame_len: int) -> tuple[int, int]:
    """Bytes a saturated MAVLink-framing sender moves in a window of
    ``remaining_ticks``, packing whole frames of ``frame_len`` per packet.
    Returns (bytes, ticks used)."""
    sent = used = 0
    while True:
        room = max_xmit(t, remaining_ticks - used)
        k = room // frame_len
        if k == 0:
            break
        n = k * frame_len
        sent += n
        used += t.flight_ticks(n + TRAILER_LEN)
    return sent, used


def serial_bytes_per_s(baud: int) -> float:
    """8N1: ten bits on the wire per byte."""
    return baud / 10.0


def model_goodput(t: TdmTiming, frame_len: int, serial_baud: int) -> float:
    """Predicted one-way goodput (frame bytes/s) of a radio pair when one side is
    saturated and the other idle, MAVLink framing on.

    The sender fills its own window; the idle peer opens its window with a
    zero-length packet (and, twice a second, a statistics packet first) that
    yields the rest to the sender as bonus time. The serial ports cap the rate.
    """
    w = t.tx_window_width
    own, _ = fill_window(t, w, frame_len)
    yield_pkt = t.flight_ticks(TRAILER_LEN)
    stats_pkt = t.flight_ticks(STATS_LEN + TRAILER_LEN)
    round_s = t.round_s(2)
    stats_per_round = min(1.0, round_s / 0.5)
    bonus_plain, _ = fill_window(t, w - yield_pkt, frame_len)
    bonus_stats, _ = fill_window(t, w - yield_pkt - stats_pkt, frame_len)
    bonus = stats_per_round * bonus_stats + (1 - stats_per_round) * bonus_plain
    air = (own + bonus) / round_s
    return min(air, serial_bytes_per_s(serial_baud))


def model_latency_s(
    t: TdmTiming,
    frame_len: int,
    serial_baud: int,
    slots: int = 2,
    *,
    peer_idle: bool = True,
    multipoint: bool = False,
) -> dict[str, float]:
    """Predicted one-way latency of a small frame on an otherwise quiet channel.

    serial in + wait for a chance to transmit + flight + serial out, with the frame
    arriving at a uniformly random moment:

    * standard pair: an idle radio yields its window at once with a zero-length
      packet (tdm.c), so data that arrives later waits for the next window start.
      When the peer is idle (``peer_idle``) its yield hands the sender bonus ticks
      at the start of the peer's window too: a chance every half round. With
      traffic both ways, once per round. The wait is uniform over that interval;
    * multipoint (no bonus): a node sends at once inside its own window and
      otherwise waits for the next one: with round R and window W the wait is 0
      with probability W/R and uniform over R-W otherwise.

    Returns p50, p99 and mean in seconds.
    """
    byte_s = 1.0 / serial_bytes_per_s(serial_baud)
    fixed = 2 * frame_len * byte_s + t.flight_s(frame_len + TRAILER_LEN)
    rnd = t.round_s(slots)
    if multipoint:
        w = t.window_s

        def q(p: float) -> float:
            return fixed + max(0.0, p * rnd - w)

        return {
            "p50": q(0.5),
            "p99": q(0.99),
            "mean": fixed + (rnd - w) ** 2 / (2 * rnd),
            "wait_max": rnd - w,
        }
    interval = rnd / 2 if peer_idle else rnd
    return {
        "p50": fixed + 0.5 * interval,
        "p99": fixed + 0.99 * interval,
        "mean": fixed + 0.5 * interval,
        "wait_max": interval,
    }
