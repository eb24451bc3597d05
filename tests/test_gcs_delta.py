"""The station's state deltas (swarm.core.station.delta): a delta stream applied to the
first state reproduces every later state exactly, over random changes of agents,
fields, trails and events (hypothesis), through JSON as on the wire; and the page's
own code (static/delta.js, in headless Chromium) applies the same streams to the same
states."""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator
from typing import Any

import pytest
from gcs_browser import browser
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from swarm.core.station.delta import DeltaError, apply, apply_list, build, list_delta, same
from swarm.runtime.station.server import STATIC_DIR

# rounded as the station rounds them; inside a list a -0.0 compares as 0.0 (the page's
# numbers cannot tell them apart either), so the points here have no negative zero
coord = st.floats(min_value=-90, max_value=90, allow_nan=False).map(lambda x: round(x, 7) + 0.0)
point = st.tuples(coord, coord).map(list)
scalar = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-5, 300),
    st.floats(-1e6, 1e6, allow_nan=False).map(lambda x: round(x, 2)),
    st.text(max_size=6),
)
FIELDS = ("connected", "mode", "armed", "battery", "rssi", "phase", "holding", "alt")


@st.composite
def agent(draw: Any, aid: int) -> dict[str, Any]:
    a: dict[str, Any] = {"id": aid, "name": f"a{aid}"}
    lat, lon = draw(coord), draw(coord)
    a["lat"], a["lon"] = draw(st.sampled_from([(lat, lon), (None, None)]))
    for k in draw(st.lists(st.sampled_from(FIELDS), unique=True)):
        a[k] = draw(scalar)
    a["pool"] = draw(st.lists(st.integers(1, 250), max_size=4))
    trail = draw(st.lists(point, max_size=12))
    if a["lat"] is not None and draw(st.booleans()):
        trail.append([a["lat"], a["lon"]])  # the newest point: the agent's position
    a["trail"] = trail
    return a


ALERT_FIELDS = ("count", "cleared", "acked", "quiet", "level", "text")


@st.composite
def alarm(draw: Any) -> dict[str, Any]:
    a: dict[str, Any] = {"id": draw(st.integers(1, 30))}
    station = draw(st.sampled_from([None, "gcs", "east"]))
    if station is not None:
        a["station"] = station
    for k in draw(st.lists(st.sampled_from(ALERT_FIELDS), unique=True)):
        a[k] = draw(scalar)
    return a


