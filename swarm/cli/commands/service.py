"""``swarm service print|install agent|gcs``: the systemd units shipped in the package.

Theory of operation
-------------------
The package carries two unit templates (``swarm/cli/units``): ``swarm-agent@.service``,
whose instance is the name of the agent's settings (``swarm-agent@NAME`` runs
``swarm agent --config /etc/uav-swarm/NAME.toml``), and ``swarm-gcs.service``
(``swarm gcs --config /etc/uav-swarm/gcs.toml``). Their ``@SWARM@`` becomes the
command that runs this very installation: the running interpreter's path
(``sys.executable``, not resolved: a virtual environment's ``bin/python`` keeps its
packages) with ``-m swarm.cli``. That survives a venv in ``/opt/uav-swarm`` and needs
no ``PATH``. The path is quoted and escaped as systemd's command lines want (``%``
and ``$`` are systemd's own); a path with a control character is refused.

``print`` writes the unit to stdout. ``install`` writes it to ``/etc/systemd/system``
(root only: a one-line error otherwise) or ``--dir DIR``, through a temporary file
renamed into place: a symlink there is replaced, never followed. A file or symlink
already there (a masked unit is a symlink to ``/dev/null``) is kept unless
``--force``; the same content is left alone. Then it prints the commands that finish
the set-up (the service user in ``dialout``, the settings folder, ``systemctl
daemon-reload`` and ``enable --now``).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
from importlib import resources
from pathlib import Path

from swarm.cli.util import UsageError, guarded, parser
from swarm.errors import SwarmError

PROG = "swarm service"
UNIT_DIR = "/etc/systemd/system"
CONFIG_DIR = "/etc/uav-swarm"
STATE_DIR = "/var/lib/uav-swarm"
USER = "uav-swarm"
#: kind -> unit file name in the package and in the unit folder
UNITS = {"agent": "swarm-agent@.service", "gcs": "swarm-gcs.service"}
MARK = "@SWARM@"


class ServiceError(SwarmError):
    """The unit cannot be written where asked (exit 1)."""


def systemd_quote(word: str) -> str:
    """``word`` as one systemd command-line word: quoted when it has a space or a quote,
    ``%`` -> ``%%`` and ``$`` -> ``$$``. Raises UsageError for a control character."""
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in word):
        raise UsageError(f"{word!r}: a path with a control character cannot go in a unit file")
    word = word.replace("%", "%%").replace("$", "$$")
    if not any(c in word for c in " \t\"'\\;"):
        return word
    return '"' + word.replace("\\", "\\\\").replace('"', '\\"') + '"'


def swarm_command(executable: str | None = None) -> str:
    """The ExecStart words that run this installation's ``swarm``. Raises UsageError
    when the interpreter's path is unknown or relative."""
    exe = sys.executable if executable is None else executable
    if not exe or not os.path.isabs(exe):
        raise UsageError(
            f"the Python interpreter's path is unknown ({exe!r}): run swarm from its installation"
        )
    return f"{systemd_quote(exe)} -m swarm.cli"


def unit_text(kind: str, executable: str | None = None) -> str:
    """The unit for ``kind`` (agent, gcs) with this installation's command."""
    template = resources.files("swarm.cli").joinpath("units", UNITS[kind]).read_text(encoding="utf-8")
    return template.replace(MARK, swarm_command(executable))


def build_parser() -> argparse.ArgumentParser:
    p = parser(PROG, "Print or install the systemd unit of a swarm agent or of the ground station.")
    sub = p.add_subparsers(dest="action", required=True, metavar="print|install")
    pr = sub.add_parser("print", help="print the unit on stdout")
    pr.add_argument("kind", choices=UNITS, help="agent (swarm-agent@.service) or gcs (swarm-gcs.service)")
    ins = sub.add_parser("install", help=f"write the unit to {UNIT_DIR} (root) or --dir")
    ins.add_argument("kind", choices=UNITS, help="agent (swarm-agent@.service) or gcs (swarm-gcs.service)")
    ins.add_argument("--dir", metavar="DIR", help=f"the folder to write it to (default {UNIT_DIR}, as root)")
    ins.add_argument("--force", action="store_true", help="replace a different unit file of the same name")
    return p


