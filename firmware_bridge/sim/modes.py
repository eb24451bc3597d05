"""Flight-mode tables of the two simulated autopilots (PX4 and ArduCopter, as in their sources).

A mode is known by its name in the simulator (``"OFFBOARD"``, ``"AUTO.LOITER"``,
``"GUIDED"``...). Each profile maps names to the HEARTBEAT ``custom_mode`` encoding:
PX4 packs ``main << 16 | sub << 24``; ArduCopter sends the mode number. ``BEHAVIOUR``
says what the simulated position controller does in each mode; ``NEEDS_POSITION`` the
modes that need a global position (refused without GPS, and what arming checks).
"""

from __future__ import annotations

PX4_MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (1, 0),
    "ALTCTL": (2, 0),
    "POSCTL": (3, 0),
    "AUTO.TAKEOFF": (4, 2),
    "AUTO.LOITER": (4, 3),
    "AUTO.MISSION": (4, 4),
    "AUTO.RTL": (4, 5),
    "AUTO.LAND": (4, 6),
    "ACRO": (5, 0),
    "OFFBOARD": (6, 0),
    "STABILIZED": (7, 0),
}
PX4_BY_NUMBER: dict[tuple[int, int], str] = {v: k for k, v in PX4_MODES.items()}

AP_MODES: dict[str, int] = {
    "STABILIZE": 0,
    "ACRO": 1,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "CIRCLE": 7,
    "LAND": 9,
    "POSHOLD": 16,
    "BRAKE": 17,
    "SMART_RTL": 21,
    "FOLLOW": 23,
}
AP_BY_NUMBER: dict[int, str] = {v: k for k, v in AP_MODES.items()}

#: what the position controller does: hold, offboard, guided, takeoff, land, rtl
BEHAVIOUR: dict[str, str] = {
    "OFFBOARD": "offboard",
    "GUIDED": "guided",
    "AUTO.TAKEOFF": "takeoff",
    "AUTO.LAND": "land",
    "LAND": "land",
    "AUTO.RTL": "rtl",
    "RTL": "rtl",
    "SMART_RTL": "rtl",
}

NEEDS_POSITION: frozenset[str] = frozenset(
    {
        "POSCTL",
        "OFFBOARD",
        "AUTO.TAKEOFF",
        "AUTO.LOITER",
        "AUTO.MISSION",
        "AUTO.RTL",
        "GUIDED",
        "AUTO",
        "LOITER",
        "RTL",
        "CIRCLE",
        "POSHOLD",
        "BRAKE",
        "SMART_RTL",
        "FOLLOW",
    }
)

#: ArduCopter modes from which MAVLink arming is refused ("Arm: Mode not armable")
AP_NOT_ARMABLE: frozenset[str] = frozenset({"RTL", "LAND", "SMART_RTL", "CIRCLE"})


def behaviour(mode: str) -> str:
    return BEHAVIOUR.get(mode, "hold")


def px4_custom_mode(mode: str) -> int:
    main, sub = PX4_MODES[mode]
    return main << 16 | sub << 24


def px4_base_flags(mode: str) -> int:
    """MAV_MODE_FLAG bits PX4 sets besides CUSTOM_MODE_ENABLED and SAFETY_ARMED."""
    if mode in ("MANUAL", "ACRO"):
        return 64  # MANUAL_INPUT
    if mode in ("ALTCTL", "POSCTL", "STABILIZED"):
        return 64 | 16  # MANUAL_INPUT | STABILIZE
    if mode == "OFFBOARD":
        return 16  # STABILIZE only (recorded from PX4 v1.15)
    return 4 | 8 | 16  # AUTO | GUIDED | STABILIZE (auto modes)
