"""Config files for the long-running commands: a flat TOML file whose keys are the flags.

Theory of operation. A command's argparse parser is the one description of its
options; this module derives the file's keys from it, so the file cannot drift from
the flags. A key is a flag's long name without ``--``, dashes as underscores
(``--zenoh-connect`` -> ``zenoh_connect``); its TOML type follows the flag: a
string, an integer, a number (an integer is taken too), ``true``/``false`` for a
switch, an array of strings for a flag taking several values or given several
times. ``choices`` are checked here; ranges stay in the command's own checks.

:func:`read_arguments` is how such a command reads its arguments:
1. a first parse of the command line (nothing required) finds ``--config FILE``;
2. the file is read as hostile input (:func:`load_file`: a regular file of at most
   1 MiB, UTF-8, TOML, flat) and each key checked against the parser
   (:func:`file_values`): an unknown key (the nearest known one suggested), a wrong
   type, a value outside ``choices``, a control character or an over-long string is
   one :class:`~swarm.cli.util.UsageError` naming the file and the key (exit 2);
   paths (flags whose metavar is ``FILE``, ``DIR`` or ``CAPTURE``) are taken relative
   to the file's folder;
3. the file's keys become the parser's defaults (``None``, filled in after the
   parse, so that every value given on the command line wins; a required flag may
   come from the file), and the full parse runs;
4. a file that holds a secret (a flag whose metavar is ``TOKEN``) must be kept from
   the machine's other users, and any file from being changed by them
   (:mod:`radios.secretfile`): one UsageError naming the file, its mode and the fix;
5. what came from the file is remembered on the namespace (:class:`FileOrigin`), so
   that :func:`file_errors` can turn the command's own range checks ("--id 300:
   ...") into "agent.toml: id = 300: ..." when the value came from the file.
Logging (``--log-level``, ``--log-format``, keys ``log_level`` and ``log_format``)
is configured once the arguments are read. The parser is read through argparse's
``_actions`` and action classes: private names, unchanged since Python 3.2; a flag
of a kind a file cannot give raises TypeError, which the tests catch.
"""

from __future__ import annotations

import argparse
import datetime
import difflib
import json
import math
import os
import re
import stat
import tomllib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from radios.secretfile import TOKEN, config_file_problem, secret_file_problem
from swarm.cli.util import UsageError, add_log_arguments, apply_log_arguments

#: the largest config file read (bytes); a bigger one is refused unread
MAX_FILE_BYTES = 1 << 20
#: the longest string value (characters) and the longest array a key takes
MAX_STRING = 4096
MAX_ARRAY = 64
#: the metavars of flags whose value is a path: relative to the file's folder
PATH_METAVARS = ("FILE", "DIR", "CAPTURE")
#: how much of a value or key an error message shows
SHOW_CHARS = 200
KEY_SHOW_CHARS = 60  # an unknown key as quoted in its error
#: the metavars of flags whose value is a secret: a file holding one is kept from others
SECRET_METAVARS = ("TOKEN",)


@dataclass(frozen=True)
class Key:
    """One key of a command's file: the flag's argparse action and how to read it."""

    name: str
    action: argparse.Action
    kind: str  # "bool", "int", "float", "str"
    array: bool = False

    @property
    def flag(self) -> str:
        return next(s for s in self.action.option_strings if s.startswith("--"))

    @property
    def is_secret(self) -> bool:
        return self.action.metavar in SECRET_METAVARS

    @property
    def is_path(self) -> bool:
        m = self.action.metavar
        return isinstance(m, str) and (m in PATH_METAVARS or m.endswith("|FILE"))


@dataclass
class FileOrigin:
    """Which values of a namespace came from a config file: ``path`` (as given) and
    dest -> (key, value) for each of them."""

    path: str
    values: dict[str, tuple[str, Any]] = field(default_factory=dict)
    flags: dict[str, str] = field(default_factory=dict)  # "--flag" -> dest, for every key


def prepare(p: argparse.ArgumentParser, *, config: bool = True) -> argparse.ArgumentParser:
    """Add the options every long-running command shares: ``--log-level``,
    ``--log-format`` and (``config``) ``--config FILE``. Returns ``p``."""
    add_log_arguments(p)
    if config:
        p.add_argument(
            "--config",
            metavar="FILE",
            help="read options from a TOML file: each key a flag without -- and with _ for - "
            f"(swarm config example {getattr(p, 'config_example', p.prog.split()[-1])}); "
            "flags given here override it",
        )
    return p


