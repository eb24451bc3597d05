"""Simulated PX4 / ArduCopter multicopters speaking MAVLink 2 (``swarm sim``).

``VehicleSim(SimConfig(...)).start()`` returns one pymavlink connection string per
vehicle; :mod:`firmware_bridge.sim.autopilot` is the I/O-free vehicle core, which
asks its flavour (:mod:`firmware_bridge.sim.flavour`: :mod:`~firmware_bridge.sim.px4`
or :mod:`~firmware_bridge.sim.ardupilot`) whatever differs between the two autopilots;
:mod:`firmware_bridge.sim.telemetry` encodes its messages,
:mod:`firmware_bridge.sim.dynamics` is its point-mass physics,
:mod:`firmware_bridge.sim.boot` ArduCopter's recorded boot timeline and
:mod:`firmware_bridge.sim.runner` the sockets and the thread.
"""

from firmware_bridge.sim.autopilot import Autopilot, VehicleState
from firmware_bridge.sim.runner import REALISTIC_BOOT, REALISTIC_BOOTS, SimConfig, Vehicle, VehicleSim

__all__ = [
    "REALISTIC_BOOT",
    "REALISTIC_BOOTS",
    "Autopilot",
    "SimConfig",
    "Vehicle",
    "VehicleSim",
    "VehicleState",
]
