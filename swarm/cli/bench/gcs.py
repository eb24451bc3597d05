"""``swarm bench gcs``: the ground station with 50 simulated agents at 5 Hz.

A ``swarm gcs --zenoh-listen`` process is the station. Another process (this module
run with ``--feed``) plays N agents over one Zenoh session: each speaks the real
agent side of the connection protocol (:class:`swarm.core.agent.gslink.GsLink`: GSAdvertize,
GSConnectAck, Telemetry as its heartbeat at ``hz``) and also publishes its pose
and its AgentState at ``hz``, flying a circle. Once the station has all of them
connected:

* ``ws_bytes_per_s``: bytes of text one WebSocket client receives per second (the
  whole state once, then a delta per push at the station's 5 Hz, plus events; what
  the page parses: a browser that negotiates compression gets fewer on the wire),
  with ``ws_messages_per_s``, ``ws_deltas_per_s``, ``ws_delta_bytes`` (the mean
  delta) and ``ws_state_kb`` (the whole state, sent on connect);
  ``ws_wire_bytes_per_s``: the same texts compressed as on a browser's socket
  (permessage-deflate, which Chromium negotiates and the station accepts: one
  raw deflate stream per connection, each message flushed);
* ``server_cpu_percent``: the station process's CPU time over the same window, as
  a percentage of one core (:func:`swarm.cli.procs.cpu_seconds`);
* ``page_frame_ms_p95`` (and the page's other figures): the page in headless
  Chromium (:func:`swarm.cli.bench.gcs_page.measure_frames`), measured afterwards
  with the station still fed; null with a ``page_error`` when no browser can run.

``click_to_setpoint_ms_p50`` (and ``_p95``): from a Go clicked on the page to the
agent's first setpoint towards it, on a second bench of real processes with 10 %
radio loss (:mod:`swarm.cli.bench.gcs_click`), run after the first is stopped;
null with a ``click_to_setpoint_error`` when that bench cannot run.

Targets (the issue): station under 20% of one core; ``ws_bytes_per_s`` at most
20,000; page frame p95 at most 17 ms (one frame at 60 Hz).

``alarms_announced_per_10_min``, ``alarms_critical_at_start``, ``alarm_ws_bytes_per_s``
(and the alarm bench's other figures, :mod:`swarm.cli.bench.gcs_alarms`): 50 agents
of which 5 links flap and 5 batteries sit on the warning threshold, an operator who
acknowledges at once; on a station of its own (10 minutes; 90 s with ``--quick``).

``flood_operator_answered`` of ``flood_operator_requests`` (and the flood's other figures,
:mod:`swarm.cli.bench.gcs_flood`): the operator's requests answered while 2,000 idle
connections press on a station limited to 1024 open files, with their latency
against the same requests before; run last, on a station of its own.

"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import queue
import subprocess
import sys
import time
import urllib.request
import zlib
from typing import Any

from radios.ports import free_port
from swarm.cli.procs import Child, cpu_seconds
from swarm.core.agent.gslink import GsConfig, GsLink
from swarm.core.wire.codes import FLAG_AIRBORNE, FLAG_ARMED, FLAG_FC_OK, mode_code
from swarm.core.wire.message_types import AgentState, Phase, Pose, PoseReport, Telemetry
from swarm.core.wire.messages import decode, encode

AGENTS = 50
HZ = 5.0
CENTER = (47.397742, 8.545594)
TARGET_CPU = 20.0
TARGET_FRAME_MS = 17.0
TARGET_WS_BYTES = 20_000
FLAP_PERIOD_S = 60.0
FLAP_OFF_S = 15.0


def _get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


async def _ws_count(url: str, seconds: float) -> dict[str, Any]:
    import aiohttp

    counts: dict[str, Any] = {
        "messages": 0,
        "states": 0,
        "deltas": 0,
        "events": 0,
        "bytes": 0,
        "delta_bytes": 0,
        "wire_bytes": 0,
    }
    deflate = zlib.compressobj(wbits=-15)
    async with aiohttp.ClientSession() as s, s.ws_connect(url) as ws:
        first = await ws.receive(timeout=10)  # the whole state, sent on connect
        counts["state_bytes"] = len(first.data.encode()) if first.type == aiohttp.WSMsgType.TEXT else 0
        loop = asyncio.get_running_loop()
        begin = loop.time()
        end = begin + seconds
        while (left := end - loop.time()) > 0:
            try:
                msg = await ws.receive(timeout=left)
            except TimeoutError:
                break
            if msg.type != aiohttp.WSMsgType.TEXT:
                break
            counts["messages"] += 1
            raw = msg.data.encode()
            size = len(raw)
            counts["bytes"] += size
            # permessage-deflate (RFC 7692): the flush's empty block's 4 bytes are not sent
            counts["wire_bytes"] += len(deflate.compress(raw) + deflate.flush(zlib.Z_SYNC_FLUSH)) - 4
            if msg.data.startswith('{"type": "state"'):
                counts["states"] += 1
            elif msg.data.startswith('{"type":"delta"'):
                counts["deltas"] += 1
                counts["delta_bytes"] += size
            elif msg.data.startswith('{"type": "event"'):
                counts["events"] += 1
        counts["seconds"] = loop.time() - begin
    return counts


def run(quick: bool = False, agents: int = AGENTS, hz: float = HZ) -> dict[str, Any]:
    seconds = 8.0 if quick else 20.0
    # full trails (60 s) make the biggest state messages: the steady state
    warm_up = 2.0 if quick else 62.0
    ep = f"tcp/127.0.0.1:{free_port('tcp')}"
    station = Child(
        ["gcs", "--zenoh-listen", ep, "--http", f"127.0.0.1:{free_port('tcp')}", "--tiles", "none", "--json"],
        name="gcs",
    )
    feeder: subprocess.Popen[bytes] | None = None
    out: dict[str, Any] = {"agents": agents, "rate_hz": hz, "warm_up_s": warm_up, "measure_s": seconds}
    try:
        url = json.loads(station.wait_lines(1, 30)[0])["url"]
        feeder = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "swarm.cli.bench.gcs",
                "--feed",
                ep,
                "--agents",
                str(agents),
                "--hz",
                str(hz),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        out.update(_wait_connected(station, feeder, url, agents))
        time.sleep(warm_up)
        out.update(_measure(station, url, seconds, agents, hz))
        page = _page(url, 5.0 if quick else 10.0)
        page["page_seconds"] = page.pop("seconds", None)
        out.update(page)
        out["page_frame_target_ms"] = TARGET_FRAME_MS
        out["meets_targets"] = (
            out["server_cpu_percent"] < TARGET_CPU
            and out["ws_bytes_per_s"] <= TARGET_WS_BYTES
            and out.get("page_frame_ms_p95") is not None
            and out["page_frame_ms_p95"] <= TARGET_FRAME_MS
        )
    finally:
        if feeder is not None:
            feeder.terminate()
            try:
                feeder.wait(10)
            except subprocess.TimeoutExpired:
                feeder.kill()
                feeder.wait(5)
        station.stop()
    out.update(_click(5 if quick else 11))  # its own bench, once this one is stopped
    out.update(_alarms(quick))  # the alarms while links flap: its own station
    out.update(_flood(quick))  # and the connection flood's
    return out


def _wait_connected(station: Child, feeder: subprocess.Popen[bytes], url: str, agents: int) -> dict[str, Any]:
    """Wait (60 s at most) until the station has every fed agent connected.

    Raises:
        RuntimeError: the feeder or the station exited.
    """
    t0 = time.monotonic()
    connected = 0
    while time.monotonic() - t0 < 60:
        if feeder.poll() is not None or station.proc.poll() is not None:
            raise RuntimeError("the feeder or the station exited early: " + " | ".join(station.errors[-3:]))
        state = _get(url + "api/state")
        connected = sum(1 for a in state["agents"] if a["connected"])
        if connected == agents:
            break
        time.sleep(0.2)
    return {
        "connect_all_s": round(time.monotonic() - t0, 2) if connected == agents else None,
        "connected": connected,
    }


def _measure(station: Child, url: str, seconds: float, agents: int, hz: float) -> dict[str, Any]:
    """One WebSocket client's traffic and the station's CPU over ``seconds``, then the
    station's state."""
    out: dict[str, Any] = {}
    cpu0, w0 = cpu_seconds(station.pid), time.monotonic()
    counts = asyncio.run(_ws_count(url.replace("http://", "ws://") + "ws", seconds))
    cpu1, w1 = cpu_seconds(station.pid), time.monotonic()
    wall = w1 - w0
    out["ws_bytes_per_s"] = round(counts["bytes"] / counts["seconds"])
    out["ws_bytes_target"] = TARGET_WS_BYTES
    out["ws_wire_bytes_per_s"] = round(counts["wire_bytes"] / counts["seconds"])
    out["ws_messages_per_s"] = round(counts["messages"] / counts["seconds"], 2)
    out["ws_deltas_per_s"] = round(counts["deltas"] / counts["seconds"], 2)
    out["ws_states_per_s"] = round(counts["states"] / counts["seconds"], 2)  # whole states after the first
    out["ws_delta_bytes"] = round(counts["delta_bytes"] / max(1, counts["deltas"]))
    out["ws_state_kb"] = round(counts["state_bytes"] / 1024, 1)
    out["input_messages_per_s"] = round(agents * hz * 3, 1)  # telemetry + pose + state
    out["server_cpu_percent"] = round(100.0 * (cpu1 - cpu0) / wall, 1)
    out["server_cpu_target"] = TARGET_CPU
    state = _get(url + "api/state")
    out["connected_at_end"] = sum(1 for a in state["agents"] if a["connected"])
    out["leader"] = state["leader"]
    out["trail_points_per_agent"] = max(len(a["trail"]) for a in state["agents"])
    return out


