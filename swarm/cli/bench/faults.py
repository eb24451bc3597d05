"""``swarm bench faults``: a real signed swarm, flying, put through one fault after another.

Theory of operation
-------------------
:class:`FaultBench` starts, each in its own process: the radio emulator (one radio per
agent, one for the station, one for a rogue), one ``swarm sim`` per agent (so one
vehicle can fail alone), four ``swarm agent`` processes with flight controllers and the
swarm key, and ``swarm gcs`` with the same key. It waits for the election, takes off
and flies the V (FOLLOW) through the station's HTTP API, as an operator would.

A monitor thread samples the swarm every 0.2 s: each live agent's newest ``state``
line (``--json``), and the station's ``/api/state``. The swarm is *healthy* when every
live agent is LEADER or MEMBER of one and the same leader, the leader's member list is
every other live agent, and the station is connected to every live agent and names the
same leader. Each fault is injected, then the bench waits for health again:

* ``recovery_s``: from the moment the fault ends (the kill, the SIGCONT, the restart,
  the replug, the last rogue frame) to health;
* ``dual_leader_s``: how long two or more live agents claimed to lead, from the fault's
  start to health (a SIGSTOPped agent is not live while stopped);
* ``commands_lost``: commands the station reported without result that the swarm did
  not carry out, or reported carried out when they were not;
* ``frames_accepted_from_rogue``: rogue frames that had an effect (a forged id in a
  pool, a leader or the station's list; a replayed frame of an agent that is not there
  seen as alive; a radio moved off the swarm's network).

``survived`` means health came back within the fault's deadline with nothing lost or
accepted. Targets (reported, not asserted here): recovery within two election times,
dual leadership within one leader timeout, nothing lost, nothing accepted.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import random
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
    detail: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "fault": self.fault,
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

    def healthy(self) -> bool:
        live = set(self.states)
        if not live or self.station is None:
            return False
        leaders = self.leaders()
        if len(leaders) != 1:
            return False
        lead = next(iter(leaders))
        if any(
            s.get("phase") not in ("LEADER", "MEMBER") or s.get("leader") != lead
            for s in self.states.values()
        ):
            return False
        if set(self.states[lead].get("members", [])) != live - {lead}:
            return False
        connected = {a["id"] for a in self.station.get("agents", []) if a.get("connected")}
        return live <= connected and self.station.get("leader") == lead


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
        # the radio guard: a radio moved off the swarm's network by a rogue's RT commands is
        # restored by its agent once it has heard no one for RECHECK_S
        self.agent_args: list[str] = [
            "--radio-params",
            "NETID=25",
            "--restore-radio",
            "--radio-recheck",
            str(RECHECK_S),
        ]
        self.log = log or (lambda _s: None)
        self.emu: Child | None = None
        self.links: list[str] = []
        self.base_port = 0
        self.agents: dict[int, AgentProc] = {}
        self.station: Child | None = None
        self.station_url = ""
        self.elect_s: float | None = None
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
        from swarm.cli.demo import _free_base_port
        from swarm.core.protocol import fast_profile, paper_profile

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
        )
        self.base_port = _free_base_port(self.n + 2)
        for k in range(1, self.n + 1):
            a = self.agents[k] = AgentProc(self, k)
            a.start_sim()
        for a in self.agents.values():
            a.start_agent()
        t0 = time.monotonic()
        self.start_station()
        round_s = float(self.agents[1].ready.get("round_s", 0.5))
        prof = fast_profile(round_s) if self.profile == "fast" else paper_profile(round_s)
        self.leader_timeout_s = prof.leader_timeout
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
            f"no healthy swarm {timeout:.0f} s after {what}: " + (_describe(snap) if snap else "no sample")
        )

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

    # -- faults ---------------------------------------------------------------------
    def _settled(self, what: str) -> None:
        self.wait_healthy(HEALTH_TIMEOUT_S, f"before {what}")

    def _measure(self, name: str, fault_start: float, fault_end: float, **detail: Any) -> FaultResult:
        res = FaultResult(name, detail=dict(detail))
        try:
            res.recovery_s = self.wait_healthy(HEALTH_TIMEOUT_S, name, since=fault_end)
            res.survived = True
        except BenchError as exc:
            res.detail["error"] = str(exc)
        res.dual_leader_s = self.dual_leader_s(fault_start, time.monotonic())
        return res

    def fault_leader_kill(self) -> FaultResult:
        self._settled("leader kill")
        lead = self.leader()
        t = time.monotonic()
        self.agents[lead].kill()
        res = self._measure("leader kill -9", t, t, killed=f"agent{lead}")
        self.agents[lead].start_agent()  # back for the next fault
        return res

    def fault_leader_stop(self, stop_s: float = 10.0) -> FaultResult:
        self._settled("leader SIGSTOP")
        lead = self.leader()
        a = self.agents[lead]
        assert a.agent is not None
        t = time.monotonic()
        os.killpg(a.agent.proc.pid, signal.SIGSTOP)
        a.stopped = True
        time.sleep(stop_s)
        os.killpg(a.agent.proc.pid, signal.SIGCONT)
        a.stopped = False
        return self._measure(f"leader SIGSTOP {stop_s:g} s", t, time.monotonic(), stopped=f"agent{lead}")

    def fault_member_restart(self, uptime_s: float = 90.0) -> FaultResult:
        self._settled("member restart")
        lead = self.leader()
        k = next(k for k in sorted(self.agents) if k != lead)
        a = self.agents[k]
        # the restarted member must verify streams that have run that long (their
        # signing timestamps lagged by their uptime before the fix)
        oldest = max(time.monotonic() - b.started_at for b in self.agents.values() if b is not a)
        wait = uptime_s - oldest
        if wait > 0:
            time.sleep(wait)
        t = time.monotonic()
        a.kill()
        restart = time.monotonic()  # recovery counts from here: the new process's start-up included
        a.start_agent()
        return self._measure(
            f"member kill -9 and restart after {uptime_s:g} s", t, restart, restarted=f"agent{k}"
        )

    def fault_station_restart(self) -> FaultResult:
        self._settled("station restart")
        assert self.station is not None
        t = time.monotonic()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.station.proc.pid, signal.SIGKILL)
        self.station.stop()
        restart = time.monotonic()
        self.start_station()
        return self._measure("station kill -9 and restart", t, restart)

    def fault_vehicle_restart(self, down_s: float = 5.0) -> FaultResult:
        self._settled("vehicle restart")
        lead = self.leader()
        k = next(k for k in sorted(self.agents, reverse=True) if k != lead)
        a = self.agents[k]
        assert a.sim is not None
        t = time.monotonic()
        a.sim.stop()
        time.sleep(down_s)
        a.start_sim()
        res = self._measure(
            "vehicle simulator killed and restarted", t, time.monotonic(), vehicle=f"agent{k}"
        )
        res.detail["agent_events"] = [e.get("text", "") for e in a.events("vehicle")][-4:]
        return res

    def fault_garbage(self, size: int = 1 << 20) -> FaultResult:
        self._settled("garbage")
        lead = self.leader()
        k = next(k for k in sorted(self.agents) if k != lead)
        rnd = random.Random(self.seed)
        data = rnd.randbytes(size)
        t = time.monotonic()
        fd = os.open(self.agents[k].radio, os.O_WRONLY | os.O_NOCTTY | os.O_NONBLOCK)
        written = 0
        try:
            while written < size:
                try:
                    written += os.write(fd, data[written : written + 4096])
                except BlockingIOError:
                    time.sleep(0.01)
        finally:
            os.close(fd)
        return self._measure(
            f"{size // 1024} KiB of garbage into a member's radio", t, time.monotonic(), radio=f"agent{k}"
        )

    def fault_garbage_small(self) -> FaultResult:
        return self.fault_garbage(64 * 1024)

    def _control(self, line: str) -> None:
        """One line to the emulator's control FIFO (``unplug``, ``replug``, ``loss``)."""
        fd = os.open(os.path.join(self.workdir, "radios", "control"), os.O_WRONLY | os.O_NONBLOCK)
        try:
            os.write(fd, (line + "\n").encode())
        finally:
            os.close(fd)

    def fault_radio_unplug(self, down_s: float = 3.0) -> FaultResult:
        """The leader's USB radio pulled out and plugged back: the agent waits for it."""
        self._settled("radio unplug")
        lead = self.leader()
        t = time.monotonic()
        self._control(f"unplug {lead - 1}")
        time.sleep(down_s)
        self._control(f"replug {lead - 1}")
        res = self._measure(
            f"the leader's radio unplugged for {down_s:g} s and plugged back",
            t,
            time.monotonic(),
            radio=f"agent{lead}",
        )
        res.detail["agent_alive"] = self.agents[lead].live
        if not self.agents[lead].live:
            res.survived = False
        return res

    def fault_commands(self, count: int = 20, loss: float = 0.2) -> FaultResult:
        """``count`` swarm commands (FOLLOW with a new heading, STOP, in turn) through the
        station's API at ``loss``, each outcome checked against the agents' own logs."""
        from swarm.cli.bench.commands import _campaign, _judge

        self._settled("commands")
        marks = {k: len(a.agent.lines) for k, a in self.agents.items() if a.agent is not None}
        assert self.station is not None
        station_mark = len(self.station.lines)
        self._control(f"loss {loss:g}")
        t = time.monotonic()
        try:
            camp = _campaign(self.station_url + "/", count, [self.station])
        finally:
            self._control(f"loss {self.loss:g}")
        end = time.monotonic()
        time.sleep(3.0)  # the last answers and log lines
        agents = [
            _Lines(a.agent.lines[marks[k] :])
            for k, a in self.agents.items()
            if a.agent is not None and k in marks
        ]
        judged = _judge(_Lines(self.station.lines[station_mark:]), agents, camp.pop("_bodies"))
        # the swarm commands leave the V stopped or following: FOLLOW again for the next fault
        self.command({"target": "swarm", "kind": "follow", "heading": 0})
        res = self._measure(f"{count} swarm commands at {loss:.0%} loss", t, end)
        res.commands_lost = int(judged["silently_lost"]) + int(judged["wrongly_reported"])
        res.detail.update(
            {
                k: judged[k]
                for k in (
                    "addressees",
                    "accepted",
                    "carried_out_unacked",
                    "refused",
                    "no_answer",
                    "silently_lost",
                    "wrongly_reported",
                    "wrong",
                )
            }
        )
        res.detail.update({k: camp[k] for k in ("refused_at_station", "command_s_p50", "command_s_max")})
        return res

    def _pose_stats(self, start_wall: float, end_wall: float) -> dict[int, tuple[int, float]]:
        """Per agent: pose frames put on the air in the window, and the longest gap."""
        from radios.errors import RadioError
        from radios.tlog import read_tlog
        from swarm.core.tunnel import Kind, unpack_tunnel
        from swarm.errors import SwarmError

        times: dict[int, list[float]] = {k: [] for k in self.agents}
        try:
            with read_tlog(self.capture) as r:
                for rec in r:
                    if rec.t < start_wall or rec.t > end_wall:
                        continue
                    f = rec.frame
                    if f.msgid != 385 or f.sysid not in times:
                        continue
                    with contextlib.suppress(SwarmError):
                        u = unpack_tunnel(f.payload)
                        if u is not None and u[0] == Kind.POSE:
                            times[f.sysid].append(rec.t)
        except RadioError:  # the record being written: what was read is enough
            pass
        out = {}
        for k, ts in times.items():
            edges = [start_wall, *ts, end_wall]
            out[k] = (len(ts), max(b - a for a, b in itertools.pairwise(edges)))
        return out

    def fault_rogue_radio_status(self, seconds: float = 20.0, hz: float = 10.0) -> FaultResult:
        """Forged RADIO_STATUS (sysid 51, compid 68, txbuf 0) from the rogue at ``hz``: the
        pose streams may slow by at most 20 %."""
        import struct

        from radios.link import open_link
        from radios.mavlink import pack_frame

        self._settled("forged RADIO_STATUS")
        before_start = time.time()
        time.sleep(seconds)  # the baseline window, the same length
        before_end = time.time()
        t = time.monotonic()
        start_wall = time.time()
        link = open_link(self.links[self.n + 1])
        sent = 0
        try:
            while time.time() - start_wall < seconds:
                link.send(
                    pack_frame(
                        109,
                        struct.pack("<HHBBBBB", 0, 0, 200, 200, 0, 30, 30),
                        sysid=51,
                        compid=68,
                        seq=sent & 0xFF,
                    )
                )
                sent += 1
                time.sleep(1.0 / hz)
        finally:
            link.close()
        end_wall = time.time()
        time.sleep(1.0)
        base = self._pose_stats(before_start, before_end)
        during = self._pose_stats(start_wall, end_wall)
        res = self._measure(
            f"rogue radio: forged RADIO_STATUS at {hz:g} Hz, txbuf 0", t, time.monotonic(), rogue_frames=sent
        )
        rates = {k: (during[k][0] / base[k][0]) if base[k][0] else None for k in base}
        worst = min((r for r in rates.values() if r is not None), default=None)
        res.detail.update(
            {
                "pose_rate_ratio_min": None if worst is None else round(worst, 3),
                "longest_pose_gap_s_before": round(max(g for _n, g in base.values()), 2),
                "longest_pose_gap_s_during": round(max(g for _n, g in during.values()), 2),
            }
        )
        if worst is None or worst < 0.8:
            res.frames_accepted_from_rogue = sent  # the forgeries slowed the swarm
        return res

    # -- the rogue radio --------------------------------------------------------------
    def _rogue_send(self, frames: list[bytes], rate_bps: float = 3000.0) -> None:
        """Write frames into the rogue radio at about ``rate_bps`` (under its serial rate)."""
        from radios.link import open_link

        link = open_link(self.links[self.n + 1])
        try:
            for raw in frames:
                link.send(raw)
                time.sleep(len(raw) / rate_bps)
        finally:
            link.close()

    def _rogue_effects(self, start: float, leader: int) -> dict[str, int]:
        """What rogue frames could have done, seen in the samples since ``start``."""
        with self._hist_lock:
            samples = [s for s in self.history if s.t >= start]
        forged = changed = 0
        for s in samples:
            for st in s.states.values():
                ids = {st.get("leader"), st.get("candidate"), *st.get("pool", []), *st.get("members", [])}
                if ROGUE_ID in ids:
                    forged += 1
                usurper = st.get("phase") == "LEADER" and st.get("id") != leader
                if usurper or st.get("leader") not in (leader, None):
                    changed += 1
            if s.station is not None and any(a.get("id") == ROGUE_ID for a in s.station.get("agents", [])):
                forged += 1
        return {"samples_with_forged_id": forged, "samples_with_leader_change": changed}

    def _rogue_fault(self, name: str, frames: list[bytes]) -> FaultResult:
        self._settled(name)
        lead = self.leader()
        t = time.monotonic()
        self._rogue_send(frames)
        end = time.monotonic()
        time.sleep(max(3.0, self.leader_timeout_s))  # room for an effect to show
        res = self._measure(name, t, end, rogue_frames=len(frames))
        eff = self._rogue_effects(t, lead)
        res.detail.update(eff)
        res.frames_accepted_from_rogue = eff["samples_with_forged_id"] + eff["samples_with_leader_change"]
        return res

    def _forgeries(self, key: bytes | None, sysid: int) -> list[bytes]:
        """Advertize, StartPool, a vote for the rogue and a Heartbeat claiming every agent."""
        from radios.mavlink import FrameBuilder
        from swarm.core.messages import Advertize, Heartbeat, Selection, StartPool, encode
        from swarm.core.tunnel import COMP_ID, PAYLOAD_TYPE_BASE, Kind

        b = FrameBuilder(sysid, COMP_ID, signing_key=key)
        members = frozenset(self.agents) - {sysid}

        def tun(kind: Kind, msg: bytes, target: int = 0) -> bytes:
            return b.tunnel(msg, target_system=target, payload_type=PAYLOAD_TYPE_BASE + int(kind))

        name = "rogue" if sysid == ROGUE_ID else f"agent{sysid}"
        out = [tun(Kind.ADVERTIZE, encode(Advertize(sysid, name)))]
        for _ in range(5):
            for k in self.agents:
                if k == sysid:
                    continue
                out.append(tun(Kind.P2P, encode(StartPool(sysid)), k))
                out.append(tun(Kind.P2P, encode(Selection(sysid, sysid, 0xFFFFFFFF, 1)), k))
                out.append(tun(Kind.P2P, encode(Heartbeat(sysid, 1, 1, members | {ROGUE_ID})), k))
        return out

    def fault_rogue_unsigned(self) -> FaultResult:
        frames = self._forgeries(None, ROGUE_ID) + self._forgeries(None, self.leader() or 1)
        return self._rogue_fault("rogue radio: unsigned frames (forged ids and the leader's id)", frames)

    def fault_rogue_wrong_key(self) -> FaultResult:
        from radios.signing import key_from_passphrase

        other = key_from_passphrase("not the swarm key")
        frames = self._forgeries(other, ROGUE_ID) + self._forgeries(other, self.leader() or 1)
        return self._rogue_fault("rogue radio: frames signed with another key", frames)

    def fault_rogue_replay(self, seconds: float = 30.0) -> FaultResult:
        """Frames recorded from the air at the start (the election, the first leader's
        heartbeats, the take-off commands) played back from the rogue radio."""
        from radios.tlog import read_tlog

        frames: list[bytes] = []
        with read_tlog(self.capture) as r:
            t0 = None
            for rec in r:
                t0 = rec.t if t0 is None else t0
                if rec.t - t0 > seconds:
                    break
                raw = bytes(rec.raw)
                if raw[0] == 0xFD and raw[2] & 1:  # signed swarm frames only
                    frames.append(raw)
        return self._rogue_fault(f"rogue radio: {len(frames)} signed frames replayed from the air", frames)

    def fault_rogue_vote(self, seconds: float = 15.0) -> FaultResult:
        """The leader killed, and while the others elect a new one the rogue sends
        Selections for a candidate that does not exist (id 77, the heaviest weight, the
        survivors' election epoch), unsigned and signed with another key, in its own name
        and in the survivors' names."""
        from radios.mavlink import FrameBuilder
        from radios.signing import key_from_passphrase
        from swarm.core.messages import Selection, encode, pool_digest
        from swarm.core.tunnel import COMP_ID, PAYLOAD_TYPE_BASE, Kind

        self._settled("forged vote")
        lead = self.leader()
        survivors = sorted(k for k in self.agents if k != lead)
        epoch = pool_digest(survivors) & 0xFFFF
        builders = [
            FrameBuilder(sysid, COMP_ID, signing_key=key)
            for sysid in (ROGUE_ID, *survivors)
            for key in (None, key_from_passphrase("not the swarm key"))
        ]
        t = time.monotonic()
        self.agents[lead].kill()
        frames: list[bytes] = []
        while time.monotonic() - t < seconds and len(frames) < 2000:
            batch = [
                b.tunnel(
                    encode(Selection(b.mav.srcSystem, ROGUE_ID, 0xFFFFFFFF, epoch)),
                    target_system=k,
                    payload_type=PAYLOAD_TYPE_BASE + int(Kind.P2P),
                )
                for b in builders
                for k in survivors
            ]
            self._rogue_send(batch)
            frames += batch
        res = self._measure(
            "rogue radio: forged votes during an election (leader killed)",
            t,
            time.monotonic(),
            rogue_frames=len(frames),
            killed=f"agent{lead}",
        )
        with self._hist_lock:
            samples = [x for x in self.history if x.t >= t]
        forged = sum(
            1
            for x in samples
            for st in x.states.values()
            if ROGUE_ID in (st.get("leader"), st.get("candidate"))
        )
        res.detail["samples_with_forged_candidate"] = forged
        res.frames_accepted_from_rogue = forged
        self.agents[lead].start_agent()
        return res

    def fault_rogue_remote_at(self) -> FaultResult:
        """The rogue's host puts its radio in command mode and sends the leader's radio
        ``RTS3=77``, ``RT&W`` and ``RTZ`` (multipoint: ``,<node>``): the leader's radio
        moves to NETID 77 for good unless its agent notices and restores it."""
        from radios.errors import RadioError
        from radios.sik.config import SikConfigurator, open_port

        self._settled("rogue remote AT")
        lead = self.leader()
        node = lead - 1  # radio K-1 is node K-1
        t = time.monotonic()
        port = open_port(self.links[self.n + 1])
        try:
            conf = SikConfigurator(port, flavour="multipoint", port_name="rogue")
            conf.enter_command_mode()
            for cmd in (f"RTS3=77,{node}", f"RT&W,{node}", f"RTZ,{node}"):
                for _ in range(3):  # air loss: a rogue repeats itself (RTZ is never answered)
                    with contextlib.suppress(RadioError):
                        conf.command(cmd, timeout=1.0)
            with contextlib.suppress(Exception):
                conf.exit_command_mode()
        finally:
            port.close()
        res = self._measure(
            "rogue radio: remote AT (RTS3=77, RT&W, RTZ) to the leader's radio",
            t,
            time.monotonic(),
            target=f"agent{lead}",
        )
        moved = any(e.get("event") == "radio-restored" for e in self.agents[lead].all_events())
        res.detail["leader_radio_restored"] = moved
        if not res.survived:
            res.frames_accepted_from_rogue += 1  # the radio stayed moved: the commands took
        return res


