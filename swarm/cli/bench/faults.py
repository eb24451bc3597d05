"""``swarm bench faults``: a real signed swarm, flying, put through one fault after another.

Theory of operation
-------------------
The bench (:class:`swarm.cli.bench.fault_bench.FaultBench`: the processes, the health
monitor, ``recovery_s`` and ``dual_leader_s``) flies a signed V; each fault here is a
function of the bench that waits for a healthy swarm, injects the fault, and measures
the recovery (:data:`FAULTS`, by name). Besides the bench's two measures a fault
reports:

* ``commands_lost``: commands the station reported without result that the swarm did
  not carry out, or reported carried out when they were not;
* ``frames_accepted_from_rogue``: rogue frames that had an effect (a forged id in a
  pool, a leader or the station's list; a replayed frame of an agent that is not there
  seen as alive; a radio moved off the swarm's network).

``survived`` means health came back within the fault's deadline with nothing lost or
accepted. Targets (reported, not asserted here): recovery within two election times,
dual leadership within one leader timeout, nothing lost, nothing accepted.
:func:`run_faults` runs a list of faults on one bench and sums them up.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import random
import signal
import time
from collections.abc import Callable
from typing import Any

from swarm.cli.bench.fault_bench import (
    CHECK_PERIOD_S,
    ROGUE_ID,
    BenchError,
    FaultBench,
    FaultResult,
)
from swarm.cli.procs import json_events


def leader_kill(bench: FaultBench) -> FaultResult:
    bench.settled("leader kill")
    lead = bench.leader()
    t = time.monotonic()
    bench.agents[lead].kill()
    res = bench.measure(
        "leader kill -9", t, t, injected=f"SIGKILL to the leader, agent{lead}", killed=f"agent{lead}"
    )
    new_leader = bench.first_agreed(t)
    res.detail["new_leader_s"] = None if new_leader is None else round(new_leader, 2)
    res.observed = (
        f"a new leader followed by every survivor {_s(new_leader)} after the kill "
        f"(target: two election times of the profile, {2 * bench.profile_elect_s:.1f} s), "
        f"the station connected to all {_s(res.recovery_s)} after it"
    )
    bench.agents[lead].start_agent()  # back for the next fault
    return res


def _s(v: float | None) -> str:
    return "never" if v is None else f"{v:.1f} s"


def leader_stop(bench: FaultBench, stop_s: float = 10.0) -> FaultResult:
    bench.settled("leader SIGSTOP")
    lead = bench.leader()
    a = bench.agents[lead]
    assert a.agent is not None
    t = time.monotonic()
    os.killpg(a.agent.proc.pid, signal.SIGSTOP)
    a.stopped = True
    time.sleep(stop_s)
    os.killpg(a.agent.proc.pid, signal.SIGCONT)
    a.stopped = False
    return bench.measure(
        f"leader SIGSTOP {stop_s:g} s",
        t,
        time.monotonic(),
        injected=f"SIGSTOP to the leader, agent{lead}, SIGCONT {stop_s:g} s later",
        stopped=f"agent{lead}",
    )


def member_restart(bench: FaultBench, uptime_s: float = 90.0) -> FaultResult:
    bench.settled("member restart")
    lead = bench.leader()
    k = next(k for k in sorted(bench.agents) if k != lead)
    a = bench.agents[k]
    # the restarted member must verify streams that have run that long (their
    # signing timestamps lagged by their uptime before the fix)
    oldest = max(time.monotonic() - b.started_at for b in bench.agents.values() if b is not a)
    wait = uptime_s - oldest
    if wait > 0:
        time.sleep(wait)
    t = time.monotonic()
    a.kill()
    restart = time.monotonic()  # recovery counts from here: the new process's start-up included
    a.start_agent()
    return bench.measure(
        f"member kill -9 and restart after {uptime_s:g} s",
        t,
        restart,
        injected=f"SIGKILL to member agent{k} after {uptime_s:g} s of everyone's uptime, started again "
        "at once (recovery counts from the new process's start)",
        restarted=f"agent{k}",
    )


def station_restart(bench: FaultBench) -> FaultResult:
    bench.settled("station restart")
    assert bench.station is not None
    t = time.monotonic()
    with contextlib.suppress(ProcessLookupError):
        os.killpg(bench.station.proc.pid, signal.SIGKILL)
    bench.station.stop()
    restart = time.monotonic()
    bench.start_station()
    return bench.measure(
        "station kill -9 and restart", t, restart, injected="SIGKILL to the station, started again at once"
    )


def station_restart_in_command(
    bench: FaultBench, after_s: float = 0.3, heading: float = 123.0
) -> FaultResult:
    """The station killed ``after_s`` into a swarm FOLLOW sent through its API, and
    started again. Nothing may be lost or done twice: the operator's request either
    answers truthfully or fails (never a false result); no agent carries the command out
    twice; after the restart the station shows the task the leader really flies."""
    import threading

    from swarm.cli.bench.commands import AGENT_RE

    bench.settled("station restart during a command")
    assert bench.station is not None
    marks = {k: len(a.agent.lines) for k, a in bench.agents.items() if a.agent is not None}
    box: dict[str, Any] = {}

    def post() -> None:
        try:
            box["answer"] = bench.command(
                {"target": "swarm", "kind": "follow", "heading": heading}, timeout=40
            )
        except OSError as exc:  # the station died under the request
            box["error"] = type(exc).__name__

    sender = threading.Thread(target=post, name="fault-command", daemon=True)
    t = time.monotonic()
    sender.start()
    time.sleep(after_s)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(bench.station.proc.pid, signal.SIGKILL)
    bench.station.stop()
    restart = time.monotonic()
    bench.start_station()
    sender.join(45)
    res = bench.measure(
        "station kill -9 during a command, and restart",
        t,
        restart,
        injected=f"a swarm FOLLOW (heading {heading:g}) posted to the station's API, the station killed "
        f"{after_s:g} s later and started again",
    )
    time.sleep(3.0)  # the leader's next heartbeats carry the task to the new station
    done: dict[int, dict[int, int]] = {}  # agent -> seq -> times carried out
    for k, a in bench.agents.items():
        for e in json_events(a.agent.lines[marks.get(k, 0) :] if a.agent else [], "pilot"):
            m = AGENT_RE.match(str(e.get("text", "")))
            if m and m.group(1) == "FOLLOW" and m.group(4) == "ACCEPTED" and int(m.group(3)) >= 251:
                seqs = done.setdefault(k, {})
                seqs[int(m.group(2))] = seqs.get(int(m.group(2)), 0) + 1
    twice = sum(n - 1 for seqs in done.values() for n in seqs.values() if n > 1)
    carried = bool(done)
    status, body = box.get("answer", (None, {}))
    answered = [r for r in (body.get("results") or []) if r.get("result") == "ACCEPTED"]
    false_results = sum(1 for r in answered if r.get("agent") not in done)  # an ACCEPTED never logged
    st = bench.station_state() or {}
    task = st.get("task") or {}
    shown = task.get("heading")
    wrong_view = carried and (shown is None or abs((float(shown) - heading + 180.0) % 360.0 - 180.0) > 1.0)
    res.commands_lost = twice + false_results + int(wrong_view)
    res.detail.update(
        {
            "http_status": status,
            "http_error": box.get("error"),
            "carried_out_by": sorted(done),
            "carried_out_twice": twice,
            "false_results": false_results,
            "station_task_heading_after": shown,
        }
    )
    res.observed += (
        "; the operator's request "
        + (f"answered {status}" if status is not None else f"failed ({box.get('error', 'no answer')})")
        + f"; FOLLOW carried out by {sorted(done) or 'no agent'}, {twice} times twice; "
        + f"{false_results} results claimed that no agent logged; the restarted station shows the task "
        + f"heading {shown} (flown: {heading:g} if carried out)"
    )
    bench.command({"target": "swarm", "kind": "follow", "heading": 0})  # the V as before
    return res


def vehicle_restart(bench: FaultBench, down_s: float = 5.0) -> FaultResult:
    bench.settled("vehicle restart")
    lead = bench.leader()
    k = next(k for k in sorted(bench.agents, reverse=True) if k != lead)
    a = bench.agents[k]
    assert a.sim is not None
    t = time.monotonic()
    a.sim.stop()
    time.sleep(down_s)
    a.start_sim()
    res = bench.measure(
        "vehicle simulator killed and restarted",
        t,
        time.monotonic(),
        injected=f"agent{k}'s vehicle simulator stopped, started again {down_s:g} s later",
        vehicle=f"agent{k}",
    )
    res.detail["agent_events"] = [e.get("text", "") for e in a.events("vehicle")][-4:]
    return res


def garbage(bench: FaultBench, size: int = 1 << 20) -> FaultResult:
    bench.settled("garbage")
    lead = bench.leader()
    k = next(k for k in sorted(bench.agents) if k != lead)
    rnd = random.Random(bench.seed)
    data = rnd.randbytes(size)
    paused_before = len([e for e in bench.agents[k].events("radio") if e.get("state") == "paused"])
    t = time.monotonic()
    fd = os.open(bench.agents[k].radio, os.O_WRONLY | os.O_NOCTTY | os.O_NONBLOCK)
    written = 0
    try:
        while written < size:
            try:
                written += os.write(fd, data[written : written + 4096])
            except BlockingIOError:
                time.sleep(0.01)
    finally:
        os.close(fd)
    end = time.monotonic()
    res = bench.measure(
        f"{size // 1024} KiB of garbage into a member's radio",
        t,
        end,
        injected=f"{size // 1024} KiB of random bytes written into member agent{k}'s radio port "
        f"(taken in {end - t:.0f} s: the radio sends them on the air in its own slots)",
        radio=f"agent{k}",
    )
    checks = [e for e in bench.agents[k].events("radio") if e.get("state") == "paused"][paused_before:]
    res.detail["radio_checks_during"] = len(checks)
    res.observed += f"; agent{k}'s radio checked {len(checks)} times (it still heard the swarm)"
    return res


def garbage_small(bench: FaultBench) -> FaultResult:
    return garbage(bench, 64 * 1024)


def radio_unplug(bench: FaultBench, down_s: float = 3.0) -> FaultResult:
    """The leader's USB radio pulled out and plugged back: the agent waits for it."""
    bench.settled("radio unplug")
    lead = bench.leader()
    t = time.monotonic()
    bench.control(f"unplug {lead - 1}")
    time.sleep(down_s)
    bench.control(f"replug {lead - 1}")
    res = bench.measure(
        f"the leader's radio unplugged for {down_s:g} s and plugged back",
        t,
        time.monotonic(),
        injected=f"the leader agent{lead}'s radio device removed for {down_s:g} s (the emulator's unplug)",
        radio=f"agent{lead}",
    )
    res.detail["agent_alive"] = bench.agents[lead].live
    if not bench.agents[lead].live:
        res.survived = False
    return res


