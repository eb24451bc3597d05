"""``swarm bench sim``: the vehicle simulator's cost and the driver's setpoint timing.

A ``swarm sim --vehicles 20`` process (PX4 profile, real time, default telemetry
rates) runs on free UDP ports; its CPU is read from /proc. The driver connects to
vehicle 1 in this process, leaves its stream rates alone and streams position
setpoints at 10 Hz while the 20 vehicles run. Figures:

* ``realtime_factor``: simulated seconds per wall second, from vehicle 1's
  GLOBAL_POSITION_INT ``time_boot_ms`` advancing against the wall clock;
* ``cpu_percent``: the simulator process's CPU over the window (100 = one core);
* ``setpoint_interval_ms_p50`` / ``_p99``: the streamer's own measured send gaps.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

from firmware_bridge.driver import connect
from radios.ports import free_port_range
from swarm.cli.procs import Child, cpu_seconds

VEHICLES = 20
RATE_HZ = 10.0


def _percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def run(quick: bool = False) -> dict[str, Any]:
    window = 3.0 if quick else 10.0
    warmup = 1.0 if quick else 2.0
    base = free_port_range(VEHICLES, "udp")
    child = Child(["sim", "--vehicles", str(VEHICLES), "--base-port", str(base)], name="vehicle simulator")
    try:
        lines = child.wait_lines(VEHICLES + 1, 60.0)
        endpoints = [ln.split("->", 1)[1].split()[0] for ln in lines if "->" in ln]
        endpoint = endpoints[0] if endpoints else f"udpin:127.0.0.1:{base}"
        with connect(endpoint, timeout=15.0, setpoint_rate_hz=RATE_HZ, request_telemetry=False) as v:
            s = v.wait_for(lambda s: s.ned is not None and s.time_boot_ms > 0, 15.0, "telemetry")
            assert s.ned is not None
            v.set_target_ned(*s.ned, yaw=s.yaw)  # proof-of-life stream; disarmed, nothing moves
            time.sleep(warmup)
            n_before = len(v.setpoint_intervals())
            s0, w0, c0 = v.state, time.monotonic(), cpu_seconds(child.pid)
            time.sleep(window)
            s1, w1, c1 = v.state, time.monotonic(), cpu_seconds(child.pid)
            intervals = v.setpoint_intervals()[n_before:]
            v.stop_setpoints()
    finally:
        child.stop()
    # time_boot_ms of the messages seen at the two wall instants (each up to one
    # telemetry period old: the same bias at both ends)
    rt = ((s1.time_boot_ms - s0.time_boot_ms) / 1000.0) / (
        (s1.last_message_time - s0.last_message_time) or (w1 - w0)
    )
    cpu = 100.0 * (c1 - c0) / (w1 - w0)
    ms = [1000.0 * x for x in intervals]
    p50 = statistics.median(ms) if ms else float("nan")
    p99 = _percentile(ms, 0.99)
    period_ms = 1000.0 / RATE_HZ
    return {
        "vehicles": VEHICLES,
        "realtime_factor": round(rt, 3),
        "cpu_percent": round(cpu, 1),
        "setpoint_rate_hz": RATE_HZ,
        "setpoint_interval_ms_p50": round(p50, 2),
        "setpoint_interval_ms_p99": round(p99, 2),
        "setpoint_intervals": len(ms),
        "window_s": window,
        "targets": {
            "20_vehicles_under_50pct_of_one_core": cpu < 50.0 and abs(rt - 1.0) <= 0.05,
            "setpoint_p99_under_1.5x_period": p99 < 1.5 * period_ms,
        },
    }
