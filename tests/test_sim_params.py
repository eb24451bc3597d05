"""The simulator answers the MAVLink parameter protocol as each real autopilot does
(measured on ArduCopter 4.7 and PX4 v1.15 SITL): a standard client could not set a
parameter on it (PARAM_SET was never echoed). Pure cores on real MAVLink bytes, then
one pymavlink client over a real UDP socket against ``swarm sim``'s runner."""

from __future__ import annotations

import math
import struct
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from test_sim_flavours import POS_MASK, Pilot

from firmware_bridge.sim import SimConfig
from firmware_bridge.sim.runner import VehicleSim


def values(msgs: list[mavlink.MAVLink_message]) -> list[mavlink.MAVLink_message]:
    return [m for m in msgs if m.get_type() == "PARAM_VALUE"]


def test_px4_reads_sets_and_lists_as_px4_does() -> None:
    p = Pilot("px4")
    (v,) = values(p.send(p.cl.param_request_read_encode(1, 1, b"MPC_XY_CRUISE", -1)))
    assert (v.param_id, v.param_value, v.param_type) == ("MPC_XY_CRUISE", 5.0, 9)
    assert v.param_index not in (65535, -1) and v.param_count == len(p.ap.params)
    (v,) = values(p.send(p.cl.param_request_read_encode(1, 1, b"SYS_AUTOSTART", -1)))
    assert v.param_type == 6 and struct.unpack("<i", struct.pack("<f", v.param_value))[0] == 10040  # bytewise
    assert values(p.send(p.cl.param_request_read_encode(1, 1, b"NO_SUCH_PARAM", -1))) == []  # no answer
    (v,) = values(p.send(p.cl.param_set_encode(1, 1, b"COM_OF_LOSS_T", 3.0, 9)))
    assert (v.param_id, v.param_value) == ("COM_OF_LOSS_T", 3.0)
    assert values(p.send(p.cl.param_set_encode(1, 1, b"NO_SUCH_PARAM", 1.0, 9))) == []
    listing = values(p.send(p.cl.param_request_list_encode(1, 1)))
    assert listing[0].param_id == "_HASH_CHECK" and listing[0].param_index == 65535
    assert [m.param_index for m in listing[1:]] == list(range(len(p.ap.params)))
    # by index, with an empty name
    (v,) = values(p.send(p.cl.param_request_read_encode(1, 1, b"", 0)))
    assert v.param_id == listing[1].param_id


def test_a_set_parameter_is_what_the_simulation_flies_by() -> None:
    """PX4's COM_OF_LOSS_T set to 3 s: the offboard-loss failsafe comes after 3 s of
    silence, not the default 1 s."""
    p = Pilot("px4")
    p.send(p.cl.param_set_encode(1, 1, b"COM_OF_LOSS_T", 3.0, 9))
    assert p.command(400, 1).result == 0
    assert p.command(22, 0, 0, 0, 0, 0, 0, 488.0 + 6).result == 0
    p.run(12.0)

    def stream() -> None:
        p.send(
            p.cl.set_position_target_local_ned_encode(0, 1, 1, 1, POS_MASK, 0, 0, -6, 0, 0, 0, 0, 0, 0, 0, 0)
        )

    p.run(0.5, stream)
    assert p.command(176, 1, 6, 0).result == 0 and p.ap.mode == "OFFBOARD"
    p.run(2.0)  # silent for 2 s: still within 3 s
    assert p.ap.mode == "OFFBOARD"
    p.run(2.0)
    assert p.ap.mode != "OFFBOARD"


def test_ardupilot_reads_sets_and_lists_as_ardupilot_does() -> None:
    p = Pilot("ardupilot")
    (v,) = values(p.send(p.cl.param_request_read_encode(1, 1, b"FS_GCS_ENABLE", -1)))
    assert (v.param_value, v.param_type, v.param_index) == (0.0, 2, 65535)  # converted, no index
    (v,) = values(p.send(p.cl.param_set_encode(1, 1, b"RTL_ALT", 2500.0, 6)))
    assert (v.param_value, v.param_type, v.param_index) == (2500.0, 6, 65535)
    (v,) = values(p.send(p.cl.param_set_encode(1, 1, b"FS_GCS_ENABLE", 1000.0, 2)))  # beyond INT8
    assert v.param_value == 0.0  # left as it was, and said so
    (v,) = values(p.send(p.cl.param_set_encode(1, 1, b"GUID_TIMEOUT", math.nan, 9)))
    assert v.param_value == 3.0
    listing = values(p.send(p.cl.param_request_list_encode(1, 1)))
    assert listing[0].param_id == "FORMAT_VERSION" and listing[0].param_index == 0
    assert len(listing) == len(p.ap.params)


@pytest.mark.processes
def test_a_standard_mavlink_client_sets_a_parameter_over_udp() -> None:
    from net_helpers import free_port

    port = free_port("udp")
    sim = VehicleSim(SimConfig(profile="px4", vehicles=1, base_port=port))
    sim.start()
    client = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    try:
        assert client.wait_heartbeat(timeout=30) is not None
        deadline = time.monotonic() + 30
        got = None
        while got is None and time.monotonic() < deadline:
            client.mav.param_set_send(1, 1, b"MPC_XY_CRUISE", 7.5, 9)
            got = client.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
        assert got is not None and got.param_id == "MPC_XY_CRUISE" and got.param_value == 7.5
    finally:
        client.close()
        sim.stop()
