"""Map tiles from an MBTiles file (``swarm gcs --tiles-mbtiles FILE``): one file, offline.

Theory of operation
-------------------
An MBTiles file is an SQLite database (https://github.com/mapbox/mbtiles-spec) with a
``tiles`` table (or view) of ``zoom_level, tile_column, tile_row, tile_data`` and a
``metadata`` table of ``name, value`` pairs (``format``: png, jpg or webp;
``minzoom``, ``maxzoom``, ``attribution``...). Rows count from the south (TMS): the
slippy-map tile ``z/x/y`` the page asks for is row ``2**z - 1 - y``.

The file is the operator's, but it may be anything (a download that went wrong, a
FIFO, a device, a crafted database), so :func:`open_mbtiles` checks before trusting:

* the path is opened without blocking and must be a regular file starting with
  SQLite's 16-byte header (a FIFO nobody writes to, ``/dev/zero`` or a folder is
  refused before SQLite sees it);
* SQLite opens it read-only through a ``file:`` URI whose path is percent-encoded
  (a name holding ``?mode=rwc`` or ``#`` stays a name); queries bind their values,
  and the table names are fixed here, so nothing in the file or its name becomes SQL;
* both tables must answer the queries the server will run, and ``format`` must be
  one of :data:`FORMATS` (vector tiles, ``pbf``, are not drawn by the page);
* every query runs under a progress handler that stops it after
  :data:`MAX_STEPS` SQLite steps (a ``tiles`` view that recurses for ever, a table
  without an index scanned for each tile), and a tile larger than
  :data:`MAX_TILE_BYTES`, or not a blob, is no tile (a query error is logged once
  per reason; a well-formed file, indexed as the specification asks, looks a tile
  up in a few hundred steps). Metadata values are read
  shortened and the attribution is HTML-escaped (the page shows it as HTML).

Any failure to open is one :class:`MbTilesError` with a one-line reason ("FILE:
..."); a bad tile later is ``None`` (the server answers 404), never an exception.
:meth:`MbTiles.tile` is thread-safe (one connection under a lock; the server calls it
from a worker thread so a slow disk does not stall its event loop).
"""

from __future__ import annotations

import html
import logging
import os
import sqlite3
import stat
import threading
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

from swarm.errors import SwarmError

log = logging.getLogger(__name__)

SQLITE_HEADER = b"SQLite format 3\x00"
#: the image formats the page draws, and their content types
FORMATS = {"png": "image/png", "jpg": "image/jpeg", "jpeg": "image/jpeg", "webp": "image/webp"}
#: the largest tile served (bytes): real tiles are tens of KiB
MAX_TILE_BYTES = 1 << 20
#: SQLite virtual-machine steps (in thousands, see set_progress_handler) a query may take
MAX_STEPS = 2000
#: the longest metadata value kept (characters)
MAX_META = 1000
MAX_ZOOM = 24


class MbTilesError(SwarmError):
    """An MBTiles file that cannot be served (the text says why, after the path)."""


@dataclass(frozen=True)
class TileMeta:
    """What the page needs from the metadata."""

    format: str  # png | jpg | webp
    content_type: str
    attribution: str  # HTML-escaped text ("" when absent)
    min_zoom: int
    max_zoom: int


