"""The simulator's flavour objects (PX4, ArduPilot) driven through the pure Autopilot core.

Every message goes through real MAVLink bytes both ways; time is simulated and advanced
by the test, so nothing here sleeps or opens a socket.
"""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.errors import ConnectError
from firmware_bridge.px4_events import parse_event
from firmware_bridge.sim import Autopilot, SimConfig, modes, px4_boot
from firmware_bridge.sim.ardupilot import ArduPilot
from firmware_bridge.sim.autopilot import make_flavour
from firmware_bridge.sim.flavour import IN_AIR, LANDING, ON_GROUND, TAKEOFF
from firmware_bridge.sim.px4 import Px4

HOME = (47.397742, 8.545594, 488.0)
POS_MASK = 3576
ACCEPTED, TEMPORARILY_REJECTED, FAILED = 0, 1, 4


class Pilot:
    """One pure autopilot, a ground station's encoder and a simulated clock."""

    def __init__(self, profile: str, **kw: object) -> None:
        self.ap = Autopilot(profile, 1, HOME, **kw)  # type: ignore[arg-type]
        self.cl = mavlink.MAVLink(None, 255, 0)
        self.t = 0.0
        self.heard: list[mavlink.MAVLink_message] = []
        self.landed_seen = [self.ap.landed_state]  # MAV_LANDED_STATE after each tick, repeats dropped

    def _decode(self, msgs: list[mavlink.MAVLink_message]) -> list[mavlink.MAVLink_message]:
        enc, rx = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 0, 0)
        out = [rx.parse_buffer(m.pack(enc))[0] for m in msgs]
        self.heard.extend(out)
        return out

    def send(self, msg: mavlink.MAVLink_message) -> list[mavlink.MAVLink_message]:
        parsed = mavlink.MAVLink(None, 0, 0).parse_buffer(msg.pack(self.cl))
        assert parsed
        return self._decode(self.ap.handle(parsed[0], self.t))

    def command(self, cmd: int, *params: float) -> mavlink.MAVLink_message:
        p = list(params) + [0.0] * (7 - len(params))
        acks = [
            m
            for m in self.send(self.cl.command_long_encode(1, 1, cmd, 0, *p))
            if m.get_type() == "COMMAND_ACK"
        ]
        assert len(acks) == 1 and acks[0].command == cmd
        return acks[0]

    def run(self, seconds: float, each: object = None) -> None:
        end = self.t + seconds
        while self.t < end - 1e-9:
            self.t = round(self.t + 0.05, 6)
            if callable(each):
                each()
            self._decode(self.ap.tick(self.t))
            if not self.landed_seen or self.landed_seen[-1] != self.ap.landed_state:
                self.landed_seen.append(self.ap.landed_state)

    def heartbeat(self) -> mavlink.MAVLink_message:
        self.heard.clear()
        self.run(1.0)
        return [m for m in self.heard if m.get_type() == "HEARTBEAT"][-1]

    def texts(self) -> list[str]:
        return [m.text for m in self.heard if m.get_type() == "STATUSTEXT"]

    def events(self) -> list[tuple[int, bytes]]:
        """PX4's EVENTs heard (pymavlink's UNKNOWN_410): (id, arguments without the trailing zeros)."""
        evs = [parse_event(bytes(m.data)) for m in self.heard if m.get_type() == "UNKNOWN_410"]
        return [(e.id, e.arguments.rstrip(b"\0")) for e in evs if e is not None]


def test_make_flavour_gives_each_vehicle_its_own_object_and_refuses_unknown_values() -> None:
    assert isinstance(make_flavour("px4", "land"), Px4) and make_flavour("px4", "land").loss_action == "land"
    assert isinstance(make_flavour("ardupilot"), ArduPilot)
    assert make_flavour("px4") is not make_flavour("px4")  # state is per vehicle
    with pytest.raises(ValueError, match="unknown profile 'inav'"):
        Autopilot("inav", 1, HOME)
    with pytest.raises(ValueError, match="unknown offboard_loss_action 'kill'"):
        Autopilot("px4", 1, HOME, offboard_loss_action="kill")


