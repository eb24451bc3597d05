"""pymavlink client helpers shared by the simulator tests (plain scripts of the kind
PX4's and ArduPilot's documentation show): the one ``wait_msg`` and ``command``.

PX4 says what it says in EVENT messages (id 410), which pymavlink's dialects do not
know: it hands them over as ``UNKNOWN_410``; :func:`event_id` reads the event's id
from such a frame, and ``command(..., texts=)`` notes each as ``event 0x<id>``."""

from __future__ import annotations

import time
from collections.abc import Callable

from pymavlink import mavutil

from firmware_bridge.px4_events import parse_event

EVENT = "UNKNOWN_410"


def event_id(msg: object) -> int | None:
    """The id of the PX4 EVENT ``msg`` (an ``UNKNOWN_410``), None if it is not one."""
    ev = parse_event(bytes(getattr(msg, "data", b"")))
    return None if ev is None else ev.id


def event_text(ev_id: int) -> str:
    return f"event 0x{ev_id:x}"


#: Wall seconds a simulator test waits for a message or an answer: the simulators run
#: faster than real time, so this only bounds a failing test.
MAV_DEADLINE = 20.0


def _any(_msg: object) -> bool:
    return True


def wait_msg(
    conn: mavutil.mavfile,
    types: str | list[str],
    cond: Callable[[object], bool] = _any,
    timeout: float = MAV_DEADLINE,
    tick: Callable[[], None] | None = None,
) -> object:
    """The first message of ``types`` satisfying ``cond`` (any, by default) within
    ``timeout`` s; ``tick`` runs between reads (e.g. to keep a setpoint stream going)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if tick is not None:
            tick()
        m = conn.recv_match(type=types, blocking=True, timeout=0.05)
        if m is not None and cond(m):
            return m
    raise AssertionError(f"no {types} matching in {timeout} s")


def command(
    conn: mavutil.mavfile,
    cmd: int,
    *params: float,
    timeout: float = MAV_DEADLINE,
    tick: Callable[[], None] | None = None,
    texts: list[str] | None = None,
) -> int:
    """Send COMMAND_LONG ``cmd`` and return the COMMAND_ACK result; STATUSTEXTs (and
    PX4's EVENTs, as ``event 0x<id>``) seen meanwhile are appended to ``texts``."""
    p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
    conn.mav.command_long_send(conn.target_system, 1, cmd, 0, *p)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if tick is not None:
            tick()
        m = conn.recv_match(type=["COMMAND_ACK", "STATUSTEXT", EVENT], blocking=True, timeout=0.05)
        if m is None:
            continue
        if m.get_type() == EVENT:
            ev = event_id(m)
            if texts is not None and ev is not None:
                texts.append(event_text(ev))
        elif m.get_type() == "STATUSTEXT":
            if texts is not None:
                texts.append(m.text)
        elif m.command == cmd:
            return int(m.result)
    raise AssertionError(f"no COMMAND_ACK for {cmd}")
