"""The flight simulator's weather (swarm.sim.weather): wind that pushes the vehicles,
gusts the autopilots cannot cancel at once, GPS errors in what each vehicle believes
and reports, all seeded; and a whole flight in it, measured on the true positions."""

from __future__ import annotations

import math

import pytest

from firmware_bridge.sim.dynamics import Body, Limits, Target
from swarm.sim.flightsim import FlightScenario, FlightSim
from swarm.sim.weather import Environment, Weather

DT = 0.02


@pytest.mark.parametrize(
    "bad",
    [
        {"wind_mps": -1.0},
        {"wind_mps": math.nan},
        {"gust_mps": math.inf},
        {"gps_noise_m": 100.0},
        {"gust_tau_s": 0.0},
        {"wind_from_deg": 400.0},
        {"gps_noise_m": "0.5"},
    ],
)
def test_weather_out_of_range_is_refused_with_its_name(bad: dict[str, object]) -> None:
    with pytest.raises(ValueError, match=f"weather {next(iter(bad))}="):
        Weather(**bad)  # type: ignore[arg-type]


def test_the_same_seed_gives_the_same_weather_and_another_seed_another() -> None:
    w = Weather(wind_mps=5.0, gust_mps=1.5, gps_noise_m=0.5)

    def run(seed: int) -> list[float]:
        env = Environment(w, 2, seed)
        out = []
        for _ in range(500):
            env.step(DT)
            out += [*env.wind, *env.gps_error(1)]
        return out

    assert run(7) == run(7) and run(7) != run(8)


def test_gps_errors_have_the_asked_rms_and_differ_between_vehicles() -> None:
    env = Environment(Weather(gps_noise_m=0.5, gps_tau_s=2.0), 2, 1)
    sq = [0.0, 0.0]
    steps = 100_000  # 2000 s of virtual time: 1000 correlation times
    same = 0
    for _ in range(steps):
        env.step(DT)
        for i in range(2):
            n, e = env.gps_error(i)
            sq[i] += n * n + e * e
        same += env.gps_error(0) == env.gps_error(1)
    for s in sq:
        assert math.sqrt(s / steps) == pytest.approx(0.5, rel=0.2)
    assert same == 0


def hover(w: Weather, seconds: float) -> float:
    """The largest distance a hovering vehicle strays from its hold point in ``w``."""
    env = Environment(w, 1, 3)
    b = Body(pos=[0.0, 0.0, -20.0])
    hold = Target.hold((0.0, 0.0, -20.0), 0.0)
    worst = 0.0
    for _ in range(round(seconds / DT)):
        b.step(hold, Limits(), DT, True)
        dn, de = env.push(0, b.vel, DT)
        b.vel[0] += dn
        b.vel[1] += de
        env.step(DT)
        worst = max(worst, math.hypot(b.pos[0], b.pos[1]))
    return worst


def test_a_steady_wind_is_cancelled_and_gusts_push_the_vehicle_about() -> None:
    assert hover(Weather(), 60.0) == 0.0
    assert hover(Weather(wind_mps=8.0), 60.0) < 0.01  # the autopilot has learnt it
    gusty = hover(Weather(wind_mps=8.0, gust_mps=2.0), 60.0)
    assert 0.05 < gusty < 3.0
    # an autopilot that learns slowly is pushed further by the same gusts
    assert hover(Weather(wind_mps=8.0, gust_mps=2.0, integrator_tau_s=10.0), 60.0) > gusty


def test_a_vehicle_that_speeds_up_in_a_headwind_is_pushed_back_until_its_autopilot_learns() -> None:
    env = Environment(Weather(wind_mps=5.0, wind_from_deg=0.0), 1, 1)  # from the north
    pushes = [env.push(0, [5.0, 0.0, 0.0], DT)[0] for _ in range(500)]  # flying north at 5 m/s
    assert pushes[0] < 0.0  # more drag than at hover: backwards
    assert abs(pushes[-1]) < abs(pushes[0]) / 100.0  # learnt after 10 s


def test_a_flight_in_wind_gusts_and_gps_noise_is_measured_on_the_true_positions() -> None:
    w = Weather(wind_mps=5.0, gust_mps=1.5, gps_noise_m=0.5)
    sim = FlightSim(FlightScenario(agents=3, loss=0.1, pose_hz=4.0, leg_m=80.0, weather=w), seed=2)
    r = sim.run_flight()
    assert r.ok, r.why
    assert r.rms_straight_m is not None and 0.1 < r.rms_straight_m < 2.5
    assert r.heading_error_after_turn_deg is not None and r.heading_error_after_turn_deg <= 2.0
    # what the vehicles report is their GPS estimate, not where they are
    t = r.end_s
    for i in range(3):
        seen, true = sim.pose_of(i, t), sim.pose_of(i, t, true=True)
        assert (seen.lat, seen.lon) != (true.lat, true.lon)


def test_the_captures_analysis_measures_the_heading_error_after_the_turn() -> None:
    # the leader's last straight stretch runs east; the V's last task heading is what it held
    from swarm.core.flight.formation import offset
    from swarm.core.wire.message_types import Pose, Task, TaskKind
    from swarm.sim.tracks import Analysis, heading_error

    home = (47.397742, 8.545594)
    track = []
    for k in range(48):  # north at 5 m/s for 4 s, then east for 6 s, then hovering
        t = k * 0.25
        n, e, vn, ve = (5 * t, 0.0, 5.0, 0.0) if t < 4 else (20.0, 5 * (t - 4), 0.0, 5.0)
        if t > 10:
            n, e, vn, ve = 20.0, 30.0, 0.0, 0.0
        lat, lon = offset(*home, n, e)
        track.append((t, Pose(lat, lon, 500.0, 0.0, vn, ve, t % 2.56)))
    for held, want in ((73.68, 16.32), (90.0, 0.0), (268.0, 178.0)):
        an = Analysis(
            tracks={1: track},
            tasks=[(0.0, 1, Task(TaskKind.FOLLOW, 0.0)), (5.0, 1, Task(TaskKind.FOLLOW, held))],
        )
        assert heading_error(an) == pytest.approx(want, abs=0.05)
    assert (
        heading_error(Analysis(tracks={1: track[:2]}, tasks=[(0.0, 1, Task(TaskKind.FOLLOW, 0.0))])) is None
    )
