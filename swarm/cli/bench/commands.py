"""Command delivery through real processes on a lossy radio network.

A ``swarm radio-emu`` process with ``--loss`` (20% of the frames lost), a ``swarm gcs``
process and ``agents`` ``swarm agent`` processes, each on its own emulated radio. Once
the station sees every agent connected and a leader, ``n`` swarm commands go one
after the other through ``POST /api/command``, alternating FOLLOW (a new heading each
time) and STOP (to the leader and, fanned out, to every agent: agents without a
flight controller refuse their own STOP with their reason).

Every outcome is checked against what the agents themselves logged: the station's
event for each addressee names the command's seq (``[seq N]``) and each agent's
``--json`` output has ``command KIND seq N from 255: RESULT`` for every command it
answered (a repeat is answered from its log, never logged or run twice).

:func:`run` returns the figures: ``sent`` (commands posted), ``addressees``,
``accepted``, ``carried_out_unacked``, ``refused``, ``no_answer``,
``refused_at_station`` (no leader at that instant: nothing sent), ``silently_lost``
(an outcome the station never gave, or a command an agent carried out that the
station never reported) and ``wrongly_reported`` (ACCEPTED or CARRIED_OUT that no
agent carried out; NO_ANSWER or a refusal for a command an agent did carry out; a
refusal other than the agent's own), plus timings.
"""

from __future__ import annotations

import json
import re
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Sequence
from typing import Any, Protocol

from radios.ports import free_port
from swarm.cli.procs import Child, json_events, start_emulator

AGENT_RE = re.compile(r"^command (\w+) seq (\d+) from (\d+): (\w+)")
_STATION_RE = re.compile(r"^(\w+)(?: \(swarm\))? -> .*\((\d+)\): (\w+).* \[seq (\d+)\]$")