def radio_swap(bench: FaultBench, down_s: float = 3.0) -> FaultResult:
    """The leader's radio unplugged and another device put at its path meanwhile (a
    fresh pty the bench holds: a reassigned /dev/ttyUSB0), then its own radio back. The
    agent must write nothing to the stranger, say so once, and take its radio back."""
    import pty
    import select
    import tty

    bench.settled("radio swap")
    lead = bench.leader()
    agent = bench.agents[lead]
    path = agent.radio
    before = len([e for e in agent.events("radio") if e.get("state") == "refused"])
    t = time.monotonic()
    bench.control(f"unplug {lead - 1}")
    deadline = time.monotonic() + 10
    while os.path.lexists(path) and time.monotonic() < deadline:  # the emulator removes the link
        time.sleep(0.05)
    master, slave = pty.openpty()
    tty.setraw(slave)
    other = os.ttyname(slave)
    os.close(slave)
    written = 0
    try:
        os.symlink(other, path)
        end = time.monotonic() + down_s
        while (left := end - time.monotonic()) > 0:
            if select.select([master], [], [], left)[0]:
                try:
                    written += len(os.read(master, 4096))
                except OSError:  # nobody holds it open
                    time.sleep(0.05)
        os.unlink(path)
    finally:
        os.close(master)
    bench.control(f"replug {lead - 1}")
    res = bench.measure(
        f"the leader's radio unplugged and another device at its path for {down_s:g} s",
        t,
        time.monotonic(),
        injected=f"the leader agent{lead}'s radio unplugged, a fresh pty put at its path ({path}) for "
        f"{down_s:g} s, then its own radio plugged back",
        radio=f"agent{lead}",
    )
    refused = [e for e in agent.events("radio") if e.get("state") == "refused"][before:]
    res.detail.update(bytes_to_other_device=written, refused_lines=len(refused), agent_alive=agent.live)
    res.frames_accepted_from_rogue += written > 0
    res.observed += (
        f"; {written} bytes written to the other device, {len(refused)} 'refused' line(s) from the agent, "
        + ("the agent alive" if agent.live else "the agent DEAD")
    )
    if written or len(refused) != 1 or not agent.live:
        res.survived = False
    return res


