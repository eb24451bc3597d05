"""The station's HTTP API and WebSocket with a real server on a free port, a real
station over Zenoh, and scripted agents (each a Transport running the real agent-side
connection core, swarm.core.agent.gslink, and answering commands as the test says). Then replay:
a capture written here, played with a manual clock, and served."""

from __future__ import annotations

import asyncio
import json
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from net_helpers import ManualClock, free_port, wait_until

from radios.mavlink import FrameBuilder, dialect
from radios.tlog import TlogWriter
from swarm.core.agent.gslink import GsConfig, GsLink
from swarm.core.station.commands import CommandRefused
from swarm.core.wire.codes import FLAG_ARMED, FLAG_FC_OK, mode_code
from swarm.core.wire.message_types import (
    AckResult,
    AgentState,
    Command,
    CommandAck,
    CommandKind,
    GSAdvertize,
    Message,
    Phase,
    Pose,
    PoseReport,
    Telemetry,
)
from swarm.core.wire.messages import encode
from swarm.core.wire.tunnel import COMP_ID, PAYLOAD_TYPE_BASE, Kind
from swarm.runtime.keyspace.transport import Transport
from swarm.runtime.station.live import Station
from swarm.runtime.station.replay import ReplayStation, load_capture
from swarm.runtime.station.server import LEAFLET_DIR, STATIC_DIR, GcsServer, ServerConfig, ServerError

HOME = (47.397742, 8.545594)


class ScriptedAgent:
    """An agent that speaks the real GS connection protocol (GsLink) over Zenoh and
    answers Commands from ``answers`` (kind -> result; a kind absent: silence)."""

    def __init__(self, ep: str, agent_id: int, *, phase: Phase = Phase.MEMBER, leader: int = 1) -> None:
        self.id = agent_id
        self.name = f"agent{agent_id}"
        self.phase, self.leader = phase, leader
        self.answers: dict[CommandKind, AckResult] = {k: AckResult.ACCEPTED for k in CommandKind}
        self.commands: list[Command] = []
        self.mode = "POSCTL"
        self.tr = Transport.open(self.name, connect=[ep])
        self.gs = GsLink(agent_id, self.name, GsConfig(hb_interval=0.2))
        self.lock = threading.Lock()
        self.stop_ev = threading.Event()
        self.tr.on_inbox(self._inbox)
        self.tr.on_gs_advertize(self._inbox)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def pose(self) -> Pose:
        return Pose(HOME[0] + self.id * 1e-4, HOME[1], 500.0, 30.0 * self.id)

    def telemetry(self) -> Telemetry:
        return Telemetry(
            self.id,
            self.pose(),
            mode_code(self.mode),
            FLAG_ARMED | FLAG_FC_OK,
            self.phase,
            self.leader,
            80,
            150,
            140,
            1.5,
        )

    def _inbox(self, m: Message) -> None:
        with self.lock:
            if isinstance(m, Command):
                self.commands.append(m)
                self.on_command(m)
                result = self.answers.get(m.kind)
                if result is not None:
                    station = self.gs.station_name(m.sender)
                    if station:
                        self.tr.send(station, CommandAck(self.id, m.seq, result, "scripted"))
                return
            self._send(self.gs.handle(m, _now()))

    def on_command(self, m: Command) -> None:
        """What the agent does with a command (besides answering it): nothing here."""

    def _send(self, outs: list[Any]) -> None:
        for o in outs:
            if o.to == 0:
                self.tr.gs_advertise(o.msg)
            else:
                name = self.gs.station_name(o.to)
                if name:
                    self.tr.send(name, o.msg)

    def _run(self) -> None:
        k = 0
        while not self.stop_ev.wait(0.05):
            with self.lock:
                self._send(self.gs.tick(_now(), self.telemetry))
                if k % 4 == 0:
                    self.tr.publish_pose(PoseReport(self.pose()))
                    self.tr.publish_state(
                        AgentState(
                            self.id,
                            self.phase,
                            leader=self.leader,
                            pool=frozenset({1, 2, 3}),
                            members=frozenset({2, 3}) if self.phase == Phase.LEADER else frozenset(),
                            locked=True,
                        )
                    )
            k += 1

    def close(self) -> None:
        self.stop_ev.set()
        self.thread.join(2)
        self.tr.close()


