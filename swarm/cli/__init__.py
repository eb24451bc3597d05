"""The `swarm` command: one entry point, one module per subcommand.

Subcommand modules are imported lazily so that `swarm --help` and each command
start fast and a broken optional dependency of one command does not break others.
Only working subcommands are listed here.
"""

from __future__ import annotations

import importlib
import sys

# name -> (module in swarm.cli.commands, one-line summary)
COMMANDS: dict[str, tuple[str, str]] = {
    "radio-emu": ("radio_emu", "emulate a network of SiK radios on pseudo terminals"),
    "radio-config": ("radio_config", "read and write a SiK radio's parameters (AT commands)"),
    "replay": ("replay", "decode, re-feed and summarise a radio capture (.tlog)"),
    "sim": ("sim", "simulate N multicopters that speak MAVLink like PX4 or ArduPilot SITL"),
    "agent": ("agent", "run one swarm agent (election, membership) on a radio or Zenoh"),
    "simulate": ("simulate", "seeded leader-election runs in virtual time, with invariants"),
    "gcs": ("gcs", "ground control station: web map, JSON API, commands, replay"),
    "demo": ("demo", "the whole bench on one machine: election, take-off, V formation, route"),
    "bench": ("bench", "run a benchmark and print its figures"),
}


def _usage() -> str:
    width = max(len(n) for n in COMMANDS)
    lines = ["usage: swarm <command> [options]", "", "commands:"]
    lines += [f"  {name:<{width}}  {summary}" for name, (_, summary) in COMMANDS.items()]
    lines += ["", "Run 'swarm <command> --help' for a command's options."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if not args or args[0] in ("-h", "--help"):
        print(_usage())
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        print(f"swarm: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"swarm.cli.commands.{COMMANDS[name][0]}")
    code: int = module.main(rest)
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
