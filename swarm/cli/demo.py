"""The one-command bench demo: emulated radios, simulated vehicles, agents, a ground
node, election, take-off, V formation along a route with a 90 degree turn.

Theory of operation
-------------------
:func:`run_demo` starts, each in its own process (``swarm.cli.procs.Child``): the
radio emulator with N + 1 radios (``--capture``: everything on air goes to a
``.tlog``), ``swarm sim`` with N PX4-like vehicles 8 m apart, N ``swarm agent``
processes (agent K: radio K-1, vehicle K) and, when the ground station is
installed and ``gcs`` is asked, ``swarm gcs`` on one more radio. The demo itself
drives a ground station on the last radio: the real one,
:class:`swarm.runtime.station.live.Station` (id 254, name ``demo``), which connects the
agents and sends Commands with acknowledgement and retry, exactly as an operator's
station does (a command counts once an agent accepted it or its Telemetry shows
it carried out). A command the station refuses for a moment (409: no leader, an
agent not connected: at 10-20 % loss its view drops an agent silent for 3 s) is
tried again for ``REFUSED_WAIT_S`` before the demo gives up with the station's
reason.

The flight: wait for one leader that every agent agrees on (from the agents'
``--json`` state lines) and for every agent to be connected to the demo's
station; TAKEOFF to the swarm (each agent); once all report ``took off``, FOLLOW
(heading north) through the leader; ``settle_s`` later the route: GOTO north
``leg_m`` then WAYPOINT east ``leg_m`` (a rounded 90 degree right turn); when
the leader reports ``arrived``, ``tail_s`` more, then the swarm STOP (the
FOLLOW task ends, on the air too) and LAND to the swarm. Step lines go to
``out``; a progress line every second to ``progress`` (phase, seconds into the
route of the expected, leader, members following, the slot error over the last 5 s
read from the capture as it grows).

The summary (leader, election time, formation figures, air utilisation, capture,
plot) comes from :func:`swarm.sim.tracks.analyse` on the capture, exactly as
``swarm replay --plot`` computes it (the same interval and legs:
:data:`swarm.sim.tracks.FIGURES`, whose definitions the summary carries), and the
emulator's channel counters. Each target the run is judged on is checked in
:func:`targets`: the formation RMS on the straight legs within ``max_rms_m`` (on
the whole route, ``route_rms_m``, when it is too short to have straight legs) and
the largest error in the turns within ``max_turn_m``; a step that did not happen
(no agreed leader, a take-off refused...) is a missed target too. ``missed`` lists
each with what was measured and the limit; ``ok`` is true when it is empty.

Everything started is stopped on the way out (SIGTERM, then SIGKILL), also on
Ctrl-C/SIGTERM of the demo, which then exits 130. The working folder the demo made
itself (no ``workdir``) is removed then unless ``keep``; a capture or plot the user
asked for (``capture``, ``plot``) is written where asked and stays.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from radios.ports import free_port_range
from swarm.cli.procs import Child, ChildError, start_emulator
from swarm.cli.sitl_fleet import SitlFleet
from swarm.core.election.profiles import PROFILE_NAMES
from swarm.core.wire.message_types import AckResult, CommandKind
from swarm.errors import SwarmError

if TYPE_CHECKING:
    from swarm.runtime.station.live import Station

DEMO_ID = 254
DEMO_NAME = "demo"
#: ``--autopilot``: the simulator, or real SITL autopilots (``mix``: ArduCopter for odd
#: agents, PX4 for even ones: 3 + 2 of 5)
AUTOPILOTS = ("sim", "sitl:ardupilot", "sitl:px4", "sitl:mix")
#: where real autopilots start: the PX4 SITL's default home; agent K 8 m east of agent K-1
SITL_HOME = (47.397742, 8.545594, 488.0)
#: how long real autopilots may take to become armable (measured: PX4 about 34 s,
#: ArduCopter about 42 s after its client connects) before a refused take-off is final
BOOT_WAIT_S = 150.0
#: the take-off is tried again this often while an autopilot is still booting
BOOT_RETRY_S = 5.0
#: the whole run's default limit with real autopilots (their boot and their pace)
SITL_DURATION_S = 360.0
#: how long the demo's station tries a command before it gives up on an agent
COMMAND_GIVE_UP_S = 20.0
#: how long a 409 from the demo's station (no leader, agent not connected) may last
REFUSED_WAIT_S = 30.0


def _write_logs(children: list[Child], folder: str) -> str | None:
    """Each process's output (stdout, then stderr) to ``folder/<name>.log``, so that a
    kept working folder tells what every agent said; the folder (None: not writable)."""
    try:
        os.makedirs(folder, exist_ok=True)
        for ch in children:
            name = ch.name.replace(" ", "-")
            with open(os.path.join(folder, f"{name}.log"), "w", encoding="utf-8") as f:
                f.writelines(line + "\n" for line in [*ch.lines, *ch.errors])
    except OSError:
        return None
    return folder


class DemoError(SwarmError):
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
    max_turn_m: float = 10.0
    keep: bool = False
    gcs: bool = True
    http: str = "127.0.0.1:8080"
    seed: int = 0
    autopilot: str = "sim"

    def kinds(self) -> list[str]:
        """Each agent's autopilot: ``sim``, ``ardupilot`` or ``px4``."""
        kind = self.autopilot.removeprefix("sitl:")
        if kind == "mix":
            return ["ardupilot" if k % 2 else "px4" for k in range(1, self.agents + 1)]
        return [kind] * self.agents

    def check(self) -> None:
        if not 2 <= self.agents <= 20:
            raise ValueError("--agents: 2..20")
        if not 0.0 <= self.loss < 0.9:
            raise ValueError("--loss: a probability in 0..0.9")
        if self.profile not in PROFILE_NAMES:
            raise ValueError(f"--profile: {', '.join(PROFILE_NAMES)}")
        if not 20.0 <= self.duration <= 3600.0:
            raise ValueError("--duration: 20..3600 s")
        if not 10.0 <= self.leg_m <= 2000.0:
            raise ValueError("--leg: 10..2000 m")
        if self.autopilot not in AUTOPILOTS:
            raise ValueError(f"--autopilot: {', '.join(AUTOPILOTS)}")
        if self.autopilot != "sim":
            from firmware_bridge import sitl

            if sitl.find_sitl() is None:
                raise ValueError(
                    f"--autopilot {self.autopilot}: no SITL folder found: build ArduCopter and PX4 SITL "
                    "and set SITL_DIR to their folder (docs/autopilots.md, 'Real autopilots')"
                )
            for kind in sorted(set(self.kinds())):
                try:
                    sitl.script(kind)  # type: ignore[arg-type]
                except sitl.SitlError as exc:
                    raise ValueError(f"--autopilot {self.autopilot}: {exc}") from None


