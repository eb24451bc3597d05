"""Probe of the SiK radio: its banner and parameters, read in AT command mode.

Theory of operation
-------------------
:func:`radio_facts` opens the radio's serial device at the baud rate the agent would
use (its ``--radio`` URL, parsed as the radio guard parses it), enters command mode
(1 s of silence, ``+++``, 1 s of silence: the radio's link pauses for about 3 s),
reads ``ATI`` and ``ATI5``, asks the other radios for their banner and leaves with
``ATO``, writing nothing to any radio. ``RTI`` is answered over the air by every
radio in range on the same network (multipoint ones with their ``[node id]``); the
first answer is awaited for three TDM rounds of this radio's network
(:func:`rti_wait`), and answers are collected until 1 s passes without one, so in a
large multipoint network a node whose slot comes later may be missed. Nobody
answering is a fact too.

Whatever the radio prints is parsed by the SiK configurator, which keeps only
``S<n>:NAME=<digits>`` lines. A radio that does not answer, answers garbage or goes
away yields facts with ``answered=False`` and the reason; the port is always closed.
A radio silent at the agent's rate is tried at the SiK default (57600) and 115200
(:data:`SCAN_BAUDS`; about 5 s each when silent there too): a radio at another serial
speed is the usual reason, and the rate it answers at is the fix. Call it only on a
device no one else holds (:func:`~swarm.runtime.doctor.host.device_facts`): ``+++``
in the middle of a running agent's traffic would cost it 3 s of link.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from radios.errors import ATTimeoutError, RadioError
from radios.sik.config import SikConfigurator, open_port
from radios.sik.timing import tdm_timing
from swarm.core.doctor.radio import RadioFacts

MAX_PEER_LINES = 64  # reply lines kept from the other radios (each sends at most 252 bytes)
RTI_WAIT_MIN, RTI_WAIT_MAX = 1.0, 10.0  # seconds for the first answer to RTI
ENTER_TIMEOUT = 2.0  # per +++ try: the radio prints OK 1 s after it
SCAN_BAUDS = (57600, 115200)  # tried on a silent radio: the SiK default, and the usual other rate


def rti_wait(params: Mapping[str, int]) -> float:
    """How long to wait for the first answer to ``RTI``: three TDM rounds of this radio's
    network (one to send it, one to answer, one spare), 1 to 10 s."""
    try:
        air = params.get("AIR_SPEED", 64)
        timing = tdm_timing(air, ecc=bool(params.get("ECC")), max_window_ms=params.get("MAX_WINDOW"))
        round_s = timing.round_s(max(2, min(params.get("NODECOUNT", 2), 64)))
    except (RadioError, ValueError, ArithmeticError):  # parameters no firmware boots with
        return RTI_WAIT_MAX
    return min(RTI_WAIT_MAX, max(RTI_WAIT_MIN, 3 * round_s))


def _peers(conf: SikConfigurator, params: Mapping[str, int]) -> tuple[str, ...]:
    """The other radios' answers to ``RTI`` (their banners; multipoint: ``[id] ...``)."""
    try:
        return tuple(conf.command("RTI", timeout=rti_wait(params))[:MAX_PEER_LINES])
    except ATTimeoutError:  # nobody answered in time
        return ()


def _leave(conf: SikConfigurator) -> None:
    """Back to data mode, if the radio is (or may be) in command mode; never raises."""
    if conf.in_command_mode:
        try:
            conf.exit_command_mode()
        except RadioError:
            pass


def _answers_at(device: str, baud: int) -> bool:
    """Does a radio on ``device`` answer ``+++`` at ``baud``? (Left in data mode.)"""
    try:
        port = open_port(device, baud)
    except RadioError:
        return False
    conf = SikConfigurator(port, port_name=device)
    try:
        conf.enter_command_mode(timeout=ENTER_TIMEOUT)
        return True
    except RadioError:
        return False
    finally:
        _leave(conf)
        port.close()


def radio_facts(device: str, baud: int, *, scan: Sequence[int] = SCAN_BAUDS) -> RadioFacts:
    """Banner and parameters of the radio on ``device`` at ``baud`` (never raises for
    what the radio does). A radio silent at ``baud`` is tried at each of ``scan``."""
    try:
        port = open_port(device, baud)
    except RadioError as exc:
        return RadioFacts(device, baud, answered=False, error=str(exc))
    conf = SikConfigurator(port, port_name=device)
    try:
        try:
            conf.enter_command_mode(timeout=ENTER_TIMEOUT)
        except ATTimeoutError as exc:
            port.close()
            found = next((b for b in scan if b != baud and _answers_at(device, b)), None)
            return RadioFacts(device, baud, answered=False, error=str(exc), found_baud=found)
        banner = conf.version()
        conf.flavour = "multipoint" if banner.startswith("MP ") else "standard"
        params = conf.read_params()
        peers = _peers(conf, params)
        conf.exit_command_mode()
        return RadioFacts(device, baud, answered=True, banner=banner, params=params, peers=peers)
    except RadioError as exc:
        return RadioFacts(device, baud, answered=False, error=str(exc))
    except ValueError as exc:  # a number of thousands of digits in ATI5: not a SiK radio's answer
        return RadioFacts(device, baud, answered=False, error=f"its answer does not parse: {exc}")
    finally:
        _leave(conf)  # whatever happened
        port.close()


__all__ = ["radio_facts"]
