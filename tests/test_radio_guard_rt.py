"""Every register a rogue radio can change over RT is guarded (radios.sik.guard).

The attacks are real: a third radio of a running emulator (real ptys), the rogue,
puts itself in command mode and sends ``RTSn=v``, ``RT&W`` and ``RTZ`` to a victim
radio (multipoint: ``,<node>``), as any radio in range can. Each test first reads
the victim (the emulator's own copy of its registers) to prove the attack landed,
then lets the guard find and undo it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from emu_helpers import RunningEmulator, running_emulator
from net_helpers import wait_until

from radios.emulator_config import radio_config_of
from radios.sik.config import SikConfigurator, open_port
from radios.sik.guard import UNGUARDED, Known, baseline, check_radio, known_of
from radios.sik.param_table import params_for
from radios.sik.params import SikParams
from radios.sik.rogue import Attack, landed, plan_attack, play_rt_attack, send_line, send_reboot
from swarm.cli.procs import Child, json_events

pytestmark = pytest.mark.processes  # radios emulated in real time, agents

# the agents' deadlines: generous, for a loaded machine
AGENT_DEADLINE = 120.0


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


def _attack_and_wait(
    emu: RunningEmulator, agents: list[Child], k: int, name: str, value: int
) -> dict[str, Any]:
    """The rogue changes register ``name`` of agent ``k``'s radio (node k-1) to ``value``
    (:func:`play_rt_attack`, as the fault bench plays it): it must land (saved in its
    flash), be undone (back, saved and running), and the agent say so in its
    ``radio-restored`` event."""
    victim = emu.emu.params[k - 1]
    before = len(_events(agents[k - 1], "radio-restored"))

    def registers() -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
        return victim.as_dict(), _named(victim, victim.eeprom), _named(victim, victim.active)

    outcome = play_rt_attack(
        emu.paths[2], "multipoint", name, k - 1, registers, restore_within=AGENT_DEADLINE
    )
    print(f"agent {k}: {outcome.describe()}")  # the figures, with pytest -s
    assert outcome.attack.value == value
    assert outcome.landed_s is not None, outcome.describe()
    assert outcome.restored_s is not None, (
        f"{outcome.describe()}: {_events(agents[k - 1], 'radio-checked')[-3:]}"
    )
    restored = wait_until(
        lambda: _events(agents[k - 1], "radio-restored")[before:],
        f"agent {k}'s radio-restored event",
        10.0,
        children=agents,
    )
    assert restored[0]["differed"] == {name: value}
    return dict(restored[0])


def test_rogue_attacks_on_two_agents_radios_are_undone_and_the_swarm_keeps_one_leader(tmp_path: Path) -> None:
    """Two agents on a multipoint network, a rogue on the third radio, every guard
    given only NETID (the rest from the radio at the start check).

    1. The known hole: NUM_CHANNELS of the member's radio (20 channels instead of 50).
       The member hears no one; its guard (re-check when isolated, or the period)
       must find it and restore it, and the swarm end with one leader.
    2. TXPOWER of the leader's radio (1 dBm): the radio still hears everyone, so no
       isolation shows it; the periodic check must find it and restore it.
    """
    period = 15.0
    with running_emulator(tmp_path, 3, firmware="multipoint") as emu:
        emu.wait_locked(0, 1, 2)
        guard = ["--radio-params", "NETID=25", "--restore-radio", "--radio-recheck", "8"]
        guard += ["--radio-check-period", f"{period:g}"]
        agents = [_agent(emu.paths[0], "a1", 1, *guard), _agent(emu.paths[1], "a2", 2, *guard)]
        try:
            wait_until(
                lambda: _one_leader(agents), "one leader before the attack", AGENT_DEADLINE, children=agents
            )
            member = 2 if _leaders(agents)[0] == 1 else 1
            restored = _attack_and_wait(emu, agents, member, "NUM_CHANNELS", 20)
            wait_until(lambda: _one_leader(agents), "one leader after it", AGENT_DEADLINE, children=agents)
            restored = _attack_and_wait(emu, agents, 3 - member, "TXPOWER", 1)
            assert restored["why"] == "period"  # nothing isolated it: only the period finds it
            wait_until(lambda: _one_leader(agents), "one leader after it", AGENT_DEADLINE, children=agents)
        finally:
            for a in agents:
                a.stop()


# -- every register, on the emulator, without agents ---------------------------------

#: what the guard is given, as an agent's --radio-params; the rest comes from the radio
GIVEN = {"NETID": 25}


def _guard_table(path: str) -> tuple[dict[str, int], Known]:
    """The agent's start check: the given registers, completed from the radio."""
    report = check_radio(path, GIVEN)
    assert report.mismatches == []
    return baseline(GIVEN, report.values), known_of(report.flavour, report.values)


