"""The geofence, attacked where a command is carried out (the agent's pilot, and its
node fed raw radio bytes that never went through a station) and where it is sent
(the station's parse and submit). Altitudes are metres above the vehicle's home."""

from __future__ import annotations

import math
from typing import Any

import pytest

from swarm.core.flight.formation import ne_between, offset
from swarm.core.flight.geofence import Geofence
from swarm.core.flight.pilot import Mode, Pilot, PilotConfig, Role
from swarm.core.station.commands import CommandRefused, CommandSpec, parse_command
from swarm.core.station.core import StationCore
from swarm.core.station.model import AgentView, StationConfig
from swarm.core.wire.message_types import AckResult, Command, CommandAck, CommandKind, Phase, Pose
from swarm.core.wire.messages import decode, encode

HOME = (47.397742, 8.545594, 584.0)  # a field 584 m above sea level
MEMBER = Role(Phase.MEMBER, leader=1)


def pose(n: float = 0.0, e: float = 0.0, up: float = 0.0) -> Pose:
    lat, lon = offset(HOME[0], HOME[1], n, e)
    return Pose(lat, lon, HOME[2] + up)


def flying(cfg: PilotConfig | None = None, *, home: bool = True) -> Pilot:
    """A pilot in the air 10 m above home, holding; ``home``: the autopilot told it."""
    p = Pilot(2, cfg or PilotConfig())
    p.set_own(pose(up=10.0), True, HOME if home else None)
    p.hold("test")
    return p


def goto(alt: float, n: float = 30.0, e: float = 0.0, kind: CommandKind = CommandKind.GOTO) -> Command:
    lat, lon = offset(HOME[0], HOME[1], n, e)
    return Command(255, 1, 2, kind, lat, lon, alt)


# -- the fence's own settings ------------------------------------------------------------


@pytest.mark.parametrize(
    ("kw", "words"),
    [
        ({"floor_m": float("nan")}, "floor nan"),
        ({"ceiling_m": float("inf")}, "ceiling inf"),
        ({"radius_m": float("-inf")}, "radius -inf"),
        ({"floor_m": -1.0}, "floor -1 m: 0 or more"),
        ({"floor_m": 50.0, "ceiling_m": 50.0}, "ceiling 50 m: above the floor"),
        ({"floor_m": 60.0, "ceiling_m": 50.0}, "above the floor (60 m)"),
        ({"ceiling_m": 1e9}, "at most 5000"),
        ({"radius_m": 0.0}, "radius 0 m"),
        ({"radius_m": -5.0}, "radius -5 m"),
        ({"floor_m": True}, "floor True"),
        ({"ceiling_m": "120"}, "ceiling '120'"),
    ],
)
def test_nonsense_limits_are_one_line_errors(kw: dict[str, Any], words: str) -> None:
    with pytest.raises(ValueError) as ei:
        Geofence(**kw)
    assert words in str(ei.value) and "\n" not in str(ei.value)


def test_the_fence_answers_any_number() -> None:
    f = Geofence()
    assert f.alt_refusal(2.0) is None and f.alt_refusal(120.0) is None
    for bad in (float("nan"), float("inf"), -float("inf"), -0.0, 1.9, 120.1, 1e308, -1e308, 10**400):
        why = f.alt_refusal(bad)  # type: ignore[arg-type]
        assert why is not None and "\n" not in why, bad
    assert "below the floor (2 m above home)" in (f.alt_refusal(-564.0) or "")
    lat, lon = offset(HOME[0], HOME[1], 999.0, 0.0)
    assert f.refusal(lat, lon, 20.0, HOME[:2]) is None
    lat, lon = offset(HOME[0], HOME[1], 0.0, -1001.0)
    assert "1001 m from home, beyond the radius (1000 m)" in (f.refusal(lat, lon, 20.0, HOME[:2]) or "")
    assert f.refusal(lat, lon, 20.0, None) is None  # home unknown: the radius is the caller's to leave
    assert f.refusal(float("nan"), 8.0, 20.0, None) == "position out of range"