def _target(a: argparse.Namespace) -> Path:
    """Where the unit goes. Raises ServiceError (not root) or UsageError (bad --dir)."""
    if a.dir is None:
        if os.geteuid() != 0:
            raise ServiceError(
                f"installing into {UNIT_DIR} needs root: run it with sudo, or give --dir DIR "
                f"(swarm service print {a.kind} shows the unit)"
            )
        folder = Path(UNIT_DIR)
    else:
        folder = Path(a.dir)
        if not folder.is_dir():
            raise UsageError(f"--dir {a.dir}: not a directory")
    return folder / UNITS[a.kind]


def _existing(path: Path, force: bool) -> str | None:
    """The text of the unit file at ``path`` (None: nothing there, or a symlink that
    ``force`` replaces). Raises ServiceError for a symlink without ``force``, a folder."""
    if path.is_symlink():
        if not force:
            raise ServiceError(
                f"{path} is a symlink (to {os.readlink(path)}; a masked unit?): "
                "kept (--force replaces the link)"
            )
        return None
    if not path.exists():
        return None
    if not path.is_file():
        raise ServiceError(f"{path} exists and is not a file")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else "not UTF-8 text"
        raise ServiceError(f"{path}: {why}") from None


def write_unit(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` (mode 0644) through a temporary file renamed into
    place. Raises ServiceError."""
    fd, tmp = -1, ""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        os.fchmod(fd, 0o644)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            fd = -1
            f.write(text)
        os.replace(tmp, path)
        tmp = ""
    except OSError as exc:
        raise ServiceError(f"cannot write {path}: {exc.strerror or exc}") from None
    finally:
        if fd >= 0:
            os.close(fd)
        if tmp:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def next_steps(kind: str, path: Path) -> list[str]:
    """What the operator does next, as shell commands (with sudo)."""
    unit = "swarm-agent@NAME" if kind == "agent" else "swarm-gcs"
    conf = f"{CONFIG_DIR}/NAME.toml" if kind == "agent" else f"{CONFIG_DIR}/gcs.toml"
    steps = [
        f"sudo useradd --system --user-group --groups dialout --home-dir {STATE_DIR} "
        f"--no-create-home --shell /usr/sbin/nologin {USER}",
        f"sudo install -d -m 0750 -o root -g {USER} {CONFIG_DIR}",
        f"sudo install -d -m 0750 -o {USER} -g {USER} {STATE_DIR}"
        "   # captures (StateDirectory=): there before the first start, for swarm doctor",
        f"sudo install -m 0640 -o root -g {USER} {Path(conf).name} {conf}   # the settings",
        f"sudo install -m 0400 -o {USER} -g {USER} swarm.key {CONFIG_DIR}/swarm.key"
        "   # the swarm key: its user only",
    ]
    if path.parent != Path(UNIT_DIR):
        steps.append(f"sudo cp {path} {UNIT_DIR}/")
    steps += [
        "sudo systemctl daemon-reload",
        f"sudo systemctl enable --now {unit}",
        f"journalctl -u {unit} -f",
    ]
    return steps


def _install(a: argparse.Namespace) -> int:
    text = unit_text(a.kind)
    path = _target(a)
    old = _existing(path, a.force)
    if old == text:
        print(f"{path}: unchanged")
    elif old is not None and not a.force:
        raise ServiceError(f"{path} exists with other content: kept (--force replaces it)")
    else:
        write_unit(path, text)
        print(f"wrote {path}")
    print("next (NAME: the agent's settings, /etc/uav-swarm/NAME.toml):" if a.kind == "agent" else "next:")
    for line in next_steps(a.kind, path):
        print(f"  {line}")
    return 0


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if a.action == "print":
        sys.stdout.write(unit_text(a.kind))
        sys.stdout.flush()
        return 0
    return _install(a)


__all__ = ["UNITS", "ServiceError", "main", "next_steps", "swarm_command", "systemd_quote", "unit_text"]
