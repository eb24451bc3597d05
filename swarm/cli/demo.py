"""The one-command bench demo: emulated radios, simulated vehicles, agents, a ground
node, election, take-off, V formation along a route with a 90 degree turn.

Theory of operation
-------------------
:func:`run_demo` starts, each in its own process (``swarm.cli.procs.Child``): the
radio emulator with N + 1 radios (``--capture``: everything on air goes to a
``.tlog``), ``swarm sim`` with N PX4-like vehicles 8 m apart, N ``swarm agent``
processes (agent K: radio K-1, vehicle K) and, when the ground station is
installed and ``gcs`` is asked, ``swarm gcs`` on one more radio. The demo itself is a
ground node on the last radio: a radio bridge and a Zenoh session as a station
(id 254, name ``demo``) that announces itself on ``swarm/GSAdvertize`` and sends
Commands with acknowledgement and retry, exactly as an operator's station does.

The flight: wait for one leader that every agent agrees on (from the agents'
``--json`` state lines); TAKEOFF to each agent; once all report ``took off``,
FOLLOW (heading north) to the leader; ``settle_s`` later the route: GOTO north
``leg_m`` then WAYPOINT east ``leg_m`` (a rounded 90 degree right turn); when
the leader reports ``arrived``, ``tail_s`` more, then the swarm STOP (the
FOLLOW task ends, on the air too) and LAND to each agent. Progress
lines every few seconds show phase, leader and the formation error so far (read
from the capture as it grows). The summary (leader, election time, formation RMS
and maximum, air utilisation, capture, plot) comes from
:func:`swarm.sim.tracks.analyse` on the capture and the emulator's channel counters;
``ok`` is true when the swarm flew the route in formation with an RMS slot error
within ``max_rms_m`` on the straight legs (on the whole route, reported as
``route_rms_m``, when it is too short to have straight legs).

Everything started is stopped on the way out (SIGTERM, then SIGKILL), also on
Ctrl-C/SIGTERM of the demo, which then exits 130.
"""

from __future__ import annotations

import json
import math
import os
import socket
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from radios.errors import RadioError
from swarm.cli.procs import Child, ChildError, start_emulator
from swarm.core.messages import AckResult, Command, CommandAck, CommandKind, GSAdvertize, Message

DEMO_ID = 254
DEMO_NAME = "demo"


class DemoError(RadioError):
    """The demo could not go on (a process failed, a step timed out)."""


@dataclass
class DemoConfig:
    agents: int = 5
    loss: float = 0.1
    profile: str = "paper"
    duration: float = 170.0  # the whole run's limit, s
    workdir: str | None = None
    capture: str | None = None
    plot: str | None = None
    alt_m: float = 10.0
    leg_m: float = 100.0
    speed_mps: float = 5.0
    settle_s: float = 15.0
    tail_s: float = 5.0
    pose_hz: float = 4.0
    max_rms_m: float = 1.5
    gcs: bool = True
    http: str = "127.0.0.1:8080"
    seed: int = 0

    def check(self) -> None:
        if not 2 <= self.agents <= 20:
            raise ValueError("--agents: 2..20")
        if not 0.0 <= self.loss < 0.9:
            raise ValueError("--loss: a probability in 0..0.9")
        if self.profile not in ("paper", "fast"):
            raise ValueError("--profile: paper or fast")
        if not 20.0 <= self.duration <= 3600.0:
            raise ValueError("--duration: 20..3600 s")
        if not 10.0 <= self.leg_m <= 2000.0:
            raise ValueError("--leg: 10..2000 m")


@dataclass
class DemoResult:
    summary: dict[str, Any] = field(default_factory=dict)


