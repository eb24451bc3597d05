"""``swarm bench <area> [--json] [--quick]``: run a benchmark and print its figures.

The product's benches: what a user runs to measure the radios, the election, the
station and an agent. The project's own (the simulator against recorded and live
autopilots) are run from a checkout with ``python -m tools.bench``.

Text output is a table for people (:func:`text_table`: nested groups indented,
yes/no for targets), ``--json`` one object for programs. While it runs, a person on
a terminal sees the seconds counted on stderr (:class:`swarm.cli.progress.Ticker`).
Ctrl-C or SIGTERM stops it (exit 130); the benches stop what they started.
"""

from __future__ import annotations

import argparse
import importlib
import signal
from typing import Any

from swarm.cli.progress import Ticker
from swarm.cli.util import guarded, parser, print_json

PROG = "swarm bench"
AREAS = {  # area -> (module in swarm.cli.bench, what it measures)
    "radio": ("radio", "emulator goodput, latency, TDM round and CPU vs the SiK model"),
    "sim": ("sim", "vehicle simulator real-time factor and CPU, driver setpoint timing"),
    "messages": ("messages", "message and frame sizes, bridge latency, JSON ratio"),
    "simulate": ("simulate", "simulator campaigns for the election targets (virtual time)"),
    "scale": (
        "scale",
        "many swarms: N=50 on one channel with a cap, 200 agents on 4 channels (virtual time)",
    ),
    "campaign": ("campaign", "the seeded fault campaign: violations, scenarios per CPU second, by kind"),
    "election": ("election", "real agent processes vs the simulator: election times"),
    "gcs": ("gcs", "ground station: 50 agents at 5 Hz, WebSocket rate, server CPU, page frames"),
    "formation": ("formation", "V formation slot error and air use vs pose rate and loss"),
    "faults": ("faults", "a signed swarm in flight: crashes, restarts, unplugs, a rogue radio"),
    "agent": ("agent", "one agent: start-up to first Advertize, imports, CPU, memory, flight-log loss"),
    "scale-procs": (
        "scale_procs",
        "channels x agents, a station each and a Zenoh router: listing, command, kill",
    ),
    "ip-edge": (
        "ip_edge",
        "stations on two machines, a router over mutual TLS with an ACL, an attacker on every listener",
    ),
}


def _interrupt(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


def build_parser() -> argparse.ArgumentParser:
    p = parser(PROG, "Run a benchmark; figures are printed as a table or one JSON object.")
    p.add_argument("area", choices=sorted(AREAS), help="; ".join(f"{k}: {v[1]}" for k, v in AREAS.items()))
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true", help="shorter runs (CI): same fields, wider noise")
    return p


def run_area(prog: str, module: str, *, as_json: bool, quick: bool, **kw: Any) -> int:
    """Run ``module``'s ``run(quick=..., **kw)`` and print its figures (a table, or one
    JSON object); SIGTERM stops it as Ctrl-C does (the benches stop the processes they
    started on the way out). Also the project's own benches' runner (``tools.bench``)."""
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        with Ticker(prog, as_json=as_json):
            result = importlib.import_module(module).run(quick=quick, **kw)
    finally:
        signal.signal(signal.SIGTERM, previous)
    if as_json:
        print_json(result)
    else:
        print(text_table(result), flush=True)
    return 0


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    module = f"swarm.cli.bench.{AREAS[args.area][0]}"
    return run_area(f"{PROG} {args.area}", module, as_json=args.json, quick=args.quick)


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, list | tuple):
        return ", ".join(_value(x) for x in v) if v else "-"
    return "-" if v is None else str(v)


def text_table(result: dict[str, Any], indent: str = "") -> str:
    """The figures for a person: one ``name  value`` line each, a nested group (a
    dict) as its name then its own lines indented; no Python dicts. ``--json`` is
    for programs."""
    if not result:
        return ""
    width = max(len(str(k)) for k in result)
    lines = []
    for k, v in result.items():
        if isinstance(v, dict) and v:
            lines.append(f"{indent}{k}")
            lines.append(text_table(v, indent + "  "))
        else:
            lines.append(f"{indent}{k!s:<{width}}  {_value(v)}")
    return "\n".join(lines)
