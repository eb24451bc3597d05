"""``swarm config example agent|gcs``: print a commented config file for a command.

Theory of operation. The example is generated from the command's own argparse parser
(with the options :func:`swarm.cli.configfile.prepare` adds), through the same
:func:`~swarm.cli.configfile.keys` that reads a file, so it lists every key the
command takes and nothing else. For each key: its help as a comment, its TOML type
(and choices), then the key commented out with its default (``#profile =
"paper"``), or with a placeholder (``#radio = "<URL>"``) when it has none. A
required key (the agent's ``name`` and ``id``) is marked REQUIRED: uncomment it and
fill it in. The file loads back as printed (every line a comment) and with every
default uncommented.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import textwrap
from typing import Any

from swarm.cli.configfile import MAX_ARRAY, MAX_FILE_BYTES, MAX_STRING, Key, keys, prepare
from swarm.cli.util import guarded

PROG = "swarm config"

#: the commands that read a config file -> their module in swarm.cli.commands
CONFIG_COMMANDS = {"agent": "agent", "gcs": "gcs"}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description="Config files (TOML) for the long-running commands.")
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    ex = sub.add_parser(
        "example",
        help="print a commented file with every key and its default",
        description="Print a commented config file with every key of the command, its "
        "default and its help: save it, uncomment and change what you need, then run "
        "'swarm COMMAND --config FILE'.",
    )
    ex.add_argument("command", choices=list(CONFIG_COMMANDS), help="the command the file is for")
    return p


def command_parser(command: str) -> argparse.ArgumentParser:
    """The full parser of ``command`` (one of :data:`CONFIG_COMMANDS`), as it reads a file."""
    module = importlib.import_module(f"swarm.cli.commands.{CONFIG_COMMANDS[command]}")
    return prepare(module.build_parser())


def toml_value(value: Any) -> str:
    """A default as TOML (strings, numbers, booleans and arrays of them)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in value) + "]"
    return json.dumps(str(value))


def _type_line(key: Key) -> str:
    what = {"bool": "true or false", "int": "integer", "float": "number", "str": "string"}[key.kind]
    if key.array:
        what = f"array of {what}s, at most {MAX_ARRAY} items"
    if key.action.choices is not None:
        what += ", one of " + ", ".join(json.dumps(str(c)) for c in key.action.choices)
    if key.is_path:
        meta = key.action.metavar
        either = isinstance(meta, str) and meta.endswith("|FILE")
        what += "; a file's path is" if either else "; a path"
        what += " relative to this file's folder"
    return what


def _placeholder(key: Key) -> str:
    meta = key.action.metavar
    name = meta if isinstance(meta, str) else key.name.upper()
    text = f'"<{name}>"' if key.kind == "str" else f"<{name}>"
    return f"[{text}]" if key.array else text


def render_key(key: Key) -> list[str]:
    """The comment lines and the commented-out line of one key."""
    a = key.action
    help_text = (a.help or "").replace("%%", "%")
    lines = [f"# {x}" for x in textwrap.wrap(help_text, 86)]
    lines.append(f"# ({_type_line(key)})")
    if a.required:
        lines.append("# REQUIRED: uncomment and fill in (or give " + key.flag + " on the command line)")
        lines.append(f"#{key.name} = {_placeholder(key)}")
    elif a.default is None:
        lines.append(f"#{key.name} = {_placeholder(key)}  # default: not set")
    else:
        lines.append(f"#{key.name} = {toml_value(a.default)}")
    return lines


def render(command: str) -> str:
    """The example file of ``command``."""
    p = command_parser(command)
    out = [
        f"# swarm {command}: config file (TOML), written by 'swarm config example {command}'.",
        f"# Use: swarm {command} --config FILE [flags]. Each key is a flag of 'swarm {command} --help'",
        "# without its leading -- and with _ for - (--log-level: log_level); a flag given on",
        "# the command line overrides the file. One flat table: no [sections]. Paths are",
        "# relative to this file's folder. Every key below is commented out with its default:",
        "# uncomment and change what you need; a key the command does not know is refused.",
        f"# Limits: {MAX_FILE_BYTES} bytes, strings of at most {MAX_STRING} characters.",
    ]
    for key in keys(p).values():
        out.append("")
        out.extend(render_key(key))
    return "\n".join(out) + "\n"


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if a.action == "example":
        print(render(a.command), end="", flush=True)
    return 0
