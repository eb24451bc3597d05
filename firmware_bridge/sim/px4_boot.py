"""The simulated PX4's boot and its voice: arming checks and EVENT messages, as recorded.

Theory of operation. Recorded from PX4 v1.15.4 SITL (SIH quad, the client listening
from the start; seconds after the client's first heartbeat): HEARTBEAT, GPS_RAW_INT
(fix 3), HOME_POSITION (home follows the GPS while disarmed) and LOCAL_POSITION_NED
flow at once; the HEARTBEAT says UNINIT (0) while any arming check fails; the first
arming check report comes at 0.75 s (no attitude, no local and no global position, no
offboard signal, and three notices); the attitude is valid at 32.26 s, the first
GLOBAL_POSITION_INT at 32.35 s, and from 34.0 s the HEARTBEAT says STANDBY and an arm
is accepted. Until then every arm is refused with TEMPORARILY_REJECTED and one EVENT,
"Arming denied: Resolve system health failures first", and no STATUSTEXT: PX4 v1.15
says nothing in STATUSTEXT on this link, its words are EVENT messages (the MAVLink
events protocol, :mod:`firmware_bridge.px4_events`).

:class:`Px4Boot` is that recording scaled to a chosen length ``total`` (the moment
arming is allowed; 0: booted before the link came up). :func:`failing_checks` is the
arming check report of a state, as the EVENTs PX4 sends for it; :class:`EventMsg` is an
EVENT ready to be packed (pymavlink's dialects do not know the message). Pure: no I/O,
no clock.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any, ClassVar

from pymavlink.generator.mavcrc import x25crc

from firmware_bridge.px4_events import CRC_EXTRA, EVENT_PAYLOAD, MSG_EVENT
from firmware_bridge.sim.boot import ScaledBoot

#: recorded seconds from the first heartbeat until arming is allowed (HEARTBEAT STANDBY)
RECORDED_TOTAL = 34.0
#: the recorded milestones
FIRST_REPORT, ATTITUDE_VALID, POSITION_VALID = 0.75, 32.26, 32.35
ORIGIN_SENT = 1.0  # the one GPS_GLOBAL_ORIGIN PX4 sends unasked (recorded at 1.0 s)

#: one EVENT as recorded: (id, log_levels byte, arguments)
Ev = tuple[int, int, bytes]
ARMING_DENIED: Ev = (0x102089D, 0x62, b"")  # Arming denied: Resolve system health failures first
ARMED_BY_COMMAND: Ev = (0x190CAF3, 0x66, b"\x04")  # Armed by external command
DISARMED_BY_COMMAND: Ev = (0x1F46777, 0x66, b"\x04")  # Disarmed by external command
DISARMED_AUTO_LAND: Ev = (0x1F46777, 0x66, b"\x06")  # Disarmed by landing
DISARMED_AUTO_PREFLIGHT: Ev = (0x1F46777, 0x66, b"\x07")  # Disarmed by auto preflight disarming
DISARM_DENIED: Ev = (0x18AB9B5, 0x62, b"")  # Disarming denied: not landed
TAKEOFF_DETECTED: Ev = (0x1414569, 0x66, b"")
LANDING_DETECTED: Ev = (0x19638AC, 0x66, b"")
# the arming checks (group arming_check): failing ones at ERROR (3) and CRITICAL (2)
# keep it from arming; the WARNING and NOTICE ones come in every report
NO_ATTITUDE: Ev = (0x19F748F, 0x22, bytes.fromhex("7ed07e0014"))
NO_LOCAL_POSITION: Ev = (0x1D31BB9, 0x33, bytes.fromhex("7c007e0014"))
NO_GLOBAL_POSITION: Ev = (0x198C273, 0x33, bytes.fromhex("3800000014"))
NO_MISSION: Ev = (0x105C2D9, 0x66, bytes.fromhex("0800000014"))
NO_OFFBOARD_SIGNAL: Ev = (0x12F1DC7, 0x33, bytes.fromhex("0040000014"))
NO_MANUAL_CONTROL: Ev = (0x106ED29, 0x44, bytes.fromhex("ffffffff07"))
NO_GCS: Ev = (0x167C97B, 0x66, bytes.fromhex("ffffffff0c"))
#: "Failsafe activated: Autopilot disengaged, switching to {2}" (the first argument as
#: recorded), by the failsafe action's value: Position mode 2, Hold 5, RTL 6, Land 7
FAILSAFE_DISENGAGED = 0x1DEDBD0
FAILSAFE_ACTIONS = {"POSCTL": 2, "AUTO.LOITER": 5, "AUTO.RTL": 6, "AUTO.LAND": 7}


def failsafe_event(mode: str) -> Ev:
    """The EVENT of an offboard-loss failsafe switching to ``mode``."""
    return (FAILSAFE_DISENGAGED, 0x42, bytes.fromhex("00000600") + bytes([FAILSAFE_ACTIONS.get(mode, 0)]))


#: the report's summaries (level 8: protocol), recorded per phase: booting, positioning, ready
CHECK_SUMMARY = 0x1A893E0
HEALTH_SUMMARY = 0x11D3727
SUMMARIES: dict[str, tuple[bytes, bytes]] = {
    "attitude": (bytes.fromhex("000000100080000000802b0180802b0180"), bytes.fromhex("0002080228")),
    "position": (bytes.fromhex("000000100080000000803b0180803b0180"), bytes.fromhex("0002080228")),
    "ready": (bytes.fromhex("000000100080000000b03b7f80b03b7f80"), bytes.fromhex("000a080228")),
}


@dataclass(frozen=True)
class Px4Boot(ScaledBoot):
    """PX4's recorded boot scaled to ``total`` seconds (0: booted before the link came up)."""

    recorded_total: ClassVar[float] = RECORDED_TOTAL

    def attitude_valid(self, t: float) -> bool:
        return t >= self.at(ATTITUDE_VALID)

    def position_valid(self, t: float) -> bool:
        """GLOBAL_POSITION_INT is sent (PX4 sends none before)."""
        return t >= self.at(POSITION_VALID)

    def booted(self, t: float) -> bool:
        return t >= self.total

    def reporting(self, t: float) -> bool:
        """The arming checks have reported once (the first report at 0.75 s)."""
        return self.total <= 0.0 or t >= self.at(FIRST_REPORT)


