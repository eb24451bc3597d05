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
SIGINT or SIGTERM stops it cleanly (exit 130 after Ctrl-C, 0 after SIGTERM).

If the radio goes away (a USB radio unplugged) the agent keeps its swarm state and
waits for the device to come back at the same path, reopening it with back-off;
it prints ``agent NAME: radio lost: ...`` and ``agent NAME: radio back after S s``
(``--json``: ``{"event": "radio", "name", "id", "state": "lost"|"back", "text",
"t"}``). With ``--exit-on-radio-loss`` it exits 1 instead, with one line on stderr.

The ``fast`` and ``tdm`` profiles derive their windows from the radio network's TDM round, which
the agent does not read from the radio: give ``--round-s``, or ``--slots N`` (the
number of radios of a multipoint network; 2 for a standard pair) and
``--air-speed`` and the round is computed as the SiK firmware does.

``--radio-params NETID=25,AIR_SPEED=64`` (or a JSON/TOML file, such as the one
``swarm radio-config --write-params`` writes) makes the agent check its radio before
the bridge opens it (:mod:`radios.sik.guard`: ``+++``, ``ATI5``): any radio in range
can change a SiK radio's parameters with ``RT`` commands. A radio that differs is
named in one line and the agent exits 1; with ``--restore-radio`` it writes the
expected values back (``AT&W``, ``ATZ``), says so in one line and starts. From then
on the guard keeps every register: the given ones, and every other register at the
value the radio showed at that start check (:func:`~radios.sik.guard.baseline`).
``--radio-check-period S`` checks the radio again every S seconds, and
``--radio-recheck S`` when the agent has heard no other agent for S seconds (a radio
moved to another network hears no one): the radio bridge lends the port to the
check for about 2.3 s (:meth:`~swarm.runtime.bridge.radio_bridge.RadioBridge.lend_radio`) while
the agent goes on, in flight too: its protocol state, its pilot and its flight
controller are not touched. Each re-check prints ``radio-checked`` (``why``:
``period`` or ``isolated``; the ``radio`` events ``paused`` and ``back`` around it
say how long the radio was away); one that finds
a register changed restores it with ``--restore-radio`` (``radio-restored``, with
``differed``: name -> the value found); one that finds the radio silent, or
different without ``--restore-radio``, prints ``radio-check-failed`` and the agent
carries on and tries again at the next check.

``--capture DIR`` keeps a flight log (:mod:`radios.rotating`): the radio's traffic
both ways in ``NAME-YYYYmmddTHHMMSSZ-NNNN.tlog`` and the flight controller's key
messages in ``...NNNN.fc.tlog``, rotated at ``--capture-max-mb`` or
``--capture-rotate-s``, the oldest removed to stay under ``--capture-budget-mb``,
synced about once a second. A folder that is a symbolic link, a file, or not
writable is refused at start (exit 2); a full disk later pauses the log with one
line (``{"event": "flight-log", ...}`` with ``--json``) and the agent flies on.

