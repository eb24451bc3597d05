"""The `swarm` command: one entry point, one module per subcommand.

Subcommand modules are imported lazily so that `swarm --help` and each command
start fast and a broken optional dependency of one command does not break others.
Only working subcommands are listed here.

Global options come before the subcommand: ``-v`` (INFO; ``-vv`` DEBUG) or
``--log-level LEVEL`` sends the project's log lines at that level to stderr, one
line each with the time, the logger's name and the level; ``--log-format json``
makes each line one JSON object (time, level, logger, message). Without them
nothing is configured: only warnings and errors reach stderr, as bare lines. The
long-running commands (:data:`LOG_COMMANDS`) also take ``--log-level`` and
``--log-format`` after the command and as config-file keys: the global options are
handed to them as their first options, so the rule is one: the command line beats
the config file, and after the command beats before it. ``--version``
prints the installed release (the package's metadata) and exits 0.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from swarm.cli.util import EXIT_INTERRUPTED, EXIT_USAGE, LOG_FORMATS, LOG_LEVELS, configure_logging

# name -> (module in swarm.cli.commands, one-line summary)
COMMANDS: dict[str, tuple[str, str]] = {
    "radio-emu": ("radio_emu", "emulate a network of SiK radios on pseudo terminals"),
    "radio-config": ("radio_config", "read and write a SiK radio's parameters (AT commands)"),
    "replay": ("replay", "decode, re-feed and summarise a radio capture (.tlog)"),
    "sim": ("sim", "simulate N multicopters that speak MAVLink like PX4 or ArduPilot SITL"),
    "agent": ("agent", "run one swarm agent (election, membership) on a radio or Zenoh"),
    "simulate": ("simulate", "seeded leader-election runs in virtual time, with invariants"),
    "gcs": ("gcs", "ground control station: web map, JSON API, commands, replay"),
    "router": ("router", "a Zenoh router, so ground stations on different machines meet"),
    "tiles": ("tiles", "fetch a map area into an MBTiles file while online, for the station offline"),
    "demo": ("demo", "the whole bench on one machine: election, take-off, V formation, route"),
    "bench": ("bench", "run a benchmark and print its figures"),
    "config": ("config", "print a commented example config file: swarm config example agent|gcs"),
    "keygen": ("keygen", "write a new swarm signing key (32 random bytes, mode 0600)"),
    "certs": ("certs", "make the swarm's CA, node certificates and Zenoh ACL (TLS over IP)"),
    "service": ("service", "print or install the systemd unit of an agent or the ground station"),
    "doctor": ("doctor", "pre-flight check of a field set-up: radio, flight controller, key, clock"),
}

#: the long-running commands: they take --log-level and --log-format themselves
#: (after the command, or in their config file), and are handed the global ones
LOG_COMMANDS = ("agent", "gcs", "radio-emu", "sim", "demo")


DIST_NAME = "uav-swarm"


def version_line() -> str:
    """``swarm (uav-swarm) X.Y.Z``, from the installed package's metadata."""
    import importlib.metadata  # here, not at the top: it costs every command tens of ms

    try:
        version = importlib.metadata.version(DIST_NAME)
    except importlib.metadata.PackageNotFoundError:
        version = "unknown (not installed: pip install . or make setup)"
    return f"swarm ({DIST_NAME}) {version}"


def _usage() -> str:
    width = max(len(n) for n in COMMANDS)
    usage = "usage: swarm [--version] [-v | -vv | --log-level LEVEL] [--log-format F] <command> [options]"
    lines = [usage, ""]
    lines += ["commands:"]
    lines += [f"  {name:<{width}}  {summary}" for name, (_, summary) in COMMANDS.items()]
    lines += [
        "",
        "options (before the command):",
        "  --version          print the installed release and exit",
        "  -v, -vv            log INFO (-v) or DEBUG (-vv) lines to stderr",
        f"  --log-level LEVEL  log lines at LEVEL and above ({', '.join(LOG_LEVELS)}) to stderr",
        f"  --log-format F     {' or '.join(LOG_FORMATS)}: one JSON object a line with json",
        f"  ({', '.join(LOG_COMMANDS)} also take both after the command; agent and gcs",
        "   also as keys of --config FILE: the command line beats the file, after the",
        "   command beats before it)",
        "",
        "Run 'swarm <command> --help' for a command's options.",
    ]
    return "\n".join(lines)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        print(f"swarm: error: {message}\n\n{_usage()}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def _global_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="swarm", add_help=False)
    p.add_argument("-h", "--help", action="store_true")
    p.add_argument("--version", action="store_true")
    p.add_argument("-v", "--verbose", action="count", default=0)
    p.add_argument("--log-level", type=str.upper, choices=LOG_LEVELS)
    p.add_argument("--log-format", choices=LOG_FORMATS)
    p.add_argument("command", nargs="?")
    p.add_argument("args", nargs=argparse.REMAINDER)
    return p


def _level(a: argparse.Namespace) -> str | None:
    """The log level the global options ask for, or None (leave logging alone)."""
    if a.log_level is not None:
        return str(a.log_level)
    if a.verbose:
        return "INFO" if a.verbose == 1 else "DEBUG"
    return None


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    try:
        a = _global_parser().parse_args(args)
    except SystemExit as exc:
        return int(exc.code or 0)
    if a.version:
        print(version_line())
        return 0
    if a.help or a.command is None:
        print(_usage())
        return 0 if a.help else EXIT_USAGE
    if a.command not in COMMANDS:
        print(f"swarm: unknown command {a.command!r}\n\n{_usage()}", file=sys.stderr)
        return EXIT_USAGE
    level, fmt, rest = _level(a), a.log_format, list(a.args)
    if a.command in LOG_COMMANDS:  # the command's own options, first: its later ones win
        rest[:0] = [*(["--log-level", level] if level else []), *(["--log-format", fmt] if fmt else [])]
    elif level is not None or fmt is not None:
        configure_logging(level or "WARNING", fmt or "text")
    try:  # a Ctrl-C while the command's modules load: interrupted, as inside the command
        module = importlib.import_module(f"swarm.cli.commands.{COMMANDS[a.command][0]}")
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    code: int = module.main(rest)
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
