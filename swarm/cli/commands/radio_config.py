"""`swarm radio-config`: read and write a SiK radio's parameters with AT commands, or set
up one radio of a swarm network in one call.

Theory of operation
-------------------
Everything that can be checked without the radio is checked before the port is opened
(a ``--set`` name no firmware has, a value out of range, a bad network plan: exit 2,
nothing sent). Then the command enters AT command mode and asks the local radio's
banner (``ATI``): ``MP SiK ...`` is the multipoint firmware. That firmware's table
(``--firmware``, if given, must agree) is the one every write is checked against,
before the first ``ATSn=``: a register the firmware does not have (MAX_WINDOW on
multipoint) exits 2 with nothing written.

* ``--show`` / ``--json`` alone: read the registers (strictly, see
  :mod:`radios.sik.readout`), leave with ``ATO`` and print them; a register of the
  firmware's table that could not be read is named on stderr and the exit code is 1.
* ``--set NAME=VALUE`` and the network options (``--network N --node I --netid X``,
  :mod:`radios.sik.network`): write each value (``ATSn=``), save (``AT&W``), reboot
  (``ATZ``) so boot-time parameters take effect, enter command mode again (at the new
  serial speed if SERIAL_SPEED changed), read the registers as the radio now runs them
  and compare with what the firmware must show (AIR_SPEED and TXPOWER rounded, the
  frequencies clamped to the band ``ATI3`` names): one stderr line per register that
  differs, exit 1. In network mode the agent's ``--radio-params`` line is printed on
  stderr and, with ``--write-params FILE``, written to FILE (JSON, or TOML for
  ``.toml``) once the read-back agrees: every register the radio read back but the
  read-only FORMAT (frequencies, channels, power and duty cycle included), all of
  which the agent's radio guard then keeps.
* ``--remote``: the same reads and ``--set`` writes go to the radio at the other end as
  ``RT...`` commands (``,<node>`` appended with ``--remote-node`` in multipoint, where it
  is required: an ``RT`` line without a node reaches every radio and their answers mix).
  Each register is confirmed by two answers and asked at most five times; registers
  that could not be read are named and the exit code is 1. After ``RTZ`` the remote
  radio needs time to resynchronise, so the values compared and shown are those read
  just before the reboot. Network set-up is local only.

Encryption (SiK builds with AES only: RFD900+/RFD900U "e" firmware): ``--set
ENCRYPTION_LEVEL=1 --aes-key FILE`` (FILE holds 32, 48 or 64 hex digits for levels
1, 2, 3). The key is checked against the level before the port is opened, sent only
to the local radio (``--remote`` would carry it over the air in clear), after the
radio's ``ATI5`` has shown an ENCRYPTION_LEVEL register (a radio without AES would
overflow its 16-character line and send the rest of the key to the air as data),
checked with ``AT&E?`` after the reboot, and never printed.

Output: a table (``S1   SERIAL_SPEED   57``) or, with ``--json``, one JSON object of
parameter name -> int and nothing else on stdout. Exit codes: 0 success, 1 the radio
did not answer, refused, could not be read completely or reads back other values, 2
bad usage (bad parameter, missing port, a parameter the radio's firmware lacks).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from radios.errors import ATError, ConfigError, RadioError
from radios.sik.config import SERIAL_BAUD, SikConfigurator, open_port, strip_node
from radios.sik.network import (
    NetworkPlan,
    agent_params,
    band_of,
    differences,
    expected_readback,
    params_text,
    plan_settings,
)
from radios.sik.param_table import FLAVOURS, Flavour, check_flavour, params_for, spec_for
from radios.sik.params import validate_key_hex, validate_user_value
from radios.smallfile import read_small_file
from swarm.cli.util import UsageError, guarded, parser, print_json

PROG = "swarm radio-config"
REBOOT_SETTLE = 0.5  # seconds to let a rebooted radio start before talking to it again
NODE_MAX = 0x7FFF  # the largest multipoint NODEID
UNSAVED = "nothing was saved (values already in the radio's RAM last until it reboots)"


@dataclass
class Request:
    """What the command line asks, checked as far as it can be without the radio."""

    firmware: Flavour | None
    sets: dict[str, str]  # NAME -> value as typed (checked against every table that has NAME)
    plan: NetworkPlan | None
    remote: bool
    remote_node: int | None
    key: bytes | None
    write_params: str | None

    @property
    def writes(self) -> bool:
        return bool(self.sets) or self.plan is not None


def _parse_sets(items: list[str], firmware: Flavour | None) -> dict[str, str]:
    """``['AIR_SPEED=128', ...]`` -> {'AIR_SPEED': '128'}, each checked against ``firmware``
    or, not given, against whichever tables know the name (the radio's table decides
    later). Raises ConfigError/UsageError."""
    settings: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise UsageError(f"--set expects NAME=VALUE, got {item!r}")
        canonical = name.strip().upper()
        flavours = (firmware,) if firmware else FLAVOURS
        errors: list[ConfigError] = []
        for flavour in flavours:
            try:
                validate_user_value(flavour, canonical, value)
            except ConfigError as exc:
                errors.append(exc)
        if len(errors) == len(flavours):
            raise errors[0]
        settings[canonical] = value.strip()
    return settings


def _for_firmware(sets: dict[str, str], flavour: Flavour, banner: str) -> dict[str, int]:
    """``sets`` checked against the table of the firmware the radio runs (nothing written yet)."""
    out: dict[str, int] = {}
    for name, value in sets.items():
        try:
            spec_for(flavour, name)
        except ConfigError:
            raise ConfigError(
                f"the radio runs {flavour} firmware ({banner!r}), which has no {name}: nothing was written"
            ) from None
        out[name] = validate_user_value(flavour, name, value)
    return out


def _print_table(values: dict[str, int], indices: dict[str, int]) -> None:
    width = max((len(name) for name in values), default=0)
    for name, value in values.items():
        register = f"S{indices[name]}" if name in indices else "?"
        print(f"{register:<4} {name:<{width}}  {value}")


def _complain(lines: list[str]) -> None:
    for line in lines:
        print(f"{PROG}: {line}", file=sys.stderr, flush=True)


def build_parser() -> argparse.ArgumentParser:
    ap = parser(PROG, "Read and write a SiK radio's parameters with AT commands.")
    ap.add_argument("port", metavar="PORT", help="serial device of the radio, e.g. /dev/ttyUSB0")
    ap.add_argument("--baud", type=int, default=57600, help="serial speed to talk to it at (default 57600)")
    ap.add_argument("--show", action="store_true", help="only read and print the parameters")
    ap.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set a parameter (repeatable); saved with AT&W, applied by ATZ, read back",
    )
    net = ap.add_argument_group("network set-up (one call per radio, the same except --node)")
    net.add_argument("--network", type=int, metavar="N", help="number of radios in the swarm's network")
    net.add_argument("--node", type=int, metavar="I", help="this radio's node number, 0..N-1")
    net.add_argument("--netid", type=int, metavar="X", help="the network's NETID (one per swarm)")
    net.add_argument("--air-speed", type=int, default=64, metavar="KBPS", help="AIR_SPEED (default 64)")
    net.add_argument(
        "--serial-speed", type=int, default=57600, metavar="BAUD", help="the agent's baud (default 57600)"
    )
    net.add_argument("--ecc", type=int, default=0, choices=(0, 1), help="ECC (default 0)")
    net.add_argument(
        "--write-params",
        metavar="FILE",
        help="write the agent's --radio-params file: every register the radio reads back, but FORMAT",
    )
    ap.add_argument(
        "--remote", action="store_true", help="configure the radio at the other end of the link (RT commands)"
    )
    ap.add_argument("--remote-node", type=int, metavar="I", help="multipoint: the remote radio's node id")
    ap.add_argument(
        "--firmware", choices=FLAVOURS, default=None, help="expected firmware (default: detected)"
    )
    ap.add_argument(
        "--aes-key",
        metavar="FILE",
        help="file holding the AES key in hex, with --set ENCRYPTION_LEVEL=1|2|3 "
        "(32/48/64 digits; SiK builds with AES only; local radio only; never printed)",
    )
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    return ap


def _request(args: argparse.Namespace) -> Request:
    """The checks that need no radio. Raises UsageError/ConfigError."""
    if args.baud <= 0:
        raise UsageError(f"--baud must be positive, got {args.baud}")
    firmware = check_flavour(args.firmware) if args.firmware else None
    plan = None
    if args.network is not None:
        if args.node is None or args.netid is None:
            raise UsageError("--network N needs --node I and --netid X")
        if args.remote:
            raise UsageError(
                "--network sets up the local radio: plug each radio in and run it once per radio"
            )
        plan = NetworkPlan(args.network, args.node, args.netid, args.air_speed, args.serial_speed, args.ecc)
        plan.check()
    elif args.node is not None or args.netid is not None or args.write_params:
        raise UsageError("--node, --netid and --write-params belong to --network N")
    if args.write_params and not Path(args.write_params).resolve().parent.is_dir():
        raise UsageError(f"--write-params {args.write_params}: its directory does not exist")
    if args.show and (args.sets or plan):
        raise UsageError("--show only reads: drop it to write")
    if args.remote_node is not None and not args.remote:
        raise UsageError("--remote-node I needs --remote")
    if args.remote_node is not None and not 0 <= args.remote_node <= NODE_MAX:
        raise UsageError(f"--remote-node {args.remote_node}: a node id is 0..{NODE_MAX}")
    sets = _parse_sets(args.sets, firmware)
    level = sets.get("ENCRYPTION_LEVEL")
    key = _read_key(args.aes_key, int(level) if level else 0, args.remote)
    return Request(firmware, sets, plan, args.remote, args.remote_node, key, args.write_params)


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # argparse already printed the message
        return int(exc.code or 0)
    req = _request(args)
    port = open_port(args.port, args.baud)
    try:
        conf = SikConfigurator(port, remote=req.remote, remote_node=req.remote_node, port_name=args.port)
        conf.enter_command_mode()
        try:
            values, problems, agent = _configure(conf, req)
        except BaseException:  # Ctrl-C too: a radio left in command mode forwards nothing
            _leave_quietly(conf)
            raise
        indices = conf.indices
    finally:
        port.close()
    if args.json:
        print_json(values)
    else:
        _print_table(values, indices)
    if agent is not None and not problems:
        _agent_params(agent, req.write_params)
    _complain(problems)
    return 1 if problems else 0


def _agent_params(params: dict[str, int], path: str | None) -> None:
    """Tell the operator the agent's ``--radio-params`` and write them to ``path`` if given."""
    line = params_text(params, "line")
    print(f"{PROG}: for swarm agent: --radio-params {line}", file=sys.stderr)
    if path is None:
        return
    kind = "toml" if path.endswith(".toml") else "json"
    tmp = f"{path}.tmp{os.getpid()}"
    try:
        Path(tmp).write_text(params_text(params, kind), encoding="ascii")
        os.replace(tmp, path)
    except OSError as exc:
        raise ConfigError(f"--write-params {path}: {exc.strerror or exc} (the radio is set up)") from None
    print(f"{PROG}: wrote {path} (swarm agent --radio-params {path})", file=sys.stderr)


