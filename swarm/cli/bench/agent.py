"""``swarm bench agent``: one agent's start-up, imports, steady cost and flight-log loss.

Theory of operation
-------------------
Real processes on this machine, figures printed (never asserted: the Pi is several
times slower, and the targets say so):

* ``import_s``: a fresh interpreter importing the modules a running agent loads
  (the command, the runtime, the radio link and bridge, Zenoh, the flight-controller
  driver, the flight log), median of three; ``heavy_modules`` lists any of
  matplotlib, aiohttp or PIL among them (the agent needs none).
* ``startup_s``: a ``swarm radio-emu`` (two radios, ``--capture``) and ``swarm agent``
  on radio0, from the spawn of the agent's process to its first Advertize on the
  emulator's air (the emulator stamps each frame when it goes on air; this includes
  waiting for the radio's TDM window); median of several starts, each with a new id.
* ``cpu_percent``, ``rss_mb``: two agents, each with a ``swarm sim`` (PX4-like)
  vehicle, pose 4 Hz, on the emulated radios; the measured one keeps a flight log
  (``--capture``). Once they agree on a leader, its CPU over the window (30 s, 10 s
  with ``--quick``; 100 = one core) and its largest resident set, from /proc.
* ``capture_loss_s``: then the measured agent gets SIGKILL; the time from the last
  record on disk to the kill, and ``capture_missing_frames``: frames the emulator
  saw that agent put on the air that its flight log does not have.
* ``sync_ms_mean`` / ``sync_ms_max`` / ``put_us``: the flight log's fsync cost
  (writer thread) and the radio path's cost per queued frame, in this process.
"""

from __future__ import annotations

import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any

from radios.mavlink import MSG_TUNNEL, FrameBuilder, decode, frame_length
from radios.ports import free_port_range
from radios.rotating import FlightLog
from radios.tlog import TIMESTAMP
from radios.tlogset import read_flight_log
from swarm.cli.procs import Child, cpu_seconds, json_events, start_emulator
from swarm.core.wire.tunnel import PAYLOAD_TYPE_BASE, Kind

ADVERTIZE = PAYLOAD_TYPE_BASE + Kind.ADVERTIZE
AGENT_MODULES = (
    "swarm.cli.commands.agent",
    "swarm.runtime.agent.live",
    "swarm.runtime.bridge.radio_bridge",
    "swarm.runtime.keyspace.transport",
    "radios.link",
    "radios.seriallink",
    "radios.rotating",
    "radios.signing",
    "firmware_bridge.driver",
    "zenoh",
)
HEAVY = ("matplotlib", "aiohttp", "PIL")
IMPORT_SCRIPT = (
    "import sys, time\n"
    "t = time.perf_counter()\n"
    "for m in sys.argv[1].split(','): __import__(m)\n"
    "print(time.perf_counter() - t)\n"
    "print(','.join(sorted({m.split('.')[0] for m in sys.modules} & set(sys.argv[2].split(',')))))\n"
)


def _imports() -> dict[str, Any]:
    times, heavy = [], ""
    for _ in range(3):
        out = subprocess.run(
            [sys.executable, "-c", IMPORT_SCRIPT, ",".join(AGENT_MODULES), ",".join(HEAVY)],
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
        ).stdout.splitlines()
        times.append(float(out[0]))
        heavy = out[1] if len(out) > 1 else ""
    return {
        "import_s": round(statistics.median(times), 3),
        "heavy_modules": heavy.split(",") if heavy else [],
    }


