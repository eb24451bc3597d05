"""Fetch a map area into an MBTiles file while online, for the station offline (``swarm tiles``).

Theory of operation
-------------------
An operator prepares the field's map before leaving: the area (``bounds``: south,
west, north, east in degrees) and the zoom levels wanted, from a tile server whose
terms allow bulk download (the operator's own, or a provider's that sells it), named
by its URL template (``https://tiles.example.com/{z}/{x}/{y}.png``). OpenStreetMap's
own tile servers forbid bulk download (their tile usage policy): a template on them is
refused with that reason (:func:`check_template`).

:func:`plan` counts the tiles (the slippy-map tiles covering the bounds at each
zoom, :func:`tile_range`) before anything is fetched; :func:`estimate` fetches a few
sample tiles for their mean size, so the operator sees "N tiles, about X MB" first.
:class:`Fetcher` then fetches every tile not yet in the file, several at a time
(``parallel``, at most ``rate`` a second), each checked: at most
:data:`~swarm.runtime.station.tiles.MAX_TILE_BYTES`, an image the page draws (PNG,
JPEG or WebP by its first bytes: a server's error page is not a tile), an HTTP 404 a
tile the server does not have (counted, skipped). Tiles are written in batches, each
one SQLite transaction, so a power cut or a Ctrl-C loses at most the batch in hand;
running the same command again resumes (tiles already in the file are not fetched
again). The file is the MBTiles 1.3 layout the station reads
(:mod:`swarm.runtime.station.tiles`): ``metadata`` (name, format, bounds, center,
minzoom, maxzoom, attribution, and ``source``: the template without its query, where
an API key would be) and ``tiles`` with its unique index; rows count from the south
(TMS). A file that is not one of ours, or was fetched from another template, is
refused rather than mixed.
"""

from __future__ import annotations

import concurrent.futures
import math
import sqlite3
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from swarm.errors import SwarmError
from swarm.runtime.station.tiles import MAX_TILE_BYTES

#: hosts whose tile usage policy forbids bulk download (https://operations.osmfoundation.org/policies/tiles/)
FORBIDDEN_HOSTS = ("tile.openstreetmap.org", "tile.osm.org", "tile.openstreetmap.fr")
MAX_ZOOM = 22
TIMEOUT_S = 15.0
TRIES = 3
BATCH = 16  # tiles a transaction: what a power cut or a Ctrl-C may lose
USER_AGENT = "uav-swarm-tiles (offline map for a ground station)"
#: a tile's format from its first bytes
MAGIC = {b"\x89PNG\r\n\x1a\n": "png", b"\xff\xd8\xff": "jpg"}


class TileFetchError(SwarmError):
    """A fetch that cannot go on (one line: the server, the file, the network)."""


def check_template(url: str) -> str:
    """``url`` if it is an http(s) template with {z}, {x} and {y} on a server that
    allows bulk download. Raises ValueError with the reason."""
    if not isinstance(url, str) or len(url) > 2000:
        raise ValueError("the URL template is a string of at most 2000 characters")
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"{url[:80]!r}: an http:// or https:// URL template")
    for k in ("{z}", "{x}", "{y}"):
        if k not in url:
            raise ValueError(f"{url[:80]!r}: the template needs {{z}}, {{x}} and {{y}}")
    host = parts.hostname.lower()
    if any(host == h or host.endswith("." + h) for h in FORBIDDEN_HOSTS):
        raise ValueError(
            f"{host}: OpenStreetMap's tile servers forbid bulk download (their tile usage policy); "
            "use your own tile server or a provider whose terms allow it"
        )
    return url


def source_of(url: str) -> str:
    """The template without its query and fragment (an API key stays out of the file)."""
    p = urllib.parse.urlsplit(url)
    return urllib.parse.urlunsplit((p.scheme, p.netloc, p.path, "", ""))