# -- where it is carried out: the pilot --------------------------------------------------


@pytest.mark.parametrize(
    ("alt", "words"),
    [
        (float("nan"), "is not a finite number"),
        (float("inf"), "is not a finite number"),
        (-float("inf"), "is not a finite number"),
        (-0.0, "below the floor"),
        (1.0, "below the floor"),
        (-564.0, "below the floor"),  # an AMSL 20 read as above a 584 m home
        (604.0, "above the ceiling"),  # an old station's AMSL (584 + 20) read as above home
        (120.5, "above the ceiling"),
        (1e300, "above the ceiling"),
    ],
)
def test_the_pilot_refuses_a_goto_outside_the_fence_and_keeps_holding(alt: float, words: str) -> None:
    for kind in (CommandKind.GOTO, CommandKind.WAYPOINT):
        p = flying()
        held = p.hold_at
        res, why, calls = p.command(goto(alt, kind=kind), MEMBER, 0.0)
        assert res == AckResult.BAD_ARGUMENT and words in why and calls == [], (alt, why)
        assert p.mode == Mode.HOLD and p.hold_at == held
        sp, _ = p.step(0.1, MEMBER)
        assert sp is not None and sp.alt == pytest.approx(HOME[2] + 10.0)


def test_the_pilot_refuses_beyond_the_radius_and_configured_limits() -> None:
    p = flying()
    res, why, _ = p.command(goto(20.0, n=1200.0), MEMBER, 0.0)
    assert res == AckResult.BAD_ARGUMENT and "1200 m from home, beyond the radius (1000 m)" in why
    fenced = flying(PilotConfig(fence=Geofence(floor_m=15.0, ceiling_m=40.0, radius_m=100.0)))
    for cmd, words in (
        (goto(10.0), "below the floor (15 m above home)"),
        (goto(41.0), "above the ceiling (40 m)"),
        (goto(20.0, e=150.0), "beyond the radius (100 m)"),
    ):
        res, why, _ = fenced.command(cmd, MEMBER, 0.0)
        assert res == AckResult.BAD_ARGUMENT and words in why
    assert fenced.command(goto(20.0, e=90.0), MEMBER, 0.0)[0] == AckResult.ACCEPTED


def test_a_goto_at_20_m_flies_20_m_above_home() -> None:
    p = flying()
    res, why, _ = p.command(goto(20.0), MEMBER, 0.0)
    assert (res, why) == (AckResult.ACCEPTED, "")
    sp, _ = p.step(0.1, MEMBER)
    assert sp is not None and sp.alt == pytest.approx(HOME[2] + 20.0)
    # at the target already: it holds there, at the same height
    q = flying()
    assert q.command(goto(25.0, n=0.0), MEMBER, 0.0)[0] == AckResult.ACCEPTED
    assert q.hold_at is not None and q.hold_at.alt == pytest.approx(HOME[2] + 25.0)


def test_home_is_the_autopilots_else_where_the_vehicle_stood() -> None:
    p = Pilot(2)
    p.set_own(pose(e=3.0, up=-1.0), False)  # on the ground, no home from the autopilot
    assert p.home is not None and p.home[2] == pytest.approx(HOME[2] - 1.0)
    p.set_own(pose(up=10.0), True)
    assert p.home is not None and p.home[2] == pytest.approx(HOME[2] - 1.0)  # kept in the air
    p.set_own(pose(up=10.0), True, HOME)
    assert p.home == HOME
    p.hold("test")
    sp_res = p.command(goto(20.0), MEMBER, 0.0)
    assert sp_res[0] == AckResult.ACCEPTED and p.route_alt == pytest.approx(HOME[2] + 20.0)
    # flying with no home ever known: refused, nothing flown
    q = flying(home=False)
    res, why, _ = q.command(goto(20.0), MEMBER, 0.0)
    assert res == AckResult.REJECTED and "home unknown" in why and q.mode == Mode.HOLD


