"""``swarm doctor``: the pre-flight check of a field set-up, one line per check.

It takes exactly the flags of ``swarm agent`` (``--name`` and ``--id`` optional),
so the doctor checks the set-up the agent will run with: run it with the agent's
command line, before the agent starts. Each line is ``PASS``, ``INFO``, ``WARN`` or
``FAIL``, a name, what was seen and, unless it passed, the fix::

    PASS radio NETID 25 (expected 25)
    FAIL key mode /etc/uav-swarm/swarm.key: mode 0644: readable by others; fix: chmod 600 ...

Checked: the radio's serial device (present, openable by this user, held by no
other program), the radio in AT command mode (answers; ``--radio-params`` agree;
SERIAL_SPEED is the baud rate of ``--radio``; MAVLink framing; ECC; multipoint
NODEID and NODECOUNT; the other radios' answers to ``RTI``), the flight controller
(answers within 5 s; autopilot, firmware, vehicle type, armed, GPS fix, home or EKF
origin, serial rate), the key
file (present, mode 0600, 32 bytes), the clock (plausible for MAVLink signing), the
Zenoh endpoints (well formed; listen endpoints free), their TLS files (the CA; the
certificate: signed by that CA, this agent's name and role, not expired nor within 30
days of it; the key: mode 0600, the certificate's) and access-control file and, when
the agent captures, the disk. ``--json`` prints one object ``{"ok": bool, "checks": [{"status", "name",
"seen", "fix"}...]}`` instead. Exit 0 when nothing fails (warnings allowed), 1 when
a check fails, 2 for bad arguments (what ``swarm agent`` would refuse to start with).

Reading the radio pauses its link for about 3 s (``+++``): a device that another
program holds open (a running agent) is reported and not touched.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from radios.sik.guard import parse_expected
from swarm.cli.commands import agent
from swarm.cli.configfile import file_errors, read_arguments
from swarm.cli.util import guarded, print_json
from swarm.core.doctor import exit_code, report_json, summary, text_line
from swarm.core.doctor.radio import RadioPlan
from swarm.runtime.doctor import Setup, examine

PROG = "swarm doctor"


def build_parser() -> argparse.ArgumentParser:
    """The agent's parser, with --name and --id optional and --json meaning one report."""
    p = agent.build_parser()
    p.prog = PROG
    p.config_example = "agent"  # type: ignore[attr-defined]  # doctor reads an agent's config file
    p.description = (
        "Pre-flight check of a field set-up: give it the agent's flags. One line per "
        "check (PASS, INFO, WARN, FAIL) with the fix; exit 0 when nothing fails."
    )
    for action in p._actions:  # noqa: SLF001 (argparse keeps its actions private)
        if action.dest in ("name", "id"):
            action.required = False
        elif action.dest == "json":
            action.help = (
                'one JSON object {"ok", "checks": [{"status", "name", "seen", "fix"}]} instead of lines'
            )
    return p


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The agent's flags, checked as the agent checks them (UsageError or ConfigError:
    exit 2). Sets ``a.node``, ``a.round_s``, ``a.expected`` (parsed --radio-params or
    None) and ``a.plan``."""
    a = read_arguments(build_parser(), argv)  # --config FILE: the agent's config file
    round_given = a.round_s is not None
    probe = argparse.Namespace(**{**vars(a), "id": 1 if a.id is None else a.id, "name": a.name or "doctor"})
    # the agent would open (and create) its flight log folder: the doctor only looks at it
    probe.capture = None
    for flag in agent.CAPTURE_FLAGS:
        setattr(probe, flag[2:].replace("-", "_"), None)
    with file_errors(a):
        agent.check_arguments(probe)  # raises UsageError for what the agent refuses
        agent.make_agent(probe, agent.Lines(probe))  # builds (opens nothing): refuses what the agent would
    a.node, a.round_s, a.zenoh_warnings = probe.node, probe.round_s, probe.zenoh_warnings
    a.expected = parse_expected(a.radio_params) if a.radio_params else None
    fast = a.profile != "paper" and not round_given  # the round comes from --slots and --air-speed
    a.plan = RadioPlan(
        expected=a.expected,
        slots=a.slots if fast else None,
        air_speed=a.air_speed if fast else None,
    )
    return a


def _setup(a: argparse.Namespace) -> Setup:
    return Setup(
        radio=a.radio,
        fc=a.fc,
        key=a.key,
        zenoh_listen=tuple(a.zenoh_listen),
        zenoh_connect=tuple(a.zenoh_connect),
        capture=getattr(a, "capture", None),  # the agent's --capture DIR, when it has one
        plan=a.plan,
        # without --name the certificate's own name is not judged
        tls=a.node.tls if a.node.tls is None or a.name else dataclasses.replace(a.node.tls, name=""),
        acl=a.node.acl_file,
        zenoh_warnings=tuple(a.zenoh_warnings),
    )


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    checks = examine(_setup(a), now=time.time())
    if a.json:
        print_json(report_json(checks))
    else:
        for c in checks:
            print(text_line(c), flush=True)
        print(summary(checks), flush=True)
    return exit_code(checks)