@dataclass(frozen=True)
class Area:
    south: float
    west: float
    north: float
    east: float
    zmin: int
    zmax: int

    def __post_init__(self) -> None:
        s, w, n, e = self.south, self.west, self.north, self.east
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (s, w, n, e)):
            raise ValueError("bounds: four finite numbers S,W,N,E")
        if not (-85.0511 <= s < n <= 85.0511) or not (-180.0 <= w < e <= 180.0):
            raise ValueError(
                f"bounds {s:g},{w:g},{n:g},{e:g}: south < north within ±85.05, west < east within ±180"
            )
        if not (0 <= self.zmin <= self.zmax <= MAX_ZOOM):
            raise ValueError(f"zoom {self.zmin}-{self.zmax}: 0 <= min <= max <= {MAX_ZOOM}")


def tile_xy(lat: float, lon: float, z: int) -> tuple[int, int]:
    n = 1 << z
    x = int((lon + 180.0) / 360.0 * n)
    r = math.radians(lat)
    y = int((1.0 - math.asinh(math.tan(r)) / math.pi) / 2.0 * n)
    return min(max(x, 0), n - 1), min(max(y, 0), n - 1)


def tile_range(area: Area, z: int) -> tuple[int, int, int, int]:
    """(x0, x1, y0, y1), inclusive, of the tiles covering ``area`` at zoom ``z``."""
    x0, y0 = tile_xy(area.north, area.west, z)
    x1, y1 = tile_xy(area.south, area.east, z)
    return x0, x1, y0, y1


def plan(area: Area) -> int:
    """How many tiles cover ``area`` over its zoom levels."""
    total = 0
    for z in range(area.zmin, area.zmax + 1):
        x0, x1, y0, y1 = tile_range(area, z)
        total += (x1 - x0 + 1) * (y1 - y0 + 1)
    return total


def tiles(area: Area) -> Iterator[tuple[int, int, int]]:
    for z in range(area.zmin, area.zmax + 1):
        x0, x1, y0, y1 = tile_range(area, z)
        for x in range(x0, x1 + 1):
            for y in range(y0, y1 + 1):
                yield z, x, y


def image_format(data: bytes) -> str | None:
    """png, jpg or webp by the first bytes; None: not an image the page draws."""
    for magic, fmt in MAGIC.items():
        if data.startswith(magic):
            return fmt
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    return None


class _NoRedirectElsewhere(urllib.request.HTTPRedirectHandler):
    """Follow a redirect only to http(s) (never file:, ftp:...)."""

    def redirect_request(
        self,
        req: urllib.request.Request,
        fp: Any,
        code: int,
        msg: str,
        headers: Any,
        newurl: str,
    ) -> urllib.request.Request | None:
        if urllib.parse.urlsplit(newurl).scheme not in ("http", "https"):
            return None
        return super().redirect_request(req, fp, code, msg, headers, newurl)


_OPENER = urllib.request.build_opener(_NoRedirectElsewhere)


def get_tile(url: str, timeout: float = TIMEOUT_S) -> bytes | None:
    """One tile's bytes; None for a tile the server does not have (404, 204).

    Raises:
        TileFetchError: anything else (a network error, another status, a tile too large
            or not an image), after nothing was kept.
    """
    req = urllib.request.Request(url, headers={"User-Agent": USER_AGENT})
    try:
        with _OPENER.open(req, timeout=timeout) as r:
            if r.status == 204:
                return None
            data = r.read(MAX_TILE_BYTES + 1)
    except urllib.error.HTTPError as exc:
        if exc.code in (404, 410):
            return None
        raise TileFetchError(f"HTTP {exc.code} for a tile") from None
    except (urllib.error.URLError, OSError, ValueError) as exc:
        why = getattr(exc, "reason", None) or exc
        raise TileFetchError(f"no tile: {why}") from None
    if len(data) > MAX_TILE_BYTES:
        raise TileFetchError(f"a tile larger than {MAX_TILE_BYTES} bytes")
    if image_format(data) is None:
        raise TileFetchError("the server sent something that is not a PNG, JPEG or WebP image")
    return data