def get_json(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


def post_json(url: str, body: Any) -> tuple[int, Any]:
    req = urllib.request.Request(
        url, data=json.dumps(body).encode(), method="POST", headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(req, timeout=40) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


class HasLines(Protocol):
    """A process's output lines (a :class:`~swarm.cli.procs.Child`, or the lines from a mark on)."""

    lines: list[str]


def _events(child: HasLines, event: str) -> list[dict[str, Any]]:
    return json_events(child.lines, event)


def _alive(children: list[Child]) -> None:
    for c in children:
        if c.proc.poll() is not None:
            raise RuntimeError(f"{c.name} exited with {c.proc.returncode}: " + " | ".join(c.errors[-3:]))


def run(
    quick: bool = False,
    n: int | None = None,
    loss: float = 0.2,
    agents: int = 2,
    setup_timeout: float = 180.0,
) -> dict[str, Any]:
    n = n if n is not None else (20 if quick else 100)
    out: dict[str, Any] = {"commands": n, "loss": loss, "agents": agents}
    children: list[Child] = []
    with tempfile.TemporaryDirectory(prefix="swarm-bench-commands-") as d:
        emu, links = start_emulator(agents + 1, d, "--loss", str(loss))
        try:
            gcs = Child(
                [
                    "gcs",
                    "--radio",
                    links[0],
                    "--http",
                    f"127.0.0.1:{free_port('tcp')}",
                    "--tiles",
                    "none",
                    "--json",
                ],
                name="gcs",
            )
            children.append(gcs)
            url = json.loads(gcs.wait_lines(1, 30)[0])["url"]
            ags = [
                Child(
                    ["agent", "--name", f"agent{i}", "--id", str(i), "--radio", links[i], "--json"],
                    name=f"agent{i}",
                )
                for i in range(1, agents + 1)
            ]
            children += ags
            t0 = time.monotonic()
            while True:
                _alive(children)
                st = get_json(url + "api/state")
                if st["leader"] and sum(a["connected"] for a in st["agents"]) == agents:
                    break
                if time.monotonic() - t0 > setup_timeout:
                    raise RuntimeError(
                        f"no leader with all {agents} agents connected in {setup_timeout:.0f} s"
                    )
                time.sleep(0.5)
            out["setup_s"] = round(time.monotonic() - t0, 1)
            out.update(command_campaign(url, n, children))
            time.sleep(3.0)  # the agents' last log lines, the station's last events
            out.update(judge(gcs, ags, out.pop("_bodies")))
        finally:
            for c in children:
                c.stop(grace=3)
            emu.stop()
    return out


def command_campaign(url: str, n: int, children: list[Child]) -> dict[str, Any]:
    bodies: list[tuple[int, Any]] = []
    took: list[float] = []
    refused_here = 0
    t0 = time.monotonic()
    for k in range(n):
        _alive(children)
        cmd: dict[str, Any] = (
            {"target": "swarm", "kind": "follow", "heading": (k * 37) % 360}
            if k % 2 == 0
            else {"target": "swarm", "kind": "stop"}
        )
        t = time.monotonic()
        status, body = post_json(url + "api/command", cmd)
        if status == 409:  # no leader at this instant (an election): nothing was sent
            refused_here += 1
            time.sleep(1.0)
            continue
        took.append(time.monotonic() - t)
        bodies.append((status, body))
    took.sort()
    return {
        "_bodies": bodies,
        "sent": n,
        "refused_at_station": refused_here,
        "campaign_s": round(time.monotonic() - t0, 1),
        "command_s_p50": round(took[len(took) // 2], 2) if took else None,
        "command_s_max": round(took[-1], 2) if took else None,
    }


def judge(gcs: HasLines, agents: Sequence[HasLines], bodies: list[tuple[int, Any]]) -> dict[str, Any]:
    # what the agents did: (agent id, seq) -> result, from their own logs
    did: dict[tuple[int, int], str] = {}
    for a in agents:
        for e in _events(a, "pilot"):
            m = AGENT_RE.match(str(e.get("text", "")))
            if m and int(m.group(3)) >= 251:
                did[(int(e["id"]), int(m.group(2)))] = m.group(4)
    carried = {seq for (_, seq), r in did.items() if r == "ACCEPTED"}
    # what the station reported, per addressee, with the seq
    reported: list[tuple[int, int, str]] = []
    for e in _events(gcs, "log"):
        if e.get("kind") == "command":
            m = _STATION_RE.match(str(e.get("text", "")))
            if m:
                reported.append((int(m.group(2)), int(m.group(4)), m.group(3)))
    figures = {
        "addressees": 0,
        "accepted": 0,
        "carried_out_unacked": 0,
        "refused": 0,
        "no_answer": 0,
        "silently_lost": 0,
        "wrongly_reported": 0,
    }
    results = [r for status, body in bodies for r in (body.get("results") or [])]
    figures["addressees"] = len(results)
    # an HTTP answer without results (an error, a timeout) is an outcome never given
    figures["silently_lost"] += sum(1 for status, body in bodies if not body.get("results"))
    figures["silently_lost"] += abs(len(results) - len(reported))
    seqs_reported = {seq for _, seq, _ in reported}
    figures["silently_lost"] += len(carried - seqs_reported)  # done, never reported
    wrong: list[str] = []
    for agent, seq, result in reported:
        if result == "ACCEPTED":
            figures["accepted"] += 1
            if did.get((agent, seq)) != "ACCEPTED":
                wrong.append(f"seq {seq}: ACCEPTED by {agent}, whose log says {did.get((agent, seq))}")
        elif result == "CARRIED_OUT":
            figures["carried_out_unacked"] += 1
            if seq not in carried:
                wrong.append(f"seq {seq}: CARRIED_OUT, not in any agent's log")
        elif result == "NO_ANSWER":
            figures["no_answer"] += 1
            if seq in carried:
                wrong.append(f"seq {seq}: NO_ANSWER but carried out")
        else:
            figures["refused"] += 1
            if seq in carried or did.get((agent, seq)) != result:
                wrong.append(f"seq {seq}: {result} from {agent}, whose log says {did.get((agent, seq))}")
    figures["wrongly_reported"] = len(wrong)
    out: dict[str, Any] = dict(figures)
    out["wrong"] = wrong[:10]
    out["ok"] = figures["silently_lost"] == 0 and figures["wrongly_reported"] == 0
    return out


__all__ = ["run"]
