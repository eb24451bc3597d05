"""Probe of the SiK radio: its banner and parameters, read in AT command mode.

Theory of operation
-------------------
:func:`radio_facts` opens the radio's serial device at the baud rate the agent would
use (its ``--radio`` URL, parsed as the radio guard parses it), enters command mode
(1 s of silence, ``+++``, 1 s of silence: the radio's link pauses for about 3 s),
reads ``ATI`` and ``ATI5`` and leaves with ``ATO``, writing nothing to the radio.
Whatever the radio prints is parsed by the SiK configurator, which keeps only
``S<n>:NAME=<digits>`` lines. A radio that does not answer, answers garbage or goes
away yields facts with ``answered=False`` and the reason; the port is always closed.
Call it only on a device no one else holds (:func:`~swarm.runtime.doctor.host.device_facts`):
``+++`` in the middle of a running agent's traffic would cost it 3 s of link.
"""

from __future__ import annotations

from radios.errors import RadioError
from radios.sik.config import SikConfigurator, open_port
from swarm.core.doctor.radio import RadioFacts


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
        conf.exit_command_mode()
        return RadioFacts(device, baud, answered=True, banner=banner, params=params)
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
