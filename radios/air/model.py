"""The air model: N radios, one channel, one event queue (see :mod:`radios.air`).

Theory of operation
-------------------
:class:`AirModel` owns the radios' states (:class:`~radios.air.radio.RadioState`),
the packets on the air and a heap of timed events; it does no I/O and reads no
clock. Each event runs one handler (``_HANDLERS``): a TDM state ends, a packet
ends, a radio wakes to try again, serial bytes arrive, the AT interpreter wants
polling, a RADIO_STATUS is due, the half-second link update. Those handlers are
the firmware's main loop reduced to the moments where it can act:

* **TDM** (``_try_tx``): may this radio send now (its window, the peer's bonus
  ticks, its multipoint slot, nobody audible on the air), and what (a remote
  command, the packetiser's data, a statistics packet, a yield or sync packet);
  the packet goes on the air for its flight time.
* **Channel** (``_receive``): when a packet ends every other radio decides whether
  it heard it (settings, half duplex, collisions, hopping lock, loss models),
  re-synchronises its TDM to the packet's trailer and hands the data on.
* **Serial and packetiser**: :mod:`radios.air.serial` and
  :mod:`radios.air.packetiser`, pure functions of one radio, called from here.

Events carry a sequence number, so equal times run in the order they were
scheduled and one seed gives one run.
"""

from __future__ import annotations

import heapq
import math
import random
import struct
from collections.abc import Callable
from typing import Any, ClassVar

from radios.air import serial, tdm
from radios.air.packetiser import packet_get_next
from radios.air.radio import (
    BROADCAST,
    RADIO_STATUS_COMPID,
    RADIO_STATUS_SYSID,
    RX,
    TX,
    ATHandler,
    LossModel,
    Packet,
    RadioConfig,
    RadioState,
)
from radios.loss import RangeLoss, dbm_to_rssi
from radios.mavlink import MSG_RADIO_STATUS, pack_frame
from radios.sik.timing import STATS_LEN, TICK_S, TRAILER_LEN, max_xmit

