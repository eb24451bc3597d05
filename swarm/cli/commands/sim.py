"""``swarm sim``: N simulated multicopters that speak MAVLink 2 like PX4 or ArduPilot SITL.

Vehicle i has system id i+1. px4: it sends to 127.0.0.1:14540+i and answers whoever
talks to it (client ``udpin:127.0.0.1:14540+i``); ardupilot: it listens on TCP
5760+10*i (client ``tcp:127.0.0.1:5760+10i``). ``--serial pty`` puts vehicle 0 on a
pseudo terminal and prints the client's side. All timers run on simulated time,
``--speedup`` times faster than the wall clock. ``--boot-time S`` makes a vehicle boot
as the profile's real SITL was recorded to, scaled to S simulated seconds
(``--realistic-boot``: the recorded 41.5 s of ArduCopter, 34 s of PX4; default 3 s on
the bench; 0: booted when the link comes up). ``--wait-for-client`` (ardupilot, TCP):
simulated time stands at 0 until a client connects, as ArduPilot SITL waits for its
SERIAL0 client.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Sequence

from firmware_bridge.errors import BridgeError
from firmware_bridge.sim import REALISTIC_BOOTS, SimConfig, VehicleSim
from firmware_bridge.sim.autopilot import LOSS_ACTIONS
from swarm.cli.configfile import read_arguments
from swarm.cli.util import StopFlag, UsageError, guarded, parser

PROG = "swarm sim"
#: the default ArduPilot boot on the bench: short, but every phase of a real one is
#: there (null positions, late home, arming refused), so nothing connects and flies
#: as if the autopilot had booted before it
BENCH_BOOT = 3.0


def parse_home(text: str) -> tuple[float, float, float]:
    """``LAT,LON,ALT`` (degrees, degrees, metres AMSL) -> tuple; UsageError if malformed."""
    parts = text.split(",")
    if len(parts) != 3:
        raise UsageError(f"--home must be LAT,LON,ALT, got {text!r}")
    try:
        lat, lon, alt = (float(p) for p in parts)
    except ValueError:
        raise UsageError(f"--home must be three numbers LAT,LON,ALT, got {text!r}") from None
    if not all(math.isfinite(x) for x in (lat, lon, alt)):
        raise UsageError(f"--home must be finite numbers, got {text!r}")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise UsageError(f"--home latitude/longitude out of range: {text!r}")
    if not -1000.0 <= alt <= 10000.0:
        raise UsageError(f"--home altitude must be -1000..10000 m, got {alt}")
    return lat, lon, alt


#: a value that starts with a minus sign and a digit: a negative number, not an option
_NEGATIVE = re.compile(r"^-[0-9.]")
#: options whose value may start with a minus sign
_SIGNED_VALUES = ("--home",)


def join_negative_values(argv: Sequence[str]) -> list[str]:
    """``--home -35.3,149.1,584`` -> ``--home=-35.3,149.1,584``: argparse would take the
    southern latitude for an option; anything else is left as it is."""
    out: list[str] = []
    it = iter(argv)
    for a in it:
        if a in _SIGNED_VALUES:
            nxt = next(it, None)
            if nxt is not None and _NEGATIVE.match(nxt):
                out.append(f"{a}={nxt}")
                continue
            out.append(a)
            if nxt is not None:
                out.append(nxt)
            continue
        out.append(a)
    return out


def _add_battery_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--battery-drain",
        type=float,
        default=0.0,
        metavar="PCT_PER_MIN",
        help="every battery also loses this many percent per simulated minute, armed or not "
        "(tests of low-battery alerts; default 0: only flying drains it)",
    )


def build_parser() -> argparse.ArgumentParser:
    p = parser(
        PROG,
        "Simulate N multicopters speaking MAVLink 2 like PX4 SITL (UDP 14540+i) or "
        "ArduPilot SITL (TCP 5760+10i). Runs until SIGINT/SIGTERM.",
    )
    p.add_argument("--vehicles", type=int, required=True, metavar="N", help="number of vehicles (1..250)")
    p.add_argument(
        "--home",
        default="47.397742,8.545594,488.0",
        metavar="LAT,LON,ALT",
        help="start of vehicle 1 (default PX4 SITL's Zurich home)",
    )
    p.add_argument(
        "--spacing",
        type=float,
        default=5.0,
        metavar="M",
        help="vehicle i starts i*M metres east of home (default 5)",
    )
    p.add_argument(
        "--profile",
        choices=("px4", "ardupilot"),
        default="px4",
        help="whose autopilot to speak like: modes, acks and messages (default px4)",
    )
    p.add_argument(
        "--speedup",
        type=float,
        default=1.0,
        metavar="X",
        help="simulated seconds per wall second (default 1)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (telemetry noise)")
    p.add_argument(
        "--base-port", type=int, metavar="P", help="first port instead of 14540 (px4) or 5760 (ardupilot)"
    )
    p.add_argument(
        "--serial",
        metavar="URL",
        help='vehicle 1 on a serial device (DEVICE[:BAUD]) or "pty" for a new pseudo terminal',
    )
    p.add_argument(
        "--offboard-loss",
        choices=LOSS_ACTIONS,
        default="position",
        help="PX4 action when the offboard stream is lost (COM_OBL_RC_ACT; default position: "
        "Position mode, as PX4's default)",
    )
    _add_battery_arguments(p)
    _add_boot_arguments(p)
    p.add_argument(
        "--wait-for-client",
        action="store_true",
        help="ardupilot: simulated time starts when a client first connects, as ArduPilot "
        "SITL waits for its SERIAL0 client (a client started later still sees the whole boot)",
    )
    return p


def _add_boot_arguments(p: argparse.ArgumentParser) -> None:
    """``--boot-time S`` or ``--realistic-boot`` (ArduPilot's recorded boot)."""
    boot = p.add_mutually_exclusive_group()
    boot.add_argument(
        "--boot-time",
        type=float,
        default=BENCH_BOOT,
        metavar="S",
        help="boot as recorded on the profile's real SITL, scaled to S simulated s "
        f"(no position yet, late home, arming refused; default {BENCH_BOOT:g}; 0: already booted)",
    )
    boot.add_argument(
        "--realistic-boot",
        action="store_true",
        help="the recorded boot: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in sorted(REALISTIC_BOOTS.items()))
        + " to an armable vehicle",
    )


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    args = read_arguments(
        build_parser(), join_negative_values(sys.argv[1:] if argv is None else argv), config=False
    )
    home = parse_home(args.home)
    if not 1 <= args.vehicles <= 250:
        raise UsageError(f"--vehicles must be 1..250, got {args.vehicles}")
    boot_time = REALISTIC_BOOTS[args.profile] if args.realistic_boot else args.boot_time
    if not (math.isfinite(boot_time) and 0.0 <= boot_time <= 600.0):
        raise UsageError(f"--boot-time must be 0..600 s, got {args.boot_time}")
    if not (math.isfinite(args.battery_drain) and 0.0 <= args.battery_drain <= 6000.0):
        raise UsageError(f"--battery-drain must be 0..6000 percent per minute, got {args.battery_drain}")
    if args.wait_for_client and (args.profile != "ardupilot" or args.serial):
        raise UsageError(
            "--wait-for-client needs --profile ardupilot without --serial "
            "(PX4's link sends first; a serial line has no connection to wait for)"
        )
    if args.base_port is not None and not 1 <= args.base_port <= 65535:
        raise UsageError(f"--base-port must be 1..65535, got {args.base_port}")
    cfg = SimConfig(
        vehicles=args.vehicles,
        profile=args.profile,
        home=home,
        spacing=args.spacing,
        speedup=args.speedup,
        seed=args.seed,
        base_port=args.base_port,
        serial=args.serial,
        offboard_loss_action=args.offboard_loss,
        boot_time=boot_time,
        battery_drain=args.battery_drain,
        wait_for_client=args.wait_for_client,
    )
    stop = StopFlag().install()
    try:
        sim = VehicleSim(cfg)
        endpoints = sim.start()
    except BridgeError as exc:
        raise UsageError(str(exc)) from None
    try:
        for i, ep in enumerate(endpoints):
            v = sim.vehicle(i)
            lat, lon, alt = v.start_geo
            print(
                f"vehicle {i + 1} sysid={v.sysid} {args.profile} {v.transport.kind} -> {ep} "
                f"home={lat:.7f},{lon:.7f},{alt:.1f}",
                flush=True,
            )
        booting = f", boot {boot_time:g} s" if boot_time > 0 and args.profile == "ardupilot" else ""
        waiting = ", waiting for a client" if args.wait_for_client else ""
        print(f"ready: {len(endpoints)} vehicle(s), speedup {args.speedup:g}{booting}{waiting}", flush=True)
        while not stop.wait(0.5):
            if sim.error is not None:
                print(f"{PROG}: error: {sim.error}", file=sys.stderr, flush=True)
                return 1
    finally:
        sim.stop()
    return stop.exit_code()