@dataclass
class DemoResult:
    summary: dict[str, Any] = field(default_factory=dict)


def free_base_port(count: int) -> int:
    """A base port with ``count`` consecutive free UDP ports after it (outside the
    kernel's ephemeral range: :mod:`radios.ports`)."""
    try:
        return free_port_range(count, "udp")
    except RuntimeError:
        raise DemoError("no free UDP ports for the simulated vehicles") from None


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


class _Demo:
    """One run of the demo: its files, processes, station, clock and summary."""

    def __init__(self, cfg: DemoConfig, stop: threading.Event, out: Callable[[str], None]) -> None:
        self.cfg, self.stop, self.out = cfg, stop, out
        self.made_workdir = cfg.workdir is None  # ours to remove at the end (unless keep)
        self.workdir = cfg.workdir or tempfile.mkdtemp(prefix="swarm-demo-")
        self.progress = out
        self.phase = "start"
        os.makedirs(self.workdir, exist_ok=True)
        self.capture = cfg.capture or os.path.join(self.workdir, "air.tlog")
        self.plot_path = cfg.plot or os.path.join(self.workdir, "formation.png")
        self.stats = os.path.join(self.workdir, "emulator.json")
        self.children: list[Child] = []
        self.fleet: SitlFleet | None = None  # real autopilots (--autopilot sitl:...)
        self.accepted: list[tuple[int, str]] = []  # (agent, outcome awaited) per accepted command
        self.station: Station | None = None
        self.watch = _Watch([])
        self.t0 = time.monotonic()
        self.summary: dict[str, Any] = {
            "agents": cfg.agents,
            "loss": cfg.loss,
            "profile": cfg.profile,
            "autopilot": cfg.autopilot,
            "autopilots": cfg.kinds(),
            "leader": 0,
            "elect_s": None,
            "formation_rms_m": None,
            "formation_max_m": None,
            "turn_max_m": None,
            "heading_error_after_turn_deg": None,
            "air_utilisation": None,
            "capture": self.capture,
            "plot": None,
            "gcs": None,
            "gcs_running": False,
            "workdir": self.workdir,
            "workdir_kept": True,
            "missed": [],
            "ok": False,
        }

    # -- time, stop and waiting ------------------------------------------------------
    def elapsed(self) -> float:
        return time.monotonic() - self.t0

    def check_stop(self) -> None:
        if self.stop.is_set():
            raise KeyboardInterrupt
        if self.elapsed() > self.cfg.duration:
            raise DemoError(f"the demo did not finish within --duration {self.cfg.duration:.0f} s")

    def wait_for(self, pred: Callable[[], Any], what: str, timeout: float, every: float = 0.2) -> Any:
        end = time.monotonic() + timeout
        while True:
            self.watch.poll()
            v = pred()
            if v:
                return v
            self.check_stop()
            if time.monotonic() > end:
                raise DemoError(f"timed out after {timeout:.0f} s waiting for {what}")
            self.stop.wait(every)

    def progress_until(
        self, done: Callable[[], bool], every: float = 5.0, expect: tuple[float, float] | None = None
    ) -> None:
        """Wait for ``done``, with a progress line every second (the slot error over the last
        ``every`` s, read from the capture as it grows, refreshed that often). ``expect``:
        (when the stretch started, how long it should take), shown as a count."""
        from swarm.sim.tracks import analyse

        watch = self.watch
        last = shown = 0.0
        err = "no slot samples yet"
        while True:
            watch.poll()
            if done():
                return
            self.check_stop()
            now = time.monotonic()
            if now - last >= every:
                last = now
                errs = [e for _t, _m, e, _turn in analyse(self.capture, start=time.time() - every).errors]
                err = f"slot error last {every:g} s: max {max(errs):.1f} m" if errs else "no slot samples yet"
            if now - shown >= 1.0:
                shown = now
                n, lead = len(watch.agents), watch.leader()
                modes = sum(1 for k in watch.events if watch.has_event(k, "following"))
                count = f" {self.elapsed() - expect[0]:.0f}/{expect[1]:.0f} s" if expect else ""
                self.progress(
                    f"   t={self.elapsed():5.1f} s {self.phase}{count}: leader agent{lead}, "
                    f"following {modes}/{n - 1}, {err}"
                )
            self.stop.wait(0.2)

    # -- the station's commands ----------------------------------------------------------
    def command(
        self,
        target: int | None,
        kind: CommandKind,
        what: str,
        *,
        slow: bool = False,
        outcome: str = "",
        tolerate: bool = False,
        **args: float,
    ) -> list[dict[str, Any]]:
        """Send through the demo's station (``target`` None: the swarm) and wait until
        every addressee accepted it or shows it carried out; with ``slow`` (a take-off
        climbs for longer than the station's retry window) an agent still at it
        (IN_PROGRESS) is fine too: the caller then waits for the outcome itself.
        ``outcome``: the pilot event each agent that accepted it must show later (counted
        by :meth:`false_accepted`). Returns the results that were not accepted (only
        with ``tolerate``: else they raise).

        Raises:
            DemoError: the station refused it, or an agent refused or did not answer.
        """
        from swarm.core.station.commands import DONE_RESULTS, CommandRefused, CommandSpec

        assert self.station is not None
        # A 409 (agent not connected, no leader) can be a moment's view at 10-20 % loss:
        # the station drops an agent silent for 3 s and the leader with it. Wait for the
        # view to come back, as an operator would, then give up with the station's reason.
        end = time.monotonic() + REFUSED_WAIT_S
        said = False
        while True:
            try:
                spec = CommandSpec(
                    target,
                    kind,
                    lat=args.get("lat", 0.0),
                    lon=args.get("lon", 0.0),
                    alt=args.get("alt", 0.0),
                    heading=args.get("heading", 0.0),
                )
                fut = self.station.submit(spec)
                break
            except CommandRefused as exc:
                if exc.status != 409 or time.monotonic() > end:
                    raise DemoError(f"{what}: the station refused it: {exc.reason}") from None
                if not said:
                    self.out(f"   {what}: waiting, the station says: {exc.reason}")
                    said = True
            self.check_stop()
            self.stop.wait(0.25)
        while not fut.done():
            self.check_stop()
            self.stop.wait(0.1)
        _status, body = fut.result()
        done = (*DONE_RESULTS, AckResult.IN_PROGRESS.name) if slow else DONE_RESULTS
        bad = [r for r in body["results"] if r["result"] not in done]
        if outcome:
            self.accepted += [(int(r["agent"]), outcome) for r in body["results"] if r["result"] in done]
        if bad and not tolerate:
            raise DemoError(f"{what}: {_why(bad)}")
        return bad

    # -- the processes -------------------------------------------------------------------
    def start(self) -> None:
        """Emulator, vehicles, agents (ready), the demo's station, the ground station."""
        cfg, n = self.cfg, self.cfg.agents
        radios = n + 1 + (1 if cfg.gcs else 0)
        gone = " (removed at the end; --keep keeps it)" if self.made_workdir and not cfg.keep else ""
        self.out(f"== {n} agents, {cfg.loss:.0%} loss, {cfg.profile} profile; files in {self.workdir}{gone}")
        os.makedirs(os.path.join(self.workdir, "radios"), exist_ok=True)
        emu, links = start_emulator(
            radios,
            os.path.join(self.workdir, "radios"),
            *("--capture", self.capture, "--loss", str(cfg.loss)),
            *(("--capture-status", str(n + 1)) if cfg.gcs else ()),  # the station's radio: link quality
            *("--stats-json", self.stats, "--seed", str(cfg.seed)),
        )
        self.children.append(emu)
        fcs = self.start_vehicles()
        if self.fleet is not None:
            self.out(f"   radio emulator: {radios} radios; real autopilots: {self.fleet.describe()}")
        else:
            self.out(f"   radio emulator: {radios} radios; vehicle simulator: {n} PX4 vehicles")
        slots = ["--slots", str(radios)] if cfg.profile != "paper" else []
        flight = ["--profile", cfg.profile, *slots, "--json", "--pose-hz", str(cfg.pose_hz)]
        flight += ["--speed", str(cfg.speed_mps)]
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
                    *flight,
                ],
                name=f"agent{k}",
            )
            for k in range(1, n + 1)
        ]
        self.children += agents
        for a in agents:
            a.wait_lines(1, 60)
        self.started = self.elapsed()
        self.watch = _Watch(agents)
        self.station = _station(links[n])
        if cfg.gcs:
            self.summary["gcs"] = _start_gcs(links[n + 1], cfg.http, self.children, self.out)

    def start_vehicles(self) -> list[str]:
        """``swarm sim`` with N vehicles 8 m apart (or N real autopilots, ``--autopilot
        sitl:...``); their flight-controller URLs."""
        n = self.cfg.agents
        if self.cfg.autopilot != "sim":
            self.fleet = SitlFleet(self.cfg.kinds(), os.path.join(self.workdir, "autopilots"), SITL_HOME, 8.0)
            try:
                return self.fleet.start()
            except SwarmError as exc:
                raise DemoError(str(exc)) from None
        base = free_base_port(n)
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
                str(self.cfg.seed),
            ],
            name="vehicle simulator",
        )
        self.children.append(sim)
        lines = sim.wait_lines(n + 1, 30)
        return [line.split("-> ", 1)[1].split()[0] for line in lines[:n]]

    def stop_all(self) -> None:
        """Stop everything started (safe twice): the capture is then whole and final."""
        if self.station is not None:
            self.station.stop()
        for ch in reversed(self.children):
            try:
                ch.stop()
            except Exception:
                pass
        if self.children and (self.cfg.keep or not self.made_workdir):
            self.summary["logs"] = _write_logs(self.children, os.path.join(self.workdir, "logs"))
        self.children = []
        if self.fleet is not None:
            self.summary["autopilot_cpu_pct"] = self.fleet.cpu()
            self.fleet.stop()
            self.fleet = None
        self.summary["gcs_running"] = False  # it stopped with the demo

    def close(self) -> None:
        """Stop everything started; remove the working folder the demo made (unless ``keep``)."""
        self.stop_all()
        if self.made_workdir and not self.cfg.keep:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.summary["workdir_kept"] = False
            for key in ("capture", "plot"):
                path = self.summary.get(key)
                if path and not os.path.exists(path):
                    self.summary[key] = None  # it was in the removed folder

    # -- the flight ------------------------------------------------------------------------
    def elect(self) -> int:
        n = self.cfg.agents
        self.out("== election")
        self.phase = "election"
        leader = int(self.wait_for(self.watch.leader, "one leader agreed by every agent", 120))
        self.summary["leader"] = leader
        self.summary["elect_s"] = round(self.elapsed() - self.started, 1)
        self.out(f"   leader agent{leader} after {self.summary['elect_s']} s")
        station = self.station
        assert station is not None
        self.wait_for(
            lambda: all((a := station.agent(k)) is not None and a["connected"] for k in range(1, n + 1)),
            "every agent to connect to the demo's station",
            60,
        )
        return leader

    def take_off_and_follow(self, leader: int) -> int:
        """Take-off, then the V behind the leader; the leader then (it may have changed)."""
        n = self.cfg.agents
        self.out(f"== take-off to {self.cfg.alt_m:g} m")
        self.phase = "take-off"
        if self.fleet is None:
            self.command(
                None, CommandKind.TAKEOFF, "take-off", slow=True, outcome="took off", alt=self.cfg.alt_m
            )
        else:
            self.take_off_when_booted()
        self.wait_for(
            lambda: all(self.watch.has_event(k, "took off") for k in range(1, n + 1)),
            "every agent to take off",
            90,
        )
        self.out("== follow in V (heading north)")
        leader = self.watch.leader() or leader
        self.phase = "forming the V"
        self.command(None, CommandKind.FOLLOW, "follow", heading=0.0)
        self.accepted += [(k, "following") for k in range(1, n + 1) if k != leader]
        follow_t = self.elapsed()
        self.progress_until(
            lambda: self.elapsed() - follow_t >= self.cfg.settle_s, expect=(follow_t, self.cfg.settle_s)
        )
        return leader

    def route(self, leader: int) -> None:
        """The route, ``leg_m`` north then east, then ``tail_s``."""
        import pymap3d

        cfg = self.cfg
        emu_before = _emu_stats(self.stats)
        self.out(f"== route: {cfg.leg_m:g} m north, then {cfg.leg_m:g} m east at {cfg.speed_mps:g} m/s")
        self.phase = "route"
        lat, lon, alt = _leader_position(self.capture, leader)
        a = pymap3d.ned2geodetic(cfg.leg_m, 0.0, 0.0, lat, lon, alt)
        b = pymap3d.ned2geodetic(cfg.leg_m, cfg.leg_m, 0.0, lat, lon, alt)
        for kind, p in ((CommandKind.GOTO, a), (CommandKind.WAYPOINT, b)):
            self.command(
                leader, kind, f"the leader's {kind.name}", lat=float(p[0]), lon=float(p[1]), alt=cfg.alt_m
            )
        self.accepted.append((leader, "arrived"))
        expect = (self.elapsed(), 2 * cfg.leg_m / cfg.speed_mps + cfg.tail_s)
        self.progress_until(lambda: self.watch.has_event(leader, "arrived"), expect=expect)
        end_wait = self.elapsed() + cfg.tail_s
        self.progress_until(lambda: self.elapsed() >= end_wait, expect=expect)
        self.summary["air_utilisation"] = _utilisation(emu_before, _emu_stats(self.stats))

    def take_off_when_booted(self) -> None:
        """The take-off to every agent, tried again (every ``BOOT_RETRY_S``) for an agent
        whose real autopilot refuses it while it boots, until ``BOOT_WAIT_S``."""
        alt = self.cfg.alt_m
        end = time.monotonic() + BOOT_WAIT_S
        bad = self.command(
            None, CommandKind.TAKEOFF, "take-off", slow=True, outcome="took off", tolerate=True, alt=alt
        )
        told: set[int] = set()
        while bad:
            for r in bad:
                if int(r["agent"]) not in told:
                    told.add(int(r["agent"]))
                    why = r["reason"] or r["result"]
                    self.out(f"   agent{r['agent']}: waiting for its autopilot to boot ({why})")
            if time.monotonic() > end:
                raise DemoError(f"take-off after {BOOT_WAIT_S:.0f} s of boot: {_why(bad)}")
            self.progress_until(_after(BOOT_RETRY_S))
            bad = self.take_off_each([int(r["agent"]) for r in bad], alt)
        self.summary["boot_s"] = round(self.elapsed() - self.started, 1)

    def take_off_each(self, agents: list[int], alt: float) -> list[dict[str, Any]]:
        """The take-off to each of ``agents`` at once (an autopilot still booting takes its
        ``ready`` wait: one after the other they would add up); the results not accepted."""
        from swarm.core.station.commands import DONE_RESULTS, CommandRefused, CommandSpec

        assert self.station is not None
        futs, bad = [], []
        for k in agents:
            try:
                futs.append(self.station.submit(CommandSpec(k, CommandKind.TAKEOFF, alt=alt)))
            except CommandRefused as exc:  # a moment's view (not connected): tried again next round
                bad.append({"agent": k, "result": "REFUSED", "reason": exc.reason})
        while not all(f.done() for f in futs):
            self.check_stop()
            self.stop.wait(0.1)
        done = (*DONE_RESULTS, AckResult.IN_PROGRESS.name)
        for f in futs:
            for r in f.result()[1]["results"]:
                if r["result"] in done:
                    self.accepted.append((int(r["agent"]), "took off"))
                else:
                    bad.append(r)
        return bad

    def false_accepted(self) -> list[str]:
        """Commands an agent accepted whose outcome never showed (each: agent and outcome)."""
        return [f"agent{k}: {what}" for k, what in self.accepted if not self.watch.has_event(k, what)]

    def land(self) -> None:
        self.out("== landing")
        self.phase = "landing"
        # the swarm stop ends the FOLLOW task on the air: the capture's analysis stops there
        for kind, what in ((CommandKind.STOP, "stop"), (CommandKind.LAND, "landing")):
            try:
                self.command(None, kind, what)
            except DemoError as exc:
                self.out(f"   {exc}")

    def analyse(self) -> None:
        """The formation's figures from the capture (as ``swarm replay --plot`` computes
        them), the plot, the targets missed and ``ok``."""
        from swarm.cli.demo_report import targets
        from swarm.sim.trackplot import plot
        from swarm.sim.tracks import FIGURES, analyse

        summary = self.summary
        an = analyse(self.capture)
        s = an.summary()
        for key in (*FIGURES, "per_member", "interval"):
            summary[key] = s[key]
        summary["figures"] = FIGURES
        try:
            summary["plot"] = plot(an, self.plot_path, target_m=self.cfg.max_rms_m)
        except (OSError, ValueError) as exc:
            self.out(f"   no plot: {exc}")
        summary["false_accepted"] = self.false_accepted()
        summary["missed"] = targets(summary, self.cfg.max_rms_m, self.cfg.max_turn_m)
        if summary["false_accepted"]:
            summary["missed"].append(
                {
                    "target": "false_accepted",
                    "measured": len(summary["false_accepted"]),
                    "limit": 0,
                    "text": "accepted but never carried out: " + ", ".join(summary["false_accepted"]),
                }
            )
        summary["ok"] = not summary["missed"]
        summary["wall_s"] = round(self.elapsed(), 1)


