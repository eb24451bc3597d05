"""The simulated ArduCopter's boot: a timeline as recorded from a real ArduCopter SITL.

Theory of operation. A real ArduCopter is not ready when its link comes up. Recorded
from ArduCopter 4.7.0-dev SITL (seconds after the first connection): the HEARTBEAT says
BOOT until "ArduPilot Ready" (2.35 s); GLOBAL_POSITION_INT reads all zeros until the
GPS is detected (9.73 s); home and the EKF origin are set at 19.93 s (HOME_POSITION
starts, GPS_GLOBAL_ORIGIN arrives unrequested); LOCAL_POSITION_NED starts and arming is
allowed only once "EKF3 IMU0 is using GPS" (41.52 s). Until then every arm is refused
with the texts of its phase ("Arm: System not initialised", "Arm: Accels
inconsistent"...).

:class:`BootTimeline` holds that recording scaled to a chosen length ``total`` (the
time of "is using GPS"): every milestone and text is at ``recorded * total /
RECORDED_TOTAL``. ``total = 0`` is a vehicle booted before its link came up: no boot
phase, no refusal. It is a pure function of the simulator's own clock: each question
is asked with the simulated time ``t``; nothing here reads a clock or does I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

#: recorded seconds of "EKF3 IMU0 is using GPS" (the end of the boot)
RECORDED_TOTAL = 41.52
#: the recorded milestones, seconds after the first connection
READY, GPS_DETECTED, POSITION_VALID, ORIGIN_SET = 2.35, 9.73, 9.94, 19.93
EKF_STARTED = 4.35  # "EKF3 IMU0 initialised": EKF_STATUS_REPORT leaves "uninitialised"
#: the boot's STATUSTEXTs (recorded second, severity, text)
TEXTS: tuple[tuple[float, int, str], ...] = (
    (0.11, 7, "RCInput: decoding UDP (Pulses)"),
    (0.23, 6, "Calibrating barometer"),
    (1.83, 6, "Barometer 1 calibration complete"),
    (1.83, 6, "Barometer 2 calibration complete"),
    (2.35, 6, "ArduPilot Ready"),
    (2.35, 6, "AHRS: DCM active"),
    (2.65, 6, "RC7: SaveWaypoint LOW"),
    (4.35, 6, "EKF3 IMU0 initialised"),
    (4.35, 6, "EKF3 IMU1 initialised"),
    (4.36, 6, "AHRS: EKF3 active"),
    (5.70, 6, "EKF3 IMU0 tilt alignment complete"),
    (5.70, 6, "EKF3 IMU1 tilt alignment complete"),
    (5.80, 6, "EKF3 IMU0 MAG0 initial yaw alignment complete"),
    (5.80, 6, "EKF3 IMU1 MAG0 initial yaw alignment complete"),
    (9.71, 6, "GPS 1: probing for u-blox at 230400 baud"),
    (9.73, 6, "GPS 1: detected u-blox"),
    (19.93, 6, "EKF3 IMU0 origin set"),
    (19.95, 6, "Field Elevation Set: {elevation}m"),
    (20.12, 6, "EKF3 IMU1 origin set"),
    (30.36, 2, "PreArm: Need Position Estimate"),
    (41.52, 6, "EKF3 IMU0 is using GPS"),
    (41.53, 6, "EKF3 IMU1 is using GPS"),
)
#: why an arm is refused, by phase: (recorded end of the phase, the "Arm: ..." reasons)
ARM_REFUSALS: tuple[tuple[float, tuple[str, ...]], ...] = (
    (2.35, ("System not initialised",)),
    (5.80, ("Need Alt Estimate", "Accels inconsistent", "EKF attitude is bad", "AHRS: waiting for home")),
    (12.96, ("Accels inconsistent", "AHRS: waiting for home")),
    (19.93, ("Gyros inconsistent", "AHRS: waiting for home")),
    (22.96, ("Gyros inconsistent", "Need Position Estimate")),
    (RECORDED_TOTAL, ("Need Position Estimate",)),
)
#: parameters announced (PARAM_VALUE, index 65535) during the boot, at about 0.11 s
BOOT_PARAMS: tuple[str, ...] = (
    "STAT_RUNTIME",
    "COMPASS_DEV_ID",
    "BARO1_GND_PRESS",
    "INS_GYR_ID",
    "INS_ACC_ID",
    "EK3_SRC1_POSXY",
    "MIS_TOTAL",
)
#: the companion sees TIMESYNC (tc1 = 0) every this many seconds, the first at 9.9 s
TIMESYNC_PERIOD = 10.0
TIMESYNC_FIRST = 9.9


@dataclass(frozen=True)
class ScaledBoot:
    """A recorded boot (``recorded_total`` seconds long) scaled to ``total`` seconds (0:
    booted before the link came up); each autopilot's timeline adds its milestones."""

    recorded_total: ClassVar[float]
    total: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.total <= 600.0:
            raise ValueError(f"boot time must be 0..600 s, got {self.total}")

    def at(self, recorded: float) -> float:
        """The simulated second of a recorded moment of the boot."""
        return recorded * self.total / self.recorded_total


@dataclass(frozen=True)
class BootTimeline(ScaledBoot):
    """ArduCopter's recorded boot scaled to ``total`` seconds."""

    recorded_total: ClassVar[float] = RECORDED_TOTAL

    def booting(self, t: float) -> bool:
        """True before "ArduPilot Ready": HEARTBEAT system_status BOOT."""
        return self.total > 0.0 and t < self.at(READY)

    def position_valid(self, t: float) -> bool:
        """GPS detected: GLOBAL_POSITION_INT and GPS_RAW_INT carry a position."""
        return t >= self.at(POSITION_VALID)

    def origin_set(self, t: float) -> bool:
        """Home and EKF origin exist: HOME_POSITION answers."""
        return t >= self.at(ORIGIN_SET)

    def ekf_started(self, t: float) -> bool:
        return t >= self.at(EKF_STARTED)

    def using_gps(self, t: float) -> bool:
        """The EKF uses GPS: LOCAL_POSITION_NED flows and arming is allowed."""
        return t >= self.total

    def arm_refusal(self, t: float) -> tuple[str, ...]:
        """The "Arm: ..." texts of a refused arm at ``t``; empty once booted."""
        if self.using_gps(t):
            return ()
        for end, reasons in ARM_REFUSALS:
            if t < self.at(end):
                return tuple(f"Arm: {r}" for r in reasons)
        return ()

    def texts_between(self, t0: float, t1: float, elevation: float) -> list[tuple[int, str]]:
        """The boot texts due in (t0, t1] (all those at 0 when ``t0`` < 0)."""
        if self.total <= 0.0:
            return []
        out = []
        for rec, sev, text in TEXTS:
            if t0 < self.at(rec) <= t1 or (t0 < 0.0 <= t1 and self.at(rec) <= 0.0):
                out.append((sev, text.format(elevation=round(elevation))))
        return out

    def crossed(self, recorded: float, t0: float, t1: float) -> bool:
        """True when the recorded moment falls in (t0, t1] (a moment at 0: when t0 < 0)."""
        at = self.at(recorded)
        return t0 < at <= t1 or (at <= 0.0 and t0 < 0.0 <= t1)