def commands(bench: FaultBench, count: int = 20, loss: float = 0.2) -> FaultResult:
    """``count`` swarm commands (FOLLOW with a new heading, STOP, in turn) through the
    station's API at ``loss``, each outcome checked against the agents' own logs."""
    from swarm.cli.bench.commands import command_campaign, judge

    bench.settled("commands")
    marks = {k: len(a.agent.lines) for k, a in bench.agents.items() if a.agent is not None}
    assert bench.station is not None
    station_mark = len(bench.station.lines)
    bench.control(f"loss {loss:g}")
    t = time.monotonic()
    try:
        camp = command_campaign(bench.station_url + "/", count, [bench.station])
    finally:
        bench.control(f"loss {bench.loss:g}")
    end = time.monotonic()
    time.sleep(3.0)  # the last answers and log lines
    agents = [
        _Lines(a.agent.lines[marks[k] :])
        for k, a in bench.agents.items()
        if a.agent is not None and k in marks
    ]
    judged = judge(_Lines(bench.station.lines[station_mark:]), agents, camp.pop("_bodies"))
    # the swarm commands leave the V stopped or following: FOLLOW again for the next fault
    bench.command({"target": "swarm", "kind": "follow", "heading": 0})
    res = bench.measure(
        f"{count} swarm commands at {loss:.0%} loss",
        t,
        end,
        injected=f"{count} swarm commands (FOLLOW with a new heading and STOP in turn) through the "
        f"station's API with {loss:.0%} loss on every radio",
    )
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
    res.observed += (
        f"; per addressee: {judged['accepted']} accepted, {judged['carried_out_unacked']} carried out "
        f"without an answer, {judged['refused']} refused, {judged['no_answer']} without answer; "
        f"{judged['silently_lost']} lost silently, {judged['wrongly_reported']} reported wrongly "
        "(each checked against the agents' own logs)"
    )
    return res


def _pose_stats(bench: FaultBench, start_wall: float, end_wall: float) -> dict[int, tuple[int, float]]:
    """Per agent: pose frames put on the air in the window, and the longest gap."""
    from radios.errors import RadioError
    from radios.tlog import read_tlog
    from swarm.core.wire.tunnel import Kind, unpack_tunnel
    from swarm.errors import SwarmError

    times: dict[int, list[float]] = {k: [] for k in bench.agents}
    try:
        with read_tlog(bench.capture) as r:
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


#: forged RADIO_STATUS: the longest pose gap may grow by at most this factor over the
#: quiet window's just before (the pose streams are what separation rests on)
POSE_GAP_RATIO_MAX = 1.5


