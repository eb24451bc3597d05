"""Helpers of the ground-station page tests: an offline tile folder, the headless
browser, the station process, and polling waits.

Tiles are written here with zlib and struct (256x256 PNGs: a light ground with a
grid, darker on odd tiles), so the tests need no network and no image library.
"""

from __future__ import annotations

import json
import math
import struct
import time
import zlib
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from net_helpers import wait_until

from swarm.cli.bench.gcs_page import find_browser, launch_browser
from swarm.cli.procs import Child

REPO = Path(__file__).resolve().parent.parent
ARTIFACTS = REPO / "test-artifacts"
TILE = 256


def png(width: int, height: int, rows: Sequence[bytes]) -> bytes:
    """An 8-bit RGB PNG from ``height`` rows of ``3 * width`` bytes."""

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    raw = b"".join(b"\x00" + r for r in rows)  # filter type 0 on every row
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )


def tile_png(shade: int) -> bytes:
    """One 256x256 test tile: flat ground of ``shade`` with a 32 px grid and a border."""
    ground = bytes((shade, shade + 8, shade - 10))
    line = bytes((150, 160, 150))
    plain = bytearray(ground * TILE)
    for x in range(0, TILE, 32):
        plain[3 * x : 3 * x + 3] = line
    plain[3 * (TILE - 1) :] = line
    grid = line * TILE
    rows = [grid if y % 32 == 0 or y == TILE - 1 else bytes(plain) for y in range(TILE)]
    return png(TILE, TILE, rows)


def tile_xy(lat: float, lon: float, z: int) -> tuple[int, int]:
    """The slippy-map tile holding ``lat, lon`` at zoom ``z``."""
    n = 2**z
    x = int((lon + 180.0) / 360.0 * n)
    lat_r = math.radians(lat)
    y = int((1.0 - math.asinh(math.tan(lat_r)) / math.pi) / 2.0 * n)
    return x, y


def write_tiles(
    directory: Path, lat: float, lon: float, zooms: Sequence[int] = (17, 18, 19), radius: int = 2
) -> int:
    """Write a ``{z}/{x}/{y}.png`` folder around ``lat, lon``; returns the tile count."""
    light, dark = tile_png(196), tile_png(176)
    count = 0
    for z in zooms:
        cx, cy = tile_xy(lat, lon, z)
        for x in range(cx - radius, cx + radius + 1):
            folder = directory / str(z) / str(x)
            folder.mkdir(parents=True, exist_ok=True)
            for y in range(cy - radius, cy + radius + 1):
                (folder / f"{y}.png").write_bytes(light if (x + y) % 2 else dark)
                count += 1
    return count


@contextmanager
def browser() -> Iterator[Any]:
    """A headless Chromium context. No browser fails the test (the set-up installs one:
    a skip would hide a broken set-up)."""
    if find_browser() is None:
        pytest.fail("no chromium: `make setup` installs Debian's chromium (or set CHROMIUM)")
    with launch_browser() as ctx:
        yield ctx


@contextmanager
def new_page(ctx: Any) -> Iterator[Any]:
    """A page of the browser context ``ctx`` that keeps its script errors in ``page.errors``."""
    p = ctx.new_page()
    p.errors = []
    p.on("pageerror", lambda exc: p.errors.append(str(exc)))
    try:
        yield p
    finally:
        p.close()


def start_station(argv: Sequence[str], timeout: float = 30.0) -> tuple[Child, str]:
    """Start ``swarm gcs ... --json`` and return it with its page URL, once ready."""
    child = Child(["gcs", *argv, "--json"], name="station")
    try:
        deadline = time.monotonic() + timeout
        n = 1
        while True:
            lines = child.wait_lines(n, max(0.1, deadline - time.monotonic()))
            try:
                ready = json.loads(lines[-1])
            except ValueError:
                ready = {}
            if isinstance(ready, dict) and ready.get("url"):
                return child, str(ready["url"])
            n += 1
    except BaseException:
        child.stop()
        raise


__all__ = ["browser", "distance_m", "new_page", "poll", "screenshot", "start_station", "write_tiles"]


def poll(pred: Callable[[], Any], what: str, timeout: float, children: Sequence[Child] = ()) -> Any:
    """``wait_until`` at a page's pace (each call of ``pred`` may evaluate script in
    the browser): fail after ``timeout`` s, or as soon as one of ``children`` exits."""
    return wait_until(pred, what, timeout, 0.2, children=children)


def screenshot(page: Any, name: str) -> Path:
    """Keep a screenshot under ``test-artifacts/`` (git-ignored)."""
    ARTIFACTS.mkdir(exist_ok=True)
    path = ARTIFACTS / name
    page.screenshot(path=str(path))
    return path


def distance_m(a: Sequence[float], b: Sequence[float]) -> float:
    """Ground distance between two ``[lat, lon]`` (equirectangular: fine over a few km)."""
    k = math.pi / 180.0
    x = (b[1] - a[1]) * k * math.cos((a[0] + b[0]) * k / 2)
    y = (b[0] - a[0]) * k
    return 6371000.0 * math.hypot(x, y)