def _check_file(path: Path) -> None:
    """A regular file that starts as an SQLite database. Raises MbTilesError."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise MbTilesError(f"{path}: {exc.strerror or exc}") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise MbTilesError(f"{path}: not a regular file")
        head = os.read(fd, len(SQLITE_HEADER))
    except OSError as exc:
        raise MbTilesError(f"{path}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if head != SQLITE_HEADER:
        raise MbTilesError(f"{path}: not an MBTiles file (not an SQLite database)")


def _text(value: object) -> str:
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return str(value)[:MAX_META] if value is not None else ""


def _zoom(meta: dict[str, str], key: str, default: int) -> int:
    try:
        z = int(meta.get(key, default))
    except ValueError:
        return default
    return min(max(z, 0), MAX_ZOOM)


class MbTiles:
    """One MBTiles file opened read-only. See the module docstring."""

    def __init__(self, path: Path, conn: sqlite3.Connection, meta: TileMeta) -> None:
        self.path = path
        self.meta = meta
        self._conn = conn
        self._lock = threading.Lock()
        self._logged: set[str] = set()

    def tile(self, z: int, x: int, y: int) -> bytes | None:
        """The image of slippy-map tile ``z/x/y``, or None (no such tile, a bad one)."""
        if not (0 <= z <= MAX_ZOOM and 0 <= x < 2**z and 0 <= y < 2**z):
            return None
        row = 2**z - 1 - y
        try:
            with self._lock:
                cur = self._conn.execute(
                    "SELECT CASE WHEN typeof(tile_data) = 'blob' AND length(tile_data) <= ? "
                    "THEN tile_data END FROM tiles "
                    "WHERE zoom_level = ? AND tile_column = ? AND tile_row = ? LIMIT 1",
                    (MAX_TILE_BYTES, z, x, row),
                )
                found = cur.fetchone()
        except sqlite3.Error as exc:  # damaged, interrupted (too slow), locked...
            why = str(exc)[:200]
            if why not in self._logged:  # once per reason: a page asks for hundreds of tiles
                self._logged.add(why)
                log.warning(
                    "mbtiles %s: tile %d/%d/%d: %s (tiles failing so are not found)", self.path, z, x, y, why
                )
            return None
        if found is None or not isinstance(found[0], bytes) or not found[0]:
            return None
        return found[0]

    def close(self) -> None:
        with self._lock:
            self._conn.close()


def _connect(path: Path) -> sqlite3.Connection:
    uri = "file:" + urllib.parse.quote(str(path.resolve())) + "?mode=ro"
    try:
        conn = sqlite3.connect(uri, uri=True, check_same_thread=False, isolation_level=None)
    except sqlite3.Error as exc:
        raise MbTilesError(f"{path}: cannot open: {exc}") from None
    # the third argument of a callback: abort the running query after MAX_STEPS thousand steps
    steps = [0]

    def progress() -> int:
        steps[0] += 1
        return 1 if steps[0] > MAX_STEPS else 0

    def reset(*_: object) -> None:
        steps[0] = 0

    conn.set_progress_handler(progress, 1000)
    conn.set_trace_callback(reset)  # each statement starts with a fresh budget
    return conn


def _read_meta(path: Path, conn: sqlite3.Connection) -> TileMeta:
    try:
        rows = conn.execute(
            "SELECT substr(name, 1, 100), substr(value, 1, ?) FROM metadata LIMIT 200", (MAX_META,)
        ).fetchall()
        conn.execute(
            "SELECT tile_data FROM tiles WHERE zoom_level = 0 AND tile_column = 0 AND tile_row = 0 LIMIT 1"
        ).fetchall()
    except sqlite3.Error as exc:
        raise MbTilesError(f"{path}: not an MBTiles file ({exc})") from None
    meta = {_text(k).lower(): _text(v) for k, v in rows}
    fmt = meta.get("format", "png").strip().lower() or "png"
    if fmt not in FORMATS:
        shown = fmt[:40].encode("unicode_escape").decode("ascii")
        raise MbTilesError(f"{path}: tile format {shown!r}: the page draws png, jpg or webp")
    fmt = "jpg" if fmt == "jpeg" else fmt
    lo, hi = _zoom(meta, "minzoom", 0), _zoom(meta, "maxzoom", 19)
    return TileMeta(fmt, FORMATS[fmt], html.escape(meta.get("attribution", "")), min(lo, hi), max(lo, hi))


def open_mbtiles(path: str | Path) -> MbTiles:
    """Open ``path`` read-only and check it can be served.

    Raises:
        MbTilesError: not a regular file, not SQLite, no ``tiles`` or ``metadata``
            table, a format the page cannot draw (the reason after the path).
    """
    p = Path(path)
    _check_file(p)
    conn = _connect(p)
    try:
        meta = _read_meta(p, conn)
    except BaseException:
        conn.close()
        raise
    return MbTiles(p, conn, meta)


__all__ = ["FORMATS", "MAX_STEPS", "MAX_TILE_BYTES", "MbTiles", "MbTilesError", "TileMeta", "open_mbtiles"]
