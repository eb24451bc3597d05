"""Reading a small file a user named (a key, a token) without trusting what it is.

Theory of operation
-------------------
A path in a flag or a config file may name anything: a FIFO nobody writes to (a
blocking ``open`` waits for ever), an endless device such as ``/dev/zero`` (a plain
read fills the memory until the kernel kills the process), a folder, or a file far
larger than any key. :func:`read_small_file` opens without blocking and without
becoming the controlling terminal's owner, accepts only a regular file, and reads at
most ``limit`` bytes (one more to tell a file that is too large). Errors are
``OSError``-free: one :class:`ValueError` whose text completes "PATH: ...".
"""

from __future__ import annotations

import os
import stat
from pathlib import Path


def read_small_file(path: str | Path, limit: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` of them.

    Raises:
        ValueError: it cannot be opened or read (the OS's reason), it is not a
            regular file, or it is larger than ``limit`` bytes.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
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
    return b"".join(chunks)