def rogue_radio_status(bench: FaultBench, seconds: float = 20.0, hz: float = 10.0) -> FaultResult:
    """Forged RADIO_STATUS (sysid 51, compid 68, txbuf 0) from the rogue at ``hz``, judged
    by the pose streams as put on the air: the longest gap between two poses of any agent
    may be at most :data:`POSE_GAP_RATIO_MAX` times the longest of the quiet window just
    before, of the same length (a rate kept on average can still hide a stall)."""
    import struct

    from radios.link import open_link
    from radios.mavlink import pack_frame

    bench.settled("forged RADIO_STATUS")
    before_start = time.time()
    time.sleep(seconds)  # the baseline window, the same length
    before_end = time.time()
    t = time.monotonic()
    start_wall = time.time()
    link = open_link(bench.links[bench.n + 1])
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
    base = _pose_stats(bench, before_start, before_end)
    during = _pose_stats(bench, start_wall, end_wall)
    res = bench.measure(
        f"rogue radio: forged RADIO_STATUS at {hz:g} Hz, txbuf 0",
        t,
        time.monotonic(),
        injected=f"{sent} RADIO_STATUS frames as the local radio's (sysid 51, txbuf 0 %) from a rogue "
        f"radio at {hz:g} Hz for {seconds:g} s",
        rogue_frames=sent,
    )
    rates = {k: (during[k][0] / base[k][0]) if base[k][0] else None for k in base}
    worst = min((r for r in rates.values() if r is not None), default=None)
    gap_before = max(g for _n, g in base.values())
    gap_during = max(g for _n, g in during.values())
    ratio = gap_during / gap_before if gap_before > 0 else float("inf")
    res.detail.update(
        {
            "pose_rate_ratio_min": None if worst is None else round(worst, 3),
            "longest_pose_gap_s_before": round(gap_before, 2),
            "longest_pose_gap_s_during": round(gap_during, 2),
            "longest_pose_gap_ratio": round(ratio, 2),
        }
    )
    res.observed += (
        f"; longest pose gap {gap_during:.2f} s during against {gap_before:.2f} s in the quiet "
        f"{seconds:g} s before (ratio {ratio:.2f}, at most {POSE_GAP_RATIO_MAX:g}); pose rate "
        + ("none" if worst is None else f"{worst:.2f}")
        + " of the quiet window's at worst"
    )
    if ratio > POSE_GAP_RATIO_MAX:
        res.frames_accepted_from_rogue = sent  # the forgeries stalled a pose stream
    return res


def _rogue_effects(bench: FaultBench, start: float, leader: int) -> dict[str, int]:
    """What rogue frames could have done, seen in the samples since ``start``."""
    samples = bench.samples_since(start)
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


def _rogue_fault(
    bench: FaultBench, name: str, frames: list[bytes] | Callable[[], list[bytes]], injected: str
) -> FaultResult:
    """Send ``frames`` (or what the callable makes, once the swarm has settled) from
    the rogue radio and look for their effect (:func:`_rogue_effects`)."""
    bench.settled(name)
    lead = bench.leader()
    if callable(frames):
        frames = frames()
    t = time.monotonic()
    bench.rogue_send(frames)
    end = time.monotonic()
    time.sleep(max(3.0, bench.leader_timeout_s))  # room for an effect to show
    res = bench.measure(name, t, end, injected=injected.format(n=len(frames)), rogue_frames=len(frames))
    eff = _rogue_effects(bench, t, lead)
    res.detail.update(eff)
    res.frames_accepted_from_rogue = eff["samples_with_forged_id"] + eff["samples_with_leader_change"]
    res.observed += (
        f"; the rogue's id in {eff['samples_with_forged_id']} samples of the agents' pools, votes, "
        f"memberships or the station's list, a leader other than agent{lead} in "
        f"{eff['samples_with_leader_change']}"
    )
    return res


def _air_frames(
    bench: FaultBench, start_wall: float, end_wall: float, sysids: set[int] | None = None
) -> list[tuple[float, bytes]]:
    """The signed frames the emulator recorded on the air between two wall-clock times
    (of ``sysids`` only, if given), with their times."""
    from radios.errors import RadioError
    from radios.tlog import read_tlog

    out: list[tuple[float, bytes]] = []
    try:
        with read_tlog(bench.capture) as r:
            for rec in r:
                if rec.t < start_wall or rec.t > end_wall:
                    continue
                raw = bytes(rec.raw)
                if raw[0] == 0xFD and raw[2] & 1 and (sysids is None or rec.frame.sysid in sysids):
                    out.append((rec.t, raw))
    except RadioError:  # the record being written: what was read is enough
        pass
    return out


