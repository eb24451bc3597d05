"""MAVLink 2 message signing: keys, signing frames, verifying them with replay protection.

Theory of operation
-------------------
A signed MAVLink 2 frame has incompat flag 0x01 and 13 more bytes: link id (1),
timestamp (6, little-endian, units of 10 µs since 2015-01-01) and the first 6
bytes of SHA-256(secret_key + every byte of the frame before the signature).
:class:`~radios.mavlink.FrameBuilder` signs frames, stamped by a
:class:`~radios.mavlink.SigningClock`: the wall clock, strictly increasing, and never
behind the newest timestamp the node has accepted from a peer. :class:`Verifier` checks
the signature and drops replays, as the MAVLink signing specification says: per stream
(sysid, compid, link id) the timestamp must grow, and a frame must not be more than a
minute older than our clock (the specification asks it of a stream's first frame; we
ask it of every frame, or a recording played back slowly to a verifier that never
heard the live stream would pass for as long as it lasted). A frame from the future is
accepted, and our clock moves up to it: a machine booted with its clock behind joins
the swarm's time instead of refusing it. Also stricter than the specification, a frame
stamped before another stream of the same (sysid, compid) began is refused: a
restarted sender opens a new stream (a new link id) stamped later than its last run
began, so such a frame is an earlier run replayed. Without this rule a verifier
started after the sender's restart (which never heard the old stream) took a
recording of it, replayed within the minute, for a live one. Two live senders with
one id (two stations left at the default id) are both heard: each one's stream began
before the other's later frames. Only frames whose signature verified move the clock.

Across a restart of the verifier these rules would start from nothing: a recording of a
sender it never heard (a dead leader, recorded from the air less than a minute before)
passed for a live stream. So a node keeps its clock's mark (the latest time it issued
or accepted) in its state folder (:mod:`radios.signing_state`) and starts its clock
from it: the clock's ``start`` is at least the time the last run had reached, and a
frame stamped before it is refused, whoever sent it: it was on the air before this run
began. A live peer whose clock lags ours is refused only until it hears one of our
frames (its clock then moves up to ours, as above); of two nodes started together, the
one with the later start is always heard by the other, which then catches up. One mark
is kept, not each stream's last timestamp: every stream's last is at most the mark, so
the start reference refuses all that a restored table of streams would, and also what
the node never heard (frames recorded while it was down).

Keys: :func:`load_key` reads 32 raw bytes, 64 hex digits, or else a passphrase
turned into a key by SHA-256 as MAVProxy's ``signing setup`` does.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from radios.errors import ConfigError
from radios.mavlink import IFLAG_SIGNED, SIGNATURE_LEN, SIGNING_EPOCH, STX_V2, Frame, SigningClock
from radios.smallfile import read_small_file

EPOCH_2015 = SIGNING_EPOCH
MAX_SKEW_TICKS = 60 * 100_000  # a new stream may be one minute behind our clock
KEY_FILE_MAX = 4096  # bytes: a key is 32, or 64 hex digits, or a passphrase


def key_from_passphrase(passphrase: str) -> bytes:
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def load_key(path: str | Path) -> bytes:
    """Read a signing key file (a regular file of at most 4 KiB: a FIFO, a device or a
    folder is refused, never read for ever).

    Raises:
        ConfigError: missing, unreadable, not a regular file, too large or empty.
    """
    try:
        raw = read_small_file(path, KEY_FILE_MAX)
    except ValueError as exc:
        raise ConfigError(f"signing key {path}: {exc}") from None
    if len(raw) == 32:
        return raw
    text = raw.decode("utf-8", "replace").strip()
    if not text:
        raise ConfigError(f"signing key {path} is empty")
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return key_from_passphrase(text)


def now_ticks(clock: Callable[[], float] = time.time) -> int:
    return int((clock() - EPOCH_2015) * 100_000)


def signature(key: bytes, signed_part: bytes) -> bytes:
    return hashlib.sha256(key + signed_part).digest()[:6]


@dataclass
class VerifyStats:
    accepted: int = 0
    unsigned: int = 0
    bad_signature: int = 0
    replayed: int = 0


@dataclass
class Verifier:
    """Checks signed frames; ``allow_unsigned`` decides which unsigned frames pass
    (by default only RADIO_STATUS with the ids a SiK radio gives its own, sysid 51
    compid 68; whether it really is the local radio's, the bridge judges)."""

    key: bytes
    clock: SigningClock = field(default_factory=SigningClock)
    allow_unsigned: Callable[[Frame], bool] = lambda f: f.msgid == 109 and f.sysid == 51 and f.compid == 68
    stats: VerifyStats = field(default_factory=VerifyStats)
    _last: dict[tuple[int, int, int], int] = field(default_factory=dict)
    #: per (sysid, compid): each stream's (link id's) first accepted timestamp
    _starts: dict[tuple[int, int], dict[int, int]] = field(default_factory=dict)

    def check(self, frame: Frame) -> bool:
        raw = frame.raw
        if raw[0] != STX_V2 or not raw[2] & IFLAG_SIGNED:
            if self.allow_unsigned(frame):
                return True
            self.stats.unsigned += 1
            return False
        sig = raw[-6:]
        if signature(self.key, raw[:-6]) != sig:
            self.stats.bad_signature += 1
            return False
        link_id = raw[-SIGNATURE_LEN]
        ts = int.from_bytes(raw[-12:-6], "little")
        system = (frame.sysid, frame.compid)
        stream = (frame.sysid, frame.compid, link_id)
        last = self._last.get(stream)
        starts = self._starts.get(system)
        if (
            ts < self.clock.start  # on the air before this run began (radios.signing_state)
            or ts < self.clock.reference() - MAX_SKEW_TICKS  # more than a minute old
            or (last is not None and ts <= last)  # not newer on its stream
            or (starts is not None and any(ts < t0 for lid, t0 in starts.items() if lid != link_id))
        ):  # (the last: stamped before another stream of the sender began: an earlier run)
            self.stats.replayed += 1
            return False
        self._last[stream] = ts
        if last is None:
            self._starts.setdefault(system, {})[link_id] = ts
        self.clock.observe(ts)
        self.stats.accepted += 1
        return True