def _page(url: str, seconds: float) -> dict[str, Any]:
    try:
        from swarm.cli.bench.gcs_page import measure_frames
    except ImportError as exc:
        return {"page_frame_ms_p95": None, "page_error": f"no page benchmark module: {exc}"}
    try:
        return dict(measure_frames(url, seconds))
    except Exception as exc:  # no browser, no Playwright: report, do not fail the other figures
        return {"page_frame_ms_p95": None, "page_error": f"{type(exc).__name__}: {exc}"}


def _click(trials: int) -> dict[str, Any]:
    try:
        from swarm.cli.bench.gcs_click import measure

        return measure(trials)
    except Exception as exc:  # no browser, a bench that did not come up: report, keep the other figures
        return {"click_to_setpoint_ms_p50": None, "click_to_setpoint_error": f"{type(exc).__name__}: {exc}"}


def _alarms(quick: bool) -> dict[str, Any]:
    try:
        from swarm.cli.bench.gcs_alarms import measure

        return measure(quick)
    except Exception as exc:  # a bench that did not come up: report, keep the other figures
        return {"alarms_announced": None, "alarms_error": f"{type(exc).__name__}: {exc}"}


def _flood(quick: bool) -> dict[str, Any]:
    try:
        from swarm.cli.bench.gcs_flood import measure

        return measure(quick)
    except Exception as exc:  # a bench that did not come up: report, keep the other figures
        return {"flood_operator_answered": None, "flood_error": f"{type(exc).__name__}: {exc}"}