def ip_attacker(bench: FaultBench) -> FaultResult:
    """An attacker on the IP side (a laptop on the field's Wi-Fi): every socket a
    process of the bench listens on, found from the process itself (``/proc``), is tried
    as Zenoh, plainly and with TLS but no certificate: subscribe to everything, put a
    station's ARM and TAKEOFF to every agent (on its inbox and its command key), a
    phantom leader's Advertize and Heartbeats, and ask the stations' command keys.
    Nothing may be executed, followed or learnt; the only listeners are the station's
    page (its own security: docs/security.md, "The ground station's API") and the vehicle
    simulators' MAVLink ports (the simulator's, not the swarm's)."""
    from swarm.cli.bench.ip_attack import attack, executed, listeners

    bench.settled("an IP attacker")
    lead = bench.leader()
    names = {f"agent{k}": k for k in bench.agents}
    procs: dict[str, int] = {}
    for k, a in bench.agents.items():
        if a.agent is not None and a.agent.proc.poll() is None:
            procs[f"agent{k}"] = a.agent.proc.pid
        if a.sim is not None and a.sim.proc.poll() is None:
            procs[f"vehicle{k}"] = a.sim.proc.pid
    if bench.station is not None:
        procs["station"] = bench.station.proc.pid
    if bench.emu is not None:
        procs["emulator"] = bench.emu.proc.pid
    marks = {k: len(a.agent.lines) for k, a in bench.agents.items() if a.agent is not None}
    t = time.monotonic()
    found: dict[str, list[str]] = {}
    reports = []
    tried = 0
    for who, pid in procs.items():
        socks = listeners(pid)
        found[who] = [x.describe() for x in socks]
        tried += sum(len(x.zenoh_endpoints()) for x in socks)
        reports += [(who, attack(x, names, phantom_id=ROGUE_ID)) for x in socks]
    end = time.monotonic()
    time.sleep(max(3.0, bench.leader_timeout_s))  # room for an effect to show
    opened = [f"{who}: {ep}" for who, r in reports for ep in r.opened]
    learnt = sum(len(r.received) for _who, r in reports)
    sent = sum(r.sent for _who, r in reports)
    done = [
        text
        for k, a in bench.agents.items()
        if a.agent is not None
        for text in executed(json_events(a.agent.lines[marks.get(k, 0) :], "pilot"))
    ]
    res = bench.measure(
        "IP attacker on every listener",
        t,
        end,
        injected=f"a Zenoh client without a certificate (plain and TLS) at each of "
        f"{sum(len(v) for v in found.values())} listening sockets found in /proc of {len(procs)} processes "
        f"({tried} endpoints tried), to subscribe to everything and put ARM and TAKEOFF to every agent "
        f"(inbox and command key), a phantom leader's Advertize and Heartbeats, and ask gcs/** "
        f"({sent} puts made where a session opened)",
        listeners=found,
        zenoh_sessions_opened=opened,
        samples_learnt=learnt,
        ip_commands_executed=len(done),
    )
    eff = _rogue_effects(bench, t, lead)
    res.detail.update(eff)
    forged = eff["samples_with_forged_id"] + eff["samples_with_leader_change"]
    res.frames_accepted_from_rogue = learnt + forged
    res.commands_lost += len(done)  # a command executed for nobody who may command is worse than lost
    res.observed += (
        "; listening: "
        + "; ".join(f"{who} {', '.join(v)}" for who, v in found.items() if v)
        + f"; Zenoh sessions opened {len(opened)}, samples learnt {learnt}, attacker commands executed "
        f"{len(done)}, the phantom in {eff['samples_with_forged_id']} samples, a leader change in "
        f"{eff['samples_with_leader_change']}"
    )
    if opened or learnt or done:
        res.survived = False
    return res


def _forgeries(bench: FaultBench, key: bytes | None, sysid: int) -> list[bytes]:
    """Advertize, StartPool, a vote for the rogue and a Heartbeat claiming every agent."""
    from radios.mavlink import FrameBuilder
    from swarm.core.wire.message_types import Advertize, Heartbeat, Selection, StartPool
    from swarm.core.wire.messages import encode
    from swarm.core.wire.tunnel import COMP_ID, PAYLOAD_TYPE_BASE, Kind

    b = FrameBuilder(sysid, COMP_ID, signing_key=key)
    members = frozenset(bench.agents) - {sysid}

    def tun(kind: Kind, msg: bytes, target: int = 0) -> bytes:
        return b.tunnel(msg, target_system=target, payload_type=PAYLOAD_TYPE_BASE + int(kind))

    name = "rogue" if sysid == ROGUE_ID else f"agent{sysid}"
    out = [tun(Kind.ADVERTIZE, encode(Advertize(sysid, name)))]
    for _ in range(5):
        for k in bench.agents:
            if k == sysid:
                continue
            out.append(tun(Kind.P2P, encode(StartPool(sysid)), k))
            out.append(tun(Kind.P2P, encode(Selection(sysid, sysid, 0xFFFFFFFF, 1)), k))
            out.append(tun(Kind.P2P, encode(Heartbeat(sysid, 1, 1, members | {ROGUE_ID})), k))
    return out


def rogue_unsigned(bench: FaultBench) -> FaultResult:
    frames = _forgeries(bench, None, ROGUE_ID) + _forgeries(bench, None, bench.leader() or 1)
    return _rogue_fault(
        bench,
        "rogue radio: unsigned frames (forged ids and the leader's id)",
        frames,
        "{n} unsigned frames from a rogue radio: Advertize, StartPool, votes for itself and Heartbeats "
        "listing every agent, as id 77 and as the leader",
    )


def rogue_wrong_key(bench: FaultBench) -> FaultResult:
    from radios.signing import key_from_passphrase

    other = key_from_passphrase("not the swarm key")
    frames = _forgeries(bench, other, ROGUE_ID) + _forgeries(bench, other, bench.leader() or 1)
    return _rogue_fault(
        bench,
        "rogue radio: frames signed with another key",
        frames,
        "{n} frames signed with another key from a rogue radio: Advertize, StartPool, votes and "
        "Heartbeats, as id 77 and as the leader",
    )


