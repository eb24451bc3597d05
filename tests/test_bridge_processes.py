"""Three agents as real processes (tests/bridge_node.py) exchanging numbered P2P
messages: over Zenoh on loopback TCP, and over a real ``swarm radio-emu`` process
with 10% frame loss through a RadioBridge in each node. Every node must hear from
both others, a reasonable share of what was sent, and never the same sequence
number twice (a duplicate could only come from a loop)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port

from swarm.cli.procs import start_emulator

# timing: the share of frames through in a fixed 6 s window
pytestmark = [pytest.mark.processes, pytest.mark.timing]  # bridge processes on emulated radios and Zenoh

NODE = Path(__file__).resolve().parent / "bridge_node.py"
ROOT = NODE.parent.parent
NAMES = ("a1", "a2", "a3")
SECONDS = 6.0
RUN_DEADLINE = 90.0  # start-up, lock, sending, linger: far less unless the machine is stuck


@contextmanager
def nodes(per_node_args: Sequence[Sequence[str]]) -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    try:
        for i, extra in enumerate(per_node_args):
            name = NAMES[i]
            peers = ",".join(n for n in NAMES if n != name)
            procs.append(
                subprocess.Popen(
                    [
                        sys.executable,
                        str(NODE),
                        "--name",
                        name,
                        "--id",
                        str(i + 1),
                        "--peers",
                        peers,
                        "--seconds",
                        str(SECONDS),
                        *extra,
                    ],
                    cwd=ROOT,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    text=True,
                )
            )
        yield procs
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait(10)


def reports(procs: list[subprocess.Popen[str]]) -> dict[str, dict[str, Any]]:
    out = {}
    for p in procs:
        stdout, stderr = p.communicate(timeout=RUN_DEADLINE)
        assert p.returncode == 0, f"node exited with {p.returncode}: {stderr[-2000:]}"
        lines = [ln for ln in stdout.splitlines() if ln.startswith("{")]
        assert lines, f"no report from a node: {stderr[-2000:]}"
        r = json.loads(lines[-1])
        out[r["name"]] = r
    return out


def check(rep: dict[str, dict[str, Any]], min_fraction: float) -> None:
    for name, r in rep.items():
        assert r["stray"] == 0 and r["decode_errors"] == 0, r
        for peer in NAMES:
            if peer == name:
                continue
            got = r["received"].get(peer, [])
            sent = rep[peer]["sent"][name]
            assert sent > 0, f"{peer} never sent to {name}: {rep[peer]}"
            assert len(got) == len(set(got)), f"{name} got duplicates from {peer}: {sorted(got)}"
            assert len(got) <= sent
            assert len(got) > min_fraction * sent, f"{name} got {len(got)} of {sent} messages from {peer}"


def test_three_processes_over_zenoh_on_ip() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    with nodes([["--listen", ep], ["--connect", ep], ["--connect", ep]]) as procs:
        rep = reports(procs)
    check(rep, 0.8)


def test_three_processes_over_emulated_radios_with_loss(tmp_path: Path) -> None:
    emu, paths = start_emulator(3, tmp_path, "--loss", "0.1", "--seed", "16")
    try:
        with nodes([["--radio", p] for p in paths]) as procs:
            rep = reports(procs)
    finally:
        emu.stop()
    check(rep, 0.5)
    for name, r in rep.items():
        b = r["bridge"]
        assert b["frames_in"] > 0 and b["published"] > 0, (name, b)
        # a node sends its own messages, advertisements and heartbeats, nothing it received
        own = sum(r["sent"].values()) + r["advertized"] + b["heartbeats"] + b["conflicts"]
        assert b["frames_out"] <= own, (name, b)