@pytest.mark.parametrize("name", sorted(modes.PX4_MODES))
def test_px4_every_mode_by_number_reaches_the_heartbeat(name: str) -> None:
    p = Pilot("px4")
    main, sub = modes.PX4_MODES[name]
    assert p.command(176, 1, main, sub).result == ACCEPTED  # disarmed: any mode is accepted
    hb = p.heartbeat()
    assert hb.autopilot == 12 and hb.custom_mode == main << 16 | sub << 24
    assert p.ap.mode == name and hb.base_mode & 1


@pytest.mark.parametrize("name", sorted(modes.AP_MODES))
def test_ardupilot_every_mode_by_number_reaches_the_heartbeat(name: str) -> None:
    p = Pilot("ardupilot")
    ack = p.command(176, 1, modes.AP_MODES[name])
    texts = p.texts()
    hb = p.heartbeat()
    assert hb.autopilot == 3
    # AUTO with no mission, disarmed: ACCEPTED, as recorded on ArduCopter SITL
    assert ack.result == ACCEPTED and hb.custom_mode == modes.AP_MODES[name] and not texts


@pytest.mark.parametrize(
    ("profile", "custom", "ack_cmd"), [("px4", 4 << 16 | 6 << 24, 176), ("ardupilot", 9, 11)]
)
def test_set_mode_message_is_acked_as_each_autopilot_does(profile: str, custom: int, ack_cmd: int) -> None:
    p = Pilot(profile)
    acks = [m for m in p.send(p.cl.set_mode_encode(1, 1, custom)) if m.get_type() == "COMMAND_ACK"]
    assert [(a.command, a.result) for a in acks] == [(ack_cmd, ACCEPTED)]
    assert p.ap.mode == p.ap.flavour.land_mode


@pytest.mark.parametrize(("profile", "refusal"), [("px4", TEMPORARILY_REJECTED), ("ardupilot", FAILED)])
def test_each_flavour_refuses_with_its_own_result_code(profile: str, refusal: int) -> None:
    p = Pilot(profile)
    assert (
        p.command(176, 1, *((4,) if profile == "ardupilot" else (4, 3))).result == ACCEPTED
    )  # GUIDED / LOITER
    p.ap.set_gps(False)
    assert p.command(400, 1).result == refusal  # no position: arming refused
    assert p.command(22, 0, 0, 0, 0, 0, 0, 10).result == refusal  # take-off refused
    assert p.command(512, 33).result == refusal  # no GLOBAL_POSITION_INT to give
    assert not p.ap.armed


def test_streams_px4_at_boot_ardupilot_only_when_asked() -> None:
    px4, ap = Pilot("px4"), Pilot("ardupilot")
    px4.run(2.0)
    ap.run(2.0)
    assert {m.get_type() for m in px4.heard} >= {"HEARTBEAT", "GLOBAL_POSITION_INT", "ATTITUDE", "SYS_STATUS"}
    assert {m.get_type() for m in ap.heard} == {"HEARTBEAT"}
    px4.send(px4.cl.request_data_stream_encode(1, 1, 6, 10, 1))  # PX4 ignores it: no reply
    ap.send(ap.cl.request_data_stream_encode(1, 1, 6, 10, 1))  # POSITION group at 10 Hz
    ap.heard.clear()
    ap.run(2.0)
    assert sum(m.get_type() == "GLOBAL_POSITION_INT" for m in ap.heard) >= 19