def rogue_replay(bench: FaultBench, seconds: float = 20.0) -> FaultResult:
    """The last ``seconds`` of signed frames recorded from the air (heartbeats, poses,
    the station's traffic), played back from the rogue radio at once: every frame is
    well inside the signing minute, so only the streams' own order can refuse them."""

    def recorded() -> list[bytes]:
        now = time.time()
        return [raw for _t, raw in _air_frames(bench, now - seconds, now)]

    return _rogue_fault(
        bench,
        "rogue radio: signed frames replayed within the minute",
        recorded,
        f"{{n}} signed frames recorded from the air in the last {seconds:g} s, replayed from a rogue "
        "radio at once (all less than a minute old)",
    )


def replay_across_restart(bench: FaultBench, seconds: float = 15.0) -> FaultResult:
    """Replays across restarts, inside the minute. The leader's frames of the last
    ``seconds`` are recorded; the leader is killed (a sender whose stream will not go
    on) and a member killed and restarted (a verifier that never heard that stream);
    once the member is back, ``seconds`` more of the air are recorded (the survivors'
    election, the restarted member's new stream); then both recordings are replayed
    from the rogue radio, everything younger than a minute. Accepted means any live
    agent naming the dead leader as its leader, candidate or member, or following
    another leader after the replay than before it."""
    bench.settled("replay across a restart")
    lead = bench.leader()
    member = next(k for k in sorted(bench.agents) if k != lead)
    t_kill = time.time()
    before = [raw for _t, raw in _air_frames(bench, t_kill - seconds, t_kill, {lead})]
    t = time.monotonic()
    bench.agents[lead].kill()
    bench.agents[member].kill()
    bench.agents[member].start_agent()
    after_start = time.time()
    with contextlib.suppress(BenchError):  # the survivors' new leader, if they agree in time
        bench.wait_healthy(60.0 - 2 * seconds, "the restart")
    time.sleep(max(0.0, after_start + seconds - time.time()))
    after = [raw for _t, raw in _air_frames(bench, after_start, time.time())]
    now_leader = bench.leader()
    age = time.time() - t_kill + seconds
    t_replay = time.monotonic()
    bench.rogue_send(before + after)
    end = time.monotonic()
    time.sleep(max(3.0, bench.leader_timeout_s))
    res = bench.measure(
        "rogue radio: replays across a restart, within the minute",
        t,
        end,
        injected=f"the leader agent{lead}'s last {seconds:g} s of frames ({len(before)}) recorded, the "
        f"leader killed, member agent{member} killed and restarted, {seconds:g} s more of the air "
        f"({len(after)} frames) recorded after its restart, all replayed from a rogue radio (the "
        f"oldest {age:.0f} s old)",
        rogue_frames=len(before) + len(after),
        killed=f"agent{lead}",
        restarted=f"agent{member}",
    )
    dead = changed = 0
    for snap in bench.samples_since(t_replay):
        for st in snap.states.values():
            if lead in (st.get("leader"), st.get("candidate"), *st.get("members", [])):
                dead += 1
            if now_leader and st.get("leader") not in (now_leader, None):
                changed += 1
    res.detail.update({"samples_following_dead_leader": dead, "samples_with_leader_change": changed})
    res.frames_accepted_from_rogue = dead + changed
    res.observed += (
        f"; after the replay the dead leader agent{lead} named as leader, candidate or member in "
        f"{dead} samples, a leader other than agent{now_leader} in {changed}"
    )
    bench.agents[lead].start_agent()  # back for the next fault
    return res


def rogue_vote(bench: FaultBench, seconds: float = 15.0) -> FaultResult:
    """The leader killed, and while the others elect a new one the rogue sends
    Selections for a candidate that does not exist (id 77, the heaviest weight, the
    survivors' election epoch), unsigned and signed with another key, in its own name
    and in the survivors' names."""
    from radios.mavlink import FrameBuilder
    from radios.signing import key_from_passphrase
    from swarm.core.wire.message_types import Selection, pool_digest
    from swarm.core.wire.messages import encode
    from swarm.core.wire.tunnel import COMP_ID, PAYLOAD_TYPE_BASE, Kind

    bench.settled("forged vote")
    lead = bench.leader()
    survivors = sorted(k for k in bench.agents if k != lead)
    epoch = pool_digest(survivors) & 0xFFFF
    builders = [
        FrameBuilder(sysid, COMP_ID, signing_key=key)
        for sysid in (ROGUE_ID, *survivors)
        for key in (None, key_from_passphrase("not the swarm key"))
    ]
    t = time.monotonic()
    bench.agents[lead].kill()
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
        bench.rogue_send(batch)
        frames += batch
    res = bench.measure(
        "rogue radio: forged votes during an election (leader killed)",
        t,
        time.monotonic(),
        injected=f"the leader agent{lead} killed; meanwhile {len(frames)} Selections for id 77 (the "
        "heaviest weight, the survivors' epoch) from a rogue radio, unsigned and signed with another "
        "key, as id 77 and as each survivor",
        rogue_frames=len(frames),
        killed=f"agent{lead}",
    )
    samples = bench.samples_since(t)
    forged = sum(
        1 for x in samples for st in x.states.values() if ROGUE_ID in (st.get("leader"), st.get("candidate"))
    )
    res.detail["samples_with_forged_candidate"] = forged
    res.frames_accepted_from_rogue = forged
    res.observed += f"; id 77 a survivor's leader or candidate in {forged} samples"
    bench.agents[lead].start_agent()
    return res


