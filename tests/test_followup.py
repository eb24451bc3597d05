"""Results that mean what they say (issue 28), pure, through the station core: after
an agent's ACCEPTED the station follows the vehicle on its Telemetry and ends each
command DONE, DID_NOT_HAPPEN (with why) or REPLACED: a Go after an autopilot failsafe
(the vehicle in its loiter) is not "accepted" and done, it did not happen, with an
alarm; a Go flown is in progress with what is left, then done; a vehicle that does not
move is said so; a take-off asked of a vehicle the autopilot holds is not done; a
landing is done on the ground; a newer command replaces an older one."""

from __future__ import annotations

import math

from test_gcs_station import connect, msgs

from swarm.core.flight.formation import offset
from swarm.core.station.commands import parse_command
from swarm.core.station.core import StationCore
from swarm.core.station.followup import LOST_S, STALL_S
from swarm.core.wire.codes import FLAG_AIRBORNE, FLAG_ARMED, FLAG_CONTROL_LOST, FLAG_FC_OK, mode_code
from swarm.core.wire.message_types import AckResult, Command, CommandAck, Phase, Pose, Telemetry

HOME = (47.397742, 8.545594, 500.0)
FLYING = FLAG_ARMED | FLAG_AIRBORNE | FLAG_FC_OK


class Vehicle:
    """One agent's vehicle as its Telemetry tells it."""

    def __init__(self, core: StationCore, agent: int = 3) -> None:
        self.core, self.id = core, agent
        self.n = self.e = 0.0
        self.h = 20.0
        self.flags = FLYING
        self.mode = "OFFBOARD"
        connect(core, agent, 0.0)

    def tm(self, now: float) -> None:
        lat, lon = offset(HOME[0], HOME[1], self.n, self.e)
        pose = Pose(lat, lon, HOME[2] + self.h, 0.0)
        t = Telemetry(
            self.id, pose, mode_code(self.mode), self.flags, Phase.MEMBER, 1, 80, 1, 1, 0.0, rel_alt=self.h
        )
        self.core.handle(t, now)
        self.core.tick(now)


def send(
    core: StationCore, body: dict[str, object], now: float, result: AckResult = AckResult.ACCEPTED
) -> int:
    req, outs = core.submit(parse_command(body), now)
    (cmd,) = msgs(outs, Command)
    core.handle(CommandAck(cmd.to, cmd.msg.seq, result, ""), now + 0.1)
    assert [r.id for r in core.take_finished()] == [req.id]
    return req.id


def lines(core: StationCore) -> list[str]:
    return [e.text for e in core.events if e.kind == "command"]


def doing(core: StationCore, agent: int = 3) -> dict[str, object] | None:
    row = next(a for a in core.snapshot(0.0)["agents"] if a["id"] == agent)
    return row.get("doing")  # type: ignore[return-value]


def target(n: float, e: float, alt: float = 20.0) -> dict[str, object]:
    lat, lon = offset(HOME[0], HOME[1], n, e)
    return {"target": 3, "kind": "goto", "lat": lat, "lon": lon, "alt": alt}


def test_a_go_after_a_failsafe_did_not_happen_and_says_why() -> None:
    core = StationCore()
    v = Vehicle(core)
    v.flags, v.mode = FLYING | FLAG_CONTROL_LOST, "AUTO.LOITER"  # the autopilot's failsafe
    v.tm(1.0)
    rid = send(core, target(80.0, 0.0), 2.0)  # the agent accepts it...
    t = 2.0
    while t < 2.0 + LOST_S + 2:  # ...and the autopilot keeps its loiter: 0 m moved
        t += 0.5
        v.tm(t)
    d = doing(core)
    assert d is not None and d["state"] == "DID_NOT_HAPPEN" and d["request"] == rid
    assert "the autopilot has control (mode AUTO.LOITER)" in str(d["text"])
    assert any(x.startswith("GOTO -> agent3 (3): DID_NOT_HAPPEN") for x in lines(core))
    (alarm,) = [a for a in core.alerts.alerts.values() if a.kind == "command"]
    assert alarm.level == "warning" and alarm.in_banner  # not an advisory: the operator acts