def _free_base_port(count: int) -> int:
    """A base port with ``count`` consecutive free UDP ports after it."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + count >= 65535:
            continue
        ok = True
        for p in range(base, base + count):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                try:
                    s.bind(("127.0.0.1", p))
                except OSError:
                    ok = False
                    break
        if ok:
            return base
    raise DemoError("no free UDP ports for the simulated vehicles")


class Ground:
    """The demo's station on a radio: announces itself, sends commands, collects acks."""

    def __init__(self, radio: str) -> None:
        from radios.link import open_link
        from swarm.runtime.bridge import RadioBridge
        from swarm.runtime.transport import Transport, open_session

        self.link = open_link(radio)
        self.session = open_session()
        self.bridge = RadioBridge(self.session, self.link, name=DEMO_NAME, agent_id=DEMO_ID).start()
        self.tr = Transport(DEMO_NAME, self.session)
        self._acks: dict[int, CommandAck] = {}
        self._cond = threading.Condition()
        self._seq = 0
        self._stop = threading.Event()
        self.tr.on_inbox(self._inbox)
        self._thread = threading.Thread(target=self._advertise, name="demo-ground", daemon=True)
        self._thread.start()

    def _inbox(self, msg: Message) -> None:
        if isinstance(msg, CommandAck):
            with self._cond:
                self._acks[msg.seq] = msg
                self._cond.notify_all()

    def _advertise(self) -> None:
        while not self._stop.wait(1.0):
            try:
                self.tr.gs_advertise(GSAdvertize(DEMO_ID, DEMO_NAME))
            except Exception:
                return

    def command(
        self, agent: int, target: int, kind: CommandKind, *, timeout: float = 20.0, **args: float
    ) -> CommandAck:
        """Send until acknowledged (same sequence number: the agent answers once)."""
        with self._cond:
            self._seq = (self._seq + 1) & 0xFFFF
            seq = self._seq
        cmd = Command(DEMO_ID, seq, target, kind, **args)
        deadline = time.monotonic() + timeout
        while True:
            try:
                self.tr.send(f"agent{agent}", cmd)
            except Exception as exc:
                raise DemoError(f"cannot send {kind.name} to agent{agent}: {exc}") from exc
            with self._cond:
                self._cond.wait_for(lambda: seq in self._acks, timeout=1.5)
                ack = self._acks.get(seq)
            if ack is not None:
                return ack
            if time.monotonic() > deadline:
                raise DemoError(f"agent{agent} did not answer {kind.name} in {timeout:.0f} s")

    def close(self) -> None:
        self._stop.set()
        for close in (self.tr.close, self.bridge.close, self.link.close, self.session.close):
            try:
                close()
            except Exception:
                pass


class _Watch:
    """The agents' JSON lines: states and pilot events."""

    def __init__(self, agents: list[Child]) -> None:
        self.agents = agents
        self.seen = [0] * len(agents)
        self.state: dict[int, dict[str, Any]] = {}
        self.events: dict[int, list[str]] = {i + 1: [] for i in range(len(agents))}

    def poll(self) -> None:
        for i, ch in enumerate(self.agents):
            lines = ch.lines[self.seen[i] :]
            self.seen[i] += len(lines)
            for line in lines:
                try:
                    d = json.loads(line)
                except ValueError:
                    continue
                if d.get("event") == "state":
                    self.state[i + 1] = d
                elif d.get("event") == "pilot":
                    self.events[i + 1].append(d.get("text", ""))
            if ch.proc.poll() is not None:
                raise DemoError(
                    f"agent{i + 1} exited with {ch.proc.returncode}: " + " | ".join(ch.errors[-3:])
                )

    def leader(self) -> int:
        n = len(self.agents)
        if len(self.state) < n:
            return 0
        leaders = {d["leader"] for d in self.state.values()}
        phases = {d["phase"] for d in self.state.values()}
        if len(leaders) != 1 or 0 in leaders or not phases <= {"LEADER", "MEMBER"}:
            return 0
        lead = leaders.pop()
        members = self.state.get(lead, {}).get("members", [])
        return lead if len(members) == n - 1 else 0

    def has_event(self, agent: int, text: str) -> bool:
        return any(text in e for e in self.events[agent])


