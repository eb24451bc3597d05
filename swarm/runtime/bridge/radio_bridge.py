"""The radio bridge: the swarm's Zenoh key space carried over a SiK radio.

Theory of operation
-------------------
Zenoh has no serial transport, so each node bridges its local Zenoh session to its
radio link. Samples published locally under ``swarm/**`` cross the air as MAVLink 2
``TUNNEL`` frames; frames received are published into the local session under
the same key. Nothing else about the key travels: the key is rebuilt from the
frame's sender id, its ``target_system`` and its ``payload_type``
(32768 + kind: advertize, GSAdvertize, P2P, pose, state, multicast P2P):

=====================  ==========  ===========================================
local key              air target  key on the receiving node
=====================  ==========  ===========================================
swarm/advertize        0           swarm/advertize
swarm/GSAdvertize      0           swarm/GSAdvertize
swarm/<peer>           peer id     swarm/<own name> (only the addressee keeps it)
swarm/<peer>/command   peer id     swarm/<own name>/command (a P2P frame whose
                                   message is a Command: the same bytes on air)
swarm/<own>/pose       0           swarm/<sender name>/pose
swarm/<own>/state      0           swarm/<sender name>/state
=====================  ==========  ===========================================

* **No loops**: samples the bridge publishes carry an attachment marker and are
  never sent back to the air; a node never forwards what it did not publish.
* **Names and ids** are learnt from Advertize and GSAdvertize (:class:`swarm.core.bridge.names.NameTable`);
  a name or id claimed by two agents is counted, logged once and reported to both with NameConflict.
* **What goes next** is :class:`swarm.core.bridge.air_queue.AirQueue`'s (pure): three
  queues (protocol > pose > telemetry), each with a token bucket of air bytes per
  second, so one agent cannot flood the channel; the same P2P payload queued for
  several peers (a leader's heartbeat to its members) goes on air once, listing
  the addressees.
* **RADIO_STATUS** (flow control): only a report plausibly from the local radio
  counts (:mod:`swarm.core.bridge.radio_guard`: sysid 51 compid 68, one per HEARTBEAT we sent,
  consistent with the bytes we wrote; forged ones are counted in
  ``radio_status_rejected``), and its effect is bounded (the queue's back-off):
  below 50% free transmit buffer telemetry waits; poses are thinned by at most 15%,
  never held; protocol always goes. Reports older than 5 s are ignored, as
  ArduPilot and PX4 do with txbuf.
* **Radio loss**: when the device goes away (USB radio unplugged, emulator pty
  dropped) the bridge drops its queues, logs about once a second and reopens the
  device at the same path with back-off (``reopen_radio``), keeping its name table
  and signing state; listeners hear ``("lost", reason)`` and ``("back", "after S s")``.
  With ``reopen_radio`` off it stops and sets ``link_lost``, as before.
  **Only the same device**: the link reopens only the device it first opened
  (:mod:`radios.device_id`); another device at the path (a reassigned
  ``/dev/ttyUSB0``, another pty) is refused unopened, with one line and
  ``("refused", text)`` naming both, once per device that appears (every attempt
  counts in ``radio_refused``), and the bridge waits on for its own radio.
  :meth:`RadioBridge.lend_radio` uses the same path on purpose: it releases the
  device for a function that needs the port to itself (the radio guard's AT
  commands), then takes it back; listeners hear ``("paused", why)`` and ``("back", ...)``.
  It first checks that the device at the path is still its own (``Link.check_device``),
  so the borrower does not talk to another one.
* **HEARTBEAT** into the local radio once a second (that makes a SiK radio report
  RADIO_STATUS), and the vehicle's HEARTBEAT and GLOBAL_POSITION_INT forwarded at
  1 Hz under the agent's system id so MAVProxy or QGroundControl list vehicles.
* **Liveness**: each thread notes ``time.monotonic()`` at every round
  (:meth:`RadioBridge.beats`, the service watchdog's input): the send thread at least
  once per HEARTBEAT period (or per ``write_timeout`` of a radio that stopped taking
  bytes), the receiving one every 0.2 s and while it waits for a lost radio.
* **Signing** (optional): every frame signed with the swarm key and this radio's
  link id; unsigned (but the local RADIO_STATUS), badly signed and replayed frames
  are dropped and counted. The node's signing clock starts at its start reference
  (:mod:`radios.signing_state`: kept in ``signing_state``, the node's file in its
  state folder, carried across restarts; without one, the wall clock at start), and
  a frame stamped before it is refused: it was on the air before this run began.

The receiving side (frames into the key space) is
:class:`swarm.runtime.bridge.rx.AirToLocal`, a part of :class:`RadioBridge`; this
module keeps the sending side, the radio's loss and reopening, and the life cycle.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from radios.errors import DeviceMismatchError, LinkClosedError, LinkOpenError, RadioError
from radios.link import Link
from radios.mavlink import (
    FrameBuilder,
    SigningClock,
    frame_msgid,
)
from radios.signing import Verifier
from radios.signing_state import ClockKeeper, wall_ticks
from swarm.core.bridge.air_queue import AirItem, AirQueue, Klass
from swarm.core.bridge.names import NameTable
from swarm.core.bridge.radio_guard import RadioState, RadioStatusGuard
from swarm.core.wire.message_types import Message, Telemetry
from swarm.core.wire.messages import encode
from swarm.core.wire.tunnel import (
    COMP_ID,
    PAYLOAD_TYPE_BASE,
    TUNNEL_MAX,
    Kind,
    pack,
)
from swarm.runtime.bridge.rx import ATTACHMENT, AirToLocal
from swarm.runtime.bridge.stats import BridgeStats
from swarm.runtime.keyspace.transport import KEY_ADVERTIZE, KEY_GS_ADVERTIZE, PREFIX

log = logging.getLogger(__name__)
T = TypeVar("T")


@dataclass
class BridgeConfig:
    heartbeat_hz: float = 1.0
    telemetry_hz: float = 1.0  # forwarded vehicle HEARTBEAT / GLOBAL_POSITION_INT
    #: air bytes per second and burst (bytes) per class: protocol, pose, telemetry
    rates: tuple[float, float, float] = (600.0, 300.0, 160.0)
    bursts: tuple[float, float, float] = (1500.0, 300.0, 320.0)
    queue_sizes: tuple[int, int, int] = (64, 4, 16)
    signing_key: bytes | None = None
    link_id: int | None = None  # signing link id; None: drawn at random per start (a new stream)
    #: the file that keeps the signing clock across restarts (radios.signing_state); None: none
    signing_state: str | None = None
    radio_status_stale_s: float = 5.0
    #: reopen the radio when its device goes away (else stop and set ``link_lost``)
    reopen_radio: bool = True
    #: first and longest wait between attempts to reopen a lost radio (s)
    reopen_backoff: tuple[float, float] = (0.1, 1.0)
    #: a new P2P protocol item waits this long for identical payloads to other peers
    #: (a leader's heartbeat to N members) so they leave as one multicast frame
    coalesce_s: float = 0.005


class RadioBridge(AirToLocal):
    """Bridges one Zenoh session and one radio link (see the module docstring)."""

    def __init__(
        self,
        session: Any,
        link: Link,
        *,
        name: str,
        agent_id: int,
        config: BridgeConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.session = session
        self.link = link
        self.name = name
        self.id = agent_id
        self.cfg = config or BridgeConfig()
        self.clock = clock
        self.stats = BridgeStats()
        self.guard = RadioStatusGuard(stale_s=self.cfg.radio_status_stale_s)
        # one time base for what this node signs and verifies, from its start reference
        self._keeper: ClockKeeper | None = None
        if self.cfg.signing_key and self.cfg.signing_state:
            self._keeper = ClockKeeper(self.cfg.signing_state, name)
            signing = self._keeper.open()
        else:
            signing = SigningClock(start=wall_ticks())
        self._builder = FrameBuilder(
            agent_id, COMP_ID, signing_key=self.cfg.signing_key, link_id=self.cfg.link_id, clock=signing
        )
        self._vehicle_builder = FrameBuilder(
            agent_id, 1, signing_key=self.cfg.signing_key, link_id=self.cfg.link_id, clock=signing
        )
        self._verifier = Verifier(self.cfg.signing_key, signing) if self.cfg.signing_key else None
        self._queue = AirQueue(
            rates=self.cfg.rates,
            bursts=self.cfg.bursts,
            sizes=self.cfg.queue_sizes,
            coalesce_s=self.cfg.coalesce_s,
            signed=bool(self.cfg.signing_key),
            guard=self.guard,
            stats=self.stats,
            now=clock(),
        )
        self._cond = threading.Condition()
        self.names = NameTable(name, agent_id)
        self._conflicts_logged: set[tuple[str, int]] = set()
        self._vehicle_last: dict[int, float] = {}
        self._closed = False
        self.link_lost = False  # the radio link died and is not reopened (see reopen_radio)
        self.link_down = False  # the radio is away and being reopened
        self._lent = False  # the device is lent out (lend_radio)
        self._lent_for = ""
        self._rx_away = threading.Event()  # the receive thread is in _radio_lost
        self.loss_reason = ""
        self._listeners: list[Callable[[str, str], None]] = []
        self._next_hb = 0.0
        self._sub: Any = None
        self._threads: list[threading.Thread] = []
        self._beat_tx = self._beat_rx = time.monotonic()  # each thread's last round

    # -- life cycle -------------------------------------------------------------
    def start(self) -> RadioBridge:
        self._sub = self.session.declare_subscriber(f"{PREFIX}/**", self._on_local)
        if self._keeper is not None:
            self._keeper.start()
        for target, nm in ((self._tx_loop, "tx"), (self._rx_loop, "rx")):
            t = threading.Thread(target=target, name=f"bridge-{self.name}-{nm}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def close(self) -> None:
        """Stop both threads and undeclare the subscriber (the link is the caller's)."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except Exception:
                pass
        for t in self._threads:
            t.join(2.0)
        if self._keeper is not None:
            self._keeper.close()  # the mark, once more, for the next start

    def beats(self) -> dict[str, tuple[float, float]]:
        """Each thread's last round (``time.monotonic()``) and its longest wait between rounds."""
        return {
            "radio-send": (self._beat_tx, 1.0 / self.cfg.heartbeat_hz),
            "radio-receive": (self._beat_rx, max(0.2, self.cfg.reopen_backoff[1])),
        }

    def peers(self) -> dict[str, int]:
        return self.names.as_dict()

    @property
    def radio(self) -> RadioState:
        """The last plausible RADIO_STATUS of the local radio."""
        return self.guard.state

    def add_listener(self, fn: Callable[[str, str], None]) -> None:
        """``fn(what, text)`` when the radio goes away (``"lost"``, why) and when it is
        open again (``"back"``, after how long); called on the bridge's receive thread."""
        self._listeners.append(fn)

    def _tell(self, what: str, text: str) -> None:
        for fn in list(self._listeners):
            try:
                fn(what, text)
            except Exception:
                log.exception("bridge %s: radio listener failed", self.name)

    # -- local samples -> air -----------------------------------------------------
    def _on_local(self, sample: Any) -> None:
        att = sample.attachment
        if att is not None and att.to_bytes() == ATTACHMENT:
            return  # came from the radio: never back to the air
        key = str(sample.key_expr)
        data = sample.payload.to_bytes()
        parts = key.split("/")
        if len(parts) < 2 or parts[0] != PREFIX:
            return
        if key == KEY_ADVERTIZE:
            self._enqueue(AirItem(Klass.PROTOCOL, Kind.ADVERTIZE, [0], data))
        elif key == KEY_GS_ADVERTIZE:
            self._enqueue(AirItem(Klass.PROTOCOL, Kind.GS_ADVERTIZE, [0], data))
        elif len(parts) == 2:
            peer = self.names.id_of(parts[1])
            if parts[1] == self.name:
                return  # our own inbox: local delivery only
            if peer is None:
                self.stats.unroutable += 1
                return
            klass = Klass.TELEMETRY if data[:1] and (data[0] & 0x1F) == Telemetry.TYPE else Klass.PROTOCOL
            self._enqueue(AirItem(klass, Kind.P2P, [peer], data))
        elif len(parts) == 3 and parts[2] == "command":
            # a station's Command: on the air the P2P frame it always was (the
            # receiving bridge puts it back on the addressee's command key)
            peer = self.names.id_of(parts[1])
            if parts[1] == self.name:
                return  # to ourselves: local delivery only
            if peer is None:
                self.stats.unroutable += 1
                return
            self._enqueue(AirItem(Klass.PROTOCOL, Kind.P2P, [peer], data))
        elif len(parts) == 3 and parts[1] == self.name:
            if parts[2] == "pose":
                self._enqueue(AirItem(Klass.POSE, Kind.POSE, [0], data))
            elif parts[2] == "state":
                self._enqueue(AirItem(Klass.TELEMETRY, Kind.STATE, [0], data))

    def forward_vehicle(self, msg: Any) -> None:
        """Forward a vehicle HEARTBEAT or GLOBAL_POSITION_INT (a pymavlink message)
        under this agent's system id, at most ``telemetry_hz`` per message type."""
        mid = msg.get_msgId()
        if mid not in (0, 33):
            return
        now = self.clock()
        if now - self._vehicle_last.get(mid, -1e9) < 1.0 / self.cfg.telemetry_hz:
            return
        self._vehicle_last[mid] = now
        self._enqueue(AirItem(Klass.TELEMETRY, Kind.P2P, [0], b"", raw_frame=self._pack_vehicle(msg)))

    def _pack_vehicle(self, msg: Any) -> bytes:
        with self._cond:
            return self._vehicle_builder.build(msg)

    def _enqueue(self, item: AirItem) -> None:
        if item.raw_frame is None and len(item.payload) > TUNNEL_MAX - 1:
            self.stats.oversize += 1
            return
        with self._cond:
            if self._closed:
                return
            if self.link_down:
                self.stats.dropped_radio_down += 1
                return
            self._queue.put(item, self.clock())
            self._cond.notify()

    def _next_frame(self, now: float) -> tuple[bytes | None, float]:
        """Pick the next frame to send (under the lock). Returns (frame, wait)."""
        item, wait = self._queue.next_item(now)
        if item is None:
            return None, wait
        # packed only now, so sequence numbers and signing timestamps follow air order
        return (item.raw_frame if item.raw_frame is not None else self._pack(item)), 0.0

    def _pack(self, item: AirItem) -> bytes:
        target, ptype, payload = pack(item.kind, item.targets, item.payload)
        return self._builder.tunnel(payload, target_system=target, payload_type=ptype)

    def _tx_loop(self) -> None:
        self._next_hb = self.clock()
        while True:
            self._beat_tx = time.monotonic()
            with self._cond:
                if self._closed:
                    return
                if self.link_down:  # the receive thread is reopening the radio
                    self._cond.wait(0.25)
                    continue
                now = self.clock()
                if now >= self._next_hb:
                    self._next_hb = now + 1.0 / self.cfg.heartbeat_hz
                    frame: bytes | None = self._builder.heartbeat()
                    self.stats.heartbeats += 1
                    # before it is written: the radio's answer may come back at once
                    self.guard.heartbeat_sent(now)
                    wait = 0.0
                else:
                    frame, wait = self._next_frame(now)
                    if frame is not None and frame_msgid(frame) == 0:  # a vehicle's HEARTBEAT
                        self.guard.heartbeat_sent(now)  # the radio answers it too
                if frame is None:
                    self._cond.wait(max(0.001, min(wait, self._next_hb - now)))
                    continue
            try:
                self.link.send(frame)
                self.stats.frames_out += 1
                self.stats.bytes_out += len(frame)
                with self._cond:
                    self.guard.wrote(len(frame), now)
            except RadioError as exc:
                # a device that went away is noticed (and reopened) by the receive thread
                self.stats.send_errors += 1
                if self.link.closed:
                    log.warning("bridge %s: radio link closed: %s", self.name, exc)
                    self.link_lost = True
                    return

    # -- air -> local -------------------------------------------------------------
    def _rx_loop(self) -> None:
        while not self._closed:
            self._beat_rx = time.monotonic()
            try:
                frame = self.link.recv(0.2)
            except RadioError as exc:
                if self._closed or not self._radio_lost(str(exc)):
                    return
                continue
            if frame is None:
                continue
            try:
                self.handle_frame(frame)
            except Exception:  # a bug here must not kill the bridge
                log.exception("bridge %s: error handling a frame", self.name)

    def lend_radio(self, fn: Callable[[], T], why: str = "radio check", timeout: float = 5.0) -> T:
        """Release the radio's device, run ``fn`` (which may open the device itself: AT
        commands need the port to themselves), then take the radio back, on the caller's
        thread. The swarm state stays; frames queued meanwhile are dropped, as when the
        radio is unplugged. Raises what ``fn`` raises (after taking the radio back), and
        :class:`~radios.errors.LinkClosedError` if the bridge is closed or its radio is
        already away, :class:`~radios.errors.LinkOpenError` for a link that cannot be
        reopened (a replayed capture). Lending works with ``reopen_radio`` off too
        (``--exit-on-radio-loss``): only a radio that really goes away ends the bridge.
        """
        if not self.link.can_reopen:
            raise LinkOpenError(f"{self.link.url}: this kind of link cannot be lent and taken back")
        with self._cond:
            if self._closed or self.link_lost or self.link_down:
                raise LinkClosedError(f"{self.link.url}: the radio is not ours to lend now")
            self._lent, self._lent_for = True, why
            self.link_down = True
        try:
            self.link.release()
            deadline = time.monotonic() + timeout
            # the receive thread notices its closed port and waits in _radio_lost
            self._rx_away.wait(max(0.0, deadline - time.monotonic()))
            self.link.check_device()  # the borrower talks to our radio, not what replaced it
            return fn()
        finally:
            with self._cond:
                self._lent = False
                self._cond.notify_all()

    def _radio_lost(self, reason: str) -> bool:
        """The radio's device went away: drop the queues, then reopen it with back-off
        (True once it is back) or, without ``reopen_radio``, give up (False)."""
        self._rx_away.set()
        try:
            return self._wait_for_radio(reason)
        finally:
            self._rx_away.clear()

    def _wait_for_radio(self, reason: str) -> bool:
        t0 = self.clock()
        with self._cond:
            self.link_down = True
            self.loss_reason = reason
            if not self._lent:
                self.stats.radio_losses += 1
            self.stats.dropped_radio_down += self._queue.clear()
            self.guard.reset()
        url = self.link.url
        if not self._lent and (not self.cfg.reopen_radio or not self.link.can_reopen or self.link.closed):
            # the owner reports it (swarm agent / swarm gcs print one line and exit 1)
            log.info("bridge %s: radio %s lost: %s", self.name, url, reason)
            self.link_lost = True
            self._tell("lost", reason)
            return False
        lent = self._lent
        if lent:
            log.info("bridge %s: radio %s paused: %s", self.name, url, self._lent_for)
            self._tell("paused", self._lent_for)
        else:
            log.warning("bridge %s: radio %s lost (%s): waiting for it to come back", self.name, url, reason)
            self._tell("lost", reason)
        if not self._reopen(url, t0):
            return False
        away = self.clock() - t0
        with self._cond:
            self.link_down = False
            self.stats.radio_reopens += 1
            self._next_hb = self.clock()  # a HEARTBEAT at once: the radio reports again
            self._cond.notify_all()
        (log.info if lent else log.warning)("bridge %s: radio %s back after %.1f s", self.name, url, away)
        self._tell("back", f"after {away:.1f} s")
        return True

    def _reopen(self, url: str, t0: float) -> bool:
        """Reopen the radio with back-off, not while it is lent out: True once it is
        open, False if the bridge closes or the radio cannot come back."""
        first, longest = self.cfg.reopen_backoff
        backoff, next_log = first, t0 + 1.0
        refused = ""  # the last refusal said (one line per device that appears)
        while True:
            self._beat_rx = time.monotonic()  # the receive thread, waiting for the radio
            with self._cond:
                if self._closed:
                    return False
                self._cond.wait(backoff)
                if self._closed:
                    return False
                if self._lent:  # lent out (lend_radio): not ours to reopen yet
                    backoff, next_log = first, self.clock() + 1.0
                    continue
            try:
                self.link.reopen()
                return True
            except LinkOpenError as exc:
                mismatch = isinstance(exc, DeviceMismatchError)
                if mismatch:
                    self.stats.radio_refused += 1
                if not self.cfg.reopen_radio:  # lent, and gone (or replaced) meanwhile: as any loss
                    log.info("bridge %s: radio %s lost: %s", self.name, url, exc)
                    self.loss_reason = str(exc)
                    self.link_lost = True
                    self._tell("lost", str(exc))
                    return False
                if mismatch:  # another device at the path: never opened; said once per device
                    if str(exc) != refused:
                        refused = str(exc)
                        log.warning("bridge %s: radio refused %s; waiting for the radio", self.name, exc)
                        self._tell("refused", refused)
                    backoff = min(longest, backoff * 2)
                    continue
                refused = ""
                now = self.clock()
                if now >= next_log:  # about once a second, not once per attempt
                    next_log = now + 1.0
                    log.warning("bridge %s: radio still away after %.0f s: %s", self.name, now - t0, exc)
                backoff = min(longest, backoff * 2)
            except RadioError as exc:  # closed by its owner meanwhile
                log.info("bridge %s: radio %s not reopened: %s", self.name, url, exc)
                self.link_lost = True
                return False


def bridge_message_frame_bytes(msg: Message, *, signed: bool) -> int:
    """Bytes on air of ``msg`` in a TUNNEL frame (for the messages benchmark)."""
    key = b"\0" * 32 if signed else None
    return len(
        FrameBuilder(1, COMP_ID, signing_key=key).tunnel(
            encode(msg), target_system=1, payload_type=PAYLOAD_TYPE_BASE + Kind.P2P
        )
    )
