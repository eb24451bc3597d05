"""``swarm simulate``: seeded runs of N protocol cores over the air model, in virtual time."""

from __future__ import annotations

import argparse
import sys

from swarm.cli.util import UsageError, guarded, parser, print_json
from swarm.sim.simulate import Partition, Scenario, campaign, parse_at

PROG = "swarm simulate"


def _build_parser() -> argparse.ArgumentParser:
    p = parser(
        PROG,
        "Run K seeded scenarios of N protocol cores over the SiK air model in "
        "virtual time, check the invariants, and print the figures.",
    )
    p.add_argument("--agents", type=int, default=5, help="number of agents (default 5)")
    p.add_argument("--seeds", type=int, default=20, help="number of seeded runs (default 20)")
    p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--loss", type=float, default=0.0, help="uniform packet loss per receiver")
    p.add_argument("--burst-loss", metavar="P_GB,P_BG[,LG,LB]", help="Gilbert-Elliott bursty loss")
    p.add_argument(
        "--partition",
        action="append",
        default=[],
        metavar="T0-T1:1,2|3,4",
        help="agents in different groups cannot hear each other from T0 to T1 s",
    )
    p.add_argument(
        "--crash",
        action="append",
        default=[],
        metavar="ID@T",
        help="agent ID (or 'leader') stops for good at T s (leader: at T or when one exists)",
    )
    p.add_argument("--late", action="append", default=[], metavar="ID@T", help="agent ID starts at T s")
    p.add_argument("--profile", choices=("paper", "fast"), default="paper")
    p.add_argument("--air-speed", type=int, default=64, metavar="KBPS")
    p.add_argument("--duration", type=float, default=60.0, help="virtual seconds per run at most")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    return p


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = _build_parser().parse_args(argv)
    if not 1 <= a.agents <= 250:
        raise UsageError("--agents: 1..250")
    if a.seeds < 1:
        raise UsageError("--seeds: at least 1")
    if not 0 <= a.loss <= 1:
        raise UsageError("--loss: a probability between 0 and 1")
    try:
        for spec in a.partition:
            Partition.parse(spec)
        for spec in a.crash + a.late:
            who, _ = parse_at(spec)
            if who != "leader" and not (who.isdigit() and 1 <= int(who) <= a.agents):
                raise ValueError(f"{spec!r}: agent ids are 1..{a.agents}")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    sc = Scenario(
        agents=a.agents,
        loss=a.loss,
        burst_loss=a.burst_loss,
        partitions=a.partition,
        crashes=a.crash,
        late=a.late,
        profile=a.profile,
        air_kbps=a.air_speed,
        duration=a.duration,
    )
    result = campaign(sc, a.seeds, a.seed)
    if a.json:
        print_json(result)
    else:
        for k, v in result.items():
            if k != "failing":
                print(f"{k:<20} {v}")
        for f in result["failing"]:
            print(f"FAILED seed {f['seed']}: {'; '.join(f['violations'])}\n  replay: {f['replay']}")
    for f in result["failing"]:
        print(f"replay failing seed {f['seed']}: {f['replay']}", file=sys.stderr)
    return 0 if not result["failing"] else 1
