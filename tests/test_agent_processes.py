"""The issue's real-time test: five ``swarm agent`` processes on the emulated radios
(multipoint, 64 kbit/s) elect one leader; all five report it on stdout and on
``swarm/<name>/state``, as a sixth radio node (an observer: an isolated Zenoh
session and a radio bridge, id 99) sees through the air. Then the leader crashes
(SIGKILL) and the survivors agree on a new one; SIGTERM stops the rest with exit 0.

Nothing sleeps to hope: every wait polls for an outcome until a generous deadline.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from net_helpers import wait_until

from radios.link import open_link
from swarm.cli.procs import Child, start_emulator
from swarm.core.wire.message_types import AgentState, Phase
from swarm.runtime.bridge.radio_bridge import RadioBridge
from swarm.runtime.keyspace.transport import Transport, open_session

# timing: survivors exit within 2 s of SIGTERM
pytestmark = [pytest.mark.processes, pytest.mark.timing]  # five agent processes on emulated radios

N = 5
ELECT_DEADLINE = 90.0  # radios' hop lock plus three 2 s windows: ~8 s seen; bounds a failure
FAILOVER_DEADLINE = 60.0  # ack/leader timeout (3 s) plus one election
EXIT_DEADLINE = 2.0  # the CLI promise for SIGTERM
SETTLED = ("LEADER", "MEMBER")


def last_state(child: Child) -> dict[str, Any] | None:
    for line in reversed(list(child.lines)):
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        if obj.get("event") == "state":
            return dict(obj)
    return None


def stdout_leader(children: list[Child]) -> int | None:
    states = [last_state(c) for c in children]
    if any(s is None or s["phase"] not in SETTLED for s in states):
        return None
    leaders = {s["leader"] for s in states if s is not None}
    if len(leaders) != 1:
        return None
    lead = leaders.pop()
    # exactly one of them says LEADER, and it is the one all follow
    if [s["id"] for s in states if s is not None and s["phase"] == "LEADER"] != [lead]:
        return None
    return int(lead)


def test_five_agent_processes_elect_fail_over_and_stop(tmp_path: Path) -> None:
    emu, paths = start_emulator(N + 1, tmp_path)  # radio5: the observer
    children: list[Child] = []
    closers: list[Callable[[], object]] = []
    seen: dict[str, AgentState] = {}
    lock = threading.Lock()

    def observe(name: str, st: AgentState) -> None:
        with lock:
            seen[name] = st

    def keyspace_leader(names: list[str]) -> int | None:
        with lock:
            if any(n not in seen for n in names):
                return None
            st = [seen[n] for n in names]
        leaders = {s.leader for s in st}
        if len(leaders) != 1 or any(s.phase not in (Phase.LEADER, Phase.MEMBER) for s in st):
            return None
        return leaders.pop()

    try:
        link = open_link(paths[N])
        closers.append(link.close)
        session = open_session()  # isolated: only the radio
        closers.append(session.close)
        bridge = RadioBridge(session, link, name="observer", agent_id=99).start()
        closers.insert(0, bridge.close)
        observer = Transport("observer", session)
        closers.insert(0, observer.close)
        observer.on_state("*", observe)

        t_spawn = time.monotonic()
        for k in range(1, N + 1):
            children.append(
                Child(
                    ["agent", "--name", f"agent{k}", "--id", str(k), "--radio", paths[k - 1], "--json"],
                    name=f"agent{k}",
                )
            )
        for c in children:
            ready = json.loads(c.wait_lines(1, 30)[0])
            assert ready["event"] == "ready" and ready["name"] == c.name
        t_ready = time.monotonic()

        leader = wait_until(
            lambda: stdout_leader(children),
            "five agents to agree on a leader",
            ELECT_DEADLINE,
            children=children,
        )
        t_elected = time.monotonic()
        names = [c.name for c in children]
        assert (
            wait_until(
                lambda: keyspace_leader(names),
                "swarm/<name>/state of all five on the air",
                ELECT_DEADLINE,
                children=children,
            )
            == leader
        )
        with lock:
            lead_state = seen[f"agent{leader}"]
        assert lead_state.phase == Phase.LEADER
        assert lead_state.members == frozenset(range(1, N + 1)) - {leader}
        print(
            f"\nelected agent{leader}: {t_elected - t_ready:.2f} s after all were ready "
            f"({t_elected - t_spawn:.2f} s after spawning)"
        )

        # the leader crashes: the survivors elect another
        gone = children[leader - 1]
        gone.proc.send_signal(signal.SIGKILL)
        gone.proc.wait(5)
        t_crash = time.monotonic()
        survivors = [c for c in children if c is not gone]

        def new_leader() -> int | None:
            lead = stdout_leader(survivors)
            if lead is None or lead == leader:
                return None
            s = last_state(children[lead - 1])
            others = {int(c.name[5:]) for c in survivors} - {lead}
            return lead if s is not None and set(s["members"]) == others else None

        leader2 = wait_until(
            new_leader, "the survivors to agree on a new leader", FAILOVER_DEADLINE, children=survivors
        )
        print(f"agent{leader} killed: agent{leader2} leads {time.monotonic() - t_crash:.2f} s later")
        assert wait_until(
            lambda: keyspace_leader([c.name for c in survivors]) == leader2,
            "the new leader on swarm/<name>/state",
            FAILOVER_DEADLINE,
            children=survivors,
        )

        # SIGTERM: every survivor exits 0, promptly
        t_term = time.monotonic()
        for c in survivors:
            c.proc.send_signal(signal.SIGTERM)
        slowest = 0.0
        for c in survivors:
            c.proc.wait(10)
            slowest = max(slowest, time.monotonic() - t_term)
            assert c.proc.returncode == 0, f"{c.name}: exit {c.proc.returncode}: {c.errors[-5:]}"
            assert not [e for e in c.errors if "Traceback" in e], c.errors
        print(f"all survivors exited 0 within {slowest:.2f} s of SIGTERM")
        assert slowest < EXIT_DEADLINE
    finally:
        for c in children:
            c.stop(grace=3)
        for close in closers:
            try:
                close()
            except Exception:
                pass
        emu.stop()