def _now() -> float:
    return time.monotonic()


def http(
    base: str, method: str, path: str, body: Any = None, raw: bytes | None = None, timeout: float = 30.0
) -> tuple[int, Any, bytes]:
    data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
    req = urllib.request.Request(
        base.rstrip("/") + path, data=data, method=method, headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            content = r.read()
            status = r.status
            ctype = r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as e:
        content = e.read()
        status = e.code
        ctype = e.headers.get("Content-Type", "")
    parsed = json.loads(content) if "json" in ctype else None
    return status, parsed, content


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tiles = tmp_path_factory.mktemp("tiles")
    (tiles / "3" / "4").mkdir(parents=True)
    png = b"\x89PNG\r\n\x1a\n" + b"\0" * 32
    (tiles / "3" / "4" / "5.png").write_bytes(png)
    ep = f"tcp/127.0.0.1:{free_port()}"
    station = Station("gcs", zenoh_listen=[ep]).start()
    server = GcsServer(station, ServerConfig(port=free_port(), tiles_dir=tiles, ws_hz=5.0)).start()
    agents = {
        1: ScriptedAgent(ep, 1, phase=Phase.LEADER, leader=1),
        2: ScriptedAgent(ep, 2),
        3: ScriptedAgent(ep, 3),
    }
    agents[1].answers.pop(CommandKind.LAND)  # agent 1 never answers LAND
    agents[2].answers[CommandKind.GOTO] = AckResult.REJECTED
    base = server.url
    try:
        wait_until(
            lambda: (
                station.snapshot()["leader"] == 1
                and all(a["connected"] and a["mode"] is not None for a in station.snapshot()["agents"])
                and len(station.snapshot()["agents"]) == 3
            ),
            "three connected agents, their telemetry, and leader 1",  # a pose can come before it
            30,
        )
        yield {"base": base, "station": station, "server": server, "agents": agents, "png": png}
    finally:
        for a in agents.values():
            a.close()
        server.stop()
        station.stop()


@pytest.mark.processes
def test_config_state_and_agent(live: dict[str, Any]) -> None:
    base = live["base"]
    st, cfg, _ = http(base, "GET", "/api/config")
    assert st == 200 and cfg["tiles"] == "/tiles/{z}/{x}/{y}.png" and cfg["replay"] is False
    assert cfg["station"] == {"name": "gcs", "id": 255} and "OpenStreetMap" in cfg["attribution"]
    assert cfg["center"] == pytest.approx([HOME[0] + 1e-4, HOME[1]], abs=2e-4)
    assert cfg["fence"] == {"floor_m": 2.0, "ceiling_m": 120.0, "radius_m": 1000.0}  # the station's own
    st, state, _ = http(base, "GET", "/api/state")
    assert st == 200 and state["leader"] == 1 and state["station"]["id"] == 255
    assert abs(state["time"] - time.time()) < 60
    a2 = next(a for a in state["agents"] if a["id"] == 2)
    assert a2["name"] == "agent2" and a2["connected"] is True
    assert a2["lat"] == pytest.approx(HOME[0] + 2e-4) and a2["heading"] == 60.0
    assert (a2["mode"], a2["armed"], a2["battery"]) == ("POSCTL", True, 80)
    assert (a2["rssi"], a2["remrssi"], a2["groundspeed"]) == (150, 140, 1.5)
    assert a2["phase"] == "MEMBER" and a2["pool"] == [1, 2, 3] and a2["locked"] is True
    assert a2["trail"] and a2["trail"][-1] == [a2["lat"], a2["lon"]]
    assert [e["kind"] for e in state["events"]].count("connect") == 3
    st, one, _ = http(base, "GET", "/api/agents/1")
    assert st == 200 and one["id"] == 1 and one["phase"] == "LEADER" and one["members"] == [2, 3]
    for path in ("/api/agents/99", "/api/agents/abc", "/api/nothing"):
        st, err, _ = http(base, "GET", path)
        assert st == 404 and isinstance(err["error"], str), path
    st, err, _ = http(base, "DELETE", "/api/state")
    assert st == 405 and "DELETE" in err["error"]
    st, err, _ = http(base, "GET", "/api/replay")
    assert st == 404 and "replay" in err["error"]


@pytest.mark.timing  # six retries in a 12 s window
@pytest.mark.processes
def test_commands_acked_rejected_and_unanswered(live: dict[str, Any]) -> None:
    base, agents = live["base"], live["agents"]
    st, body, _ = http(base, "POST", "/api/command", {"target": 3, "kind": "takeoff", "alt": 12.5})
    assert st == 200
    assert body == {
        "ok": True,
        "request": body["request"],
        "results": [{"agent": 3, "result": "ACCEPTED", "reason": "scripted"}],
    }
    assert isinstance(body["request"], int)
    cmd = agents[3].commands[-1]
    assert (cmd.sender, cmd.target, cmd.kind, cmd.alt) == (255, 3, CommandKind.TAKEOFF, 12.5)
    st, body, _ = http(
        base, "POST", "/api/command", {"target": 2, "kind": "goto", "lat": 47.4, "lon": 8.55, "alt": 10}
    )
    assert st == 200 and body["ok"] is False and body["results"][0]["result"] == "REJECTED"
    st, body, _ = http(base, "POST", "/api/command", {"target": "swarm", "kind": "follow", "heading": 270})
    assert (
        st == 200
        and body["ok"] is True
        and body["results"] == [{"agent": 1, "result": "ACCEPTED", "reason": "scripted", "swarm": True}]
    )
    follow = agents[1].commands[-1]
    assert (follow.target, follow.kind, follow.heading) == (0, CommandKind.FOLLOW, 270.0)
    st, body, _ = http(base, "POST", "/api/command", {"target": "swarm", "kind": "arm"})
    assert st == 200 and sorted(r["agent"] for r in body["results"]) == [1, 2, 3]
    n = len(agents[1].commands)
    st, body, _ = http(base, "POST", "/api/command", {"target": 1, "kind": "land"})
    assert st == 504 and body["ok"] is False and body["results"][0]["result"] == "NO_ANSWER"
    land = agents[1].commands[n:]
    assert len(land) == 6 and len({c.seq for c in land}) == 1  # six tries in 12 s, one seq
    events = http(base, "GET", "/api/state")[1]["events"]
    assert any(e["kind"] == "command" and "LAND" in e["text"] and "NO_ANSWER" in e["text"] for e in events)


@pytest.mark.parametrize(
    ("raw", "status", "reason"),
    [
        (b"{not json", 400, "malformed JSON"),
        (b"[1, 2]", 400, "a command is a JSON object"),
        (b'{"target": 1, "kind": "jump"}', 400, "unknown command kind"),
        (b'{"target": 1, "kind": "takeoff"}', 400, "takeoff needs 'alt'"),
        (b'{"target": 1, "kind": "goto", "lat": 47, "lon": 200, "alt": 500}', 400, "'lon' 200 outside"),
        (b'{"target": "swarm", "kind": "follow", "heading": -5}', 400, "'heading' -5 outside"),
        (b'{"target": 1, "kind": "follow", "heading": 5}', 400, "swarm command"),
        (b'{"target": 42, "kind": "arm"}', 404, "unknown agent 42"),
        (b"\xff\xfe", 400, "malformed JSON"),
    ],
)
def test_bad_commands_are_refused_with_a_reason(
    live: dict[str, Any], raw: bytes, status: int, reason: str
) -> None:
    n = sum(len(a.commands) for a in live["agents"].values())
    st, body, _ = http(live["base"], "POST", "/api/command", raw=raw)
    assert st == status and reason in body["error"]
    assert sum(len(a.commands) for a in live["agents"].values()) == n, "nothing sent"


def test_files_tiles_and_traversal(live: dict[str, Any]) -> None:
    base = live["base"]
    st, _, content = http(base, "GET", "/tiles/3/4/5.png")
    assert st == 200 and content == live["png"]
    for path in (
        "/tiles/3/4/6.png",
        "/tiles/../../etc/passwd",
        "/tiles/3/4/%2e%2e%2f5.png",
        "/static/../station.py",
        "/static/%2e%2e/station.py",
        "/static/..%2fstation.py",
        "/vendor/leaflet/../../package.json",
        # Leaflet now sits in the package beside the server's own sources
        "/vendor/leaflet/../../server.py",
        "/vendor/leaflet/%2e%2e/%2e%2e/server.py",
        "/vendor/leaflet/..%2f..%2fserver.py",
        "/vendor/leaflet/images/..%2f..%2f..%2fsecurity.py",
        "/static/nope.js",
    ):
        st, err, _ = http(base, "GET", path)
        assert st == 404 and err is not None and "error" in err, path
    st, _, content = http(base, "GET", "/")
    assert st == 200 and content == (STATIC_DIR / "index.html").read_bytes()
    st, _, content = http(base, "GET", "/vendor/leaflet/leaflet.js")
    assert st == 200 and content == (LEAFLET_DIR / "leaflet.js").read_bytes()


@pytest.mark.processes
def test_disconnected_agent_and_no_leader_are_409(live: dict[str, Any]) -> None:
    base, station, agents = live["base"], live["station"], live["agents"]
    ep = station.node.zenoh_listen[0]
    extra = ScriptedAgent(ep, 9, phase=Phase.IDLE, leader=0)
    try:
        wait_until(lambda: (station.agent(9) or {}).get("connected"), "agent9 connected", 20)
    finally:
        extra.close()
    wait_until(lambda: station.agent(9)["connected"] is False, "agent9 dropped", 20)
    st, body, _ = http(base, "POST", "/api/command", {"target": 9, "kind": "arm"})
    assert st == 409 and body["error"] == "agent9 (9) is not connected"
    # everyone stops following a leader: no leader, FOLLOW refused
    for a in agents.values():
        a.phase, a.leader = Phase.ELECTING, 0
    try:
        wait_until(lambda: station.snapshot()["leader"] == 0, "no leader", 20)
        st, body, _ = http(base, "POST", "/api/command", {"target": "swarm", "kind": "follow", "heading": 0})
        assert st == 409 and body["error"] == "no leader elected yet"
    finally:
        agents[1].phase, agents[1].leader = Phase.LEADER, 1
        for i in (2, 3):
            agents[i].phase, agents[i].leader = Phase.MEMBER, 1
    wait_until(lambda: station.snapshot()["leader"] == 1, "leader 1 again", 20)


async def _ws_session(base: str) -> dict[str, Any]:
    got: dict[str, Any] = {"states": 0, "errors": [], "results": {}, "events": []}
    async with aiohttp.ClientSession() as s, s.ws_connect(base + "ws") as ws:
        first = await ws.receive_json(timeout=10)
        got["first"] = first
        await ws.send_str("{bad")
        await ws.send_str("[]")
        await ws.send_str(json.dumps({"type": "dance", "id": 5}))
        await ws.send_bytes(b"\x00")
        await ws.send_str(json.dumps({"type": "replay", "action": "play", "id": 6}))
        await ws.send_str(json.dumps({"type": "command", "id": "c1", "target": 2, "kind": "arm"}))
        await ws.send_str(json.dumps({"type": "command", "id": "c2", "target": 2, "kind": "warp"}))
        await ws.send_str(json.dumps({"type": "command", "id": "c3", "target": 77, "kind": "arm"}))
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 30
        while loop.time() < deadline and not (
            len(got["results"]) == 3 and got["events"] and len(got["errors"]) == 5 and got["states"] >= 3
        ):
            m = await ws.receive_json(timeout=max(0.1, deadline - loop.time()))
            kind = m["type"]
            if kind in ("state", "delta"):  # the whole state once, then deltas
                got["states"] += 1
            elif kind == "error":
                got["errors"].append(m)
            elif kind == "command_result":
                got["results"][m["id"]] = m
            elif kind == "event":
                got["events"].append(m["event"])
    return got


def test_websocket_pushes_state_and_events_and_takes_commands(live: dict[str, Any]) -> None:
    got = asyncio.run(_ws_session(live["base"]))
    first = got["first"]
    assert first["type"] == "state" and len(first["agents"]) >= 3 and first["leader"] == 1
    assert got["states"] >= 3
    errors = got["errors"]
    assert [e["status"] for e in errors] == [400, 400, 400, 400, 409]
    assert "malformed JSON" in errors[0]["reason"] and errors[2]["id"] == 5 and errors[4]["id"] == 6
    r = got["results"]
    assert r["c1"]["status"] == 200 and r["c1"]["ok"] is True and r["c1"]["results"][0]["agent"] == 2
    assert r["c2"]["status"] == 400 and "unknown command kind" in r["c2"]["error"]
    assert r["c3"]["status"] == 404
    assert any(e["kind"] == "command" and "ARM -> agent2" in e["text"] for e in got["events"])


def test_port_in_use_is_a_server_error(live: dict[str, Any]) -> None:
    with pytest.raises(ServerError, match="cannot listen"):
        GcsServer(live["station"], ServerConfig(port=live["server"].port)).start()


# -- replay --------------------------------------------------------------------------

T0 = 1_700_000_000.0


def write_capture(path: Path) -> None:
    """Agent 1 (a station connected) and agent 2 (only its vehicle's frames) for 20 s;
    agent 1 goes silent from 12 s."""
    a1 = FrameBuilder(1, COMP_ID)
    v2 = FrameBuilder(2, 1)
    gcs = FrameBuilder(255, COMP_ID)

    def tun(fb: FrameBuilder, kind: Kind, msg: Message, target: int = 0) -> bytes:
        return fb.tunnel(encode(msg), target_system=target, payload_type=PAYLOAD_TYPE_BASE + int(kind))

    with TlogWriter(path) as w:
        w.write(tun(gcs, Kind.GS_ADVERTIZE, GSAdvertize(255, "fieldgcs")), T0)
        w.write(tun(a1, Kind.GS_ADVERTIZE, GSAdvertize(1, "alpha")), T0 + 0.1)
        for k in range(0, 120):  # 0..12 s at 10 Hz
            t = T0 + 0.2 + k * 0.1
            pose = Pose(HOME[0] + k * 1e-5, HOME[1], 510.0, 90.0)
            w.write(tun(a1, Kind.P2P, Telemetry(1, pose, phase=Phase.LEADER, leader=1), 255), t)
            if k % 5 == 0:
                w.write(tun(a1, Kind.STATE, AgentState(1, Phase.LEADER, leader=1, members=frozenset({2}))), t)
        w.write(tun(gcs, Kind.P2P, Command(255, 7, 1, CommandKind.LAND), 1), T0 + 5.0)
        w.write(tun(a1, Kind.P2P, CommandAck(1, 7, AckResult.ACCEPTED), 255), T0 + 5.1)
        for k in range(0, 21):  # agent 2's vehicle, 1 Hz
            t = T0 + k
            w.write(v2.build(dialect.MAVLink_heartbeat_message(2, 12, 0x80 | 1, 3 << 16, 4, 3)), t)
            w.write(
                v2.build(
                    dialect.MAVLink_global_position_int_message(
                        k * 1000,
                        int((HOME[0] - 1e-3) * 1e7),
                        int((HOME[1] + k * 1e-5) * 1e7),
                        520_000,
                        20_000,
                        0,
                        100,
                        0,
                        4500,
                    )
                ),
                t + 0.01,
            )


def test_replay_plays_pauses_seeks_and_changes_speed(tmp_path: Path, manual_clock: ManualClock) -> None:
    path = tmp_path / "flight.tlog"
    write_capture(path)
    cap = load_capture(str(path))
    assert cap.t0 == T0 and cap.duration == pytest.approx(20.01) and cap.decode_errors == 0
    assert cap.station_name == "fieldgcs" and cap.center == pytest.approx([HOME[0] - 1e-3, HOME[1]])
    rp = ReplayStation(cap, clock=manual_clock)
    assert rp.name == "fieldgcs"
    events: list[dict[str, Any]] = []
    rp.add_listener(events.append)
    manual_clock.advance(3.0)
    rp.step()
    s = rp.snapshot()
    assert s["time"] == pytest.approx(T0 + 3.0) and s["leader"] == 1
    a1, a2 = s["agents"]
    assert (a1["name"], a1["connected"], a1["phase"]) == ("alpha", True, "LEADER")
    assert a1["lat"] == pytest.approx(HOME[0] + 28e-5)
    assert (a2["name"], a2["mode"], a2["armed"]) == ("agent2", "POSCTL", True)
    assert a2["lon"] == pytest.approx(HOME[1] + 2e-5)  # the 3 s fix is stamped 3.01 s
    assert a2["heading"] == 45.0 and a2["alt"] == 520.0
    assert [e["text"] for e in events][:2] == ["alpha (1) connected", "alpha (1) is the leader"]
    for bad in (10**400, -(10**400), float("nan"), "2", None, True):  # never OverflowError
        with pytest.raises(CommandRefused):
            rp.control("speed", bad)
        with pytest.raises(CommandRefused):
            rp.control("seek", bad)
    assert rp.control("speed", 2.0)["speed"] == 2.0
    manual_clock.advance(2.0)
    rp.step()
    assert rp.status()["position_s"] == pytest.approx(7.0)
    assert any("LAND" in e["text"] for e in events) and any("ACCEPTED" in e["text"] for e in events)
    rp.control("pause")
    manual_clock.advance(100.0)
    rp.step()
    st = rp.status()
    assert {k: st[k] for k in ("playing", "speed", "position_s", "duration_s")} == {
        "playing": False,
        "speed": 2.0,
        "position_s": 7.0,
        "duration_s": 20.01,
    }
    assert st["time"] == pytest.approx(st["start"] + 7.0) and st["radio"] is None  # no RADIO_STATUS here
    rp.control("seek", 18.0)  # agent 1 silent since 12.1 s: disconnected
    s = rp.snapshot()
    assert s["agents"][0]["connected"] is False and s["agents"][1]["connected"] is True
    n = len(events)
    rp.control("seek", 1.0)  # backwards: a fresh core, re-fed quickly, no events re-announced
    assert len(events) == n
    s = rp.snapshot()
    assert s["agents"][0]["connected"] is True and s["agents"][0]["lat"] == pytest.approx(HOME[0] + 8e-5)
    rp.control("play")
    manual_clock.advance(100.0)
    rp.step()  # runs to the end and stops there
    assert rp.status()["playing"] is False and rp.status()["position_s"] == pytest.approx(20.01)
    assert rp.control("play")["position_s"] == 0.0  # play at the end starts again
    for action, value, reason in [
        ("fly", None, "unknown replay action"),
        ("seek", 99, "seek 99"),
        ("seek", "x", "needs a number"),
        ("speed", 0, "speed 0"),
        ("speed", 1000, "speed 1000"),
    ]:
        with pytest.raises(CommandRefused, match=reason):
            rp.control(action, value)


def test_replay_served(tmp_path: Path, manual_clock: ManualClock) -> None:
    path = tmp_path / "flight.tlog"
    write_capture(path)
    rp = ReplayStation(load_capture(str(path)), clock=manual_clock, playing=False)
    server = GcsServer(rp, ServerConfig(port=free_port(), tiles=None)).start()
    base = server.url
    try:
        st, cfg, _ = http(base, "GET", "/api/config")
        assert st == 200 and cfg["replay"] is True and cfg["tiles"] is None and cfg["attribution"] == ""
        assert cfg["center"] == pytest.approx([HOME[0] - 1e-3, HOME[1]])
        st, body, _ = http(base, "POST", "/api/replay", {"action": "seek", "value": 4.0})
        assert st == 200 and body["position_s"] == 4.0 and body["playing"] is False
        st, state, _ = http(base, "GET", "/api/state")
        assert state["replay"]["position_s"] == 4.0 and state["station"]["link"].startswith("replay=")
        assert {a["name"] for a in state["agents"]} == {"alpha", "agent2"}
        st, body, _ = http(base, "GET", "/api/replay")
        assert st == 200 and body["duration_s"] == pytest.approx(20.01)
        for b, reason in [({"action": "rewind"}, "unknown replay action"), ([], "JSON object")]:
            st, err, _ = http(base, "POST", "/api/replay", b)
            assert st == 400 and reason in err["error"]
        st, err, _ = http(base, "POST", "/api/command", {"target": 1, "kind": "land"})
        assert st == 409 and "replay" in err["error"]
    finally:
        server.stop()