def unique_alarms(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    seen: dict[tuple[Any, Any], dict[str, Any]] = {}
    for a in rows:
        seen.setdefault((a.get("station"), a["id"]), a)
    return list(seen.values())


@st.composite
def state(draw: Any) -> dict[str, Any]:
    ids = sorted(draw(st.sets(st.integers(1, 250), max_size=6)))
    s: dict[str, Any] = {
        "time": draw(st.floats(0, 2e9, allow_nan=False)),
        "leader": draw(st.sampled_from([0, *ids])),
        "agents": [draw(agent(i)) for i in ids],
        "events": draw(st.lists(st.fixed_dictionaries({"t": st.floats(0, 10), "text": st.text(max_size=4)}))),
    }
    if draw(st.booleans()):
        s["station"] = {"name": "gcs", "id": 255, "link": draw(st.text(max_size=5))}
    if draw(st.integers(0, 4)):
        s["alerts"] = unique_alarms(draw(st.lists(alarm(), max_size=6)))
    return s


@st.composite
def moved_on(draw: Any, s: dict[str, Any]) -> dict[str, Any]:
    """``s`` a push later: trails moved on, fields changed, agents gone or new, events."""
    n = json.loads(json.dumps(s))
    n["time"] = s["time"] + 0.2
    for a in n["agents"]:
        if a.get("lat") is not None and "trail" in a and draw(st.booleans()):
            a["lat"], a["lon"] = draw(coord), draw(coord)
            cut = draw(st.integers(0, 2))
            a["trail"] = a["trail"][cut:-1] if draw(st.booleans()) else a["trail"][cut:]
            a["trail"].append([a["lat"], a["lon"]])
        if draw(st.booleans()):
            a[draw(st.sampled_from(FIELDS))] = draw(scalar)
        if draw(st.integers(0, 9)) == 0:
            a.pop(draw(st.sampled_from(sorted(a.keys() - {"id"}))), None)
    if n["agents"] and draw(st.booleans()):
        n["agents"].pop(draw(st.integers(0, len(n["agents"]) - 1)))
    if draw(st.booleans()):
        new = draw(st.integers(1, 250))
        if all(a["id"] != new for a in n["agents"]):
            n["agents"] = sorted([*n["agents"], draw(agent(new))], key=lambda a: a["id"])
    extra = draw(st.lists(st.fixed_dictionaries({"t": st.floats(0, 10), "text": st.text(max_size=4)})))
    n["events"] = (n["events"] + extra)[-draw(st.integers(1, 8)) :]
    if draw(st.integers(0, 5)) == 0:
        n.pop("station", None)
    if "alerts" in n:
        rows = n["alerts"]
        for a in rows:
            if draw(st.booleans()):
                a[draw(st.sampled_from(ALERT_FIELDS))] = draw(scalar)
        if rows and draw(st.booleans()):
            rows.pop(draw(st.integers(0, len(rows) - 1)))
        rows = unique_alarms(rows + draw(st.lists(alarm(), max_size=2)))
        if draw(st.integers(0, 4)) == 0:
            rows = draw(st.permutations(rows))
        n["alerts"] = list(rows)
        if draw(st.integers(0, 9)) == 0:
            n.pop("alerts")
    elif draw(st.integers(0, 3)) == 0:
        n["alerts"] = unique_alarms(draw(st.lists(alarm(), max_size=3)))
    return n


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_a_delta_stream_reproduces_every_state(data: Any) -> None:
    first = data.draw(state())
    held = json.loads(json.dumps(first))  # what a client holds: the state as JSON gave it
    cur = first
    for _ in range(data.draw(st.integers(1, 6))):
        nxt = data.draw(moved_on(cur))
        wire = json.loads(json.dumps(build(cur, nxt), separators=(",", ":")))
        held = apply(held, wire)
        assert held == nxt and json.dumps(held, sort_keys=True) == json.dumps(nxt, sort_keys=True)
        cur = nxt


@settings(max_examples=200, deadline=None)
@given(st.lists(point, max_size=10), st.lists(point, max_size=10))
def test_a_list_edit_is_exact_for_any_two_lists(old: list[Any], new: list[Any]) -> None:
    edit = list_delta(old, new)
    assert (old if edit is None else apply_list(old, edit, "x")) == new


def test_a_trail_that_moved_on_costs_one_or_two_points() -> None:
    trail = [[47.0 + i * 1e-5, 8.0] for i in range(120)]
    head = [47.5, 8.1]
    moved = [*trail[1:-1], [47.49, 8.1], head]
    old = {"agents": [{"id": 1, "lat": trail[-1][0], "lon": 8.0, "trail": trail}]}
    new = {"agents": [{"id": 1, "lat": head[0], "lon": head[1], "trail": moved}]}
    d = build(old, new)
    assert d["agents"] == {"1": {"lat": 47.5, "lon": 8.1, "trail": [1, 118, [47.49, 8.1], 0]}}
    assert apply(old, d) == new
    assert build(new, new) == {}


def test_types_count_true_is_not_one() -> None:
    old = {"agents": [{"id": 1, "armed": 1, "pool": [1]}]}
    new = {"agents": [{"id": 1, "armed": True, "pool": [True]}]}
    assert not same(1, True) and not same([1], [True])
    assert apply(old, build(old, new))["agents"][0]["armed"] is True


def test_an_alarm_counted_again_costs_its_count_not_the_list() -> None:
    rows = [
        {"id": i, "kind": "link", "agent": i, "level": "critical", "text": f"agent{i}: link lost", "count": 1}
        for i in range(1, 60)
    ]
    old = {"agents": [], "alerts": rows}
    new = {"agents": [], "alerts": [*rows[:30], {**rows[30], "count": 2}, *rows[31:]]}
    d = build(old, new)
    assert d == {"alerts": {"set": {":31": {"count": 2}}}}
    assert apply(old, d) == new


@pytest.mark.parametrize(
    "delta",
    [
        {"events": [5, 0]},
        {"events": [0]},
        {"events": ["0", 0]},
        {"drop": [9]},
        {"order": [1, 2]},
        {"agents": [{"id": 1}]},
        {"agents": {"x1": {}}},
        {"agents": {"2": {"name": "no id"}}},
        {"agents": {"1": {"trail": [0, 7]}}},
        {"agents": {"1": {"trail": [True, 0]}}},
        {"alerts": [1]},
        {"alerts": {"drop": [":9"]}},
        {"alerts": {"set": {":2": {"count": 2}}}},
        {"alerts": {"set": {":2": 5}}},
        {"alerts": {"set": []}},
        {"alerts": {"order": [":1", ":1"]}},
        {"alerts": {"order": []}},
    ],
)
def test_a_delta_that_does_not_fit_is_refused(delta: dict[str, Any]) -> None:
    old = {"agents": [{"id": 1, "trail": [[1.0, 2.0]]}], "events": [{"t": 1}], "alerts": [{"id": 1}]}
    with pytest.raises(DeltaError):
        apply(old, delta)


@pytest.fixture(scope="module")
def js_page() -> Iterator[Any]:
    """The page's delta code (static/delta.js) alone in headless Chromium."""
    with browser() as ctx:
        page = ctx.new_page()
        page.add_script_tag(path=str(STATIC_DIR / "delta.js"))
        yield page


@pytest.mark.processes
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_the_page_applies_a_delta_stream_as_the_station_builds_it(js_page: Any, data: Any) -> None:
    states = [data.draw(state())]
    for _ in range(data.draw(st.integers(1, 5))):
        states.append(data.draw(moved_on(states[-1])))
    deltas = [build(a, b) for a, b in itertools.pairwise(states)]
    held = js_page.evaluate(
        "([first, ds]) => { let s = first; return ds.map((d) => (s = window.gcsDelta.apply(s, d))); }",
        [states[0], deltas],
    )
    assert held == states[1:]
