"""A cold start on the bench: an agent and a simulated ArduCopter powered on together.

Theory of operation
-------------------
A real ArduCopter sends GLOBAL_POSITION_INT at 0, 0, 0 for seconds after boot, sets
home late and refuses to arm for about 42 s. This figure starts, at one moment, the
radio emulator (with a capture), ``swarm sim --profile ardupilot`` with the recorded
boot (``--realistic-boot``; ``quick``: the same timeline scaled to 10 s), a real
``swarm agent`` on it and a ground station on the other radio. From the moment the
agent is connected the station asks for a take-off every few seconds, as an impatient
operator would, and keeps what the agent answers, until a take-off is accepted (or in
progress) and the agent is airborne.

Then the capture is read: every pose the agent sent on the air (its PoseReports) is
checked against the simulator's boot timeline (the vehicle's GPS position is valid
from ``POSITION_VALID`` of the recorded 41.5 s, scaled, after the simulator printed
that it runs: an upper bound of the real moment, so a late pose is never excused):

* ``null_poses_sent``: poses at latitude and longitude 0 (Null Island; target 0);
* ``poses_before_fix``: poses sent before the GPS position was valid (target 0);
* ``first_pose_s``: when the first pose went out, after the simulator started;
* ``takeoff_refusals``: the distinct reasons the agent gave for refusing a take-off
  while the autopilot booted (its own words), ``takeoff_accepted_s`` when one was
  accepted; ``airborne`` whether the station saw the vehicle fly.
"""

from __future__ import annotations

import os
import tempfile
import time
from typing import Any

from firmware_bridge.sim import REALISTIC_BOOT
from firmware_bridge.sim.boot import POSITION_VALID, RECORDED_TOTAL
from radios.ports import free_port
from swarm.cli.procs import Child, start_emulator
from swarm.core.station.commands import DONE_RESULTS, CommandRefused, CommandSpec
from swarm.core.station.model import StationConfig
from swarm.core.wire.message_types import AckResult, CommandKind, PoseReport
from swarm.runtime.station.live import Station

QUICK_BOOT = 10.0
AGENT_ID = 1
STATION_ID = 254
ASK_EVERY_S = 3.0  # the impatient operator's take-off button
TAKEOFF_ALT_M = 5.0


def run(quick: bool = False) -> dict[str, Any]:
    boot = QUICK_BOOT if quick else REALISTIC_BOOT
    with tempfile.TemporaryDirectory(prefix="swarm-cold-start-") as d:
        capture = os.path.join(d, "air.tlog")
        children: list[Child] = []
        station: Station | None = None
        try:
            os.makedirs(os.path.join(d, "radios"))
            emu, links = start_emulator(2, os.path.join(d, "radios"), "--capture", capture)
            children.append(emu)
            sim = Child(
                [
                    *("sim", "--vehicles", "1", "--profile", "ardupilot"),
                    *("--boot-time", str(boot), "--base-port", str(free_port("tcp"))),
                ],
                name="vehicle simulator",
            )
            children.append(sim)
            fc = sim.wait_lines(1, 30)[0].split(" -> ", 1)[1].split()[0]
            sim_start = time.time()  # its clock started before it printed: an upper bound
            agent = Child(
                ["agent", "--name", "cold", "--id", str(AGENT_ID), "--radio", links[0], "--fc", fc],
                name="agent",
            )
            children.append(agent)
            station = Station(
                "bench", STATION_ID, radio=links[1], config=StationConfig(command_give_up=20.0)
            ).start()
            out = _ask_until_airborne(station, sim_start, boot + 90.0)
        finally:
            if station is not None:
                station.stop()
            for ch in reversed(children):
                ch.stop()
        out.update(_poses(capture, sim_start, boot))
        said = [line for line in agent.lines + agent.errors if "position" in line]
        out["agent_said"] = said[:4]
    return {"boot_s": round(boot, 2), **out}


def _ask_until_airborne(station: Station, sim_start: float, limit_s: float) -> dict[str, Any]:
    """Take-off asked every ASK_EVERY_S from the agent's connection until accepted,
    then until the station sees it airborne; what the agent said on the way."""
    refusals: list[str] = []
    accepted_at: float | None = None
    end = sim_start + limit_s
    while time.time() < end and accepted_at is None:
        asked = time.time()
        try:
            fut = station.submit(CommandSpec(AGENT_ID, CommandKind.TAKEOFF, alt=TAKEOFF_ALT_M))
            _status, body = fut.result(timeout=60.0)
        except CommandRefused:  # not connected yet
            time.sleep(0.5)
            continue
        (r,) = body["results"]
        if r["result"] in (*DONE_RESULTS, AckResult.IN_PROGRESS.name):
            accepted_at = time.time()
        elif r["reason"] not in refusals:
            refusals.append(r["reason"])
        time.sleep(max(0.0, asked + ASK_EVERY_S - time.time()))
    while accepted_at is not None and time.time() < end:
        if (station.agent(AGENT_ID) or {}).get("airborne"):
            break
        time.sleep(0.2)
    return {
        "takeoff_refusals": refusals,
        "takeoff_accepted_s": None if accepted_at is None else round(accepted_at - sim_start, 1),
        "airborne": bool((station.agent(AGENT_ID) or {}).get("airborne")),
    }


def _poses(capture: str, sim_start: float, boot: float) -> dict[str, Any]:
    """The agent's poses on the air against the boot timeline."""
    from radios.errors import CaptureError
    from radios.mavlink import MSG_TUNNEL
    from radios.tlog import read_tlog
    from swarm.core.wire.messages import decode
    from swarm.core.wire.tunnel import Kind, unpack_tunnel
    from swarm.errors import DecodeError

    valid_from = sim_start + POSITION_VALID * boot / RECORDED_TOTAL
    times: list[float] = []
    null = early = 0
    reader = read_tlog(capture)
    try:
        for rec in reader:
            if rec.frame.msgid != MSG_TUNNEL or rec.frame.sysid != AGENT_ID:
                continue
            try:
                tun = unpack_tunnel(rec.frame.payload)
                msg = decode(tun[3]) if tun is not None and tun[0] == Kind.POSE else None
            except DecodeError:
                continue
            if isinstance(msg, PoseReport):
                times.append(rec.t)
                null += msg.pose.lat == 0.0 and msg.pose.lon == 0.0
                early += rec.t < valid_from
    except CaptureError:  # a torn last record: what was read counts
        pass
    finally:
        reader.close()
    return {
        "poses_sent": len(times),
        "null_poses_sent": null,
        "poses_before_fix": early,
        "first_pose_s": round(min(times) - sim_start, 1) if times else None,
    }


__all__ = ["run"]