def keys(p: argparse.ArgumentParser) -> dict[str, Key]:
    """The keys of ``p``'s file, in the parser's order. Raises TypeError for a flag of a
    kind a file cannot give (a bug: every flag of a command with ``--config`` is a key)."""
    out: dict[str, Key] = {}
    for action in p._actions:
        longs = [s for s in action.option_strings if s.startswith("--")]
        if isinstance(action, argparse._HelpAction) or not longs or action.dest == "config":
            continue
        name = longs[0][2:].replace("-", "_")
        out[name] = _key(name, action)
    return out


def _key(name: str, action: argparse.Action) -> Key:
    if isinstance(action, (argparse._StoreTrueAction, argparse.BooleanOptionalAction)):
        return Key(name, action, "bool")
    array = isinstance(action, argparse._AppendAction) or action.nargs in ("+", "*")
    if type(action) is not argparse._StoreAction and not isinstance(action, argparse._AppendAction):
        raise TypeError(f"{action.option_strings}: a {type(action).__name__} cannot be a config key")
    kind = {int: "int", float: "float"}.get(action.type, "str")  # type: ignore[call-overload]
    return Key(name, action, kind, array)


# -- the file: hostile input ----------------------------------------------------------


def load_file(path: str) -> dict[str, Any]:
    """The TOML table in ``path``. Raises UsageError (one line naming the file) for a
    file that is missing, unreadable, not a regular file, over :data:`MAX_FILE_BYTES`,
    not UTF-8, not TOML or nested too deep."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # a FIFO must not hang us
    except OSError as exc:
        raise UsageError(f"{path}: {exc.strerror or exc}") from None
    except ValueError:  # an embedded NUL
        raise UsageError(f"{_show(path)}: not a file name") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise UsageError(f"{path}: a directory, not a config file")
        if not stat.S_ISREG(st.st_mode):
            raise UsageError(f"{path}: not a regular file")
        if st.st_size > MAX_FILE_BYTES:
            raise UsageError(f"{path}: {st.st_size} bytes; a config file is at most {MAX_FILE_BYTES} bytes")
        with os.fdopen(fd, "rb", closefd=False) as fh:
            data = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise UsageError(f"{path}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(data) > MAX_FILE_BYTES:
        raise UsageError(f"{path}: a config file is at most {MAX_FILE_BYTES} bytes")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UsageError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UsageError(f"{path}: not TOML: {exc}") from None
    except RecursionError:
        raise UsageError(f"{path}: not TOML: nested too deep") from None
    except ValueError:  # an integer of more digits than Python converts (4300)
        raise UsageError(f"{path}: not TOML: a number too long to read") from None


def file_values(p: argparse.ArgumentParser, path: str, table: dict[str, Any]) -> dict[str, tuple[str, Any]]:
    """dest -> (key, value) for each key of ``table`` (read from ``path``), checked
    against ``p``'s flags. Raises UsageError naming the file and the key."""
    known = keys(p)
    base = Path(os.path.abspath(path)).parent
    out: dict[str, tuple[str, Any]] = {}
    for name, value in table.items():
        if isinstance(value, dict):
            raise UsageError(f"{path}: [{_show_key(name)}]: a table; the file is flat, one key per flag")
        key = known.get(name)
        if key is None:
            raise UsageError(f"{path}: {_unknown(name, known)}")
        try:
            v = _value(key, value)
        except ValueError as exc:
            raise UsageError(f"{path}: {_show_key(name)} = {_show(value)}: {exc}") from None
        if key.is_path:
            v = [_relative(base, x) for x in v] if key.array else _path(key, base, v)
        out[key.action.dest] = (name, v)
    return out


def _unknown(name: str, known: dict[str, Key]) -> str:
    what = f"unknown key {_show_key(name)}"
    near = difflib.get_close_matches(name, list(known), n=1) if len(name) <= 64 else []
    if not near and len(name) <= 64:  # a flag written as such: --zenoh-connect
        plain = name.lstrip("-").replace("-", "_")
        near = [plain] if plain in known else []
    return what + (f"; did you mean {near[0]}?" if near else f"; known keys: {', '.join(known)}")


_TOML_KINDS = {"int": "an integer", "float": "a number", "str": "a string", "bool": "true or false"}


