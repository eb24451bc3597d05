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
swarm/<own>/pose       0           swarm/<sender name>/pose
swarm/<own>/state      0           swarm/<sender name>/state
=====================  ==========  ===========================================

* **No loops**: samples the bridge publishes carry an attachment marker and are
  never sent back to the air; a node never forwards what it did not publish.
* **Names and ids** are learnt from Advertize and GSAdvertize; a name or id claimed by two agents
  is counted, logged once and reported to both with NameConflict.
* **Multicast**: the same P2P payload queued for several peers (a leader's
  heartbeat to its members) goes on air once, listing the addressees.
* **Priorities and budgets**: three queues (protocol > pose > telemetry), each
  with a token bucket of air bytes per second, so one agent cannot flood the
  channel.
* **RADIO_STATUS** (flow control): only a report plausibly from the local radio
  counts (:mod:`swarm.core.radio_guard`: sysid 51 compid 68, one per HEARTBEAT we sent,
  consistent with the bytes we wrote; forged ones are counted in
  ``radio_status_rejected``), and its effect is bounded: below 50% free transmit
  buffer telemetry waits; poses are thinned by at most 15%, never held; protocol
  always goes. Reports older than 5 s are ignored, as ArduPilot and PX4 do with txbuf.
* **Radio loss**: when the device goes away (USB radio unplugged, emulator pty
  dropped) the bridge drops its queues, logs about once a second and reopens the
  device at the same path with back-off (``reopen_radio``), keeping its name table
  and signing state; listeners hear ``("lost", reason)`` and ``("back", "after S s")``.
  With ``reopen_radio`` off it stops and sets ``link_lost``, as before.
  :meth:`RadioBridge.lend_radio` uses the same path on purpose: it releases the
  device for a function that needs the port to itself (the radio guard's AT
  commands), then takes it back; listeners hear ``("paused", why)`` and ``("back", ...)``.
* **HEARTBEAT** into the local radio once a second (that makes a SiK radio report
  RADIO_STATUS), and the vehicle's HEARTBEAT and GLOBAL_POSITION_INT forwarded at
  1 Hz under the agent's system id so MAVProxy or QGroundControl list vehicles.
* **Signing** (optional): every frame signed with the swarm key and this radio's
  link id; unsigned (but the local RADIO_STATUS), badly signed and replayed frames
  are dropped and counted.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from enum import IntEnum
from typing import Any, TypeVar

from radios.errors import LinkClosedError, LinkOpenError, RadioError
from radios.link import Link
from radios.mavlink import (
    MSG_RADIO_STATUS,
    MSG_TUNNEL,
    Frame,
    FrameBuilder,
    SigningClock,
    radio_status_fields,
)
from radios.signing import Verifier
from swarm.core.messages import (
    Advertize,
    GSAdvertize,
    Message,
    NameConflict,
    Telemetry,
    decode,
    encode,
)
from swarm.core.radio_guard import RadioState, RadioStatusGuard
from swarm.core.tunnel import (
    COMP_ID,
    PAYLOAD_TYPE_BASE,
    TUNNEL_MAX,
    Kind,
    fits_multicast,
    pack,
    unpack_tunnel,
)
from swarm.errors import DecodeError, VersionMismatch
from swarm.runtime.transport import KEY_ADVERTIZE, KEY_GS_ADVERTIZE, PREFIX, inbox_key, pose_key, state_key

log = logging.getLogger(__name__)
T = TypeVar("T")

ATTACHMENT = b"radio-bridge"


class Klass(IntEnum):
    PROTOCOL = 0
    POSE = 1
    TELEMETRY = 2


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
    radio_status_stale_s: float = 5.0
    #: reopen the radio when its device goes away (else stop and set ``link_lost``)
    reopen_radio: bool = True
    #: first and longest wait between attempts to reopen a lost radio (s)
    reopen_backoff: tuple[float, float] = (0.1, 1.0)
    #: a new P2P protocol item waits this long for identical payloads to other peers
    #: (a leader's heartbeat to N members) so they leave as one multicast frame
    coalesce_s: float = 0.005


