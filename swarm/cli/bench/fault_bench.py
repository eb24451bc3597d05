"""The fault bench's harness: a real signed swarm flying, watched for health.

Theory of operation
-------------------
:class:`FaultBench` starts, each in its own process: the radio emulator (one radio per
agent, one for the station, one for a rogue), one ``swarm sim`` per agent (so one
vehicle can fail alone), four ``swarm agent`` processes with flight controllers and the
swarm key, and ``swarm gcs`` with the same key. It waits for the election, takes off
and flies the V (FOLLOW) through the station's HTTP API, as an operator would.

A monitor thread samples the swarm every 0.2 s: each live agent's newest ``state``
line (``--json``), and the station's ``/api/state``. The swarm is *healthy*
(:meth:`Snapshot.healthy`) when every live agent is LEADER or MEMBER of one and the
same leader, the leader's member list is every other live agent, and the station is
connected to every live agent and names the same leader. After a fault,
:meth:`FaultBench.measure` waits for health again and fills a :class:`FaultResult`:

* ``recovery_s``: from the moment the fault ends (the kill, the SIGCONT, the restart,
  the replug, the last rogue frame) to health;
* ``dual_leader_s``: how long two or more live agents claimed to lead, from the fault's
  start to health (a SIGSTOPped agent is not live while stopped).

The faults themselves, and the other metrics, are :mod:`swarm.cli.bench.faults`'.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from swarm.cli.procs import Child, ChildError, json_events, start_emulator

AGENTS = 4
LOSS = 0.1
KEY_PASSPHRASE = "fault bench swarm key"
HOME = (47.397742, 8.545594, 488.0)
SPACING_M = 8.0
HEALTH_TIMEOUT_S = 120.0
ROGUE_ID = 77
RECHECK_S = 5.0
#: the agents' radio-check period (``--radio-check-period``): a change that does not cut
#: the radio off (TXPOWER, MAVLINK...) is found within one and undone within two
CHECK_PERIOD_S = 20.0


class BenchError(ChildError):
    """The bench could not be set up or a step did not happen in time."""


@dataclass
class FaultResult:
    fault: str
    survived: bool = False
    recovery_s: float | None = None
    dual_leader_s: float = 0.0
    commands_lost: int = 0
    frames_accepted_from_rogue: int = 0
    #: what the fault did, and what the bench saw that proves its verdict (one line each)
    injected: str = ""
    observed: str = ""
    detail: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "fault": self.fault,
            "injected": self.injected,
            "observed": self.observed,
            "survived": self.survived,
            "recovery_s": None if self.recovery_s is None else round(self.recovery_s, 2),
            "dual_leader_s": round(self.dual_leader_s, 2),
            "commands_lost": self.commands_lost,
            "frames_accepted_from_rogue": self.frames_accepted_from_rogue,
            **self.detail,
        }


@dataclass
class Snapshot:
    t: float
    states: dict[int, dict[str, Any]]  # live agents only
    station: dict[str, Any] | None

    def leaders(self) -> set[int]:
        return {k for k, s in self.states.items() if s.get("phase") == "LEADER"}

    def agreed(self) -> bool:
        """The agents' side of health: one leader, every live agent its member."""
        live = set(self.states)
        leaders = self.leaders()
        if not live or len(leaders) != 1:
            return False
        lead = next(iter(leaders))
        if any(
            s.get("phase") not in ("LEADER", "MEMBER") or s.get("leader") != lead
            for s in self.states.values()
        ):
            return False
        return set(self.states[lead].get("members", [])) == live - {lead}

    def healthy(self) -> bool:
        if self.station is None or not self.agreed():
            return False
        lead = next(iter(self.leaders()))
        live = set(self.states)
        connected = {a["id"] for a in self.station.get("agents", []) if a.get("connected")}
        return live <= connected and self.station.get("leader") == lead


def profile_election_s(agents: int, loss: float, profile: str, seeds: int = 20) -> float:
    """The profile's election time for the bench's swarm: the median, over ``seeds``
    seeds, of a fresh election of ``agents`` agents at ``loss`` in the simulator (the
    same cores over the same air model, in virtual time: a figure that does not depend
    on how busy the machine is, unlike the bench's own first election)."""
    import statistics

    from swarm.sim.scenario import Scenario
    from swarm.sim.simulate import Sim

    times = [
        r.elect_s
        for r in (Sim(Scenario(agents=agents, loss=loss, profile=profile), s).run() for s in range(seeds))
        if r.elect_s is not None
    ]
    if not times:
        raise BenchError(f"the simulator elected no leader for {agents} agents at {loss:.0%} loss")
    return float(statistics.median(times))


