"""``swarm keygen FILE``: write a new swarm signing key (32 random bytes, mode 0600).

Theory of operation. The key is 32 bytes from :mod:`secrets`, the raw form
:func:`radios.signing.load_key` reads first (it also reads 64 hex digits or a
passphrase, for keys made elsewhere, e.g. MAVProxy's ``signing setup``). FILE is
created with ``O_CREAT | O_EXCL | O_NOFOLLOW`` and mode 0600, then set to exactly
0600 with ``fchmod`` (a umask can only narrow the mode; this makes it exact), written
and flushed to the disk (``fsync``, and the folder's entry too). An existing FILE of
any kind (a file, a folder, a symbolic link, even a dangling one) is refused, never
overwritten; the folder must exist (it is not created: where a key lives is the
operator's choice). A failure after the file was created removes it, so FILE is
never left partly written. Exit 0 with the instructions to copy the key to every
node, 2 for an existing FILE or a missing or forbidden folder, 1 for a failed write.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import os
import secrets

from swarm.cli.util import UsageError, guarded
from swarm.errors import SwarmError

PROG = "swarm keygen"
KEY_BYTES = 32


class KeyWriteError(SwarmError):
    """The key could not be written (a full disk, an I/O error): nothing is left behind."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Write a new swarm signing key: 32 random bytes, mode 0600. The same file "
        "goes to every aircraft and ground station (--key FILE). Refuses to overwrite.",
    )
    p.add_argument("file", metavar="FILE", help="the key file to create (its folder must exist)")
    return p


def _create(path: str) -> int:
    """The new file's descriptor. Raises UsageError (exists, no folder, forbidden) or
    KeyWriteError."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        return os.open(path, flags, 0o600)
    except FileExistsError:
        raise UsageError(
            f"{path} exists: a key is never overwritten (remove it first to replace it)"
        ) from None
    except (FileNotFoundError, NotADirectoryError) as exc:
        folder = os.path.dirname(path) or "."
        if not os.path.isdir(folder):
            raise UsageError(f"{path}: the folder {folder} does not exist (create it first)") from None
        raise UsageError(f"{path}: {exc.strerror}") from None
    except (PermissionError, IsADirectoryError) as exc:
        raise UsageError(f"{path}: {exc.strerror}") from None
    except OSError as exc:
        raise KeyWriteError(f"{path}: {exc.strerror or exc}") from None


def write_key(path: str) -> bytes:
    """Create ``path`` holding a new key (returned). Raises UsageError or KeyWriteError,
    leaving nothing at ``path``."""
    key = secrets.token_bytes(KEY_BYTES)
    fd = _create(path)
    try:
        os.fchmod(fd, 0o600)
        view = memoryview(key)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    except BaseException as exc:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(path)
        if isinstance(exc, OSError):
            raise KeyWriteError(f"{path}: {exc.strerror or exc}: no key written") from None
        raise
    os.close(fd)
    folder = os.open(os.path.dirname(os.path.abspath(path)), os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(folder)  # the new entry survives a power cut too
    except OSError:
        pass  # some file systems cannot sync a folder: the key itself is on disk
    finally:
        os.close(folder)
    return key


def instructions(path: str, key: bytes) -> str:
    """What to do with the new key."""
    where = os.path.abspath(path)
    digest = hashlib.sha256(key).hexdigest()
    return "\n".join(
        [
            f"wrote a new swarm signing key to {where} (32 random bytes, mode 0600)",
            "copy it to every aircraft and to the ground station, keeping it mode 0600, e.g.",
            f"  scp -p {where} USER@HOST:/etc/uav-swarm/swarm.key   (-p keeps the mode)",
            f"  install -m 0600 {where} /etc/uav-swarm/swarm.key     (from a USB stick)",
            f"check each copy: 'sha256sum FILE' must print {digest}",
            "then give it to every node: swarm agent --key FILE, swarm gcs --key FILE",
            '(or key = "FILE" in their config files). Whoever has it can command the swarm:',
            "never send it unencrypted, never commit it.",
        ]
    )


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    key = write_key(a.file)
    print(instructions(a.file, key), flush=True)
    return 0
