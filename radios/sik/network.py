"""The registers one radio of an N-radio swarm network needs, and what its read-back must show.

Theory of operation
-------------------
Pure: no port, no clock. An operator setting up ten radios gives each the same
:class:`NetworkPlan` except the node number; :func:`plan_settings` turns it into the
``NAME -> value`` writes for the firmware the radio turned out to run, checked
against that firmware's table (:func:`~radios.sik.params.validate_user_value`) so a
parameter the firmware does not have is refused before anything is written.

* Both firmwares: NETID, AIR_SPEED, SERIAL_SPEED (the code of the agent's serial
  speed), ECC and MAVLINK=1 (the swarm's traffic is MAVLink 2: framing keeps a lost
  packet from cutting a frame in two).
* Multipoint: NODECOUNT = N, NODEID = I (node 0 is the base that keeps the network in
  sync) and NODEDESTINATION = 65535 (broadcast: every agent hears every other). They
  are written NODECOUNT first, because the firmware refuses a NODEID that is not
  below the NODECOUNT already in RAM.
* Standard firmware links two radios: a plan of more than two is refused (three on one
  NETID collide, without addresses).

MIN_FREQ, MAX_FREQ, NUM_CHANNELS, TXPOWER, DUTY_CYCLE and LBT_RSSI are regional and
left alone unless the operator adds ``--set`` for them; ``extra`` settings may not
name a register the plan writes.

:func:`expected_readback` says what ``ATI5`` must show after ``AT&W`` + ``ATZ`` (the
firmware's own rewrites applied: AIR_SPEED rounded up to a rate, TXPOWER to a power
level, MIN/MAX_FREQ and NUM_CHANNELS clamped to the band), and :func:`differences`
gives one line per register that does not. :func:`agent_params` is what the agent's
radio guard (``swarm agent --radio-params``) keeps: every register the radio read back
but the read-only FORMAT, the regional ones included (a rogue's ``RT`` commands can
change any of them), and :func:`params_text` writes it as a line or a JSON/TOML file.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass

from radios.errors import ConfigError
from radios.sik.param_table import BANDS, BROADCAST, UNGUARDED, Band, spec_for
from radios.sik.params import validate_user_value

BAUD_CODES = {1200: 1, 2400: 2, 4800: 4, 9600: 9, 19200: 19, 38400: 38, 57600: 57, 115200: 115, 230400: 230}
NODECOUNT_MAX = 0x8000


@dataclass(frozen=True)
class NetworkPlan:
    """One radio of an N-radio network (``--network N --node I --netid X ...``)."""

    nodes: int
    node: int
    netid: int
    air_speed: int = 64
    serial_baud: int = 57600
    ecc: int = 0

    def check(self) -> None:
        """The checks that need no firmware: raises :class:`ConfigError` with one line."""
        if not 2 <= self.nodes <= NODECOUNT_MAX:
            raise ConfigError(f"--network {self.nodes}: a network has 2..{NODECOUNT_MAX} radios")
        if not 0 <= self.node < self.nodes:
            raise ConfigError(
                f"--node {self.node}: the nodes of a {self.nodes}-radio network are 0..{self.nodes - 1}"
            )
        if self.serial_baud not in BAUD_CODES:
            raise ConfigError(
                f"--serial-speed {self.serial_baud}: one of " + ", ".join(str(b) for b in BAUD_CODES)
            )
        for flavour_free in ("standard", "multipoint"):  # same ranges in both tables
            validate_user_value(flavour_free, "NETID", self.netid)
            validate_user_value(flavour_free, "AIR_SPEED", self.air_speed)
            validate_user_value(flavour_free, "ECC", self.ecc)


def plan_settings(plan: NetworkPlan, flavour: str, extra: Mapping[str, int] | None = None) -> dict[str, int]:
    """The writes for ``plan`` on ``flavour`` firmware, then ``extra``, in write order.

    Raises :class:`ConfigError` for a plan the firmware cannot run, an ``extra`` name
    the plan already sets or the firmware does not have, or a bad value.
    """
    plan.check()
    settings: dict[str, int] = {}
    if flavour == "multipoint":
        settings |= {"NODECOUNT": plan.nodes, "NODEID": plan.node, "NODEDESTINATION": BROADCAST}
    elif plan.nodes > 2:
        raise ConfigError(
            f"the radio runs the standard SiK firmware, which links two radios: a {plan.nodes}-radio "
            "network needs the multipoint firmware on every radio"
        )
    settings |= {
        "NETID": plan.netid,
        "AIR_SPEED": plan.air_speed,
        "SERIAL_SPEED": BAUD_CODES[plan.serial_baud],
        "ECC": plan.ecc,
        "MAVLINK": 1,
    }
    for name, value in (extra or {}).items():
        canonical = spec_for(flavour, name).name
        if canonical in settings:
            raise ConfigError(
                f"--set {canonical}: the network options already set it (to {settings[canonical]})"
            )
        settings[canonical] = value
    return {name: validate_user_value(flavour, name, value) for name, value in settings.items()}


def band_of(ati3: str) -> Band | None:
    """The band an ``ATI3`` answer names (67 = 433 MHz, ... 145 = 915 MHz), or None."""
    text = ati3.strip()
    for band in BANDS.values():
        if text == str(band.code):
            return band
    return None


def expected_readback(
    flavour: str, settings: Mapping[str, int], band: Band | None, *, booted: bool = True
) -> dict[str, int]:
    """What ``ATI5`` shows after the settings were saved and the radio rebooted: the
    firmware's rewrites on set and at boot applied (band-dependent ones only when the
    band is known, else those registers are not compared). ``booted=False``: what it
    shows before the reboot (the rewrites on set only)."""
    expected: dict[str, int] = {}
    for name, value in settings.items():
        spec = spec_for(flavour, name)
        if spec.on_set is not None:
            value = spec.on_set(value)
        if booted and spec.on_boot is not None:
            if band is None and name in ("MIN_FREQ", "MAX_FREQ", "NUM_CHANNELS", "TXPOWER"):
                continue
            value = spec.on_boot(value, band or BANDS[915])
        expected[name] = value
    return expected


def differences(expected: Mapping[str, int], actual: Mapping[str, int]) -> list[str]:
    """One line per register the radio does not show with the expected value."""
    lines = []
    for name, value in expected.items():
        if name not in actual:
            lines.append(f"{name}: not read back (expected {value})")
        elif actual[name] != value:
            lines.append(f"{name}: the radio shows {actual[name]}, expected {value}")
    return lines


def agent_params(values: Mapping[str, int]) -> dict[str, int]:
    """The registers of ``values`` the agent's radio guard keeps: every one but the
    read-only FORMAT (a rogue can change any other over RT, and each matters: see
    :mod:`radios.sik.guard`)."""
    return {name: value for name, value in values.items() if name not in UNGUARDED}


def params_text(params: Mapping[str, int], kind: str) -> str:
    """``params`` as a ``--radio-params`` value (``line``), a ``json`` or a ``toml`` file."""
    if kind == "line":
        return ",".join(f"{name}={value}" for name, value in params.items())
    if kind == "toml":
        return "".join(f"{name} = {value}\n" for name, value in params.items())
    return json.dumps(dict(params), indent=2) + "\n"