@dataclass
class BridgeStats:
    frames_out: int = 0
    frames_in: int = 0
    bytes_out: int = 0
    published: int = 0
    multicast_merged: int = 0
    queue_drops: int = 0
    oversize: int = 0
    unroutable: int = 0
    unknown_sender: int = 0
    not_for_us: int = 0
    decode_errors: int = 0
    version_mismatch: int = 0
    conflicts: int = 0
    send_errors: int = 0
    throttled: int = 0  # send-loop passes that held telemetry back (txbuf back-off)
    poses_thinned: int = 0  # poses skipped by the bounded txbuf back-off
    radio_status_accepted: int = 0
    radio_status_rejected: int = 0  # RADIO_STATUS not plausibly from the local radio
    radio_losses: int = 0  # the radio's device went away
    radio_reopens: int = 0  # ... and was opened again
    dropped_radio_down: int = 0  # frames dropped while the radio was away
    heartbeats: int = 0
    vehicle_forwarded: int = 0
    unsigned: int = 0
    bad_signature: int = 0
    replayed: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class _Item:
    klass: Klass
    kind: Kind
    targets: list[int]
    payload: bytes
    raw_frame: bytes | None = None
    t: float = 0.0  # when queued


@dataclass
class _Bucket:
    rate: float
    burst: float
    tokens: float
    t: float

    def refill(self, now: float) -> None:
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
        self.t = now

    def wait_for(self, n: int) -> float:
        return max(0.0, (min(n, self.burst) - self.tokens) / self.rate) if self.rate > 0 else 1.0


@dataclass
class _Peer:
    id: int
    name: str
    seen: float


