"""The pre-flight check's verdicts: observed facts in, one line per check out.

Theory of operation
-------------------
``swarm doctor`` looks at a field set-up (serial devices, the SiK radio, the flight
controller, the signing key, the clock, Zenoh endpoints, disk space) in two steps.
The probes (:mod:`swarm.runtime.doctor`) gather *facts*: plain frozen values that say
what was seen (a file's mode, the parameters a radio printed, the fields of a
HEARTBEAT) and never judge. The verdicts here turn facts (and ``now``, passed in) into
:class:`Check` lines: a status, a name, what was seen and, unless it passed, how to fix
it. No I/O, no clock: every rule is tested with hand-made facts, a clock in 1970
included.

* :class:`Check` is one line: ``pass`` (as it must be), ``info`` (reported, judged by
  no rule), ``warn`` (flyable, but look at it) or ``fail`` (do not fly).
* :func:`ok` and :func:`exit_code`: 0 when nothing fails (warnings allowed), else 1.
* :func:`text_line` and :func:`report_json` print them; every field is cut to
  :data:`FIELD_MAX` characters and, in text, control characters are escaped, since a
  radio's banner or a file name may hold any bytes a hostile sender chose.

The verdicts themselves live in :mod:`.radio` (the SiK radio), :mod:`.vehicle` (the
flight controller) and :mod:`.host` (devices, key, clock, Zenoh, disk).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

Status = Literal["pass", "info", "warn", "fail"]
STATUSES: tuple[Status, ...] = ("pass", "info", "warn", "fail")
FIELD_MAX = 300  # characters of one field of a check (a hostile banner is cut here)


def clean(text: object, limit: int = FIELD_MAX) -> str:
    """``text`` as one printable line: control and other unprintable characters
    escaped (``\\x1b``), cut to ``limit`` characters."""
    out = []
    for c in str(text):
        if c.isprintable():
            out.append(c)
        elif ord(c) < 0x100:
            out.append(f"\\x{ord(c):02x}")
        else:
            out.append(f"\\u{ord(c):04x}" if ord(c) < 0x10000 else f"\\U{ord(c):08x}")
    line = "".join(out)
    return line if len(line) <= limit else line[: limit - 3] + "..."


@dataclass(frozen=True)
class Check:
    """One line of the checklist: ``name`` (``radio NETID``), what was ``seen`` and,
    for a warning or a failure, the ``fix``."""

    status: Status
    name: str
    seen: str
    fix: str = ""

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise ValueError(f"check status {self.status!r}: one of {', '.join(STATUSES)}")


def passed(name: str, seen: str) -> Check:
    return Check("pass", name, seen)


def info(name: str, seen: str, fix: str = "") -> Check:
    return Check("info", name, seen, fix)


def warn(name: str, seen: str, fix: str) -> Check:
    return Check("warn", name, seen, fix)


def fail(name: str, seen: str, fix: str) -> Check:
    return Check("fail", name, seen, fix)


def ok(checks: Iterable[Check]) -> bool:
    """True when no check failed (warnings allowed)."""
    return all(c.status != "fail" for c in checks)


def exit_code(checks: Iterable[Check]) -> int:
    """0 when nothing failed, 1 otherwise."""
    return 0 if ok(checks) else 1


def text_line(c: Check) -> str:
    """``PASS radio NETID 25 (expected 25)`` or ``FAIL key ...; fix: chmod 600 ...``."""
    line = f"{c.status.upper():<4} {clean(c.name)} {clean(c.seen)}"
    return line + (f"; fix: {clean(c.fix)}" if c.fix else "")


def report_json(checks: Sequence[Check]) -> dict[str, Any]:
    """``{"ok": bool, "checks": [{"status", "name", "seen", "fix"}...]}`` (fields cut
    to :data:`FIELD_MAX`; JSON escapes the rest)."""
    return {
        "ok": ok(checks),
        "checks": [
            {
                "status": c.status,
                "name": c.name[:FIELD_MAX],
                "seen": c.seen[:FIELD_MAX],
                "fix": c.fix[:FIELD_MAX],
            }
            for c in checks
        ],
    }


def summary(checks: Sequence[Check]) -> str:
    """``3 passed, 1 warning, 1 failure: do not fly`` (one line)."""
    n = {s: sum(1 for c in checks if c.status == s) for s in STATUSES}
    parts = [f"{n['pass']} passed", f"{n['warn']} warning{'s' if n['warn'] != 1 else ''}"]
    parts.append(f"{n['fail']} failure{'s' if n['fail'] != 1 else ''}")
    verdict = "ready" if n["fail"] == 0 else "not ready: fix the failures above"
    return ", ".join(parts) + f": {verdict}"


__all__ = [
    "FIELD_MAX",
    "STATUSES",
    "Check",
    "Status",
    "clean",
    "exit_code",
    "fail",
    "info",
    "ok",
    "passed",
    "report_json",
    "summary",
    "text_line",
    "warn",
]