class AirTail:
    """The records the emulator has put in its capture so far, read as it grows."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.offset = 0
        self.records: list[tuple[float, bytes]] = []

    def poll(self) -> list[tuple[float, bytes]]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                data = f.read()
        except FileNotFoundError:
            return []
        new, pos = [], 0
        while len(data) - pos >= 11:
            n = frame_length(data, pos + 8)
            if n is None or len(data) - pos < 8 + n:
                break
            (usec,) = TIMESTAMP.unpack_from(data, pos)
            new.append((usec / 1e6, bytes(data[pos + 8 : pos + 8 + n])))
            pos += 8 + n
        self.offset += pos
        self.records += new
        return new


def advertize_from(raw: bytes, sysid: int) -> bool:
    if raw[0] != 0xFD or raw[5] != sysid or int.from_bytes(raw[7:10], "little") != MSG_TUNNEL:
        return False
    try:
        return int(decode(raw).payload_type) == ADVERTIZE
    except Exception:
        return False


def _startups(d: str, starts: int) -> list[float]:
    air = os.path.join(d, "air.tlog")
    emu, links = start_emulator(2, d, "--capture", air)
    tail = AirTail(air)
    out: list[float] = []
    try:
        for k in range(starts):
            agent_id = 10 + k
            t0 = time.time()
            child = Child(
                ["agent", "--name", f"s{agent_id}", "--id", str(agent_id), "--radio", links[0]], name="agent"
            )
            try:
                deadline = time.monotonic() + 30.0
                seen = None
                while seen is None and time.monotonic() < deadline and child.proc.poll() is None:
                    seen = next((t for t, raw in tail.poll() if advertize_from(raw, agent_id)), None)
                    time.sleep(0.005)
                if seen is not None:
                    out.append(seen - t0)
            finally:
                child.stop()
    finally:
        emu.stop()
    return out


def start_agent(k: int, radio: str, port: int, extra: list[str]) -> tuple[Child, Child]:
    sim = Child(["sim", "--vehicles", "1", "--base-port", str(port), "--seed", str(k)], name=f"vehicle {k}")
    sim.wait_lines(2, 60)
    argv = [
        "agent",
        "--name",
        f"agent{k}",
        "--id",
        str(k),
        "--radio",
        radio,
        "--fc",
        f"udpin:127.0.0.1:{port}",
    ]
    agent = Child([*argv, "--pose-hz", "4", "--json", *extra], name=f"agent{k}")
    agent.wait_lines(1, 60)
    return sim, agent


def _settled(agent: Child) -> bool:
    states = json_events(agent.lines, "state")
    return bool(states) and states[-1].get("phase") in ("LEADER", "MEMBER") and len(states[-1]["pool"]) == 2


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _steady(d: str, window: float) -> dict[str, Any]:
    air, logs, radios = os.path.join(d, "air2.tlog"), os.path.join(d, "logs"), os.path.join(d, "steady")
    os.makedirs(radios)
    emu, links = start_emulator(2, radios, "--capture", air)
    base = free_port_range(2, "udp")
    children: list[Child] = [emu]
    try:
        sim1, measured = start_agent(1, links[0], base, ["--capture", logs])
        children += [sim1, measured]
        sim2, peer = start_agent(2, links[1], base + 1, [])
        children += [sim2, peer]
        deadline = time.monotonic() + 120
        while not (_settled(measured) and _settled(peer)) and time.monotonic() < deadline:
            time.sleep(0.2)
        settled = _settled(measured) and _settled(peer)
        w0, c0, rss = time.monotonic(), cpu_seconds(measured.pid), 0.0
        while time.monotonic() - w0 < window:
            time.sleep(1.0)
            rss = max(rss, _rss_mb(measured.pid))
        cpu = 100.0 * (cpu_seconds(measured.pid) - c0) / (time.monotonic() - w0)
        os.kill(measured.pid, signal.SIGKILL)
        t_kill = time.time()
        measured.proc.wait(10)
        time.sleep(1.0)  # what was on the air by the kill reaches the emulator's capture
        loss = loss_of(logs, air, t_kill)
    finally:
        for c in reversed(children):
            c.stop()
    return {"settled": settled, "cpu_percent": round(cpu, 2), "rss_mb": round(rss, 1), **loss}


def loss_of(logs: str, air: str, t_kill: float) -> dict[str, Any]:
    reader = read_flight_log(logs, prefix="agent1")
    logged = {rec.raw: rec.t for rec in reader}
    last = max(logged.values()) if logged else float("nan")
    tail = AirTail(air)
    tail.poll()
    on_air = [raw for t, raw in tail.records if raw[0] == 0xFD and raw[5] == 1 and t <= t_kill + 1.0]
    missing = [raw for raw in on_air if raw not in logged]
    return {
        "capture_loss_s": round(t_kill - last, 3),
        "capture_records": len(logged),
        "capture_frames_on_air": len(on_air),
        "capture_missing_frames": len(missing),
        "capture_torn_tails": len(reader.torn),
    }


def sync_cost(d: str, seconds: float) -> dict[str, Any]:
    b = FrameBuilder(1, 191)
    frames = [b.tunnel(bytes(40)) for _ in range(64)]
    with FlightLog(os.path.join(d, "cost"), "cost") as log:
        t0 = time.perf_counter()
        for i in range(20_000):
            log.put("radio", frames[i % 64])
        put_us = 1e6 * (time.perf_counter() - t0) / 20_000
        end = time.monotonic() + seconds
        while time.monotonic() < end:  # about 60 frames a second, as an agent in formation
            for raw in frames[:6]:
                log.put("radio", raw)
            time.sleep(0.1)
    s = log.stats
    return {
        "put_us": round(put_us, 2),
        "sync_ms_mean": round(1000 * s.sync_total_s / max(1, s.syncs), 2),
        "sync_ms_max": round(1000 * s.sync_max_s, 2),
        "syncs": s.syncs,
    }


def run(quick: bool = False) -> dict[str, Any]:
    window = 10.0 if quick else 30.0
    with tempfile.TemporaryDirectory() as d:
        result: dict[str, Any] = _imports()
        os.makedirs(os.path.join(d, "start"))
        starts = _startups(os.path.join(d, "start"), 3 if quick else 5)
        result["startup_s"] = round(statistics.median(starts), 3) if starts else None
        result["startup_s_all"] = [round(x, 3) for x in starts]
        result.update(_steady(d, window))
        result.update(sync_cost(d, 3.0 if quick else 10.0))
    result["window_s"] = window
    result["targets"] = {
        "startup_under_1s": result["startup_s"] is not None and result["startup_s"] <= 1.0,
        "cpu_under_5pct": result["cpu_percent"] <= 5.0,
        "rss_under_80mb": result["rss_mb"] <= 80.0,
        "capture_loss_under_1s": result["capture_loss_s"] <= 1.0,
        "no_heavy_imports": not result["heavy_modules"],
    }
    return result
