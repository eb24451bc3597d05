"""The radio bridge's receiving side: frames from the air into the local key space.

Theory of operation
-------------------
:meth:`AirToLocal.handle_frame` takes each frame the radio link delivers (on the
bridge's receive thread):

* with signing on, a frame that is unsigned (but the local RADIO_STATUS), badly
  signed or replayed is dropped and counted;
* RADIO_STATUS is offered to the bridge's :class:`~swarm.core.bridge.radio_guard.RadioStatusGuard`,
  which accepts only a report plausibly from the local radio (a rejection is
  counted and logged once per reason);
* a TUNNEL frame is unpacked (:func:`swarm.core.wire.tunnel.unpack_tunnel`): a frame
  from our own id is a conflict; one addressed to another node (``target_system``,
  or a multicast list without us) is not for us (but a station takes a leader's
  Heartbeat to its members: the task and members it shows); its payload must
  decode (a message of another protocol version is counted and logged once per sender).
  Then the key is rebuilt from the kind and the sender: Advertize and GSAdvertize
  (whose sender must be the frame's) teach the name table
  (:class:`swarm.core.bridge.names.NameTable`) and are published unless the name
  conflicts; P2P goes to our own inbox (a Command to our command key); a pose or state goes under the sender's
  name, if known.

Any frame but RADIO_STATUS carrying our own system id was sent by someone else (a
radio does not echo): MAVProxy or QGroundControl on the same air with the station's
id (both default to 255), or a second node given our id. It is logged once and told
once to the bridge's listeners as ``("id_collision", text)``.

A name conflict is counted, logged once and reported with NameConflict to the
agents involved (:func:`swarm.core.bridge.names.conflict_note`) and to our own agent.
Everything published carries the :data:`ATTACHMENT` marker, so the sending side
never puts it back on air. :class:`AirToLocal` is a part of
:class:`swarm.runtime.bridge.radio_bridge.RadioBridge`, which provides the state it names.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from radios.mavlink import MSG_RADIO_STATUS, MSG_TUNNEL, Frame, radio_status_fields
from radios.signing import Verifier
from swarm.core.bridge.air_queue import AirItem, Klass
from swarm.core.bridge.names import NameTable, conflict_note
from swarm.core.bridge.radio_guard import RadioState, RadioStatusGuard
from swarm.core.wire.codes import is_station
from swarm.core.wire.message_types import Advertize, Command, GSAdvertize, Heartbeat, Message, NameConflict
from swarm.core.wire.messages import decode, encode
from swarm.core.wire.tunnel import Kind, unpack_tunnel
from swarm.errors import DecodeError, VersionMismatch
from swarm.runtime.keyspace.transport import (
    KEY_ADVERTIZE,
    KEY_GS_ADVERTIZE,
    command_key,
    inbox_key,
    pose_key,
    state_key,
)

if TYPE_CHECKING:
    from swarm.runtime.bridge.stats import BridgeStats

log = logging.getLogger("swarm.runtime.bridge.radio_bridge")  # one logger for the whole bridge

ATTACHMENT = b"radio-bridge"


class AirToLocal:
    """The receiving half of :class:`swarm.runtime.bridge.radio_bridge.RadioBridge`."""

    name: str
    id: int
    session: Any
    clock: Callable[[], float]
    stats: BridgeStats
    guard: RadioStatusGuard
    names: NameTable
    _verifier: Verifier | None
    _cond: threading.Condition
    _conflicts_logged: set[tuple[str, int]]

    def _enqueue(self, item: AirItem) -> None:
        raise NotImplementedError  # the bridge's sending side

    def _tell(self, what: str, text: str) -> None:
        raise NotImplementedError  # the bridge's listeners

    def handle_frame(self, frame: Frame) -> None:
        """Process one frame from the radio (public for tests)."""
        self.stats.frames_in += 1
        if frame.sysid == self.id and frame.msgid != MSG_RADIO_STATUS:
            self._own_id_heard(frame)
        if self._verifier is not None and not self._verifier.check(frame):
            vs = self._verifier.stats
            self.stats.unsigned, self.stats.bad_signature, self.stats.replayed = (
                vs.unsigned,
                vs.bad_signature,
                vs.replayed,
            )
            return
        if frame.msgid == MSG_RADIO_STATUS:
            self._radio_status(frame)
        elif frame.msgid == MSG_TUNNEL:
            self._tunnel(frame)

    def _own_id_heard(self, frame: Frame) -> None:
        key = ("own_id", self.id)
        if key in self._conflicts_logged:
            return
        self._conflicts_logged.add(key)
        text = (
            f"system id {self.id} collision: another sender on the air uses this node's id "
            f"({frame.name} from component {frame.compid})"
        )
        log.warning("bridge %s: %s", self.name, text)
        self._tell("id_collision", text)

    def _radio_status(self, frame: Frame) -> None:
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

    def _tunnel(self, frame: Frame) -> None:
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
        if target not in (0, self.id) or (kind == Kind.MULTI and self.id not in ids):
            self.stats.not_for_us += 1
            if kind in (Kind.P2P, Kind.MULTI) and is_station(self.id):
                self._overhear(sender, data)
            return
        if kind == Kind.MULTI:
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
        self._deliver(kind, sender, msg, data)

    def _overhear(self, sender: int, data: bytes) -> None:
        """A station hears a leader's Heartbeat on its way to the members: it is how the
        station learns the task the swarm flies and the leader's member list
        (:meth:`swarm.core.station.core.StationCore.handle`), also after its own restart.
        Only a Heartbeat of the frame's own sender; anything else for others is dropped."""
        if not data or data[0] & 0x1F != Heartbeat.TYPE:
            return  # not a Heartbeat: not decoded
        try:
            msg = decode(data)
        except DecodeError:
            self.stats.decode_errors += 1
            return
        if isinstance(msg, Heartbeat) and msg.sender == sender:
            self.stats.overheard += 1
            self._publish(inbox_key(self.name), data)

    def _deliver(self, kind: Kind, sender: int, msg: Message, data: bytes) -> None:
        """Publish a frame's message (for this node) under its key."""
        if kind in (Kind.ADVERTIZE, Kind.GS_ADVERTIZE):
            # agents announce themselves to ground stations on GSAdvertize, and a
            # station (id 255) announces itself the same way: both teach the bridge a
            # name for replies
            want, key = (
                (Advertize, KEY_ADVERTIZE) if kind == Kind.ADVERTIZE else (GSAdvertize, KEY_GS_ADVERTIZE)
            )
            if not isinstance(msg, want) or msg.sender != sender:
                self.stats.decode_errors += 1
                return
            if self._learn(msg.name, msg.sender):
                self._publish(key, data)
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
            # a Command goes to our command key, the one key a station may command on
            # over Zenoh (swarm.runtime.keyspace.transport): its frame is an ordinary P2P frame
            self._publish(command_key(self.name) if isinstance(msg, Command) else inbox_key(self.name), data)
        else:
            peer = self.names.name_of(sender)
            if peer is None:
                self.stats.unknown_sender += 1
                return
            self._publish(pose_key(peer) if kind == Kind.POSE else state_key(peer), data)

    def _publish(self, key: str, data: bytes) -> None:
        self.session.put(key, data, attachment=ATTACHMENT)
        self.stats.published += 1

    def _learn(self, name: str, agent_id: int) -> bool:
        """Record name <-> id; False (and a conflict report) if it clashes."""
        other = self.names.learn(name, agent_id, self.clock())
        if other is None:
            return True
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
        told = conflict_note(self.id, name, agent_id, other)
        if told is None:
            return
        note, targets = told
        data = encode(note)
        for t in targets:
            self._enqueue(AirItem(Klass.PROTOCOL, Kind.P2P, [t], data))
        # tell our own agent too (it may be one of the two)
        self._publish(inbox_key(self.name), data)

    def _log_once(self, key: tuple[Any, ...], fmt: str, *args: Any) -> None:
        k = (str(key), 0)
        if k in self._conflicts_logged:
            return
        self._conflicts_logged.add(k)
        log.warning(fmt, *args)
