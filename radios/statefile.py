"""A node's small state files: written so a power cut leaves the old one or the new one,
read as hostile input.

Theory of operation
-------------------
What a node keeps across restarts (its signing clock, a station's replay guard) lives
in small files in its state folder. :func:`write_atomic` writes the new content to a
temporary file beside the old one (``.NAME.tmp``, created with ``O_EXCL | O_NOFOLLOW``
and mode 0600), ``fsync``\\ s it, renames it over the old name and ``fsync``\\ s the
folder: a power cut at any moment leaves either the old file or the new one, whole
(ext4, the Pi's file system, orders the data before the rename). A temporary file
left by a cut is removed by the next write. The rename replaces whatever had the
name (a symbolic link planted there is replaced, never followed).

:func:`read_state` reads such a file without trusting it: opened without following a
symbolic link and without blocking (a FIFO), only a regular file of at most ``limit``
bytes, UTF-8 JSON whose top level is an object. Every refusal is one
:class:`ValueError` whose text completes "PATH: ..."; a missing file is
:class:`FileNotFoundError` (a first start, not a fault).
"""

from __future__ import annotations

import errno
import json
import os
import stat
from pathlib import Path
from typing import Any


def write_atomic(path: str | Path, data: bytes) -> None:
    """Replace ``path`` with ``data`` (mode 0600), durably: the old content or the new,
    never a mix.

    Raises:
        OSError: the folder is missing or not writable, the disk is full...
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(tmp, flags, 0o600)
    except FileExistsError:  # left by a power cut (or a crash) in the middle of a write
        os.unlink(tmp)
        fd = os.open(tmp, flags, 0o600)
    try:
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    folder = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.fsync(folder)  # the rename itself survives a power cut
    finally:
        os.close(folder)


def read_state(path: str | Path, limit: int) -> dict[str, Any]:
    """The JSON object in the state file ``path``.

    Raises:
        FileNotFoundError: there is none (yet).
        ValueError: a symbolic link, not a regular file, larger than ``limit`` bytes,
            unreadable, not UTF-8 JSON, or not an object.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except FileNotFoundError:
        raise
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ValueError("a symbolic link") from None
        raise ValueError(exc.strerror or str(exc)) from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ValueError("not a regular file")
        chunks: list[bytes] = []
        size = 0
        while size <= limit:
            chunk = os.read(fd, limit + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise ValueError(exc.strerror or str(exc)) from None
    finally:
        os.close(fd)
    if size > limit:
        raise ValueError(f"larger than {limit} bytes")
    try:
        obj = json.loads(b"".join(chunks).decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise ValueError("not a state file (not JSON)") from None
    if not isinstance(obj, dict):
        raise ValueError("not a state file (not a JSON object)")
    return obj


__all__ = ["read_state", "write_atomic"]