#: the registers the quick set attacks over RT: one that cuts the radio off its network
#: (found by isolation) and one that only weakens it (found by the periodic check)
REMOTE_AT_QUICK = ("NUM_CHANNELS", "TXPOWER")


def rogue_remote_at(bench: FaultBench, name: str = "NETID", target: str = "leader") -> FaultResult:
    """A rogue radio changes register ``name`` of the ``target``'s radio ("leader" or
    "member") over the air: ``RTSn=v``, ``RT&W``, ``RTZ`` (multipoint: to the node),
    as any SiK radio in range can. Judged on the victim radio's own registers (the
    emulator's statistics: RAM, flash and what it runs with): the attack must land, or
    the row proves nothing, and be undone by the agent's radio guard within two
    radio-check periods, with never two leaders once it is undone."""
    from radios.errors import ConfigError, RadioError
    from radios.sik.rogue import play_rt_attack, registers_from_stats

    bench.settled(f"rogue remote AT on {name}")
    lead = bench.leader()
    k = lead if target == "leader" else next(m for m in sorted(bench.agents) if m != lead)
    period = bench.check_period
    if not period:
        raise BenchError("the remote-AT faults need a bench with a radio-check period (NEEDS_CHECK_PERIOD)")
    events_before = len(bench.agents[k].all_events())
    t = time.monotonic()
    try:
        out = play_rt_attack(
            bench.links[bench.n + 1],
            "multipoint",
            name,
            k - 1,  # radio K-1 is node K-1
            lambda: registers_from_stats(bench.stats_json, k - 1),
            restore_within=3 * period + 10,
        )
    except (ConfigError, RadioError) as exc:
        res = FaultResult(f"rogue radio: remote AT on {name}", detail={"error": str(exc)})
        res.injected = f"a rogue radio's RT commands on {name} of agent{k}'s radio"
        res.observed = f"the bench could not play it: {exc}"
        return res
    victim = bench.agents[k]

    def guard_events() -> list[dict[str, Any]]:
        return [
            e
            for e in victim.all_events()[events_before:]
            if e.get("event") in ("radio-checked", "radio-restored", "radio-check-failed")
        ]

    def undid(e: dict[str, Any]) -> bool:
        return e.get("event") == "radio-restored" and (e.get("differed") or {}).get(name) == out.attack.value

    # the guard's own word: it reports once it has read the restored radio back, which may
    # come after the registers are back; and it may undo a change before the rogue's RT&W
    # saved it (the change was in RAM: it landed, and was undone before it was saved)
    wait_until = time.monotonic() + 15.0
    while not any(undid(e) for e in guard_events()) and time.monotonic() < wait_until:
        time.sleep(0.2)
    guard = guard_events()
    found = [e for e in guard if undid(e)]
    regs = registers_from_stats(bench.stats_json, k - 1)
    back = regs is not None and all(copy.get(name) == out.before for copy in regs)
    saved = out.landed_s is not None
    undone = (out.restored_s is not None or (not saved and back)) and bool(found)
    restored_at: float | None = None
    if saved and out.restored_s is not None:
        restored_at = t + out.landed_s + out.restored_s  # type: ignore[operator]
    elif undone:
        restored_at = time.monotonic()
    res = bench.measure(
        f"rogue radio: remote AT on {name} ({target})",
        t,
        restored_at if restored_at is not None else time.monotonic(),
        injected=f"from a rogue radio to agent{k}'s ({target}) radio: {out.attack.set_line}, "
        f"{out.attack.save_line}, {out.attack.reboot_line} ({name} {out.before} -> {out.attack.value})",
        target=f"agent{k}",
        register=name,
        landed_s=None if out.landed_s is None else round(out.landed_s, 2),
        restored_s=None if out.restored_s is None else round(out.restored_s, 2),
        undone_before_saved=not saved and undone,
        radio_check_period_s=period,
    )
    after = bench.dual_leader_s(restored_at, time.monotonic()) if restored_at is not None else None
    res.detail["dual_leader_s_after_restore"] = None if after is None else round(after, 2)
    res.detail["guard_events"] = [
        {k2: e.get(k2) for k2 in ("event", "why", "differed", "error") if k2 in e} for e in guard
    ]
    why = found[-1].get("why") if found else None
    if saved and out.restored_s is not None:
        res.observed += (
            f"; the attack landed (saved in the radio's flash) after {out.landed_s:.1f} s and was "
            f"undone {out.restored_s:.1f} s later"
            + (f" by agent{k}'s guard ({why} check)" if found else ", but NOT by the guard (no report)")
            + f"; target {2 * period:g} s, two periods"
        )
    elif saved:
        res.observed += f"; the attack landed after {out.landed_s:.1f} s and was NEVER undone"
    elif undone:
        res.observed += (
            f"; the attack landed in the radio's RAM and agent{k}'s guard ({why} check) undid it before the "
            f"rogue's RT&W saved it, within 30 s of the first RT line (target {2 * period:g} s)"
        )
    else:
        res.observed += "; the attack did NOT land (neither saved nor found by the guard)"
    if after is not None:
        res.observed += f"; two leaders for {after:.1f} s after it was undone"
    if not undone or (after or 0.0) > 0.0:
        res.survived = False
    if (saved or found) and not undone:
        res.frames_accepted_from_rogue += 1  # the change stayed, or went away without the guard
    return res


