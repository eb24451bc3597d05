"""Opt-in tests against a real SiK radio: `SIK_PORT=/dev/ttyUSB0 pytest -m hardware`.
Deselected by default (no radio on CI); they fail, not skip, when selected without a port."""

from __future__ import annotations

import os

import pytest

from radios.sik.config import SikConfigurator, open_port


@pytest.mark.hardware
def test_real_radio_answers_at_commands() -> None:
    port_path = os.environ.get("SIK_PORT")
    assert port_path, "set SIK_PORT to the radio's serial device to run hardware tests"
    port = open_port(port_path, int(os.environ.get("SIK_BAUD", "57600")))
    try:
        cfg = SikConfigurator(port, port_name=port_path)
        cfg.enter_command_mode()
        assert "SiK" in cfg.version()
        params = cfg.read_params()
        assert {"NETID", "AIR_SPEED", "SERIAL_SPEED"} <= set(params)
        cfg.exit_command_mode()
    finally:
        port.close()
