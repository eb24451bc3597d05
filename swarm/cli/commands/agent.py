"""``swarm agent``: run one swarm agent (leader election and membership) until stopped.

The agent meets others either through a radio (``--radio URL``: a SiK radio or an
emulator pty; the Zenoh session then has no endpoints) or over IP with Zenoh
endpoints (``--zenoh-listen`` / ``--zenoh-connect``). It prints one line when ready,
then one line per change of its protocol state; with ``--json`` each of those is
one JSON object: the ready line ``{"event": "ready", "name", "id", "link"}``, then
``{"event": "state", "name", "id", "phase", "leader", "pool", "locked", "members",
"candidate", "weight", "epoch", "t"}`` (``t``: seconds since the agent started).
With ``--json``, what the pilot does (commands answered, following, holds and
why; each command with its seq) comes as ``{"event": "pilot", "name", "id", "text",
"t"}`` lines, and a flight controller falling silent or heard again as
``{"event": "vehicle", "name", "id", "link": false | true, "text", "t"}``.
SIGINT or SIGTERM stops it cleanly (exit 0).

If the radio goes away (a USB radio unplugged) the agent keeps its swarm state and
waits for the device to come back at the same path, reopening it with back-off;
it prints ``agent NAME: radio lost: ...`` and ``agent NAME: radio back after S s``
(``--json``: ``{"event": "radio", "name", "id", "state": "lost"|"back", "text",
"t"}``). With ``--exit-on-radio-loss`` it exits 1 instead, with one line on stderr.

The ``fast`` profile derives its windows from the radio network's TDM round, which
the agent does not read from the radio: give ``--round-s``, or ``--slots N`` (the
number of radios of a multipoint network; 2 for a standard pair) and
``--air-speed`` and the round is computed as the SiK firmware does.

``--radio-params NETID=25,AIR_SPEED=64`` (or a JSON/TOML file) makes the agent check
its radio before the bridge opens it (:mod:`radios.sik.guard`: ``+++``, ``ATI5``):
any radio in range can change a SiK radio's parameters with ``RT`` commands. A
radio that differs is named in one line and the agent exits 1; with
``--restore-radio`` it writes the expected values back (``AT&W``, ``ATZ``), says so
in one line and starts. ``--radio-recheck S`` repeats the check when the agent has
heard no other agent for S seconds (a radio moved to another NETID hears no one):
the radio bridge lends the port to the check for a few seconds
(:meth:`~swarm.runtime.bridge.RadioBridge.lend_radio`) while the agent goes on, in flight
too: its protocol state, its pilot and its flight controller are not touched, and
a radio that hears no one loses nothing by the pause. A re-check that finds the
radio silent, or different without ``--restore-radio``, prints one line
(``radio-check-failed``) and the agent carries on; it tries again S seconds later.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from firmware_bridge.errors import BridgeError, ConnectError, HeartbeatTimeout
from radios.errors import ATError, RadioError
from radios.sik.guard import RecheckTimer, check_radio, describe, parse_expected
from swarm.cli.util import EXIT_FAILURE, EXIT_USAGE, StopFlag, UsageError, guarded, parser, print_json
from swarm.core.formation import FormationConfig
from swarm.core.messages import AgentState
from swarm.core.pilot import PilotConfig
from swarm.errors import MessageError, TransportError
from swarm.runtime.agent import (
    PROFILES,
    VEHICLE_LINK_BACK,
    VEHICLE_LINK_LOST,
    VOTES,
    Agent,
    default_round_s,
    state_dict,
)

PROG = "swarm agent"


def _build_parser() -> argparse.ArgumentParser:
    p = parser(
        PROG,
        "Run one swarm agent: dynamic leader selection and membership over a "
        "radio or Zenoh, until SIGINT/SIGTERM.",
    )
    p.add_argument("--name", required=True, help="agent name (1-16 of A-Z a-z 0-9 _ -)")
    p.add_argument("--id", required=True, type=int, help="MAVLink system id, 1..250, unique in the swarm")
    p.add_argument("--radio", metavar="URL", help="radio link: serial device or emulator pty (DIR/radioK)")
    p.add_argument(
        "--zenoh-listen",
        nargs="+",
        default=[],
        metavar="EP",
        help="Zenoh endpoints to listen on (tcp/127.0.0.1:7447), instead of a radio",
    )
    p.add_argument(
        "--zenoh-connect",
        nargs="+",
        default=[],
        metavar="EP",
        help="Zenoh endpoints to connect to, instead of a radio",
    )
    p.add_argument(
        "--fc",
        metavar="URL",
        help="flight controller (udpin:0.0.0.0:14540, tcp:host:port, /dev/ttyACM0...): optional",
    )
    p.add_argument(
        "--profile",
        choices=PROFILES,
        default="paper",
        help="timing profile: the paper's windows, or fast (from the TDM round)",
    )
    p.add_argument(
        "--round-s",
        type=float,
        metavar="S",
        help="TDM round of the radio network in seconds, for --profile fast "
        "(default: computed from --slots and --air-speed)",
    )
    p.add_argument(
        "--slots",
        type=int,
        default=2,
        metavar="N",
        help="radios in the network (multipoint slots; 2 for a standard pair; default 2)",
    )
    p.add_argument(
        "--air-speed", type=int, default=64, metavar="KBPS", help="radio air rate for the round (default 64)"
    )
    p.add_argument("--key", metavar="FILE", help="swarm signing key (32 bytes, 64 hex digits or passphrase)")
    p.add_argument(
        "--radio-params",
        metavar="NAME=V,...|FILE",
        help="the swarm's radio parameters (NETID=25,AIR_SPEED=64,... or a JSON/TOML "
        "file): check the radio before starting, refuse to start if it differs",
    )
    p.add_argument(
        "--radio-recheck",
        type=float,
        default=0.0,
        metavar="S",
        help="with --radio-params: check the radio again after S seconds without "
        "hearing another agent (not while the vehicle is armed; default: off)",
    )
    p.add_argument(
        "--restore-radio",
        action="store_true",
        help="with --radio-params: write the expected values back (AT&W, ATZ) instead of refusing to start",
    )
    p.add_argument(
        "--vote",
        choices=VOTES,
        default="random",
        help="vote weight: random (the paper), battery, or link (RSSI)",
    )
    p.add_argument("--pose-hz", type=float, default=4.0, help="pose rate with a flight controller")
    f = p.add_argument_group("formation and flight (with --fc)")
    f.add_argument(
        "--speed", type=float, default=5.0, metavar="M/S", help="route speed of a leader (default 5)"
    )
    f.add_argument("--back", type=float, default=10.0, metavar="M", help="slot distance behind (default 10)")
    f.add_argument(
        "--side", type=float, default=5.0, metavar="M", help="slot distance to the side (default 5)"
    )
    f.add_argument(
        "--stagger",
        type=float,
        default=0.0,
        metavar="M",
        help="altitude step per chain position (default 0: one altitude)",
    )
    f.add_argument(
        "--min-separation",
        type=float,
        default=3.0,
        metavar="M",
        help="hold when another agent is closer than this (default 3)",
    )
    f.add_argument(
        "--turn-radius",
        type=float,
        default=25.0,
        metavar="M",
        help="corner radius of a leader's route (default 25)",
    )
    p.add_argument("--json", action="store_true", help="JSON lines instead of text")
    add_radio_loss_argument(p)
    return p


def add_radio_loss_argument(p: argparse.ArgumentParser) -> None:
    """``--exit-on-radio-loss``, shared with ``swarm gcs``."""
    p.add_argument(
        "--exit-on-radio-loss",
        action="store_true",
        help="exit 1 when the radio goes away, instead of waiting for it to come "
        "back (for a service manager that restarts the program)",
    )


def radio_loss_message(bridge: Any) -> str:
    """The one line for a radio lost for good (``bridge`` may be None)."""
    reason = getattr(bridge, "loss_reason", "")
    return "radio link lost" + (f": {reason}" if reason else "")


def _text(name: str, st: AgentState) -> str:
    d = state_dict(name, st)
    parts = [f"agent {name} id={d['id']} {d['phase']}"]
    if d["leader"]:
        parts.append(f"leader={d['leader']}")
    parts.append("pool=" + ",".join(map(str, d["pool"])) + (" locked" if d["locked"] else ""))
    if d["members"]:
        parts.append("members=" + ",".join(map(str, d["members"])))
    if d["candidate"]:
        parts.append(f"vote={d['candidate']}:{d['weight']:#010x}")
    return " ".join(parts)


def _check_radio(a: argparse.Namespace, *, again: bool = False, lock: threading.Lock | None = None) -> None:
    """The radio guard (before the bridge opens the port, or on a port it lent). Raises
    RadioError for a radio that differs (without --restore-radio) or does not answer, and
    ConfigError for bad expected parameters. ``again``: a re-check of an isolated agent,
    which says so in one line even when the radio is as expected. ``lock``: held while
    printing (not while checking: the agent's threads print too)."""
    report = check_radio(a.radio, parse_expected(a.radio_params), restore=a.restore_radio)

    def say(obj: dict[str, Any], text: str) -> None:
        with lock if lock is not None else contextlib.nullcontext():
            try:
                if a.json:
                    print_json({**obj, "name": a.name, "id": a.id, "radio": a.radio})
                else:
                    print(f"agent {a.name}: {text}", flush=True)
            except (BrokenPipeError, ValueError):
                pass

    if not report.mismatches:
        if again:
            say(
                {"event": "radio-checked"},
                f"radio {a.radio} checked after {a.radio_recheck:g} s "
                "without hearing another agent: as expected",
            )
        return
    what = describe(report.mismatches)
    if not report.restored:
        raise ATError(
            f"radio {a.radio} differs from the swarm's parameters: {what}; "
            "another radio may have reconfigured it (RT commands). Fix it with "
            "swarm radio-config, or pass --restore-radio"
        )
    say(
        {"event": "radio-restored", "differed": {m.name: m.actual for m in report.mismatches}},
        f"radio {a.radio} differed from the swarm's parameters ({what}): restored",
    )


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = _build_parser().parse_args(argv)
    if not 1 <= a.id <= 250:
        raise UsageError(f"--id {a.id}: agent ids are 1..250 (255 is the ground station)")
    if a.radio is None and not (a.zenoh_listen or a.zenoh_connect):
        raise UsageError("give --radio URL, or --zenoh-listen / --zenoh-connect endpoints")
    if a.radio is not None and (a.zenoh_listen or a.zenoh_connect):
        raise UsageError("--radio and Zenoh endpoints exclude each other")
    if a.exit_on_radio_loss and a.radio is None:
        raise UsageError("--exit-on-radio-loss is for an agent on a radio (--radio)")
    if a.round_s is None:
        if not 2 <= a.slots <= 32:
            raise UsageError("--slots: 2..32")
        try:
            a.round_s = default_round_s(a.slots, a.air_speed)
        except ValueError as exc:
            raise UsageError(f"--air-speed: {exc}") from None
    if (a.restore_radio or a.radio_recheck) and not a.radio_params:
        raise UsageError("--restore-radio and --radio-recheck need --radio-params")
    if a.radio_recheck < 0:
        raise UsageError(f"--radio-recheck {a.radio_recheck}: seconds, 0 for off")
    if a.radio_params:
        if a.radio is None:
            raise UsageError("--radio-params checks a radio: give --radio")
        _check_radio(a)
    lock = threading.Lock()
    t0 = time.monotonic()

    # state changes that happen before the ready line is out wait for it, so that
    # readers always see "ready" first
    gate: dict[str, Any] = {"ready": False, "pending": [], "t0": t0}

    def on_state(st: AgentState) -> None:
        with lock:
            if not gate["ready"]:
                gate["pending"].append(st)
                return
            emit(st)

    def emit(st: AgentState) -> None:  # called with ``lock`` held
        try:
            if a.json:
                print_json({"event": "state", **state_dict(a.name, st), "t": round(time.monotonic() - t0, 3)})
            else:
                print(_text(a.name, st), flush=True)
        except (BrokenPipeError, ValueError):  # stdout gone: keep running quietly
            pass

    def on_event(text: str) -> None:
        with lock:
            if not gate["ready"]:
                return
            try:
                if a.json and text in (VEHICLE_LINK_LOST, VEHICLE_LINK_BACK):
                    print_json(
                        {
                            "event": "vehicle",
                            "name": a.name,
                            "id": a.id,
                            "link": text == VEHICLE_LINK_BACK,
                            "text": text,
                            "t": round(time.monotonic() - t0, 3),
                        }
                    )
                elif a.json:
                    print_json(
                        {
                            "event": "pilot",
                            "name": a.name,
                            "id": a.id,
                            "text": text,
                            "t": round(time.monotonic() - t0, 3),
                        }
                    )
                else:
                    print(f"agent {a.name}: {text}", flush=True)
            except (BrokenPipeError, ValueError):
                pass

    try:
        pilot = PilotConfig(
            speed_mps=a.speed,
            turn_radius_m=a.turn_radius,
            formation=FormationConfig(
                back_m=a.back, side_m=a.side, stagger_m=a.stagger, min_separation_m=a.min_separation
            ),
        )

        agent = Agent(
            a.name,
            a.id,
            radio=a.radio,
            zenoh_listen=a.zenoh_listen,
            zenoh_connect=a.zenoh_connect,
            fc=a.fc,
            profile=a.profile,
            round_s=a.round_s,
            key_file=a.key,
            vote=a.vote,
            pose_hz=a.pose_hz,
            pilot=pilot,
            on_state=on_state,
            on_event=on_event,
        )
    except (MessageError, ValueError) as exc:
        raise UsageError(str(exc)) from None
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run(a, agent, StopFlag().install(), lock, gate, emit)
    finally:
        for sig, handler in previous.items():  # main() may run inside another program
            signal.signal(sig, handler)


def _watch_radio(a: argparse.Namespace, bridge: Any, lock: threading.Lock, gate: dict[str, Any]) -> None:
    """Radio lost / back as events; with --exit-on-radio-loss the bridge gives up
    instead of reopening (the agent then stops and main exits 1)."""
    if a.exit_on_radio_loss:
        bridge.cfg.reopen_radio = False
    t0 = gate["t0"]

    def on_radio(what: str, text: str) -> None:
        with lock:
            if not gate["ready"]:
                return
            try:
                if a.json:
                    print_json(
                        {
                            "event": "radio",
                            "name": a.name,
                            "id": a.id,
                            "state": what,
                            "text": text,
                            "t": round(time.monotonic() - t0, 3),
                        }
                    )
                else:
                    sep = ": " if what in ("lost", "paused") else " "
                    print(f"agent {a.name}: radio {what}{sep}{text}", flush=True)
            except (BrokenPipeError, ValueError):
                pass

    bridge.add_listener(on_radio)


def _isolated(agent: Agent) -> bool:
    """The agent hears no other agent: alone in its pool, following no one else."""
    st = agent.state()
    if st is None:
        return True
    others = (st.pool | st.members) - {agent.id}
    return not others and st.leader in (0, agent.id)


def _recheck_radio(a: argparse.Namespace, bridge: Any, lock: threading.Lock) -> None:
    """Check (and restore) the radio of a running agent: the bridge lends the port."""
    try:
        bridge.lend_radio(lambda: _check_radio(a, again=True, lock=lock), why="radio check")
    except RadioError as exc:  # silent, different, refused: say so, keep flying, retry later
        with lock:
            try:
                if a.json:
                    print_json(
                        {
                            "event": "radio-check-failed",
                            "name": a.name,
                            "id": a.id,
                            "radio": a.radio,
                            "error": str(exc),
                        }
                    )
                else:
                    print(f"agent {a.name}: radio check failed: {exc}", flush=True)
            except (BrokenPipeError, ValueError):
                pass


def _start(agent: Agent) -> int | None:
    """Start the agent; None on success, else the exit code (message printed)."""
    try:
        agent.start()
    except TransportError as exc:
        agent.stop()
        raise UsageError(str(exc)) from None
    except HeartbeatTimeout as exc:
        agent.stop()
        print(f"{PROG}: error: flight controller: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except ConnectError as exc:
        agent.stop()
        print(f"{PROG}: error: flight controller: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BridgeError as exc:
        agent.stop()
        print(f"{PROG}: error: flight controller: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    return None


def _run(
    a: argparse.Namespace,
    agent: Agent,
    stop: StopFlag,
    lock: threading.Lock,
    gate: dict[str, Any],
    emit: Callable[[AgentState], None],
) -> int:
    failed = _start(agent)
    if failed is not None:
        return failed
    if agent.bridge is not None:
        _watch_radio(a, agent.bridge, lock, gate)
    recheck = RecheckTimer(a.radio_recheck) if a.radio_recheck else None
    try:
        with lock:
            if a.json:
                print_json(
                    {
                        "event": "ready",
                        "name": a.name,
                        "id": a.id,
                        "link": agent.describe(),
                        "profile": agent.profile.name,
                        "round_s": round(agent.round_s, 4),
                    }
                )
            else:
                print(
                    f"agent {a.name} id={a.id} {agent.describe()} profile={agent.profile.name} ready",
                    flush=True,
                )
            gate["ready"] = True
            for st in gate["pending"]:
                emit(st)
            gate["pending"].clear()
        while not stop.wait(0.5):
            if (
                recheck is not None
                and agent.bridge is not None
                and recheck.update(_isolated(agent), time.monotonic())
            ):
                _recheck_radio(a, agent.bridge, lock)
                continue
            if not agent.running:
                why = (
                    radio_loss_message(agent.bridge)
                    if agent.bridge is not None and agent.bridge.link_lost
                    else "the agent's protocol thread stopped"
                )
                print(f"{PROG}: error: {why}", file=sys.stderr)
                return EXIT_FAILURE
    finally:
        agent.stop()
    return 0
