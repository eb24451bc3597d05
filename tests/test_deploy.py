"""The README's "Deploy on a companion computer" section, run here as far as it can be.

What cannot run here is the hardware (a Pi's UART, a real SiK radio, a Pixhawk) and
root's steps (a user, files under /etc, systemctl). What can is the flow itself, in
its order: ``swarm keygen``, ``swarm radio-config --network --write-params`` on an
emulated radio, the README's own agent settings (its ``toml`` block, read from the
README, with the device names, the state folder and the radio count of this bench
put in), ``swarm doctor --config`` passing on that set-up, and ``swarm agent
--config`` starting from it, advertising and keeping its flight log where the file
says. A README example that named a key no agent has, or a value the agent refuses,
fails here.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from firmware_bridge.sim import SimConfig, VehicleSim
from radios.signing import load_key, signature
from radios.tlog import read_tlog
from swarm.cli.commands.agent import build_parser
from swarm.cli.configfile import file_values, keys, prepare
from swarm.cli.procs import Child, start_emulator

# the README's section, moved to the docs site
README = Path(__file__).resolve().parent.parent / "docs" / "deployment.md"


def _section() -> str:
    text = README.read_text(encoding="utf-8")
    start = text.index("# Deploy on a companion computer")
    return text[start : text.index("\n## Config files", start)]


def _readme_agent_settings() -> dict[str, Any]:
    blocks = re.findall(r"```toml\n(.*?)```", _section(), re.S)
    assert len(blocks) == 1, "the deployment section shows one agent settings file"
    return tomllib.loads(blocks[0])


def _swarm(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "swarm.cli", *args], capture_output=True, text=True, timeout=timeout
    )


def test_the_readme_agent_settings_are_all_agent_keys_of_the_right_types(tmp_path: Path) -> None:
    table = _readme_agent_settings()
    p = prepare(build_parser())
    known = keys(p)
    assert set(table) <= set(known), set(table) - set(known)
    values = file_values(p, str(tmp_path / "agent1.toml"), table)  # raises for a wrong type
    assert values["fc"][1] == "/dev/ttyAMA0?baud=921600"
    # paths the file names are beside it; the capture folder is the service's state folder
    assert values["key"][1] == str(tmp_path / "swarm.key")
    assert values["capture"][1] == "/var/lib/uav-swarm/flights"


@pytest.mark.processes
def test_the_deployment_flow_runs_on_the_bench(tmp_path: Path) -> None:
    etc, state = tmp_path / "etc", tmp_path / "state"
    etc.mkdir()
    state.mkdir()
    done = _swarm("keygen", str(etc / "swarm.key"))
    assert done.returncode == 0, done.stderr
    (tmp_path / "radios").mkdir()
    emu, radios = start_emulator(2, tmp_path / "radios")
    sim = VehicleSim(SimConfig(vehicles=1, profile="px4", seed=0, base_port=free_port("udp")))
    (fc,) = sim.start()
    agent: Child | None = None
    try:
        # a standard pair: the radio of aircraft 1 is node 1 of 2
        done = _swarm(
            "radio-config", radios[0], "--network", "2", "--node", "1", "--netid", "30",
            "--write-params", str(etc / "radio.toml"),
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        settings = _readme_agent_settings()
        settings.update(radio=radios[0], fc=fc, capture=str(state / "flights"), slots=2)
        settings["json"] = True
        conf = etc / "agent1.toml"
        conf.write_text("".join(f"{k} = {json.dumps(v)}\n" for k, v in settings.items()))

        done = _swarm("doctor", "--config", str(conf), "--json")
        report = json.loads(done.stdout)
        failed = [c for c in report["checks"] if c["status"] == "fail"]
        assert done.returncode == 0 and report["ok"] and not failed, failed or done.stderr
        names = {c["name"] for c in report["checks"]}
        assert {"radio NETID", "key mode", "clock", "disk"} <= names, names

        agent = Child(["agent", "--config", str(conf)], name="agent1")
        ready = json.loads(agent.wait_lines(1, 60)[0])
        assert ready["event"] == "ready" and ready["name"] == "agent1", ready
        flights = state / "flights"
        wait_until(
            lambda: any(p.stat().st_size > 0 for p in flights.glob("agent1-*.tlog")),
            "the agent's flight log in the folder its settings name",
            60,
            0.2,
            children=[agent],
        )
        agent.stop(grace=10)
        assert agent.proc.returncode == 0, agent.errors[-5:]
        agent = None
        shown = _swarm("replay", str(flights), "--json")
        assert shown.returncode == 0, shown.stderr
        frames = [json.loads(line) for line in shown.stdout.splitlines()]
        # what it put on the air: its advertisements, in TUNNEL frames signed with the key
        assert any(f["msg"] == "TUNNEL" and f["sysid"] == 1 for f in frames), frames[:3]
        key = load_key(etc / "swarm.key")
        own = 0
        for path in sorted(flights.glob("agent1-*[0-9].tlog")):
            with read_tlog(path) as records:
                for rec in records:
                    if rec.frame.sysid == 1 and rec.frame.name == "TUNNEL":
                        f = rec.frame
                        assert f.signed and signature(key, f.raw[:-6]) == f.raw[-6:]
                        own += 1
        assert own > 0
    finally:
        if agent is not None:
            agent.stop(grace=5)
        sim.stop()
        emu.stop()
