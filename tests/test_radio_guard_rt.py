"""Every register a rogue radio can change over RT is guarded (radios.sik.guard).

The attacks are real: a third radio of a running emulator (real ptys), the rogue,
puts itself in command mode and sends ``RTSn=v``, ``RT&W`` and ``RTZ`` to a victim
radio (multipoint: ``,<node>``), as any radio in range can. Each test first reads
the victim (the emulator's own copy of its registers) to prove the attack landed,
then lets the guard find and undo it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from emu_helpers import running_emulator
from net_helpers import wait_until

from radios.sik.config import SikConfigurator, open_port
from radios.sik.rogue import Attack, landed, plan_attack, send_attack
from swarm.cli.procs import Child, json_events

pytestmark = pytest.mark.processes  # radios emulated in real time, agents

# the agents' deadlines: generous, for a loaded machine
AGENT_DEADLINE = 120.0


def _rogue(path: str, attack: Attack) -> bool:
    """The rogue's host: command mode on its own radio, the attack, back to data mode."""
    port = open_port(path)
    try:
        conf = SikConfigurator(port, flavour="multipoint", port_name="rogue")
        conf.enter_command_mode()
        ok = send_attack(conf, attack)
        conf.exit_command_mode()
        return ok
    finally:
        port.close()


def _agent(path: str, name: str, ident: int, *extra: str) -> Child:
    return Child(
        ["agent", "--name", name, "--id", str(ident), "--radio", path, "--slots", "3", "--json", *extra],
        name=name,
    )


def _leaders(agents: list[Child]) -> list[int]:
    """Each agent's leader in its last state line (0: none yet)."""
    out = []
    for child in agents:
        states = json_events(child.lines, "state")
        out.append(int(states[-1]["leader"]) if states else 0)
    return out


def _one_leader(agents: list[Child]) -> bool:
    leaders = _leaders(agents)
    return leaders[0] != 0 and len(set(leaders)) == 1


def _events(child: Child, kind: str) -> list[dict[str, Any]]:
    return json_events(child.lines, kind)


def test_rogue_moves_a_members_radio_to_other_channels_and_the_guard_puts_it_back(tmp_path: Path) -> None:
    """The known hole: NUM_CHANNELS, which the swarm's --radio-params line does not
    name. The member's radio hops on 20 channels instead of 50 and hears no one; its
    agent re-checks the radio (isolated) and must restore it, and the swarm must end
    with one leader."""
    with running_emulator(tmp_path, 3, firmware="multipoint") as emu:
        emu.wait_locked(0, 1, 2)
        guard = ["--radio-params", "NETID=25,AIR_SPEED=64", "--restore-radio", "--radio-recheck", "8"]
        agents = [_agent(emu.paths[0], "a1", 1, *guard), _agent(emu.paths[1], "a2", 2, *guard)]
        try:
            wait_until(lambda: _one_leader(agents), "one leader before the attack", AGENT_DEADLINE, children=agents)
            victim = emu.emu.params[1]
            attack = plan_attack("multipoint", "NUM_CHANNELS", victim.as_dict(), node=1)
            _rogue(emu.paths[2], attack)
            # the attack landed: in flash, and the radio runs with it
            assert attack.value == 20
            wait_until(
                lambda: victim.eeprom[10] == 20 and victim.active[10] == 20, "the attack landed", 30.0
            )
            restored = wait_until(
                lambda: _events(agents[1], "radio-restored"),
                "the member's guard restores its radio",
                AGENT_DEADLINE,
                children=agents,
                detail=lambda: _events(agents[1], "radio-checked"),
            )
            assert restored[0]["differed"] == {"NUM_CHANNELS": 20}
            assert (victim.eeprom[10], victim.active[10]) == (50, 50)
            wait_until(lambda: _one_leader(agents), "one leader after the restore", AGENT_DEADLINE, children=agents)
        finally:
            for a in agents:
                a.stop()