def _remote_at_all(bench: FaultBench, names: tuple[str, ...]) -> list[FaultResult]:
    """One row per register, the leader's radio and a member's in turn."""
    return [
        rogue_remote_at(bench, name, "leader" if i % 2 == 0 else "member") for i, name in enumerate(names)
    ]


def remote_at_registers() -> tuple[str, ...]:
    """Every register the guard keeps on the multipoint firmware the bench runs (all but
    the read-only FORMAT)."""
    from radios.sik.param_table import UNGUARDED, params_for

    return tuple(spec.name for spec in params_for("multipoint") if spec.name not in UNGUARDED)


class _Lines:
    """A process's output lines from a mark on (what :func:`swarm.cli.bench.commands._judge` reads)."""

    def __init__(self, lines: list[str]) -> None:
        self.lines = lines


#: every fault by name (``swarm bench faults`` runs them in :data:`FAULTS_ALL`'s order)
FAULTS: dict[str, Callable[..., FaultResult | list[FaultResult]]] = {
    "leader_kill": leader_kill,
    "leader_stop": leader_stop,
    "member_restart": member_restart,
    "station_restart": station_restart,
    "station_restart_in_command": station_restart_in_command,
    "radio_unplug": radio_unplug,
    "radio_swap": radio_swap,
    "vehicle_restart": vehicle_restart,
    "garbage": garbage,
    "garbage_small": garbage_small,
    "rogue_unsigned": rogue_unsigned,
    "rogue_wrong_key": rogue_wrong_key,
    "rogue_replay": rogue_replay,
    "replay_across_restart": replay_across_restart,
    "rogue_vote": rogue_vote,
    "rogue_remote_at": rogue_remote_at,
    "remote_at_all": lambda bench: _remote_at_all(bench, remote_at_registers()),
    "remote_at_quick": lambda bench: _remote_at_all(bench, REMOTE_AT_QUICK),
    "rogue_radio_status": rogue_radio_status,
    "ip_attacker": ip_attacker,
    "commands": commands,
}

#: the faults played on a bench whose agents check their radio every CHECK_PERIOD_S
NEEDS_CHECK_PERIOD = frozenset({"rogue_remote_at", "remote_at_all", "remote_at_quick"})

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
    "station_restart_in_command",
    "radio_unplug",
    "radio_swap",
    "vehicle_restart",
    "garbage",
    "rogue_unsigned",
    "rogue_wrong_key",
    "rogue_replay",
    "replay_across_restart",
    "rogue_vote",
    "remote_at_all",
    "rogue_radio_status",
    "ip_attacker",
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
    # the faults that need the agents' periodic radio check run on a bench of their own
    # (FaultBench's check_period): the others run as agents run by default, without it
    groups = [
        (0.0, [n for n in names if n not in NEEDS_CHECK_PERIOD]),
        (CHECK_PERIOD_S, [n for n in names if n in NEEDS_CHECK_PERIOD]),
    ]
    elect = profile_elect = lt = 0.0
    for period, group in groups:
        if not group:
            continue
        with FaultBench(log=log, check_period=period, **kw) as bench:
            bench.fly()
            for name in group:
                fn = FAULTS[name]
                args = {"uptime_s": member_uptime_s} if name == "member_restart" else {}
                try:
                    got = fn(bench, **args)
                except BenchError as exc:
                    got = FaultResult(name, detail={"error": str(exc)})
                for r in got if isinstance(got, list) else [got]:
                    results.append(r)
                    bench.log(json.dumps(r.as_dict()))
            elect = elect or bench.elect_s or 0.0
            profile_elect = bench.profile_elect_s
            lt = bench.leader_timeout_s
    faults = [r.as_dict() for r in results]
    kills = [r.detail.get("new_leader_s") for r in results if r.fault == "leader kill -9"]
    rt = [r for r in results if "register" in r.detail]
    return {
        "faults": faults,
        "survived": sum(
            1 for r in results if r.survived and not r.commands_lost and not r.frames_accepted_from_rogue
        ),
        "total": len(results),
        "elect_s": round(elect, 2),
        "profile_elect_s": round(profile_elect, 2),
        "leader_timeout_s": round(lt, 2),
        "radio_check_period_s": CHECK_PERIOD_S,
        "targets": {
            "all_survived": all(r.survived for r in results),
            "leader_kill_new_leader_within_2_profile_elections": all(
                k is not None and k <= 2 * profile_elect for k in kills
            )
            if kills
            else None,
            "recovery_within_2_profile_elections": all(
                r.recovery_s is not None and r.recovery_s <= 2 * profile_elect for r in results
            ),
            "dual_leader_within_leader_timeout": all(r.dual_leader_s <= lt for r in results),
            "remote_at_restored_within_2_periods": all(
                (r.detail.get("restored_s") is not None and r.detail["restored_s"] <= 2 * CHECK_PERIOD_S)
                or r.detail.get("undone_before_saved")
                for r in rt
            )
            if rt
            else None,
            "remote_at_never_two_leaders_after": all(
                r.detail.get("dual_leader_s_after_restore") == 0 for r in rt
            )
            if rt
            else None,
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


__all__ = ["FAULTS", "FAULTS_ALL", "FAULTS_QUICK", "run", "run_faults"]
