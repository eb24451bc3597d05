"""Flight-mode names <-> HEARTBEAT ``custom_mode`` and DO_SET_MODE parameters.

Pure tables, no I/O (from PX4's commander and px4_custom_mode.h, and ArduCopter's mode
numbers in its mode.h):

* PX4 packs ``custom_mode = main << 16 | sub << 24``; DO_SET_MODE takes
  param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 = main mode, param3 = sub mode
  (never the packed value: PX4 casts param2 to uint8 and accepts a no-op).
* ArduCopter's ``custom_mode`` is the mode number; DO_SET_MODE takes param1 = 1,
  param2 = number.

Names are PX4's (``AUTO.LOITER``, ``OFFBOARD``) and ArduCopter's (``GUIDED``,
``LOITER``); a few aliases (``HOLD``, ``RTL``, ``LAND`` ...) map to each autopilot's
equivalent so callers can stay autopilot-neutral.
"""

from __future__ import annotations

from firmware_bridge.errors import BridgeError

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_PX4 = 12
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128


class UnknownMode(BridgeError, ValueError):
    """A mode name or number this autopilot does not have (the caller's mistake)."""


# PX4 main modes and AUTO sub modes (px4_custom_mode.h)
PX4_MAIN = {
    1: "MANUAL",
    2: "ALTCTL",
    3: "POSCTL",
    4: "AUTO",
    5: "ACRO",
    6: "OFFBOARD",
    7: "STABILIZED",
    8: "RATTITUDE",
}
PX4_AUTO_SUB = {
    1: "READY",
    2: "TAKEOFF",
    3: "LOITER",
    4: "MISSION",
    5: "RTL",
    6: "LAND",
    7: "RTGS",
    8: "FOLLOW_TARGET",
    9: "PRECLAND",
    10: "VTOL_TAKEOFF",
}
PX4_POSCTL_SUB = {0: "POSCTL", 1: "ORBIT"}

PX4_MODES: dict[str, tuple[int, int]] = {name: (main, 0) for main, name in PX4_MAIN.items() if main != 4}
PX4_MODES.update({f"AUTO.{name}": (4, sub) for sub, name in PX4_AUTO_SUB.items()})
PX4_MODES["POSCTL.ORBIT"] = (3, 1)
PX4_ALIASES = {
    "HOLD": "AUTO.LOITER",
    "LOITER": "AUTO.LOITER",
    "RTL": "AUTO.RTL",
    "RETURN": "AUTO.RTL",
    "LAND": "AUTO.LAND",
    "TAKEOFF": "AUTO.TAKEOFF",
    "MISSION": "AUTO.MISSION",
    "POSITION": "POSCTL",
    "ALTITUDE": "ALTCTL",
    "STABILIZE": "STABILIZED",
}

# ArduCopter mode numbers (ArduCopter/mode.h)
ARDUCOPTER_MODES: dict[str, int] = {
    "STABILIZE": 0,
    "ACRO": 1,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "CIRCLE": 7,
    "LAND": 9,
    "DRIFT": 11,
    "SPORT": 13,
    "FLIP": 14,
    "AUTOTUNE": 15,
    "POSHOLD": 16,
    "BRAKE": 17,
    "THROW": 18,
    "AVOID_ADSB": 19,
    "GUIDED_NOGPS": 20,
    "SMART_RTL": 21,
    "FLOWHOLD": 22,
    "FOLLOW": 23,
    "ZIGZAG": 24,
    "SYSTEMID": 25,
    "AUTOROTATE": 26,
    "AUTO_RTL": 27,
    "TURTLE": 28,
}
ARDUCOPTER_NAMES = {v: k for k, v in ARDUCOPTER_MODES.items()}
ARDUCOPTER_ALIASES = {
    "HOLD": "LOITER",
    "RETURN": "RTL",
    "AUTO.LOITER": "LOITER",
    "AUTO.RTL": "RTL",
    "AUTO.LAND": "LAND",
}


def autopilot_name(autopilot: int) -> str:
    """``"px4"``, ``"ardupilot"`` or ``"other"`` from HEARTBEAT.autopilot."""
    if autopilot == MAV_AUTOPILOT_PX4:
        return "px4"
    if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    return "other"


def decode_mode(autopilot: str, custom_mode: int, base_mode: int = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) -> str:
    """Mode name from a HEARTBEAT's custom_mode (``"UNKNOWN(n)"`` when not in the table)."""
    if not base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and autopilot != "ardupilot":
        return f"UNKNOWN({custom_mode})"
    if autopilot == "px4":
        main = (custom_mode >> 16) & 0xFF
        sub = (custom_mode >> 24) & 0xFF
        if main == 4:
            sub_name = PX4_AUTO_SUB.get(sub)
            return f"AUTO.{sub_name}" if sub_name else f"AUTO.UNKNOWN({sub})"
        if main == 3 and sub == 1:
            return "POSCTL.ORBIT"
        return PX4_MAIN.get(main, f"UNKNOWN({custom_mode})")
    if autopilot == "ardupilot":
        return ARDUCOPTER_NAMES.get(custom_mode, f"UNKNOWN({custom_mode})")
    return f"UNKNOWN({custom_mode})"


def canonical_mode(autopilot: str, name: str) -> str:
    """The autopilot's own name for ``name`` (aliases resolved, case ignored).

    Raises:
        UnknownMode: the autopilot has no such mode.
    """
    key = name.strip().upper()
    if autopilot == "px4":
        key = PX4_ALIASES.get(key, key)
        if key in PX4_MODES:
            return key
    elif autopilot == "ardupilot":
        key = ARDUCOPTER_ALIASES.get(key, key)
        if key in ARDUCOPTER_MODES:
            return key
    raise UnknownMode(f"{autopilot} has no flight mode {name!r}")


def encode_mode(autopilot: str, name: str) -> tuple[float, float, float]:
    """DO_SET_MODE params 1-3 for ``name``.

    Raises:
        UnknownMode: the autopilot has no such mode.
    """
    key = canonical_mode(autopilot, name)
    if autopilot == "px4":
        main, sub = PX4_MODES[key]
        return float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(main), float(sub)
    return float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(ARDUCOPTER_MODES[key]), 0.0


def custom_mode_of(autopilot: str, name: str) -> int:
    """HEARTBEAT custom_mode a vehicle in mode ``name`` reports.

    Raises:
        UnknownMode: the autopilot has no such mode.
    """
    key = canonical_mode(autopilot, name)
    if autopilot == "px4":
        main, sub = PX4_MODES[key]
        return main << 16 | sub << 24
    return ARDUCOPTER_MODES[key]