With ``--key`` on a radio the agent keeps its signing clock in its state folder
(``--state-dir``, :mod:`swarm.cli.state_dir`): a frame stamped before this start is
refused, so a recording made before a restart is not taken after it.
"""

from __future__ import annotations

import argparse
import math
import random
import signal
import sys
import threading
import time
from dataclasses import replace
from typing import Any

from firmware_bridge.errors import BridgeError
from radios.errors import ATError, RadioError
from radios.secretfile import KEY, secret_file_problem
from radios.sik.guard import CheckSchedule, baseline, check_radio, describe, known_of, parse_expected
from swarm.cli.configfile import file_errors, read_arguments
from swarm.cli.fence_args import add_fence_arguments, fence_from
from swarm.cli.state_dir import add_state_dir_argument, node_file, open_state_dir
from swarm.cli.util import (
    StopFlag,
    UsageError,
    add_node_arguments,
    exit_code,
    exit_when_stopped,
    guarded,
    node_options,
    parser,
    peer_watch,
    print_json,
)
from swarm.core.agent.node import VEHICLE_LINK_BACK, VEHICLE_LINK_LOST
from swarm.core.election.caps import MAX_CAP, check_cap
from swarm.core.flight.formation import FormationConfig
from swarm.core.flight.pilot import PilotConfig
from swarm.core.wire.message_types import NAME_RE, AgentState
from swarm.errors import MessageError
from swarm.runtime.agent.live import Agent, default_round_s
from swarm.runtime.agent.vehicle import state_dict
from swarm.runtime.notify import Service
from swarm.runtime.options import PROFILES, VOTES, AgentConfig

PROG = "swarm agent"
MIN_CHECK_PERIOD_S = 10.0  # a radio check pauses the link about 2.3 s: at most a quarter of the time


def build_parser() -> argparse.ArgumentParser:
    p = parser(
        PROG,
        "Run one swarm agent: dynamic leader selection and membership over a "
        "radio or Zenoh, until SIGINT/SIGTERM.",
    )
    p.add_argument("--name", required=True, help="agent name (1-16 of A-Z a-z 0-9 _ -)")
    p.add_argument("--id", required=True, type=int, help="MAVLink system id, 1..250, unique in the swarm")
    add_node_arguments(p)
    add_state_dir_argument(p)
    p.add_argument(
        "--fc",
        metavar="URL",
        help="flight controller (udpin:0.0.0.0:14540, tcp:host:port, /dev/ttyACM0...): optional",
    )
    _add_timing_arguments(p)
    _add_radio_check_arguments(p)
    p.add_argument(
        "--vote",
        choices=VOTES,
        default="random",
        help="vote weight: random (the paper), battery, or link (RSSI)",
    )
    p.add_argument("--pose-hz", type=float, default=4.0, help="pose rate with a flight controller")
    p.add_argument(
        "--swarm-cap",
        type=int,
        default=0,
        metavar="N",
        help="the most agents in this agent's swarm (2..250): agents beyond it form further swarms, "
        "each with its own leader; 0: no cap, one swarm (default)",
    )
    p.add_argument(
        "--swarm-name",
        metavar="NAME",
        help="pool and merge only with agents given this swarm name (1-16 of A-Z a-z 0-9 _ -); "
        "default: none (only with agents without a name)",
    )
    _add_flight_arguments(p)
    add_fence_arguments(p, "the agent's pilot")
    _add_capture_arguments(p)
    p.add_argument("--json", action="store_true", help="JSON lines instead of text")
    return p


#: flag -> (default, what): the flight log's sizes and age (defaults for a Pi's SD card)
CAPTURE_FLAGS = {
    "--capture-max-mb": (16.0, "start a new file past this size"),
    "--capture-rotate-s": (600.0, "start a new file after this many seconds"),
    "--capture-budget-mb": (512.0, "remove the oldest files to keep the set under this size"),
}


def _add_capture_arguments(p: argparse.ArgumentParser) -> None:
    c = p.add_argument_group("flight log")
    c.add_argument(
        "--capture",
        metavar="DIR",
        help="keep a flight log in DIR (created if missing): the radio's traffic both ways and "
        "the flight controller's key messages, as rotated .tlog files",
    )
    for flag, (default, what) in CAPTURE_FLAGS.items():
        c.add_argument(
            flag,
            type=float,
            metavar="MB" if flag.endswith("mb") else "S",
            help=f"{what} (default {default:g})",
        )


def _flight_log(a: argparse.Namespace, out: Lines) -> Any:
    """The flight log ``--capture`` asks for (None without it). Raises UsageError for
    its flags and ConfigError for a folder that is a link, a file or not writable."""
    given = {f: getattr(a, f[2:].replace("-", "_")) for f in CAPTURE_FLAGS}
    if a.capture is None:
        if any(v is not None for v in given.values()):
            raise UsageError(f"{', '.join(f for f, v in given.items() if v is not None)} need --capture")
        return None
    from radios.rotating import MB, FlightLog, RotationPolicy

    v = {f: CAPTURE_FLAGS[f][0] if x is None else x for f, x in given.items()}
    for flag, x in v.items():
        if not (math.isfinite(x) and x > 0):
            raise UsageError(f"{flag} {x:g}: must be a positive number")
    try:
        policy = RotationPolicy(
            max_bytes=int(v["--capture-max-mb"] * MB),
            rotate_s=v["--capture-rotate-s"],
            budget_bytes=int(v["--capture-budget-mb"] * MB),
        )
    except ValueError as exc:
        raise UsageError(f"--capture: {exc}") from None

    def say(text: str) -> None:
        out.line({"event": "flight-log", "name": a.name, "id": a.id, "text": text}, f"agent {a.name}: {text}")

    return FlightLog(a.capture, a.name, policy, on_error=say)


def _add_timing_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--profile",
        choices=PROFILES,
        default="paper",
        help="timing profile: the paper's windows, fast (from the TDM round), or tdm (from the "
        "round, votes exchanged while pooling: the fastest election on SiK multipoint)",
    )
    p.add_argument(
        "--round-s",
        type=float,
        metavar="S",
        help="TDM round of the radio network in seconds, for --profile fast or tdm "
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


def _add_radio_check_arguments(p: argparse.ArgumentParser) -> None:
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
        "hearing another agent (default: off)",
    )
    p.add_argument(
        "--radio-check-period",
        type=float,
        default=0.0,
        metavar="S",
        help="with --radio-params: check every register of the radio every S seconds "
        "(the link pauses about 2.3 s each time; 0: off, the default)",
    )
    p.add_argument(
        "--restore-radio",
        action="store_true",
        help="with --radio-params: write the expected values back (AT&W, ATZ) instead of refusing to start",
    )


def _add_flight_arguments(p: argparse.ArgumentParser) -> None:
    f = p.add_argument_group("formation and flight (with --fc)")
    for flag, default, what in (
        ("--speed", 5.0, "route speed of a leader"),
        ("--back", 10.0, "slot distance behind"),
        ("--side", 5.0, "slot distance to the side"),
        ("--stagger", 0.0, "altitude step per chain position"),
        ("--min-separation", 3.0, "hold when another agent is closer than this"),
        ("--turn-radius", 25.0, "corner radius of a leader's route"),
    ):
        note = ": one altitude" if flag == "--stagger" else ""
        metavar = "M/S" if flag == "--speed" else "M"
        f.add_argument(
            flag, type=float, default=default, metavar=metavar, help=f"{what} (default {default:g}{note})"
        )


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


class Lines:
    """The agent's stdout, from any of its threads: text, or JSON lines with ``--json``.
    The ready line comes first: states before it wait for it, events before it are
    dropped. A closed stdout is ignored (the agent keeps running quietly)."""

    def __init__(self, a: argparse.Namespace) -> None:
        self.name, self.id, self.json = a.name, a.id, a.json
        self.lock = threading.Lock()
        self.t0 = time.monotonic()
        self.ready = False
        self._pending: list[AgentState] = []

    def _put(self, obj: dict[str, Any], text: str) -> None:  # called with ``lock`` held
        try:
            if self.json:
                print_json(obj)
            else:
                print(text, flush=True)
        except (BrokenPipeError, ValueError):  # stdout gone: keep running quietly
            pass

    def line(self, obj: dict[str, Any], text: str) -> None:
        """One line at once, ready or not (the radio check's)."""
        with self.lock:
            self._put(obj, text)

    def event(self, event: str, text: str, /, **fields: Any) -> None:
        """``{"event", "name", "id", **fields, "t"}`` or ``agent NAME: text``, once ready."""
        obj = {"event": event, "name": self.name, "id": self.id, **fields}
        obj["t"] = round(time.monotonic() - self.t0, 3)
        with self.lock:
            if self.ready:
                self._put(obj, f"agent {self.name}: {text}")

    def state(self, st: AgentState) -> None:
        with self.lock:
            if not self.ready:
                self._pending.append(st)
            else:
                self._state(st)

    def _state(self, st: AgentState) -> None:  # called with ``lock`` held
        t = round(time.monotonic() - self.t0, 3)
        self._put({"event": "state", **state_dict(self.name, st), "t": t}, _text(self.name, st))

    def pilot(self, text: str) -> None:
        """The agent's events: its vehicle link lost or back, what its pilot does."""
        if text in (VEHICLE_LINK_LOST, VEHICLE_LINK_BACK):
            self.event("vehicle", text, link=text == VEHICLE_LINK_BACK, text=text)
        else:
            self.event("pilot", text, text=text)

    def radio(self, what: str, text: str) -> None:
        sep = ": " if what in ("lost", "paused") else " "
        self.event("radio", f"radio {what}{sep}{text}", state=what, text=text)

    def open(self, agent: Agent) -> None:
        """The ready line, then the states that waited for it."""
        obj = {"event": "ready", "name": self.name, "id": self.id, "link": agent.describe()}
        obj.update(profile=agent.profile.name, round_s=round(agent.round_s, 4))
        text = f"agent {self.name} id={self.id} {agent.describe()} profile={agent.profile.name} ready"
        with self.lock:
            self._put(obj, text)
            self.ready = True
            for st in self._pending:
                self._state(st)
            self._pending.clear()


def _check_radio(a: argparse.Namespace, out: Lines, *, why: str | None = None) -> bool:
    """The radio guard (before the bridge opens the port, or on a port it lent); True when
    it found the radio off the swarm's settings and put it back. Raises RadioError for a
    radio that differs (without --restore-radio) or does not answer, and ConfigError for
    bad expected parameters. The start check (``why`` None) sets ``a.radio_guard``, every
    register the later checks keep, and ``a.radio_known``; a re-check (``why``:
    ``period`` or ``isolated``) compares them all and says so in one line even when the
    radio is as expected."""
    guard = getattr(a, "radio_guard", None)
    expected = guard if guard is not None else parse_expected(a.radio_params)
    report = check_radio(a.radio, expected, restore=a.restore_radio, known=getattr(a, "radio_known", None))
    if guard is None:
        a.radio_guard = baseline(expected, report.values)
        a.radio_known = known_of(report.flavour, report.values)

    def say(obj: dict[str, Any], text: str) -> None:
        fields = {} if why is None else {"why": why}
        out.line({**obj, "name": a.name, "id": a.id, "radio": a.radio, **fields}, f"agent {a.name}: {text}")

    if not report.mismatches:
        if why is not None:
            after = (
                f"after {a.radio_recheck:g} s without hearing another agent"
                if why == "isolated"
                else f"(every {a.radio_check_period:g} s)"
            )
            say(
                {"event": "radio-checked", "registers": len(expected)},
                f"radio {a.radio} checked {after}: as expected",
            )
        return False
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
    return True


def check_arguments(a: argparse.Namespace) -> None:
    """What argparse cannot check. Raises UsageError; sets ``a.round_s``."""
    if not 1 <= a.id <= 250:
        raise UsageError(f"--id {a.id}: agent ids are 1..250 (255 is the ground station)")
    try:
        check_cap(a.swarm_cap)
    except ValueError:
        raise UsageError(f"--swarm-cap {a.swarm_cap}: 0 (no cap) or 2..{MAX_CAP} agents") from None
    if a.swarm_name is not None and not NAME_RE.match(a.swarm_name):
        raise UsageError(f"--swarm-name {a.swarm_name!r}: 1 to 16 letters, digits, '_' or '-'")
    a.node = node_options(a, "an agent")
    unsafe = None if a.key is None else secret_file_problem(a.key, KEY)
    if unsafe is not None:  # the swarm's key, readable by others (docs/security.md)
        raise UsageError(f"--key {unsafe}")
    a.fence = fence_from(a)
    if a.round_s is None:
        if not 2 <= a.slots <= 32:
            raise UsageError("--slots: 2..32")
        try:
            a.round_s = default_round_s(a.slots, a.air_speed)
        except ValueError as exc:
            raise UsageError(f"--air-speed: {exc}") from None
    if (a.restore_radio or a.radio_recheck or a.radio_check_period) and not a.radio_params:
        raise UsageError("--restore-radio, --radio-recheck and --radio-check-period need --radio-params")
    for flag, value in (("--radio-recheck", a.radio_recheck), ("--radio-check-period", a.radio_check_period)):
        if not (math.isfinite(value) and value >= 0):
            raise UsageError(f"{flag} {value}: seconds, 0 for off")
    if 0 < a.radio_check_period < MIN_CHECK_PERIOD_S:
        raise UsageError(
            f"--radio-check-period {a.radio_check_period:g}: at least {MIN_CHECK_PERIOD_S:g} s "
            "(each check pauses the link about 2.3 s)"
        )
    if a.radio_params and a.radio is None:
        raise UsageError("--radio-params checks a radio: give --radio")


def check_state_files(a: argparse.Namespace) -> None:
    """With --key on a radio: the signing clock's file in the state folder, in the node
    options (swarm.cli.state_dir; made if missing: not by swarm doctor, which only looks).
    Raises UsageError for a --state-dir that cannot be used."""
    if a.key is not None and a.node.on_radio:
        folder = open_state_dir(a.state_dir, PROG)
        if folder is not None:
            a.node = replace(a.node, signing_state=node_file(folder, "agent", a.name, a.id, "signing"))


def make_agent(a: argparse.Namespace, out: Lines) -> Agent:
    """The agent the arguments describe (not started), with its flight log open. Raises
    UsageError, or ConfigError for the flight log's folder."""
    flight_log = _flight_log(a, out)
    try:
        formation = FormationConfig(
            back_m=a.back, side_m=a.side, stagger_m=a.stagger, min_separation_m=a.min_separation
        )
        pilot = PilotConfig(
            speed_mps=a.speed, turn_radius_m=a.turn_radius, formation=formation, fence=a.fence
        )
        config = AgentConfig(
            profile=a.profile,
            round_s=a.round_s,
            vote=a.vote,
            pose_hz=a.pose_hz,
            pilot=pilot,
            swarm_cap=a.swarm_cap,
            swarm_name=a.swarm_name or "",
        )
        return Agent(
            a.name,
            a.id,
            a.node,
            fc=a.fc,
            config=config,
            on_state=out.state,
            on_event=out.pilot,
            flight_log=flight_log,
        )
    except (MessageError, ValueError) as exc:
        if flight_log is not None:
            flight_log.close()
        raise UsageError(str(exc)) from None


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = read_arguments(build_parser(), argv)
    with file_errors(a):
        check_arguments(a)
        check_state_files(a)
    out = Lines(a)
    if a.radio_params:
        _check_radio(a, out)
    agent = make_agent(a, out)
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run(a, agent, StopFlag().install(), out)
    finally:
        for sig, handler in previous.items():  # main() may run inside another program
            signal.signal(sig, handler)


def _isolated(agent: Agent) -> bool:
    """The agent is alone: in its pool, following no one else."""
    st = agent.state()
    if st is None:
        return True
    others = (st.pool | st.members) - {agent.id}
    return not others and st.leader in (0, agent.id)


class _Isolation:
    """Whether the agent hears no other agent, looked at every half second: alone
    (:func:`_isolated`) and nothing from another node came off its radio since the last
    look. An agent alone that still hears the others (expelled while a flood kept its
    own frames from getting out) has a radio that works: a check would only take it
    away, every few seconds for as long as the flood lasted (the fault bench's 1 MiB
    flood: a failed check every 5 s)."""

    def __init__(self, agent: Agent) -> None:
        self.agent = agent
        self.heard = self._published()

    def _published(self) -> int:
        bridge = self.agent.bridge
        return bridge.stats.published if bridge is not None else 0

    def __call__(self) -> bool:
        n, before = self._published(), self.heard
        self.heard = n
        return _isolated(self.agent) and n == before


def _recheck_radio(a: argparse.Namespace, agent: Agent, out: Lines, why: str) -> None:
    """Check (and restore) the radio of a running agent: the bridge lends the port. A
    radio found off the swarm's settings and put back had cut the agent off: it is told
    (:meth:`Agent.radio_restored`)."""
    try:
        if agent.bridge.lend_radio(lambda: _check_radio(a, out, why=why), why="radio check"):
            agent.radio_restored()
    except RadioError as exc:  # silent, different, refused: say so, keep flying, retry later
        out.line(
            {
                "event": "radio-check-failed",
                "name": a.name,
                "id": a.id,
                "radio": a.radio,
                "why": why,
                "error": str(exc),
            },
            f"agent {a.name}: radio check failed: {exc}",
        )


def _start(agent: Agent) -> int | None:
    """Start the agent; None on success, else the exit code (message printed). The
    guard reports the radio's and Zenoh's errors; the flight controller's are named."""
    try:
        agent.start()
    except BridgeError as exc:
        print(f"{PROG}: error: flight controller: {exc}", file=sys.stderr)
        return exit_code(exc)
    return None


def _run(a: argparse.Namespace, agent: Agent, stop: StopFlag, out: Lines) -> int:
    failed = _start(agent)
    if failed is not None:
        return failed
    if agent.bridge is not None:
        if a.exit_on_radio_loss:  # the bridge gives up instead of reopening: main exits 1
            agent.bridge.cfg.reopen_radio = False
        agent.bridge.add_listener(out.radio)
    # the first periodic check at a random point of the second period: agents started
    # together do not all pause their radios at once (the network would fall silent)
    first = a.radio_check_period * (1.0 + random.random())
    checks = CheckSchedule(a.radio_check_period, a.radio_recheck, time.monotonic(), first)
    isolated = _Isolation(agent)
    # systemd's READY and WATCHDOG (docs/deployment.md, "Run as a service")
    service = Service(agent.loop_beats)
    try:
        out.open(agent)
        service.ready(f"agent {a.name} id={a.id} {agent.describe()} ready")
        check_peer = peer_watch(PROG, a, agent)
        while not stop.wait(0.5):
            check_peer()
            why = checks.due(isolated(), time.monotonic()) if checks.active else None
            if why is not None and agent.bridge is not None:
                _recheck_radio(a, agent, out, why)
                checks.checked(time.monotonic())
                continue
            if not agent.running:
                return exit_when_stopped(PROG, agent, "the agent's protocol thread")
    finally:
        service.stopping()
        agent.stop()
    return stop.exit_code()
