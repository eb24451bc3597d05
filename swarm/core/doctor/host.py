"""Verdicts on the companion computer: serial devices, the key file, the clock, Zenoh
endpoints and disk space.

Theory of operation
-------------------
Each verdict is a function from the facts a probe gathered (:mod:`swarm.runtime.doctor`)
to one :class:`~swarm.core.doctor.Check`:

* :func:`device_check`: the radio's or flight controller's serial device exists, is a
  character device and this user can open it (else: the ``dialout`` group, or a session
  that predates joining it, or another program holding the port).
* :func:`key_check`: the signing key file is a regular file this user can read, no
  one else can (mode 0600 or 0400), and holds 32 bytes (raw or 64 hex digits); a
  passphrase warns (its SHA-256 is the key: as strong as the phrase).
* :func:`clock_check`: the wall clock is plausible for MAVLink signing, whose
  timestamps count 10 µs from 2015 in 48 bits: not before :data:`CLOCK_FLOOR` (a
  board without a real-time clock boots in 1970, and peers refuse a stream more than
  a minute behind theirs), not after the 48-bit range ends (2104), and a warning
  beyond :data:`CLOCK_AHEAD_S` after the floor (peers follow a clock that runs
  ahead, so one wrong clock drags the whole swarm's). ``now`` is passed in.
* :func:`parse_zenoh_endpoint` and :func:`zenoh_check`: a Zenoh endpoint
  (``tcp/127.0.0.1:7447``) is well formed, a listen endpoint is free to bind, a
  connect endpoint's host resolves.
* :func:`disk_check`: the capture directory is writable and has room.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from swarm.core.doctor import Check, fail, info, passed, warn

CLOCK_FLOOR = 1767225600.0  # 2026-01-01T00:00:00Z: this release is newer, so is a sane clock
CLOCK_FLOOR_TEXT = "2026-01-01"
CLOCK_AHEAD_S = 20 * 365.25 * 86400  # beyond this after the floor: a clock set wrong
SIGNING_EPOCH = 1420070400.0  # 2015-01-01T00:00:00Z
SIGNING_END = SIGNING_EPOCH + 2**48 / 100_000  # 48-bit timestamps of 10 µs run out (2104)
KEY_SIZE = 32
KEY_FILE_MAX = 4096  # bytes: a larger "key file" is something else
DISK_FAIL = 100 * 2**20  # bytes free under which captures fail
DISK_WARN = 1024 * 2**20  # bytes free under which captures warn
#: Zenoh link protocols whose endpoint is HOST:PORT, and the socket each binds
BINDABLE = {"tcp": "tcp", "tls": "tcp", "ws": "tcp", "udp": "udp", "quic": "udp"}


# -- serial devices ---------------------------------------------------------------------


@dataclass(frozen=True)
class DeviceFacts:
    """A serial device as this process sees it. ``open_error``: ``""`` (opened),
    ``"permission"``, ``"busy"`` (another program holds it) or another reason;
    ``group``: the device's group; ``in_group``: this process has it;
    ``group_member``: the user is listed in it (a later login would have it)."""

    role: str  # "radio" or "fc"
    path: str
    exists: bool
    is_char: bool = False
    open_error: str = ""
    user: str = ""
    group: str = ""
    in_group: bool = False
    group_member: bool = False


def device_check(f: DeviceFacts) -> Check:
    name = f"{f.role} device"
    if not f.exists:
        return fail(
            name,
            f"{f.path}: no such device",
            "plug it in, or check the path (ls -l /dev/serial/by-id/ gives names that survive a replug)",
        )
    if not f.is_char:
        return fail(name, f"{f.path}: not a serial device", "give the path of the serial device")
    if f.open_error == "permission":
        if f.group_member and not f.in_group:
            fix = f"{f.user} is in group {f.group} but this session is older: log out and in again"
        else:
            fix = f"sudo usermod -aG {f.group or 'dialout'} {f.user or '$USER'}, then log out and in again"
        return fail(name, f"{f.path}: permission denied for {f.user or 'this user'}", fix)
    if f.open_error == "busy":
        return fail(
            name,
            f"{f.path}: in use by another program",
            "stop it first (a running swarm agent or its service, ModemManager, a ground station)",
        )
    if f.open_error:
        return fail(name, f"{f.path}: cannot open: {f.open_error}", "check the device and its driver (dmesg)")
    return passed(name, f"{f.path} opens for {f.user or 'this user'}")


def same_device_check(radio: str, fc: str) -> Check | None:
    """A failure when the radio and the flight controller name the same device."""
    if radio != fc:
        return None
    return fail("devices", f"--radio and --fc both name {radio}", "give each its own serial device")


# -- the signing key ----------------------------------------------------------------------


@dataclass(frozen=True)
class KeyFacts:
    """The key file as this process sees it. ``kind``: ``raw`` (32 bytes), ``hex`` (64
    hex digits), ``passphrase``, ``empty`` or ``""`` when not read; ``error``: why it
    could not be read."""

    path: str
    exists: bool
    is_file: bool = False
    mode: int = 0
    owner: int = -1
    uid: int = -1
    size: int = 0
    kind: str = ""
    error: str = ""


def key_checks(f: KeyFacts | None, *, on_radio: bool) -> list[Check]:
    """The key file's checks (``f`` None: no ``--key`` given)."""
    if f is None:
        if not on_radio:
            return [
                info("key", "none (signing covers the radio's frames; this agent meets others over Zenoh)")
            ]
        return [
            warn(
                "key",
                "no --key: the radio's frames go unsigned, any radio in range can talk to the swarm",
                "head -c 32 /dev/urandom > swarm.key && chmod 600 swarm.key, the same file on every "
                "agent and the station, and --key swarm.key",
            )
        ]
    if not f.exists:
        return [fail("key", f"{f.path}: no such file", "copy the swarm's key file there, or fix --key")]
    if not f.is_file:
        return [fail("key", f"{f.path}: not a regular file", "give the path of the key file")]
    out = [_key_mode(f)]
    if f.owner != f.uid:
        out.append(
            warn(
                "key owner",
                f"{f.path}: owned by uid {f.owner}, not this user (uid {f.uid})",
                f"chown the key to the user that runs the agent: sudo chown $(id -u) {f.path}",
            )
        )
    out.append(_key_content(f))
    return out


