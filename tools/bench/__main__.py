"""``python -m tools.bench <area> [--json] [--quick] [--real]``: the project's own benches.

From a checkout (they read its recorded traces and find the SITL builds through
``$SITL_DIR``); output, Ctrl-C and SIGTERM as ``swarm bench``.
"""

from __future__ import annotations

import argparse

from swarm.cli.commands.bench import run_area
from swarm.cli.util import UsageError, guarded, parser

PROG = "python -m tools.bench"
AREAS = {  # area -> (module in tools.bench, what it measures)
    "conformance": (
        "conformance",
        "simulated ArduCopter and PX4 vs recorded SITL traces: milestones, acks, timings; "
        "--real: the simulator vs real ArduCopter and PX4 SITL, live",
    ),
    "replay": (
        "replay_speed",
        "swarm replay --json on the checked-in demo capture: capture seconds per wall second",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    p = parser(PROG, "Run one of the project's own benches (from a checkout).")
    p.add_argument("area", choices=sorted(AREAS), help="; ".join(f"{k}: {v[1]}" for k, v in AREAS.items()))
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true", help="shorter runs (CI): same fields, wider noise")
    p.add_argument(
        "--real",
        action="store_true",
        help="conformance: fly the real autopilots ($SITL_DIR) beside the simulator, live",
    )
    return p


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.real and args.area != "conformance":
        raise UsageError(f"--real is for the conformance bench, not {args.area}")
    kw = {"real": True} if args.real else {}
    module = f"tools.bench.{AREAS[args.area][0]}"
    return run_area(f"{PROG} {args.area}", module, as_json=args.json, quick=args.quick, **kw)


if __name__ == "__main__":
    raise SystemExit(main())
