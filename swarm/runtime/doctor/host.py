"""Probes of the companion computer: serial devices, the key file, Zenoh endpoints, disk.

Theory of operation
-------------------
Each probe looks and returns facts (:mod:`swarm.core.doctor.host`); none judges, none
writes, none raises for what it finds. They are careful with what they touch:

* :func:`device_facts` stats the device, opens it without becoming its controlling
  terminal and without blocking, tries the lock pyserial's ``exclusive`` users take,
  and lists the other processes that hold it open (``/proc/PID/fd``): a running agent
  opens its radio without a lock, and the doctor must not send ``+++`` into a radio
  an agent is flying with.
* :func:`key_facts` opens the key file non-blocking and reads it only once ``fstat``
  says it is a regular file of at most 4 KiB: a FIFO or ``/dev/zero`` given as the key
  neither hangs nor floods the check. The key's bytes are classified and dropped.
* :func:`zenoh_facts` binds each listen endpoint's address (and closes it at once)
  and resolves each connect endpoint's host; it connects to nothing.
* :func:`disk_facts` measures the capture directory, or its nearest existing parent.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import grp
import os
import pwd
import shutil
import socket
import stat
from pathlib import Path

from swarm.core.doctor.host import (
    BINDABLE,
    KEY_FILE_MAX,
    KEY_SIZE,
    DeviceFacts,
    DiskFacts,
    KeyFacts,
    ZenohFacts,
    parse_zenoh_endpoint,
)

#: Zenoh protocols the doctor knows but cannot try (no host and port to bind)
ZENOH_UNCHECKED = frozenset({"unixsock-stream", "unixpipe", "serial", "vsock"})


def _user() -> str:
    try:
        return pwd.getpwuid(os.getuid()).pw_name
    except KeyError:
        return str(os.getuid())


def _group(gid: int, user: str) -> tuple[str, bool]:
    """(name of group ``gid``, whether ``user`` is listed in it or has it as primary)."""
    try:
        g = grp.getgrgid(gid)
    except KeyError:
        return str(gid), False
    try:
        primary = pwd.getpwnam(user).pw_gid == gid
    except KeyError:
        primary = False
    return g.gr_name, primary or user in g.gr_mem


def holders(path: str) -> list[str]:
    """``PID (command)`` of each other process with ``path`` open (those this user
    may look at)."""
    target = os.path.realpath(path)
    found = []
    me = os.getpid()
    with contextlib.suppress(OSError):
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit() or int(entry.name) == me:
                continue
            try:
                fds = os.listdir(f"/proc/{entry.name}/fd")
                if any(os.readlink(f"/proc/{entry.name}/fd/{fd}") == target for fd in fds):
                    comm = Path(f"/proc/{entry.name}/comm").read_text().strip()
                    found.append(f"{entry.name} ({comm})")
            except OSError:
                continue
    return found


def _open_error(path: str) -> str:
    """Open ``path`` as a serial port would be, try pyserial's lock, close: "" or why not."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        if exc.errno in (errno.EACCES, errno.EPERM):
            return "permission"
        if exc.errno == errno.EBUSY:
            return "busy"
        return exc.strerror or str(exc)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
    except OSError:
        return "busy"
    finally:
        os.close(fd)
    return "busy" if holders(path) else ""


def device_facts(path: str, role: str) -> DeviceFacts:
    """What this process can do with the serial device ``path``."""
    user = _user()
    try:
        st = os.stat(path)
    except (FileNotFoundError, ValueError):  # ValueError: a NUL in the path, no device has one
        return DeviceFacts(role, path, exists=False, user=user)
    except OSError as exc:
        return DeviceFacts(
            role, path, exists=True, is_char=True, open_error=exc.strerror or str(exc), user=user
        )
    if not stat.S_ISCHR(st.st_mode):
        return DeviceFacts(role, path, exists=True, user=user)
    group, member = _group(st.st_gid, user)
    in_group = st.st_gid == os.getegid() or st.st_gid in os.getgroups()
    return DeviceFacts(
        role,
        path,
        exists=True,
        is_char=True,
        open_error=_open_error(path),
        user=user,
        group=group,
        in_group=in_group,
        group_member=member,
    )


