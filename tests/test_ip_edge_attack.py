"""Issue 27, "nothing listens where nobody asked": an attacker on every socket of a
running swarm on radios.

Real processes: ``swarm radio-emu`` (three radios), ``swarm sim`` (one vehicle on a
pseudo terminal, so the agent's flight controller is no socket), two signed ``swarm
agent`` processes (agent1 flying the vehicle) and a signed ``swarm gcs``, all on the
emulated radios. Once the station has both agents connected, every socket each
process listens on is found from the process itself (``/proc/PID/fd`` against
``/proc/PID/net/*``: :func:`swarm.cli.bench.ip_attack.listeners`) and attacked: a Zenoh
session connecting there (plain and TLS without a certificate) subscribes to
everything and publishes a station's ARM and TAKEOFF to both agents (on their inboxes
and command keys), a phantom leader's Advertize and Heartbeats, and queries the
stations' command queryables. Then: nothing executed (no command in the agents' own
lines, the vehicle not armed as the station reports it), no phantom leader followed,
nothing learnt (no sample, no reply); and the only socket left is the station's HTTP
port (which has its own security, tested elsewhere).

Before the fix every radio node's Zenoh session also listened on every address on a
random port: the attacker's ARM reached agent1 (and, through its signed radio bridge,
agent2) and was carried out.
"""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from swarm.cli.bench.ip_attack import PHANTOM_ID, attack, describe, executed, listeners
from swarm.cli.commands.keygen import write_key
from swarm.cli.procs import Child, json_events, start_emulator

pytestmark = pytest.mark.processes  # an emulator, a vehicle, two agents and a station

DEADLINE = 90.0
AGENTS = {"agent1": 1, "agent2": 2}


def api(url: str, path: str) -> Any:
    with urllib.request.urlopen(url + path, timeout=30) as r:
        return json.loads(r.read())


def agent_events(child: Child, event: str) -> list[dict[str, Any]]:
    return json_events(child.lines, event)


@pytest.mark.timeout(300)
def test_an_ip_attacker_on_every_listener_executes_and_learns_nothing(tmp_path: Path) -> None:
    key = tmp_path / "swarm.key"
    write_key(str(key))
    emu, radios = start_emulator(3, tmp_path)
    children: list[Child] = [emu]
    try:
        sim = Child(["sim", "--vehicles", "1", "--serial", "pty"], name="sim")
        children.append(sim)
        tty = sim.wait_lines(1, DEADLINE)[0].split(" -> ")[1].split()[0]
        signed = ["--key", str(key), "--json"]
        a1 = Child(
            ["agent", "--name", "agent1", "--id", "1", "--radio", radios[0], "--fc", tty, *signed],
            name="agent1",
        )
        a2 = Child(["agent", "--name", "agent2", "--id", "2", "--radio", radios[1], *signed], name="agent2")
        http = free_port()
        gcs = Child(
            ["gcs", "--radio", radios[2], "--http", f"127.0.0.1:{http}", "--tiles", "none", *signed],
            name="gcs",
        )
        children += [a1, a2, gcs]
        url = f"http://127.0.0.1:{http}/"
        ready = wait_until(
            lambda: json_events(gcs.lines, "ready"), "the station ready", DEADLINE, children=children
        )
        assert ready[0]["url"] == url

        def connected() -> set[int]:
            return {a["id"] for a in api(url, "api/state")["agents"] if a["connected"]}

        wait_until(lambda: connected() == {1, 2}, "both agents connected", DEADLINE, children=children)
        wait_until(
            lambda: api(url, "api/agents/1")["home_alt"] is not None,
            "agent1's vehicle seen",
            DEADLINE,
            children=children,
        )
        pids = {"agent1": a1.proc.pid, "agent2": a2.proc.pid, "gcs": gcs.proc.pid}
        found = {name: listeners(pid) for name, pid in pids.items()}
        reports = [attack(lst, AGENTS) for name in pids for lst in found[name]]

        # nothing executed: no command reached either agent's pilot, the vehicle stays
        # disarmed, no agent follows or lists the phantom leader
        wait_until(lambda: len(api(url, "api/state")["agents"]) == 2, "the station's view", 10)
        commands = [e["text"] for c in (a1, a2) for e in agent_events(c, "pilot") if "command" in e["text"]]
        assert executed(e for c in (a1, a2) for e in agent_events(c, "pilot")) == commands
        assert commands == [], f"the attacker's commands were carried out: {commands}"
        assert api(url, "api/agents/1")["armed"] is False
        phantom = [
            s for c in (a1, a2) for s in agent_events(c, "state")
            if s["leader"] == PHANTOM_ID or PHANTOM_ID in s["members"] or PHANTOM_ID in s["pool"]
        ]  # fmt: skip
        assert phantom == [], f"a phantom leader was followed: {phantom[:3]}"
        # nothing learnt
        assert [r.as_dict() for r in reports if r.received] == []
        # the only listener left is the station's HTTP port, which the user asked for
        assert found["agent1"] == [] and found["agent2"] == [], {n: describe(v) for n, v in found.items()}
        assert describe(found["gcs"]) == [f"tcp 127.0.0.1:{http}"]
        for c in (a1, a2, gcs):
            assert c.proc.poll() is None, f"{c.name} died: {c.errors[-3:]}"
    finally:
        for c in reversed(children):
            c.stop(grace=5)
