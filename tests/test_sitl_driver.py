"""The flight-controller driver against real autopilots: ArduCopter 4.7 and PX4 v1.15
SITL (their own flight code and physics), started from ``$SITL_DIR`` by
:mod:`firmware_bridge.sitl` (tests/conftest.py leaves these out, and says so, when no
SITL folder is found).

Each autopilot runs the README's driver example twice in a row (take off, setpoint
control, a 20 m move, land): PX4 disarms by itself about a second after a landing, and
a take-off sent in that second used to be accepted and then waited on for 60 s with
the motors stopped. An arm sent while the autopilot boots is refused with the
autopilot's own reason, never a boot text heard just before. Nothing here judges
time: the autopilots run faster than real time where that is all a test needs.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from net_helpers import wait_until

from firmware_bridge import sitl
from firmware_bridge.driver import Vehicle, connect
from firmware_bridge.errors import CommandRejected, FlightInterrupted

pytestmark = [pytest.mark.processes, pytest.mark.sitl, pytest.mark.timeout(600)]  # boots and flights

SPEED = {"ardupilot": 4.0, "px4": 2.0}  # faster than real time: no test here judges time
CONNECT_S = 60.0
READY_S = 180.0  # a booting autopilot arms after about 40 s of its own time


@pytest.fixture(params=sitl.KINDS)
def autopilot(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[sitl.Sitl]:
    kind = request.param
    with sitl.start(kind, tmp_path / kind, speed=SPEED[kind]) as s:
        yield s


def fly_the_readme_example(v: Vehicle) -> None:
    """The lines of the README's driver example (timeouts for a loaded machine)."""
    v.takeoff(10, ready_timeout=READY_S, timeout=120)
    v.start_offboard()
    v.set_target_ned(20, 0, -10)
    v.wait_ned(20, 0, -10, tolerance=0.5, timeout=120)
    v.land(wait=True, timeout=180)


def test_the_readme_example_twice_in_a_row(autopilot: sitl.Sitl) -> None:
    for run in (1, 2):
        with connect(autopilot.url, timeout=CONNECT_S) as v:
            assert v.autopilot == autopilot.kind
            fly_the_readme_example(v)
            s = v.state
            assert s.landed_state == 1 or not s.armed, (run, s)
            assert s.ned is not None and abs(s.ned[0] - 20) < 2.0 and abs(s.ned[1]) < 2.0, (run, s.ned)
        assert autopilot.running, autopilot.log_tail()


def test_an_early_arm_is_refused_with_the_autopilots_reasons(autopilot: sitl.Sitl) -> None:
    """Right after start neither autopilot can arm. ArduCopter says why in "Arm:" or
    "PreArm:" texts just after its COMMAND_ACK (boot texts heard before it are not the
    reason). PX4 refuses with TEMPORARILY_REJECTED and no STATUSTEXT: its words come
    as EVENT messages (decoded with the build's own metadata), and its failing arming
    checks from its latest check report; before, the refusal carried no reason."""
    with connect(autopilot.url, timeout=CONNECT_S) as v:
        wait_until(lambda: v.statustexts(), "its first texts or events", 30.0, 0.1)
        with pytest.raises(CommandRejected) as refused:
            v.arm()
        e = refused.value
        assert e.result != 0 and e.text, e
        parts = e.text.split("; ")
        if autopilot.kind == "ardupilot":
            assert all(part.startswith(("Arm:", "PreArm:")) for part in parts), e.text
        else:
            assert e.result == 1, e  # TEMPORARILY_REJECTED
            assert "No valid global position estimate" in parts, e.text  # a check its events named
            assert len(parts) == len(set(parts)), e.text
            assert not any(p.startswith("PX4 event 0x") for p in parts), e.text  # all in words


def test_a_failsafe_is_noticed_at_once_and_control_taken_back(autopilot: sitl.Sitl) -> None:
    """PX4 leaves OFFBOARD by itself when the setpoints stop (its default: descend and
    land); an ArduCopter pilot's RC switch leaves GUIDED. A wait for a point ends at
    once, saying so (it used to wait out its timeout), and ``take_control`` brings the
    vehicle back under setpoint control where it is: it holds there, no longer
    descending."""
    with connect(autopilot.url, timeout=CONNECT_S) as v:
        v.takeoff(10, ready_timeout=READY_S, timeout=120)
        v.start_offboard()
        v.set_target_ned(60, 0, -10)  # far: not reached before the failsafe
        outcome: list[BaseException | None] = []

        def wait() -> None:
            try:
                v.wait_ned(60, 0, -10, timeout=120)
                outcome.append(None)
            except BaseException as exc:
                outcome.append(exc)

        waiter = threading.Thread(target=wait, daemon=True)
        waiter.start()
        time.sleep(1.0)
        setpoint_mode = "OFFBOARD" if autopilot.kind == "px4" else "GUIDED"
        if autopilot.kind == "px4":
            v.stop_setpoints()  # the stream is lost: PX4's failsafe
        else:
            v.set_mode("BRAKE")  # the pilot's RC switch
        waiter.join(60)
        assert outcome and isinstance(outcome[0], FlightInterrupted), outcome
        assert f"left {setpoint_mode} by itself" in str(outcome[0]), outcome[0]
        assert v.state.mode != setpoint_mode
        v.take_control()
        taken = v.state
        assert taken.mode == setpoint_mode and taken.rel_alt is not None
        time.sleep(4.0)
        s = v.state
        assert s.mode == setpoint_mode and s.armed, s
        assert s.rel_alt is not None and abs(s.rel_alt - taken.rel_alt) < 2.0, (taken.rel_alt, s.rel_alt)
        v.land(wait=True, timeout=180)


@pytest.mark.timeout(900)  # four flights of about a minute each, on a busy machine longer
def test_the_conformance_bench_flies_both_real_autopilots_beside_the_simulator() -> None:
    """``python -m tools.bench conformance --real --quick``: the figures are measured, never
    judged here (the bench prints its misses); every milestone of the real flight is
    timed, and the simulator's beside it."""
    from tools.bench.conformance_real import MILESTONES, run_real

    out = run_real(quick=True)
    assert isinstance(out["target_met"], bool)
    for kind in sitl.KINDS:
        c = out[kind]
        for m in MILESTONES:
            row = c["milestones"][m]
            if m == "setpoint_loss" and kind == "ardupilot":  # ArduCopter holds a position target
                assert row["real_s"] is None, row
                continue
            assert row["real_s"] is not None and row["real_s"] > 0 and row["sim_s"] is not None, (
                kind,
                m,
                row,
            )
        assert c["acks"]["early_arm"]["real"] in ("FAILED", "TEMPORARILY_REJECTED"), c["acks"]
        assert c["modes"]["real"][-1] in ("LAND", "AUTO.LAND"), c["modes"]
