"""`swarm replay` reads the swarm's TUNNEL payloads as messages (swarm.core.wire.tunnel_decode):
the fields of each kind, text and JSON lines, and hostile payloads (cut, padded, garbage,
lying lengths and addressee lists) shown as undecodable on one line, never a traceback."""

from __future__ import annotations

import json
import random
import re
from pathlib import Path

import pytest

from radios.mavlink import FrameBuilder
from radios.tlog import TlogWriter
from swarm.cli.commands.replay import main
from swarm.core.wire.message_types import (
    AckResult,
    AgentState,
    Assignment,
    Command,
    CommandAck,
    CommandKind,
    Heartbeat,
    Phase,
    Pose,
    Side,
    Task,
    TaskKind,
    Telemetry,
)
from swarm.core.wire.messages import encode
from swarm.core.wire.tunnel import PAYLOAD_TYPE_BASE, Kind, pack
from swarm.core.wire.tunnel_decode import decode_tunnel

T0 = 1_700_000_000.0
TIME_RE = r"\d\d:\d\d:\d\d\.\d{3}"
POSE = Pose(47.3977, 8.5456, 488.5, 90.0, 1.0, -0.5, 1.25)
HB = Heartbeat(
    1, 4, 17, frozenset({2, 3}), Task(TaskKind.FOLLOW, 45.0, assignments=(Assignment(2, 1, Side.LEFT),))
)


def tunnel_payload(kind: Kind, targets: list[int], body: bytes) -> bytes:
    """The MAVLink TUNNEL message's payload as it is on the air (before zero truncation)."""
    target, ptype, data = pack(kind, targets, body)
    return bytes([ptype & 0xFF, ptype >> 8, target, 0, len(data)]) + data.ljust(128, b"\0")


def raw_payload(ptype: int, target: int, length: int, data: bytes) -> bytes:
    return bytes([ptype & 0xFF, ptype >> 8, target, 0, length]) + data.ljust(128, b"\0")[:128]


# -- decoding ----------------------------------------------------------------------------------


def test_heartbeat_to_several_members_as_one_multicast() -> None:
    d = decode_tunnel(tunnel_payload(Kind.MULTI, [3, 2], encode(HB)))
    assert d is not None
    assert (d["tunnel"], d["kind"], d["to"]) == ("multi", "Heartbeat", [2, 3])
    f = d["fields"]
    assert (f["sender"], f["epoch"], f["seq"], f["members"]) == (1, 4, 17, [2, 3])
    assert f["task"]["kind"] == "FOLLOW" and f["task"]["heading"] == pytest.approx(45.0, abs=1.5)
    assert f["task"]["assignments"] == [{"member": 2, "follows": 1, "side": "LEFT"}]
    json.dumps(d)  # JSON's types only


def test_telemetry_pose_and_state_fields() -> None:
    tel = Telemetry(4, POSE, mode=3, flags=3, phase=Phase.MEMBER, leader=1, battery=80, groundspeed=5.0)
    d = decode_tunnel(tunnel_payload(Kind.P2P, [255], encode(tel)))
    assert d is not None and (d["tunnel"], d["kind"], d["to"]) == ("p2p", "Telemetry", [255])
    assert d["fields"]["phase"] == "MEMBER" and d["fields"]["battery"] == 80
    assert d["fields"]["pose"]["lat"] == pytest.approx(POSE.lat, abs=1e-6)
    st = AgentState(2, Phase.LEADER, 2, 0, 7, 3, True, frozenset({1, 2}), frozenset({1}))
    d = decode_tunnel(tunnel_payload(Kind.STATE, [0], encode(st)))
    assert (
        d is not None and d["to"] == [0] and d["fields"]["pool"] == [1, 2] and d["fields"]["locked"] is True
    )


def test_command_arguments_are_fields() -> None:
    cmd = Command(255, 9, 3, CommandKind.GOTO, 47.4, 8.55, 520.0)
    d = decode_tunnel(tunnel_payload(Kind.P2P, [3], encode(cmd)))
    assert d is not None and d["kind"] == "Command"
    assert d["fields"]["kind"] == "GOTO" and d["fields"]["alt"] == pytest.approx(520.0)


