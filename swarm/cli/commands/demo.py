"""``swarm demo``: the whole bench on one machine (emulated radios, simulated PX4
vehicles, agents, ground station): election, take-off, V formation along a route
with a 90 degree turn, landing, then a summary and a plot.

Steps and progress go to stdout: on a terminal the progress is one line updated in
place (every second), otherwise a plain line every 5 s; with ``--json`` nothing but the
summary, one JSON object on stdout (``leader``, ``elect_s``, the formation figures and
their ``figures`` definitions, ``air_utilisation``, ``capture``, ``plot``, ``gcs``,
``gcs_running``, ``workdir``, ``workdir_kept``, ``missed``, ``ok``...). The text summary
(:func:`swarm.cli.demo_report.summary_lines`) names every target missed and by how much.
The ground station's page is opened once it is up unless ``--headless``; where it cannot
be (no display, no browser) that is said once.

Exit 0 when every target was met; 1 when one was missed (a formation figure beyond its
limit, or a step that did not happen: no leader agreed, a process that failed); 2 for bad
usage; 130 on Ctrl-C or SIGTERM, after stopping every process it started. The working
folder it made is removed at the end unless ``--keep``.
"""

from __future__ import annotations

import argparse
import errno
import os
import shutil
import socket
import sys
import time
import webbrowser
from typing import TextIO

from swarm.cli.commands.gcs import parse_http
from swarm.cli.configfile import read_arguments
from swarm.cli.demo import AUTOPILOTS, SITL_DURATION_S, DemoConfig, run_demo
from swarm.cli.demo_report import summary_lines
from swarm.cli.util import EXIT_FAILURE, StopFlag, UsageError, guarded, parser, print_json
from swarm.core.election.profiles import PROFILE_NAMES

PROG = "swarm demo"


def build_parser() -> argparse.ArgumentParser:
    p = parser(PROG, "Run the whole swarm on this machine: radios, vehicles, agents, ground station.")
    p.add_argument("--agents", type=int, default=5, metavar="N", help="agents (2..20, default 5)")
    p.add_argument("--loss", type=float, default=0.1, metavar="P", help="radio packet loss (default 0.1)")
    p.add_argument("--profile", choices=PROFILE_NAMES, default="paper", help="election timing profile")
    p.add_argument(
        "--autopilot",
        choices=AUTOPILOTS,
        default="sim",
        help="the vehicles: the simulator (default), or real ArduCopter / PX4 SITL autopilots from "
        "$SITL_DIR (sitl:mix: ArduCopter for odd agents, PX4 for even ones)",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help=f"give up after this many seconds (default 170; {SITL_DURATION_S:.0f} with real autopilots)",
    )
    p.add_argument("--leg", type=float, default=100.0, metavar="M", help="route leg length (default 100)")
    p.add_argument("--speed", type=float, default=5.0, metavar="M/S", help="leader speed (default 5)")
    p.add_argument(
        "--settle",
        type=float,
        default=15.0,
        metavar="S",
        help="time for the V to form before the route (default 15)",
    )
    p.add_argument(
        "--max-rms",
        type=float,
        default=1.5,
        metavar="M",
        help="formation RMS slot error that counts as flying in formation (default 1.5)",
    )
    p.add_argument(
        "--max-turn",
        type=float,
        default=10.0,
        metavar="M",
        help="largest slot error in the turn that still counts as in formation (default 10)",
    )
    p.add_argument("--headless", action="store_true", help="do not open the ground station page")
    p.add_argument("--no-gcs", action="store_true", help="do not start the ground station")
    p.add_argument(
        "--http",
        default="127.0.0.1:8080",
        metavar="HOST:PORT",
        help="the ground station's address (default 127.0.0.1:8080)",
    )
    p.add_argument("--capture", metavar="FILE", help="the radio capture (default DIR/air.tlog)")
    p.add_argument("--plot", metavar="FILE", help="the formation plot (default DIR/formation.png)")
    p.add_argument(
        "--dir",
        metavar="DIR",
        help="working directory, kept (default: a new temporary one, removed at the end)",
    )
    p.add_argument("--keep", action="store_true", help="keep the temporary working directory")
    p.add_argument("--seed", type=int, default=0, help="seed of the radio loss")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    return p