def _key_kind(raw: bytes) -> str:
    """How :func:`radios.signing.load_key` reads these bytes: raw, hex, passphrase, empty."""
    if len(raw) == KEY_SIZE:
        return "raw"
    text = raw.decode("utf-8", "replace").strip()
    if not text:
        return "empty"
    if len(text) == 2 * KEY_SIZE:
        try:
            bytes.fromhex(text)
            return "hex"
        except ValueError:
            pass
    return "passphrase"


def key_facts(path: str) -> KeyFacts:
    """The key file ``path`` as this process sees it (contents classified, not kept)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    except (FileNotFoundError, ValueError):  # ValueError: a NUL in the path, no file has one
        return KeyFacts(path, exists=False)
    except OSError as exc:
        try:
            st = os.stat(path)
        except OSError:
            return KeyFacts(path, exists=True, is_file=True, error=exc.strerror or str(exc))
        return KeyFacts(
            path, True, stat.S_ISREG(st.st_mode), st.st_mode, st.st_uid, os.getuid(), st.st_size,
            error=exc.strerror or str(exc),
        )  # fmt: skip
    try:
        st = os.fstat(fd)
        facts = KeyFacts(path, True, stat.S_ISREG(st.st_mode), st.st_mode, st.st_uid, os.getuid(), st.st_size)
        if not facts.is_file or st.st_size > KEY_FILE_MAX:
            return facts
        with os.fdopen(os.dup(fd), "rb") as f:
            raw = f.read(KEY_FILE_MAX + 1)
        return KeyFacts(path, True, True, st.st_mode, st.st_uid, os.getuid(), len(raw), _key_kind(raw))
    except OSError as exc:
        return KeyFacts(path, exists=True, is_file=True, error=exc.strerror or str(exc))
    finally:
        os.close(fd)


def _bind_error(proto: str, host: str, port: int) -> str:
    kind = socket.SOCK_STREAM if BINDABLE[proto] == "tcp" else socket.SOCK_DGRAM
    try:
        infos = socket.getaddrinfo(host, port, type=kind)
    except (socket.gaierror, UnicodeError, ValueError) as exc:
        return f"cannot resolve {host!r}: {exc}"
    family, socktype, sockproto, _, address = infos[0]
    try:
        with socket.socket(family, socktype, sockproto) as s:
            if kind == socket.SOCK_STREAM:  # as a server does: a port in TIME_WAIT is free
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(address)
    except OSError as exc:
        return exc.strerror or str(exc)
    return ""


def _resolve_error(host: str, port: int) -> str:
    try:
        socket.getaddrinfo(host, port)
    except (socket.gaierror, UnicodeError, ValueError) as exc:
        return f"cannot resolve host {host!r}: {exc}"
    return ""


def zenoh_facts(endpoint: str, role: str) -> ZenohFacts:
    """Parse ``endpoint``; bind it (``listen``) or resolve its host (``connect``)."""
    try:
        proto, host, port = parse_zenoh_endpoint(endpoint)
    except ValueError as exc:
        unchecked = endpoint.partition("/")[0].strip().lower() in ZENOH_UNCHECKED
        return ZenohFacts(endpoint, role, parse_error=str(exc), unchecked=unchecked)
    error = _bind_error(proto, host, port) if role == "listen" else _resolve_error(host, port)
    return ZenohFacts(endpoint, role, error=error)


def disk_facts(path: str) -> DiskFacts:
    """Free space and write access where captures go (``path`` or its nearest existing
    parent; the parent of an existing file)."""
    if "\x00" in path:
        return DiskFacts(path, error="a path cannot contain a NUL character")
    p = Path(path)
    try:
        while not p.exists() and p != p.parent:
            p = p.parent
        if p.exists() and not p.is_dir():
            p = p.parent
        free = shutil.disk_usage(p).free
    except (OSError, ValueError) as exc:
        return DiskFacts(path, error=getattr(exc, "strerror", None) or str(exc))
    return DiskFacts(str(p), free=free, writable=os.access(p, os.W_OK | os.X_OK))


__all__ = ["device_facts", "disk_facts", "holders", "key_facts", "zenoh_facts"]
