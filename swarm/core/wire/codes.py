"""What the numbers and words inside the messages mean: Telemetry's mode codes and flag
bits, the station ids, notice severities, and the one line every notice and reason is cut to."""

from __future__ import annotations

from swarm.core.wire.message_types import NOTICE_MAX, REASON_MAX

#: MAVLink severities (MAV_SEVERITY)
EMERGENCY, ALERT, CRITICAL, ERROR, WARNING, NOTICE, INFO, DEBUG = range(8)


SEVERITY_NAMES = ("emergency", "alert", "critical", "error", "warning", "notice", "info", "debug")


#: the pilot's event when it holds because another agent is too close (the station
#: raises a separation alert on a notice starting so)
SEPARATION_HOLD = "holding: too close"


def printable_line(text: str | bytes) -> str:
    """``text`` as one printable line: every character that is not printable (control
    characters, line ends, NUL; bytes are read as UTF-8, bad bytes replaced) becomes a
    blank, runs of blanks one space."""
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    return " ".join("".join(c if c.isprintable() else " " for c in str(text)).split())


def cut_utf8(line: str, limit: int) -> str:
    """``line`` cut to ``limit`` bytes of UTF-8 (whole characters), with "..." where it
    was cut."""
    raw = line.encode("utf-8")
    if len(raw) <= limit:
        return line
    return raw[: limit - 3].decode("utf-8", errors="ignore").rstrip() + "..."


def one_line(text: str | bytes, limit: int = NOTICE_MAX) -> str:
    """``text`` as one printable line (:func:`printable_line`) of at most ``limit``
    bytes of UTF-8 (:func:`cut_utf8`)."""
    return cut_utf8(printable_line(text), limit)


#: station ids (MAVLink ground stations use 255 and the ids just below it)
STATION_IDS = range(251, 256)


#: Telemetry.mode codes: PX4 names, then ArduCopter names (0: unknown)
MODES: tuple[str, ...] = (
    "",
    "MANUAL",
    "STABILIZED",
    "ALTCTL",
    "POSCTL",
    "OFFBOARD",
    "AUTO.TAKEOFF",
    "AUTO.LOITER",
    "AUTO.MISSION",
    "AUTO.RTL",
    "AUTO.LAND",
    "AUTO.READY",
    "ACRO",
    "STABILIZE",
    "ALT_HOLD",
    "GUIDED",
    "LOITER",
    "RTL",
    "LAND",
    "AUTO",
    "BRAKE",
    "POSHOLD",
)


_MODE_CODES = {name: i for i, name in enumerate(MODES)}


# Telemetry.flags bits
FLAG_ARMED = 0x01


FLAG_AIRBORNE = 0x02


FLAG_FC_OK = 0x04


FLAG_HOLDING = 0x08  # holding position: stale pose, separation, or a stop command


FLAG_CONTROL_LOST = 0x10  # the autopilot left setpoint control by itself (a failsafe, RC)


FLAG_READY_KNOWN = 0x20  # the autopilot reports its pre-arm checks (FLAG_READY says how)


FLAG_READY = 0x40  # its pre-arm checks pass: ready to arm


#: the modes an operator may select for one vehicle, and what each means for the swarm:
#: "hold" (the autopilot holds it where it is: it leaves the swarm's control), "land",
#: "return", "swarm" (back under the swarm's setpoints, holding). Manual modes and those
#: that need RC sticks (POSCTL, ALTCTL; ArduPilot LOITER, POSHOLD, ALT_HOLD) are not
#: offered: a companion-only vehicle has no pilot on the sticks.
SELECTABLE_MODES: dict[str, str] = {
    "AUTO.LOITER": "hold",
    "AUTO.RTL": "return",
    "AUTO.LAND": "land",
    "OFFBOARD": "swarm",
    "BRAKE": "hold",
    "RTL": "return",
    "LAND": "land",
    "GUIDED": "swarm",
}


def mode_code(name: str) -> int:
    return _MODE_CODES.get(name, 0)


def mode_name(code: int) -> str:
    return MODES[code] if 0 <= code < len(MODES) else ""


def is_station(agent_id: int) -> bool:
    return agent_id in STATION_IDS


def short_reason(text: str) -> str:
    """``text`` as a CommandAck's reason: one line (control characters and runs of
    blanks become one space), cut to what the frame holds (``REASON_MAX`` bytes of
    UTF-8, whole characters) with "..." where it was cut. An autopilot's STATUSTEXTs
    are joined with "; " by the driver: a text repeated is kept once (the driver also
    counts a text heard just before the command, often the last refusal's), and a
    long list keeps its first texts."""
    line = "; ".join(dict.fromkeys(printable_line(text).split("; ")))
    return cut_utf8(line, REASON_MAX)