def _config(a: argparse.Namespace) -> DemoConfig:
    """The run's configuration. Raises UsageError."""
    cfg = DemoConfig(
        agents=a.agents,
        loss=a.loss,
        profile=a.profile,
        duration=a.duration
        if a.duration is not None
        else (170.0 if a.autopilot == "sim" else SITL_DURATION_S),
        autopilot=a.autopilot,
        workdir=a.dir,
        capture=a.capture,
        plot=a.plot,
        leg_m=a.leg,
        speed_mps=a.speed,
        settle_s=a.settle,
        max_rms_m=a.max_rms,
        max_turn_m=a.max_turn,
        keep=a.keep,
        gcs=not a.no_gcs,
        http=a.http,
        seed=a.seed,
    )
    try:
        cfg.check()
        if not 0.5 <= a.speed <= 15 or not 0.1 <= a.max_rms <= 50 or not 0 <= a.settle <= 300:
            raise ValueError("--speed 0.5..15 m/s, --max-rms 0.1..50 m, --settle 0..300 s")
        if not 0.1 <= a.max_turn <= 100:
            raise ValueError("--max-turn 0.1..100 m")
        for flag, path in (("--capture", a.capture), ("--plot", a.plot)):
            parent = os.path.dirname(os.path.abspath(path)) if path else ""
            if path and not os.path.isdir(parent):
                raise ValueError(f"{flag} {path}: no such directory {parent}")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if cfg.gcs:  # the arguments first, then what the machine has
        _check_http(a.http)
    return cfg


def _check_http(text: str) -> None:
    """The station's ``--http`` address can be listened on now (checked before anything
    starts: a demo without the station it was asked for is not the demo). Raises
    UsageError."""
    host, port = parse_http(text)
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError):
        raise UsageError(f"--http {text}: no such host {host!r}") from None
    family, kind, proto, _name, addr = infos[0]
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the station's server binds
        try:
            s.bind(addr)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                why = f"port {port} in use (another station or program?)"
            elif exc.errno == errno.EADDRNOTAVAIL:
                why = f"{host} is not an address of this machine"
            else:
                why = exc.strerror or str(exc)
            raise UsageError(f"--http {text}: {why}: give another --http HOST:PORT, or --no-gcs") from None


class Lines:
    """Step lines and progress for people: on a terminal the progress is one line updated in
    place; otherwise a plain line every ``PLAIN_EVERY_S``; with ``quiet`` nothing."""

    PLAIN_EVERY_S = 5.0

    def __init__(self, stream: TextIO, quiet: bool) -> None:
        self.stream, self.quiet = stream, quiet
        self.tty = stream.isatty()
        self.open = False  # a progress line is on screen, not ended
        self.last = -1e9

    def step(self, line: str) -> None:
        if self.quiet:
            return
        self.end()
        print(line, file=self.stream, flush=True)

    def progress(self, line: str) -> None:
        if self.quiet:
            return
        if self.tty:
            width = shutil.get_terminal_size().columns - 1  # a wrapped line would not be redrawn
            self.stream.write("\r\x1b[K" + line.strip()[:width])
            self.stream.flush()
            self.open = True
        elif time.monotonic() - self.last >= self.PLAIN_EVERY_S:
            self.last = time.monotonic()
            print(line, file=self.stream, flush=True)

    def end(self) -> None:
        if self.open:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
            self.open = False


def _has_display() -> bool:
    """A browser can show a page here: not a Linux/BSD machine without X or Wayland."""
    if sys.platform.startswith(("linux", "freebsd", "openbsd", "netbsd")):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def open_page(url: str, lines: Lines) -> None:
    """Open the station's page, or say once why it was not."""
    why = "" if _has_display() else "no display here"
    if not why:
        try:
            why = "" if webbrowser.open(url) else "no browser found"
        except Exception as exc:
            why = f"the browser did not start ({exc})"
    if why:
        print(f"   page not opened: {why}; open {url} while the demo runs", file=sys.stderr, flush=True)


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = read_arguments(build_parser(), argv, config=False)
    cfg = _config(a)
    lines = Lines(sys.stdout, quiet=a.json)
    opened = False

    def out(line: str) -> None:
        nonlocal opened
        lines.step(line)
        if line.strip().startswith("ground station: http") and not a.headless and not opened:
            opened = True
            open_page(line.split(": ", 1)[1], lines)

    stop = StopFlag().install()
    try:
        summary = run_demo(cfg, stop.event, out, lines.progress)
    except KeyboardInterrupt:
        lines.end()
        print(f"{PROG}: stopped; every process it started is stopped", file=sys.stderr)
        return 130
    lines.end()
    if a.json:
        print_json(summary)
    else:
        print("\n".join(summary_lines(summary)), flush=True)
    return 0 if summary["ok"] else EXIT_FAILURE
