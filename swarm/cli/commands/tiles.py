"""``swarm tiles fetch``: prepare an offline map while online, for ``swarm gcs --tiles-mbtiles``.

Theory of operation. The operator names a tile server whose terms allow bulk download
(its URL template), the field's bounds and the zoom levels; the command counts the
tiles and estimates the size from a few sample tiles first, and asks before fetching
(``--yes`` to go on without asking; without a terminal to ask on, ``--yes`` is
needed). It then fetches into one MBTiles file with a progress line, resumable (the
same command again fetches only what is missing; Ctrl-C or SIGTERM stops after the
batch in hand, which is kept). OpenStreetMap's own servers are refused with their
reason. The work and its checks are :mod:`swarm.runtime.station.tilefetch`'s.

Exit 0 when every tile is in the file (or the server has none for some: counted),
1 when the fetch could not go on (the file keeps what came; run it again), 2 for
bad arguments, a refused server or a file that is not ours, 130 after Ctrl-C.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from swarm.cli.progress import Progress
from swarm.cli.util import StopFlag, UsageError, guarded, print_json
from swarm.runtime.station.tilefetch import (
    Area,
    Fetcher,
    TileFetchError,
    check_template,
    estimate,
    open_store,
    plan,
    source_of,
)

PROG = "swarm tiles"
MAX_TILES = 100_000


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Fetch a map area into an MBTiles file while online, for the ground station "
        "offline (swarm gcs --tiles-mbtiles FILE).",
    )
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    f = sub.add_parser("fetch", help="fetch an area's tiles into an MBTiles file (resumable)")
    f.add_argument("--url", required=True, metavar="TEMPLATE",
                   help="the tile server's URL template with {z}, {x}, {y}: a server whose terms allow bulk "
                   "download (OpenStreetMap's own do not)")  # fmt: skip
    f.add_argument(
        "--bounds", required=True, metavar="S,W,N,E", help="the area: south, west, north, east (degrees)"
    )
    f.add_argument("--zoom", required=True, metavar="MIN-MAX", help="zoom levels, e.g. 12-18 (or one: 17)")
    f.add_argument("--out", required=True, metavar="FILE", help="the MBTiles file (resumed if it exists)")
    f.add_argument(
        "--attribution", default=None, help="the map's credit, shown on the page (default: the server)"
    )
    f.add_argument("--max-tiles", type=int, default=MAX_TILES, metavar="N",
                   help=f"refuse an area of more tiles (default {MAX_TILES})")  # fmt: skip
    f.add_argument("--parallel", type=int, default=4, metavar="N", help="requests at once (1..16, default 4)")
    f.add_argument(
        "--rate", type=float, default=20.0, metavar="R", help="requests a second at most (default 20)"
    )
    f.add_argument("--yes", action="store_true", help="do not ask before fetching")
    f.add_argument("--json", action="store_true", help="print the estimate and the result as JSON lines")
    return p


def parse_bounds(text: str) -> tuple[float, float, float, float]:
    try:
        s, w, n, e = (float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"--bounds {text[:60]!r}: four numbers S,W,N,E") from None
    return s, w, n, e


def parse_zoom(text: str) -> tuple[int, int]:
    try:
        lo, _, hi = text.partition("-")
        return int(lo), int(hi or lo)
    except ValueError:
        raise UsageError(f"--zoom {text[:40]!r}: MIN-MAX, e.g. 12-18") from None


def _ask(question: str) -> bool:
    if not sys.stdin.isatty():
        raise UsageError("not a terminal to ask on: add --yes to fetch")
    try:
        return input(question).strip().lower() in ("y", "yes")
    except EOFError:
        return False


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    a = parser.parse_args(argv)
    if a.action != "fetch":
        parser.print_usage(sys.stderr)
        print(f"{PROG}: error: an action: fetch", file=sys.stderr)
        return 2
    try:
        template = check_template(a.url)
        area = Area(*parse_bounds(a.bounds), *parse_zoom(a.zoom))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not 1 <= a.parallel <= 16:
        raise UsageError("--parallel: 1..16")
    if not 0.1 <= a.rate <= 1000:
        raise UsageError("--rate: 0.1..1000 requests a second")
    total = plan(area)
    if total > a.max_tiles:
        raise UsageError(
            f"{total} tiles: more than --max-tiles {a.max_tiles} (a smaller area, fewer zoom levels)"
        )
    mean = estimate(template, area)
    size = f"about {total * mean / 1e6:.1f} MB" if mean else "size unknown (no sample tile came)"
    line = f"{total} tiles, zoom {area.zmin}-{area.zmax}, {size} from {source_of(template)}"
    if a.json:
        print_json({"event": "estimate", "tiles": total, "mean_tile_bytes": mean, "out": a.out})
    else:
        print(f"{PROG}: {line}", file=sys.stderr, flush=True)
    if not a.yes and not _ask(f"fetch {total} tiles into {a.out}? [y/N] "):
        print(f"{PROG}: nothing fetched", file=sys.stderr)
        return 0
    attribution = a.attribution or f"tiles: {source_of(template).split('/')[2]}"
    try:
        db = open_store(Path(a.out), template, area, attribution)
    except TileFetchError as exc:
        raise UsageError(str(exc)) from None
    stop = StopFlag().install()
    bar = Progress(PROG, total, "tiles", as_json=a.json)
    try:
        fetcher = Fetcher(
            template, area, db, parallel=a.parallel, rate=a.rate, stop=stop.event,
            report=lambda p: (bar.advance(p.done - bar.done)),
        )  # fmt: skip
        p = fetcher.run()
    finally:
        bar.close()
        db.close()
        stop.restore()
    result = {"event": "done", "tiles": total, "in_file": p.done, "fetched": p.fetched, "missing": p.missing,
              "failed": p.failed, "bytes": p.bytes, "out": a.out}  # fmt: skip
    if a.json:
        print_json(result)
    else:
        print(f"{PROG}: {p.done}/{total} tiles in {a.out} ({p.fetched} fetched now, {p.bytes / 1e6:.1f} MB; "
              f"{p.missing} the server does not have, {p.failed} failed)", flush=True)  # fmt: skip
    if stop.is_set():
        print(f"{PROG}: stopped; the same command resumes", file=sys.stderr, flush=True)
        return stop.exit_code()
    if p.failed:
        print(f"{PROG}: {p.failed} tiles failed; the same command fetches them again", file=sys.stderr)
        return 1
    if not a.json:
        print(f"use it offline: swarm gcs --tiles-mbtiles {a.out}", flush=True)
    return 0
