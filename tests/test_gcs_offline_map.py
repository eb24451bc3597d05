"""The page's map offline, in a real headless browser against ``swarm gcs`` processes.

With a tile source that does not answer (OpenStreetMap's address from a field with no
network: here a closed local port, with OpenStreetMap's default credit), the page draws
a metric grid with its spacing beside the scale bar and credits no one. With an
MBTiles file, the file's tiles are drawn and its own credit shown once they are.
Screenshots in ``test-artifacts/``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_browser import browser, poll, screenshot, start_station, tile_png, tile_xy
from net_helpers import free_port
from test_gcs_tiles import make_mbtiles

pytestmark = pytest.mark.processes  # a browser against a station process

HOME = (47.397742, 8.545594)
UI_DEADLINE = 30.0


@pytest.fixture
def page() -> Iterator[Any]:
    """A page of its own headless browser, with the script errors it met in ``errors``."""
    with browser() as ctx:
        p = ctx.new_page()
        p.errors = []
        p.on("pageerror", lambda exc: p.errors.append(str(exc)))
        yield p


def open_page(page: Any, url: str) -> None:
    page.goto(url)
    page.wait_for_function("() => window.gcs && window.gcs.ready", timeout=UI_DEADLINE * 1000)


def attribution(page: Any) -> str:
    return str(page.inner_text(".leaflet-control-attribution"))


GRID_TILES = "document.querySelectorAll('canvas.leaflet-tile').length"
FAILED_TILES = (
    "Array.from(document.querySelectorAll('img.leaflet-tile'))"
    ".filter(i => i.complete && i.src.startsWith('data:')).length"
)
LOADED_TILES = (
    "Array.from(document.querySelectorAll('img.leaflet-tile-loaded'))"
    ".filter(i => i.src.includes('/tiles/')).length"
)


def test_offline_the_page_draws_a_grid_and_credits_no_one(page: Any) -> None:
    dead = free_port()  # nothing listens there: every tile fails, as offline
    argv = ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}", "--http", f"127.0.0.1:{free_port()}"]
    argv += ["--tiles", f"http://127.0.0.1:{dead}/{{z}}/{{x}}/{{y}}.png", "--center", f"{HOME[0]},{HOME[1]}"]
    station, url = start_station(argv)
    try:
        open_page(page, url)
        assert "OpenStreetMap" in page.evaluate("window.gcs.config.attribution")  # the default credit
        poll(lambda: page.evaluate(FAILED_TILES) > 0, "the tiles to fail", UI_DEADLINE, [station])
        poll(lambda: page.evaluate(GRID_TILES) > 0, "the grid drawn", UI_DEADLINE, [station])
        text = attribution(page)
        assert "OpenStreetMap" not in text and "no map tiles" in text, text
        legend = str(page.inner_text(".gcs-grid-legend"))
        spacing = page.evaluate("window.gcsGrid.layer.gridInfo().spacing_m")
        assert legend in (f"grid {spacing} m", f"grid {spacing / 1000} km") and 1 <= spacing <= 1000, legend
        assert page.locator(".leaflet-control-scale-line").count() >= 2  # the scale bar and the legend
        screenshot(page, "gcs_offline_grid.png")
        # zoomed out, the spacing grows with the scale
        page.evaluate("window.gcsGrid.map.setZoom(12)")
        poll(
            lambda: page.evaluate("window.gcsGrid.layer.gridInfo().spacing_m") > spacing,
            "a wider grid zoomed out",
            UI_DEADLINE,
            [station],
        )
        assert "OpenStreetMap" not in attribution(page)
        assert page.errors == []
    finally:
        station.stop()


def test_mbtiles_tiles_are_drawn_with_their_own_credit(tmp_path: Path, page: Any) -> None:
    tiles = {}
    light, dark = tile_png(196), tile_png(176)
    for z in (16, 17, 18):
        cx, cy = tile_xy(*HOME, z)
        for x in range(cx - 3, cx + 4):
            for y in range(cy - 3, cy + 4):
                tiles[(z, x, y)] = light if (x + y) % 2 else dark
    path = tmp_path / "field.mbtiles"
    make_mbtiles(path, tiles, extra={"attribution": "Field survey <b>2026</b>"})
    argv = ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}", "--http", f"127.0.0.1:{free_port()}"]
    argv += ["--tiles-mbtiles", str(path), "--center", f"{HOME[0]},{HOME[1]}"]
    station, url = start_station(argv)
    try:
        open_page(page, url)
        poll(lambda: page.evaluate(LOADED_TILES) > 0, "the file's tiles drawn", UI_DEADLINE, [station])
        poll(lambda: "Field survey" in attribution(page), "the file's credit", UI_DEADLINE, [station])
        text = attribution(page)
        assert "<b>" in text and "OpenStreetMap" not in text and "no map tiles" not in text, text
        assert page.locator(".gcs-grid-legend").count() == 0  # the grid is only under the tiles
        screenshot(page, "gcs_mbtiles.png")
        assert page.errors == []
    finally:
        station.stop()
