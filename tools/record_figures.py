#!/usr/bin/env python3
"""Record benchmark figures for the docs' figures page: run ``swarm bench AREA --json``
for each AREA given (with ``--quick`` or ``--real`` passed on) and keep what it printed,
untouched, in ``docs/figures/AREA.json`` with when, where and from which commit it was
measured. The docs build renders every recorded file into the figures page: no figure
is ever copied by hand.

    .venv/bin/python tools/record_figures.py messages radio sim   # on a quiet machine
    .venv/bin/python tools/record_figures.py --real conformance   # the real autopilots

A bench that fails (exit status other than 0) or prints no JSON object is reported in
one line and its previous record is kept. Exit status: 0 when every area was recorded,
1 otherwise, 2 for bad usage, 130 when interrupted.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import signal
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "figures"


def _swarm() -> list[str]:
    venv = ROOT / ".venv" / "bin" / "swarm"
    return [str(venv)] if venv.exists() else [sys.executable, "-m", "swarm.cli"]


def commit() -> str:
    """The checkout's commit (``git describe --always --dirty``), or "unknown"."""
    try:
        run = subprocess.run(
            ["git", "-C", str(ROOT), "describe", "--always", "--dirty"], capture_output=True, text=True
        )
    except OSError:
        return "unknown"
    return run.stdout.strip() or "unknown"


def machine(load_before: float | None = None) -> dict[str, object]:
    """This machine as a record names it: CPUs, the 1-minute load before the run (now, if
    not given), the system and Python."""
    return {
        "cpus": os.cpu_count(),
        "load_1m_before": round(os.getloadavg()[0], 2) if load_before is None else load_before,
        "system": f"{platform.system()} {platform.machine()}",
        "python": platform.python_version(),
    }


#: the project's own benches (``python -m tools.bench``); every other area is ``swarm bench``'s
OWN_BENCHES = ("conformance", "replay")


def record(area: str, extra: list[str], out: Path = OUT) -> bool:
    if area in OWN_BENCHES:
        command = ["python", "-m", "tools.bench", area, *extra, "--json"]
        argv = [sys.executable, *command[1:]]
    else:
        command = ["swarm", "bench", area, *extra, "--json"]
        argv = [*_swarm(), *command[1:]]
    started = datetime.datetime.now(datetime.UTC)
    host = machine()
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        stdout, stderr = proc.communicate()
    except KeyboardInterrupt:  # Ctrl-C (the bench has it too) or SIGTERM: the bench stops with us
        proc.terminate()
        proc.wait()
        raise
    if proc.returncode != 0:
        last = (stderr.strip().splitlines() or ["no output"])[-1]
        print(f"record-figures: {area}: swarm bench exited {proc.returncode}: {last}", file=sys.stderr)
        return False
    try:
        result = json.loads(stdout)
    except json.JSONDecodeError:
        print(f"record-figures: {area}: swarm bench printed no JSON object", file=sys.stderr)
        return False
    if not isinstance(result, dict):
        print(f"record-figures: {area}: swarm bench printed no JSON object", file=sys.stderr)
        return False
    host["load_1m_after"] = round(os.getloadavg()[0], 2)
    took = (datetime.datetime.now(datetime.UTC) - started).total_seconds()
    entry = {
        "area": area,
        "command": " ".join(command),
        "recorded": started.strftime("%Y-%m-%dT%H:%MZ"),
        "took_s": round(took, 1),
        "commit": commit(),
        "machine": host,
        "result": result,
    }
    out.mkdir(parents=True, exist_ok=True)
    name = area if not extra else f"{area}{''.join(e.replace('--', '-') for e in extra)}"
    tmp = out / f".{name}.json.tmp"
    tmp.write_text(json.dumps(entry, indent=1) + "\n", encoding="utf-8")
    tmp.replace(out / f"{name}.json")
    print(f"record-figures: {area}: recorded in {took:.0f} s -> {out / name}.json", flush=True)
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tools/record_figures.py", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "areas",
        nargs="+",
        metavar="AREA",
        help="swarm bench areas (and the project's own: conformance, replay), recorded one after another",
    )
    parser.add_argument("--quick", action="store_true", help="pass --quick to each bench")
    parser.add_argument("--real", action="store_true", help="pass --real to each bench")
    parser.add_argument("--out", type=Path, default=OUT, help="where the records go (default docs/figures)")
    args = parser.parse_args(argv)
    extra = [flag for flag, on in (("--quick", args.quick), ("--real", args.real)) if on]
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        ok = [record(area, extra, args.out) for area in args.areas]
    except KeyboardInterrupt:
        print("record-figures: interrupted", file=sys.stderr)
        return 130
    return 0 if all(ok) else 1


if __name__ == "__main__":
    sys.exit(main())