def _read_key(path: str | None, level: int, remote: bool) -> bytes | None:
    """The AES key from ``--aes-key FILE``, checked against ENCRYPTION_LEVEL; raises
    UsageError/ConfigError (messages never contain the key)."""
    if path is None:
        if level:
            raise UsageError(
                "--set ENCRYPTION_LEVEL needs --aes-key FILE: without it the "
                "radio encrypts with whatever key it holds (by default a known one)"
            )
        return None
    if remote:
        raise UsageError(
            "--aes-key only configures the local radio: RT commands cross the air unencrypted, key included"
        )
    if not level:
        raise UsageError("--aes-key needs --set ENCRYPTION_LEVEL=1, 2 or 3")
    try:  # a regular file of at most 4 KiB: never a FIFO or a device read for ever
        text = read_small_file(path, 4096).decode("ascii")
    except ValueError as exc:  # UnicodeDecodeError too
        why = "not ASCII text" if isinstance(exc, UnicodeDecodeError) else str(exc)
        raise UsageError(f"--aes-key {path}: cannot read it: {why}") from None
    return validate_key_hex(level, text)


def _detect(conf: SikConfigurator, req: Request) -> str:
    """The local radio's banner; sets ``conf.flavour`` to its firmware. Raises ConfigError
    if ``--firmware`` disagrees, UsageError for a multipoint ``--remote`` without a node."""
    banner = strip_node(conf.command("ATI", lines=1)[0])
    detected: Flavour = "multipoint" if banner.startswith("MP ") else "standard"
    if req.firmware is not None and req.firmware != detected:
        raise ConfigError(
            f"the radio runs {detected} firmware ({banner!r}), not {req.firmware}: "
            f"pass --firmware {detected} or leave it out"
        )
    if detected == "multipoint" and req.remote and req.remote_node is None:
        raise UsageError(
            "--remote on multipoint firmware needs --remote-node I: an RT command without a "
            "node reaches every radio and their answers mix"
        )
    conf.flavour = detected
    return banner


