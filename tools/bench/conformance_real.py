"""``python -m tools.bench conformance --real``: the simulator against the real autopilots, live.

The same mission is flown with the project's driver on a real autopilot (ArduCopter
4.7 and PX4 v1.15 SITL, :mod:`firmware_bridge.sitl`) and on the simulator's profile of
it (``VehicleSim``; ArduCopter with its recorded boot, waiting for its client as the
real one does), each measured the same way from the driver's side:

* ``boot``: from the first heartbeat until the vehicle is armable (``wait_ready``);
* ``early_arm``: the COMMAND_ACK result of an arm sent at the first heartbeat;
* ``takeoff``: NAV_TAKEOFF to 10 m until 9.5 m;
* ``move``: 20 m north at 10 m under setpoint control, until within 0.5 m horizontally;
* ``climb``: 5 m up, until within 0.3 m;
* ``yaw``: a 90 degree turn on the spot, until within 5 degrees;
* ``setpoint_loss``: the setpoints stopped, until the autopilot leaves setpoint
  control (and which mode it takes: ``after_loss``; none within 15 s: null, as
  ArduCopter holding a position target does);
* ``land``: back under control and at 10 m, LAND until on the ground.

Per autopilot the figures are each milestone's real and simulated seconds and their
ratio (simulator / real; target 0.8-1.2), the ACK results and the modes the autopilot
took, real against simulated (target: the same). ``--quick`` runs both at twice real
time (the same ratios, coarser). An honest miss is printed as a miss.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from firmware_bridge import sitl
from firmware_bridge.driver import Vehicle, connect
from firmware_bridge.errors import BridgeError, CommandRejected
from firmware_bridge.session import WaitTimeout
from firmware_bridge.sim import REALISTIC_BOOTS, SimConfig, VehicleSim
from radios.ports import free_port
from swarm.errors import SwarmError

RATIO_RANGE = (0.8, 1.2)
ALT = 10.0
MILESTONES = ("boot", "takeoff", "move", "climb", "yaw", "setpoint_loss", "land")
DEADLINE = 180.0  # any one step, simulated seconds
LOSS_WAIT_S = 15.0  # how long a setpoint loss is given to end setpoint control


def _timed(v: Vehicle, what: str, speed: float, fn: Callable[[], object]) -> float:
    """Seconds of the autopilot's own time ``fn`` took (wall time x ``speed``)."""
    t0 = time.monotonic()
    try:
        fn()
    except BridgeError as exc:
        raise SwarmError(f"{what} on {v.autopilot}: {exc}") from None
    return (time.monotonic() - t0) * speed


def fly(url: str, speed: float) -> dict[str, Any]:
    """The mission on the vehicle at ``url`` whose clock runs ``speed`` times real time."""
    out: dict[str, Any] = {"modes": []}
    step = DEADLINE / speed
    with connect(url, timeout=60.0) as v:
        modes: list[str] = out["modes"]

        def note(_msg: Any = None) -> None:
            m = v.state.mode
            if m and (not modes or modes[-1] != m):
                modes.append(m)

        v.add_message_hook(lambda msg: note() if msg.get_type() == "HEARTBEAT" else None)
        first = time.monotonic()
        try:
            v.arm()
            out["early_arm"] = "ACCEPTED"
            v.disarm(force=True)
        except CommandRejected as e:
            out["early_arm"] = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 4: "FAILED"}.get(
                e.result, str(e.result)
            )
        v.wait_ready(step)
        out["boot"] = (time.monotonic() - first) * speed
        t: dict[str, float] = {}
        t["takeoff"] = _timed(v, "take-off", speed, lambda: v.takeoff(ALT, timeout=step, ready_timeout=step))
        v.start_offboard(timeout=step)
        s = v.state
        assert s.ned is not None
        n0, e0 = s.ned[0], s.ned[1]
        z = -ALT
        v.set_target_ned(n0 + 20, e0, z, yaw=s.yaw)

        def moved() -> None:  # its track, as the recorded traces measure it (PX4 sags as it speeds up)
            def ok(st: Any) -> bool:
                return st.ned is not None and math.hypot(st.ned[0] - n0 - 20, st.ned[1] - e0) < 0.5

            v.wait_for(ok, step, "20 m move")

        t["move"] = _timed(v, "20 m move", speed, moved)
        v.set_target_ned(n0 + 20, e0, z - 5, yaw=s.yaw)
        t["climb"] = _timed(
            v, "5 m climb", speed, lambda: v.wait_ned(n0 + 20, e0, z - 5, tolerance=0.3, timeout=step)
        )
        goal = (s.yaw + math.pi / 2 + math.pi) % (2 * math.pi) - math.pi
        v.set_target_ned(n0 + 20, e0, z - 5, yaw=goal)

        def turned() -> None:
            def ok(st: Any) -> bool:
                return abs((st.yaw - goal + math.pi) % (2 * math.pi) - math.pi) < math.radians(5)

            v.wait_for(ok, step, "yaw")

        t["yaw"] = _timed(v, "90 degree turn", speed, turned)
        held = v.state.mode
        v.stop_setpoints()
        lost = time.monotonic()
        try:  # ArduCopter holds a position target for ever: no failsafe is an answer too
            v.wait_for(lambda st: st.mode != held, LOSS_WAIT_S / speed, "failsafe")
            t["setpoint_loss"] = (time.monotonic() - lost) * speed
        except WaitTimeout:
            out["setpoint_loss"] = None
        out["after_loss"] = v.state.mode
        with contextlib.suppress(BridgeError):  # landed by itself already: nothing to take back
            v.take_control()
            v.set_target_ned(n0 + 20, e0, z)
            v.wait_ned(n0 + 20, e0, z, tolerance=0.5, timeout=step)
        t["land"] = _timed(v, "landing", speed, lambda: v.land(wait=True, timeout=step))
        out.update(t)
        note()
    return out