def _value(key: Key, value: Any) -> Any:
    """``value`` checked (and converted) for ``key``. Raises ValueError (the reason)."""
    if not key.array:
        return _scalar(key, value)
    if isinstance(key.action, argparse._AppendAction) and isinstance(value, str):
        value = [value]  # a flag given once (``radio = "URL"``, as before it could be repeated)
    if not isinstance(value, list):
        raise ValueError(f"an array of {_TOML_KINDS[key.kind].split(' ', 1)[-1]}s: [..]")
    if len(value) > MAX_ARRAY:
        raise ValueError(f"{len(value)} items; at most {MAX_ARRAY}")
    return [_scalar(key, x) for x in value]


def _scalar(key: Key, value: Any) -> Any:
    kind = key.kind
    ok = {
        "bool": isinstance(value, bool),
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "str": isinstance(value, str),
    }[kind]
    if not ok:
        raise ValueError(f"{_toml_type(value)}, not {_TOML_KINDS[kind]}")
    if kind == "float":
        try:
            value = float(value)
        except OverflowError:  # an integer beyond any float
            value = math.inf
        if not math.isfinite(value):
            raise ValueError("not a finite number")
    if kind == "str":
        if len(value) > MAX_STRING:
            raise ValueError(f"{len(value)} characters; at most {MAX_STRING}")
        if any(ord(c) < 0x20 or ord(c) == 0x7F for c in value):
            raise ValueError("a control character in a string")
        if key.action.type is not None:  # str.upper for --log-level
            try:
                value = key.action.type(value)  # type: ignore[operator]
            except (ValueError, TypeError, argparse.ArgumentTypeError) as exc:
                raise ValueError(str(exc) or "not valid") from None
    choices = key.action.choices
    if choices is not None and value not in choices:
        raise ValueError(f"one of {', '.join(map(str, choices))}")
    return value


def _path(key: Key, base: Path, value: str) -> str:
    """A path relative to the file's folder (``NAME=V,...`` of --radio-params is not one)."""
    meta = key.action.metavar
    if isinstance(meta, str) and meta.endswith("|FILE") and "=" in value:
        return value
    return _relative(base, value)


def _relative(base: Path, value: str) -> str:
    return value if not value or os.path.isabs(value) else os.path.normpath(base / value)


def _toml_type(value: Any) -> str:
    for t, name in (
        (bool, "true or false"),
        (int, "an integer"),
        (float, "a number"),
        (str, "a string"),
        (list, "an array"),
        (dict, "a table"),
    ):
        if isinstance(value, t):
            return name
    return "a date or time"


def _show_key(name: str) -> str:
    """A key as written in TOML: bare if it can be, else quoted and cut to
    :data:`KEY_SHOW_CHARS` (the known keys follow it on the same line: escaped
    characters such as ``\\ud800\\udc00`` took it past a line's length)."""
    if re.fullmatch(r"[A-Za-z0-9_-]{1,60}", name):
        return name
    text = json.dumps(name[: KEY_SHOW_CHARS + 1])
    return text if len(text) <= KEY_SHOW_CHARS else text[: KEY_SHOW_CHARS - 3] + "..."


def _show(value: Any) -> str:
    """A scalar or a flat array as TOML, cut to :data:`SHOW_CHARS`; others by type
    (never a recursive repr: a hostile value may be nested thousands deep)."""
    if isinstance(value, list):
        if not all(isinstance(x, (str, int, float)) for x in value):
            return "[...]"
        text = "[" + ", ".join(_show(x) for x in value[:8]) + (", ...]" if len(value) > 8 else "]")
    elif isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, (int, float)):
        text = repr(value)
    elif isinstance(value, str):
        text = json.dumps(value[: SHOW_CHARS + 1])
    elif isinstance(value, (datetime.date, datetime.time)):
        text = value.isoformat()  # datetime is a date
    else:
        return _toml_type(value)
    return text if len(text) <= SHOW_CHARS else text[: SHOW_CHARS - 3] + "..."


# -- reading a command's arguments ------------------------------------------------------