def test_two_vehicles_keep_their_own_offboard_and_guided_state() -> None:
    a, b = Pilot("px4"), Pilot("px4")
    a.send(a.cl.set_position_target_local_ned_encode(0, 1, 1, 1, POS_MASK, 1, 2, -3, 0, 0, 0, 0, 0, 0, 0, 0))
    assert isinstance(a.ap.flavour, Px4) and isinstance(b.ap.flavour, Px4)
    assert a.ap.flavour.setpoint is not None and b.ap.flavour.setpoint is None
    assert b.command(176, 1, 6, 0).result == ACCEPTED  # disarmed: accepted...
    assert b.command(400, 1).result == TEMPORARILY_REJECTED  # ...but no stream of its own to arm on
    c, d = Pilot("ardupilot"), Pilot("ardupilot")
    for p in (c, d):
        p.command(176, 1, 4)
        p.command(400, 1)
    c.command(22, 0, 0, 0, 0, 0, 0, 5)
    assert isinstance(c.ap.flavour, ArduPilot) and isinstance(d.ap.flavour, ArduPilot)
    assert c.ap.flavour.sub == "takeoff" and d.ap.flavour.sub == "idle"


def test_one_flight_in_each_flavour_px4_offboard() -> None:
    p = Pilot("px4")
    assert p.command(400, 1).result == ACCEPTED
    assert p.command(22, 0, 0, 0, 0, 0, 0, HOME[2] + 6).result == ACCEPTED  # AMSL
    p.run(12.0)
    assert p.ap.mode == "AUTO.LOITER"  # take-off done

    def stream() -> None:
        p.send(
            p.cl.set_position_target_local_ned_encode(0, 1, 1, 1, POS_MASK, 10, 0, -8, 0, 0, 0, 0, 0, 0, 0, 0)
        )

    p.run(0.5, stream)
    assert p.command(176, 1, 6, 0).result == ACCEPTED
    p.run(12.0, stream)
    assert p.ap.mode == "OFFBOARD" and math.dist(p.ap.snapshot().position, (10.0, 0.0, -8.0)) < 0.5
    assert p.command(21).result == ACCEPTED
    p.run(20.0)
    assert p.landed_seen == [ON_GROUND, TAKEOFF, IN_AIR, LANDING, ON_GROUND]
    # as PX4 v1.15: said in EVENTs, none in STATUSTEXT; disarmed, back in the mode it was
    # last put in that allows arming (OFFBOARD), not AUTO.LAND
    said = [e for e, _a in p.events()]
    assert said.index(px4_boot.LANDING_DETECTED[0]) < said.index(px4_boot.DISARMED_AUTO_LAND[0])
    assert px4_boot.TAKEOFF_DETECTED[0] in said and p.texts() == []
    assert not p.ap.armed and p.ap.mode == "OFFBOARD"


def test_one_flight_in_each_flavour_ardupilot_guided() -> None:
    p = Pilot("ardupilot")
    assert p.command(176, 1, 4).result == ACCEPTED  # GUIDED before arming
    assert p.command(400, 1).result == ACCEPTED
    assert p.command(22, 0, 0, 0, 0, 0, 0, 6).result == ACCEPTED  # metres above home
    p.run(12.0)
    p.send(p.cl.set_position_target_local_ned_encode(0, 1, 1, 1, POS_MASK, 10, 0, -8, 0, 0, 0, 0, 0, 0, 0, 0))
    p.run(12.0)  # a position target never times out
    assert p.ap.mode == "GUIDED" and math.dist(p.ap.snapshot().position, (10.0, 0.0, -8.0)) < 0.5
    assert p.command(21).result == ACCEPTED
    p.run(30.0)
    assert p.landed_seen == [ON_GROUND, TAKEOFF, IN_AIR, LANDING, ON_GROUND]
    assert "Disarming motors" in p.texts() and not p.ap.armed and p.ap.mode == "LAND"


@pytest.mark.parametrize(("profile", "vehicles", "ok"), [("px4", 250, True), ("ardupilot", 60, False)])
def test_sim_config_takes_ports_from_the_flavour(profile: str, vehicles: int, ok: bool) -> None:
    cfg = SimConfig(vehicles=vehicles, profile=profile, base_port=65000)
    if ok:
        cfg.validate()  # PX4: one UDP port a vehicle, 65000..65249
    else:
        with pytest.raises(ConnectError, match="out of range"):
            cfg.validate()  # ArduPilot: TCP ports ten apart, 65000..65590
    assert SimConfig(profile=profile).first_port() == {"px4": 14540, "ardupilot": 5760}[profile]