def test_a_go_flown_is_in_progress_with_what_is_left_then_done() -> None:
    core = StationCore()
    v = Vehicle(core)
    v.tm(1.0)
    send(core, target(60.0, 0.0, 25.0), 2.0)
    seen = []
    t = 2.0
    while v.n < 60.0:
        t += 1.0
        v.n, v.h = min(60.0, v.n + 5.0), min(25.0, v.h + 1.0)
        v.tm(t)
        d = doing(core)
        assert d is not None
        seen.append((d["state"], d["text"]))
    assert seen[0][0] == "IN_PROGRESS" and seen[0][1].endswith("m to go")
    assert seen[-1][0] == "DONE" and str(seen[-1][1]).startswith("arrived")
    assert [x for x in lines(core) if "DONE" in x] == [f"GOTO -> agent3 (3): DONE ({seen[-1][1]})"]


def test_a_vehicle_that_does_not_move_is_said_so() -> None:
    core = StationCore()
    v = Vehicle(core)
    v.tm(1.0)
    send(core, target(100.0, 0.0), 2.0)
    t = 2.0
    while t < 2.0 + STALL_S + 1:
        t += 0.5
        v.tm(t)  # under setpoint control, yet it stays where it is
    d = doing(core)
    assert d is not None and d["state"] == "DID_NOT_HAPPEN"
    assert "has not moved toward it in 15 s (100 m to go, mode OFFBOARD)" in str(d["text"])


def test_a_take_off_asked_of_a_vehicle_the_autopilot_holds_is_not_done() -> None:
    core = StationCore()
    v = Vehicle(core)
    v.h, v.flags, v.mode = 10.0, FLYING | FLAG_CONTROL_LOST, "AUTO.LOITER"
    v.tm(1.0)
    send(core, {"target": 3, "kind": "takeoff", "alt": 10}, 2.0)  # "accepted (already flying)"
    v.tm(2.5)
    d = doing(core)
    assert d is not None and d["state"] == "IN_PROGRESS" and "autopilot has control" in str(d["text"])
    v.flags, v.mode = FLYING, "OFFBOARD"  # control taken back: now it is done
    v.tm(3.0)
    d = doing(core)
    assert d is not None and d["state"] == "DONE" and d["text"] == "airborne at 10.0 m above home"


def test_a_landing_is_done_on_the_ground_and_a_newer_command_replaces_an_older_one() -> None:
    core = StationCore()
    v = Vehicle(core)
    v.tm(1.0)
    first = send(core, target(100.0, 0.0), 2.0)
    v.tm(2.5)
    send(core, {"target": 3, "kind": "land"}, 3.0)
    assert "GOTO -> agent3 (3): REPLACED (by LAND)" in lines(core)
    v.mode = "AUTO.LAND"
    t = 3.0
    while v.h > 0:
        t += 1.0
        v.h = max(0.0, v.h - 3.0)
        if v.h == 0.0:
            v.flags = FLAG_ARMED | FLAG_FC_OK  # on the ground
        v.tm(t)
    d = doing(core)
    assert d is not None and d["state"] == "DONE" and d["text"] == "on the ground" and d["request"] != first
    v.tm(t + 61.0)
    assert doing(core) is None  # shown a minute, then the log has it


def test_a_landing_the_autopilot_leaves_did_not_happen() -> None:
    core = StationCore()
    v = Vehicle(core)
    v.tm(1.0)
    send(core, {"target": 3, "kind": "land"}, 2.0)
    v.mode = "AUTO.LOITER"  # an RC pilot took over at once
    t = 2.0
    while t < 2.0 + 10.0 + LOST_S + 2:
        t += 0.5
        v.tm(t)
    d = doing(core)
    assert (
        d is not None
        and d["state"] == "DID_NOT_HAPPEN"
        and d["text"] == "the vehicle left landing (mode AUTO.LOITER)"
    )


def test_a_refused_or_unanswered_command_is_not_followed() -> None:
    core = StationCore()
    v = Vehicle(core)
    v.tm(1.0)
    send(core, target(50.0, 0.0), 2.0, AckResult.REJECTED)
    assert doing(core) is None
    assert math.isfinite(core.next_deadline())
