"""Figures of the V formation: the demo's flight in virtual time (swarm.sim.flightsim) for
pose rates 1, 2, 4 and 10 Hz and loss 0, 10 and 20%, the target case in wind (steady
and gusts) and GPS noise (swarm.sim.weather), and the air use of a steady formation of
10 agents."""

from __future__ import annotations

import time
from typing import Any

from swarm.sim.flightsim import FlightScenario
from swarm.sim.flightsim import run as fly
from swarm.sim.tracks import FIGURES
from swarm.sim.weather import Weather

#: the bench's figures are the demo's (swarm.sim.tracks.FIGURES: the same legs and interval,
#: the turn margin 8 s), measured here on the true positions every 0.1 s in virtual time
FIGURE_NAMES = {
    "rms_straight_m": "formation_rms_m",
    "max_straight_m": "formation_max_m",
    "max_turn_m": "turn_max_m",
    "heading_error_after_turn_deg": "heading_error_after_turn_deg",
}

#: the weather cases: a 5 m/s west wind (across the first leg, behind the second),
#: with gusts of 1.5 m/s (standard deviation), and GPS errors of 0.5 m RMS per vehicle
WEATHER = {
    "wind5": Weather(wind_mps=5.0),
    "wind5_gusts1.5": Weather(wind_mps=5.0, gust_mps=1.5),
    "gps0.5": Weather(gps_noise_m=0.5),
    "wind5_gusts1.5_gps0.5": Weather(wind_mps=5.0, gust_mps=1.5, gps_noise_m=0.5),
}


def _case(fs: FlightScenario, seeds: list[int]) -> dict[str, Any]:
    rs = [fly(fs, s) for s in seeds]
    ok = [r for r in rs if r.ok]

    def worst(key: str) -> float | None:
        vals = [getattr(r, key) for r in ok if getattr(r, key) is not None]
        return round(max(vals), 3) if vals else None

    return {
        "runs": len(rs),
        "ok": len(ok),
        "rms_straight_m": worst("rms_straight_m"),
        "max_straight_m": worst("max_straight_m"),
        "max_turn_m": worst("max_turn_m"),
        "heading_error_after_turn_deg": worst("heading_error_after_turn_deg"),
        "air_utilisation": worst("air_utilisation"),
    }


def run(quick: bool = False) -> dict[str, Any]:
    out: dict[str, Any] = {
        "agents": 5,
        "speed_mps": 5.0,
        "leg_m": 150,
        "turn_deg": 90,
        "note": "worst of the seeds per case; virtual time, same cores and pilots as the "
        "agents, PX4 position-loop dynamics",
        "figures": {
            k: f"{FIGURES[v]} (swarm demo's {v}; here on the true positions every 0.1 s)"
            for k, v in FIGURE_NAMES.items()
        },
    }
    t0 = time.process_time()
    virtual = 0.0
    rates = (4.0,) if quick else (1.0, 2.0, 4.0, 10.0)
    losses = (0.1,) if quick else (0.0, 0.1, 0.2)
    cases: dict[str, Any] = {}
    for hz in rates:
        for loss in losses:
            fs = FlightScenario(agents=5, loss=loss, pose_hz=hz, leg_m=150.0)
            c = _case(fs, [1] if quick else [1, 2])
            cases[f"pose{hz:g}hz_loss{round(loss * 100)}"] = c
            virtual += 100.0 * c["runs"]
    out["cases"] = cases
    target = FlightScenario(agents=5, loss=0.1, pose_hz=4.0, leg_m=150.0)
    out["target_n5_pose4_loss10"] = _case(target, [3] if quick else [3, 4, 5, 6, 7])
    out["target_met"] = bool(
        out["target_n5_pose4_loss10"]["ok"] == out["target_n5_pose4_loss10"]["runs"]
        and (out["target_n5_pose4_loss10"]["rms_straight_m"] or 99) <= 1.0
        and (out["target_n5_pose4_loss10"]["max_turn_m"] or 99) <= 5.0
        and (out["target_n5_pose4_loss10"]["heading_error_after_turn_deg"] or 99) <= 2.0
    )
    weather: dict[str, Any] = {}
    for name, w in WEATHER.items():
        if quick and name != "wind5_gusts1.5_gps0.5":
            continue
        fs = FlightScenario(agents=5, loss=0.1, pose_hz=4.0, leg_m=150.0, weather=w)
        weather[name] = {**w.describe(), **_case(fs, [3] if quick else [3, 4])}
    out["weather_n5_pose4_loss10"] = weather
    steady = FlightScenario(agents=10, loss=0.1, pose_hz=4.0, leg_m=100.0 if quick else 150.0)
    s10 = _case(steady, [1])
    out["steady_n10_pose4_air_utilisation"] = s10["air_utilisation"]
    out["steady_n10_ok"] = s10["ok"] == s10["runs"]
    out["cpu_s"] = round(time.process_time() - t0, 1)
    return out