def _configure(
    conf: SikConfigurator, req: Request
) -> tuple[dict[str, int], list[str], dict[str, int] | None]:
    """Everything done in command mode: (values to print, problems to name, agent params)."""
    banner = _detect(conf, req)
    flavour = conf.flavour
    sets = _for_firmware(req.sets, flavour, banner)
    settings = plan_settings(req.plan, flavour, sets) if req.plan is not None else sets
    band = None if req.remote else band_of(strip_node(conf.command("ATI3", lines=1)[0]))
    values = conf.read_params()
    if not req.writes:
        conf.exit_command_mode()
        return values, _unread(conf, values, flavour), None
    if conf.unreadable:
        raise ATError(
            "could not read the remote radio's "
            + ", ".join(conf.unreadable)
            + " before writing: nothing was written"
        )
    if "ENCRYPTION_LEVEL" in settings and "ENCRYPTION_LEVEL" not in values:
        raise ConfigError(
            f"the radio's firmware ({banner!r}) has no AES encryption (its ATI5 "
            "shows no ENCRYPTION_LEVEL): nothing was written"
        )
    _write(conf, settings, req.key)
    values = _save(conf, settings, req.remote, req.key)
    expected = expected_readback(flavour, settings, band, booted=not req.remote)
    problems = _unread(conf, values, flavour) + differences(expected, values)
    agent = agent_params(values) if req.plan is not None else None
    return values, problems, agent