# -- the feeder process ------------------------------------------------------------


class _Feeder:
    """``agents`` agents at ``hz`` over one Zenoh session (see the module docstring)."""

    def __init__(
        self, ep: str, agents: int, hz: float, flap: int = 0, wobble: int = 0, flap_after: float = 0.0
    ) -> None:
        from swarm.runtime.keyspace import transport  # Zenoh: in the feeder process only

        self.keys = transport
        self.session = transport.open_session(connect=[ep])
        self.agents = agents
        self.period = 1.0 / hz
        self.ids = list(range(1, agents + 1))
        self.names = {i: f"sim{i}" for i in self.ids}
        self.by_name = {n: i for i, n in self.names.items()}
        self.links = {i: GsLink(i, self.names[i], GsConfig(hb_interval=self.period)) for i in self.ids}
        self.inbox: queue.Queue[tuple[int, Any]] = queue.Queue()
        self.members = frozenset(self.ids[1:])
        self.pool = frozenset(self.ids)
        # the alarm bench's troubles: links that flap (the last ``flap`` agents: silent
        # FLAP_OFF_S of every FLAP_PERIOD_S, each at its own phase, from ``flap_after``
        # s on) and batteries on the warning threshold (the ``wobble`` before them)
        self.flap = frozenset(self.ids[agents - flap :]) if flap else frozenset()
        self.wobble = frozenset(self.ids[agents - flap - wobble : agents - flap]) if wobble else frozenset()
        self.start = time.monotonic()
        self.flap_after = flap_after
        self.subs = [self.session.declare_subscriber("swarm/*", self._on_sample)]

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        try:
            msg = decode(sample.payload.to_bytes())
        except ValueError:
            return
        if key == self.keys.KEY_GS_ADVERTIZE:
            for k in self.ids:
                self.inbox.put((k, msg))
        else:
            to = self.by_name.get(key.split("/", 1)[1])
            if to is not None:
                self.inbox.put((to, msg))

    def pose(self, i: int, now: float) -> Pose:
        ang = now * 0.05 + i * 2 * math.pi / self.agents
        r = 0.002
        return Pose(
            CENTER[0] + r * math.cos(ang),
            CENTER[1] + r * 1.5 * math.sin(ang),
            520.0,
            math.degrees(ang + math.pi / 2) % 360.0,
            -5.0 * math.sin(ang),
            5.0 * math.cos(ang),
            now,
        )

    def telemetry(self, i: int, now: float) -> Telemetry:
        battery = 90 - i % 30
        if i in self.wobble:  # 29, 30 or 31 %: on the warning threshold (30 %)
            battery = 30 + round(math.sin(now * 0.7 + i))
        return Telemetry(
            i,
            self.pose(i, now),
            mode_code("OFFBOARD"),
            FLAG_ARMED | FLAG_AIRBORNE | FLAG_FC_OK,
            Phase.LEADER if i == 1 else Phase.MEMBER,
            1,
            battery,
            200,
            190,
            5.0,
            rel_alt=20.0,
            climb=0.0,
            gps_fix=3,
            satellites=14,
            home_dist=float(i),
        )

    def silent(self, i: int, now: float) -> bool:
        """A flapping agent in its silence (its radio out of reach: it sends nothing)."""
        t = now - self.start - self.flap_after
        if i not in self.flap or t < 0:
            return False
        return (t + FLAP_PERIOD_S * (i % 7) / 7) % FLAP_PERIOD_S < FLAP_OFF_S

    def put(self, key: str, msg: Any) -> None:
        self.session.put(key, encode(msg))

    def answer(self, now: float) -> None:
        """Each agent's answers to what the station sent it."""
        while True:
            try:
                i, msg = self.inbox.get_nowait()
            except queue.Empty:
                return
            if self.silent(i, now):
                continue  # out of reach: it never heard it
            for o in self.links[i].handle(msg, now):
                st = self.links[i].station_name(o.to)
                if st:
                    self.put(self.keys.inbox_key(st), o.msg)

    def speak(self, i: int, now: float, due: dict[int, float]) -> None:
        """Agent ``i``'s link timers (Telemetry, GSAdvertize) and, when due, its pose and state."""
        keys = self.keys
        g = self.links[i]
        if self.silent(i, now):
            return
        for o in g.tick(now, lambda i=i: self.telemetry(i, time.monotonic())):  # type: ignore[misc]
            if o.to == 0:
                self.put(keys.KEY_GS_ADVERTIZE, o.msg)
            else:
                st = g.station_name(o.to)
                if st:
                    self.put(self.keys.inbox_key(st), o.msg)
        if now >= due[i]:
            due[i] += self.period
            if due[i] < now:
                due[i] = now + self.period
            self.put(keys.pose_key(self.names[i]), PoseReport(self.pose(i, now)))
            self.put(
                keys.state_key(self.names[i]),
                AgentState(
                    i,
                    Phase.LEADER if i == 1 else Phase.MEMBER,
                    leader=1,
                    locked=True,
                    pool=self.pool,
                    members=self.members if i == 1 else frozenset(),
                ),
            )

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def feed(ep: str, agents: int, hz: float, flap: int = 0, wobble: int = 0, flap_after: float = 0.0) -> None:
    """Play ``agents`` agents at ``hz`` over one Zenoh session until SIGTERM (``flap``,
    ``wobble``, ``flap_after``: the alarm bench's troubles, :class:`_Feeder`)."""
    import signal

    stop = [False]
    signal.signal(signal.SIGTERM, lambda *_: stop.__setitem__(0, True))
    f = _Feeder(ep, agents, hz, flap, wobble, flap_after)
    start = time.monotonic()
    due = {i: start + f.period * k / agents for k, i in enumerate(f.ids)}
    while not stop[0]:
        now = time.monotonic()
        f.answer(now)
        for i in f.ids:
            f.speak(i, now, due)
        time.sleep(0.01)
    f.close()


def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m swarm.cli.bench.gcs")
    p.add_argument("--feed", metavar="EP", required=True, help="Zenoh endpoint of the station")
    p.add_argument("--agents", type=int, default=AGENTS)
    p.add_argument("--hz", type=float, default=HZ)
    p.add_argument("--flap", type=int, default=0, help="agents whose links flap")
    p.add_argument("--wobble", type=int, default=0, help="agents whose battery sits on the warning")
    p.add_argument("--flap-after", type=float, default=0.0, help="seconds before the links start to flap")
    a = p.parse_args(argv)
    feed(a.feed, a.agents, a.hz, a.flap, a.wobble, a.flap_after)
    return 0


if __name__ == "__main__":
    sys.exit(_main())
