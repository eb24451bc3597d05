"""Map tiles from an MBTiles file (swarm.runtime.station.tiles): served byte-exact by a real
server, and hostile files (not SQLite, missing tables, huge or non-blob tiles, a
view that never ends, SQL and URI syntax in the name, a FIFO, a device) refused at
start in one line (exit 2) or answered with a 404 per tile, never a 500.

The MBTiles files are written here with sqlite3 and the PNG tiles of gcs_browser."""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_browser import tile_png, tile_xy
from net_helpers import free_port

from swarm.cli.commands.gcs import main as gcs_main
from swarm.runtime.station.live import Station
from swarm.runtime.station.server import GcsServer, ServerConfig
from swarm.runtime.station.tiles import MAX_TILE_BYTES, MbTilesError, open_mbtiles

HOME = (47.397742, 8.545594)
ZOOM = 17


def make_mbtiles(
    path: Path,
    tiles: dict[tuple[int, int, int], Any],
    *,
    fmt: str | None = "png",
    metadata: bool = True,
    extra: dict[str, str] | None = None,
) -> None:
    """An MBTiles file with ``tiles`` keyed by slippy-map (z, x, y), stored TMS (row flipped)."""
    with sqlite3.connect(path) as db:
        db.execute(
            "CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_data)"
        )
        db.execute("CREATE UNIQUE INDEX tile_index ON tiles (zoom_level, tile_column, tile_row)")
        for (z, x, y), data in tiles.items():
            db.execute("INSERT INTO tiles VALUES (?, ?, ?, ?)", (z, x, 2**z - 1 - y, data))
        if metadata:
            db.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
            meta = {"name": "test field", "minzoom": "16", "maxzoom": "18", **(extra or {})}
            if fmt is not None:
                meta["format"] = fmt
            db.executemany("INSERT INTO metadata VALUES (?, ?)", meta.items())
    db.close()


