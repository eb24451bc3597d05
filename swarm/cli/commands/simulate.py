"""``swarm simulate``: seeded runs of N protocol cores over the air model, in virtual time.

Seeds run over ``--jobs`` processes (:mod:`swarm.sim.parallel`; the figures do not
depend on it). Ctrl-C or SIGTERM stops the workers, prints one line and exits 130.
``--channels``, ``--place`` and ``--command-at`` run a deployment over several
channels, with a station on each relaying one swarm command (:mod:`swarm.sim.channels`).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from swarm.cli.progress import Progress
from swarm.cli.util import EXIT_INTERRUPTED, UsageError, guarded, parser, print_json
from swarm.core.election.caps import MAX_CAP, check_cap
from swarm.core.election.profiles import PROFILE_NAMES
from swarm.sim.campaign import run_campaign
from swarm.sim.channels import DEFAULT_LATENCY_S, MAX_CHANNELS, ChannelScenario, run_channels
from swarm.sim.parallel import sweep
from swarm.sim.scenario import Link, parse_drift, parse_span
from swarm.sim.simulate import Partition, Scenario, parse_at

PROG = "swarm simulate"
#: the repeatable fault flags: (flag, Scenario field, metavar, help)
_FAULT_FLAGS = (
    (
        "--partition",
        "partitions",
        "T0-T1:1,2|3,4",
        "agents in different groups cannot hear each other from T0 to T1 s",
    ),
    (
        "--crash",
        "crashes",
        "ID@T",
        "agent ID (or 'leader') stops for good at T s (leader: at T or when one exists)",
    ),
    ("--late", "late", "ID@T", "agent ID starts at T s"),
    (
        "--link",
        "links",
        "A>B:P[@T0-T1]",
        "what agent A sends reaches B with loss P (1: a one-way link), for the run or from T0 to T1 s",
    ),
    (
        "--restart",
        "restarts",
        "ID@T0-T1",
        "agent ID's process is down from T0 and starts afresh (no state) at T1 s",
    ),
    (
        "--pause",
        "pauses",
        "ID@T0-T1",
        "agent ID is frozen from T0 and resumes with its state at T1 s (SIGSTOP/SIGCONT)",
    ),
    ("--drift", "drift", "ID:PPM", "agent ID's clock runs PPM ppm fast (negative: slow)"),
)


def build_parser() -> argparse.ArgumentParser:
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
    for flag, _, metavar, text in _FAULT_FLAGS:
        p.add_argument(flag, action="append", default=[], metavar=metavar, help=text)
    p.add_argument(
        "--strict", action="store_true", help="check the fault campaign's continuous invariants too"
    )
    p.add_argument(
        "--cap",
        type=int,
        default=0,
        metavar="N",
        help="each agent's swarm size cap (sub-swarms of at most N; 0: none, one swarm; default 0)",
    )
    p.add_argument(
        "--campaign",
        type=int,
        metavar="K",
        help="run K scenarios drawn from the fault distribution seeded --seed (ignores the scenario "
        "flags), shrink the failing ones and print their replay commands",
    )
    profiles = (
        "timing profile: the paper's windows, fast (from the TDM round) or tdm (votes while "
        "pooling, for SiK multipoint); default paper; with --campaign: every scenario's "
        "(default: each draws paper or fast)"
    )
    p.add_argument("--profile", choices=PROFILE_NAMES, default=None, help=profiles)
    p.add_argument(
        "--air-speed", type=int, default=64, metavar="KBPS", help="air rate in kbit/s (default 64)"
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="virtual seconds per run at most (default: 60, or 20 TDM rounds when longer)",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        metavar="N",
        help="worker processes for the seeds (default: all cores; 1 runs them here); "
        "the results are the same for any N",
    )
    _add_channel_flags(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    return p


def _add_channel_flags(p: argparse.ArgumentParser) -> None:
    """Several channels and the station relaying between them (:mod:`swarm.sim.channels`)."""
    p.add_argument(
        "--channels",
        type=int,
        default=1,
        metavar="K",
        help=f"radio channels (NETIDs, 1..{MAX_CHANNELS}): the agents are dealt over them round robin, "
        "each channel its own TDM ring; figures per channel and for the whole run (default 1)",
    )
    p.add_argument(
        "--place",
        metavar="A-B:C,...",
        help="which agents are on which channel, e.g. 1-50:1,51-100:2 (with --channels)",
    )
    p.add_argument(
        "--command-at",
        type=float,
        metavar="T",
        help="a station on each channel; the operator gives the station of channel 1 one swarm "
        "command (FOLLOW) at T s, the stations pass it on to every channel; counts the swarms that answer",
    )
    p.add_argument(
        "--relay-latency",
        type=float,
        default=DEFAULT_LATENCY_S,
        metavar="S",
        help=f"seconds a command takes from one station to another (default {DEFAULT_LATENCY_S:g})",
    )


def _raise_interrupt(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


@contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """SIGTERM stops the run as Ctrl-C does (the pool's workers are ended before exit)."""
    old = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _interruptible(run: Callable[[], dict[str, Any]]) -> dict[str, Any] | None:
    """``run()``, or None after one line when Ctrl-C or SIGTERM stopped it (and its workers)."""
    try:
        with _sigterm_interrupts():
            return run()
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted, workers stopped, no results", file=sys.stderr, flush=True)
        return None


def _check_specs(a: argparse.Namespace) -> None:
    """Every fault flag parses and names agents 1..--agents (one line, exit 2 if not)."""
    n = a.agents
    try:
        for spec in a.partition:
            Partition.parse(spec)
        ids: list[tuple[str, str]] = []
        for spec in a.crash + a.late:
            who, _ = parse_at(spec)
            ids.append((spec, who))
        for spec in a.link:
            k = Link.parse(spec)
            ids += [(spec, str(k.src)), (spec, str(k.dst))]
        ids += [(spec, str(parse_span(spec)[0])) for spec in a.restart + a.pause]
        ids += [(spec, str(parse_drift(spec)[0])) for spec in a.drift]
        for spec, who in ids:
            if who != "leader" and not (who.isdigit() and 1 <= int(who) <= n):
                raise ValueError(f"{spec!r}: agent ids are 1..{n}")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if a.campaign is not None and not 1 <= a.campaign <= 1_000_000:
        raise UsageError("--campaign: 1..1000000 scenarios")


def _campaign(a: argparse.Namespace) -> int:
    def scenarios() -> dict[str, Any]:
        with Progress(PROG, a.campaign, "scenarios", as_json=a.json) as bar:
            return run_campaign(a.campaign, a.seed, jobs=a.jobs, on_done=bar.advance, profile=a.profile)

    result = _interruptible(scenarios)
    if result is None:
        return EXIT_INTERRUPTED
    if a.json:
        print_json(result)
    else:
        for k in ("scenarios", "seed", "violations", "virtual_s", "agents_max"):
            print(f"{k:<20} {result[k]}")
        for kind, v in result["by_kind"].items():
            print(f"  {kind:<18} {v['scenarios']:>6} scenarios {v['failing']:>5} failing")
    for f in result["failing"]:
        print(f"FAILED scenario {f['index']}: {'; '.join(f['violations'])}", file=sys.stderr)
        print(f"  replay: {f['replay']}", file=sys.stderr)
        if "shrunk" in f:
            print(f"  shrunk: {f['shrunk']['replay']}", file=sys.stderr)
    return 0 if not result["failing"] else 1


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if not 1 <= a.agents <= 250:
        raise UsageError("--agents: 1..250")
    if a.seeds < 1:
        raise UsageError("--seeds: at least 1")
    if a.duration is not None and not 0 < a.duration <= 86400:
        raise UsageError("--duration: virtual seconds, more than 0 and at most 86400")
    if not 1 <= a.jobs <= 256:
        raise UsageError("--jobs: 1..256")
    if not 0 <= a.loss <= 1:
        raise UsageError("--loss: a probability between 0 and 1")
    try:
        check_cap(a.cap)
    except ValueError:
        raise UsageError(f"--cap {a.cap}: 0 (no cap) or 2..{MAX_CAP} agents per swarm") from None
    _check_specs(a)
    faults: dict[str, Any] = {field: getattr(a, flag[2:]) for flag, field, _, _ in _FAULT_FLAGS}
    sc = Scenario(
        agents=a.agents,
        loss=a.loss,
        burst_loss=a.burst_loss,
        profile=a.profile or "paper",
        air_kbps=a.air_speed,
        duration=a.duration,
        strict=a.strict,
        cap=a.cap,
        command_at=a.command_at,
        **faults,
    )
    if a.command_at is None and a.relay_latency != DEFAULT_LATENCY_S:
        raise UsageError("--relay-latency: only with --command-at")
    if a.channels != 1 or a.place is not None or a.command_at is not None:
        return _channels(a, sc)
    if a.campaign is not None:
        return _campaign(a)

    def seeded() -> dict[str, Any]:
        with Progress(PROG, a.seeds, "seeds", as_json=a.json) as bar:
            return sweep(sc, a.seeds, a.seed, jobs=a.jobs, on_done=bar.advance)

    result = _interruptible(seeded)
    if result is None:
        return EXIT_INTERRUPTED
    if a.json:
        print_json(result)
        for f in result["failing"]:  # for the person running the program that reads stdout
            print(f"replay failing seed {f['seed']}: {f['replay']}", file=sys.stderr)
    else:
        print(text_report(result), flush=True)
    return 0 if not result["failing"] else 1


def _channels(a: argparse.Namespace, sc: Scenario) -> int:
    """``--channels K``: the deployment's seeds, each channel a run (:mod:`swarm.sim.channels`)."""
    if a.campaign is not None or any(getattr(a, flag[2:]) for flag, _, _, _ in _FAULT_FLAGS):
        raise UsageError("--channels: the faults that name agents and --campaign are one-channel only")
    if a.command_at is not None and (a.strict or not 0 <= a.command_at <= 86400):
        raise UsageError("--command-at: virtual seconds 0..86400, not with --strict")

    try:
        cs = ChannelScenario.make(sc, a.channels, a.place, a.relay_latency)
    except ValueError as exc:
        raise UsageError(str(exc)) from None

    def seeded() -> dict[str, Any]:
        with Progress(PROG, a.seeds * cs.channels, "channel runs", as_json=a.json) as bar:
            return run_channels(cs, a.seeds, a.seed, jobs=a.jobs, on_done=bar.advance)

    result = _interruptible(seeded)
    if result is None:
        return EXIT_INTERRUPTED
    if a.json:
        print_json(result)
    else:
        print(channels_report(result), flush=True)
    for f in result["failing"]:
        print(f"replay failing seed {f['seed']} (channel {f['channel']}): {f['replay']}", file=sys.stderr)
        print(f"  that channel alone: {f['replay_channel']}", file=sys.stderr)
    return 0 if not result["failing"] else 1


def channels_report(r: dict[str, Any]) -> str:
    """The figures of a run over several channels (:func:`swarm.sim.channels.run_channels`)."""
    n, e = r["runs"], r["all_led_s"]
    lines = [
        f"{r['agents']} agents on {r['channels']} channel{'s' if r['channels'] > 1 else ''}, "
        f"{r['profile']} profile, "
        f"loss {r['loss']:g}: {n} runs",
        f"  every agent led       {r['all_led']} of {n} runs (every channel agreed and held)",
        f"  time until then       p50 {_fig(e['p50'])}, p95 {_fig(e['p95'])}, max {_fig(e['max'])}",
        f"  violations            {r['violations']} in all channel runs",
    ]
    for c in r["per_channel"]:
        ce, air = c["elect_s"], c["air_utilisation"]
        lines.append(
            f"  channel {c['channel']:<2} {c['agents']:>3} agents (round {c['round_s']:g} s): converged "
            f"{c['converged']} of {n}, p50 {_fig(ce['p50'])}, p95 {_fig(ce['p95'])}, "
            f"air max {_fig(_pct(air['max']), ' %')}"
        )
    if "relay" in r:
        x = r["relay"]
        e = x["all_answered_s"]
        lines += [
            f"  swarm command at {x['command_at']:g} s from the station of channel 1 "
            f"(stations {x['latency_s']:g} s apart):",
            f"    every swarm answered  {x['all_answered']} of {n} runs; swarms answering "
            f"{x['answered']['min']}..{x['answered']['max']} of {x['swarms']}, accepting "
            f"{x['accepted']['min']}..{x['accepted']['max']}",
            f"    last answer after     p50 {_fig(e['p50'])}, p95 {_fig(e['p95'])}, max {_fig(e['max'])}",
        ]
        lines += [f"    refused at once       {k}: {v} channel runs" for k, v in x["refused_at_once"].items()]
    return "\n".join(lines)


def _fig(v: float | None, unit: str = " s") -> str:
    return "-" if v is None else f"{v:g}{unit}"


def text_report(r: dict[str, Any]) -> str:
    """The campaign's figures (:func:`swarm.sim.parallel.sweep`) for a person: one
    line a figure saying what it counts, then each failing seed once with its replay."""
    n, e, air = r["runs"], r["elect_s"], r["air_utilisation"]
    rounds = r.get("election_rounds", {"p50": None, "p95": None})
    lines = [
        f"{r['agents']} agents, {r['profile']} profile, loss {r['loss']:g}: {n} runs "
        f"(TDM round {r['round_s']:g} s)",
        f"  converged             {r['converged']} of {n} runs (one agreed swarm held for the settle time)",
        f"  stable at the end     {r['stable_at_end']} of {n} runs (one leader all agree on at the end)",
        f"  violations            {r['violations']} in all runs (each failing run below says which)",
        f"  election time         p50 {_fig(e['p50'])}, p95 {_fig(e['p95'])}, max {_fig(e['max'])}",
        f"  election in rounds    p50 {_fig(rounds['p50'], '')}, p95 {_fig(rounds['p95'], '')} (TDM rounds)",
    ]
    if "failover_s" in r:
        f = r["failover_s"]
        lines.append(f"  failover time         p50 {_fig(f['p50'])}, p95 {_fig(f['p95'])}")
    lines += [
        f"  air time used         p50 {_fig(_pct(air['p50']), ' %')}, max {_fig(_pct(air['max']), ' %')}",
        f"  messages per agent    p50 {_fig(r['messages_per_agent']['p50'], '')}",
    ]
    fails = r["failing"]
    lines.append(
        f"failing runs: {len(fails)}" + (" (the first 10)" if len(fails) >= 10 else "") if fails else ""
    )
    for f in fails:
        lines.append(f"  seed {f['seed']}: {'; '.join(f['violations'])}")
        lines.append(f"    replay: {f['replay']}")
    return "\n".join(line for line in lines if line)


def _pct(share: float | None) -> float | None:
    return None if share is None else round(100 * share, 1)
