"""Where a node keeps what it must remember across restarts: ``--state-dir DIR``.

Theory of operation
-------------------
A signed node keeps small files there (:mod:`radios.signing_state`: its signing
clock; a station joined over Zenoh, its replay guard too), one per node and channel,
named by the node (``agent-NAME-ID.signing.json``, ``gcs-NAME-ID.signing.json``,
``gcs-NAME-ID-NET.signing.json`` per channel, ``gcs-NAME.federation.json``), so
several agents of one machine (the demo, the benches) never share one.

The folder is ``--state-dir DIR`` (config key ``state_dir``), else the service
manager's (``$STATE_DIRECTORY``: systemd sets it from the units'
``StateDirectory=uav-swarm``, ``/var/lib/uav-swarm``), else ``$XDG_STATE_HOME/uav-swarm``,
else ``~/.local/state/uav-swarm``; made with mode 0700 if missing. A folder given
(flag or file) that cannot be used (not a folder, not writable) is a usage error
(exit 2): the operator asked for it. The default one that cannot be used is one
warning line and the node runs without (replays are then refused from the wall clock
at start only: across a restart with a clock behind the swarm's, a recording less
than a minute old may pass), so a read-only home never keeps an aircraft on the
ground. A folder other users may write to is one warning line: they could weaken the
protection. Without ``--key`` nothing is kept (nothing is signed) and no folder is
made.
"""

from __future__ import annotations

import argparse
import os
import stat
import sys
from collections.abc import Mapping
from pathlib import Path

from swarm.cli.util import UsageError

APP = "uav-swarm"


def add_state_dir_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--state-dir",
        metavar="DIR",
        help="where this node keeps what it needs across restarts (with --key: its signing "
        "clock, so nothing recorded before a restart is taken after it); default "
        "$STATE_DIRECTORY, $XDG_STATE_HOME/uav-swarm or ~/.local/state/uav-swarm",
    )


def default_state_dir(env: Mapping[str, str]) -> Path | None:
    """The default folder (module docstring), None if the environment names none."""
    found = _default(env)
    return None if found is None else found[1]


def _default(env: Mapping[str, str]) -> tuple[Path, Path] | None:
    """(the folder that must exist already, the state folder in it)."""
    service = env.get("STATE_DIRECTORY", "")
    if service:
        path = Path(service.split(":")[0])  # systemd: one path per StateDirectory= entry
        return path, path
    xdg = env.get("XDG_STATE_HOME", "")
    if os.path.isabs(xdg):
        return Path(xdg), Path(xdg) / APP
    home = env.get("HOME", "")
    return (Path(home), Path(home) / ".local" / "state" / APP) if os.path.isabs(home) else None


def _prepare(path: Path, *, parents: bool) -> str | None:
    """Make the folder if missing (0700); None once usable, else why not."""
    try:
        if parents:
            os.makedirs(path, mode=0o700, exist_ok=True)
        else:
            try:
                os.mkdir(path, 0o700)
            except FileExistsError:
                pass
        st = os.stat(path)
    except OSError as exc:
        return exc.strerror or str(exc)
    if not stat.S_ISDIR(st.st_mode):
        return "not a folder"
    if not os.access(path, os.W_OK | os.X_OK):
        return "not writable by this user"
    return None


def open_state_dir(given: str | None, prog: str, env: Mapping[str, str] | None = None) -> Path | None:
    """The node's state folder, made if missing; None (one warning line) if the default
    one cannot be used.

    Raises:
        UsageError: a folder given (``--state-dir``) that cannot be used.
    """
    env = os.environ if env is None else env
    if given is not None:
        path = Path(given)
        why = _prepare(path, parents=False)
        if why is not None:
            raise UsageError(f"--state-dir {given}: {why}")
    else:
        pair = _default(env)
        found = None if pair is None else pair[1]
        if pair is None:
            why = "no $STATE_DIRECTORY, $XDG_STATE_HOME or $HOME"
        elif not pair[0].is_dir():
            why = f"{pair[0]} is no folder"  # a home that does not exist is not made
        else:
            why = _prepare(pair[1], parents=True)
        if found is None or why is not None:
            where = "" if found is None else f" {found}"
            print(
                f"{prog}: warning: no state folder{where} ({why}): replays recorded before a "
                "restart are refused from the wall clock only (give --state-dir DIR)",
                file=sys.stderr,
                flush=True,
            )
            return None
        path = found
    if os.stat(path).st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        print(
            f"{prog}: warning: state folder {path} is writable by other users: they could "
            "weaken replay protection (chmod 700 it)",
            file=sys.stderr,
            flush=True,
        )
    return path


def node_file(folder: Path, kind: str, name: str, ident: int | None, what: str, channel: str = "") -> str:
    """The path of one node's file ``what`` (``signing``, ``federation``) in ``folder``."""
    parts = [kind, name] + ([str(ident)] if ident is not None else []) + ([channel] if channel else [])
    return str(folder / f"{'-'.join(parts)}.{what}.json")


__all__ = ["add_state_dir_argument", "default_state_dir", "node_file", "open_state_dir"]