@pytest.mark.parametrize(
    "alt", [float("nan"), float("inf"), -0.0, 0.0, 0.5, 1.9, 121.0, 1e300, -564.0, 604.0]
)
def test_the_pilot_refuses_a_takeoff_outside_the_fence(alt: float) -> None:
    p = Pilot(2)
    p.set_own(pose(), False)
    res, why, calls = p.command(Command(255, 1, 2, CommandKind.TAKEOFF, alt=alt), MEMBER, 0.0)
    assert res == AckResult.BAD_ARGUMENT and why.startswith("take-off altitude") and calls == []
    assert p.mode == Mode.IDLE


def test_a_takeoff_inside_the_fence_is_made() -> None:
    p = Pilot(2, PilotConfig(fence=Geofence(floor_m=0.0)))
    p.set_own(pose(), False)
    assert (
        p.command(Command(255, 1, 2, CommandKind.TAKEOFF, alt=0.5), MEMBER, 0.0)[0] == AckResult.BAD_ARGUMENT
    )
    res, why, calls = p.command(Command(255, 2, 2, CommandKind.TAKEOFF, alt=10.0), MEMBER, 0.0)
    assert why == "taking off to 10 m"
    assert res == AckResult.ACCEPTED and [c.kind for c in calls] == ["takeoff"] and calls[0].alt == 10.0


# -- a raw radio Command reaching an agent's node (no station on the way) ----------------


def _node() -> Any:
    from swarm.core.agent.node import AgentNode, OwnPose
    from swarm.core.election.profiles import profile_by_name
    from swarm.core.wire.message_types import GSAdvertize, GSConnect

    node = AgentNode(2, "agent2", profile_by_name("paper", 0.25), has_fc=True)
    node.start(0.0)
    node.handle(OwnPose(pose(up=10.0), True, HOME), 0.0)
    node.pilot.hold("test")
    node.handle(GSAdvertize(255, "gcs"), 0.0)
    node.handle(GSConnect(255, 1), 0.0)
    return node


def _answer(node: Any, raw: bytes, now: float) -> CommandAck:
    outs = node.handle(decode(raw), now)
    acks = [o.msg for o in outs if isinstance(getattr(o, "msg", None), CommandAck)]
    assert len(acks) == 1, outs
    return acks[0]


@pytest.mark.parametrize(
    ("alt", "result"),
    [
        (-564.0, AckResult.BAD_ARGUMENT),  # 20 m AMSL as the old convention meant it
        (604.0, AckResult.BAD_ARGUMENT),  # 20 m above a 584 m home, sent as AMSL
        (-1000.0, AckResult.BAD_ARGUMENT),  # the wire's lowest
        (5553.5, AckResult.BAD_ARGUMENT),  # the wire's highest
        (0.0, AckResult.BAD_ARGUMENT),
        (20.0, AckResult.ACCEPTED),
    ],
)
def test_a_raw_radio_goto_bypassing_the_station_meets_the_agents_fence(alt: float, result: AckResult) -> None:
    node = _node()
    raw = encode(goto(alt))
    ack = _answer(node, raw, 0.1)
    assert ack.result == result, ack
    sp, _ = node.pilot.step(0.2, MEMBER)
    want = HOME[2] + (20.0 if result == AckResult.ACCEPTED else 10.0)
    if result != AckResult.ACCEPTED:
        assert sp is not None and sp.alt == pytest.approx(want) and node.pilot.mode == Mode.HOLD
    else:
        assert node.pilot.mode == Mode.GOTO and sp is not None and sp.alt == pytest.approx(want)


# -- where it is sent: the station -------------------------------------------------------


def station(fence: Geofence | None = None, *, home: bool = True) -> StationCore:
    core = StationCore("gcs", 255, StationConfig(fence=fence or Geofence()))
    a = AgentView(3, "agent3", connected=True)
    a.pose = pose(up=10.0)
    a.home = HOME if home else None
    core.agents[3] = a
    return core


def sent(core: StationCore, spec: CommandSpec) -> list[Command]:
    _, out = core.submit(spec, 1.0)
    return [o.msg for o in out if isinstance(o.msg, Command)]