def test_other_payload_types_are_not_the_swarms() -> None:
    assert decode_tunnel(b"") is None  # payload type 0
    assert decode_tunnel(raw_payload(0, 0, 3, b"abc")) is None
    assert decode_tunnel(raw_payload(PAYLOAD_TYPE_BASE + len(Kind), 0, 3, b"abc")) is None


HOSTILE = {
    "header only": bytes([0, 0x80, 0, 0]),
    "zero length": raw_payload(PAYLOAD_TYPE_BASE + Kind.P2P, 1, 0, encode(HB)),
    "cut short": raw_payload(PAYLOAD_TYPE_BASE + Kind.P2P, 1, 5, encode(HB)),
    "length past the message": raw_payload(PAYLOAD_TYPE_BASE + Kind.P2P, 1, len(encode(HB)) + 9, encode(HB)),
    "length past 128": raw_payload(PAYLOAD_TYPE_BASE + Kind.P2P, 1, 255, encode(HB)),
    "unknown type": raw_payload(PAYLOAD_TYPE_BASE + Kind.P2P, 1, 3, bytes([0x1F, 1, 2])),
    "other version": raw_payload(PAYLOAD_TYPE_BASE + Kind.P2P, 1, 3, bytes([0xE0 | 2, 1, 2])),
    "multicast list too long": raw_payload(PAYLOAD_TYPE_BASE + Kind.MULTI, 0, 4, bytes([200, 1, 2, 3])),
    "multicast empty": raw_payload(PAYLOAD_TYPE_BASE + Kind.MULTI, 0, 0, b""),
    "bad pose": raw_payload(PAYLOAD_TYPE_BASE + Kind.POSE, 0, 30, b"\x2a" + b"\xff" * 29),
}


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_hostile_payloads_are_undecodable_not_errors(name: str) -> None:
    d = decode_tunnel(HOSTILE[name])
    assert d is not None and d["kind"] is None and d["fields"] == {}
    assert d["error"] and "\n" not in d["error"]
    json.dumps(d)


def test_garbage_never_raises() -> None:
    rng = random.Random(13)
    for _ in range(1000):
        n = rng.randrange(0, 134)
        payload = bytes([rng.randrange(256) for _ in range(n)])
        if n >= 2 and rng.random() < 0.8:  # mostly the swarm's payload types
            payload = bytes([rng.randrange(6), 0x80]) + payload[2:]
        d = decode_tunnel(payload)
        if d is not None:
            assert (d["kind"] is None) == ("error" in d)
            json.dumps(d)


# -- swarm replay on a capture holding good and hostile TUNNEL frames ---------------------------


def swarm_capture(path: Path) -> int:
    """Three good swarm frames, every hostile payload, one foreign TUNNEL; the count."""
    b1, b2 = FrameBuilder(1, 191), FrameBuilder(2, 191)
    frames = [
        b1.tunnel(
            pack(Kind.MULTI, [2, 3], encode(HB))[2], target_system=0, payload_type=PAYLOAD_TYPE_BASE + 5
        ),
        b2.tunnel(encode(Telemetry(2, POSE)), target_system=255, payload_type=PAYLOAD_TYPE_BASE + 2),
    ]
    for name in sorted(HOSTILE):
        p = HOSTILE[name].ljust(5, b"\0")
        ptype, target, length, data = p[0] | p[1] << 8, p[2], p[4], p[5:].rstrip(b"\0")
        data = data[:128]
        frames.append(b2.build(_tunnel_msg(target, ptype, length, data)))
    frames.append(b1.tunnel(b"not ours", payload_type=7))
    with TlogWriter(path) as w:
        for i, raw in enumerate(frames):
            w.write(raw, T0 + 0.1 * i)
    return len(frames)


def _tunnel_msg(target: int, ptype: int, length: int, data: bytes) -> object:
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    return dialect.MAVLink_tunnel_message(target, 0, ptype, length, data.ljust(128, b"\0"))


