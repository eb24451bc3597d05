"""`swarm replay`: decode, summarise or re-feed a radio capture (.tlog) or a flight log.

Theory of operation
-------------------
One capture file, or a folder holding an agent's flight log (``swarm agent
--capture DIR``: :func:`radios.tlogset.read_flight_log` reads its rotated files as
one capture, in time order; ``--agent NAME`` chooses among several agents' logs and
``--fc`` reads the flight controller's files instead of the radio's; a record torn
by a power cut at the end of a file is skipped with one note on stderr). Four
modes (each its own function below; only one runs):

* dump (default): one line per frame, MAVProxy-like text or, with ``--json``, one
  JSON object per line (:func:`radios.replay.decode_record`). A swarm TUNNEL frame
  is shown as the message it carries (:func:`swarm.core.wire.tunnel_decode.decode_tunnel`):
  text ``TIME SYSID/COMPID KIND FROM -> TO {field : value, ...}``, JSON the header
  facts plus ``tunnel``, ``kind``, ``from``, ``to`` and ``fields``; a payload that
  does not decode (a capture is hostile input) is one line saying why (``kind``
  null and ``error`` in JSON). A text line's unprintable characters (a newline or
  an escape sequence in a sender's text) are written as ``\\xNN`` escapes. TUNNEL
  frames are read by the swarm's own codec without pymavlink, which keeps
  ``--json`` fast (``python -m tools.bench replay``: ``replay_json_speed``);
* ``--stats``: totals, per-sysid frames, bytes and approximate share of air time,
  message counts (:class:`radios.replay.CaptureStats`), as a table or one JSON
  object (``unknown_ids``: the frames skipped per message id);
* ``--plot FILE.png``: the formation: a map of every agent's track from its pose
  stream (start, end, direction, turns, slots) and each member's slot error over
  time (:mod:`swarm.sim.trackplot`; matplotlib is imported only here), and the
  formation figures, each named with its legs and interval exactly as ``swarm
  demo`` names and computes them (:data:`swarm.sim.tracks.FIGURES`);
* ``--to URL``: the frames are written to a link opened with
  :func:`radios.link.open_link` (a radio, an emulator pty, ``loop://``...) at the
  recorded pace scaled by ``--speed`` with silences capped at ``--max-gap``
  (:class:`radios.replay.Player`), then a summary is printed. SIGINT or SIGTERM
  stops it before the next frame (exit 130 for SIGINT, 0 for SIGTERM).

Frames of a message id no dialect here knows (a real PX4 sends several) are
skipped and counted; one note on stderr says how many of which ids (exit code
unchanged). ``--plot`` reads one file. The capture is streamed, never loaded whole. A damaged
capture is used up to the damage: every whole record is printed (or counted, or
sent), then the damage message goes to stderr and the exit code is 2: a damaged
file, a file that is not a capture and a missing file are all bad input (exit 2,
as for ``swarm gcs --replay``). Errors never show a traceback (:func:`swarm.cli.util.guarded`).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from radios.errors import CaptureDamagedError, CaptureError, ConfigError, LinkError
from radios.mavlink import MSG_TUNNEL, STX_V2
from radios.replay import (
    DEFAULT_MAX_GAP,
    DEFAULT_SPEED,
    CaptureStats,
    Player,
    PlayStats,
    decode_record,
    format_record,
    format_time,
)
from radios.tlog import TlogReader, TlogRecord, read_tlog
from radios.url import parse_link_url
from swarm.cli.util import (
    EXIT_FAILURE,
    EXIT_INTERRUPTED,
    EXIT_USAGE,
    StopFlag,
    UsageError,
    capture_damage,
    guarded,
    parser,
    print_json,
)
from swarm.core.wire.tunnel_decode import decode_tunnel, format_fields, format_to

if TYPE_CHECKING:  # the flight log and link modules are imported where used: a dump needs neither
    from radios.tlogset import FlightLogReader

PROG = "swarm replay"
_dumps = json.JSONEncoder(check_circular=False).encode


def build_parser() -> argparse.ArgumentParser:
    p = parser(PROG, "Decode, summarise or re-feed a radio capture (.tlog).")
    p.add_argument("file", metavar="FILE", help="the capture (.tlog), or a flight log's folder")
    p.add_argument("--agent", metavar="NAME", help="with a folder: whose flight log (if it holds several)")
    p.add_argument(
        "--fc", action="store_true", help="with a folder: the flight controller's messages, not the radio's"
    )
    p.add_argument("--json", action="store_true", help="JSON lines / one JSON object")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--stats", action="store_true", help="print statistics, not frames")
    mode.add_argument(
        "--plot",
        metavar="PNG",
        help="draw the agents' tracks, the leader and the formation slots to PNG "
        "and print the formation metrics",
    )
    mode.add_argument(
        "--to", metavar="URL", help="re-feed the frames to this link or port at the recorded pace"
    )
    p.add_argument(
        "--speed",
        type=float,
        default=None,
        metavar="X",
        help=f"with --to: pace factor, 0 = as fast as possible (default {DEFAULT_SPEED:g})",
    )
    p.add_argument(
        "--max-gap",
        type=float,
        default=None,
        metavar="S",
        help=f"with --to: longest wait between frames in seconds (default {DEFAULT_MAX_GAP:g})",
    )
    p.add_argument("--baud", type=int, default=None, metavar="B", help="with --to: serial baud rate of URL")
    return p


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error argparse already printed
        return exc.code if isinstance(exc.code, int) else EXIT_FAILURE
    if args.to is None:
        given = [
            f
            for f, v in (("--speed", args.speed), ("--max-gap", args.max_gap), ("--baud", args.baud))
            if v is not None
        ]
        if given:
            raise UsageError(f"{', '.join(given)} only appl{'ies' if len(given) == 1 else 'y'} with --to")
    reader = _open(args.file, args)
    try:
        if args.to is not None:
            return _feed(reader, args)
        if args.stats:
            return _stats(reader, args.file, as_json=args.json)
        if args.plot is not None:
            return _plot(args.file, args.plot, as_json=args.json)
        return _dump(reader, as_json=args.json)
    except BrokenPipeError:  # e.g. `swarm replay x.tlog | head`
        _silence_stdout()
        return EXIT_FAILURE
    finally:
        reader.close()
        _torn_notes(reader)
        _unknown_note(reader)


def _open(path: str, args: argparse.Namespace) -> TlogReader | FlightLogReader:
    """A file's reader, or a flight log folder's. Raises UsageError for a path that is
    neither (or flags that do not fit it), CaptureError otherwise."""
    if not os.path.exists(path):
        raise UsageError(f"{path}: no such capture file")
    if os.path.isdir(path):
        from radios.rotating import FC, RADIO
        from radios.tlogset import read_flight_log

        if args.plot is not None:
            raise UsageError(f"--plot reads one capture file, not the folder {path}")
        try:
            return read_flight_log(path, prefix=args.agent, source=FC if args.fc else RADIO)
        except ConfigError as exc:
            raise UsageError(str(exc)) from None
    if args.agent is not None or args.fc:
        raise UsageError("--agent and --fc choose among a flight log folder's files: give the folder")
    try:
        return read_tlog(path)
    except CaptureError as exc:  # cannot be read (permissions, a device): the user's input
        raise UsageError(str(exc)) from None


def _torn_notes(reader: TlogReader | FlightLogReader) -> None:
    for path, offset in getattr(reader, "torn", ()):
        print(
            f"{PROG}: note: {path}: the last record (from byte {offset}) was cut short, "
            "as a power cut leaves it: skipped",
            file=sys.stderr,
            flush=True,
        )


def unknown_summary(unknown: dict[int, int]) -> str:
    """``"3 frames of message ids not known here (411 x2, 410 x1)"``, or ``""``."""
    if not unknown:
        return ""
    n = sum(unknown.values())
    ids = ", ".join(f"{mid} x{k}" for mid, k in sorted(unknown.items(), key=lambda x: (-x[1], x[0])))
    return f"{n} frame{'' if n == 1 else 's'} of message ids not known here ({ids})"


def _unknown_note(reader: TlogReader | FlightLogReader) -> None:
    text = unknown_summary(getattr(reader, "unknown", {}))
    if text:
        print(f"{PROG}: note: skipped {text}", file=sys.stderr, flush=True)


def _damaged(exc: CaptureDamagedError) -> int:
    """Every whole record is out: say where the damage is; a bad file is bad input (2)."""
    sys.stdout.flush()
    print(f"{PROG}: error: {capture_damage(exc)}", file=sys.stderr, flush=True)
    return EXIT_USAGE


def _silence_stdout() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):
        pass


# -- dump -----------------------------------------------------------------------


def _dump(reader: TlogReader | FlightLogReader, *, as_json: bool) -> int:
    write = sys.stdout.write
    line = _json_line if as_json else _text_line
    try:
        for rec in reader:
            write(line(rec))
    except CaptureDamagedError as exc:
        return _damaged(exc)
    sys.stdout.flush()
    return 0


def _swarm(rec: TlogRecord) -> dict[str, Any] | None:
    """The record's swarm message (:func:`swarm.core.wire.tunnel_decode.decode_tunnel`) with
    the MAVLink header facts, or None when it is not a swarm TUNNEL frame."""
    frame = rec.frame
    raw = frame.raw
    v2 = raw[0] == STX_V2
    if (raw[7] | raw[8] << 8 | raw[9] << 16 if v2 else raw[5]) != MSG_TUNNEL:
        return None
    d = decode_tunnel(frame.payload)
    if d is None:
        return None
    sysid = raw[5] if v2 else raw[3]
    head = {
        "t": rec.t,
        "sysid": sysid,
        "compid": raw[6] if v2 else raw[4],
        "seq": raw[4] if v2 else raw[2],
        "msg": "TUNNEL",
        "msgid": MSG_TUNNEL,
        "len": len(raw),
        "from": sysid,
    }
    head.update(d)
    return head


def _json_line(rec: TlogRecord) -> str:
    d = _swarm(rec)
    return _dumps(d if d is not None else decode_record(rec)) + "\n"


def _text_line(rec: TlogRecord) -> str:
    d = _swarm(rec)
    if d is None:
        line = format_record(rec)
    else:
        head = f"{format_time(d['t'])} {d['sysid']}/{d['compid']}"
        route = f"{d['from']} -> {format_to(d['to'])}"
        if d["kind"] is None:
            line = f"{head} TUNNEL swarm {d['tunnel']} {route} <cannot decode: {d['error']}>"
        else:
            line = f"{head} {d['kind']} {route} {format_fields(d['fields'])}"
    return (line if line.isprintable() else _escaped(line)) + "\n"


def _escaped(line: str) -> str:
    """``line`` with its control and other unprintable characters as ``\\xNN``/``\\uNNNN``:
    a sender's text (a refusal's reason, a STATUSTEXT) cannot start a forged line or
    send escape sequences to the terminal."""
    return "".join(
        c if c.isprintable() else f"\\x{ord(c):02x}" if ord(c) < 256 else f"\\u{ord(c):04x}" for c in line
    )


# -- statistics -------------------------------------------------------------------


def _stats(reader: TlogReader | FlightLogReader, path: str, *, as_json: bool) -> int:
    acc = CaptureStats()
    damage: CaptureDamagedError | None = None
    try:
        for rec in reader:
            acc.add(rec)
    except CaptureDamagedError as exc:
        damage = exc
    stats = acc.as_dict()
    unknown = getattr(reader, "unknown", {})
    stats["unknown_ids"] = {str(mid): n for mid, n in sorted(unknown.items())}
    if as_json:
        print_json({"file": path, **stats, "damage": str(damage) if damage else None})
    else:
        print(_stats_table(path, stats), flush=True)
    return _damaged(damage) if damage else 0


def _stats_table(path: str, s: dict[str, Any]) -> str:
    lines = [f"{path}: {s['frames']} frames, {s['bytes']} bytes"]
    if s["start"] is not None:
        lines[0] += f" over {s['duration']:.3f} s ({format_time(s['start'])} to {format_time(s['end'])})"
    if not s["systems"]:
        return lines[0]
    lines.append("")
    lines.append(f"{'sysid':>5}  {'frames':>7}  {'bytes':>9}  {'bytes/s':>8}  {'air %':>5}  messages")
    for sy in s["systems"]:
        rate = "-" if sy["bytes_per_s"] is None else f"{sy['bytes_per_s']:.1f}"
        msgs = ", ".join(f"{name} {n}" for name, n in sy["messages"].items())
        lines.append(
            f"{sy['sysid']:>5}  {sy['frames']:>7}  {sy['bytes']:>9}  {rate:>8}"
            f"  {100 * sy['airtime_share']:>5.1f}  {msgs}"
        )
    lines.append("")
    lines.append("messages: " + ", ".join(f"{n} {c}" for n, c in s["messages"].items()))
    lines.append(
        f"(air % = share of frame bytes + {s['airtime_overhead_bytes']} bytes per "
        "frame; the emulator's air model is the fuller account)"
    )
    return "\n".join(lines)


# -- re-feeding a port --------------------------------------------------------------


def _with_baud(url: str, baud: int | None) -> str:
    if baud is None:
        return url
    if "baud" in parse_link_url(url).options:
        raise UsageError("give the baud rate either in the URL or with --baud, not both")
    return f"{url}{'&' if '?' in url else '?'}baud={baud}"


@contextmanager
def _signals(flag: StopFlag) -> Iterator[None]:
    """Route SIGINT/SIGTERM to ``flag`` while inside; restore the old handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    flag.install()
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _feed(reader: TlogReader | FlightLogReader, args: argparse.Namespace) -> int:
    from radios.link import open_link

    url = _with_baud(args.to, args.baud)
    speed = DEFAULT_SPEED if args.speed is None else args.speed
    max_gap = DEFAULT_MAX_GAP if args.max_gap is None else args.max_gap
    flag = StopFlag()
    player = Player(reader, speed=speed, max_gap=max_gap, stop=flag.event)  # checks values
    damage: CaptureDamagedError | None = None
    with _signals(flag), open_link(url) as link:
        if not link.can_send:
            raise UsageError(f"{args.to} is receive-only, cannot re-feed it")
        try:
            player.play(link)
        except CaptureDamagedError as exc:
            damage = exc
        except LinkError:
            _print_summary(player.stats, args, speed, max_gap)
            raise
    _print_summary(player.stats, args, speed, max_gap)
    if damage is not None:
        return _damaged(damage)
    if player.stats.stopped and flag.signal == signal.SIGINT:
        return EXIT_INTERRUPTED
    return 0