def refused(core: StationCore, spec: CommandSpec) -> CommandRefused:
    before = core.counters.commands_sent
    with pytest.raises(CommandRefused) as ei:
        core.submit(spec, 1.0)
    assert core.counters.commands_sent == before and not core.commands.in_flight, "nothing sent"
    assert "\n" not in ei.value.reason
    return ei.value


def _goto_spec(alt: float = 20.0, n: float = 30.0, **kw: Any) -> CommandSpec:
    lat, lon = offset(HOME[0], HOME[1], n, 0.0)
    return CommandSpec(3, CommandKind.GOTO, lat, lon, alt, **kw)


@pytest.mark.parametrize(
    ("spec", "words"),
    [
        (_goto_spec(1.0), "below the floor (2 m above home)"),
        (_goto_spec(-0.0), "below the floor"),
        (_goto_spec(-564.0), "below the floor"),
        (_goto_spec(604.0), "above the ceiling (120 m)"),
        (_goto_spec(float("nan")), "not a finite number"),
        (_goto_spec(float("inf")), "not a finite number"),
        (_goto_spec(20.0, n=1500.0), "beyond the radius (1000 m)"),
        (_goto_spec(0.0, alt_amsl=20.0), "altitude -564 m above home is below the floor"),
        (CommandSpec(3, CommandKind.TAKEOFF, alt=0.5), "below the floor"),
        (CommandSpec(3, CommandKind.TAKEOFF, alt=500.0), "above the ceiling"),
        (CommandSpec(None, CommandKind.TAKEOFF, alt=1.0), "below the floor"),
        (CommandSpec(None, CommandKind.TAKEOFF, alt=float("nan")), "not a finite number"),
    ],
)
def test_the_station_refuses_outside_its_fence_and_sends_nothing(spec: CommandSpec, words: str) -> None:
    err = refused(station(), spec)
    assert err.status == 400 and "refused by the station's geofence" in err.reason and words in err.reason


def test_the_station_sends_inside_its_fence_above_home() -> None:
    (cmd,) = sent(station(), _goto_spec(20.0))
    assert (cmd.kind, cmd.alt) == (CommandKind.GOTO, 20.0)
    (cmd,) = sent(station(), _goto_spec(0.0, alt_amsl=HOME[2] + 30.0))  # AMSL, named as such
    assert cmd.alt == pytest.approx(30.0)
    # its own limits
    tight = Geofence(floor_m=10.0, ceiling_m=50.0, radius_m=200.0)
    assert "below the floor (10 m" in refused(station(tight), _goto_spec(5.0)).reason
    assert "beyond the radius (200 m)" in refused(station(tight), _goto_spec(20.0, n=250.0)).reason
    assert sent(station(tight), _goto_spec(20.0, n=150.0))[0].alt == 20.0


def test_without_the_agents_home_the_station_leaves_the_radius_to_the_agent() -> None:
    core = station(home=False)
    (cmd,) = sent(core, _goto_spec(20.0, n=1500.0))  # the agent's own fence refuses it
    n, e = ne_between(HOME[0], HOME[1], cmd.lat, cmd.lon)
    assert math.hypot(n, e) == pytest.approx(1500.0, abs=1.0)
    assert "below the floor" in refused(station(home=False), _goto_spec(1.0)).reason
    err = refused(station(home=False), _goto_spec(0.0, alt_amsl=604.0))
    assert err.status == 409 and "home is unknown here: give 'alt' (metres above home)" in err.reason


def test_the_station_learns_the_home_where_telemetry_shows_the_vehicle_on_the_ground() -> None:
    from swarm.core.wire.codes import FLAG_AIRBORNE, FLAG_ARMED, FLAG_FC_OK
    from swarm.core.wire.message_types import Telemetry

    core = station(home=False)
    core.handle(Telemetry(3, pose(up=10.0), 0, FLAG_FC_OK | FLAG_ARMED | FLAG_AIRBORNE), 1.0)
    assert core.agents[3].home is None  # flying: not its home
    core.handle(Telemetry(3, pose(e=2.0), 0, FLAG_FC_OK), 2.0)
    assert core.agents[3].home is not None and core.agents[3].home[2] == HOME[2]
    assert core.agents[3].as_dict(2.0)["home_alt"] == HOME[2]
    core.handle(Telemetry(3, pose(up=30.0), 0, FLAG_FC_OK | FLAG_AIRBORNE), 3.0)
    assert core.agents[3].home[2] == HOME[2]


