"""Verdicts on a SiK radio: does it answer, and do its parameters suit the swarm?

Theory of operation
-------------------
The probe enters AT command mode, reads the banner (``ATI``) and every parameter
(``ATI5``) and leaves; :class:`RadioFacts` holds what it saw, with the baud rate the
agent opens the radio at (its ``--radio`` URL) and, from the agent's options, what
the radio must agree with. :func:`radio_checks` judges:

* **answers**: no answer to ``+++`` fails (wrong baud rate, port held, not a SiK radio);
  when the probe found the rate the radio does answer at, the fix names it.
* **expected parameters** (the agent's ``--radio-params``): each one passes or fails
  by name (``radio NETID 77 (expected 25)``).
* **always checkable**, expected or not: SERIAL_SPEED is the baud rate the agent opens
  the port at (else every byte is garbled: on real hardware the radio would not even
  answer); MAVLINK framing is on (1 or 2: whole frames per air packet and the
  RADIO_STATUS the bridge's flow control needs); ECC=1 warns (stock SiK builds
  compile the Golay code out, so ECC=1 drops the CRC and NETID filter with nothing in
  their place); on multipoint firmware NODEID < NODECOUNT; with the ``fast`` profile
  the TDM round the agent computes (``--slots``, ``--air-speed``) must match
  NODECOUNT and AIR_SPEED.
* **the other radios** (their answers to ``RTI``, when the probe asked): one answering
  with this radio's NODEID fails (two radios in one slot); others answering pass, or
  warn when they run another firmware than this one (both ends must match); nobody
  answering is reported (the others may be off), as is a NODEID no one else was seen
  to have.
* without expected parameters the radio's main values are reported as ``info``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field

from swarm.core.doctor import Check, fail, info, passed, warn

#: SiK SERIAL_SPEED code -> baud rate (the firmware's table)
SERIAL_BAUD = {1: 1200, 2: 2400, 4: 4800, 9: 9600, 19: 19200, 38: 38400, 57: 57600, 115: 115200, 230: 230400}
SIK_DEFAULT_BAUD = 57600
_NODE = re.compile(r"^(?:\[\d+\]\s*)+")  # multipoint prefixes of an RT reply: "[2] [2] MP SiK..."
_FIRST_NODE = re.compile(r"^\[([0-9]{1,5})\]")  # the node that answered (16 bits)
#: what the doctor reports of a radio given no expected parameters
SHOWN = ("NETID", "AIR_SPEED", "SERIAL_SPEED", "ECC", "MAVLINK", "TXPOWER", "NUM_CHANNELS", "MAX_WINDOW")


@dataclass(frozen=True)
class RadioFacts:
    """What the radio probe saw. ``device``: the serial device; ``baud``: the rate the
    agent opens it at; ``error``: why it did not answer (empty when it did)."""

    device: str
    baud: int
    answered: bool
    error: str = ""
    banner: str = ""
    params: Mapping[str, int] = field(default_factory=dict)
    peers: tuple[str, ...] | None = None  # the other radios' answers to RTI; None: not asked
    found_baud: int | None = None  # silent at ``baud``, the radio answered +++ at this rate


@dataclass(frozen=True)
class RadioPlan:
    """What the radio must agree with, from the agent's options: ``expected``
    (``--radio-params``, or None), and for the ``fast`` profile with a computed round
    the ``slots`` and ``air_speed`` it is computed from (else None)."""

    expected: Mapping[str, int] | None = None
    slots: int | None = None
    air_speed: int | None = None


def _set(device: str, baud: int, name: str, value: int) -> str:
    """The command that sets one parameter (the radio answered at ``baud``)."""
    at = f" --baud {baud}" if baud != SIK_DEFAULT_BAUD else ""
    return f"swarm radio-config {device}{at} --set {name}={value}"


def radio_checks(f: RadioFacts, plan: RadioPlan) -> list[Check]:
    """Every check of one radio (see the module docstring)."""
    if not f.answered:
        return [_silent(f)]
    out = [info("radio firmware", f"{f.banner or '?'} on {f.device}")]
    p = f.params
    if plan.expected is not None:
        out += [_expected(f, name, want) for name, want in plan.expected.items()]
    else:
        shown = " ".join(f"{n}={p[n]}" for n in SHOWN if n in p)
        out.append(
            info(
                "radio parameters",
                shown or "none read",
                "give the agent --radio-params NETID=..,AIR_SPEED=.. so that these are checked",
            )
        )
    out.append(_baud(f))
    if plan.expected is None or "MAVLINK" not in plan.expected:
        out.append(_framing(f, p.get("MAVLINK")))
    if p.get("ECC") == 1:
        out.append(
            warn(
                "radio ECC",
                "ECC=1: stock SiK builds have no Golay code, so ECC=1 drops the CRC and the "
                "NETID filter (corrupt and foreign packets get through)",
                "set ECC=0 on every radio of the swarm: " + _set(f.device, f.baud, "ECC", 0),
            )
        )
    if "NODEID" in p:
        out += _multipoint(f, p)
    out += _peer_checks(f)
    out += _round(p, plan)
    return out


def _silent(f: RadioFacts) -> Check:
    seen = f.error if f.device in f.error else f"{f.device} at {f.baud} baud: {f.error}"
    if f.found_baud is not None:
        code = {b: c for c, b in SERIAL_BAUD.items()}.get(f.baud)
        also = f", or {_set(f.device, f.found_baud, 'SERIAL_SPEED', code)}" if code is not None else ""
        return fail(
            "radio",
            f"{seen}; the radio answers at {f.found_baud} baud",
            f"give the agent --radio {f.device}?baud={f.found_baud}{also}",
        )
    hint = (
        f"check that the radio runs SERIAL_SPEED for {f.baud} baud (the SiK default is "
        f"{SIK_DEFAULT_BAUD}: try swarm radio-config {f.device} --baud {SIK_DEFAULT_BAUD} --show), "
        "that no other program holds the port, and that it is a SiK radio"
    )
    return fail("radio", seen, hint)


def _expected(f: RadioFacts, name: str, want: int) -> Check:
    what, got = f"radio {name}", f.params.get(name)
    if got == want:
        return passed(what, f"{got} (expected {want})")
    if got is None:
        return fail(what, f"missing (expected {want})", "this radio's firmware has no such parameter")
    fix = _set(f.device, f.baud, name, want) + " (or start the agent with --restore-radio)"
    return fail(what, f"{got} (expected {want})", fix)


def _baud(f: RadioFacts) -> Check:
    code = f.params.get("SERIAL_SPEED")
    if code is None:
        return warn(
            "radio baud", "the radio did not report SERIAL_SPEED", "read it: swarm radio-config --show"
        )
    rate = SERIAL_BAUD.get(code)
    if rate == f.baud:
        return passed("radio baud", f"SERIAL_SPEED {code} = {rate} baud, as the agent opens it")
    shown = f"{rate} baud" if rate is not None else "no valid rate"
    fix = f"give the agent --radio {f.device}?baud={rate}" if rate is not None else ""
    code_for = {b: c for c, b in SERIAL_BAUD.items()}.get(f.baud)
    if code_for is not None:
        fix = (fix + ", or " if fix else "") + _set(f.device, f.baud, "SERIAL_SPEED", code_for)
    return fail(
        "radio baud",
        f"SERIAL_SPEED {code} = {shown}, but the agent opens the radio at {f.baud} baud",
        fix or "set a valid SERIAL_SPEED",
    )


def _framing(f: RadioFacts, mavlink: int | None) -> Check:
    if mavlink in (1, 2):
        return passed("radio MAVLINK", f"{mavlink}: MAVLink framing on (whole frames, RADIO_STATUS)")
    seen = "not reported" if mavlink is None else f"{mavlink}: raw framing"
    return fail(
        "radio MAVLINK",
        f"{seen}: frames split across air packets and no RADIO_STATUS for flow control",
        _set(f.device, f.baud, "MAVLINK", 1),
    )


def _multipoint(f: RadioFacts, p: Mapping[str, int]) -> list[Check]:
    node, count = p["NODEID"], p.get("NODECOUNT")
    if count is None or not node < count:
        return [
            fail(
                "radio NODEID",
                f"NODEID {node} with NODECOUNT {count}: a node id must be below NODECOUNT",
                _set(f.device, f.baud, "NODECOUNT", node + 1) + " on every radio",
            )
        ]
    out = [passed("radio NODEID", f"NODEID {node} < NODECOUNT {count}")]
    ids = sorted({int(m.group(1)) for line in f.peers or () if (m := _FIRST_NODE.match(line))})
    base = " (the base, which keeps the sync)" if node == 0 else ""
    if node in ids:
        out.append(
            fail(
                "radio NODEID unique",
                f"another radio answers RTI as node {node}, this radio's NODEID",
                "give every radio of the swarm its own NODEID (0 for one of them): "
                + _set(f.device, f.baud, "NODEID", max([*ids, node]) + 1),
            )
        )
    elif ids:
        heard = ", ".join(map(str, ids))
        out.append(
            passed("radio NODEID unique", f"NODEID {node}{base}; nodes {heard} answered RTI, none as {node}")
        )
    else:
        out.append(
            info(
                "radio NODEID unique",
                f"NODEID {node}{base}: no other radio answered RTI, so no other id was seen",
                "power the swarm's other radios and check again, to see their ids",
            )
        )
    return out


def _peer_checks(f: RadioFacts) -> list[Check]:
    """Did another radio answer RTI, and does it run the same firmware as this one?"""
    if f.peers is None:
        return []
    banners = sorted({_NODE.sub("", line).strip() for line in f.peers} - {""})
    if not banners:
        return [
            info(
                "radio peers",
                "no other radio answered RTI in three TDM rounds",
                "if the others are on: check NETID, AIR_SPEED, frequencies and antennas on both ends",
            )
        ]
    mine = _NODE.sub("", f.banner).strip()
    other = [b for b in banners if b != mine]
    if other:
        return [
            warn(
                "radio peers",
                f"another radio runs {other[0]!r}, this one {mine!r}",
                "run the same SiK firmware version on every radio of the swarm",
            )
        ]
    return [passed("radio peers", f"{len(f.peers)} answer(s) to RTI, all {mine!r}")]


def _round(p: Mapping[str, int], plan: RadioPlan) -> list[Check]:
    """The fast profile's round is computed from --slots and --air-speed: do they match?"""
    out: list[Check] = []
    count = p.get("NODECOUNT")
    if plan.slots is not None and count is not None and count != plan.slots:
        out.append(
            warn(
                "radio NODECOUNT",
                f"{count}, but the agent computes its TDM round for --slots {plan.slots}",
                f"give the agent --slots {count}, or set NODECOUNT={plan.slots} on every radio",
            )
        )
    air = p.get("AIR_SPEED")
    if plan.air_speed is not None and air is not None and air != plan.air_speed:
        out.append(
            warn(
                "radio AIR_SPEED",
                f"{air}, but the agent computes its TDM round for --air-speed {plan.air_speed}",
                f"give the agent --air-speed {air}",
            )
        )
    return out


__all__ = ["SERIAL_BAUD", "RadioFacts", "RadioPlan", "radio_checks"]
