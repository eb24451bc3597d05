"""The air: a network of SiK radios as a pure discrete-event model.

Theory of operation
-------------------
This module owns everything between the serial pins of N radios: serial pacing,
the radios' buffers, the MAVLink-aware packetiser, the TDM medium access, the
channel (one transmission at a time, collisions, half duplex, NETID, loss) and
RADIO_STATUS injection. It does no I/O and reads no clock: the caller feeds bytes
with :meth:`AirModel.host_write` at a time ``now``, moves time forward with
:meth:`AirModel.advance`, collects each radio's serial output with
:meth:`AirModel.take_output`, and sleeps until :meth:`AirModel.next_deadline`.
The pty emulator (:mod:`radios.emulator`) drives it in real time; the swarm's
deterministic simulator drives the very same model in virtual time.

Each radio runs the firmware's loop, reduced to the moments where it can act:

* TDM (tdm.c): TRANSMIT(W) -> SILENCE(S) -> RECEIVE(W) -> SILENCE(S). Whenever a
  radio may transmit (its own window, or the peer's window when the peer yielded
  it "bonus" ticks) it sends one packet at once: user data, a statistics packet
  twice a second, or a zero-length packet that yields the rest of the window.
  Every packet's 2-byte trailer says how many ticks its sender has left, and the
  receiver re-synchronises its own state to it (``sync_tx_windows``). Two radios
  thus form the standard pair; three or more standard radios on one NETID each
  sync to whatever they heard last and collide, as the real firmware does.
* Multipoint firmware: node ids own windows in turn (NODECOUNT slots of W+S),
  packets carry a destination (0xFFFF broadcast); idle nodes stay silent except
  the base (node 0) whose packet keeps the network in sync. No bonus ticks.
* Packetiser (packet.c): with MAVLINK framing it waits for a whole frame (but no
  longer than the frame's serial time), packs as many whole frames as fit, sends
  non-MAVLink bytes as they come, and splits frames too large for one packet.
* Channel: a packet occupies the air for flight(n) = L + n·tpb ticks; a receiver
  hears it only if it has the same NETID and air settings, is not transmitting
  itself meanwhile, no other audible packet overlaps it (collision), it is locked
  to the hopping sequence (an unlocked radio is on the right channel with
  probability 1/NUM_CHANNELS per packet) and no loss model drops it.
* Serial side: bytes from the host reach the radio at the serial rate and are
  dropped when the 1850-byte input buffer is full (``srx``); received data leaves
  at the serial rate through a 645-byte output buffer, truncated when full
  (``stx``). A HEARTBEAT sent from the host makes the radio inject RADIO_STATUS
  (rssi, remrssi, txbuf % free, noise, remnoise, rxerrors) into its serial output.

AES builds (``RadioConfig.key`` not empty; tdm.c, packet.c, freq_hopping.c): the
hopping sequence is seeded by a CRC-16 of the key instead of the NETID, so a radio
with another key (or none) shares a channel with this one only by chance: it hears
a packet with probability 1/NUM_CHANNELS and never locks. Data and injected replies
are encrypted: a receiver with another key writes garbage of the same length to its
host. ``RT`` commands travel in clear and any radio that hears one runs it, key or
no key. Packets carry at most 31 bytes of data (packet_get_next) and need 16 more
bytes of window.

Not modelled (documented simplifications): duty cycle and LBT, temperature, the
per-channel frequency plan (NETIDs never interfere), opportunistic resend (off
since 2.0), CTS unless ``flow_control`` is set by the caller.
"""

from __future__ import annotations

import binascii
import heapq
import math
import random
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from radios.loss import RangeLoss, dbm_to_rssi
from radios.mavlink import MSG_RADIO_STATUS, STX_V1, STX_V2, frame_length, pack_frame
from radios.sik.timing import STATS_LEN, TICK_S, TRAILER_LEN, TdmTiming, max_xmit, tdm_timing

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

    def hop_seed(self) -> int:
        """What seeds the channel shuffle (freq_hopping.c shuffleRand): the NETID, or a
        CRC-16 of the 32-byte key when encryption is on."""
        if not self.key:
            return self.netid
        return binascii.crc_hqx((self.key + bytes(32))[:32], 0)

    def compatible(self, other: RadioConfig) -> bool:
        """Both ends must match on these to hear each other (reference/sik.md)."""
        return (
            self.netid == other.netid
            and self.air_kbps == other.air_kbps
            and self.ecc == other.ecc
            and self.min_freq == other.min_freq
            and self.max_freq == other.max_freq
            and self.num_channels == other.num_channels
            and self.firmware == other.firmware
        )

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


