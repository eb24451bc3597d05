"""Is a file that holds a secret (a key, a token) kept from the other users of the machine?

Theory of operation
-------------------
A secret in a file others may read is no longer a secret, and one in a file others
may write is no longer the owner's; a node that starts with either says nothing
about it and carries on for months. :func:`secret_file_problem` reads a file's mode
(``os.stat``: the file a link points to) and says, in one line that completes
"PATH: ...", what is wrong and the fix (``chmod 600 PATH``), or None when nothing
is. Two rules:

* :data:`KEY` (the swarm's signing key, a TLS private key): the owner only, no bit for
  the group or others (0600 or 0400), as ``swarm doctor`` and ssh ask of a private key.
* :data:`TOKEN` (the station page's token, a config file that holds it): no bit for
  others, the group may not write (nor execute), and may read only when the file's
  group is this process's own effective group. The service set-up installs the
  settings and the token as 0640 root:uav-swarm and runs the station as group
  uav-swarm: the service reads them through its group and cannot change them; a file
  of another group (``users``, shared with every login) is refused, and so is the
  service's file read by another user (root trying the service's settings by hand:
  ``sudo -u uav-swarm``, as the service runs). Only the effective group counts: a
  supplementary group is usually shared.

:func:`config_file_problem` is for a settings file that holds no secret: others may
read it, but neither others nor a group that is not this process's may change it
(the settings choose the key file, the listening address, who may command).

A file that cannot be stat'ed or is not a regular file is not judged here (None): the
reader that opens it next says what it is. The checks run as the command starts and
cost one ``stat`` each.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

KEY = "key"
TOKEN = "token"

_VERBS = ((4, "readable"), (2, "writable"), (1, "executable"))


def _verbs(bits: int) -> str:
    return " and ".join(v for b, v in _VERBS if bits & b)


def _regular_mode(path: str | Path) -> os.stat_result | None:
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st if stat.S_ISREG(st.st_mode) else None


def _group(gid: int) -> str:
    """``uav-swarm (gid 999)``, or ``(gid 999)`` for a group without a name."""
    try:
        import grp

        return f"{grp.getgrgid(gid).gr_name} (gid {gid})"
    except (ImportError, KeyError):
        return f"(gid {gid})"


def _describe(group: int, others: int, gid: int, foreign_read: bool) -> str:
    """``readable by its group, readable and writable by others`` for the offending bits."""
    g = _verbs(group)
    o = _verbs(others)
    whose = "its group"
    if foreign_read:
        whose += f" {_group(gid)}, not this process's group {_group(os.getegid())}"
    if g and o and g == o and not foreign_read:
        return f"{g} by its group and others"
    parts = [f"{g} by {whose}"] if g else []
    if o:
        parts.append(f"{o} by others")
    return ", ".join(parts)


def secret_file_problem(path: str | Path, policy: str, what: str = "") -> str | None:
    """What is wrong with the mode of the file ``path`` holding a secret under
    ``policy`` (:data:`KEY` or :data:`TOKEN`), as one line "PATH<what>: mode 0644:
    readable by others; fix: chmod 600 PATH"; None when nothing is (or the file is
    missing or not a regular file: its reader reports that).

    Raises:
        ValueError: an unknown policy.
    """
    if policy not in (KEY, TOKEN):
        raise ValueError(f"unknown secret file policy {policy!r}")
    st = _regular_mode(path)
    if st is None:
        return None
    perm = stat.S_IMODE(st.st_mode)
    group, others = (perm >> 3) & 7, perm & 7
    foreign_read = False
    if policy == TOKEN:
        own = st.st_gid == os.getegid()
        foreign_read = bool(group & 4) and not own
        group &= 3 if own else 7  # its own group may read
    if not (group or others):
        return None
    who = _describe(group, others, st.st_gid, foreign_read)
    fix = f"chmod 600 {path}"
    if foreign_read and not (group & 3 or others):  # only that: the service set-up run by another user
        fix += " (or run as its group, as the service does: sudo -u USER ...)"
    return f"{path}{what}: mode {perm:04o}: {who}; fix: {fix}"


def config_file_problem(path: str | Path) -> str | None:
    """What is wrong with a settings file ``path`` others (or a group not this
    process's) may change, as one line ending in the fix; None when nothing is."""
    st = _regular_mode(path)
    if st is None:
        return None
    perm = stat.S_IMODE(st.st_mode)
    others = perm & 2
    group = (perm >> 3) & 2 if st.st_gid != os.getegid() else 0
    if not (group or others):
        return None
    who = "go" if group and others else "g" if group else "o"
    whose = f"its group {_group(st.st_gid)}, not this process's group {_group(os.getegid())}"
    text = ", ".join(
        x for x in (f"writable by {whose}" if group else "", "writable by others" if others else "") if x
    )
    return f"{path}: mode {perm:04o}: {text}; fix: chmod {who}-w {path}"


__all__ = ["KEY", "TOKEN", "config_file_problem", "secret_file_problem"]
