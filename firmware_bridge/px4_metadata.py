"""PX4's event metadata found and read (the I/O beside :mod:`firmware_bridge.px4_events`).

Where the words of PX4's events come from, in this order: the file given to
:func:`~firmware_bridge.driver.connect` (``px4_events=``), ``$PX4_EVENTS``, else the
SITL folder's own build (``$SITL_DIR/px4/etc/extras/all_events.json.xz``, the metadata
of the PX4 that runs there). A PX4 build writes it to
``build/<target>/etc/extras/all_events.json.xz``; a vehicle serves it over MAVLink FTP
(not fetched here). Plain ``.json`` or xz-compressed; at most :data:`MAX_BYTES`.
"""

from __future__ import annotations

import json
import lzma
import os
from pathlib import Path

from firmware_bridge.errors import ConnectError
from firmware_bridge.px4_events import EventCatalog

__all__ = ["MAX_BYTES", "find_metadata", "load_catalog"]

MAX_BYTES = 16 * 1024 * 1024  # PX4 v1.15's is 160 kB


def find_metadata(given: str | os.PathLike[str] | None = None) -> Path | None:
    """The metadata file to read: ``given``, ``$PX4_EVENTS``, the SITL folder's, or None."""
    if given is not None:
        return Path(given)
    env = os.environ.get("PX4_EVENTS", "").strip()
    if env:
        return Path(env)
    from firmware_bridge.sitl import find_sitl

    d = find_sitl()
    if d is not None:
        built = d / "px4" / "etc" / "extras" / "all_events.json.xz"
        if built.is_file():
            return built
    return None


def load_catalog(path: Path) -> EventCatalog:
    """Read PX4's ``all_events.json`` (or ``.json.xz``).

    Raises:
        ConnectError: unreadable, too large, not xz or not JSON (one line).
    """
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_BYTES + 1)
        if raw[:6] == b"\xfd7zXZ\x00":
            dec = lzma.LZMADecompressor()
            raw = dec.decompress(raw, MAX_BYTES + 1)
        if len(raw) > MAX_BYTES:
            raise ConnectError(f"PX4 event metadata {path}: larger than {MAX_BYTES // 2**20} MiB")
        data = json.loads(raw)
    except OSError as exc:
        raise ConnectError(f"PX4 event metadata {path}: {exc.strerror or exc}") from None
    except (lzma.LZMAError, ValueError, RecursionError) as exc:
        raise ConnectError(f"PX4 event metadata {path}: not PX4's all_events.json ({exc})") from None
    if not isinstance(data, dict) or "components" not in data:
        raise ConnectError(f"PX4 event metadata {path}: no 'components': not PX4's all_events.json")
    return EventCatalog(data)
