"""Reading a SiK radio's registers strictly: every line checked against the firmware's table,
and over the air every value confirmed by two answers.

Theory of operation
-------------------
A register line (``S3:NETID=25``, multipoint ``[2] S3:NETID=25``) counts only if it is
whole: the form matches exactly, the name is one of the firmware's registers (the
flavour's table, plus S16 ``ENCRYPTION_LEVEL`` for the standard firmware's AES builds)
and the S number is that register's number. :func:`parse_register_line` is that check.

* **Local** (:func:`parse_local`): the serial line between host and radio does not lose
  bytes, so any line of an ``ATI5`` answer that is not a register line is an error
  (:class:`~radios.errors.ATError` naming the line), and so is a known name under the
  wrong number or twice. A well-formed line with a name the table does not know, under
  a number the table does not use, is kept (firmware variants add registers, such as
  ``S16:GPI1_1R/CIN=0``).
* **Remote** (:func:`read_remote`, ``RT`` commands): the answer crosses the air in
  packets of at most 32 bytes, with no retransmission, and the remote captures at most
  252 bytes (a multipoint ``RTI5`` with its ``[id] `` prefixes does not fit). A lost
  packet in the middle of ``RTI5`` splices two lines into one, which can look whole
  (``S3:NETID=2`` + ``0`` of the next line). So nothing read over the air is believed
  once: a value is accepted when two answers agree on it, the strict lines of one
  ``RTI5`` and then ``RTSn?`` per register (a one-line answer travels in one packet, so
  it arrives whole or not at all), each register asked at most ``tries`` times. In
  multipoint every answer must carry the target node's ``[id] `` prefix: another
  node's answer is not this radio's. Registers still unconfirmed are returned as
  ``unreadable`` for the caller to name; if neither ``RTI5`` nor the first ``RTSn?``
  is answered, the link is down (:class:`~radios.errors.ATTimeoutError`).

The remote reader is given ``ask`` (send one command line, return its reply lines,
raise ``ATTimeoutError`` when nothing comes back), so its rules are tested without a
radio and run unchanged over a real link.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field

from radios.errors import ATError, ATTimeoutError
from radios.sik.param_table import AES_PARAM, UINT32_MAX, params_for

_REGISTER = re.compile(r"^(?:\[(\d{1,5})\] )?S(\d{1,2}):\s?([A-Z][A-Z0-9_/]*)=(\d{1,10})$")
_VALUE = re.compile(r"^(?:\[(\d{1,5})\] )?(\d{1,10})$")

DEFAULT_TRIES = 5  # answers asked for per register over the air (RTI5 counts as one)


def register_table(flavour: str) -> dict[str, int]:
    """Register name -> S number of a firmware flavour (standard includes the AES register)."""
    table = {spec.name: spec.index for spec in params_for(flavour)}
    if flavour == "standard":
        table[AES_PARAM.name] = AES_PARAM.index
    return table


def _prefix_ok(prefix: str | None, node: int | None) -> bool:
    """``node`` None: any single prefix or none (a local radio); else exactly ``[node]``."""
    return node is None or (prefix is not None and int(prefix) == node)


def parse_register_line(
    line: str, table: dict[str, int], node: int | None = None, *, known_only: bool = True
) -> tuple[str, int, int] | None:
    """``'S3:NETID=25'`` -> ``('NETID', 3, 25)``, or None if the line is not a whole
    register line of ``table`` (see the module docstring). ``node`` demands the
    multipoint prefix ``[node] ``; ``known_only=False`` also accepts a well-formed line
    whose name the table does not know (if its number is not a known register's)."""
    match = _REGISTER.match(line.strip())
    if match is None or not _prefix_ok(match.group(1), node):
        return None
    index, name, value = int(match.group(2)), match.group(3), int(match.group(4))
    if value > UINT32_MAX:
        return None
    if name in table:
        return (name, index, value) if table[name] == index else None
    if known_only or index in table.values():
        return None
    return name, index, value


def parse_local(lines: list[str], flavour: str, where: str) -> dict[str, tuple[int, int]]:
    """A local ``ATI5`` answer -> name -> (S number, value), in the radio's order.

    Raises :class:`ATError` naming the first line that is not a register line of the
    flavour's table (or is one twice), and if there is no register line at all.
    """
    table = register_table(flavour)
    found: dict[str, tuple[int, int]] = {}
    for line in lines:
        parsed = parse_register_line(line, table, known_only=False)
        if parsed is None or parsed[0] in found:
            what = "a second" if parsed is not None else "not a"
            raise ATError(f"ATI5 on {where}: {line.strip()[:60]!r} is {what} {flavour} SiK register line")
        found[parsed[0]] = (parsed[1], parsed[2])
    if not found:
        raise ATError(f"ATI5 on {where} returned no parameter lines")
    return found


def parse_value(lines: list[str], node: int | None) -> int | None:
    """The answer to ``ATSn?`` (one line, the number; with ``node``, prefixed ``[node] ``),
    or None for anything else (ERROR, another node's answer, a garbled line)."""
    values = []
    for line in lines:
        match = _VALUE.match(line.strip())
        if match is not None and _prefix_ok(match.group(1), node):
            values.append(int(match.group(2)))
    return values[0] if len(values) == 1 and values[0] <= UINT32_MAX else None


@dataclass
class RemoteReadout:
    """What :func:`read_remote` could and could not read."""

    values: dict[str, tuple[int, int]]  # name -> (S number, value), confirmed, in S order
    unreadable: list[str] = field(default_factory=list)  # registers no two answers agreed on
    garbled: int = 0  # RTI5 lines that were not whole register lines


def _confirmed(seen: list[int]) -> int | None:
    """The latest value seen at least twice, if any."""
    for value in reversed(seen):
        if seen.count(value) >= 2:
            return value
    return None


def read_remote(
    ask: Callable[[str], list[str]], flavour: str, node: int | None = None, tries: int = DEFAULT_TRIES
) -> RemoteReadout:
    """Read every register of the remote radio (see the module docstring).

    ``ask`` sends ``RTI5``/``RTSn?`` (with ``,<node>`` appended in multipoint when
    ``node`` is given) and returns the reply lines. Raises :class:`ATTimeoutError` if the
    remote radio answers nothing at all.
    """
    table = register_table(flavour)
    target = f",{node}" if node is not None else ""
    seen: dict[str, list[int]] = {name: [] for name in table}
    garbled = 0
    answered = False
    try:
        for line in ask("RTI5" + target):
            answered = True
            parsed = parse_register_line(line, table, node)
            if parsed is None:
                garbled += 1
            else:
                seen[parsed[0]].append(parsed[2])
    except ATTimeoutError:
        pass
    wanted = [n for n in table if n != AES_PARAM.name or seen[n]]  # S16 only where RTI5 showed it
    values: dict[str, tuple[int, int]] = {}
    unreadable: list[str] = []
    for name in sorted(wanted, key=table.__getitem__):
        for _ in range(tries):
            if _confirmed(seen[name]) is not None:
                break
            try:
                value = parse_value(ask(f"RTS{table[name]}?{target}"), node)
                answered = True
            except ATTimeoutError:
                if not answered:
                    raise ATTimeoutError(
                        f"the remote radio answered neither RTI5 nor RTS{table[name]}? (link down?)"
                    ) from None
                continue
            if value is not None:
                seen[name].append(value)
        confirmed = _confirmed(seen[name])
        if confirmed is None:
            unreadable.append(name)
        else:
            values[name] = (table[name], confirmed)
    return RemoteReadout(values, unreadable, garbled)
