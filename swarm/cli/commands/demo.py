"""``swarm demo``: the whole bench on one machine (emulated radios, simulated PX4
vehicles, agents, ground station): election, take-off, V formation along a route
with a 90 degree turn, landing, then a summary and a plot.

Progress goes to stdout (to stderr with ``--json``, whose stdout is one JSON
object: ``leader``, ``elect_s``, ``formation_rms_m``, ``formation_max_m``,
``turn_max_m``, ``air_utilisation``, ``capture``, ``plot``, ``gcs``, ``ok``...).
Exit 0 only when the swarm flew in formation (RMS slot error within
``--max-rms``); 1 otherwise (a process that failed, a step that did not happen in
time: :class:`~swarm.cli.demo.DemoError` and :class:`~swarm.cli.procs.ChildError`,
reported by the command guard); 130 on Ctrl-C or SIGTERM, after stopping every
process it started.
"""

from __future__ import annotations

import argparse
import sys
import webbrowser

from swarm.cli.configfile import read_arguments
from swarm.cli.demo import DemoConfig, run_demo
from swarm.cli.util import EXIT_FAILURE, StopFlag, UsageError, guarded, parser, print_json

PROG = "swarm demo"


def _build_parser() -> argparse.ArgumentParser:
    p = parser(PROG, "Run the whole swarm on this machine: radios, vehicles, agents, ground station.")
    p.add_argument("--agents", type=int, default=5, metavar="N", help="agents (2..20, default 5)")
    p.add_argument("--loss", type=float, default=0.1, metavar="P", help="radio packet loss (default 0.1)")
    p.add_argument("--profile", choices=("paper", "fast"), default="paper", help="election timing profile")
    p.add_argument(
        "--duration",
        type=float,
        default=170.0,
        metavar="S",
        help="give up after this many seconds (default 170)",
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
    p.add_argument("--dir", metavar="DIR", help="working directory (default: a new temporary one)")
    p.add_argument("--seed", type=int, default=0, help="seed of the radio loss")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    return p


def _config(a: argparse.Namespace) -> DemoConfig:
    """The run's configuration. Raises UsageError."""
    cfg = DemoConfig(
        agents=a.agents,
        loss=a.loss,
        profile=a.profile,
        duration=a.duration,
        workdir=a.dir,
        capture=a.capture,
        plot=a.plot,
        leg_m=a.leg,
        speed_mps=a.speed,
        settle_s=a.settle,
        max_rms_m=a.max_rms,
        gcs=not a.no_gcs,
        http=a.http,
        seed=a.seed,
    )
    try:
        cfg.check()
        if not 0.5 <= a.speed <= 15 or not 0.1 <= a.max_rms <= 50 or not 0 <= a.settle <= 300:
            raise ValueError("--speed 0.5..15 m/s, --max-rms 0.1..50 m, --settle 0..300 s")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return cfg


SUMMARY_KEYS = (
    "leader",
    "elect_s",
    "formation_rms_m",
    "formation_max_m",
    "turn_max_m",
    "air_utilisation",
    "capture",
    "plot",
    "gcs",
    "wall_s",
    "ok",
)


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = read_arguments(_build_parser(), argv, config=False)
    cfg = _config(a)
    stream = sys.stderr if a.json else sys.stdout
    opened = False

    def out(line: str) -> None:
        nonlocal opened
        print(line, file=stream, flush=True)
        if line.strip().startswith("ground station: http") and not a.headless and not opened:
            opened = True
            try:
                webbrowser.open(line.split(": ", 1)[1])
            except Exception:
                pass

    stop = StopFlag().install()
    try:
        summary = run_demo(cfg, stop.event, out)
    except KeyboardInterrupt:
        print(f"{PROG}: stopped; every process it started is stopped", file=sys.stderr)
        return 130
    if a.json:
        print_json(summary)
    else:
        print("== summary")
        for k in SUMMARY_KEYS:
            print(f"   {k}: {summary.get(k)}")
    return 0 if summary["ok"] else EXIT_FAILURE
