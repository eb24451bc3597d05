"""Probe of the SiK radio: its banner and parameters, read in AT command mode.

Theory of operation
-------------------
:func:`radio_facts` opens the radio's serial device at the baud rate the agent would
use (its ``--radio`` URL, parsed as the radio guard parses it), enters command mode
(1 s of silence, ``+++``, 1 s of silence: the radio's link pauses for about 3 s),
reads ``ATI`` and ``ATI5``, asks the other radios for their banner (``RTI``: every
radio in range on the same network answers it over the air, multipoint ones with
their ``[node id]``; nobody answering within 2 s is a fact too) and leaves with
``ATO``, writing nothing to any radio.
Whatever the radio prints is parsed by the SiK configurator, which keeps only
``S<n>:NAME=<digits>`` lines. A radio that does not answer, answers garbage or goes
away yields facts with ``answered=False`` and the reason; the port is always closed.
Call it only on a device no one else holds (:func:`~swarm.runtime.doctor.host.device_facts`):
``+++`` in the middle of a running agent's traffic would cost it 3 s of link.
"""

from __future__ import annotations

from radios.errors import ATTimeoutError, RadioError
from radios.sik.config import SikConfigurator, open_port
from swarm.core.doctor.radio import RadioFacts

MAX_PEER_LINES = 64  # reply lines kept from the other radios (each sends at most 252 bytes)


def _peers(conf: SikConfigurator) -> tuple[str, ...]:
    """The other radios' answers to ``RTI`` (their banners; multipoint: ``[id] ...``)."""
    try:
        return tuple(conf.command("RTI")[:MAX_PEER_LINES])
    except ATTimeoutError:  # nobody answered within 2 s
        return ()


def radio_facts(device: str, baud: int) -> RadioFacts:
    """Banner and parameters of the radio on ``device`` at ``baud`` (never raises for
    what the radio does)."""
    try:
        port = open_port(device, baud)
    except RadioError as exc:
        return RadioFacts(device, baud, answered=False, error=str(exc))
    conf = SikConfigurator(port, port_name=device)
    try:
        conf.enter_command_mode()
        banner = conf.version()
        conf.flavour = "multipoint" if banner.startswith("MP ") else "standard"
        params = conf.read_params()
        peers = _peers(conf)
        conf.exit_command_mode()
        return RadioFacts(device, baud, answered=True, banner=banner, params=params, peers=peers)
    except RadioError as exc:
        return RadioFacts(device, baud, answered=False, error=str(exc))
    finally:
        if conf.in_command_mode:  # leave the radio in data mode whatever happened
            try:
                conf.exit_command_mode()
            except RadioError:
                pass
        port.close()


__all__ = ["radio_facts"]
