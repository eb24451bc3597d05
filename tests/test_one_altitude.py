"""One altitude (issue 28): every agent sends its height above its autopilot's home
beside AMSL (and the vehicle detail an operator's table shows: climb, GPS fix and
satellites, distance from home, ready to arm) in Telemetry's detail block; an earlier
agent's Telemetry without it still decodes; a hostile block is refused or read as
unknown; the station derives home's height from it, so a station started while the
agents fly shows heights above home, never AMSL in the same column; the agent's side
reads it from a real driver state (the simulator's MAVLink)."""

from __future__ import annotations

import struct

import pytest
from test_gcs_station import connect

from swarm.core.agent.node import AgentNode, VehicleInfo
from swarm.core.election.profiles import profile_by_name
from swarm.core.station.core import StationCore
from swarm.core.station.federation import clean_agent
from swarm.core.wire.codes import FLAG_AIRBORNE, FLAG_ARMED, FLAG_FC_OK, FLAG_READY, FLAG_READY_KNOWN
from swarm.core.wire.message_types import Phase, Pose, Telemetry
from swarm.core.wire.messages import decode, encode
from swarm.errors import DecodeError
from swarm.runtime.agent.vehicle import vehicle_info

POSE = Pose(47.397, 8.545, 508.0, 90.0)
FLYING = FLAG_ARMED | FLAG_AIRBORNE | FLAG_FC_OK


def tm(**detail: object) -> Telemetry:
    return Telemetry(3, POSE, 1, FLYING, Phase.MEMBER, 1, 80, 150, 140, 4.0, **detail)  # type: ignore[arg-type]


def test_the_detail_block_round_trips_in_seven_bytes() -> None:
    bare = tm()
    full = tm(rel_alt=9.8, climb=-1.25, gps_fix=3, satellites=14, home_dist=123.0)
    assert len(encode(full)) == len(encode(bare)) + 7
    assert decode(encode(full)) == full and decode(encode(bare)) == bare
    some = tm(rel_alt=9.8)  # only what it knows: the rest unknown, not zero
    assert decode(encode(some)) == some and decode(encode(some)).satellites is None


def test_values_beyond_the_block_are_clamped_and_not_finite_is_unknown() -> None:
    m = decode(encode(tm(rel_alt=9999.0, climb=-99.0, home_dist=1e9, gps_fix=12, satellites=300)))
    assert (m.rel_alt, m.climb, m.home_dist, m.gps_fix, m.satellites) == (3276.7, -31.75, 65534.0, None, None)
    m = decode(encode(tm(rel_alt=float("nan"), climb=float("inf"))))
    assert (m.rel_alt, m.climb) == (None, None)


@pytest.mark.parametrize(
    ("tail", "why"),
    [
        (b"\x00", "truncated"),
        (struct.pack("<hbBBH", 0, 0, 9, 0, 0), "GPS fix type 9"),
        (struct.pack("<hbBBH", 0, 0, 3, 0, 0) + b"\x00", "trailing"),
        (struct.pack("<hbBBH", -32768, -128, 255, 255, 65535), "knows nothing"),  # one encoding only
    ],
)
def test_a_hostile_detail_block_is_refused_with_one_line(tail: bytes, why: str) -> None:
    with pytest.raises(DecodeError) as exc:
        decode(encode(tm()) + tail)
    assert why in str(exc.value) and "\n" not in str(exc.value)


def test_the_agent_sends_its_autopilots_height_above_home_and_ready_state() -> None:
    nd = AgentNode(4, "agent4", profile_by_name("paper", 0.25), has_fc=True)
    nd.start(0.0)
    nd.handle(
        VehicleInfo(mode="OFFBOARD", armed=True, airborne=True, battery=87, rel_alt=9.8, climb=0.5, gps_fix=3,
                    satellites=12, home_dist=40.0, ready=True),
        1.0,
    )  # fmt: skip
    t = nd.telemetry()
    assert (t.rel_alt, t.climb, t.gps_fix, t.satellites, t.home_dist) == (9.8, 0.5, 3, 12, 40.0)
    assert t.flags & FLAG_READY_KNOWN and t.flags & FLAG_READY
    nd.handle(VehicleInfo(mode="OFFBOARD", armed=True, rel_alt=9.8, ready=False, link_ok=False), 2.0)
    t = nd.telemetry()  # its flight controller silent: none of it is known now
    assert (t.rel_alt, t.gps_fix, t.flags & FLAG_READY_KNOWN) == (None, None, 0)