def _print_summary(st: PlayStats, args: argparse.Namespace, speed: float, max_gap: float) -> None:
    if args.json:
        print_json(
            {
                "to": args.to,
                **st.as_dict(),
                "speed": speed,
                "max_gap": max_gap if max_gap != float("inf") else None,
            }
        )
        return
    text = (
        f"sent {st.frames} frames ({st.bytes} bytes) to {args.to} in {st.elapsed:.3f} s;"
        f" recorded span {st.recorded:.3f} s, speed {speed:g}, max gap {max_gap:g} s"
    )
    if st.stopped:
        text += "; stopped before the end"
    print(text, flush=True)


# -- plot ---------------------------------------------------------------------


def _plot(path: str, out: str, *, as_json: bool) -> int:
    """Tracks, leader, slots (swarm.sim.tracks.plot) and the formation metrics."""
    from swarm.cli.progress import Ticker
    from swarm.sim.trackplot import plot
    from swarm.sim.tracks import analyse

    parent = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(parent):
        raise UsageError(f"--plot {out}: no such directory {parent}")
    with Ticker(PROG, f"reading and drawing {os.path.basename(path)}", as_json=as_json):
        an = analyse(path)
        try:
            plot(an, out)
        except ValueError as exc:  # nothing to draw in this file (no pose stream): bad input
            print(f"{PROG}: error: {path}: {exc}", file=sys.stderr)
            return EXIT_USAGE
        except OSError as exc:
            raise UsageError(f"--plot {out}: {exc.strerror or exc}") from None
    s = an.summary()
    s["plot"] = out
    if as_json:
        print(json.dumps(s))
    else:
        print("\n".join(_plot_lines(s)))
    if an.damaged:
        print(f"{PROG}: error: {an.damaged}", file=sys.stderr)
        return EXIT_USAGE
    return 0


def _plot_lines(s: dict[str, Any]) -> list[str]:
    """The formation figures for people, named with their legs and interval (as ``swarm demo``)."""
    from swarm.sim.tracks import INTERVAL, LEGS, fmt

    dur, straight = fmt(s["interval"]["duration_s"], " s"), s["straight_samples"]
    out = [
        f"plot: {s['plot']}",
        f"leader: agent {s['leader']}; agents {', '.join(map(str, s['agents']))}",
        f"slot error {INTERVAL}: {dur}, {s['samples']} samples ({straight} on straight legs)",
    ]
    out += [f"  {key}: {fmt(s[key])} ({LEGS[key]})" for key in LEGS]
    for m, d in s["per_member"].items():
        out.append(f"  agent {m}: RMS {fmt(d['rms_m'])} on straight legs, max {fmt(d['max_m'])}")
    return out


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(None))