def read_arguments(
    p: argparse.ArgumentParser, argv: Sequence[str] | None, *, config: bool = True
) -> argparse.Namespace:
    """Parse ``argv`` with ``p`` (plus :func:`prepare`'s options) and, with ``--config
    FILE``, the file's keys under it; configure logging. The namespace's
    ``config_origin`` is a :class:`FileOrigin` or None. Raises UsageError for a bad
    file; argparse's own errors exit 2 as usual."""
    prepare(p, config=config)
    if not config:
        a = p.parse_args(argv)
        apply_log_arguments(a)
        return a
    path = _config_path(p, argv)
    origin, displaced = None, {}
    if path is not None:
        origin = FileOrigin(path, file_values(p, path, load_file(path)))
        origin.flags = {k.flag: k.action.dest for k in keys(p).values()}
        displaced = _under(p, origin)
    a = p.parse_args(argv)
    if origin is not None and path is not None:
        secrets = [name for name, _v in origin.values.values() if keys(p)[name].is_secret]
        _fill(p, a, origin, displaced)
        _check_mode(path, secrets)
    a.config_origin = origin
    apply_log_arguments(a)
    return a


def _check_mode(path: str, secrets: list[str]) -> None:
    """A file holding a secret (``secrets``: its keys) must be kept from others, any file
    from being changed by them (:mod:`radios.secretfile`). Raises UsageError."""
    if secrets:
        why = secret_file_problem(path, TOKEN, f" (it holds {' and '.join(secrets)})")
    else:
        why = config_file_problem(path)
    if why is not None:
        raise UsageError(why)


def _config_path(p: argparse.ArgumentParser, argv: Sequence[str] | None) -> str | None:
    """``--config`` as the full parser reads it (abbreviations too), nothing required."""
    required = [x for x in p._actions if x.required]
    for x in required:
        x.required = False
    try:
        first, _ = p.parse_known_args(argv)
    finally:
        for x in required:
            x.required = True
    return first.config


def _under(p: argparse.ArgumentParser, origin: FileOrigin) -> dict[str, Any]:
    """The file's keys become defaults of None, filled in by :func:`_fill` when the
    command line gives no value; their flags are no longer required. Returns the
    defaults they displaced."""
    displaced = {x.dest: x.default for x in p._actions if x.dest in origin.values}
    for x in p._actions:
        if x.dest in origin.values:
            x.required = False
    p.set_defaults(**{dest: None for dest in origin.values})
    return displaced


def _fill(
    p: argparse.ArgumentParser, a: argparse.Namespace, origin: FileOrigin, displaced: dict[str, Any]
) -> None:
    """The file's values where the command line gave none; a flag given on the command
    line also drops the file's value of a flag it excludes (``--token-file`` over a
    file's ``token``). Raises UsageError for a file giving two exclusive keys."""
    on_cli = {d for d in origin.values if getattr(a, d) is not None}
    for dest in on_cli:
        del origin.values[dest]  # the command line's value stands
    for group in p._mutually_exclusive_groups:
        dests = [x.dest for x in group._group_actions]
        from_file = [d for d in dests if d in origin.values]
        if any(d in on_cli or (d not in displaced and getattr(a, d) != p.get_default(d)) for d in dests):
            for d in from_file:  # the command line chose another of the group
                del origin.values[d]
                setattr(a, d, displaced[d])
        elif len(from_file) > 1:
            names = " and ".join(origin.values[d][0] for d in from_file)
            raise UsageError(f"{origin.path}: {names}: give one of them, not both")
    for dest, (_, value) in origin.values.items():
        setattr(a, dest, value)


# -- the command's own checks, told which values came from the file ------------------

_FLAG = re.compile(r"--[a-z0-9][a-z0-9-]*")
_HEAD = re.compile(r"""(--[a-z0-9][a-z0-9-]*)(?: ('[^']*'|"[^"]*"|\S+))?: """)


@contextmanager
def file_errors(a: argparse.Namespace) -> Iterator[None]:
    """Run a command's checks of its arguments: a UsageError about a flag whose value
    came from the config file is re-raised naming the file and the key instead
    ("--id 300: agent ids are 1..250" -> "agent.toml: id = 300: agent ids are 1..250")."""
    try:
        yield
    except UsageError as exc:
        origin = getattr(a, "config_origin", None)
        text = blame(str(exc), origin) if origin is not None else None
        if text is None:
            raise
        raise UsageError(text) from None


def blame(message: str, origin: FileOrigin) -> str | None:
    """``message`` rewritten for the first flag it names whose value came from the file
    (None if it names none)."""
    for flag in _FLAG.findall(message):
        dest = origin.flags.get(flag)
        if dest is None or dest not in origin.values:
            continue
        key, value = origin.values[dest]
        head = _HEAD.match(message)
        if head is not None and head.group(1) == flag:
            message = message[head.end() :]  # "--id 300: " -> the file's own words
        return f"{origin.path}: {key} = {_show(value)}: {message}"
    return None