def _home(k: int) -> str:
    import pymap3d

    lat, lon, alt = pymap3d.enu2geodetic(k * SPACING_M, 0.0, 0.0, *HOME)
    return f"{float(lat):.7f},{float(lon):.7f},{float(alt):.1f}"


class AgentProc:
    """One agent's processes: its vehicle simulator and the agent itself."""

    def __init__(self, bench: FaultBench, k: int) -> None:
        self.bench, self.k = bench, k
        self.name = f"agent{k}"
        self.radio = bench.links[k - 1]
        self.port = bench.base_port + k
        self.sim: Child | None = None
        self.agent: Child | None = None
        self.stopped = False  # SIGSTOPped
        self.started_at = 0.0
        self.ready: dict[str, Any] = {}

    @property
    def fc(self) -> str:
        return f"udpin:127.0.0.1:{self.port}"

    def start_sim(self) -> None:
        self.sim = Child(
            [
                "sim",
                "--vehicles",
                "1",
                "--home",
                _home(self.k),
                "--base-port",
                str(self.port),
                "--seed",
                str(self.k),
            ],
            name=f"vehicle {self.k}",
        )
        self.sim.wait_lines(2, 30)

    def start_agent(self) -> None:
        b = self.bench
        self.agent = Child(
            [
                "agent",
                "--name",
                self.name,
                "--id",
                str(self.k),
                "--radio",
                self.radio,
                "--fc",
                self.fc,
                "--key",
                b.key_file,
                "--state-dir",
                b.state_dir,
                "--profile",
                b.profile,
                "--slots",
                str(b.radios),
                "--json",
                *b.agent_args,
            ],
            name=self.name,
        )
        self.ready = json.loads(self.agent.wait_lines(1, 60)[0])
        self.stopped = False
        self.started_at = time.monotonic()

    @property
    def live(self) -> bool:
        return self.agent is not None and self.agent.proc.poll() is None and not self.stopped

    def state(self) -> dict[str, Any] | None:
        """The newest ``state`` line (the agent prints one on every change)."""
        for line in reversed(self.agent.lines if self.agent else []):
            if '"event": "state"' in line:
                found = json_events([line], "state")
                if found:
                    return found[0]
        return None

    def events(self, kind: str = "pilot") -> list[dict[str, Any]]:
        return json_events(self.agent.lines if self.agent else [], kind)

    def all_events(self) -> list[dict[str, Any]]:
        return json_events(self.agent.lines if self.agent else [])

    def kill(self) -> None:
        if self.agent is not None and self.agent.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.agent.proc.pid, signal.SIGCONT)  # a stopped process dies only when run
                os.killpg(self.agent.proc.pid, signal.SIGKILL)
            self.agent.proc.wait(10)
            self.agent.stop()
        self.stopped = False

    def stop_all(self) -> None:
        with contextlib.suppress(Exception):
            self.kill()
        if self.sim is not None:
            with contextlib.suppress(Exception):
                self.sim.stop()