@pytest.mark.parametrize(
    ("body", "words"),
    [
        (
            {"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt": "20 m"},
            "'alt' must be a number, not a string",
        ),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt": None}, "not null"),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt": [20]}, "not a list"),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt": True}, "not true/false"),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt": float("nan")}, "not NaN"),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt": float("-inf")}, "not -Infinity"),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt": 10**400}, "more than 15 digits"),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5}, "goto needs 'alt' (metres above home)"),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt": 20, "alt_amsl": 604}, "not both"),
        ({"target": 3, "kind": "waypoint", "lat": 47.4, "lon": 8.5, "alt_amsl": "604"}, "'alt_amsl' must be"),
        ({"target": 3, "kind": "goto", "lat": 47.4, "lon": 8.5, "alt_amsl": 1e6}, "'alt_amsl' 1000000.0"),
        ({"target": 3, "kind": "takeoff", "alt": "20 m"}, "'alt' must be a number"),
        ({"target": 3, "kind": "takeoff", "alt": -1}, "'alt' -1 outside 0..5553"),
        ({"target": 3, "kind": "takeoff", "alt_amsl": 604}, "takeoff needs 'alt'"),
    ],
)
def test_parse_refuses_what_is_no_altitude(body: dict[str, Any], words: str) -> None:
    with pytest.raises(CommandRefused) as ei:
        parse_command(body)
    assert ei.value.status == 400 and words in ei.value.reason, ei.value.reason


# -- mixed versions: an earlier agent or station never misreads a height -------------------
#: the command kinds of the version before altitudes above home (GOTO 6 and WAYPOINT 9
#: carried AMSL), as that version's decoder knew them
EARLIER_KINDS = frozenset(range(1, 10))


def test_a_goto_above_home_is_a_kind_an_earlier_agent_cannot_decode() -> None:
    """An earlier agent read a go-to's altitude as AMSL: 20 m above home would be 20 m
    above the sea, into the ground. The new kinds are unknown to it: it drops the
    Command (an undecodable kind) and the station reports no answer; nothing flies."""
    for kind in (CommandKind.GOTO, CommandKind.WAYPOINT):
        raw = encode(goto(20.0, kind=kind))
        assert raw[5] == kind.value and kind.value not in EARLIER_KINDS  # after header, sender, seq, target
    # the mode selector's kind is new too: an earlier agent drops it (no answer), nothing flies
    assert CommandKind.SET_MODE.value not in EARLIER_KINDS
    for kind in CommandKind:  # every other kind means what it meant
        if kind not in (CommandKind.GOTO, CommandKind.WAYPOINT, CommandKind.SET_MODE):
            assert kind.value in EARLIER_KINDS, kind


@pytest.mark.parametrize("kind", [CommandKind.GOTO_AMSL, CommandKind.WAYPOINT_AMSL])
def test_an_earlier_stations_amsl_goto_is_decoded_and_refused_by_the_agent(kind: CommandKind) -> None:
    node = _node()
    raw = encode(goto(604.0, kind=kind))  # 20 m above a 584 m home, as an earlier station sent it
    assert raw[5] in (6, 9)
    ack = _answer(node, raw, 0.1)
    assert ack.result == AckResult.REJECTED and "update the station" in ack.reason, ack
    assert node.pilot.mode == Mode.HOLD


@pytest.mark.parametrize("name", ["goto_amsl", "waypoint_amsl", "GOTO_AMSL"])
def test_the_station_never_sends_an_earlier_kind(name: str) -> None:
    with pytest.raises(CommandRefused) as info:
        parse_command({"target": 1, "kind": name, "lat": HOME[0], "lon": HOME[1], "alt": 20.0})
    assert info.value.status == 400