class RadioBridge:
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
        signing = SigningClock()  # one time base for what this node signs and verifies
        self._builder = FrameBuilder(
            agent_id, COMP_ID, signing_key=self.cfg.signing_key, link_id=self.cfg.link_id, clock=signing
        )
        self._vehicle_builder = FrameBuilder(
            agent_id, 1, signing_key=self.cfg.signing_key, link_id=self.cfg.link_id, clock=signing
        )
        self._verifier = Verifier(self.cfg.signing_key, signing) if self.cfg.signing_key else None
        now = clock()
        self._queues: list[deque[_Item]] = [deque() for _ in Klass]
        self._buckets = [_Bucket(r, b, b, now) for r, b in zip(self.cfg.rates, self.cfg.bursts, strict=True)]
        self._cond = threading.Condition()
        self._by_name: dict[str, _Peer] = {name: _Peer(agent_id, name, float("inf"))}
        self._by_id: dict[int, _Peer] = {agent_id: self._by_name[name]}
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

    # -- life cycle -------------------------------------------------------------
    def start(self) -> RadioBridge:
        self._sub = self.session.declare_subscriber(f"{PREFIX}/**", self._on_local)
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

    def peers(self) -> dict[str, int]:
        return {n: p.id for n, p in self._by_name.items()}

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
            self._enqueue(_Item(Klass.PROTOCOL, Kind.ADVERTIZE, [0], data))
        elif key == KEY_GS_ADVERTIZE:
            self._enqueue(_Item(Klass.PROTOCOL, Kind.GS_ADVERTIZE, [0], data))
        elif len(parts) == 2:
            peer = self._by_name.get(parts[1])
            if parts[1] == self.name:
                return  # our own inbox: local delivery only
            if peer is None:
                self.stats.unroutable += 1
                return
            klass = Klass.TELEMETRY if data[:1] and (data[0] & 0x1F) == Telemetry.TYPE else Klass.PROTOCOL
            self._enqueue(_Item(klass, Kind.P2P, [peer.id], data))
        elif len(parts) == 3 and parts[1] == self.name:
            if parts[2] == "pose":
                self._enqueue(_Item(Klass.POSE, Kind.POSE, [0], data))
            elif parts[2] == "state":
                self._enqueue(_Item(Klass.TELEMETRY, Kind.STATE, [0], data))

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
        self._enqueue(_Item(Klass.TELEMETRY, Kind.P2P, [0], b"", raw_frame=self._pack_vehicle(msg)))

    def _pack_vehicle(self, msg: Any) -> bytes:
        with self._cond:
            return self._vehicle_builder.build(msg)

    def _enqueue(self, item: _Item) -> None:
        if item.raw_frame is None and len(item.payload) > TUNNEL_MAX - 1:
            self.stats.oversize += 1
            return
        q = self._queues[item.klass]
        limit = self.cfg.queue_sizes[item.klass]
        with self._cond:
            if self._closed:
                return
            if self.link_down:
                self.stats.dropped_radio_down += 1
                return
            if len(q) >= limit:
                q.popleft()  # the oldest is the stalest
                self.stats.queue_drops += 1
            item.t = self.clock()
            q.append(item)
            self._cond.notify()

    def _allowed_classes(self, now: float) -> tuple[Klass, ...]:
        # protocol and poses always go (poses may be thinned, see _next_frame)
        if self.guard.telemetry_allowed(now):
            return tuple(Klass)
        return (Klass.PROTOCOL, Klass.POSE)

    def _next_frame(self, now: float) -> tuple[bytes | None, float]:
        """Pick the next frame to send (under the lock). Returns (frame, wait)."""
        wait = 0.25
        allowed = self._allowed_classes(now)
        for klass in Klass:
            q = self._queues[klass]
            if not q:
                continue
            if klass not in allowed:
                self.stats.throttled += 1
                continue
            bucket = self._buckets[klass]
            bucket.refill(now)
            item = q[0]
            if item.raw_frame is None and item.kind == Kind.P2P:
                hold = item.t + self.cfg.coalesce_s - now
                if hold > 0:
                    wait = min(wait, hold)
                    continue
                self._merge_multicast(q, item)
            size = self._frame_size(item)
            if bucket.tokens < min(size, bucket.burst):
                wait = min(wait, bucket.wait_for(size))
                continue
            q.popleft()
            if klass == Klass.POSE and not self.guard.take_pose(now):
                self.stats.poses_thinned += 1  # bounded txbuf back-off: skip this one
                return None, 0.0
            bucket.tokens -= size
            # packed only now, so sequence numbers and signing timestamps follow air order
            return (item.raw_frame if item.raw_frame is not None else self._pack(item)), 0.0
        return None, wait

    def _frame_size(self, item: _Item) -> int:
        if item.raw_frame is not None:
            return len(item.raw_frame)
        extra = 1 + len(set(item.targets)) if item.kind == Kind.MULTI else 0
        return 12 + 5 + len(item.payload) + extra + (13 if self.cfg.signing_key else 0)

    def _merge_multicast(self, q: deque[_Item], item: _Item) -> None:
        same = [
            o
            for o in q
            if o is not item and o.kind == Kind.P2P and o.raw_frame is None and o.payload == item.payload
        ]
        if not same or not fits_multicast(len(item.payload), len(item.targets) + len(same)):
            return
        for o in same:
            item.targets.extend(o.targets)
            q.remove(o)
        item.kind = Kind.MULTI
        self.stats.multicast_merged += len(same)

    def _pack(self, item: _Item) -> bytes:
        target, ptype, payload = pack(item.kind, item.targets, item.payload)
        return self._builder.tunnel(payload, target_system=target, payload_type=ptype)

    def _tx_loop(self) -> None:
        self._next_hb = self.clock()
        while True:
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
            for q in self._queues:
                self.stats.dropped_radio_down += len(q)
                q.clear()
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
        first, longest = self.cfg.reopen_backoff
        backoff, next_log = first, t0 + 1.0
        while True:
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
                break
            except LinkOpenError as exc:
                if not self.cfg.reopen_radio:  # lent, and gone meanwhile: as any loss without reopening
                    log.info("bridge %s: radio %s lost: %s", self.name, url, exc)
                    self.link_lost = True
                    self._tell("lost", str(exc))
                    return False
                now = self.clock()
                if now >= next_log:  # about once a second, not once per attempt
                    next_log = now + 1.0
                    log.warning("bridge %s: radio still away after %.0f s: %s", self.name, now - t0, exc)
                backoff = min(longest, backoff * 2)
            except RadioError as exc:  # closed by its owner meanwhile
                log.info("bridge %s: radio %s not reopened: %s", self.name, url, exc)
                self.link_lost = True
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

    def handle_frame(self, frame: Frame) -> None:
        """Process one frame from the radio (public for tests)."""
        self.stats.frames_in += 1
        if self._verifier is not None and not self._verifier.check(frame):
            vs = self._verifier.stats
            self.stats.unsigned, self.stats.bad_signature, self.stats.replayed = (
                vs.unsigned,
                vs.bad_signature,
                vs.replayed,
            )
            return
        if frame.msgid == MSG_RADIO_STATUS:
            f = radio_status_fields(frame)
            report = RadioState(f["rssi"], f["remrssi"], f["txbuf"], f["noise"], f["remnoise"], f["rxerrors"])
            with self._cond:
                why = self.guard.offer(frame.sysid, frame.compid, report, self.clock())
                if why is None:
                    self.stats.radio_status_accepted += 1
                else:
                    self.stats.radio_status_rejected += 1
                    self._log_once(
                        ("radio_status", why),
                        "bridge %s: RADIO_STATUS rejected (%s): not plausibly from the local radio",
                        self.name,
                        why,
                    )
            return
        if frame.msgid != MSG_TUNNEL:
            return
        try:
            tun = unpack_tunnel(frame.payload)
        except DecodeError:
            self.stats.decode_errors += 1
            return
        if tun is None:
            return
        kind, target, ids, data = tun
        sender = frame.sysid
        if sender == self.id:
            self._conflict(self.name, sender, reason="a frame from another radio uses our id")
            return
        if target not in (0, self.id):
            self.stats.not_for_us += 1
            return
        if kind == Kind.MULTI:
            if self.id not in ids:
                self.stats.not_for_us += 1
                return
            kind = Kind.P2P
        try:
            msg = decode(data)
        except VersionMismatch as exc:
            self.stats.version_mismatch += 1
            self._log_once(("version", sender), "bridge %s: agent %d: %s", self.name, sender, exc)
            return
        except DecodeError:
            self.stats.decode_errors += 1
            return
        if kind == Kind.ADVERTIZE:
            if not isinstance(msg, Advertize) or msg.sender != sender:
                self.stats.decode_errors += 1
                return
            if not self._learn(msg.name, msg.sender):
                return
            self._publish(KEY_ADVERTIZE, data)
        elif kind == Kind.GS_ADVERTIZE:
            # agents announce themselves to ground stations here, and a station (id 255)
            # announces itself the same way: both teach the bridge a name for replies
            if not isinstance(msg, GSAdvertize) or msg.sender != sender:
                self.stats.decode_errors += 1
                return
            if not self._learn(msg.name, msg.sender):
                return
            self._publish(KEY_GS_ADVERTIZE, data)
        elif kind == Kind.P2P:
            if isinstance(msg, NameConflict) and msg.sender == sender:
                self._log_once(
                    ("nc", msg.name),
                    "bridge %s: name/id conflict reported by agent %d for %r (other id %d)",
                    self.name,
                    sender,
                    msg.name,
                    msg.other_id,
                )
            self._publish(inbox_key(self.name), data)
        else:
            peer = self._by_id.get(sender)
            if peer is None:
                self.stats.unknown_sender += 1
                return
            key = pose_key(peer.name) if kind == Kind.POSE else state_key(peer.name)
            self._publish(key, data)

    def _publish(self, key: str, data: bytes) -> None:
        self.session.put(key, data, attachment=ATTACHMENT)
        self.stats.published += 1

    def _learn(self, name: str, agent_id: int) -> bool:
        """Record name <-> id; False (and a conflict report) if it clashes."""
        now = self.clock()
        by_name, by_id = self._by_name.get(name), self._by_id.get(agent_id)
        if (by_name is None or by_name.id == agent_id) and (by_id is None or by_id.name == name):
            peer = by_name or _Peer(agent_id, name, now)
            peer.seen = now
            self._by_name[name] = self._by_id[agent_id] = peer
            return True
        # a stale mapping (not heard for 30 s) gives way to the new claim
        stale = [p for p in (by_name, by_id) if p is not None and now - p.seen > 30.0]
        if stale and len(stale) == len([p for p in (by_name, by_id) if p is not None]):
            for p in stale:
                self._by_name.pop(p.name, None)
                self._by_id.pop(p.id, None)
            return self._learn(name, agent_id)
        other = (
            by_name.id
            if by_name is not None and by_name.id != agent_id
            else (by_id.id if by_id is not None else agent_id)
        )
        self._conflict(name, agent_id, reason=f"also claimed by id {other}", other=other)
        return False

    def _conflict(self, name: str, agent_id: int, *, reason: str, other: int | None = None) -> None:
        self.stats.conflicts += 1
        self._log_once(
            ("conflict", name, agent_id),
            "bridge %s: name/id conflict: %r id %d %s",
            self.name,
            name,
            agent_id,
            reason,
        )
        if self.id > 250:  # a ground station (251..255) reports nothing to agents
            return
        note = (
            NameConflict(self.id, name, other if other is not None and 1 <= other <= 250 else agent_id)
            if 1 <= agent_id <= 250
            else None
        )
        if note is None:
            return
        data = encode(note)
        targets = {agent_id} | ({other} if other else set())
        for t in sorted(targets - {self.id}):
            if 1 <= t <= 250:
                self._enqueue(_Item(Klass.PROTOCOL, Kind.P2P, [t], data))
        # tell our own agent too (it may be one of the two)
        self._publish(inbox_key(self.name), data)

    def _log_once(self, key: tuple[Any, ...], fmt: str, *args: Any) -> None:
        k = (str(key), 0)
        if k in self._conflicts_logged:
            return
        self._conflicts_logged.add(k)
        log.warning(fmt, *args)