class FaultBench:
    """The bench (see the module docstring). Use as a context manager."""

    def __init__(
        self,
        *,
        agents: int = AGENTS,
        loss: float = LOSS,
        profile: str = "paper",
        seed: int = 0,
        workdir: str | None = None,
        log: Callable[[str], None] | None = None,
        check_period: float = 0.0,
    ) -> None:
        self.n = agents
        self.loss = loss
        self.profile = profile
        self.seed = seed
        self.radios = agents + 2  # the agents, the station, the rogue
        self._tmp = None if workdir else tempfile.TemporaryDirectory(prefix="swarm-faults-")
        self.workdir = workdir or self._tmp.name  # type: ignore[union-attr]
        self.key_file = os.path.join(self.workdir, "swarm.key")
        self.capture = os.path.join(self.workdir, "air.tlog")
        # what the nodes keep across their restarts (their signing clocks): this run's own
        self.state_dir = os.path.join(self.workdir, "state")
        # the radio guard: a radio moved off the swarm's network by a rogue's RT commands is
        # restored by its agent once it has heard no one for RECHECK_S; with ``check_period``
        # (the remote-AT faults: CHECK_PERIOD_S) it is also checked that often, which finds
        # what does not cut a radio off (TXPOWER...) but costs every agent 2.3 s of radio
        # each time: the other faults run as the agents run by default, without it
        self.check_period = check_period
        self.agent_args: list[str] = [
            "--radio-params",
            "NETID=25",
            "--restore-radio",
            "--radio-recheck",
            str(RECHECK_S),
        ]
        if check_period:
            self.agent_args += ["--radio-check-period", str(check_period)]
        #: the emulator's statistics (every radio's registers: RAM, flash, running)
        self.stats_json = os.path.join(self.workdir, "emulator-stats.json")
        self.log = log or (lambda _s: None)
        self.emu: Child | None = None
        self.links: list[str] = []
        self.base_port = 0
        self.agents: dict[int, AgentProc] = {}
        self.station: Child | None = None
        self.station_url = ""
        self.elect_s: float | None = None
        #: the profile's election time for this swarm (simulated: profile_election_s)
        self.profile_elect_s = 0.0
        self.leader_timeout_s = 0.0
        self.history: list[Snapshot] = []
        self._hist_lock = threading.Lock()
        self._stop = threading.Event()
        self._monitor: threading.Thread | None = None

    # -- set-up ---------------------------------------------------------------------
    def __enter__(self) -> FaultBench:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        from swarm.cli.demo import free_base_port
        from swarm.core.election.profiles import profile_by_name

        with open(self.key_file, "w", encoding="utf-8") as fh:
            fh.write(KEY_PASSPHRASE + "\n")
        os.chmod(self.key_file, 0o600)
        radio_dir = os.path.join(self.workdir, "radios")
        os.makedirs(radio_dir, exist_ok=True)
        self.emu, self.links = start_emulator(
            self.radios,
            radio_dir,
            "--loss",
            str(self.loss),
            "--seed",
            str(self.seed),
            "--capture",
            self.capture,
            "--stats-json",
            self.stats_json,
        )
        self.base_port = free_base_port(self.n + 2)
        for k in range(1, self.n + 1):
            a = self.agents[k] = AgentProc(self, k)
            a.start_sim()
        for a in self.agents.values():
            a.start_agent()
        t0 = time.monotonic()
        self.start_station()
        round_s = float(self.agents[1].ready.get("round_s", 0.5))
        prof = profile_by_name(self.profile, round_s)
        self.leader_timeout_s = prof.leader_timeout
        self.profile_elect_s = profile_election_s(self.n, self.loss, self.profile)
        self._monitor = threading.Thread(target=self._watch, name="fault-bench-monitor", daemon=True)
        self._monitor.start()
        self.wait_healthy(HEALTH_TIMEOUT_S, "the first election")
        self.elect_s = time.monotonic() - t0
        self.log(f"elected in {self.elect_s:.1f} s: leader agent{self.leader()}")

    def start_station(self) -> None:
        self.station = Child(
            [
                "gcs",
                "--radio",
                self.links[self.n],
                "--key",
                self.key_file,
                "--state-dir",
                self.state_dir,
                "--http",
                "127.0.0.1:0",
                "--json",
                "--tiles",
                "none",
            ],
            name="station",
        )
        ready = json.loads(self.station.wait_lines(1, 60)[0])
        self.station_url = str(ready["url"]).rstrip("/")

    def close(self) -> None:
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join(5)
        for a in self.agents.values():
            a.stop_all()
        for ch in (self.station, self.emu):
            if ch is not None:
                with contextlib.suppress(Exception):
                    ch.stop()
        if self._tmp is not None:
            self._tmp.cleanup()

    # -- observation ------------------------------------------------------------------
    def station_state(self, timeout: float = 3.0) -> dict[str, Any] | None:
        if self.station is None or self.station.proc.poll() is not None:
            return None
        try:
            with urllib.request.urlopen(self.station_url + "/api/state", timeout=timeout) as r:
                d: dict[str, Any] = json.loads(r.read())
                return d
        except (OSError, ValueError, urllib.error.URLError):
            return None

    def snapshot(self) -> Snapshot:
        states = {}
        for k, a in self.agents.items():
            if a.live:
                st = a.state()
                states[k] = st or {}
        return Snapshot(time.monotonic(), states, self.station_state())

    def _watch(self) -> None:
        while not self._stop.wait(0.2):
            snap = self.snapshot()
            with self._hist_lock:
                self.history.append(snap)
                if len(self.history) > 20_000:
                    del self.history[:10_000]

    def latest(self) -> Snapshot | None:
        with self._hist_lock:
            return self.history[-1] if self.history else None

    def leader(self) -> int:
        snap = self.latest()
        if snap is None:
            return 0
        leaders = snap.leaders()
        return next(iter(leaders)) if len(leaders) == 1 else 0

    def wait_healthy(self, timeout: float, what: str, since: float | None = None) -> float:
        """Wait for health; seconds from ``since`` (default: now) to the first healthy sample.

        Raises:
            BenchError: not healthy within ``timeout``.
        """
        start = time.monotonic() if since is None else since
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._hist_lock:
                hit = next((s for s in self.history if s.t >= start and s.healthy()), None)
            if hit is not None:
                return hit.t - start
            self._check_children()
            time.sleep(0.2)
        snap = self.latest()
        raise BenchError(
            f"no healthy swarm {timeout:.0f} s after {what}: " + (describe(snap) if snap else "no sample")
        )

    def first_agreed(self, start: float) -> float | None:
        """Seconds from ``start`` to the first sample where the agents agree on one
        leader (:meth:`Snapshot.agreed`; the station not asked), None if none yet."""
        with self._hist_lock:
            hit = next((s for s in self.history if s.t >= start and s.agreed()), None)
        return None if hit is None else hit.t - start

    def dual_leader_s(self, start: float, end: float) -> float:
        with self._hist_lock:
            samples = [s for s in self.history if start <= s.t <= end]
        total = 0.0
        for a, b in itertools.pairwise(samples):
            if len(a.leaders()) > 1:
                total += b.t - a.t
        return total

    def _check_children(self) -> None:
        if self.emu is not None and self.emu.proc.poll() is not None:
            raise BenchError(f"the radio emulator exited: {' | '.join(self.emu.errors[-3:])}")

    # -- commands through the station's API ----------------------------------------------
    def command(self, body: dict[str, Any], timeout: float = 60.0) -> tuple[int, dict[str, Any]]:
        req = urllib.request.Request(
            self.station_url + "/api/command",
            data=json.dumps(body).encode(),
            headers={"Content-Type": "application/json"},
            method="POST",
        )
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as e:
            try:
                return e.code, json.loads(e.read())
            except ValueError:
                return e.code, {}

    def fly(self, alt: float = 10.0) -> None:
        """Take off (every agent) and fly the V (FOLLOW to the swarm)."""
        status, body = self.command({"target": "swarm", "kind": "takeoff", "alt": alt})
        if status != 200:
            raise BenchError(f"take-off: {status} {body}")
        deadline = time.monotonic() + 90
        while not all(any("took off" in e.get("text", "") for e in a.events()) for a in self.agents.values()):
            if time.monotonic() > deadline:
                raise BenchError("the agents did not all take off in 90 s")
            time.sleep(0.5)
        status, body = self.command({"target": "swarm", "kind": "follow", "heading": 0})
        if status != 200:
            raise BenchError(f"follow: {status} {body}")

    # -- for the faults (swarm.cli.bench.faults) ----------------------------------------
    def settled(self, what: str) -> None:
        self.wait_healthy(HEALTH_TIMEOUT_S, f"before {what}")

    def measure(
        self, name: str, fault_start: float, fault_end: float, *, injected: str = "", **detail: Any
    ) -> FaultResult:
        """Wait for health after a fault and say what was seen: ``observed`` starts as
        the recovery and the dual leadership; a fault adds what proves its own claim."""
        res = FaultResult(name, injected=injected, detail=dict(detail))
        try:
            res.recovery_s = self.wait_healthy(HEALTH_TIMEOUT_S, name, since=fault_end)
            res.survived = True
        except BenchError as exc:
            res.detail["error"] = str(exc)
        res.dual_leader_s = self.dual_leader_s(fault_start, time.monotonic())
        healthy = (
            f"healthy {res.recovery_s:.1f} s after the fault"
            if res.recovery_s is not None
            else f"NOT healthy within {HEALTH_TIMEOUT_S:.0f} s"
        )
        res.observed = f"{healthy}; two leaders for {res.dual_leader_s:.1f} s"
        return res

    def samples_since(self, start: float) -> list[Snapshot]:
        """The monitor's samples taken at ``start`` or later."""
        with self._hist_lock:
            return [s for s in self.history if s.t >= start]

    def control(self, line: str) -> None:
        """One line to the emulator's control FIFO (``unplug``, ``replug``, ``loss``)."""
        fd = os.open(os.path.join(self.workdir, "radios", "control"), os.O_WRONLY | os.O_NONBLOCK)
        try:
            os.write(fd, (line + "\n").encode())
        finally:
            os.close(fd)

    def rogue_send(self, frames: list[bytes], rate_bps: float = 3000.0) -> None:
        """Write frames into the rogue radio at about ``rate_bps`` (under its serial rate)."""
        from radios.link import open_link

        link = open_link(self.links[self.n + 1])
        try:
            for raw in frames:
                link.send(raw)
                time.sleep(len(raw) / rate_bps)
        finally:
            link.close()


def describe(s: Snapshot) -> str:
    parts = [
        f"agent{k} {st.get('phase', '?')} leader={st.get('leader')} members={st.get('members')}"
        for k, st in sorted(s.states.items())
    ]
    if s.station is None:
        parts.append("station: no answer")
    else:
        conn = sorted(a["id"] for a in s.station.get("agents", []) if a.get("connected"))
        parts.append(f"station connected={conn} leader={s.station.get('leader')}")
    return "; ".join(parts)
