"""Probe of the flight controller: who it is and whether it knows where it is.

Theory of operation
-------------------
:func:`vehicle_facts` parses the agent's ``--fc`` string and opens the link with the
driver's own connection code (:func:`firmware_bridge.connection.open_link`: a
deadline on the TCP connect and on the first autopilot HEARTBEAT, the companion's
heartbeat sent once a second meanwhile). Then, for at most :data:`LISTEN_S` seconds,
it asks the autopilot (MAV_CMD_REQUEST_MESSAGE, again after :data:`ASK_AGAIN_S` for
what has not come) for AUTOPILOT_VERSION, GPS_RAW_INT, HOME_POSITION and
GPS_GLOBAL_ORIGIN (it stops listening once they have come) and SYSTEM_TIME (kept if
it came by then: its Unix time, set from GPS, less our wall clock at its arrival is
how far our clock is off), and keeps the fields of those that come from the
autopilot's system and component (anything else on the link is ignored). It commands nothing:
requests for messages are all it sends. Any failure becomes facts with
``answered=False`` and the reason; the link is always closed. A serial port (not a
USB CDC ``ttyACM`` one, which ignores the rate) that stays silent is tried at the
other usual rates (:data:`SCAN_BAUDS`, :data:`SCAN_S` each): an autopilot at another
baud rate is the usual reason, and the rate it answers at is the fix.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

from firmware_bridge.connection import (
    COMPANION_COMPONENT,
    Endpoint,
    close_link,
    companion_heartbeat,
    open_link,
    parse_url,
)
from firmware_bridge.errors import BridgeError, HeartbeatTimeout
from firmware_bridge.modes import MAV_MODE_FLAG_SAFETY_ARMED
from swarm.core.doctor.vehicle import VehicleFacts

HEARTBEAT_S = 5.0  # the flight controller answers within this, or fails the check
LISTEN_S = 2.5  # then at most this long for the requested messages
ASK_AGAIN_S = 1.0
MAV_CMD_REQUEST_MESSAGE = 512
WANTED = {"AUTOPILOT_VERSION": 148, "GPS_RAW_INT": 24, "HOME_POSITION": 242, "GPS_GLOBAL_ORIGIN": 49}
OPTIONAL = {"SYSTEM_TIME": 2}  # asked for too, not waited for (an autopilot without GPS time may not send it)
SIGNING_EPOCH_US = 1420070400 * 1_000_000  # an autopilot's time before 2015 is no GPS time
#: the rates autopilots' telemetry ports run at, most common first (tried on a silent UART)
SCAN_BAUDS = (57600, 115200, 921600, 460800, 230400)
SCAN_S = 1.5  # per rate: an autopilot sends a heartbeat every second


def _scan(ep: Endpoint, per_rate: float) -> int | None:
    """The first other baud rate at which an autopilot's heartbeat comes on the serial
    device of ``ep``, or None (not serial, a USB CDC port, or none)."""
    if ep.scheme != "serial" or per_rate <= 0 or "ttyACM" in ep.device:  # CDC ACM ignores the rate
        return None
    for baud in SCAN_BAUDS:
        if baud == ep.baud:
            continue
        try:
            conn, _ = open_link(
                replace(ep, baud=baud),
                timeout=per_rate,
                source_system=1,
                source_component=COMPANION_COMPONENT,
            )
        except BridgeError:
            continue
        close_link(conn)
        return baud
    return None


def vehicle_facts(
    url: str, *, timeout: float = HEARTBEAT_S, listen: float = LISTEN_S, scan: float = SCAN_S
) -> VehicleFacts:
    """What the flight controller at ``url`` says of itself (never raises for what it
    does). ``scan``: seconds per other baud rate tried on a silent UART (0: none)."""
    try:
        ep = parse_url(url)
    except BridgeError as exc:
        return VehicleFacts(url, "?", answered=False, error=str(exc))
    base = VehicleFacts(url, ep.scheme, answered=False, baud=ep.baud if ep.scheme == "serial" else 0)
    try:  # system id 1 until the heartbeat says the vehicle's: a companion shares its vehicle's
        conn, hb = open_link(ep, timeout=timeout, source_system=1, source_component=COMPANION_COMPONENT)
    except HeartbeatTimeout as exc:
        return replace(base, error=str(exc), found_baud=_scan(ep, scan))
    except BridgeError as exc:
        return replace(base, error=str(exc))
    conn.mav.srcSystem = hb.get_srcSystem()
    facts = replace(
        base,
        answered=True,
        sysid=hb.get_srcSystem(),
        autopilot=int(hb.autopilot),
        vehicle_type=int(hb.type),
        armed=bool(hb.base_mode & MAV_MODE_FLAG_SAFETY_ARMED),
    )
    try:
        return _listen(conn, facts, (hb.get_srcSystem(), hb.get_srcComponent()), listen)
    except OSError as exc:  # the link broke after the heartbeat: keep what was heard
        return replace(facts, error=f"link error: {exc}")
    finally:
        close_link(conn)


def _ask(conn: Any, src: tuple[int, int], names: list[str]) -> None:
    for name in names:
        msg_id = WANTED.get(name) or OPTIONAL[name]
        conn.mav.send(
            conn.mav.command_long_encode(*src, MAV_CMD_REQUEST_MESSAGE, 0, msg_id, 0, 0, 0, 0, 0, 0)
        )
    conn.mav.send(companion_heartbeat())


def _listen(conn: Any, facts: VehicleFacts, src: tuple[int, int], listen: float) -> VehicleFacts:
    heard: set[str] = set()
    deadline = time.monotonic() + listen
    next_ask = 0.0
    while not heard.issuperset(WANTED):
        now = time.monotonic()
        if now >= deadline:
            break
        if now >= next_ask:
            _ask(conn, src, [n for n in (*WANTED, *OPTIONAL) if n not in heard])
            next_ask = now + ASK_AGAIN_S
        conn.select(min(0.1, deadline - now))
        while time.monotonic() < deadline and (msg := conn.recv_msg()) is not None:  # a flood ends too
            if (msg.get_srcSystem(), msg.get_srcComponent()) != src:
                continue
            facts = _fold(facts, msg, time.time())
            heard.add(msg.get_type())
    return facts


def _fold(f: VehicleFacts, msg: Any, wall: float) -> VehicleFacts:
    """``f`` with what ``msg`` says; ``wall``: our clock when it arrived."""
    kind = msg.get_type()
    if kind == "HEARTBEAT":
        return replace(f, armed=bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED))
    if kind == "AUTOPILOT_VERSION":
        return replace(f, version=int(msg.flight_sw_version))
    if kind == "GPS_RAW_INT":
        return replace(f, gps_fix=int(msg.fix_type), satellites=int(msg.satellites_visible))
    if kind == "HOME_POSITION":
        return replace(f, home=True)
    if kind == "GPS_GLOBAL_ORIGIN":
        return replace(f, origin=True)
    if kind == "SYSTEM_TIME" and msg.time_unix_usec > SIGNING_EPOCH_US:
        return replace(f, clock_offset_s=msg.time_unix_usec / 1e6 - wall)
    return f


__all__ = ["vehicle_facts"]