def _key_mode(f: KeyFacts) -> Check:
    perm = f.mode & 0o777
    if perm & 0o077:
        who = "others" if perm & 0o007 else "its group"
        return fail("key mode", f"{f.path}: mode {perm:04o}: readable by {who}", f"chmod 600 {f.path}")
    return passed("key mode", f"{f.path}: mode {perm:04o}")


def _key_content(f: KeyFacts) -> Check:
    if f.error:
        return fail(
            "key", f"{f.path}: cannot read: {f.error}", "run as the agent's user, or fix the file's owner"
        )
    if f.size > KEY_FILE_MAX:
        return fail("key", f"{f.path}: {f.size} bytes: not a key file", "give the swarm's 32-byte key file")
    if f.kind == "raw":
        return passed("key", f"{f.path}: {KEY_SIZE} bytes")
    if f.kind == "hex":
        return passed("key", f"{f.path}: 64 hex digits ({KEY_SIZE} bytes)")
    if f.kind == "passphrase":
        return warn(
            "key",
            f"{f.path}: a passphrase of {f.size} bytes, not {KEY_SIZE} random bytes (the key is its SHA-256)",
            "use a random key: head -c 32 /dev/urandom > FILE, on every agent and the station",
        )
    return fail("key", f"{f.path}: empty", "write the swarm's key into it (32 bytes)")


# -- the clock ----------------------------------------------------------------------------