def _unread(conf: SikConfigurator, values: dict[str, int], flavour: str) -> list[str]:
    """One line naming the firmware's registers that were not read, if any."""
    missing = [spec.name for spec in params_for(flavour) if spec.name not in values]
    if not missing:
        return []
    where = "the remote radio" if conf.remote else f"the radio on {conf.port_name}"
    return [
        f"could not read {', '.join(missing)} of {where} ({len(values)} of {len(values) + len(missing)} read)"
    ]


def _write(conf: SikConfigurator, settings: dict[str, int], key: bytes | None) -> None:
    """The settings and the key, in the radio's RAM (an ATError says nothing was saved)."""
    for name, value in settings.items():
        try:
            conf.set_param(name, value)
        except ATError as exc:
            raise ATError(f"{exc}; {UNSAVED}") from None
    if key is not None:
        try:
            conf.set_key(key)
        except ATError as exc:
            raise ATError(f"{exc}; {UNSAVED}") from None


def _save(conf: SikConfigurator, settings: dict[str, int], remote: bool, key: bytes | None) -> dict[str, int]:
    """Save, reboot and read the values back (a remote radio: just before the reboot)."""
    if remote:
        values = conf.read_params()
        conf.save()
        conf.reboot()
        conf.exit_command_mode()
        print(
            f"{PROG}: remote radio saved and rebooting; values shown are as saved (AIR_SPEED and "
            "TXPOWER are rounded at boot)",
            file=sys.stderr,
        )
        return values
    conf.save()
    conf.reboot()
    if "SERIAL_SPEED" in settings:
        conf.port.baudrate = SERIAL_BAUD[settings["SERIAL_SPEED"]]
    time.sleep(REBOOT_SETTLE)
    try:
        conf.enter_command_mode()
    except ATError as exc:
        raise ATError(f"settings saved and radio rebooted, but reading them back failed: {exc}") from None
    values = conf.read_params()
    if key is not None and not conf.key_matches(key):
        conf.exit_command_mode()
        raise ATError("the radio rebooted without the new key (AT&E? shows another one)")
    conf.exit_command_mode()
    return values


def _leave_quietly(conf: SikConfigurator) -> None:
    """Best effort to return the radio to data mode after a failure."""
    if not conf.in_command_mode:
        return
    try:
        conf.exit_command_mode()
    except RadioError:
        pass
