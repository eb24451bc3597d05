"""One radio of the air model: what it runs with and the state it keeps.

Theory of operation
-------------------
:class:`RadioConfig` is a radio's active parameters after boot (what both ends must
share to hear each other, what seeds its hopping sequence, its TDM timing).
:class:`RadioState` is everything one radio holds while the model runs: its serial
wire and buffers, the packetiser's pending frame, its TDM state and link quality.
:class:`Packet` is one transmission on the air. Nothing here moves time: the
serial side (:mod:`radios.air.serial`), the packetiser
(:mod:`radios.air.packetiser`) and the model (:mod:`radios.air.model`) change
these fields.
"""

from __future__ import annotations

import binascii
import math
import random
from collections import deque
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Protocol

from radios.sik.timing import TdmTiming, tdm_timing

TX, SILENCE1, RX, SILENCE2 = 0, 1, 2, 3
BROADCAST = 0xFFFF
PREAMBLE_BYTES = 8  # preamble_length 16 nibbles
INJECT_MAX = 32  # remote AT replies travel in packets of at most 32 bytes
RADIO_STATUS_SYSID = 51  # '3'
RADIO_STATUS_COMPID = 68  # 'D'


@dataclass(frozen=True)
class RadioConfig:
    """What a radio runs with (its active parameters after boot)."""

    netid: int = 25
    air_kbps: int = 64
    serial_baud: int = 57600
    ecc: bool = False
    mavlink: int = 1  # 0 raw, 1 (and 2) MAVLink framing
    max_window_ms: int = 131
    num_channels: int = 50
    min_freq: int = 915000
    max_freq: int = 928000
    txpower_dbm: int = 20
    firmware: str = "standard"  # or "multipoint"
    node_id: int = 0  # multipoint NODEID
    node_destination: int = BROADCAST
    node_count: int = 2
    in_buf: int = 1850
    out_buf: int = 645
    key: bytes = b""  # the AES key it runs with (AES builds, ENCRYPTION_LEVEL > 0)

    @cached_property
    def hop(self) -> int:
        """What seeds the channel shuffle (freq_hopping.c shuffleRand): the NETID, or a
        CRC-16 of the 32-byte key when encryption is on (worked out once: the air model
        asks it per receiver)."""
        if not self.key:
            return self.netid
        return binascii.crc_hqx((self.key + bytes(32))[:32], 0)

    @cached_property
    def air_key(self) -> tuple[int, int, bool, int, int, int, str]:
        """The settings of :meth:`compatible`: two radios hear each other when theirs are equal."""
        return (
            self.netid,
            self.air_kbps,
            self.ecc,
            self.min_freq,
            self.max_freq,
            self.num_channels,
            self.firmware,
        )

    @property
    def multipoint_base(self) -> bool:
        """The multipoint network's base (node 0): it sends the sync every node follows."""
        return self.firmware == "multipoint" and self.node_id == 0

    def compatible(self, other: RadioConfig) -> bool:
        """Both ends must match on these to hear each other (ArduPilot's SiK radio
        documentation: NETID, air speed, ECC, the band and its channels, and the
        firmware: a 1.9 radio does not hear a 2.0 one)."""
        return self.air_key == other.air_key

    def timing(self) -> TdmTiming:
        mw = None if self.firmware == "multipoint" else self.max_window_ms
        return tdm_timing(self.air_kbps, ecc=self.ecc, max_window_ms=mw, num_channels=self.num_channels)


class LossModel(Protocol):
    def lost(self, sender: int, receiver: int, t: float, rng: random.Random) -> bool: ...


class ATHandler(Protocol):
    """What the model needs of a radio's AT command interpreter (radios.sik.at)."""

    @property
    def in_command_mode(self) -> bool: ...

    def feed(self, data: bytes, now: float) -> Any: ...

    def poll(self, now: float) -> Any: ...

    def next_deadline(self) -> float | None: ...

    def run_remote(self, command: str) -> Any: ...


@dataclass
class Packet:
    sender: int
    payload: bytes
    window: int  # ticks left in the sender's state after this packet (0: stats packet)
    bonus: bool
    command: bool
    dest: int
    t_start: float
    t_end: float
    kind: str  # "data", "yield", "stats", "command", "sync"


@dataclass
class RadioStats:
    tx_packets: int = 0
    tx_bytes: int = 0  # user payload bytes put on air
    tx_airtime_s: float = 0.0
    rx_packets: int = 0
    rx_bytes: int = 0  # user payload bytes written to the serial output
    rx_errors: int = 0  # packets heard but corrupted (collision, noise)
    collisions: int = 0
    lost: int = 0  # packets dropped by a loss model
    srx: int = 0  # serial input overflow: bytes dropped
    stx: int = 0  # serial output overflow: bytes truncated
    serial_in: int = 0
    serial_out: int = 0
    radio_status: int = 0

    def as_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


class RadioState:
    """State of one radio. Manipulated only by the air model (:mod:`radios.air`)."""

    def __init__(
        self, index: int, cfg: RadioConfig, at: ATHandler | None, rng: random.Random, now: float
    ) -> None:
        self.index = index
        self.at = at
        self.stats = RadioStats()
        # serial input: chunks in flight on the wire (start, end, data)
        self.wire: deque[tuple[float, float, bytes]] = deque()
        self.wire_free_at = now
        self.inbuf = bytearray()
        # serial output: bytes in the radio's buffer, then bytes handed to the host
        self.outbuf = bytearray()
        self.drain_clock = now  # when the last byte handed to the host left
        self.drain_base = now  # the output line's busy spell began here...
        self.drained = 0  # ...and has carried this many bytes since
        self.host_ready = bytearray()
        # packetiser
        self.mav_pending = 0  # 0 none, 1 waiting for the header, else frame length
        self.mav_start = 0.0
        self.mav_max_time = 0.0
        self.injected = bytearray()  # remote AT reply waiting to be sent
        self.inject_packets: deque[bytes] = deque()  # multipoint RTI5: one line per packet
        self.remote_cmd: str | None = None
        self.rs_seq = 0
        self.rs_pending = False
        # link state
        self.locked = False
        self.last_rx = -math.inf
        self.avg_rssi = 0
        self.avg_noise = 40
        self.remote_rssi = 0
        self.remote_noise = 0
        self.send_statistics = False
        self.unlock_count = 0
        self.receive_count = 0
        self.configure(cfg, rng, now)

    def configure(self, cfg: RadioConfig, rng: random.Random, now: float) -> None:
        self.cfg = cfg
        self.t = cfg.timing()
        self.byte_s = 10.0 / cfg.serial_baud
        # a new serial rate starts a new busy spell where the old one stands
        self.drain_base = self.drain_clock
        self.drained = 0
        self.tx_until = now
        self.wait_until = now
        self.bonus = False
        self.yielded = False
        self.version = getattr(self, "version", 0) + 1
        self.state = TX
        # a radio boots at an arbitrary phase of its own TDM cycle
        self.state_end = now + rng.uniform(0.0, self.t.window_s)
        self.locked = cfg.num_channels <= 1
        self.mav_pending = 0
        self.wake_at = -1.0
        self.mp_synced_until = -1.0
        self.stalled_at: float | None = None
