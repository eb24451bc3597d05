"""Verdicts on the flight controller: does it answer, and is it ready to fly in a swarm?

Theory of operation
-------------------
The probe opens the agent's ``--fc`` link, waits at most a few seconds for the
autopilot's HEARTBEAT, asks for AUTOPILOT_VERSION, GPS_RAW_INT, HOME_POSITION and
GPS_GLOBAL_ORIGIN (REQUEST_MESSAGE) and listens briefly; :class:`VehicleFacts` holds
the numbers it saw (raw MAVLink enum values, never judged there). :func:`vehicle_checks`
judges them:

* **answers**: no HEARTBEAT within the deadline fails, with the fix for the link's
  kind (a serial port: cable, MAVLink protocol and baud rate on the autopilot's side;
  the rate it does answer at, when the probe found one).
* **autopilot and vehicle type**: PX4 and ArduPilot are what the driver speaks (another
  autopilot warns); the formation law flies multicopters (another type warns).
* **armed** warns: check on the ground, disarmed.
* **firmware version** (AUTOPILOT_VERSION) is reported; no answer warns.
* **GPS**: a 3D fix (or better) passes, 2D warns, none fails; not heard warns.
* **home / EKF origin**: HOME_POSITION or GPS_GLOBAL_ORIGIN heard passes; neither fails
  (positions and return-to-launch need them).
* **clock** (when the autopilot sent SYSTEM_TIME with a GPS time): our wall clock within
  5 s of it passes, within a minute warns, further fails (signing peers refuse a stream
  a minute behind theirs and follow one ahead).
* **serial link rate**: reported; under 57600 baud warns (setpoints and telemetry share it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from swarm.core.doctor import Check, fail, info, passed, warn

AUTOPILOTS = {3: "ArduPilot", 12: "PX4"}
#: MAV_TYPE values the formation law can fly (multicopters and helicopters)
ROTORCRAFT = {
    2: "quadrotor",
    3: "coaxial",
    4: "helicopter",
    13: "hexarotor",
    14: "octorotor",
    15: "tricopter",
    29: "dodecarotor",
    35: "decarotor",
    43: "multirotor",
}
OTHER_TYPES = {1: "fixed wing", 10: "ground rover", 11: "surface boat", 12: "submarine", 20: "VTOL quadrotor"}
FIX_NAMES = {0: "no GPS", 1: "no fix", 2: "2D fix", 3: "3D fix", 4: "DGPS", 5: "RTK float", 6: "RTK fixed"}
FIRMWARE_TYPES = {0: "dev", 64: "alpha", 128: "beta", 192: "rc", 255: ""}
MIN_SERIAL_BAUD = 57600
CLOCK_CLOSE_S = 5.0  # our clock this close to the autopilot's GPS time passes
CLOCK_FAR_S = 60.0  # further than this fails: signing refuses a stream a minute old


@dataclass(frozen=True)
class VehicleFacts:
    """What the flight-controller probe saw. ``kind``: the link's scheme (serial,
    udpin, udpout, tcp); ``baud``: a serial link's rate (0 otherwise); ``error``: why
    nothing answered (empty when it did). The rest is None when not heard."""

    url: str
    kind: str
    answered: bool
    error: str = ""
    baud: int = 0
    sysid: int = 0
    autopilot: int | None = None
    vehicle_type: int | None = None
    armed: bool = False
    version: int | None = None  # AUTOPILOT_VERSION.flight_sw_version
    gps_fix: int | None = None
    satellites: int | None = None
    home: bool = False
    origin: bool = False
    clock_offset_s: float | None = None  # the autopilot's GPS time minus our clock (SYSTEM_TIME)
    found_baud: int | None = None  # silent at ``baud``, the autopilot answered at this rate


def firmware_version(v: int) -> str:
    """``flight_sw_version`` as ``1.14.0`` (``-dev``, ``-beta``... unless official)."""
    kind = FIRMWARE_TYPES.get(v & 0xFF, f"type {v & 0xFF}")
    text = f"{(v >> 24) & 0xFF}.{(v >> 16) & 0xFF}.{(v >> 8) & 0xFF}"
    return text + (f"-{kind}" if kind else "")


def vehicle_checks(f: VehicleFacts) -> list[Check]:
    """Every check of the flight controller (see the module docstring)."""
    if not f.answered:
        return [_silent(f)]
    out = [_identity(f)]
    if f.armed:
        out.append(
            warn("fc armed", "the vehicle is armed", "run the pre-flight check on the ground, disarmed")
        )
    if f.version is not None:
        out.append(
            info(
                "fc firmware",
                f"{AUTOPILOTS.get(f.autopilot or 0, 'autopilot')} {firmware_version(f.version)}",
            )
        )
    else:
        out.append(
            warn(
                "fc firmware", "no AUTOPILOT_VERSION answer", "update the autopilot (REQUEST_MESSAGE support)"
            )
        )
    out += [_gps(f), _home(f)]
    if f.clock_offset_s is not None:
        out.append(_clock(f.clock_offset_s))
    if f.kind == "serial":
        out.append(_rate(f.baud))
    return out


def _silent(f: VehicleFacts) -> Check:
    seen = f.error if f.url in f.error or ":" in f.error else f"{f.url}: {f.error}"
    if f.kind == "serial" and f.found_baud is not None:
        return fail(
            "fc",
            f"{seen}; the autopilot answers at {f.found_baud} baud",
            f"give the agent --fc with :{f.found_baud} (or set the autopilot's port to {f.baud} baud)",
        )
    if f.kind == "serial":
        fix = (
            f"check the cable and that the autopilot's port speaks MAVLink 2 at {f.baud} baud "
            "(ArduPilot: SERIALn_PROTOCOL 2 and SERIALn_BAUD; PX4: MAV_n_CONFIG and SER_TELn_BAUD), "
            "or give the agent --fc DEVICE:BAUD with the autopilot's rate"
        )
    elif f.kind == "udpin":
        fix = "check that the autopilot (or SITL) sends to this port, and that nothing else listens there"
    else:
        fix = "check that the autopilot (or SITL) runs and listens at this address and port"
    return fail("fc", seen, fix)


def _identity(f: VehicleFacts) -> Check:
    ap = AUTOPILOTS.get(f.autopilot if f.autopilot is not None else -1)
    vt = f.vehicle_type if f.vehicle_type is not None else -1
    kind = ROTORCRAFT.get(vt) or OTHER_TYPES.get(vt) or f"MAV_TYPE {vt}"
    seen = f"{ap or f'MAV_AUTOPILOT {f.autopilot}'} {kind}, system id {f.sysid}, on {f.url}"
    if ap is None:
        return warn("fc", seen, "the driver speaks PX4 and ArduPilot: other autopilots are untested")
    if vt not in ROTORCRAFT:
        return warn(
            "fc", seen, "the swarm's formation law flies multicopters: this vehicle cannot hold a slot"
        )
    return passed("fc", seen)


def _gps(f: VehicleFacts) -> Check:
    if f.gps_fix is None:
        return warn("fc GPS", "no GPS_RAW_INT heard", "check the GPS on the autopilot's own ground station")
    name = FIX_NAMES.get(f.gps_fix, f"fix type {f.gps_fix}")
    sats = f", {f.satellites} satellites" if f.satellites is not None and f.satellites != 255 else ""
    if f.gps_fix >= 3:
        return passed("fc GPS", name + sats)
    if f.gps_fix == 2:
        return warn("fc GPS", name + sats, "wait for a 3D fix (open sky, away from metal)")
    return fail("fc GPS", name + sats, "wait for a 3D fix (open sky, away from metal), then check again")


def _home(f: VehicleFacts) -> Check:
    if f.home or f.origin:
        parts = [p for p, seen in (("home", f.home), ("EKF origin", f.origin)) if seen]
        return passed("fc home", " and ".join(parts) + " set")
    return fail(
        "fc home",
        "neither HOME_POSITION nor GPS_GLOBAL_ORIGIN answered: no home or EKF origin",
        "wait for a 3D GPS fix (the autopilot sets its origin then), then check again",
    )


def _clock(offset: float) -> Check:
    """Our wall clock against the autopilot's GPS time: signing peers refuse a stream a
    minute behind theirs, and follow one ahead."""
    if not math.isfinite(offset):
        return warn("fc clock", f"the autopilot's time is {offset}", "check the autopilot's GPS")
    way = "ahead of" if offset < 0 else "behind"
    seen = f"this computer's clock is {abs(offset):.1f} s {way} the autopilot's GPS time"
    fix = "set the clock before the agent starts (NTP, or GPS time: chrony with gpsd)"
    if abs(offset) <= CLOCK_CLOSE_S:
        return passed("fc clock", seen)
    if abs(offset) <= CLOCK_FAR_S:
        return warn("fc clock", seen, fix)
    return fail("fc clock", seen + ": signed frames would be refused or drag the swarm's clock", fix)


def _rate(baud: int) -> Check:
    if baud >= MIN_SERIAL_BAUD:
        return passed("fc link", f"serial at {baud} baud")
    return warn(
        "fc link",
        f"serial at {baud} baud: telemetry and 10 Hz setpoints share it",
        "run the autopilot's port at 115200 baud or more, and the agent's --fc DEVICE:BAUD with it",
    )


__all__ = ["VehicleFacts", "firmware_version", "vehicle_checks"]
