"""``swarm bench scale-procs``: swarms on several channels, real processes, one Zenoh router.

Theory of operation
-------------------
Issue 16's process target: C channels (one ``swarm radio-emu`` each, its own NETID)
with N ``swarm agent`` processes each plus one radio for a ``swarm gcs``; every
station also connects to one ``swarm router``, and all of them share a swarm key
(radio frames and station envelopes signed). Measured from the moment the last
process printed its ready line:

* ``listing_s``: until station A's ``/api/state`` lists all C*N agents connected, in
  C swarms (each with a leader);
* ``command``: a FOLLOW to the swarm of the last channel (by its leader's id) sent as
  station A's page sends it (its WebSocket), whose results must include an ACCEPTED
  from that leader (carried there by its station);
* ``survivors``: station B (the second) killed with SIGKILL, until A shows B's agents
  disconnected and the other channels' swarms still led and connected.
* ``federation`` (before the kill): what the stations' whole states cost on the
  router. ``measured``: a Zenoh session of the bench's own on the router, subscribed
  to ``gcs/*/state`` for :data:`TRAFFIC_S` seconds, counts each station's envelopes
  and bytes (what one receiving station gets; the router sends every station's state
  to each of the others; the agents here have no vehicle: no position, no trail);
  ``model_5``, ``model_50``, ``model_200``: the envelope the same code seals for a
  station of 5, 50 or 200 agents *in flight* (:func:`state_cost`: this deployment's
  own agents copied, each with a position and a trail as long as a station keeps),
  sent as the federation sends it, and its bytes a second at the same rate, with
  what the same state cost before trails were cut and states deflated.

:class:`Deployment` starts and stops the processes (the process tests use it too);
``run(quick)`` is the bench: 3 x 5 with 3 stations, or 2 x 2 with 2 when quick.
"""

from __future__ import annotations

import json
import os
import signal
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

from radios.ports import free_port
from swarm.cli.procs import Child, start_emulator

DEADLINE = 60.0
TRAFFIC_S = 10.0  # how long the stations' states are counted on the router
TRAIL_POINTS = 120  # a station's trail at most (StationConfig.trail_points): the model's
PUBLISH_HZ = 2.0  # the federation's period: 0.5 s