def test_text_lines_decode_the_swarm(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "swarm.tlog"
    n = swarm_capture(path)
    assert main([str(path)]) == 0
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert err == "" and len(lines) == n
    assert re.fullmatch(
        TIME_RE + r" 1/191 Heartbeat 1 -> 2,3 \{sender : 1, epoch : 4, seq : 17, .*\}", lines[0]
    )
    assert re.fullmatch(
        TIME_RE + r" 2/191 Telemetry 2 -> 255 \{sender : 2, pose : \{lat : 47.3977, .*\}", lines[1]
    )
    bad = lines[2:-1]
    assert len(bad) == len(HOSTILE)
    assert all(
        re.fullmatch(TIME_RE + r" 2/191 TUNNEL swarm \w+ 2 -> \S+ <cannot decode: .+>", b) for b in bad
    ), bad
    assert re.fullmatch(TIME_RE + r" 1/191 TUNNEL \{.*payload_type : 7, .*\}", lines[-1])


def test_json_lines_decode_the_swarm(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "swarm.tlog"
    n = swarm_capture(path)
    assert main([str(path), "--json"]) == 0
    objs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(objs) == n
    hb = objs[0]
    assert {k: hb[k] for k in ("sysid", "compid", "msg", "msgid", "tunnel", "kind", "from", "to")} == {
        "sysid": 1,
        "compid": 191,
        "msg": "TUNNEL",
        "msgid": 385,
        "tunnel": "multi",
        "kind": "Heartbeat",
        "from": 1,
        "to": [2, 3],
    }
    assert hb["t"] == pytest.approx(T0) and hb["fields"]["members"] == [2, 3] and "seq" in hb
    assert objs[1]["kind"] == "Telemetry" and objs[1]["to"] == [255]
    for o in objs[2:-1]:
        assert o["kind"] is None and o["error"] and o["fields"] == {}
    assert "kind" not in objs[-1] and objs[-1]["fields"]["payload_type"] == 7  # not ours: MAVLink's view


def test_truncated_capture_decodes_every_whole_record_then_says_where(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "cut.tlog"
    n = swarm_capture(path)
    path.write_bytes(path.read_bytes()[:-7])  # a record cut in the middle
    for argv in ([str(path)], [str(path), "--json"]):
        assert main(argv) == 2  # a damaged file is bad input
        out, err = capsys.readouterr()
        assert len(out.splitlines()) == n - 1 and "Heartbeat" in out.splitlines()[0]
        assert err.startswith("swarm replay: error: ") and len(err.splitlines()) == 1
        assert "Traceback" not in err


def test_hostile_text_cannot_forge_lines_or_drive_the_terminal(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A reason string (CommandAck) or a STATUSTEXT with a newline or an escape
    sequence: still one line each, the control characters shown escaped."""
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    forged = "ok\n00:00:00.000 9/191 Command 9 -> all {}\x1b[2J"
    ack = CommandAck(3, 7, AckResult.REJECTED, forged)
    b3 = FrameBuilder(3, 191)
    frames = [
        b3.tunnel(encode(ack), target_system=255, payload_type=PAYLOAD_TYPE_BASE + Kind.P2P),
        b3.build(dialect.MAVLink_statustext_message(4, b"low\nbattery\x1b]0;pwned\x07")),
    ]
    path = tmp_path / "hostile-text.tlog"
    with TlogWriter(path) as w:
        for i, raw in enumerate(frames):
            w.write(raw, T0 + i)
    assert main([str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2, lines
    assert all(line.isprintable() for line in lines), lines
    assert "CommandAck" in lines[0] and "\\x0a00:00:00.000" in lines[0] and "\\x1b[2J" in lines[0]
    assert "STATUSTEXT" in lines[1] and "\\x1b]0;pwned\\x07" in lines[1]
    assert main([str(path), "--json"]) == 0
    objs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert objs[0]["fields"]["reason"] == forged  # JSON keeps the text exactly (escaped by JSON)
