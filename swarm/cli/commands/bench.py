"""``swarm bench <area> [--json] [--quick]``: run a benchmark and print its figures."""

from __future__ import annotations

import importlib
import signal
from typing import Any

from swarm.cli.util import guarded, parser, print_json

PROG = "swarm bench"
AREAS = {  # area -> (module in swarm.cli.bench, what it measures)
    "radio": ("radio", "emulator goodput, latency, TDM round and CPU vs the SiK model"),
    "sim": ("sim", "vehicle simulator real-time factor and CPU, driver setpoint timing"),
    "messages": ("messages", "message and frame sizes, bridge latency, JSON ratio"),
    "simulate": ("simulate", "simulator campaigns for the election targets (virtual time)"),
    "campaign": ("campaign", "the seeded fault campaign: violations, scenarios per CPU second, by kind"),
    "election": ("election", "real agent processes vs the simulator: election times"),
    "gcs": ("gcs", "ground station: 50 agents at 5 Hz, WebSocket rate, server CPU, page frames"),
    "formation": ("formation", "V formation slot error and air use vs pose rate and loss"),
    "faults": ("faults", "a signed swarm in flight: crashes, restarts, unplugs, a rogue radio"),
    "agent": ("agent", "one agent: start-up to first Advertize, imports, CPU, memory, flight-log loss"),
    "conformance": ("conformance", "simulated ArduCopter vs recorded SITL traces: milestones, acks, timings"),
}


def _interrupt(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    p = parser(PROG, "Run a benchmark; figures are printed as a table or one JSON object.")
    p.add_argument("area", choices=sorted(AREAS), help="; ".join(f"{k}: {v[1]}" for k, v in AREAS.items()))
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true", help="shorter runs (CI): same fields, wider noise")
    args = p.parse_args(argv)
    # SIGTERM as Ctrl-C: the benches stop the processes they started on the way out
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        result = importlib.import_module(f"swarm.cli.bench.{AREAS[args.area][0]}").run(quick=args.quick)
    finally:
        signal.signal(signal.SIGTERM, previous)
    if args.json:
        print_json(result)
    else:
        width = max(len(k) for k in result)
        for k, v in result.items():
            print(f"{k:<{width}}  {v}")
    return 0
