#!/usr/bin/env python3
"""Run the whole test suite on a busy machine: ``make test`` RUNS times in a row with BUSY
CPU-bound loops running beside it (the issue's "two busy loops, three times in a row"),
and record each run's verdict, wall time and failed tests in
``docs/figures/stress-suite.json`` for the docs' figures page.

    .venv/bin/python tools/stress_suite.py                  # 3 runs, 2 busy loops
    .venv/bin/python tools/stress_suite.py --runs 1 --busy 0   # one run on a quiet machine

Every run goes on even when one fails (the record says which tests failed). Exit status
0 when every run passed, 1 otherwise, 130 when interrupted (the busy loops and the run
in progress are stopped).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from record_figures import commit, machine  # the records' shared fields (tools/ is on sys.path)

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "figures"
BUSY = "while True: pass"


def one_run(command: list[str], log: Path) -> dict[str, object]:
    started = time.monotonic()
    with log.open("w") as out:
        proc = subprocess.Popen(
            command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
        )
        try:
            code = proc.wait()
        except BaseException:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait()
            raise
    text = log.read_text(errors="replace")
    failed = sorted(set(re.findall(r"^(?:FAILED|ERROR) (\S+)", text, re.M)))
    return {
        "passed": code == 0,
        "exit": code,
        "wall_s": round(time.monotonic() - started, 1),
        "failed": failed,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tools/stress_suite.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs in a row (default 3)")
    parser.add_argument("--busy", type=int, default=2, help="CPU-bound loops beside the suite (default 2)")
    parser.add_argument("--out", type=Path, default=OUT, help="where the record goes (default docs/figures)")
    parser.add_argument("--command", default="make test", help="what one run is (default: make test)")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.busy < 0:
        parser.error("--runs at least 1, --busy at least 0")
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    before = round(os.getloadavg()[0], 2)
    loops = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(args.busy)]
    runs: list[dict[str, object]] = []
    recorded = datetime.datetime.now(datetime.UTC)
    try:
        for i in range(1, args.runs + 1):
            log = Path(tempfile.gettempdir()) / f"stress-suite-run-{i}.log"  # not in the checkout
            args.out.mkdir(parents=True, exist_ok=True)
            print(
                f"stress-suite: run {i} of {args.runs} ({args.busy} busy loops): {args.command}", flush=True
            )
            result = one_run(args.command.split(), log)
            result["run"] = i
            result["load_1m_at_end"] = round(os.getloadavg()[0], 2)
            runs.append(result)
            verdict = "passed" if result["passed"] else f"FAILED {result['failed'] or result['exit']}"
            print(f"stress-suite: run {i}: {verdict} in {result['wall_s']} s (log {log})", flush=True)
    except KeyboardInterrupt:
        print("stress-suite: interrupted", file=sys.stderr)
        return 130
    finally:
        for p in loops:
            p.kill()
            p.wait()
    entry = {
        "area": "stress-suite",
        "command": f"tools/stress_suite.py --runs {args.runs} --busy {args.busy}",
        "recorded": recorded.strftime("%Y-%m-%dT%H:%MZ"),
        "took_s": round(sum(float(str(r["wall_s"])) for r in runs), 1),
        "commit": commit(),
        "machine": {**machine(before), "load_1m_after": round(os.getloadavg()[0], 2)},
        "result": {
            "busy_loops": args.busy,
            "runs": [
                {k: r[k] for k in ("run", "passed", "exit", "wall_s", "load_1m_at_end", "failed")}
                for r in runs
            ],
            "passed": sum(1 for r in runs if r["passed"]),
            "targets": {
                f"passes_{args.runs}_times_in_a_row_with_{args.busy}_busy_loops": all(
                    r["passed"] for r in runs
                )
            },
        },
    }
    (args.out / "stress-suite.json").write_text(json.dumps(entry, indent=1) + "\n", encoding="utf-8")
    return 0 if all(r["passed"] for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