def run_demo(cfg: DemoConfig, stop: threading.Event, out: Callable[[str], None]) -> dict[str, Any]:
    """Run the demo; returns the summary. ``out`` gets progress lines.

    Raises:
        DemoError, ChildError: a process failed or a step did not happen in time.
    """
    cfg.check()
    n = cfg.agents
    workdir = cfg.workdir or tempfile.mkdtemp(prefix="swarm-demo-")
    os.makedirs(workdir, exist_ok=True)
    capture = cfg.capture or os.path.join(workdir, "air.tlog")
    plot_path = cfg.plot or os.path.join(workdir, "formation.png")
    stats = os.path.join(workdir, "emulator.json")
    children: list[Child] = []
    ground: Ground | None = None
    t0 = time.monotonic()
    summary: dict[str, Any] = {
        "agents": n,
        "loss": cfg.loss,
        "profile": cfg.profile,
        "leader": 0,
        "elect_s": None,
        "formation_rms_m": None,
        "formation_max_m": None,
        "turn_max_m": None,
        "air_utilisation": None,
        "capture": capture,
        "plot": None,
        "gcs": None,
        "workdir": workdir,
        "ok": False,
    }

    def elapsed() -> float:
        return time.monotonic() - t0

    def check_stop() -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        if elapsed() > cfg.duration:
            raise DemoError(f"the demo did not finish within --duration {cfg.duration:.0f} s")

    def wait_for(pred: Callable[[], Any], what: str, timeout: float, every: float = 0.2) -> Any:
        end = time.monotonic() + timeout
        while True:
            watch.poll()
            v = pred()
            if v:
                return v
            check_stop()
            if time.monotonic() > end:
                raise DemoError(f"timed out after {timeout:.0f} s waiting for {what}")
            stop.wait(every)

    try:
        radios = n + 1 + (1 if cfg.gcs else 0)
        out(f"== {n} agents, {cfg.loss:.0%} loss, {cfg.profile} profile; files in {workdir}")
        os.makedirs(os.path.join(workdir, "radios"), exist_ok=True)
        emu, links = start_emulator(
            radios,
            os.path.join(workdir, "radios"),
            "--capture",
            capture,
            "--loss",
            str(cfg.loss),
            "--stats-json",
            stats,
            "--seed",
            str(cfg.seed),
        )
        children.append(emu)
        base = _free_base_port(n)
        sim = Child(
            [
                "sim",
                "--vehicles",
                str(n),
                "--spacing",
                "8",
                "--base-port",
                str(base),
                "--seed",
                str(cfg.seed),
            ],
            name="vehicle simulator",
        )
        children.append(sim)
        lines = sim.wait_lines(n + 1, 30)
        fcs = [line.split("-> ", 1)[1].split()[0] for line in lines[:n]]
        out(f"   radio emulator: {radios} radios; vehicle simulator: {n} PX4 vehicles")
        slots = ["--slots", str(radios)] if cfg.profile == "fast" else []
        agents = [
            Child(
                [
                    "agent",
                    "--name",
                    f"agent{k}",
                    "--id",
                    str(k),
                    "--radio",
                    links[k - 1],
                    "--fc",
                    fcs[k - 1],
                    "--profile",
                    cfg.profile,
                    *slots,
                    "--json",
                    "--pose-hz",
                    str(cfg.pose_hz),
                    "--speed",
                    str(cfg.speed_mps),
                ],
                name=f"agent{k}",
            )
            for k in range(1, n + 1)
        ]
        children += agents
        for a in agents:
            a.wait_lines(1, 60)
        started = elapsed()
        watch = _Watch(agents)
        ground = Ground(links[n])
        if cfg.gcs:
            summary["gcs"] = _start_gcs(links[n + 1], cfg.http, children, out)
        out("== election")
        leader = wait_for(watch.leader, "one leader agreed by every agent", 120)
        summary["leader"] = leader
        summary["elect_s"] = round(elapsed() - started, 1)
        out(f"   leader agent{leader} after {summary['elect_s']} s")
        out(f"== take-off to {cfg.alt_m:g} m")
        for k in range(1, n + 1):
            ack = ground.command(k, k, CommandKind.TAKEOFF, alt=cfg.alt_m)
            if ack.result != AckResult.ACCEPTED:
                raise DemoError(f"agent{k} refused take-off: {ack.result.name} {ack.reason}")
        wait_for(
            lambda: all(watch.has_event(k, "took off") for k in range(1, n + 1)),
            "every agent to take off",
            90,
        )
        out("== follow in V (heading north)")
        leader = watch.leader() or leader
        ack = ground.command(leader, 0, CommandKind.FOLLOW, heading=0.0)
        if ack.result != AckResult.ACCEPTED:
            raise DemoError(f"the leader refused follow: {ack.result.name} {ack.reason}")
        follow_t = elapsed()
        _progress_until(
            lambda: elapsed() - follow_t >= cfg.settle_s, watch, capture, out, elapsed, check_stop, stop
        )
        emu_before = _emu_stats(stats)
        out(f"== route: {cfg.leg_m:g} m north, then {cfg.leg_m:g} m east at {cfg.speed_mps:g} m/s")
        lat, lon, alt = _leader_position(capture, leader)
        import pymap3d

        a = pymap3d.ned2geodetic(cfg.leg_m, 0.0, 0.0, lat, lon, alt)
        b = pymap3d.ned2geodetic(cfg.leg_m, cfg.leg_m, 0.0, lat, lon, alt)
        for kind, p in ((CommandKind.GOTO, a), (CommandKind.WAYPOINT, b)):
            ack = ground.command(leader, leader, kind, lat=float(p[0]), lon=float(p[1]), alt=float(alt))
            if ack.result != AckResult.ACCEPTED:
                raise DemoError(f"the leader refused {kind.name}: {ack.result.name} {ack.reason}")
        route_wall = time.time()
        _progress_until(
            lambda: watch.has_event(leader, "arrived"), watch, capture, out, elapsed, check_stop, stop
        )
        end_wait = elapsed() + cfg.tail_s
        _progress_until(lambda: elapsed() >= end_wait, watch, capture, out, elapsed, check_stop, stop)
        emu_after = _emu_stats(stats)
        if emu_before and emu_after and emu_after["elapsed_s"] > emu_before["elapsed_s"]:
            busy = (
                emu_after["utilisation"] * emu_after["elapsed_s"]
                - emu_before["utilisation"] * emu_before["elapsed_s"]
            )
            summary["air_utilisation"] = round(busy / (emu_after["elapsed_s"] - emu_before["elapsed_s"]), 3)
        out("== landing")
        try:  # the swarm stop ends the FOLLOW task on the air: the capture's analysis stops there
            ground.command(leader, 0, CommandKind.STOP, timeout=8.0)
        except DemoError as exc:
            out(f"   {exc}")
        for k in range(1, n + 1):
            try:
                ground.command(k, k, CommandKind.LAND, timeout=8.0)
            except DemoError as exc:
                out(f"   {exc}")
        from swarm.sim.tracks import analyse, plot

        an = analyse(capture, start=route_wall)
        s = an.summary()
        summary["formation_rms_m"] = s["formation_rms_m"]
        summary["turn_max_m"] = s["turn_max_m"]
        all_err = [e for _t, _m, e, _turn in an.errors]
        summary["formation_max_m"] = round(max(all_err), 2) if all_err else None
        summary["per_member"] = s["per_member"]
        try:
            summary["plot"] = plot(an, plot_path)
        except (OSError, ValueError) as exc:
            out(f"   no plot: {exc}")
        rms = summary["formation_rms_m"]
        if rms is None and all_err:  # a route too short for straight legs: judge it whole
            rms = math.sqrt(sum(e * e for e in all_err) / len(all_err))
            summary["route_rms_m"] = round(rms, 3)
        summary["ok"] = rms is not None and rms <= cfg.max_rms_m
        summary["wall_s"] = round(elapsed(), 1)
        return summary
    finally:
        if ground is not None:
            ground.close()
        for ch in reversed(children):
            try:
                ch.stop()
            except Exception:
                pass


