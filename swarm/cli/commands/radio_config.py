"""`swarm radio-config`: read and write a SiK radio's parameters with AT commands.

Theory of operation
-------------------
Every ``--set NAME=VALUE`` is validated against the firmware's parameter table before
the port is even opened, so a bad name or value exits 2 with nothing written. Then the
command enters AT command mode, checks the banner (``ATI``) against ``--firmware``,
reads the parameters (``ATI5``), applies each setting (``ATSn=``), saves (``AT&W``)
and reboots (``ATZ``) so that boot-time parameters take effect. For a local radio it
then enters command mode again (at the new serial speed if SERIAL_SPEED changed),
reads the parameters as the radio now runs them (AIR_SPEED and TXPOWER rounded) and
leaves with ``ATO``. Without ``--set`` it only reads and leaves with ``ATO``.

With ``--remote`` the same operations go to the radio at the other end of the link as
``RT...`` commands; after ``RTZ`` the remote radio needs time to resynchronise, so
the values shown are those read just before the reboot.

Encryption (SiK builds with AES only: RFD900+/RFD900U "e" firmware): ``--set
ENCRYPTION_LEVEL=1 --aes-key FILE`` (FILE holds 32, 48 or 64 hex digits for levels
1, 2, 3). The key is checked against the level before the port is opened, sent only
to the local radio (``--remote`` would carry it over the air in clear), after the
radio's ``ATI5`` has shown an ENCRYPTION_LEVEL register (a radio without AES would
overflow its 16-character line and send the rest of the key to the air as data),
checked with ``AT&E?`` after the reboot, and never printed.

Output: a table (``S1   SERIAL_SPEED   57``) or, with ``--json``, one JSON object of
parameter name -> int and nothing else on stdout. Exit codes: 0 success, 1 the radio
did not answer or refused, 2 bad usage (bad parameter, missing port).
"""

from __future__ import annotations

import sys
import time

from radios.errors import ATError, ConfigError, RadioError
from radios.sik.config import SERIAL_BAUD, SikConfigurator, open_port
from radios.sik.params import (
    FLAVOURS,
    Flavour,
    check_flavour,
    validate_key_hex,
    validate_user_value,
)
from swarm.cli.util import UsageError, guarded, parser, print_json

PROG = "swarm radio-config"
REBOOT_SETTLE = 0.5  # seconds to let a rebooted radio start before talking to it again


def _parse_sets(items: list[str], flavour: Flavour) -> dict[str, int]:
    """``['AIR_SPEED=128', ...]`` -> {'AIR_SPEED': 128}; raises ConfigError/UsageError."""
    settings: dict[str, int] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise UsageError(f"--set expects NAME=VALUE, got {item!r}")
        canonical = name.strip().upper()
        settings[canonical] = validate_user_value(flavour, canonical, value)
    return settings


def _detected_flavour(banner: str) -> Flavour:
    return "multipoint" if banner.startswith("MP ") else "standard"


def _print_table(values: dict[str, int], indices: dict[str, int]) -> None:
    width = max((len(name) for name in values), default=0)
    for name, value in values.items():
        register = f"S{indices[name]}" if name in indices else "?"
        print(f"{register:<4} {name:<{width}}  {value}")


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    ap = parser(PROG, "Read and write a SiK radio's parameters with AT commands.")
    ap.add_argument("port", metavar="PORT", help="serial device of the radio, e.g. /dev/ttyUSB0")
    ap.add_argument("--baud", type=int, default=57600, help="serial speed (default 57600)")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--show", action="store_true", help="only read and print the parameters")
    mode.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set a parameter (repeatable); saved with AT&W, applied by ATZ",
    )
    ap.add_argument(
        "--remote", action="store_true", help="configure the radio at the other end of the link (RT commands)"
    )
    ap.add_argument(
        "--firmware",
        choices=FLAVOURS,
        default=None,
        help="firmware flavour the parameters are checked against "
        "(default: standard; the radio's banner must agree when setting)",
    )
    ap.add_argument(
        "--aes-key",
        metavar="FILE",
        help="file holding the AES key in hex, with --set ENCRYPTION_LEVEL=1|2|3 "
        "(32/48/64 digits; SiK builds with AES only; local radio only; "
        "never printed)",
    )
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    try:
        args = ap.parse_args(argv)
    except SystemExit as exc:  # argparse already printed the message
        return int(exc.code or 0)
    if args.baud <= 0:
        raise UsageError(f"--baud must be positive, got {args.baud}")
    flavour = check_flavour(args.firmware or "standard")
    settings = _parse_sets(args.sets, flavour)
    key = _read_key(args.aes_key, settings, args.remote)

    port = open_port(args.port, args.baud)
    try:
        conf = SikConfigurator(port, flavour=flavour, remote=args.remote, port_name=args.port)
        conf.enter_command_mode()
        try:
            values = _configure(conf, args.firmware, settings, args.remote, key)
        except RadioError:
            _leave_quietly(conf)
            raise
        indices = conf.indices
    finally:
        port.close()

    if args.json:
        print_json(values)
    else:
        _print_table(values, indices)
    return 0


def _read_key(path: str | None, settings: dict[str, int], remote: bool) -> bytes | None:
    """The AES key from ``--aes-key FILE``, checked against ENCRYPTION_LEVEL; raises
    UsageError/ConfigError (messages never contain the key)."""
    level = settings.get("ENCRYPTION_LEVEL")
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
    try:
        with open(path, encoding="ascii") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(
            f"--aes-key {path}: cannot read it: {getattr(exc, 'strerror', None) or exc.__class__.__name__}"
        ) from None
    return validate_key_hex(level, text)


def _configure(
    conf: SikConfigurator,
    firmware: str | None,
    settings: dict[str, int],
    remote: bool,
    key: bytes | None = None,
) -> dict[str, int]:
    """Everything done in command mode; returns the values to print."""
    banner = conf.version()
    detected = _detected_flavour(banner)
    if settings and detected != conf.flavour:
        given = "--firmware " + conf.flavour if firmware else "the default standard table"
        raise ConfigError(
            f"the radio runs {detected} firmware ({banner!r}) but the settings "
            f"were checked against {given}: pass --firmware {detected}"
        )
    values = conf.read_params()
    if not settings:
        conf.exit_command_mode()
        return values
    if "ENCRYPTION_LEVEL" in settings and "ENCRYPTION_LEVEL" not in values:
        raise ConfigError(
            f"the radio's firmware ({banner!r}) has no AES encryption (its ATI5 "
            "shows no ENCRYPTION_LEVEL): nothing was written"
        )
    _write(conf, settings, key)
    return _save(conf, settings, remote, key)


def _write(conf: SikConfigurator, settings: dict[str, int], key: bytes | None) -> None:
    """The settings and the key, in the radio's RAM (an ATError says nothing was saved)."""
    for name, value in settings.items():
        try:
            conf.set_param(name, value)
        except ATError as exc:
            raise ATError(f"{exc}; nothing was saved") from None
    if key is not None:
        try:
            conf.set_key(key)
        except ATError as exc:
            raise ATError(f"{exc}; nothing was saved") from None


def _save(conf: SikConfigurator, settings: dict[str, int], remote: bool, key: bytes | None) -> dict[str, int]:
    """Save, reboot and (a local radio) read the values back; returns them."""
    if remote:
        values = conf.read_params()
        conf.save()
        conf.reboot()
        conf.exit_command_mode()
        print(
            "remote radio saved and rebooting; values shown are as saved (AIR_SPEED and "
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