def get(base: str, path: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(base.rstrip("/") + path, timeout=30) as r:
            return r.status, r.headers.get("Content-Type", ""), r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers.get("Content-Type", ""), e.read()


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    root = tmp_path_factory.mktemp("mbtiles")
    x, y = tile_xy(*HOME, ZOOM)
    light, dark = tile_png(196), tile_png(176)
    tiles: dict[tuple[int, int, int], Any] = {(ZOOM, x, y): light, (ZOOM, x + 1, y): dark}
    tiles[(ZOOM, x, y + 1)] = "text, not a blob"
    tiles[(ZOOM, x, y + 2)] = b"\x89PNG" + bytes(MAX_TILE_BYTES)  # larger than any tile
    tiles[(ZOOM, x, y + 3)] = 12345
    tiles[(ZOOM, x, y + 4)] = b""
    path = root / "field.mbtiles"
    make_mbtiles(path, tiles, extra={"attribution": '<img src=x onerror="alert(1)">survey 2026'})
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    mb = open_mbtiles(path)
    station = Station("gcs", zenoh_listen=[f"tcp/127.0.0.1:{free_port()}"]).start()
    server = GcsServer(station, ServerConfig(port=free_port(), tiles_mbtiles=mb)).start()
    try:
        yield {"base": server.url, "server": server, "x": x, "y": y, "light": light, "dark": dark}
    finally:
        server.stop()
        station.stop()
        mb.close()
    assert hashlib.sha256(path.read_bytes()).hexdigest() == digest, "the MBTiles file was changed"


@pytest.mark.processes
def test_mbtiles_tiles_are_served_byte_exact(served: dict[str, Any]) -> None:
    base, x, y = served["base"], served["x"], served["y"]
    st, ctype, body = get(base, f"/tiles/{ZOOM}/{x}/{y}.png")
    assert st == 200 and ctype == "image/png" and body == served["light"]
    st, ctype, body = get(base, f"/tiles/{ZOOM}/{x + 1}/{y}.png")
    assert st == 200 and body == served["dark"]
    st, _, body = get(base, "/api/config")
    cfg = json.loads(body)
    assert cfg["tiles"] == "/tiles/{z}/{x}/{y}.png" and cfg["tiles_max_zoom"] == 18
    # the file's attribution is shown as text, never as the file's HTML
    assert "<img" not in cfg["attribution"] and "survey 2026" in cfg["attribution"]


@pytest.mark.processes
def test_bad_mbtiles_tiles_are_404_never_500(served: dict[str, Any]) -> None:
    base, x, y = served["base"], served["x"], served["y"]
    for path in (
        f"/tiles/{ZOOM}/{x}/{y + 1}.png",  # text in tile_data
        f"/tiles/{ZOOM}/{x}/{y + 2}.png",  # a blob beyond MAX_TILE_BYTES
        f"/tiles/{ZOOM}/{x}/{y + 3}.png",  # an integer
        f"/tiles/{ZOOM}/{x}/{y + 4}.png",  # empty
        f"/tiles/{ZOOM}/{x}/{y + 9}.png",  # absent
        f"/tiles/{ZOOM}/{x}/{y}.jpg",  # not the file's format
        f"/tiles/3/{2**3}/0.png",  # beyond the zoom's columns
        "/tiles/99/0/0.png",
        f"/tiles/{ZOOM}/{x}/{y}.png%27%3B%20DROP%20TABLE%20tiles%3B--",
    ):
        st, ctype, _ = get(base, path)
        assert st == 404 and "json" in ctype, path
    st, _, body = get(base, f"/tiles/{ZOOM}/{x}/{y}.png")
    assert st == 200 and body == served["light"], "the table is still there"


def test_a_tiles_view_that_never_ends_is_stopped(tmp_path: Path) -> None:
    path = tmp_path / "loop.mbtiles"
    make_mbtiles(path, {})
    with sqlite3.connect(path) as db:
        db.execute("ALTER TABLE tiles RENAME TO real_tiles")
        db.execute(
            "CREATE VIEW tiles AS WITH RECURSIVE n(i) AS (SELECT 0 UNION ALL SELECT i + 1 FROM n) "
            "SELECT i % 25 AS zoom_level, i % 1000003 AS tile_column, -1 - i % 2 AS tile_row, "
            "x'00' AS tile_data FROM n"
        )
    db.close()
    with pytest.raises(MbTilesError, match="interrupted"):  # the check at start is stopped
        open_mbtiles(path)


def test_a_slow_tile_query_is_a_missing_tile(tmp_path: Path) -> None:
    path = tmp_path / "slow.mbtiles"
    make_mbtiles(path, {(0, 0, 0): b"\x89PNG tile"})
    with sqlite3.connect(path) as db:  # a view that counts to 10**8 for any tile not in the table
        db.execute("ALTER TABLE tiles RENAME TO real_tiles")
        db.execute(
            "CREATE VIEW tiles AS SELECT * FROM real_tiles UNION ALL SELECT * FROM ("
            "WITH RECURSIVE n(i) AS (SELECT 0 UNION ALL SELECT i + 1 FROM n WHERE i < 100000000) "
            "SELECT i % 25 AS zoom_level, i % 1000003 AS tile_column, -1 - i % 2 AS tile_row, "
            "x'00' AS tile_data FROM n)"
        )
    db.close()
    mb = open_mbtiles(path)
    try:
        assert mb.tile(0, 0, 0) == b"\x89PNG tile"
        t0 = time.monotonic()
        assert mb.tile(5, 1, 1) is None
        assert time.monotonic() - t0 < 30, "the query was not stopped"
        assert mb.tile(0, 0, 0) == b"\x89PNG tile", "each query has its own budget"
    finally:
        mb.close()


def _hostile_files(tmp: Path) -> list[tuple[str, str]]:
    """(path, the reason expected in the one-line error)."""
    (tmp / "text.mbtiles").write_text("not a database\n" * 10)
    (tmp / "empty.mbtiles").write_bytes(b"")
    (tmp / "folder.mbtiles").mkdir()
    os.mkfifo(tmp / "fifo.mbtiles")
    with sqlite3.connect(tmp / "notiles.mbtiles") as db:
        db.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
    db.close()
    make_mbtiles(tmp / "nometa.mbtiles", {}, metadata=False)
    make_mbtiles(tmp / "vector.mbtiles", {}, fmt="pbf")
    make_mbtiles(tmp / "evil.mbtiles", {}, fmt="png'); DROP TABLE tiles; --")
    return [
        (str(tmp / "text.mbtiles"), "not an SQLite database"),
        (str(tmp / "empty.mbtiles"), "not an SQLite database"),
        (str(tmp / "folder.mbtiles"), "not a regular file"),
        (str(tmp / "fifo.mbtiles"), "not a regular file"),
        ("/dev/zero", "not a regular file"),
        (str(tmp / "nosuch.mbtiles"), "No such file"),
        (str(tmp / "notiles.mbtiles"), "no such table: tiles"),
        (str(tmp / "nometa.mbtiles"), "no such table: metadata"),
        (str(tmp / "vector.mbtiles"), "tile format 'pbf'"),
        (str(tmp / "evil.mbtiles"), "the page draws png, jpg or webp"),
        (str(tmp / "nosuch.mbtiles?mode=rwc"), "No such file"),
    ]


def test_hostile_mbtiles_files_are_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for path, reason in _hostile_files(tmp_path):
        argv = ["--zenoh-listen", "tcp/127.0.0.1:1", "--tiles-mbtiles", path]
        assert gcs_main(argv) == 2, path
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("swarm gcs: error: --tiles-mbtiles "), err
        assert reason in err[0], (path, err)
    # the URI syntax in a name stayed a name: nothing was created
    assert not (tmp_path / "nosuch.mbtiles").exists()
    assert not (tmp_path / "nosuch.mbtiles?mode=rwc").exists()


def test_a_name_with_uri_and_sql_syntax_is_just_a_name(tmp_path: Path) -> None:
    path = tmp_path / "a?mode=rwc#x'; DROP TABLE tiles;--%20.mbtiles"
    make_mbtiles(path, {(1, 0, 1): b"\x89PNG one"})
    mb = open_mbtiles(path)
    try:
        assert mb.tile(1, 0, 1) == b"\x89PNG one" and mb.meta.format == "png"
        assert mb.tile(1, 0, 0) is None
    finally:
        mb.close()
    ro = open_mbtiles(path)
    try:
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            ro._conn.execute("DELETE FROM tiles")  # noqa: SLF001 (white box: the read-only connection): opened read-only: SQLite refuses
    finally:
        ro.close()


def test_jpg_and_webp_by_the_metadata(tmp_path: Path) -> None:
    for fmt, ctype in (("jpg", "image/jpeg"), ("jpeg", "image/jpeg"), ("webp", "image/webp")):
        path = tmp_path / f"{fmt}.mbtiles"
        make_mbtiles(path, {(0, 0, 0): b"img"}, fmt=fmt)
        mb = open_mbtiles(path)
        assert mb.meta.content_type == ctype and mb.meta.format in ("jpg", "webp")
        assert ServerConfig(tiles_mbtiles=mb).tile_template == f"/tiles/{{z}}/{{x}}/{{y}}.{mb.meta.format}"
        mb.close()


def test_config_key_takes_a_path_beside_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "bad.mbtiles").write_text("not a database\n")
    cfg = tmp_path / "gcs.toml"
    cfg.write_text('zenoh_listen = ["tcp/127.0.0.1:1"]\ntiles_mbtiles = "bad.mbtiles"\n')
    assert gcs_main(["--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f'tiles_mbtiles = "{tmp_path / "bad.mbtiles"}"' in err[0], err
    assert "not an SQLite database" in err[0], err


def test_a_tile_folder_says_its_deepest_zoom(tmp_path: Path) -> None:
    """Tiles saved to a folder up to zoom 17: the page must enlarge zoom 17 beyond it,
    not ask for zoom 18 tiles the folder does not have (the map went blank when the
    page zoomed to the agents, at 18: an operator in a field without internet saw no
    map at all)."""
    for z in (15, 16, 17):
        (tmp_path / str(z) / "1").mkdir(parents=True)
        (tmp_path / str(z) / "1" / "1.png").write_bytes(tile_png(196))
    (tmp_path / "notes").mkdir()  # not a zoom level
    (tmp_path / "99").write_text("a file, not a zoom level")
    assert ServerConfig(tiles_dir=tmp_path).tiles_max_zoom == 17
    empty = tmp_path / "empty"
    empty.mkdir()
    assert ServerConfig(tiles_dir=empty).tiles_max_zoom == 19  # nothing there yet: the page's usual depth
    assert ServerConfig(tiles="https://tile.example/{z}/{x}/{y}.png").tiles_max_zoom == 19