@contextlib.contextmanager
def _real(kind: sitl.Kind, work: Path, speed: float) -> Iterator[str]:
    try:
        s = sitl.start(kind, work / f"real-{kind}", speed=speed)
    except sitl.SitlError as exc:
        raise SwarmError(str(exc)) from None
    with s:
        yield s.url


@contextlib.contextmanager
def _simulated(kind: str, speed: float) -> Iterator[str]:
    port = free_port("udp" if kind == "px4" else "tcp")
    cfg = SimConfig(
        profile=kind,
        vehicles=1,
        base_port=port,
        speedup=speed,
        boot_time=REALISTIC_BOOTS[kind],
        wait_for_client=kind == "ardupilot",
    )
    sim = VehicleSim(cfg)
    (url,) = sim.start()
    try:
        yield url
    finally:
        sim.stop()


def _compare(real: dict[str, Any], sim: dict[str, Any]) -> dict[str, Any]:
    lo, hi = RATIO_RANGE
    rows: dict[str, Any] = {}
    for k in MILESTONES:
        r, s = real.get(k), sim.get(k)
        ratio = round(s / r, 2) if r and s is not None else None
        rows[k] = {
            "real_s": _r(r),
            "sim_s": _r(s),
            "ratio": ratio,
            "ok": (ratio is not None and lo <= ratio <= hi) or (r is None and s is None),  # neither happened
        }
    acks = {"early_arm": {"real": real.get("early_arm"), "sim": sim.get("early_arm")}}
    acks["early_arm"]["same"] = acks["early_arm"]["real"] == acks["early_arm"]["sim"]
    modes = {
        "real": real.get("modes"),
        "sim": sim.get("modes"),
        "same": real.get("modes") == sim.get("modes"),
    }
    return {
        "milestones": rows,
        "acks": acks,
        "after_loss": {"real": real.get("after_loss"), "sim": sim.get("after_loss")},
        "modes": modes,
        "ratios_in_range": sum(1 for v in rows.values() if v["ok"]),
        "ratios_total": len(rows),
        "ack_mismatches": sum(1 for a in acks.values() if not a["same"]),
        "mode_mismatch": not modes["same"],
    }


def _r(x: float | None) -> float | None:
    return None if x is None else round(x, 1)


def run_real(quick: bool = False) -> dict[str, Any]:
    speed = 2.0 if quick else 1.0
    out: dict[str, Any] = {
        "note": "the same mission by the driver on the real SITL and on swarm sim; ratios simulator / real",
        "speed": speed,
        "target": {"ratio": list(RATIO_RANGE), "ack_mismatches": 0, "mode_mismatches": 0},
    }
    met = True
    with tempfile.TemporaryDirectory(prefix="swarm-conformance-") as tmp:
        for kind in sitl.KINDS:
            with _real(kind, Path(tmp), speed) as url:
                real = fly(url, speed)
            with _simulated(kind, speed) as url:
                sim = fly(url, speed)
            c = _compare(real, sim)
            out[kind] = c
            met = met and c["ratios_in_range"] == c["ratios_total"] and not c["ack_mismatches"]
            met = met and not c["mode_mismatch"]
    out["target_met"] = met
    return out