def http(url: str, body: Any = None) -> tuple[int, Any]:
    """GET (or POST ``body`` as JSON) ``url``: (status, JSON)."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def ws_command(url: str, body: dict[str, Any], timeout: float = 30.0) -> dict[str, Any]:
    """``body`` sent as the page sends a command (on station ``url``'s WebSocket): its
    ``command_result``."""
    import asyncio

    import aiohttp

    async def go() -> dict[str, Any]:
        async with aiohttp.ClientSession() as s, s.ws_connect(url + "ws") as ws:
            await ws.send_json({"type": "command", "id": 1, **body})
            while True:
                msg = await asyncio.wait_for(ws.receive_json(), timeout)
                if msg.get("type") == "command_result":
                    return dict(msg)

    return asyncio.run(go())


def poll(check: Callable[[], Any], what: str, timeout: float = DEADLINE) -> Any:
    """``check()`` until it is truthy (returned); RuntimeError after ``timeout``."""
    end = time.monotonic() + timeout
    while True:
        v = check()
        if v:
            return v
        if time.monotonic() > end:
            raise RuntimeError(f"not within {timeout:.0f} s: {what}")
        time.sleep(0.2)


class Deployment:
    """``channels`` emulators x ``agents`` agents, one station per channel, one router."""

    def __init__(
        self,
        directory: Path,
        channels: int,
        agents: int,
        *,
        key: bool = True,
        agent_args: tuple[str, ...] = (),
    ) -> None:
        self.dir = directory
        self.channels, self.agents = channels, agents
        self.agent_args = list(agent_args)  # more flags for every agent (e.g. --swarm-cap N)
        self.children: list[Child] = []
        self.stations: list[Child] = []
        self.urls: list[str] = []
        self.killed: list[Child] = []
        self.t_start = 0.0
        self.key = str(directory / "swarm.key") if key else None
        self.router_ep = f"tcp/127.0.0.1:{free_port('tcp')}"

    def _child(self, argv: list[str], name: str) -> Child:
        c = Child(argv, name=name)
        self.children.append(c)
        return c

    def start(self) -> Deployment:
        self.t_start = time.monotonic()
        if self.key is not None:
            Path(self.key).write_bytes(os.urandom(32))
            Path(self.key).chmod(0o600)  # the agents refuse a key others can read
        # the nodes' state (their signing clocks, the stations' replay guards): this run's own
        keyed = ["--key", self.key, "--state-dir", str(self.dir / "state")] if self.key else []
        router = self._child(["router", "--listen", self.router_ep, "--json"], "router")
        router.wait_lines(1, 30)
        waiting = []
        for c in range(self.channels):
            d = self.dir / f"ch{c}"
            d.mkdir()
            emu, links = start_emulator(self.agents + 1, d, "--netid", str(25 + c), "--seed", str(16 + c))
            self.children.append(emu)
            for i in range(self.agents):
                aid = c * 20 + i + 1
                argv = ["agent", "--name", f"a{aid}", "--id", str(aid), "--radio", links[i + 1]]
                argv += [
                    "--profile",
                    "fast",
                    "--slots",
                    str(self.agents + 1),
                    "--json",
                    *keyed,
                    *self.agent_args,
                ]
                waiting.append(self._child(argv, f"a{aid}"))
            st = self._child(self.station_argv(c, links[0]), f"st{c}")
            self.stations.append(st)
        for st in self.stations:
            line = json.loads(st.wait_lines(1, 60)[0])
            self.urls.append(line["url"])
        for w in waiting:
            w.wait_lines(1, 60)
        return self

    def station_argv(self, c: int, link: str) -> list[str]:
        argv = ["gcs", "--name", f"st{c}", "--radio", f"c{c}={link}", "--zenoh-connect", self.router_ep]
        argv += ["--http", f"127.0.0.1:{free_port('tcp')}", "--tiles", "none", "--json"]
        return argv + (["--key", self.key, "--state-dir", str(self.dir / "state")] if self.key else [])

    def state(self, station: int = 0) -> dict[str, Any]:
        for c in self.children:
            if c.proc.poll() is not None and c not in self.killed:
                raise RuntimeError(f"{c.name} exited {c.proc.returncode}: {c.errors[-3:]}")
        return dict(http(self.urls[station] + "api/state")[1])

    def kill_station(self, c: int) -> None:
        st = self.stations[c]
        self.killed.append(st)
        st.proc.send_signal(signal.SIGKILL)
        st.proc.wait(10)

    def stop(self) -> None:
        for c in reversed(self.children):
            c.stop(grace=5)


def led_swarms(state: dict[str, Any]) -> dict[str, list[int]]:
    """Each channel's connected agents if they all follow one leader, by channel."""
    nets: dict[str, list[dict[str, Any]]] = {}
    for a in state["agents"]:
        nets.setdefault(a.get("net") or "?", []).append(a)
    out = {}
    for net, agents in nets.items():
        leaders = {a["leader"] for a in agents}
        if all(a["connected"] for a in agents) and len(leaders) == 1 and 0 not in leaders:
            out[net] = sorted(a["id"] for a in agents)
    return out


def state_traffic(router: str, seconds: float = TRAFFIC_S) -> dict[str, Any]:
    """Every station's ``gcs/<name>/state`` envelopes heard on ``router`` for ``seconds``:
    per station the envelopes a second and bytes a second, and their sum."""
    import threading

    from swarm.core.station.federation import PREFIX
    from swarm.runtime.keyspace.transport import open_session

    got: dict[str, list[int]] = {}
    lock = threading.Lock()

    def on(sample: Any) -> None:
        name = str(sample.key_expr).split("/")[1]
        with lock:
            got.setdefault(name, []).append(len(sample.payload.to_bytes()))

    session = open_session(connect=[router])
    try:
        sub = session.declare_subscriber(f"{PREFIX}/*/state", on)
        time.sleep(1.0)  # the route to the subscriber
        with lock:
            got.clear()
        time.sleep(seconds)
        with lock:
            counts = {k: list(v) for k, v in got.items()}
        sub.undeclare()
    finally:
        session.close()
    per = {
        k: {"states_per_s": round(len(v) / seconds, 2), "bytes_per_s": round(sum(v) / seconds),
            "state_bytes": round(sum(v) / len(v))}
        for k, v in sorted(counts.items())
    }  # fmt: skip
    return {"stations": per, "bytes_per_s": sum(x["bytes_per_s"] for x in per.values())}


def state_cost(agents: list[dict[str, Any]], n: int, key: bytes | None = b"k" * 32) -> dict[str, Any]:
    """The sealed state envelope of a station of ``n`` agents in flight, made of
    ``agents`` (a real station's, copied round-robin), each given a position, a home and
    a trail of :data:`TRAIL_POINTS` points of a random walk (7 decimals, as a station
    rounds them), one swarm per 10 agents: its bytes as sent (trails cut to
    :data:`~swarm.core.station.federation.TRAIL_SENT`, deflated) and a second at
    :data:`PUBLISH_HZ`; ``json_bytes``: its JSON once inflated; ``before_bytes_per_s``:
    whole trails, not deflated (what was sent before); ``seal_ms``: the time to make it
    (JSON, deflate, MAC), once a period.
    """
    import random

    from swarm.core.station.federation import KIND_STATE, TRAIL_SENT, fed_key, seal, thin
    from swarm.core.station.rows import StationState

    rng = random.Random(16)
    made = []
    for i in range(n):
        lat, lon = 47.3977419 + i * 1.3e-5, 8.5455938 + i * 1.7e-5
        a = dict(agents[i % len(agents)])
        a.update(id=i + 1, name=f"a{i + 1}", leader=i // 10 * 10 + 1, lat=lat, lon=lon, alt=512.3)
        a.update(heading=271.4, groundspeed=4.87, home=[round(lat, 7), round(lon, 7)], home_alt=488.1)
        trail = []
        for _ in range(TRAIL_POINTS):
            lat, lon = lat + rng.uniform(-4e-6, 4e-6), lon + rng.uniform(-6e-6, 6e-6)
            trail.append([round(lat, 7), round(lon, 7)])
        a["trail"] = trail
        made.append(a)
    swarms = [
        {"leader": k + 1, "members": list(range(k + 1, min(n, k + 10) + 1)), "colour": k // 10, "net": "c0"}
        for k in range(0, n, 10)
    ]
    # a made-up state in the shape a station publishes
    body = cast(StationState, {"agents": made, "events": [], "swarms": swarms, "alerts": []})
    fkey = fed_key(key) if key else None
    t0 = time.perf_counter()
    text = json.dumps(thin(body, TRAIL_SENT), separators=(",", ":")).encode()
    sent = seal(KIND_STATE, "st0", 1, 1, text, fkey, deflate=True)
    cpu_ms = (time.perf_counter() - t0) * 1000  # JSON, deflate, MAC: once per period
    before = seal(KIND_STATE, "st0", 1, 1, json.dumps(body, separators=(",", ":")).encode(), fkey)
    return {
        "agents": n,
        "state_bytes": len(sent),
        "bytes_per_s": round(len(sent) * PUBLISH_HZ),
        "json_bytes": len(text),
        "seal_ms": round(cpu_ms, 1),
        "before_bytes_per_s": round(len(before) * PUBLISH_HZ),
    }


def federation_cost(dep: Deployment) -> dict[str, Any]:
    """``federation``'s figures (module docstring) on a running deployment."""
    traffic = state_traffic(dep.router_ep)
    local = [a for a in dep.state()["agents"] if a.get("station") == "st0"]
    trail = sum(len(a.get("trail") or []) for a in local) / max(1, len(local))
    traffic["trail_points_mean"] = round(trail, 1)
    flying = {"model_5": state_cost(local, 5), "model_50": state_cost(local, 50)}
    return {"measured": traffic, **flying, "model_200": state_cost(local, 200)}


def measure(dep: Deployment) -> dict[str, Any]:
    """The three figures (see the module docstring) on a started deployment."""
    n, c = dep.channels * dep.agents, dep.channels
    t0 = time.monotonic()
    poll(
        lambda: len(led_swarms(dep.state())) == c and len(dep.state()["agents"]) == n,
        f"{n} agents in {c} swarms",
    )
    listing = time.monotonic() - t0
    last = f"c{c - 1}"
    leader = next(a["leader"] for a in dep.state()["agents"] if a["net"] == last)
    t1 = time.monotonic()
    body = ws_command(dep.urls[0], {"target": "swarm", "swarm": leader, "kind": "follow", "heading": 90})
    status = body["status"]
    acked = any(r.get("agent") == leader and r.get("result") == "ACCEPTED" for r in body.get("results", []))
    command = {
        "status": status,
        "acked_by_leader_on": last if acked else None,
        "s": round(time.monotonic() - t1, 2),
    }
    federation = federation_cost(dep)
    dep.kill_station(1)
    t2 = time.monotonic()

    def survivors() -> dict[str, list[int]] | None:
        s = dep.state()
        gone = [a for a in s["agents"] if a["net"] == "c1"]
        led = led_swarms({"agents": [a for a in s["agents"] if a["net"] != "c1"]})
        return led if len(led) == c - 1 and all(not a["connected"] for a in gone) else None

    led = poll(survivors, "station st1's agents shown gone, the others still led")
    return {
        "channels": c,
        "agents": n,
        "stations": c,
        "listing_s": round(listing, 2),
        "listing_since_first_start_s": round(t0 + listing - dep.t_start, 2),
        "command": command,
        "survivors": {"swarms": len(led), "agents": sum(len(v) for v in led.values())},
        "gone_after_kill_s": round(time.monotonic() - t2, 2),
        "federation": federation,
    }


def run(quick: bool) -> dict[str, Any]:
    channels, agents = (2, 2) if quick else (3, 5)
    with tempfile.TemporaryDirectory() as d:
        dep = Deployment(Path(d), channels, agents)
        try:
            dep.start()
            return measure(dep)
        finally:
            dep.stop()


__all__ = ["Deployment", "http", "led_swarms", "measure", "poll", "run", "state_cost", "state_traffic"]