def _start_gcs(radio: str, http: str, children: list[Child], out: Callable[[str], None]) -> str | None:
    import importlib.util

    if importlib.util.find_spec("swarm.cli.commands.gcs") is None:
        return None
    gcs = Child(["gcs", "--radio", radio, "--http", http, "--json"], name="ground station")
    children.append(gcs)
    try:
        line = gcs.wait_lines(1, 30)[0]
        ready = json.loads(line)
        url = ready.get("open") or ready.get("url")  # with its token beyond loopback
    except (ChildError, ValueError) as exc:
        out(f"   ground station not started: {exc}")
        return None
    out(f"   ground station: {url}")
    return str(url) if url else None


def _emu_stats(path: str) -> dict[str, Any] | None:
    try:
        with open(path, encoding="utf-8") as fh:
            d: dict[str, Any] = json.load(fh)
            return d
    except (OSError, ValueError):
        return None


def _leader_position(capture: str, leader: int) -> tuple[float, float, float]:
    from swarm.sim.tracks import read_capture

    an = read_capture(capture)
    track = an.tracks.get(leader)
    if not track:
        raise DemoError(f"no pose of the leader agent{leader} on the air")
    p = track[-1][1]
    return p.lat, p.lon, p.alt


def _progress_until(
    done: Callable[[], bool],
    watch: _Watch,
    capture: str,
    out: Callable[[str], None],
    elapsed: Callable[[], float],
    check_stop: Callable[[], None],
    stop: threading.Event,
    every: float = 5.0,
) -> None:
    from swarm.sim.tracks import analyse

    last = time.monotonic()
    while True:
        watch.poll()
        if done():
            return
        check_stop()
        if time.monotonic() - last >= every:
            last = time.monotonic()
            an = analyse(capture, start=time.time() - every)
            errs = [e for _t, _m, e, _turn in an.errors]
            lead = watch.leader()
            modes = sum(1 for k in watch.events if watch.has_event(k, "following"))
            err = f"slot error last {every:g} s: max {max(errs):.1f} m" if errs else "no slot samples yet"
            out(f"   t={elapsed():5.1f} s leader=agent{lead} following={modes}/{len(watch.agents) - 1} {err}")
        stop.wait(0.2)


__all__ = ["DemoConfig", "DemoError", "Ground", "run_demo"]