def failing_checks(*, attitude: bool, position: bool, booted: bool, offboard_signal: bool) -> list[Ev]:
    """The arming check EVENTs of one report, in PX4's order."""
    out: list[Ev] = []
    if not attitude:
        out.append(NO_ATTITUDE)
    if not (position and booted):
        out += [NO_LOCAL_POSITION, NO_GLOBAL_POSITION]
    out.append(NO_MISSION)
    if not offboard_signal:
        out.append(NO_OFFBOARD_SIGNAL)
    return [*out, NO_MANUAL_CONTROL, NO_GCS]


def blocking(checks: list[Ev]) -> bool:
    """True when a check of the report keeps PX4 from arming (ERROR or worse; the
    offboard signal only counts in OFFBOARD: the caller leaves it out elsewhere)."""
    return any(level & 0x0F <= 3 for _id, level, _a in checks)


def summary(checks: list[Ev]) -> list[Ev]:
    """The two summary EVENTs closing a report (recorded, by phase)."""
    phase = "attitude" if NO_ATTITUDE in checks else "position" if NO_LOCAL_POSITION in checks else "ready"
    arming, health = SUMMARIES[phase]
    return [(CHECK_SUMMARY, 0x88, arming), (HEALTH_SUMMARY, 0x88, health)]


@dataclass
class EventMsg:
    """An EVENT (id 410) the simulator sends: packs itself like a pymavlink message."""

    id: int
    log_levels: int
    arguments: bytes
    sequence: int
    time_boot_ms: int
    destination_system: int = 0
    destination_component: int = 0

    def get_type(self) -> str:
        return "EVENT"

    def get_msgId(self) -> int:
        return MSG_EVENT

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        """The MAVLink 2 frame (trailing zeros trimmed), from ``mav``'s system, component
        and sequence, as pymavlink packs its own messages."""
        payload = (
            EVENT_PAYLOAD.pack(
                self.id & 0xFFFFFFFF,
                self.time_boot_ms & 0xFFFFFFFF,
                self.sequence & 0xFFFF,
                self.destination_component,
                self.destination_system,
                self.log_levels,
                self.arguments[:40],
            ).rstrip(b"\0")
            or b"\0"
        )
        head = (
            bytes([0xFD, len(payload), 0, 0, mav.seq & 0xFF, mav.srcSystem, mav.srcComponent])
            + struct.pack("<I", MSG_EVENT)[:3]
        )
        crc = x25crc(head[1:] + payload)
        crc.accumulate(bytes([CRC_EXTRA[MSG_EVENT]]))
        return head + payload + struct.pack("<H", crc.crc)
