"""The emulator's configuration: options, their checks, and what each radio boots with.

Theory of operation
-------------------
:class:`EmulatorConfig` holds what ``swarm radio-emu`` was given; ``validate()``
refuses any bad value with a one-line :class:`~radios.errors.ConfigError` before a
pty is created. :func:`stored_params` says which SiK parameters radio *i* boots
with (the options, then ``--param NAME=VALUE`` from :func:`parse_param`), and
:func:`radio_config_of` turns a radio's active parameters into the air model's
:class:`~radios.air.RadioConfig`. :func:`check_capture_path` fails early when a
capture cannot be created. The running emulator is :mod:`radios.emulator`.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

from radios.air import RadioConfig
from radios.errors import ConfigError
from radios.sik.param_table import spec_for
from radios.sik.params import SikParams, validate_user_value

SERIAL_BAUD = {1: 1200, 2: 2400, 4: 4800, 9: 9600, 19: 19200, 38: 38400, 57: 57600, 115: 115200, 230: 230400}
BAUD_CODE = {v: k for k, v in SERIAL_BAUD.items()}


@dataclass
class EmulatorConfig:
    nodes: int
    directory: str
    air_speed: int = 64
    serial_speed: int = 57600
    netids: list[int] = field(default_factory=lambda: [25])
    firmware: str | None = None  # None: standard for 2 radios or fewer, else multipoint
    loss: float = 0.0
    burst_loss: str | None = None
    positions: str | None = None
    params: dict[str, int] = field(default_factory=dict)
    flow_control: bool = False
    capture: str | None = None
    #: the radio (0-based, as ``radioN``) whose RADIO_STATUS reports to its host the
    #: capture records too, as a capture on that host (a ground station) would hold them
    capture_status: int | None = None
    stats_json: str | None = None
    seed: int = 0
    aes: bool = False  # RFD900P radios running a SiK build with AES (standard firmware)

    def resolved_firmware(self) -> str:
        if self.firmware is not None:
            return self.firmware
        return "standard" if self.nodes <= 2 else "multipoint"

    def validate(self) -> None:
        """Raises ConfigError with a clear message for any bad value."""
        if not 1 <= self.nodes <= 250:
            raise ConfigError(f"--nodes {self.nodes}: between 1 and 250 radios")
        if self.resolved_firmware() not in ("standard", "multipoint"):
            raise ConfigError(f"--firmware {self.firmware}: standard or multipoint")
        if self.serial_speed not in BAUD_CODE:
            raise ConfigError(
                f"--serial-speed {self.serial_speed}: one of " + ", ".join(str(b) for b in sorted(BAUD_CODE))
            )
        validate_user_value(self.resolved_firmware(), "AIR_SPEED", self.air_speed)
        if len(self.netids) not in (1, self.nodes):
            raise ConfigError(
                f"--netid: give one NETID for all radios or one per radio "
                f"({self.nodes}), not {len(self.netids)}"
            )
        for n in self.netids:
            validate_user_value(self.resolved_firmware(), "NETID", n)
        if not 0.0 <= self.loss <= 1.0:
            raise ConfigError(f"--loss {self.loss}: a probability between 0 and 1")
        if self.capture_status is not None and (
            self.capture is None or not 0 <= self.capture_status < self.nodes
        ):
            raise ConfigError(
                f"--capture-status {self.capture_status}: a radio 0..{self.nodes - 1}, with --capture"
            )
        if self.aes and self.resolved_firmware() != "standard":
            raise ConfigError("--aes: the multipoint SiK firmware has no AES encryption")
        for name, value in self.params.items():
            if name.upper() == "ENCRYPTION_LEVEL" and not self.aes:
                raise ConfigError("ENCRYPTION_LEVEL exists only on firmware built with AES")
            validate_user_value(self.resolved_firmware(), name, value)


def parse_param(text: str) -> tuple[str, int]:
    """``NAME=VALUE`` as given to ``--param``. Raises ConfigError."""
    name, sep, value = text.partition("=")
    if not sep:
        raise ConfigError(f"--param {text!r}: expected NAME=VALUE")
    try:
        return name.strip().upper(), int(value)
    except ValueError:
        raise ConfigError(f"--param {text!r}: the value must be an integer") from None


def radio_config_of(p: SikParams) -> RadioConfig:
    """What the air model needs of a radio whose parameters are ``p`` (its active copy)."""

    def a(name: str) -> int:
        return p.active[spec_for(p.flavour, name).index]

    mp = p.flavour == "multipoint"
    return RadioConfig(
        netid=a("NETID"),
        air_kbps=a("AIR_SPEED"),
        serial_baud=SERIAL_BAUD.get(a("SERIAL_SPEED"), 57600),
        ecc=bool(a("ECC")),
        mavlink=a("MAVLINK"),
        max_window_ms=131 if mp else a("MAX_WINDOW"),
        num_channels=a("NUM_CHANNELS"),
        min_freq=a("MIN_FREQ"),
        max_freq=a("MAX_FREQ"),
        txpower_dbm=a("TXPOWER"),
        firmware=p.flavour,
        node_id=a("NODEID") if mp else 0,
        node_destination=a("NODEDESTINATION") if mp else 0xFFFF,
        node_count=a("NODECOUNT") if mp else 2,
        key=p.active_key(),
    )


def stored_params(cfg: EmulatorConfig, i: int) -> dict[str, int]:
    """The parameters radio ``i`` boots with: the emulator's options, then ``--param``."""
    stored = {
        "AIR_SPEED": cfg.air_speed,
        "SERIAL_SPEED": BAUD_CODE[cfg.serial_speed],
        "NETID": cfg.netids[i] if len(cfg.netids) > 1 else cfg.netids[0],
    }
    if cfg.resolved_firmware() == "multipoint":
        stored["NODECOUNT"] = max(cfg.nodes, 2)
        stored["NODEID"] = i
        stored["MAVLINK"] = 1  # the swarm runs MAVLink framing; multipoint defaults to raw
    stored.update(cfg.params)
    # order matters for the multipoint cross-checks (NODEID < NODECOUNT)
    order = ["NODECOUNT"] + [k for k in stored if k != "NODECOUNT"]
    return {k: stored[k] for k in order if k in stored}


def check_capture_path(path: str) -> None:
    """Fail early (ConfigError) if a capture file cannot be created at ``path``."""
    parent = Path(path).parent
    if not parent.is_dir():
        raise ConfigError(f"--capture {path}: directory {parent} does not exist")
    if Path(path).exists() and not stat.S_ISREG(os.stat(path).st_mode):
        raise ConfigError(f"--capture {path}: not a regular file")


__all__ = [
    "BAUD_CODE",
    "SERIAL_BAUD",
    "EmulatorConfig",
    "check_capture_path",
    "parse_param",
    "radio_config_of",
    "stored_params",
]
