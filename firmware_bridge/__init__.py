"""MAVLink to the flight controller (telemetry in, setpoints out) and a vehicle simulator."""