def _attack_order(flavour: str) -> list[str]:
    """Every guarded register; NODECOUNT and NODEID last (they apply at once, and the
    victim then answers to a new id in a new slot: its answers come slowly)."""
    names = [s.name for s in params_for(flavour) if s.name not in UNGUARDED]
    return sorted(names, key=lambda n: {"NODECOUNT": 1, "NODEID": 2}.get(n, 0))


@pytest.mark.parametrize("flavour", ["standard", "multipoint"])
def test_every_register_a_rogue_changes_over_rt_is_found_and_restored(tmp_path: Path, flavour: str) -> None:
    """The rogue changes every writable register of the victim over RT, one ``RTSn=``
    each (each confirmed in the victim's RAM, and for those SiK applies at once in the
    running radio), then ``RT&W`` and ``RTZ``: the victim saved them all and runs with
    them all. One guard check, given only NETID at the start, names every one and
    restores every one. (Multipoint: the victim is node 1, the rogue the base.)"""
    v, r = (1, 0) if flavour == "multipoint" else (0, 1)
    # 2 hopping channels: the victim re-locks onto the rogue at once after a reboot
    with running_emulator(tmp_path, 2, firmware=flavour, params={"NUM_CHANNELS": 2}) as emu:
        emu.wait_locked(0, 1)
        table, known = _guard_table(emu.paths[v])
        victim = emu.emu.params[v]
        node = v if flavour == "multipoint" else None
        port = open_port(emu.paths[r])
        attacks: list[Attack] = []
        try:
            rogue = SikConfigurator(port, flavour=flavour, port_name="rogue")
            rogue.enter_command_mode()
            for name in _attack_order(flavour):
                attack = plan_attack(flavour, name, victim.as_dict(), node=node)
                send_line(rogue, attack.set_line)
                assert landed(victim.as_dict(), attack), attack  # the victim's ATI5 shows it
                if attack.applies_now:  # and SiK runs with it at once (param_set)
                    assert victim.active_value(name) == attack.value, attack
                    assert emu.emu.model is not None
                    assert emu.emu.model.radios[v].cfg == radio_config_of(victim), attack
                attacks.append(attack)
                if name == "NODEID":
                    node = attack.value  # the victim answers to its new id at once
            changed = {a.name: a.value for a in attacks}

            def running() -> bool:
                return {n: _named(victim, victim.active)[n] for n in changed} == changed

            send_line(rogue, attacks[-1].save_line)
            assert {n: _named(victim, victim.eeprom)[n] for n in changed} == changed  # saved
            for _ in range(10):  # unanswered: a rogue repeats it until the victim runs with it
                send_reboot(rogue, attacks[-1].reboot_line, 1)
                if wait_for(running, 2.0):
                    break
            assert running()
            rogue.exit_command_mode()
        finally:
            port.close()

        report = check_radio(emu.paths[v], table, restore=True, known=known)
        assert {m.name: m.actual for m in report.mismatches} == changed
        assert report.restored
        for copy in (victim.ram, victim.eeprom, victim.active):
            assert {n: x for n, x in _named(victim, copy).items() if n in table} == table
        assert check_radio(emu.paths[v], table, known=known).mismatches == []


def wait_for(pred: Callable[[], bool], seconds: float) -> bool:
    """Whether ``pred`` holds within ``seconds`` (polled)."""
    deadline = time.monotonic() + seconds
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _named(p: SikParams, copy: dict[int, int]) -> dict[str, int]:
    return {spec.name: copy[spec.index] for spec in p.specs}