class _Radio:
    """State of one radio. Manipulated only by :class:`AirModel`."""

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
        self.drain_clock = now
        self.host_ready = bytearray()
        # packetiser
        self.mav_pending = 0  # 0 none, 1 waiting for the header, else frame length
        self.mav_start = 0.0
        self.mav_max_time = 0.0
        self.injected = bytearray()  # remote AT reply waiting to be sent
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
        self.cts_stopped = False


class AirModel:
    """N SiK radios sharing the air. See the module docstring.

    ``on_air(sender, payload, t_start, t_end, kind)`` is called for every packet put
    on air (user data packets carry the bytes the host wrote).
    """

    def __init__(
        self,
        configs: list[RadioConfig],
        *,
        seed: int = 0,
        losses: list[LossModel] | None = None,
        start: float = 0.0,
        at_factory: Callable[[int, RadioConfig], ATHandler | None] | None = None,
        on_reboot: Callable[[int], RadioConfig] | None = None,
        on_air: Callable[[int, bytes, float, float, str], None] | None = None,
        flow_control: bool = False,
        rssi_base: int = 190,
    ) -> None:
        self.rng = random.Random(seed)
        self.now = start
        self.start = start
        self.losses = list(losses or [])
        self.on_reboot = on_reboot
        self.on_air = on_air
        self.flow_control = flow_control
        self.rssi_base = rssi_base
        self._events: list[tuple[float, int, int, int, Any]] = []
        self._seq = 0
        self.radios: list[_Radio] = []
        for i, cfg in enumerate(configs):
            at = at_factory(i, cfg) if at_factory else None
            self.radios.append(_Radio(i, cfg, at, self.rng, start))
        self._airing: list[Packet] = []  # packets on air or recently ended
        self.busy_s = 0.0  # total time the channel carried at least one packet
        self._busy_until = start
        for r in self.radios:
            self._schedule_state_end(r)
            self._push(start + 0.5 * self.rng.random(), _LINK_UPDATE, r.index, None)

    # ------------------------------------------------------------------ API
    def host_write(self, node: int, data: bytes, now: float) -> None:
        """Bytes the host wrote to ``node``'s serial port at ``now``; they reach the
        radio at the serial rate."""
        if not data:
            return
        r = self.radios[node]
        start = max(now, r.wire_free_at)
        end = start + len(data) * r.byte_s
        r.wire.append((start, end, bytes(data)))
        r.wire_free_at = end
        r.stats.serial_in += len(data)
        self._push(end, _SERIAL_IN, node, None)

    def serial_backlog_s(self, node: int, now: float) -> float:
        """How long the bytes already written take to reach the radio (infinite
        while flow control holds the line)."""
        r = self.radios[node]
        if r.stalled_at is not None:
            return math.inf
        return max(0.0, r.wire_free_at - now)

    def input_room(self, node: int) -> int:
        """Free bytes in the radio's serial input buffer (for CTS flow control)."""
        r = self.radios[node]
        return r.cfg.in_buf - len(r.inbuf)

    def cts_clear(self, node: int) -> bool:
        """The radio's CTS line: asserted (stop) with fewer than 17 bytes free,
        released above 34. Hosts honour it only with flow control."""
        room = self.input_room(node)
        r = self.radios[node]
        stopped = r.cts_stopped
        if stopped and room > 34:
            stopped = False
        elif not stopped and room < 17:
            stopped = True
        r.cts_stopped = stopped
        return not stopped

    def advance(self, now: float) -> None:
        """Run every event up to ``now``."""
        ev = self._events
        while ev and ev[0][0] <= now:
            t, _, kind, node, data = heapq.heappop(ev)
            self.now = max(self.now, t)
            _HANDLERS[kind](self, self.radios[node], t, data)
        self.now = max(self.now, now)
        for r in self.radios:
            # serial output keeps flowing whether or not the host reads it
            if r.outbuf:
                self._drain(r, now)

    def take_output(self, node: int, now: float) -> bytes:
        """Bytes the radio has written to its serial output by ``now``."""
        r = self.radios[node]
        if r.outbuf:
            self._drain(r, now)
        if not r.host_ready:
            return b""
        out = bytes(r.host_ready)
        r.host_ready.clear()
        r.stats.serial_out += len(out)
        return out

    def next_deadline(self) -> float | None:
        """When :meth:`advance` next has work (output draining included)."""
        t = self._events[0][0] if self._events else None
        for r in self.radios:
            if r.outbuf:
                # wake when the buffer is drained, or after 5 ms of output at most
                d = r.drain_clock + min(len(r.outbuf) * r.byte_s, 0.005)
                t = d if t is None or d < t else t
        return t

    def utilisation(self, now: float | None = None) -> float:
        """Share of elapsed time the channel carried at least one packet."""
        end = self.now if now is None else now
        span = end - self.start
        return self.busy_s / span if span > 0 else 0.0

    def round_s(self, node: int = 0) -> float:
        r = self.radios[node]
        slots = r.cfg.node_count if r.cfg.firmware == "multipoint" else 2
        return r.t.round_s(slots)

    def status(self, node: int) -> dict[str, Any]:
        r = self.radios[node]
        return {
            "rssi": r.avg_rssi,
            "remrssi": r.remote_rssi,
            "noise": r.avg_noise,
            "remnoise": r.remote_noise,
            "txbuf": self._txbuf(r),
            "locked": r.locked,
            **r.stats.as_dict(),
        }

    def reconfigure(self, node: int, cfg: RadioConfig, now: float) -> None:
        r = self.radios[node]
        r.configure(cfg, self.rng, now)
        self._schedule_state_end(r)

    def ati6(self, node: int) -> str:
        t = self.radios[node].t
        return (
            f"silence_period: {t.silence_period}\r\ntx_window_width: {t.tx_window_width}\r\n"
            f"max_data_packet_length: {t.max_data_packet_length}\r\n"
        )

    def ati7(self, node: int) -> str:
        r = self.radios[node]
        s = r.stats
        return (
            f"L/R RSSI: {r.avg_rssi}/{r.remote_rssi}  L/R noise: {r.avg_noise}/{r.remote_noise} "
            f"pkts: {r.receive_count}  txe=0 rxe={s.rx_errors} stx={s.stx} srx={s.srx} "
            f"ecc=0/0 temp=25 dco=0\r\n"
        )

    # ------------------------------------------------------------ internals
    def _push(self, t: float, kind: int, node: int, data: Any) -> None:
        self._seq += 1
        heapq.heappush(self._events, (t, self._seq, kind, node, data))

    def _schedule_state_end(self, r: _Radio) -> None:
        r.version += 1
        self._push(r.state_end, _STATE_END, r.index, r.version)

    # serial side ------------------------------------------------------------
    def _pull_serial(self, r: _Radio, t: float) -> None:
        """Move the bytes that have crossed the serial line by ``t`` into the radio.

        With flow control, a full input buffer stalls the line (the host honours
        CTS) instead of dropping bytes; :meth:`_unstall` restarts it."""
        if r.stalled_at is not None:
            self._unstall(r, t)
            if r.stalled_at is not None:
                return
        while r.wire:
            start, end, data = r.wire[0]
            if end <= t + 1e-12:
                k = len(data)
            elif start < t:
                k = int((t - start) / r.byte_s)
                if k <= 0:
                    break
            else:
                break
            if self.flow_control and (r.at is None or not r.at.in_command_mode):
                room = r.cfg.in_buf - len(r.inbuf)
                if room < k:
                    k = max(room, 0)
                    if k == 0:
                        r.stalled_at = start
                        break
            arrive = start + k * r.byte_s
            if k < len(data):
                r.wire[0] = (arrive, end, data[k:])
            else:
                r.wire.popleft()
            self._serial_arrive(r, data[:k], min(arrive, t))
            if r.wire and r.wire[0][0] < t and self.flow_control and r.cfg.in_buf - len(r.inbuf) <= 0:
                r.stalled_at = r.wire[0][0]
                break

    def _unstall(self, r: _Radio, t: float) -> None:
        """Resume a stalled serial line once the radio has room again."""
        assert r.stalled_at is not None
        if r.cfg.in_buf - len(r.inbuf) <= 34:  # CTS released above 34 free bytes
            return
        delta = max(0.0, t - r.stalled_at)
        r.stalled_at = None
        if delta > 0:
            r.wire = deque((s0 + delta, e0 + delta, d) for s0, e0, d in r.wire)
            r.wire_free_at += delta
        if r.wire:
            self._push(r.wire[0][1], _SERIAL_IN, r.index, None)

    def _serial_arrive(self, r: _Radio, data: bytes, t: float) -> None:
        if r.at is not None:
            out = r.at.feed(data, t)
            self._at_output(r, out, t)
        else:
            self._inbuf_add(r, data)

    def _inbuf_add(self, r: _Radio, data: bytes) -> None:
        room = r.cfg.in_buf - len(r.inbuf)
        if len(data) > room:
            r.stats.srx += len(data) - max(room, 0)
            data = data[: max(room, 0)]
        r.inbuf += data

    def _at_output(self, r: _Radio, out: Any, t: float) -> None:
        if out is None:
            return
        if out.to_air:
            self._inbuf_add(r, out.to_air)
        if out.to_host:
            self._output(r, out.to_host, t)
        if out.remote_command:
            r.remote_cmd = out.remote_command
        if out.reboot and self.on_reboot is not None:
            self.reconfigure(r.index, self.on_reboot(r.index), t)
        dl = r.at.next_deadline() if r.at is not None else None
        if dl is not None:
            self._push(max(dl, t), _AT_POLL, r.index, None)

    def _output(self, r: _Radio, data: bytes, t: float) -> None:
        self._drain(r, t)
        room = r.cfg.out_buf - len(r.outbuf)
        if len(data) > room:
            r.stats.stx += len(data) - max(room, 0)
            data = data[: max(room, 0)]
        r.outbuf += data

    def _drain(self, r: _Radio, t: float) -> None:
        """Move the bytes the serial line has carried by ``t`` to the host side.
        ``drain_clock`` is when the last byte moved finished."""
        if not r.outbuf:
            if r.drain_clock < t:
                r.drain_clock = t
            return
        k = int((t - r.drain_clock) / r.byte_s + 1e-9)
        if k <= 0:
            return
        k = min(k, len(r.outbuf))
        r.host_ready += r.outbuf[:k]
        del r.outbuf[:k]
        r.drain_clock += k * r.byte_s

    def _txbuf(self, r: _Radio) -> int:
        free = r.cfg.in_buf - len(r.inbuf)
        return (100 * (free // 8)) // (r.cfg.in_buf // 8)

    # packetiser (packet.c) ----------------------------------------------------
    def _packet_get_next(self, r: _Radio, mx: int, t: float) -> tuple[bytes, bool]:
        if r.cfg.key:
            # packet.c: encrypted packets are at most 32 bytes of cipher text
            mx = 0 if mx <= 16 else 15 if mx <= 32 else 31
        if r.injected and mx > 0:
            n = min(mx, INJECT_MAX)
            chunk = bytes(r.injected[:n])
            del r.injected[:n]
            return chunk, True
        buf = r.inbuf
        if not buf or mx <= 0:
            return b"", False
        if r.cfg.mavlink == 0:
            chunk = bytes(buf[:mx])
            del buf[:mx]
            return chunk, False
        slen = min(len(buf), mx)
        if r.mav_pending == 1:
            hdr = 3 if buf[0] == STX_V2 else 2
            if len(buf) < hdr:
                if t - r.mav_start > r.mav_max_time:
                    chunk = bytes(buf[:slen])
                    del buf[:slen]
                    r.mav_pending = 0
                    return chunk, False
                return b"", False
            r.mav_pending = 0
        if r.mav_pending:
            if slen < r.mav_pending:
                if t - r.mav_start > r.mav_max_time:
                    chunk = bytes(buf[:slen])
                    del buf[:slen]
                    r.mav_pending = 0
                    return chunk, False
                return b"", False
            return self._mavlink_frames(r, mx), False
        i = 0
        while i < slen:
            c = buf[i]
            if c in (STX_V2, STX_V1):
                hdr = 3 if c == STX_V2 else 2
                if len(buf) - i < hdr:
                    if i == 0:
                        r.mav_pending = 1
                        r.mav_start = t
                        r.mav_max_time = r.byte_s * hdr
                        return b"", False
                    break
                if buf[i + 1] + 25 > r.t.mav_max_xmit:
                    i += 1  # too big to frame: its bytes go as they come
                    continue
                flen = frame_length(buf, i) or 0
                if i > 0:
                    chunk = bytes(buf[:i])
                    del buf[:i]
                    r.mav_pending = flen
                    r.mav_start = t
                    r.mav_max_time = flen * r.byte_s
                    return chunk, False
                if flen > len(buf) or flen > mx:
                    r.mav_pending = flen
                    r.mav_start = t
                    r.mav_max_time = flen * r.byte_s
                    return b"", False
                return self._mavlink_frames(r, mx), False
            i += 1
        chunk = bytes(buf[:i])
        del buf[:i]
        return chunk, False

    def _mavlink_frames(self, r: _Radio, mx: int) -> bytes:
        buf = r.inbuf
        first = frame_length(buf, 0) or len(buf)
        used = first
        self._check_heartbeat(r, buf, 0)
        while len(buf) - used >= 8:
            c = buf[used]
            if c != STX_V2 and c != STX_V1:
                break
            flen = frame_length(buf, used)
            if flen is None or buf[used + 1] + 25 > r.t.mav_max_xmit:
                break
            if flen > mx - used or flen > len(buf) - used:
                break
            self._check_heartbeat(r, buf, used)
            used += flen
        chunk = bytes(buf[:used])
        del buf[:used]
        r.mav_pending = 0
        return chunk

    def _check_heartbeat(self, r: _Radio, buf: bytearray, i: int) -> None:
        """packet.c's check_heartbeat: one flag, so one report per main-loop pass
        however many heartbeats a packet carried."""
        version = 0
        if buf[i] == STX_V2:
            if (
                len(buf) - i >= 10
                and buf[i + 1] <= 9
                and buf[i + 7] == 0
                and buf[i + 8] == 0
                and buf[i + 9] == 0
            ):
                version = 2
        elif buf[i] == STX_V1 and len(buf) - i >= 6 and buf[i + 1] == 9 and buf[i + 5] == 0:
            version = 1
        if version and not r.rs_pending:
            r.rs_pending = True
            self._push(self.now, _RADIO_STATUS, r.index, version)

    # TDM ---------------------------------------------------------------------
    def _audible_busy_until(self, r: _Radio, t: float) -> float | None:
        """End of a packet whose preamble ``r`` has detected by ``t``. Detecting a
        preamble takes PREAMBLE_BYTES byte times, so radios that start within that
        time of each other do not see each other and collide."""
        end = None
        detect = PREAMBLE_BYTES * r.t.ticks_per_byte * TICK_S
        for p in self._airing:
            if (
                p.sender != r.index
                and p.t_start + detect <= t < p.t_end
                and self.radios[p.sender].cfg.compatible(r.cfg)
            ):
                end = p.t_end if end is None else max(end, p.t_end)
        return end

    def _mp_slot(self, r: _Radio, t: float) -> tuple[bool, float, float]:
        """Multipoint: (inside own transmit window, end of that window, start of the
        next own window). Computed on whole ticks so that waking at an edge always
        lands inside the window."""
        w = r.t.tx_window_width
        slot = w + r.t.silence_period
        count = max(r.cfg.node_count, 1)
        rnd = slot * count
        now_tick = math.floor((t - self.start) / TICK_S + 1e-6)
        mine = now_tick - now_tick % rnd + (r.cfg.node_id % count) * slot
        if mine <= now_tick < mine + w:
            return True, self.start + (mine + w) * TICK_S, self.start + (mine + rnd) * TICK_S
        nxt = mine if now_tick < mine else mine + rnd
        return False, self.start + nxt * TICK_S, self.start + nxt * TICK_S

    def _wake_at(self, r: _Radio, t: float) -> None:
        if r.wake_at != t:
            r.wake_at = t
            self._push(t, _WAKE, r.index, None)

    def _try_tx(self, r: _Radio, t: float) -> None:
        if r.tx_until > t + 1e-12:
            return
        mp = r.cfg.firmware == "multipoint"
        if mp:
            mine, end, next_start = self._mp_slot(r, t)
            if not mine:
                self._wake_at(r, next_start)
                return
            in_rx = False
        else:
            if not (r.state == TX or (r.bonus and r.state == RX)):
                return
            if r.yielded:
                return
            end = r.state_end
            in_rx = r.state == RX
            next_start = r.state_end
        if r.wait_until > t + 1e-12:
            self._wake_at(r, r.wait_until)
            return
        busy = self._audible_busy_until(r, t)
        if busy is not None:
            # a preamble is on the air: hold off for a packet latency
            r.wait_until = busy + r.t.packet_latency * TICK_S
            self._wake_at(r, r.wait_until)
            return
        remaining = int((end - t) / TICK_S)
        mx = max_xmit(r.t, remaining)
        if r.cfg.key:
            mx = mx - 16 if mx >= 16 else 0  # tdm.c: room for the cipher's padding
        if mx <= 0:
            if mp:
                self._wake_at(r, next_start)
            return
        self._pull_serial(r, t)
        command = False
        kind = "data"
        if r.remote_cmd is not None and mx >= len(r.remote_cmd):
            payload = r.remote_cmd.encode("ascii", "replace")
            r.remote_cmd = None
            command = True
            kind = "command"
        else:
            payload, command = self._packet_get_next(r, mx, t)
            if command:
                kind = "command"
            if r.stalled_at is not None:
                self._pull_serial(r, t)
        window = remaining - r.t.flight_ticks(len(payload) + TRAILER_LEN)
        if not payload:
            if not in_rx and r.send_statistics and mx >= STATS_LEN:
                r.send_statistics = False
                payload = struct.pack("<BBH", r.avg_rssi, r.avg_noise, r.receive_count & 0xFFFF)
                window = 0
                kind = "stats"
            elif mp:
                # multipoint: only the base speaks when idle, once per own window
                if r.cfg.node_id != 0 or r.mp_synced_until >= end:
                    self._wake_at(r, next_start)
                    return
                r.mp_synced_until = end
                kind = "sync"
            else:
                r.yielded = True
                kind = "yield"
        if window < 0:
            window = 0 if kind == "stats" else 1
        flight = r.t.flight_ticks(len(payload) + TRAILER_LEN) * TICK_S
        pkt = Packet(
            r.index,
            payload,
            min(window, 0x1FFF),
            in_rx,
            command,
            r.cfg.node_destination if mp else BROADCAST,
            t,
            t + flight,
            kind,
        )
        r.tx_until = t + flight
        st = r.stats
        st.tx_packets += 1
        st.tx_airtime_s += flight
        if kind == "data":
            st.tx_bytes += len(payload)
        self._airing.append(pkt)
        if t + flight > self._busy_until:
            self.busy_s += t + flight - max(t, self._busy_until)
            self._busy_until = t + flight
        if self.on_air is not None:
            self.on_air(r.index, payload, t, t + flight, kind)
        self._push(t + flight, _TX_END, r.index, pkt)

    def _sync(self, r: _Radio, pkt: Packet, t: float) -> None:
        """sync_tx_windows() of tdm.c."""
        window_s = pkt.window * TICK_S
        if pkt.bonus:
            if r.state == SILENCE1:
                r.state_end = t + r.t.silence_s
            elif r.state in (RX, SILENCE2):
                r.state = SILENCE2
                r.state_end = t + TICK_S
            else:
                r.state = TX
                r.state_end = t + window_s
        else:
            r.state = RX
            r.state_end = t + window_s
        r.bonus = r.state == RX and len(pkt.payload) == 0
        if r.state != TX:
            r.yielded = False
        self._schedule_state_end(r)

    def _receive(self, r: _Radio, pkt: Packet, t: float) -> None:
        sender = self.radios[pkt.sender]
        if not r.cfg.compatible(sender.cfg):
            return
        seed = r.cfg.hop_seed()
        for other in self._airing:
            if other is pkt or not (other.t_start < pkt.t_end and pkt.t_start < other.t_end):
                continue
            if other.sender == r.index:
                return  # half duplex: it was transmitting and heard nothing
            ocfg = self.radios[other.sender].cfg
            if ocfg.compatible(r.cfg) and ocfg.hop_seed() == seed:
                r.stats.collisions += 1
                r.stats.rx_errors += 1
                return
        if sender.cfg.hop_seed() != seed:
            # another hopping sequence (AES key): on our channel only by chance
            if self.rng.random() >= 1.0 / max(r.cfg.num_channels, 1):
                return
        elif not r.locked:
            # the multipoint base sends its sync on a fixed channel: heard at once
            base = r.cfg.firmware == "multipoint" and sender.cfg.node_id == 0
            if not base and self.rng.random() >= 1.0 / max(r.cfg.num_channels, 1):
                return
            # r now follows the sender's TDM and hop sequence: they are in step
            r.locked = True
            sender.locked = True
        for model in self.losses:
            if model.lost(pkt.sender, r.index, t, self.rng):
                r.stats.lost += 1
                r.stats.rx_errors += 1
                return
        r.last_rx = t
        r.unlock_count = 0
        r.receive_count += 1
        r.avg_rssi = (self._rssi(pkt.sender, r.index, t) + 7 * r.avg_rssi) // 8
        mp = r.cfg.firmware == "multipoint"
        if pkt.window == 0 and pkt.payload and pkt.kind == "stats":
            rssi, noise, _count = struct.unpack("<BBH", pkt.payload[:4])
            r.remote_rssi, r.remote_noise = rssi, noise
            r.receive_count -= 1
            return
        if not mp:
            self._sync(r, pkt, t)
        if (
            sender.cfg.key != r.cfg.key
            and pkt.payload
            and not (pkt.command and pkt.payload.startswith(b"RT"))
        ):
            # encrypted with another key (or not at all): decrypts to garbage
            pkt = Packet(
                pkt.sender,
                self.rng.randbytes(len(pkt.payload)),
                pkt.window,
                pkt.bonus,
                pkt.command,
                pkt.dest,
                pkt.t_start,
                pkt.t_end,
                pkt.kind,
            )
        if pkt.command:
            self._remote_at(r, pkt, t)
        elif pkt.payload and (not mp or pkt.dest in (BROADCAST, r.cfg.node_id)):
            if r.at is None or not r.at.in_command_mode:
                r.stats.rx_packets += 1
                r.stats.rx_bytes += len(pkt.payload)
                self._output(r, pkt.payload, t)
        if not mp:
            self._try_tx(r, t)

    def _remote_at(self, r: _Radio, pkt: Packet, t: float) -> None:
        text = pkt.payload.decode("ascii", "replace")
        if not text.startswith("RT") or r.at is None:
            self._output(r, pkt.payload, t)  # a reply: print it
            return
        if r.cfg.firmware == "multipoint" and "," in text:
            cmd, _, target = text.partition(",")
            if target.strip().isdigit() and int(target) != r.cfg.node_id:
                return
            text = cmd
        res = r.at.run_remote(text)
        reply = getattr(res, "output", res)
        if isinstance(reply, str):
            reply = reply.encode()
        if reply:
            if r.cfg.firmware == "multipoint":
                reply = f"[{r.cfg.node_id}] ".encode() + reply
            r.injected += reply[:252]
        if getattr(res, "reboot", False) and self.on_reboot is not None:
            self.reconfigure(r.index, self.on_reboot(r.index), t)

    def _rssi(self, sender: int, receiver: int, t: float) -> int:
        for m in self.losses:
            if isinstance(m, RangeLoss):
                dbm = m.rx_dbm(sender, receiver, t)
                if dbm is not None:
                    return dbm_to_rssi(dbm + self.rng.gauss(0.0, 1.0))
        return max(0, min(255, int(self.rssi_base + self.rng.gauss(0.0, 3.0))))

    # event handlers ----------------------------------------------------------
    def _on_state_end(self, r: _Radio, t: float, version: Any) -> None:
        if version != r.version:
            return
        if r.cfg.firmware == "multipoint":
            self._try_tx(r, t)
            return
        r.state = (r.state + 1) % 4
        dur = r.t.window_s if r.state in (TX, RX) else r.t.silence_s
        r.state_end = t + dur
        r.bonus = False
        r.yielded = False
        r.wait_until = t
        self._schedule_state_end(r)
        self._try_tx(r, t)

    def _on_tx_end(self, r: _Radio, t: float, pkt: Any) -> None:
        for other in self.radios:
            if other is not r:
                self._receive(other, pkt, t)
        # forget packets that can no longer overlap anything
        horizon = t - 0.5
        self._airing = [p for p in self._airing if p.t_end > horizon]
        self._try_tx(r, t)

    def _on_wake(self, r: _Radio, t: float, _data: Any) -> None:
        if r.wake_at == t:
            r.wake_at = -1.0
        self._try_tx(r, t)

    def _on_serial_in(self, r: _Radio, t: float, _data: Any) -> None:
        self._pull_serial(r, t)
        if r.cfg.firmware == "multipoint":
            self._try_tx(r, t)

    def _on_at_poll(self, r: _Radio, t: float, _data: Any) -> None:
        if r.at is None:
            return
        dl = r.at.next_deadline()
        if dl is None or dl > t + 1e-9:
            if dl is not None:
                self._push(dl, _AT_POLL, r.index, None)
            return
        self._at_output(r, r.at.poll(t), t)

    def _on_radio_status(self, r: _Radio, t: float, version: Any) -> None:
        r.rs_pending = False
        if r.cfg.mavlink == 0 or (r.at is not None and r.at.in_command_mode):
            return
        self._pull_serial(r, t)
        payload = struct.pack(
            "<HHBBBBB",
            min(r.stats.rx_errors, 0xFFFF),
            0,
            r.avg_rssi,
            r.remote_rssi,
            self._txbuf(r),
            r.avg_noise,
            r.remote_noise,
        )
        frame = pack_frame(
            MSG_RADIO_STATUS,
            payload,
            sysid=RADIO_STATUS_SYSID,
            compid=RADIO_STATUS_COMPID,
            seq=r.rs_seq,
            version=int(version),
        )
        self._drain(r, t)
        if r.cfg.out_buf - len(r.outbuf) < len(frame):
            return  # no room: the firmware skips the report
        r.rs_seq = (r.rs_seq + 1) & 0xFF
        r.stats.radio_status += 1
        self._output(r, frame, t)

    def _on_link_update(self, r: _Radio, t: float, _data: Any) -> None:
        """link_update() of tdm.c, every 0.5 s."""
        if t - r.last_rx > 0.5:
            r.unlock_count += 1
        if r.unlock_count > 40 and r.cfg.num_channels > 1:
            r.locked = False
            r.unlock_count = 5
        if r.unlock_count > 5:
            r.remote_rssi = r.remote_noise = 0
        r.avg_noise = (max(0, int(40 + self.rng.gauss(0.0, 2.0))) + 3 * r.avg_noise) // 4
        r.send_statistics = True
        self._push(t + 0.5, _LINK_UPDATE, r.index, None)


_STATE_END, _TX_END, _WAKE, _SERIAL_IN, _AT_POLL, _RADIO_STATUS, _LINK_UPDATE = range(7)
_HANDLERS: dict[int, Callable[[AirModel, _Radio, float, Any], None]] = {
    _STATE_END: AirModel._on_state_end,
    _TX_END: AirModel._on_tx_end,
    _WAKE: AirModel._on_wake,
    _SERIAL_IN: AirModel._on_serial_in,
    _AT_POLL: AirModel._on_at_poll,
    _RADIO_STATUS: AirModel._on_radio_status,
    _LINK_UPDATE: AirModel._on_link_update,
}


@dataclass
class ModelSummary:
    utilisation: float
    round_s: float
    radios: list[dict[str, Any]] = field(default_factory=list)
