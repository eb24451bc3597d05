"""Offline maps an operator can prepare (issue 28): ``swarm tiles fetch`` against a local
tile server the test starts (real HTTP on loopback): the estimate first, the tiles into
one MBTiles file the station then serves offline; resumable after a failure and after
Ctrl-C (only what is missing is fetched again); OpenStreetMap's servers refused with
their reason; a hostile server's error pages and oversized answers never become tiles;
bad arguments one line each, exit 2."""

from __future__ import annotations

import http.server
import json
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_browser import tile_png

from swarm.cli.commands.tiles import main
from swarm.runtime.station.tilefetch import Area, plan, tile_range
from swarm.runtime.station.tiles import open_mbtiles

BOUNDS = "47.396,8.543,47.399,8.548"  # a field beside the PX4 SITL home
ZOOM = "15-17"


class TileServer:
    """Serves ``/{z}/{x}/{y}.png`` on loopback: a PNG per tile, with the troubles asked."""

    def __init__(self) -> None:
        self.requests: list[str] = []
        self.fail_after: int | None = None  # answer 503 once this many tiles were served
        self.missing: set[str] = set()  # paths answered 404
        self.html: set[str] = set()  # paths answered with an HTML page (200)
        self.huge: set[str] = set()  # paths answered with 2 MB
        self.redirect: set[str] = set()  # paths redirected to a local file
        self.delay = 0.0
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                server.requests.append(self.path)
                time.sleep(server.delay)
                served = sum(1 for _ in server.requests) - 1
                if server.fail_after is not None and served >= server.fail_after:
                    self.send_error(503)
                    return
                if self.path in server.missing:
                    self.send_error(404)
                    return
                if self.path in server.redirect:
                    self.send_response(302)
                    self.send_header("Location", "file:///etc/passwd")
                    self.end_headers()
                    return
                body = (
                    b"<html>quota exceeded</html>" if self.path in server.html
                    else b"\x89PNG\r\n\x1a\n" + b"0" * 2_000_000 if self.path in server.huge
                    else tile_png(len(self.path) * 7 % 255)
                )  # fmt: skip
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: Any) -> None:
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/{{z}}/{{x}}/{{y}}.png?key=SECRET"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def tiles_fetched(self) -> list[str]:
        return [r for r in self.requests]


@pytest.fixture
def server() -> Iterator[TileServer]:
    s = TileServer()
    yield s
    s.httpd.shutdown()
    s.httpd.server_close()


def fetch(server: TileServer, out: Path, *extra: str) -> int:
    return main(["fetch", "--url", server.url, "--bounds", BOUNDS, "--zoom", ZOOM, "--out", str(out), "--yes",
                 "--json", *extra])  # fmt: skip


def rows(path: Path) -> int:
    with sqlite3.connect(path) as db:
        return int(db.execute("SELECT COUNT(*) FROM tiles").fetchone()[0])


def test_an_area_is_estimated_fetched_and_served_offline(
    server: TileServer, tmp_path: Path, capsys: Any
) -> None:
    out = tmp_path / "field.mbtiles"
    total = plan(Area(47.396, 8.543, 47.399, 8.548, 15, 17))
    assert fetch(server, out) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert lines[0]["event"] == "estimate" and lines[0]["tiles"] == total and lines[0]["mean_tile_bytes"] > 0
    assert lines[-1] == {**lines[-1], "event": "done", "in_file": total, "fetched": total, "failed": 0}
    assert rows(out) == total
    mb = open_mbtiles(out)  # the station's own reader: the file is one it serves
    x0, _, y0, _ = tile_range(Area(47.396, 8.543, 47.399, 8.548, 17, 17), 17)
    assert mb.tile(17, x0, y0) is not None and mb.tile(16, 0, 0) is None
    with sqlite3.connect(out) as db:
        meta = dict(db.execute("SELECT name, value FROM metadata").fetchall())
    assert meta["format"] == "png" and meta["minzoom"] == "15" and meta["maxzoom"] == "17"
    assert "SECRET" not in json.dumps(meta)  # the API key stays out of the file


def test_a_fetch_that_fails_halfway_resumes_with_only_what_is_missing(
    server: TileServer, tmp_path: Path
) -> None:
    out = tmp_path / "field.mbtiles"
    total = plan(Area(47.396, 8.543, 47.399, 8.548, 15, 17))
    server.fail_after = 3 + 10  # the estimate's 3 samples, then 10 tiles
    assert fetch(server, out, "--parallel", "1") == 1
    kept = rows(out)
    assert 0 < kept < total
    server.fail_after, server.requests = None, []
    assert fetch(server, out) == 0
    assert rows(out) == total
    assert len(server.requests) == 3 + total - kept  # the samples, then only the missing ones