def estimate(
    url: str, area: Area, samples: int = 3, get: Callable[[str], bytes | None] = get_tile
) -> float | None:
    """Mean bytes of up to ``samples`` tiles at the deepest zoom (None: none came)."""
    z = area.zmax
    x0, x1, y0, y1 = tile_range(area, z)
    picks = {((x0 + x1) // 2, (y0 + y1) // 2), (x0, y0), (x1, y1)}
    sizes = []
    for x, y in sorted(picks)[:samples]:
        try:
            data = get(tile_url(url, z, x, y))
        except TileFetchError:
            continue  # a bad sample: the estimate rests on the others
        if data is not None:
            sizes.append(len(data))
    return sum(sizes) / len(sizes) if sizes else None


def tile_url(template: str, z: int, x: int, y: int) -> str:
    return template.replace("{z}", str(z)).replace("{x}", str(x)).replace("{y}", str(y))


# -- the file ----------------------------------------------------------------------------


def open_store(path: Path, template: str, area: Area, attribution: str) -> sqlite3.Connection:
    """The MBTiles file to fill: created, or an existing one of ours from the same
    template (a resume). Raises TileFetchError (one line)."""
    source = source_of(template)
    exists = path.exists()
    if exists and not path.is_file():
        raise TileFetchError(f"{path}: not a regular file")
    if exists and path.stat().st_size > 0:
        with path.open("rb") as f:
            if f.read(16) != b"SQLite format 3\x00":
                raise TileFetchError(f"{path}: exists and is not an MBTiles file (not overwritten)")
    try:
        db = sqlite3.connect(str(path), check_same_thread=False)
        db.execute("CREATE TABLE IF NOT EXISTS metadata (name TEXT, value TEXT)")
        db.execute("CREATE UNIQUE INDEX IF NOT EXISTS metadata_name ON metadata (name)")
        db.execute(
            "CREATE TABLE IF NOT EXISTS tiles (zoom_level INTEGER, tile_column INTEGER, "
            "tile_row INTEGER, tile_data BLOB)"
        )
        db.execute(
            "CREATE UNIQUE INDEX IF NOT EXISTS tile_index ON tiles (zoom_level, tile_column, tile_row)"
        )
        meta = dict(db.execute("SELECT name, value FROM metadata").fetchall())
    except sqlite3.DatabaseError as exc:
        raise TileFetchError(f"{path}: {exc}") from None
    if meta.get("source") not in (None, source):
        db.close()
        raise TileFetchError(f"{path}: holds tiles from {meta['source']}, not {source} (use another file)")
    zmin = min(area.zmin, int(meta.get("minzoom", area.zmin)))
    zmax = max(area.zmax, int(meta.get("maxzoom", area.zmax)))
    values = {
        "name": meta.get("name", path.stem),
        "type": "baselayer",
        "version": "1.3",
        "description": "fetched with swarm tiles for an offline ground station",
        "source": source,
        "attribution": attribution,
        "bounds": f"{area.west},{area.south},{area.east},{area.north}",
        "center": f"{(area.west + area.east) / 2},{(area.south + area.north) / 2},{area.zmax}",
        "minzoom": str(zmin),
        "maxzoom": str(zmax),
    }
    suffix = Path(urllib.parse.urlsplit(template).path).suffix.lstrip(".").lower()
    if "format" not in meta and suffix in ("png", "jpg", "jpeg", "webp"):
        values["format"] = "jpg" if suffix == "jpeg" else suffix  # until a tile says
    with db:
        db.executemany("INSERT OR REPLACE INTO metadata (name, value) VALUES (?, ?)", values.items())
    return db


def have(db: sqlite3.Connection, z: int) -> set[tuple[int, int]]:
    """The tiles of zoom ``z`` already in the file, as (x, y)."""
    n = 1 << z
    rows = db.execute("SELECT tile_column, tile_row FROM tiles WHERE zoom_level = ?", (z,))
    return {(x, n - 1 - row) for x, row in rows}


@dataclass
class Progress:
    total: int
    done: int = 0  # in the file (already, or fetched now)
    fetched: int = 0
    missing: int = 0  # the server has no such tile
    failed: int = 0
    bytes: int = 0
    started: float = field(default_factory=time.monotonic)


class Fetcher:
    """Fetch ``area`` from ``template`` into ``db`` (module docstring). ``report`` is
    called with the progress after each batch; ``stop`` set ends it after the batch."""

    def __init__(
        self,
        template: str,
        area: Area,
        db: sqlite3.Connection,
        *,
        parallel: int = 4,
        rate: float = 20.0,
        get: Callable[[str], bytes | None] = get_tile,
        report: Callable[[Progress], None] = lambda p: None,
        stop: threading.Event | None = None,
        max_failures: int = 20,
    ) -> None:
        self.template, self.area, self.db = template, area, db
        self.parallel, self.rate, self.get, self.report = parallel, rate, get, report
        self.stop = stop if stop is not None else threading.Event()
        self.max_failures = max_failures
        self.format: str | None = None
        self._next = time.monotonic()
        self._lock = threading.Lock()

    def _paced(self, url: str) -> bytes | None:
        with self._lock:  # at most ``rate`` requests a second, whatever the threads
            now = time.monotonic()
            wait = self._next - now
            self._next = max(now, self._next) + 1.0 / self.rate
        if wait > 0:
            time.sleep(wait)
        last: TileFetchError | None = None
        for attempt in range(TRIES):
            try:
                return self.get(url)
            except TileFetchError as exc:
                last = exc
                time.sleep(0.2 * (attempt + 1))
        assert last is not None
        raise last

    def run(self) -> Progress:
        """Fetch what is missing. Raises TileFetchError after ``max_failures`` tiles
        that could not be fetched in a row (the batch in hand is written first)."""
        p = Progress(plan(self.area))
        todo: list[tuple[int, int, int]] = []
        for z in range(self.area.zmin, self.area.zmax + 1):
            got = have(self.db, z)
            for t in tiles(Area(self.area.south, self.area.west, self.area.north, self.area.east, z, z)):
                if (t[1], t[2]) in got:
                    p.done += 1
                else:
                    todo.append(t)
        self.report(p)
        in_a_row = 0
        with concurrent.futures.ThreadPoolExecutor(self.parallel) as pool:
            for i in range(0, len(todo), BATCH):
                if self.stop.is_set():
                    break
                batch = todo[i : i + BATCH]
                urls = [tile_url(self.template, z, x, y) for z, x, y in batch]
                rows = []
                futures = [pool.submit(self._paced, u) for u in urls]
                error: TileFetchError | None = None
                for (z, x, y), fut in zip(batch, futures, strict=True):
                    try:
                        data = fut.result()
                    except TileFetchError as exc:
                        p.failed += 1
                        in_a_row += 1
                        error = exc
                        continue
                    in_a_row = 0
                    if data is None:
                        p.missing += 1
                        p.done += 1
                        continue
                    self.format = self.format or image_format(data)
                    rows.append((z, x, (1 << z) - 1 - y, sqlite3.Binary(data)))
                    p.fetched += 1
                    p.done += 1
                    p.bytes += len(data)
                with self.db:
                    self.db.executemany(
                        "INSERT OR REPLACE INTO tiles (zoom_level, tile_column, tile_row, tile_data) "
                        "VALUES (?, ?, ?, ?)",
                        rows,
                    )
                    if self.format is not None:
                        self.db.execute(
                            "INSERT OR REPLACE INTO metadata (name, value) VALUES ('format', ?)",
                            (self.format,),
                        )
                self.report(p)
                if in_a_row >= self.max_failures and error is not None:
                    raise TileFetchError(f"{in_a_row} tiles in a row could not be fetched, the last: {error}")
        return p


__all__ = [
    "FORBIDDEN_HOSTS",
    "Area",
    "Fetcher",
    "Progress",
    "TileFetchError",
    "check_template",
    "estimate",
    "get_tile",
    "image_format",
    "open_store",
    "plan",
    "source_of",
    "tile_range",
    "tiles",
]
