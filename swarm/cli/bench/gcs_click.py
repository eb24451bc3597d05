"""``click_to_setpoint_ms`` for ``swarm bench gcs``: from a click on the page to the agent steering.

A real bench on a lossy radio: ``swarm radio-emu --loss P`` (10 % of the frames
lost), two ``swarm agent`` processes each flying a ``swarm sim`` vehicle, and
``swarm gcs`` on the third radio. Once both agents are connected, agent 1 is armed
and takes off (over the HTTP API); then the page, in headless Chromium, sends
go-tos to it: each trial fills the go-to fields and clicks Go, and the time runs
until agent 1's ``--json`` output says its pilot took that command (``command GOTO
seq N from 255: ACCEPTED``: the pilot turns to the target there and sends its first
setpoint towards it on its next step, within 0.1 s, which the figures add whole:
an upper bound). What the time holds: the
page's WebSocket, the station, the radio hops with their losses and retries, the
agent's protocol and pilot. The agent's output is read as it comes (every 5 ms), so
the figure is a few milliseconds late at most, plus the pilot's next step.
"""

from __future__ import annotations

import json
import re
import statistics
import tempfile
import time
from typing import Any

from radios.ports import free_port, free_port_range
from swarm.cli.bench.agent import start_agent
from swarm.cli.bench.commands import get_json
from swarm.cli.bench.commands import post_json as post
from swarm.cli.bench.gcs_page import launch_browser, percentile
from swarm.cli.procs import Child, json_events, start_emulator

_GOTO_RE = re.compile(r"^command GOTO seq (\d+) from \d+: (\w+)")
SETUP_S = 150.0
STEP_S = 0.1  # the pilot's setpoint period: the first setpoint follows the command within one


def post_json(url: str, body: Any) -> Any:
    return post(url, body)[1]


def _until(pred: Any, what: str, timeout: float, children: list[Child]) -> Any:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        for c in children:
            if c.proc.poll() is not None:
                raise RuntimeError(f"{c.name} exited: " + " | ".join(c.errors[-3:]))
        got = pred()
        if got:
            return got
        time.sleep(0.25)
    raise RuntimeError(f"{what}: not within {timeout:.0f} s")


def _agent1(url: str) -> dict[str, Any] | None:
    return next((a for a in get_json(url + "api/state")["agents"] if a["id"] == 1), None)


def _fly(url: str, children: list[Child]) -> None:
    """Agent 1 armed and airborne (commands retried until accepted)."""

    def ok(body: dict[str, Any]) -> bool:
        return bool(body.get("ok")) and all(
            r.get("result") in ("ACCEPTED", "CARRIED_OUT") for r in body["results"]
        )

    _until(lambda: ok(post_json(url + "api/command", {"target": 1, "kind": "arm"})), "arm", 60, children)
    _until(
        lambda: ok(post_json(url + "api/command", {"target": 1, "kind": "takeoff", "alt": 10})),
        "takeoff",
        60,
        children,
    )
    a = _until(
        lambda: (lambda a: a if a and a.get("airborne") else None)(_agent1(url)), "airborne", 90, children
    )
    # the climb done, the pilot takes a go-to (it refuses one while taking off)
    here = {"target": 1, "kind": "goto", "lat": a["lat"], "lon": a["lon"], "alt": _above_home(a)}
    _until(lambda: ok(post_json(url + "api/command", here)), "a go-to taken after the take-off", 90, children)


def _above_home(a: dict[str, Any]) -> float:
    """The agent's height above its home (every altitude a command carries), 10 m when
    the station has not seen its home."""
    if isinstance(a.get("alt"), (int, float)) and isinstance(a.get("home_alt"), (int, float)):
        return max(5.0, round(float(a["alt"]) - float(a["home_alt"])))
    return 10.0


def _trial(page: Any, agent: Child, lat: float, lon: float, alt: float) -> float | None:
    """One go-to from the page: seconds from the click to the pilot's ACCEPTED, or None."""
    page.fill("#goto-lat", f"{lat:.7f}")
    page.fill("#goto-lon", f"{lon:.7f}")
    page.fill("#goto-alt", f"{alt:.0f}")
    mark = len(agent.lines)
    t0 = time.monotonic()
    page.click("#goto-go")
    while time.monotonic() - t0 < 30.0:
        for e in json_events(agent.lines[mark:], "pilot"):
            m = _GOTO_RE.match(str(e.get("text", "")))
            if m:
                return time.monotonic() - t0 if m.group(2) == "ACCEPTED" else None
        time.sleep(0.005)
    return None


def measure(trials: int = 7, loss: float = 0.1) -> dict[str, Any]:
    """``click_to_setpoint_ms_p50`` (and its spread) over ``trials`` go-tos."""
    children: list[Child] = []
    with tempfile.TemporaryDirectory(prefix="swarm-bench-click-") as d:
        emu, links = start_emulator(3, d, "--loss", str(loss))
        try:
            base = free_port_range(2, "udp")
            for k in (1, 2):
                children += start_agent(k, links[k - 1], base + k - 1, [])
            http = f"127.0.0.1:{free_port('tcp')}"
            gcs = Child(["gcs", "--radio", links[2], "--http", http, "--tiles", "none", "--json"], name="gcs")
            children.append(gcs)
            url = json.loads(gcs.wait_lines(1, 30)[0])["url"]
            st = lambda: sum(a["connected"] for a in get_json(url + "api/state")["agents"]) == 2  # noqa: E731
            _until(st, "both agents connected", SETUP_S, children)
            _fly(url, children)
            a = _agent1(url) or {}
            took: list[float] = []
            with launch_browser() as ctx:
                page = ctx.new_page()
                page.goto(url)
                page.wait_for_function("() => window.gcs && window.gcs.markers >= 2", timeout=30000)
                page.click('#agents [data-agent-id="1"]')
                for i in range(trials):
                    d_lat = 1.5e-4 * (1 if i % 2 else -1)
                    t = _trial(page, children[1], a["lat"] + d_lat, a["lon"], _above_home(a))
                    if t is not None:
                        took.append(t * 1000.0)
                    time.sleep(1.0)
        finally:
            for c in children:
                c.stop(grace=3)
            emu.stop()
    return {
        # the pilot took the command; its first setpoint follows within one step (counted whole)
        "click_to_setpoint_ms_p50": round(statistics.median(took) + STEP_S * 1000) if took else None,
        "click_to_setpoint_ms_p95": round(percentile(took, 0.95) + STEP_S * 1000) if took else None,
        "click_to_setpoint_trials": trials,
        "click_to_setpoint_taken": len(took),
        "click_to_setpoint_loss": loss,
    }