def utc_text(t: float) -> str:
    """Unix seconds as ``2026-11-24 21:20 UTC`` (proleptic Gregorian, no clock read)."""
    days, rest = divmod(int(t // 60), 1440)
    z = days + 719468  # days from 0000-03-01 (H. Hinnant's civil_from_days)
    era, doe = divmod(z, 146097)
    yoe = (doe - doe // 1460 + doe // 36524 - doe // 146096) // 365
    doy = doe - (365 * yoe + yoe // 4 - yoe // 100)
    mp = (5 * doy + 2) // 153
    day, month = doy - (153 * mp + 2) // 5 + 1, mp + 3 if mp < 10 else mp - 9
    year = yoe + era * 400 + (month <= 2)
    return f"{year:04d}-{month:02d}-{day:02d} {rest // 60:02d}:{rest % 60:02d} UTC"


def clock_check(now: float) -> Check:
    """Is the wall clock ``now`` (Unix seconds) plausible for MAVLink signing?"""
    if not math.isfinite(now):
        return fail("clock", f"the clock reads {now}", "set the clock")
    if now < CLOCK_FLOOR:
        years = (now - SIGNING_EPOCH) / (365.25 * 86400)
        seen = f"{utc_text(now)}: before {CLOCK_FLOOR_TEXT}"
        if now < SIGNING_EPOCH:
            seen += " and before MAVLink signing's epoch (2015): signing timestamps cannot be made"
        else:
            seen += f" ({years:.1f} years after signing's 2015 epoch)"
        return fail(
            "clock",
            seen,
            "set the clock (an RTC, NTP: timedatectl set-ntp true, or date -s) before the agent starts: "
            "peers refuse signed frames more than a minute behind theirs",
        )
    if now >= SIGNING_END:
        return fail("clock", f"{utc_text(now)}: beyond signing's 48-bit timestamps (2104)", "set the clock")
    if now > CLOCK_FLOOR + CLOCK_AHEAD_S:
        return warn(
            "clock",
            f"{utc_text(now)}: more than 20 years after {CLOCK_FLOOR_TEXT}",
            "check the clock: peers follow a signing clock that runs ahead",
        )
    return passed("clock", f"{utc_text(now)}: plausible for signing")


# -- Zenoh ----------------------------------------------------------------------------------


def parse_zenoh_endpoint(text: str) -> tuple[str, str, int]:
    """``tcp/127.0.0.1:7447`` -> ``("tcp", "127.0.0.1", 7447)`` (``[v6]`` brackets
    dropped; metadata after ``?`` or ``#`` ignored).

    Raises:
        ValueError: not ``PROTO/HOST:PORT`` with a port 0..65535 (for a protocol
            that takes a host and port: :data:`BINDABLE`), or an unknown protocol
            shape (the message says which).
    """
    proto, sep, rest = text.partition("/")
    proto = proto.strip().lower()
    if not sep or not proto or not rest:
        raise ValueError(f"{text!r}: expected PROTO/ADDRESS, e.g. tcp/127.0.0.1:7447")
    if proto not in BINDABLE:
        raise ValueError(f"{text!r}: protocol {proto!r} is not checked here ({', '.join(BINDABLE)} are)")
    address = rest.split("?", 1)[0].split("#", 1)[0]
    host, colon, port_s = address.rpartition(":")
    digits = port_s.isascii() and port_s.isdigit() and len(port_s) <= 5
    if not colon or not digits or not 0 <= int(port_s) <= 65535:
        raise ValueError(f"{text!r}: expected {proto}/HOST:PORT with a port 0..65535")
    host = host.strip("[]")
    if not host:
        raise ValueError(f"{text!r}: no host")
    return proto, host, int(port_s)


@dataclass(frozen=True)
class ZenohFacts:
    """One endpoint: ``role`` ``listen`` or ``connect``; ``parse_error`` from
    :func:`parse_zenoh_endpoint`, or ``unchecked`` (a protocol the probe cannot try),
    or ``error``: why binding (listen) or resolving (connect) failed; empty if it worked."""

    endpoint: str
    role: str
    parse_error: str = ""
    unchecked: bool = False
    error: str = ""


def zenoh_check(f: ZenohFacts) -> Check:
    name = f"zenoh {f.role}"
    if f.unchecked:
        return info(name, f"{f.endpoint}: {f.parse_error}")
    if f.parse_error:
        return fail(name, f.parse_error, "write it as PROTO/HOST:PORT, e.g. tcp/192.168.1.10:7447")
    if f.role == "listen" and f.error:
        return fail(
            name,
            f"{f.endpoint}: cannot bind: {f.error}",
            "use a free port and an address of this machine (is an agent already running?)",
        )
    if f.error:
        return fail(name, f"{f.endpoint}: {f.error}", "use an address, or a name this machine resolves")
    what = "free" if f.role == "listen" else "resolves"
    return passed(name, f"{f.endpoint}: {what}")


# -- disk ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DiskFacts:
    """The capture directory (or the nearest existing parent of it): free bytes, and
    whether this user can write there; ``error``: why it could not be looked at."""

    path: str
    free: int = 0
    writable: bool = False
    error: str = ""


def disk_check(f: DiskFacts) -> Check:
    if f.error:
        return fail("disk", f"{f.path}: {f.error}", "give a capture directory that exists")
    if not f.writable:
        return fail(
            "disk", f"{f.path}: not writable by this user", f"chown or chmod {f.path}, or capture elsewhere"
        )
    mb = f.free / 2**20
    if f.free < DISK_FAIL:
        return fail("disk", f"{f.path}: {mb:.0f} MB free", "free space, or capture to another disk")
    if f.free < DISK_WARN:
        return warn("disk", f"{f.path}: {mb:.0f} MB free", "free space before a long flight day")
    return passed("disk", f"{f.path}: {mb / 1024:.1f} GB free")


__all__ = [
    "CLOCK_FLOOR",
    "DeviceFacts",
    "DiskFacts",
    "KeyFacts",
    "ZenohFacts",
    "clock_check",
    "device_check",
    "disk_check",
    "key_checks",
    "parse_zenoh_endpoint",
    "same_device_check",
    "zenoh_check",
]