class _Lines:
    """A process's output lines from a mark on (what :func:`swarm.cli.bench.commands._judge` reads)."""

    def __init__(self, lines: list[str]) -> None:
        self.lines = lines


def _describe(s: Snapshot) -> str:
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


#: the bounded set the test suite runs (``--quick``): ordered so that the member restart
#: needs no extra wait for the others' uptime
FAULTS_QUICK = (
    "rogue_unsigned",
    "rogue_wrong_key",
    "station_restart",
    "garbage_small",
    "leader_kill",
    "member_restart",
    "rogue_replay",
)
FAULTS_ALL = (
    "leader_kill",
    "leader_stop",
    "member_restart",
    "station_restart",
    "radio_unplug",
    "vehicle_restart",
    "garbage",
    "rogue_unsigned",
    "rogue_wrong_key",
    "rogue_replay",
    "rogue_vote",
    "rogue_remote_at",
    "rogue_radio_status",
    "commands",
)


def run_faults(
    names: tuple[str, ...],
    *,
    log: Callable[[str], None] | None = None,
    member_uptime_s: float = 90.0,
    **kw: Any,
) -> dict[str, Any]:
    results: list[FaultResult] = []
    with FaultBench(log=log, **kw) as bench:
        bench.fly()
        for name in names:
            fn = getattr(bench, f"fault_{name}")
            args = {"uptime_s": member_uptime_s} if name == "member_restart" else {}
            try:
                r = fn(**args)
            except BenchError as exc:
                r = FaultResult(name, detail={"error": str(exc)})
            results.append(r)
            bench.log(json.dumps(r.as_dict()))
        elect = bench.elect_s or 0.0
        lt = bench.leader_timeout_s
    faults = [r.as_dict() for r in results]
    return {
        "faults": faults,
        "survived": sum(
            1 for r in results if r.survived and not r.commands_lost and not r.frames_accepted_from_rogue
        ),
        "total": len(results),
        "elect_s": round(elect, 2),
        "leader_timeout_s": round(lt, 2),
        "targets": {
            "all_survived": all(r.survived for r in results),
            "recovery_within_2_elections": all(
                r.recovery_s is not None and r.recovery_s <= 2 * elect for r in results
            ),
            "dual_leader_within_leader_timeout": all(r.dual_leader_s <= lt for r in results),
            "no_command_lost": all(r.commands_lost == 0 for r in results),
            "no_rogue_frame_accepted": all(r.frames_accepted_from_rogue == 0 for r in results),
        },
    }


def run(quick: bool = False) -> dict[str, Any]:
    import sys

    def log(s: str) -> None:
        print(s, file=sys.stderr, flush=True)

    if quick:
        return run_faults(FAULTS_QUICK, log=log, member_uptime_s=75.0)
    return run_faults(FAULTS_ALL, log=log)