def run_demo(
    cfg: DemoConfig,
    stop: threading.Event,
    out: Callable[[str], None],
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the demo; returns the summary. ``out`` gets step lines, ``progress`` (default
    ``out``) a progress line every second. A step that failed (a process exited, no
    leader agreed, a command refused) is a missed target in the summary, not an error.

    Raises:
        KeyboardInterrupt: ``stop`` was set (everything started is stopped).
    """
    cfg.check()
    demo = _Demo(cfg, stop, out)
    demo.progress = progress or out
    try:
        demo.start()
        leader = demo.elect()
        leader = demo.take_off_and_follow(leader)
        demo.route(leader)
        demo.land()
        demo.stop_all()  # the capture final: the figures are those a replay of it computes
        demo.analyse()
    except (DemoError, ChildError) as exc:
        demo.summary["missed"] = [{"target": demo.phase, "text": f"{demo.phase}: {exc}"}]
        demo.summary["ok"] = False
        demo.summary["wall_s"] = round(demo.elapsed(), 1)
    finally:
        demo.close()
    return demo.summary


def _after(seconds: float) -> Callable[[], bool]:
    """True from ``seconds`` from now on."""
    end = time.monotonic() + seconds
    return lambda: time.monotonic() >= end


def _why(bad: list[dict[str, Any]]) -> str:
    return "; ".join(f"agent{r['agent']} {r['result']} {r['reason']}".rstrip() for r in bad)


def _station(radio: str) -> Station:
    """The demo's ground station on ``radio`` (started)."""
    from swarm.core.station.model import StationConfig
    from swarm.runtime.station.live import Station

    return Station(
        DEMO_NAME, DEMO_ID, radio=radio, config=StationConfig(command_give_up=COMMAND_GIVE_UP_S)
    ).start()


def _utilisation(before: dict[str, Any] | None, after: dict[str, Any] | None) -> float | None:
    """The air's busy share between two emulator counter snapshots."""
    if not (before and after and after["elapsed_s"] > before["elapsed_s"]):
        return None
    busy = after["utilisation"] * after["elapsed_s"] - before["utilisation"] * before["elapsed_s"]
    return round(busy / (after["elapsed_s"] - before["elapsed_s"]), 3)


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
    except (ChildError, ValueError) as exc:  # asked for and not there: the demo stops
        raise DemoError(f"the ground station did not start: {exc}") from None
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


__all__ = ["DEMO_ID", "DEMO_NAME", "DemoConfig", "DemoError", "run_demo"]