def bridge_message_frame_bytes(msg: Message, *, signed: bool) -> int:
    """Bytes on air of ``msg`` in a TUNNEL frame (for the messages benchmark)."""
    key = b"\0" * 32 if signed else None
    return len(
        FrameBuilder(1, COMP_ID, signing_key=key).tunnel(
            encode(msg), target_system=1, payload_type=PAYLOAD_TYPE_BASE + Kind.P2P
        )
    )


def open_node(
    name: str,
    agent_id: int,
    *,
    radio: str | None = None,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    key_file: str | None = None,
    capture: str | None = None,
) -> tuple[Any, Any, RadioBridge | None]:
    """A node's way into the key space: ``(session, link, bridge)``. With ``radio`` the
    Zenoh session has no endpoints and no scouting (only the radio), the link is
    opened (captured to ``capture`` if given) and bridged, MAVLink 2 signed with the
    key in ``key_file``; otherwise a session on the Zenoh endpoints, no link or bridge.
    Whatever was opened is closed again if a later step fails.

    Raises:
        radios.errors.ConfigError: the key file. radios.errors.LinkOpenError: the radio.
        swarm.errors.TransportError: the Zenoh endpoints.
    """
    from radios.link import open_link
    from radios.signing import load_key
    from swarm.runtime.transport import open_session

    key = load_key(key_file) if key_file is not None else None
    if radio is None:
        return open_session(listen, connect), None, None
    link = open_link(radio, capture=capture)
    try:
        session = open_session()
    except BaseException:
        link.close()
        raise
    try:
        bridge = RadioBridge(
            session, link, name=name, agent_id=agent_id, config=BridgeConfig(signing_key=key)
        ).start()
    except BaseException:
        link.close()
        session.close()
        raise
    return session, link, bridge