def test_a_station_started_in_flight_shows_heights_above_home() -> None:
    core = StationCore()  # never saw the agent on the ground
    connect(core, 3, 0.0)
    core.handle(tm(), 0.5)  # an earlier agent: no detail, AMSL only
    a = core.snapshot(0.5)["agents"][0]
    assert (a["alt"], a["home_alt"], a["rel_alt"]) == (508.0, None, None)
    core.handle(tm(rel_alt=9.8, gps_fix=3, satellites=11, home_dist=55.0, climb=0.0), 1.0)
    a = core.snapshot(1.0)["agents"][0]
    assert (a["alt"], a["rel_alt"], a["home_alt"]) == (508.0, 9.8, 498.2)
    assert (a["gps_fix"], a["satellites"], a["home_dist"], a["ready"]) == (3, 11, 55, None)
    ready = Telemetry(3, POSE, 1, FLYING | FLAG_READY_KNOWN | FLAG_READY, Phase.MEMBER, 1, 80, 1, 1, 0.0)
    core.handle(ready, 1.5)
    assert core.snapshot(1.5)["agents"][0]["ready"] is True
    lost = Telemetry(3, POSE, 0, 0, Phase.MEMBER, 1, 255, 1, 1, 0.0, rel_alt=9.8)
    core.handle(lost, 2.0)  # the vehicle link lost: unknown, not the last values
    a = core.snapshot(2.0)["agents"][0]
    assert (a["rel_alt"], a["gps_fix"], a["ready"]) == (None, None, None)


def test_another_stations_agent_detail_is_rebuilt_typed() -> None:
    base = {"id": 5, "name": "a5", "rel_alt": 9.8, "gps_fix": 3, "satellites": 12, "ready": True}
    good = clean_agent(base)
    assert (good["rel_alt"], good["gps_fix"], good["satellites"], good["ready"]) == (9.8, 3, 12, True)
    hostile = {"rel_alt": "9", "gps_fix": 99, "satellites": -1, "ready": "yes", "climb": 1e400}
    evil = clean_agent({**base, **hostile})
    assert (evil["rel_alt"], evil["gps_fix"], evil["satellites"], evil["ready"], evil["climb"]) == (
        None, None, None, None, None
    )  # fmt: skip


def test_a_real_ardupilots_recorded_flight_gives_the_detail() -> None:
    """The driver's state folded from a flight recorded from a real ArduPilot."""
    from test_driver_boot import FLIGHT, folded

    states = folded(FLIGHT)
    infos = [vehicle_info(s, link_ok=True) for _, s in states if s.position_valid]
    last = infos[-1]
    assert last.gps_fix is not None and last.gps_fix >= 3 and last.satellites is not None
    flying = [i for i in infos if i.rel_alt is not None and i.rel_alt > 2.0]
    assert flying, "the recorded flight climbs"
    assert all(i.home_dist is not None for i in flying)
    assert max(i.climb for i in infos if i.climb is not None) > 0.5  # it climbed: up is positive
    assert {i.ready for i in infos} <= {True, False, None}


def test_the_simulators_autopilot_gives_the_detail() -> None:
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from firmware_bridge.sim.autopilot import Autopilot
    from firmware_bridge.telemetry import TelemetryFolder

    ap = Autopilot("ardupilot", 1, (47.0, 8.0, 500.0))
    folder = TelemetryFolder("ardupilot", target_system=1, target_component=1, own_system=255)
    for mid in (24, 33, 242):  # GPS_RAW_INT, GLOBAL_POSITION_INT, HOME_POSITION, as the driver asks
        ap.set_stream(mid, 0.5)
    rx = mavlink.MAVLink(None)
    t = 0.0
    while t < 8.0:
        t = round(t + 0.02, 2)
        for msg in ap.tick(t):  # through MAVLink bytes, as a driver reads them
            for back in rx.parse_buffer(msg.pack(ap.mav)) or []:
                folder.fold(back, t)
    info = vehicle_info(folder.state, link_ok=True)
    assert (info.gps_fix, info.satellites) == (6, 12)
    assert info.rel_alt is not None and abs(info.rel_alt) < 1.0
    assert info.home_dist is not None and info.home_dist < 5.0