_STATE_END, _TX_END, _WAKE, _SERIAL_IN, _AT_POLL, _RADIO_STATUS, _LINK_UPDATE = range(7)


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
        self.radios: list[RadioState] = []
        for i, cfg in enumerate(configs):
            at = at_factory(i, cfg) if at_factory else None
            self.radios.append(RadioState(i, cfg, at, self.rng, start))
        self._airing: list[Packet] = []  # packets on air or recently ended
        self.busy_s = 0.0  # total time the channel carried at least one packet
        self._busy_until = start
        # radios whose output grew, for a driver that asks (it sets a list and clears it)
        self.touched: list[int] | None = None
        for r in self.radios:
            self._schedule_state_end(r)
            self._push(start + 0.5 * self.rng.random(), _LINK_UPDATE, r.index, None)

    # ------------------------------------------------------------------ API
    @property
    def queue(self) -> list[tuple[float, int, int, int, Any]]:
        """The pending events, a heap by time: the queue itself, for a scheduler that
        runs them at their own times (the simulator's host streams); never change it."""
        return self._events

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

    def advance(self, now: float) -> None:
        """Run every event up to ``now``."""
        ev = self._events
        while ev and ev[0][0] <= now:
            t, _, kind, node, data = heapq.heappop(ev)
            self.now = max(self.now, t)
            self._HANDLERS[kind](self, self.radios[node], t, data)
        self.now = max(self.now, now)
        # serial output flows whether or not the host reads it: serial.drain is in
        # closed form, so it runs when the output is read (or added to), not here

    def take_output(self, node: int, now: float) -> bytes:
        """Bytes the radio has written to its serial output by ``now``."""
        r = self.radios[node]
        if r.outbuf:
            serial.drain(r, now)
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
                serial.drain(r, self.now)  # closed form: draining now changes no time
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
            "txbuf": serial.txbuf_percent(r),
            "locked": r.locked,
            **r.stats.as_dict(),
        }

    def reconfigure(self, node: int, cfg: RadioConfig, now: float) -> None:
        r = self.radios[node]
        serial.drain(r, now)  # what left at the old serial rate, before the new one
        r.configure(cfg, self.rng, now)
        self._schedule_state_end(r)

    def apply_now(self, node: int, cfg: RadioConfig) -> None:
        """A register the firmware applies at once (``ATSn=`` or ``RTSn=`` of TXPOWER,
        MAVLINK, DUTY_CYCLE, LBT_RSSI, RTSCTS, OPPRESEND; multipoint NODEID,
        NODEDESTINATION, SYNCANY, NODECOUNT) changed: the radio runs with ``cfg`` from
        now on, its TDM phase, lock, buffers and counters untouched (SiK's param_set)."""
        r = self.radios[node]
        r.cfg = cfg
        if cfg.mavlink == 0:
            r.mav_pending = 0  # raw bytes from now on: no frame to wait for

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

    def _schedule_state_end(self, r: RadioState) -> None:
        r.version += 1
        self._push(r.state_end, _STATE_END, r.index, r.version)

    # serial side (radios.air.serial) ----------------------------------------
    def _pull_serial(self, r: RadioState, t: float) -> None:
        """Move the bytes that have crossed the serial line by ``t`` into the radio;
        with flow control a stalled line first resumes if there is room again."""
        if r.stalled_at is not None:
            resume = serial.unstall(r, t)
            if resume is not None:
                self._push(resume, _SERIAL_IN, r.index, None)
            if r.stalled_at is not None:
                return
        for data, when in serial.arrivals(r, t, self.flow_control):
            self._serial_arrive(r, data, when)

    def _serial_arrive(self, r: RadioState, data: bytes, t: float) -> None:
        if r.at is not None:
            out = r.at.feed(data, t)
            self._at_output(r, out, t)
        else:
            serial.inbuf_add(r, data)

    def _at_output(self, r: RadioState, out: Any, t: float) -> None:
        if out is None:
            return
        if out.to_air:
            serial.inbuf_add(r, out.to_air)
        if out.to_host:
            self._output(r, out.to_host, t)
        if out.remote_command:
            r.remote_cmd = out.remote_command
        if out.reboot and self.on_reboot is not None:
            self.reconfigure(r.index, self.on_reboot(r.index), t)
        elif getattr(out, "applied", False) and self.on_reboot is not None:
            self.apply_now(r.index, self.on_reboot(r.index))
        dl = r.at.next_deadline() if r.at is not None else None
        if dl is not None:
            self._push(max(dl, t), _AT_POLL, r.index, None)

    def _output(self, r: RadioState, data: bytes, t: float) -> None:
        """Data for ``r``'s host (:func:`radios.air.serial.output`); ``touched`` lists
        the radios whose output grew, for a driver that wakes only for them."""
        serial.output(r, data, t)
        if self.touched is not None:
            self.touched.append(r.index)

    def _packet_get_next(self, r: RadioState, mx: int, t: float) -> tuple[bytes, bool]:
        payload, command, heartbeat = packet_get_next(r, mx, t)
        if heartbeat:
            self._push(self.now, _RADIO_STATUS, r.index, heartbeat)
        return payload, command

    # TDM ---------------------------------------------------------------------
    def _wake_at(self, r: RadioState, t: float) -> None:
        if r.wake_at != t:
            r.wake_at = t
            self._push(t, _WAKE, r.index, None)

    def _try_tx(self, r: RadioState, t: float) -> None:
        """Send one packet now if ``r`` may (see the module docstring)."""
        if r.tx_until > t + 1e-12:
            return
        window = self._tx_window(r, t)
        if window is None or not self._clear_to_send(r, t):
            return
        end, next_start, in_rx = window
        mp = r.cfg.firmware == "multipoint"
        remaining = int((end - t) / TICK_S)
        mx = max_xmit(r.t, remaining)
        if r.cfg.key:
            mx = mx - 16 if mx >= 16 else 0  # tdm.c: room for the cipher's padding
        if mx <= 0:
            if mp:
                self._wake_at(r, next_start)
            return
        payload, command, kind = self._choose_payload(r, mx, t)
        ticks = remaining - r.t.flight_ticks(len(payload) + TRAILER_LEN)
        if not payload:
            if not in_rx and r.send_statistics and mx >= STATS_LEN:
                r.send_statistics = False
                payload = struct.pack("<BBH", r.avg_rssi, r.avg_noise, r.receive_count & 0xFFFF)
                ticks = 0
                kind = "stats"
            elif mp:
                # multipoint: only the base speaks when idle, once per own window
                if not r.cfg.multipoint_base or r.mp_synced_until >= end:
                    self._wake_at(r, next_start)
                    return
                r.mp_synced_until = end
                kind = "sync"
            else:
                r.yielded = True
                kind = "yield"
        if ticks < 0:
            ticks = 0 if kind == "stats" else 1
        self._transmit(r, t, payload, min(ticks, 0x1FFF), in_rx, command, kind)

    def _tx_window(self, r: RadioState, t: float) -> tuple[float, float, bool] | None:
        """``(end of the window, start of the next own window, in the peer's window)``
        if ``r`` holds a window it may send in at ``t``, else None (a multipoint radio
        outside its slot is woken at the next one)."""
        if r.cfg.firmware == "multipoint":
            mine, end, next_start = tdm.multipoint_slot(r, t, self.start)
            if not mine:
                self._wake_at(r, next_start)
                return None
            return end, next_start, False
        if not (r.state == TX or (r.bonus and r.state == RX)):
            return None
        if r.yielded:
            return None
        return r.state_end, r.state_end, r.state == RX

    def _clear_to_send(self, r: RadioState, t: float) -> bool:
        """Not holding off, and no preamble audible on the air (else hold off for a
        packet latency after it and wake then)."""
        if r.wait_until > t + 1e-12:
            self._wake_at(r, r.wait_until)
            return False
        busy = tdm.audible_busy_until(r, t, self._airing, self.radios)
        if busy is not None:
            r.wait_until = busy + r.t.packet_latency * TICK_S
            self._wake_at(r, r.wait_until)
            return False
        return True

    def _choose_payload(self, r: RadioState, mx: int, t: float) -> tuple[bytes, bool, str]:
        """``(payload, is_command, kind)``: a remote AT command waiting to go, else what
        the packetiser gives (possibly nothing)."""
        self._pull_serial(r, t)
        if r.remote_cmd is not None and mx >= len(r.remote_cmd):
            payload = r.remote_cmd.encode("ascii", "replace")
            r.remote_cmd = None
            return payload, True, "command"
        payload, command = self._packet_get_next(r, mx, t)
        if r.stalled_at is not None:
            self._pull_serial(r, t)
        return payload, command, "command" if command else "data"

    def _transmit(
        self, r: RadioState, t: float, payload: bytes, ticks: int, in_rx: bool, command: bool, kind: str
    ) -> None:
        """Put one packet on the air for its flight time; its end is an event."""
        mp = r.cfg.firmware == "multipoint"
        flight = r.t.flight_ticks(len(payload) + TRAILER_LEN) * TICK_S
        pkt = Packet(
            r.index,
            payload,
            ticks,
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

    def _heard(self, r: RadioState, pkt: Packet, t: float, overlapping: list[Packet]) -> bool:
        """Whether ``r`` hears ``pkt`` (``overlapping``: the other packets on the air
        meanwhile): same settings, not transmitting itself, no collision, on the
        packet's channel (locked, or by chance), not lost. Hearing a sender on its own
        hopping sequence locks both."""
        sender = self.radios[pkt.sender]
        rcfg = r.cfg
        key = rcfg.air_key
        if sender.cfg.air_key != key:
            return False
        seed = rcfg.hop
        radios = self.radios
        me = r.index
        for other in overlapping:
            if other.sender == me:
                return False  # half duplex: it was transmitting and heard nothing
            ocfg = radios[other.sender].cfg
            if ocfg.air_key == key and ocfg.hop == seed:
                r.stats.collisions += 1
                r.stats.rx_errors += 1
                return False
        if sender.cfg.hop != seed:
            # another hopping sequence (AES key): on our channel only by chance
            if self.rng.random() >= 1.0 / max(r.cfg.num_channels, 1):
                return False
        elif not r.locked:
            # the multipoint base sends its sync on a fixed channel: heard at once
            if not sender.cfg.multipoint_base and self.rng.random() >= 1.0 / max(r.cfg.num_channels, 1):
                return False
            # r now follows the sender's TDM and hop sequence: they are in step
            r.locked = True
            sender.locked = True
        for model in self.losses:
            if model.lost(pkt.sender, r.index, t, self.rng):
                r.stats.lost += 1
                r.stats.rx_errors += 1
                return False
        return True

    def _receive(self, r: RadioState, pkt: Packet, t: float, overlapping: list[Packet]) -> None:
        """``pkt`` ended: if ``r`` heard it, take its statistics or follow its TDM
        trailer, and hand its data, command or reply on."""
        if not self._heard(r, pkt, t, overlapping):
            return
        sender = self.radios[pkt.sender]
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
            tdm.sync_tx_windows(r, pkt, t)
            self._schedule_state_end(r)
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

    def _remote_at(self, r: RadioState, pkt: Packet, t: float) -> None:
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
        if reply and getattr(res, "per_line", False):  # multipoint RTI5: a packet per line
            r.inject_packets.extend(line + b"\n" for line in reply.split(b"\n") if line)
        elif reply:  # multipoint: run_remote already put the "[id] " prefix on every line
            r.injected += reply[:252]
        if getattr(res, "reboot", False) and self.on_reboot is not None:
            self.reconfigure(r.index, self.on_reboot(r.index), t)
        elif getattr(res, "applied", False) and self.on_reboot is not None:
            self.apply_now(r.index, self.on_reboot(r.index))

    def _rssi(self, sender: int, receiver: int, t: float) -> int:
        for m in self.losses:
            if isinstance(m, RangeLoss):
                dbm = m.rx_dbm(sender, receiver, t)
                if dbm is not None:
                    return dbm_to_rssi(dbm + self.rng.gauss(0.0, 1.0))
        return max(0, min(255, int(self.rssi_base + self.rng.gauss(0.0, 3.0))))

    # event handlers ----------------------------------------------------------
    def _on_state_end(self, r: RadioState, t: float, version: Any) -> None:
        if version != r.version:
            return
        if r.cfg.firmware == "multipoint":
            self._try_tx(r, t)
            return
        tdm.next_state(r, t)
        self._schedule_state_end(r)
        self._try_tx(r, t)

    def _on_tx_end(self, r: RadioState, t: float, pkt: Any) -> None:
        # the packets on the air while it was: the same for every receiver
        t0, t1 = pkt.t_start, pkt.t_end
        overlapping = [p for p in self._airing if p is not pkt and p.t_start < t1 and t0 < p.t_end]
        for other in self.radios:
            if other is not r:
                self._receive(other, pkt, t, overlapping)
        # forget packets that can no longer overlap anything
        horizon = t - 0.5
        self._airing = [p for p in self._airing if p.t_end > horizon]
        self._try_tx(r, t)

    def _on_wake(self, r: RadioState, t: float, _data: Any) -> None:
        if r.wake_at == t:
            r.wake_at = -1.0
        self._try_tx(r, t)

    def _on_serial_in(self, r: RadioState, t: float, _data: Any) -> None:
        self._pull_serial(r, t)
        if r.cfg.firmware == "multipoint":
            self._try_tx(r, t)

    def _on_at_poll(self, r: RadioState, t: float, _data: Any) -> None:
        if r.at is None:
            return
        dl = r.at.next_deadline()
        if dl is None or dl > t + 1e-9:
            if dl is not None:
                self._push(dl, _AT_POLL, r.index, None)
            return
        self._at_output(r, r.at.poll(t), t)

    def _on_radio_status(self, r: RadioState, t: float, version: Any) -> None:
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
            serial.txbuf_percent(r),
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
        serial.drain(r, t)
        if r.cfg.out_buf - len(r.outbuf) < len(frame):
            return  # no room: the firmware skips the report
        r.rs_seq = (r.rs_seq + 1) & 0xFF
        r.stats.radio_status += 1
        self._output(r, frame, t)

    def _on_link_update(self, r: RadioState, t: float, _data: Any) -> None:
        """link_update() of tdm.c, every 0.5 s."""
        if t - r.last_rx > 0.5:
            r.unlock_count += 1
        if r.unlock_count > 40 and r.cfg.num_channels > 1 and not r.cfg.multipoint_base:
            # the multipoint base is the network's clock: it hops on its own sequence
            # whether it hears anyone or not, so it never loses the sync it gives
            r.locked = False
            r.unlock_count = 5
        if r.unlock_count > 5:
            r.remote_rssi = r.remote_noise = 0
        r.avg_noise = (max(0, int(40 + self.rng.gauss(0.0, 2.0))) + 3 * r.avg_noise) // 4
        r.send_statistics = True
        self._push(t + 0.5, _LINK_UPDATE, r.index, None)

    #: one handler per event kind
    _HANDLERS: ClassVar[dict[int, Callable[[AirModel, RadioState, float, Any], None]]] = {
        _STATE_END: _on_state_end,
        _TX_END: _on_tx_end,
        _WAKE: _on_wake,
        _SERIAL_IN: _on_serial_in,
        _AT_POLL: _on_at_poll,
        _RADIO_STATUS: _on_radio_status,
        _LINK_UPDATE: _on_link_update,
    }
