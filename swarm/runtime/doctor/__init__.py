"""The pre-flight check of a field set-up: run the probes, hand their facts to the verdicts.

Theory of operation
-------------------
:class:`Setup` is what an agent is configured with, as far as the check is concerned
(its radio URL, flight controller, key file, Zenoh endpoints, capture directory and
what its radio must agree with). :func:`examine` turns it into the checklist, in a
fixed order: the radio (its device, then what it says in AT command mode), the
flight controller (its device if serial, then its MAVLink answers), the key file,
the clock, the Zenoh endpoints (and their TLS files and access control) and the
capture disk. The two slow probes, the radio's
(about 3 s of AT command mode) and the flight controller's (up to 5 s for its
heartbeat, 2.5 s for the messages asked for), run at the same time on two threads;
the rest is quick. The verdicts are the pure functions of :mod:`swarm.core.doctor`;
``now`` (the wall clock) is passed in, so a test can check a clock in 1970.

A device someone else holds (a running agent) is not probed: ``+++`` in its traffic
would pause its radio for 3 s.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from firmware_bridge.connection import parse_url
from firmware_bridge.errors import BridgeError
from radios.errors import ConfigError
from radios.sik.guard import split_radio_url
from swarm.core.doctor import Check, fail, info, warn
from swarm.core.doctor.host import (
    clock_check,
    device_check,
    disk_check,
    key_checks,
    same_device_check,
    zenoh_check,
)
from swarm.core.doctor.radio import RadioFacts, RadioPlan, radio_checks
from swarm.core.doctor.tls import acl_check, tls_checks
from swarm.core.doctor.vehicle import VehicleFacts, vehicle_checks
from swarm.core.keyspace.endpoints import CERTS_HINT
from swarm.runtime.doctor.host import device_facts, disk_facts, key_facts, zenoh_facts
from swarm.runtime.doctor.radio import radio_facts
from swarm.runtime.doctor.vehicle import HEARTBEAT_S, vehicle_facts
from swarm.runtime.keyspace.tls_probe import acl_facts, tls_facts

if TYPE_CHECKING:
    from swarm.runtime.options import TlsFiles


@dataclass(frozen=True)
class Setup:
    """An agent's configuration as the check sees it (see the module docstring).
    ``fc_timeout``: how long the flight controller has to send its heartbeat."""

    radio: str | None = None
    fc: str | None = None
    key: str | None = None
    zenoh_listen: Sequence[str] = ()
    zenoh_connect: Sequence[str] = ()
    capture: str | None = None
    plan: RadioPlan = field(default_factory=RadioPlan)
    fc_timeout: float = HEARTBEAT_S
    tls: TlsFiles | None = None  # --tls-ca/--tls-cert/--tls-key, with the name and role expected
    acl: str | None = None  # --zenoh-acl
    zenoh_warnings: Sequence[
        str
    ] = ()  # what the agent would warn of its Zenoh (swarm.core.keyspace.endpoints)


def _radio_device(setup: Setup, out: list[Check]) -> tuple[str, int] | None:
    """The radio's serial device and baud rate, or None (a line says why)."""
    if setup.radio is None:
        out.append(info("radio", "none: the agent meets the others over Zenoh"))
        return None
    try:
        return split_radio_url(setup.radio)
    except ConfigError as exc:
        out.append(warn("radio", f"{exc}: not checked", "give the radio's serial device in --radio"))
        return None


def _fc_device(setup: Setup, out: list[Check]) -> str | None:
    """The flight controller's serial device, or None (not serial, none, or malformed)."""
    if setup.fc is None:
        out.append(info("fc", "none: --fc not given, the agent flies no vehicle"))
        return None
    try:
        ep = parse_url(setup.fc)
    except BridgeError as exc:
        out.append(fail("fc", str(exc), "write it as udpin:HOST:PORT, tcp:HOST:PORT or /dev/DEVICE:BAUD"))
        return None
    return ep.device if ep.scheme == "serial" else None


def examine(setup: Setup, *, now: float) -> list[Check]:
    """The whole checklist for ``setup``; ``now``: the wall clock (Unix seconds)."""
    radio_out: list[Check] = []
    fc_out: list[Check] = []
    radio = _radio_device(setup, radio_out)
    fc_dev = _fc_device(setup, fc_out)
    probe_fc = setup.fc is not None and not fc_out  # a network link: nothing to open first
    if radio is not None and fc_dev is not None:
        same = same_device_check(os.path.realpath(radio[0]), os.path.realpath(fc_dev))
        if same is not None:
            radio_out.append(same)
            radio, fc_dev, probe_fc = None, None, False
    if radio is not None:
        dev = device_check(device_facts(radio[0], "radio"))
        radio_out.append(dev)
        radio = radio if dev.status == "pass" else None
    if fc_dev is not None:
        dev = device_check(device_facts(fc_dev, "fc"))
        fc_out.append(dev)
        probe_fc = dev.status == "pass"
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="doctor") as pool:
        radio_job: Future[RadioFacts] | None = None
        fc_job: Future[VehicleFacts] | None = None
        if radio is not None:
            radio_job = pool.submit(radio_facts, *radio)
        if probe_fc and setup.fc is not None:
            fc_job = pool.submit(vehicle_facts, setup.fc, timeout=setup.fc_timeout)
        if radio_job is not None:
            radio_out += radio_checks(radio_job.result(), setup.plan)
        if fc_job is not None:
            fc_out += vehicle_checks(fc_job.result())
    return radio_out + fc_out + _host_checks(setup, now)


def _host_checks(setup: Setup, now: float) -> list[Check]:
    out = key_checks(
        key_facts(setup.key) if setup.key is not None else None, on_radio=setup.radio is not None
    )
    out.append(clock_check(now))
    out += [zenoh_check(zenoh_facts(ep, "listen")) for ep in setup.zenoh_listen]
    out += [zenoh_check(zenoh_facts(ep, "connect")) for ep in setup.zenoh_connect]
    if setup.tls is not None:
        t = setup.tls
        out += tls_checks(tls_facts(t.ca, t.cert, t.key, expect_name=t.name, expect_role=t.role), now)
    if setup.acl is not None:
        out.append(acl_check(acl_facts(setup.acl)))
    out += [warn("zenoh", text.removeprefix("warning: "), CERTS_HINT) for text in setup.zenoh_warnings]
    if setup.capture is not None:
        out.append(disk_check(disk_facts(setup.capture)))
    return out


__all__ = ["Setup", "examine"]
