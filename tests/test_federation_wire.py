"""The stations' envelope and what may cross between stations (swarm.core.station.federation):
attacks first (forged, tampered, replayed, late, huge, malformed, hostile fields), then
the command checks on both sides. Pure: times are given."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.core.flight.geofence import Geofence
from swarm.core.station.commands import CommandRefused, parse_command
from swarm.core.station.federation import (
    KIND_COMMAND,
    KIND_RESULT,
    KIND_STATE,
    MAX_ENVELOPE,
    WINDOW_S,
    FederationRefused,
    Gate,
    Stamp,
    check_remote,
    clean_result,
    clean_state,
    fed_key,
    load_body,
    seal,
    spec_body,
)

KEY = fed_key(bytes(range(32)))
NOW = 1_800_000_000.0
T = int(NOW * 1e6)


def state_env(body: object, *, sender: str = "gcsC", t: int = T, key: bytes | None = KEY) -> bytes:
    return seal(KIND_STATE, sender, 7, t, json.dumps(body).encode(), key)


def test_a_signed_envelope_opens_once_and_only_with_its_key() -> None:
    data = state_env({"agents": []})
    env = Gate(KEY).open(data, NOW, KIND_STATE)
    assert (env.sender, env.signed, env.instance, load_body(env.body)) == ("gcsC", True, 7, {"agents": []})
    with pytest.raises(FederationRefused, match="bad signature"):
        Gate(fed_key(b"x" * 32)).open(data, NOW, KIND_STATE)
    gate = Gate(KEY)
    gate.open(data, NOW, KIND_STATE)
    with pytest.raises(FederationRefused, match="replayed"):
        gate.open(data, NOW, KIND_STATE)
    assert gate.refused == {"replayed": 1}


def test_tampering_with_any_byte_is_refused() -> None:
    data = state_env({"agents": [{"id": 1, "name": "a1"}]})
    for i in range(len(data)):
        bad = data[:i] + bytes([data[i] ^ 0x01]) + data[i + 1 :]
        with pytest.raises(FederationRefused):
            Gate(KEY).open(bad, NOW, KIND_STATE)


def test_unsigned_late_huge_and_wrong_kind_envelopes_are_refused() -> None:
    with pytest.raises(FederationRefused, match="unsigned"):
        Gate(KEY).open(state_env({"agents": []}, key=None), NOW, KIND_STATE)
    late = state_env({"agents": []}, t=T - int((WINDOW_S + 1) * 1e6))
    with pytest.raises(FederationRefused, match="out of window"):
        Gate(KEY).open(late, NOW, KIND_STATE)
    huge = seal(KIND_STATE, "gcsC", 1, T, b" " * MAX_ENVELOPE, KEY)
    with pytest.raises(FederationRefused, match="too large"):
        Gate(KEY).open(huge, NOW, KIND_STATE)
    with pytest.raises(FederationRefused, match="malformed"):
        Gate(KEY).open(state_env({}), NOW, KIND_COMMAND)  # a state is not a command
    with pytest.raises(FederationRefused, match="malformed"):
        Gate(KEY).open(seal(KIND_STATE, "bad name/x", 1, T, b"{}", KEY), NOW, KIND_STATE)


def test_commands_without_a_key_are_refused_unless_allowed() -> None:
    cmd = seal(KIND_COMMAND, "gcsA", 1, T, b"{}", None)
    with pytest.raises(FederationRefused, match="unsigned command"):
        Gate(None).open(cmd, NOW, KIND_COMMAND)
    assert Gate(None, accept_unsigned_commands=True).open(cmd, NOW, KIND_COMMAND).signed is False
    # a keyed station never takes an unsigned command, whatever the flag says
    with pytest.raises(FederationRefused, match="unsigned"):
        Gate(KEY, accept_unsigned_commands=True).open(cmd, NOW, KIND_COMMAND)
    # without a key, states are taken unsigned (and signed ones as unsigned)
    assert Gate(None).open(state_env({"agents": []}), NOW, KIND_STATE).signed is False


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_garbage_only_ever_raises_the_refusal(data: bytes) -> None:
    for key in (KEY, None):
        for kind in (KIND_STATE, KIND_COMMAND, KIND_RESULT):
            try:
                env = Gate(key, accept_unsigned_commands=True).open(data, NOW, kind)
                clean_state(load_body(env.body))
            except FederationRefused:
                pass


def test_a_stamp_is_strictly_increasing() -> None:
    s = Stamp()
    assert [s.next(10.0), s.next(10.0), s.next(9.0), s.next(11.0)] == [
        10_000_000,
        10_000_001,
        10_000_002,
        11_000_000,
    ]


def test_a_hostile_state_is_rebuilt_from_known_fields() -> None:
    evil = "<img src=x onerror=alert(1)>\x1b[2J" + "x" * 5000
    body = {
        "agents": [
            {"id": 3, "name": "a3", "lat": float("nan"), "lon": 8.5, "rssi": 10**400, "battery": "full",
             "mode": evil, "connected": "yes", "leader": 999, "pool": [1, 2, "x", 300, True],
             "trail": [[47.0, 8.0], [91, 0], "x"], "home": [47.0, 8.0], "script": evil, "net": "../etc"},
            {"id": 3, "name": "dup"},
        ],
        "events": [{"t": 1.0, "kind": "x" * 99, "text": evil}, "junk"] * 100,
        "swarms": [{"leader": 3, "members": [3, 4]}, {"leader": 0}],
        "extra": evil,
    }  # fmt: skip
    s = clean_state(json.loads(json.dumps(body)))
    assert [a["name"] for a in s["agents"]] == ["dup"]  # one agent per id (the last)
    a = clean_state({"agents": body["agents"][:1]})["agents"][0]
    assert (
        a["lat"] is None
        and a["lon"] == 8.5
        and a["battery"] is None
        and a["rssi"] is None
        and a["connected"] is False
    )
    assert a["leader"] == 0 and a["pool"] == [1, 2] and a["trail"] == [[47.0, 8.0]] and a["net"] is None
    assert "script" not in a and len(a["mode"]) == 32 and "\x1b" not in a["mode"]
    assert len(s["events"]) == 25 and all(len(e["text"]) <= 200 for e in s["events"])
    assert s["swarms"] == [{"leader": 3, "members": [3, 4], "net": None}] and "extra" not in s
    for bad in ({"agents": [{"id": 0, "name": "a"}]}, {"agents": [{"id": 1, "name": "no/slash"}]}, [], {}):
        with pytest.raises(FederationRefused):
            clean_state(bad)
    with pytest.raises(FederationRefused, match="too large"):
        clean_state({"agents": [{"id": 1, "name": "a"}] * 251})
    with pytest.raises(FederationRefused, match="not JSON"):
        load_body(b"[" * 100_000)


def test_a_result_must_answer_our_request() -> None:
    good = {
        "to": "gcsA",
        "req": 5,
        "status": 200,
        "body": {"ok": True, "results": [{"agent": 3, "result": "ACCEPTED"}]},
    }
    assert clean_result(good, "gcsA", 5) == (200, good["body"])
    for bad in ({**good, "req": 4}, {**good, "to": "gcsB"}, {**good, "status": 99}, {**good, "status": True}):
        with pytest.raises(FederationRefused):
            clean_result(bad, "gcsA", 5)


def test_a_command_for_another_station_is_checked_here_and_carried_as_the_api_object() -> None:
    fence = Geofence(floor_m=2, ceiling_m=50, radius_m=100)
    agent = {"id": 3, "name": "a3", "connected": True, "home": [47.0, 8.0], "home_alt": 400.0}
    far = parse_command({"target": 3, "kind": "goto", "lat": 47.1, "lon": 8.0, "alt": 10})
    with pytest.raises(CommandRefused, match="geofence") as e:
        check_remote(far, fence, agent)
    assert e.value.status == 400
    with pytest.raises(CommandRefused, match="geofence"):
        check_remote(parse_command({"target": "swarm", "kind": "takeoff", "alt": 80}), fence, None)
    with pytest.raises(CommandRefused, match="not connected"):
        check_remote(parse_command({"target": 3, "kind": "land"}), fence, {**agent, "connected": False})
    amsl = parse_command({"target": 3, "kind": "goto", "lat": 47.0001, "lon": 8.0, "alt_amsl": 420})
    checked = check_remote(amsl, fence, agent)
    assert spec_body(checked) == {"target": 3, "kind": "goto", "lat": 47.0001, "lon": 8.0, "alt": 20.0}
    for body in (
        {"target": "swarm", "kind": "follow", "heading": 90.0},
        {"target": 3, "kind": "takeoff", "alt": 10.0},
        {"target": 3, "kind": "arm"},
    ):
        assert spec_body(parse_command(body)) == body


def test_a_state_too_large_is_thinned_not_refused() -> None:
    from swarm.core.station.federation import thin

    body = {"agents": [{"id": i, "name": f"a{i}", "trail": [[47.0, 8.0]] * 120} for i in range(1, 251)]}
    small = thin(body)
    assert all(len(a["trail"]) == 10 for a in small["agents"]) and len(small["agents"]) == 250
    assert len(body["agents"][0]["trail"]) == 120  # the station's own view untouched


def test_a_gate_remembers_a_bounded_number_of_senders() -> None:
    from swarm.core.station.federation import MAX_SENDERS

    gate = Gate(None)
    for i in range(MAX_SENDERS + 50):  # names made up by the thousand, unsigned
        gate.open(state_env({"agents": []}, sender=f"s{i}", key=None, t=T + i), NOW, KIND_STATE)
    assert gate.remembered == MAX_SENDERS


def test_commands_may_cross_on_the_way_but_each_is_taken_once() -> None:
    gate = Gate(KEY)
    first, second = (seal(KIND_COMMAND, "gcsA", 1, T + i, b"{}", KEY) for i in (1, 2))
    assert gate.open(second, NOW, KIND_COMMAND).t_us == T + 2  # sent at once, arrived crossed
    assert gate.open(first, NOW, KIND_COMMAND).t_us == T + 1
    for again in (first, second):
        with pytest.raises(FederationRefused, match="replayed"):
            gate.open(again, NOW + 5, KIND_COMMAND)
    with pytest.raises(FederationRefused, match="out of window"):  # once forgotten, too old anyway
        gate.open(first, NOW + WINDOW_S + 1, KIND_COMMAND)
    # unsigned commands (allowed) are held to the window too: no record grows without end
    loose = Gate(None, accept_unsigned_commands=True)
    with pytest.raises(FederationRefused, match="out of window"):
        loose.open(seal(KIND_COMMAND, "x", 1, T - 10**9, b"{}", None), NOW, KIND_COMMAND)
    from swarm.core.station.federation import MAX_ONCE

    for i in range(MAX_ONCE):
        loose.open(seal(KIND_COMMAND, "x", 1, T + i, b"{}", None), NOW, KIND_COMMAND)
    with pytest.raises(FederationRefused, match="busy"):  # until the window has passed
        loose.open(seal(KIND_COMMAND, "x", 1, T - 1, b"{}", None), NOW, KIND_COMMAND)
    assert (
        loose.open(seal(KIND_COMMAND, "x", 1, T + 61_000_000, b"{}", None), NOW + 61, KIND_COMMAND)
        is not None
    )


def test_a_hostile_stations_alerts_are_rebuilt_bounded_and_plain() -> None:
    """Alerts cross in the state (issue 16): a hostile station's are cut to a bounded
    count of known fields and types, text printable and short; junk is dropped, never
    the whole state."""
    from swarm.core.station.federation import MAX_ALERTS

    evil = "<img src=x onerror=alert(1)>\x1b[2J\u202e" + "x" * 5000
    good = {"id": 7, "kind": "battery", "agent": 41, "level": "critical", "text": "a41 battery 9 %",
            "raised": 1.8e9, "last": 1.8e9, "cleared": None, "acked": False, "count": 1,
            "announced": 1.8e9, "quiet": None, "shelved_until": None, "net": "c1"}  # fmt: skip
    hostile = [
        {**good, "id": 8, "text": evil, "kind": evil, "level": "<b>", "agent": 999, "count": 10**30,
         "acked": "yes", "cleared": "never", "net": "../x", "script": evil, "raised": 1.8e9 + 1,
         "quiet": evil, "shelved_until": "x", "announced": [1]},
        {**good, "id": True}, {**good, "id": -1}, {**good, "id": 2**60}, {**good, "id": 9, "raised": "now"},
        {**good, "id": 10, "text": ["x"]}, "junk", None, [good], 5,
    ]  # fmt: skip
    s = clean_state(json.loads(json.dumps({"agents": [], "alerts": [good, *hostile]})))
    assert s["alerts"][0] == good
    bad = s["alerts"][1]
    assert set(bad) == set(good) and bad["id"] == 8
    assert (bad["kind"], bad["level"], bad["agent"], bad["count"]) == ("other", "warning", 0, 1)
    assert (bad["acked"], bad["cleared"], bad["net"]) == (False, None, None)
    assert (bad["quiet"], bad["shelved_until"], bad["announced"]) == (None, None, None)
    assert len(bad["text"]) <= 200 and "\x1b" not in bad["text"] and "\u202e" not in bad["text"]
    assert len(s["alerts"]) == 2  # the rest dropped, the state kept
    # a flood: the newest MAX_ALERTS kept, one per id
    flood = [{**good, "id": i % 500, "raised": 1.8e9 + i} for i in range(20_000)]
    s = clean_state({"agents": [], "alerts": flood})
    assert len(s["alerts"]) <= MAX_ALERTS and len({a["id"] for a in s["alerts"]}) == len(s["alerts"])
    assert max(a["raised"] for a in s["alerts"]) == 1.8e9 + 19_999
    for junk in ("alerts", {"id": 1}, 7, None):
        assert clean_state({"agents": [], "alerts": junk})["alerts"] == []


def forge(flags: int, body: bytes, key: bytes | None) -> bytes:
    """A state envelope with any ``flags`` (signed with ``key`` when given)."""
    import hashlib
    import hmac

    from swarm.core.station.federation import HEADER, MAGIC

    data = HEADER.pack(MAGIC, KIND_STATE, flags | (1 if key else 0), T, 7, 4) + b"gcsC" + body
    return data + hmac.new(key, data, hashlib.sha256).digest() if key else data


def test_a_compressed_state_opens_and_a_bomb_or_junk_is_refused() -> None:
    """States are sent deflated (issue 16: 200 agents' states cost 0.55 MB/s plain).
    The MAC covers the deflated bytes (checked before inflating); inflating stops at
    MAX_ENVELOPE: a bomb is refused as too large, junk as malformed, signed or not."""
    import zlib

    from swarm.core.station.federation import FLAG_DEFLATE

    body = {"agents": [{"id": i, "name": f"a{i}", "trail": [[47.0, 8.0]] * 40} for i in range(1, 101)]}
    plain = json.dumps(body).encode()
    for key in (KEY, None):
        packed = seal(KIND_STATE, "gcsC", 7, T, plain, key, deflate=True)
        assert len(packed) < len(plain) / 5
        env = Gate(key).open(packed, NOW, KIND_STATE)
        assert load_body(env.body) == body and env.signed is (key is not None)
    bomb = zlib.compress(b"[" * (MAX_ENVELOPE * 8), 9)  # 8 MiB of JSON in a few kB
    assert len(bomb) < 64 * 1024
    for key in (KEY, None):
        with pytest.raises(FederationRefused, match="too large"):
            Gate(key).open(forge(FLAG_DEFLATE, bomb, key), NOW, KIND_STATE)
        with pytest.raises(FederationRefused, match="malformed"):
            Gate(key).open(forge(FLAG_DEFLATE, b"\x78\x9cnot deflate", key), NOW, KIND_STATE)
        with pytest.raises(FederationRefused, match="malformed"):  # an unknown flag
            Gate(key).open(forge(8, plain, key), NOW, KIND_STATE)
    # tampered deflated bytes: the MAC refuses them before anything is inflated
    good = bytearray(seal(KIND_STATE, "gcsC", 7, T, plain, KEY, deflate=True))
    good[40] ^= 1
    with pytest.raises(FederationRefused, match="bad signature"):
        Gate(KEY).open(bytes(good), NOW, KIND_STATE)