def test_a_hostile_servers_pages_and_giant_answers_never_become_tiles(
    server: TileServer, tmp_path: Path
) -> None:
    out = tmp_path / "field.mbtiles"
    x0, _, y0, _ = tile_range(Area(47.396, 8.543, 47.399, 8.548, 15, 15), 15)
    a, b, c, d = tile_range(Area(47.396, 8.543, 47.399, 8.548, 17, 17), 17)
    assert (a, c) != (b, d)
    server.html.add(f"/15/{x0}/{y0}.png?key=SECRET")
    server.huge.add(f"/17/{a}/{c}.png?key=SECRET")
    server.missing.add(f"/17/{b}/{d}.png?key=SECRET")
    server.redirect.add(f"/17/{a}/{d}.png?key=SECRET")
    assert (a, d) not in ((a, c), (b, d))
    assert fetch(server, out) == 1  # three failed: the same command tries them again
    with sqlite3.connect(out) as db:
        blobs = [bytes(b) for (b,) in db.execute("SELECT tile_data FROM tiles")]
    assert all(b.startswith(b"\x89PNG") and len(b) < 100_000 for b in blobs)
    total = plan(Area(47.396, 8.543, 47.399, 8.548, 15, 17))
    assert len(blobs) == total - 4  # the page, the giant, the redirect and the one the server has not


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--url", "https://tile.openstreetmap.org/{z}/{x}/{y}.png"], "forbid bulk download"),
        (["--url", "https://a.tile.openstreetmap.org/{z}/{x}/{y}.png"], "forbid bulk download"),
        (["--url", "file:///etc/{z}/{x}/{y}"], "http:// or https://"),
        (["--url", "https://example.com/tiles.png"], "needs {z}, {x} and {y}"),
        (["--bounds", "47.4,8.5,47.3,8.6"], "south < north"),
        (["--bounds", "a,b,c,d"], "four numbers"),
        (["--bounds", "nan,8.5,47.3,8.6"], "finite"),
        (["--zoom", "18-12"], "min <= max"),
        (["--zoom", "5-30"], "<= 22"),
        (["--zoom", "x"], "MIN-MAX"),
        (["--zoom", "0-19", "--bounds", "-80,-170,80,170"], "more than --max-tiles"),
        (["--parallel", "0"], "--parallel"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(
    server: TileServer, tmp_path: Path, capsys: Any, args: list[str], says: str
) -> None:
    base = {"--url": server.url, "--bounds": BOUNDS, "--zoom": ZOOM, "--out": str(tmp_path / "x.mbtiles")}
    for k, v in zip(args[::2], args[1::2], strict=True):
        base[k] = v
    argv = ["fetch", *[f"{k}={v}" for k, v in base.items()], "--yes"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err
    assert server.requests == [] and not (tmp_path / "x.mbtiles").exists()


def test_a_file_that_is_not_ours_or_from_another_server_is_never_touched(
    server: TileServer, tmp_path: Path
) -> None:
    notes = tmp_path / "notes.mbtiles"
    notes.write_text("my flight notes")
    assert fetch(server, notes) == 2 and notes.read_text() == "my flight notes"
    out = tmp_path / "field.mbtiles"
    assert fetch(server, out) == 0
    other = TileServer()
    try:
        assert fetch(other, out) == 2  # another server's tiles are not mixed in
    finally:
        other.httpd.shutdown()


@pytest.mark.processes
def test_without_a_terminal_it_asks_for_yes_and_ctrl_c_keeps_what_came(
    server: TileServer, tmp_path: Path
) -> None:
    out = tmp_path / "field.mbtiles"
    cmd = [sys.executable, "-m", "swarm.cli", "tiles", "fetch", "--url", server.url, "--bounds", BOUNDS,
           "--zoom", "15-19", "--out", str(out)]  # fmt: skip
    r = subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "add --yes" in r.stderr and not out.exists()
    server.delay = 0.05
    p = subprocess.Popen([*cmd, "--yes", "--parallel", "1"], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while (not out.exists() or rows(out) < 1) and time.monotonic() < deadline:
        time.sleep(0.1)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "the same command resumes" in err and "Traceback" not in err
    kept = rows(out)
    total = plan(Area(47.396, 8.543, 47.399, 8.548, 15, 19))
    assert 0 < kept < total
    server.delay = 0.0
    r = subprocess.run([*cmd, "--yes"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert rows(out) == total and "swarm gcs --tiles-mbtiles" in r.stdout
