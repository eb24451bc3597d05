"""``swarm gcs`` as a process against real ``swarm agent`` processes: over Zenoh
(connect, an agent killed -> disconnected, restarted -> connected again, SIGTERM exits
0), over the emulated radios with a capture that ``swarm gcs --replay`` then plays, and
the CLI's bad-input messages (exit 2, one line, no traceback).

Nothing sleeps to hope: every wait polls for an outcome until a generous deadline."""

from __future__ import annotations

import json
import signal
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from swarm.cli.commands.gcs import main as gcs_main
from swarm.cli.procs import Child, start_emulator

DEADLINE = 40.0


def ready(child: Child) -> dict[str, Any]:
    line = json.loads(child.wait_lines(1, 30)[0])
    assert line["event"] == "ready", line
    return dict(line)


def logs(child: Child) -> list[dict[str, Any]]:
    out = []
    for line in list(child.lines)[1:]:
        obj = json.loads(line)
        if obj.get("event") == "log":
            out.append(obj)
    return out


def get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


def agent(name: str, aid: int, *link: str) -> Child:
    return Child(["agent", "--name", name, "--id", str(aid), *link, "--json"], name=name)


def alive(*children: Child) -> None:
    for c in children:
        assert c.proc.poll() is None, f"{c.name} exited {c.proc.returncode}: {c.errors[-5:]}"


def post(url: str, body: Any) -> tuple[int, Any]:
    req = urllib.request.Request(
        url, data=json.dumps(body).encode(), method="POST", headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


@pytest.mark.processes
def test_agents_connect_answer_commands_drop_when_killed_and_reconnect(tmp_path: Path) -> None:
    ep, ep1 = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    gcs = Child(
        ["gcs", "--zenoh-listen", ep, "--http", f"127.0.0.1:{free_port()}", "--tiles", "none", "--json"],
        name="gcs",
    )
    children = [gcs]
    try:
        r = ready(gcs)
        assert r["url"].startswith("http://127.0.0.1:") and r["replay"] is False and r["tiles"] is None
        assert r["name"] == "gcs" and r["id"] == 255 and r["link"] == f"zenoh listen={ep}"
        # agent1 listens too, so the agents meet each other as well as the station
        a1 = agent("agent1", 1, "--zenoh-listen", ep1, "--zenoh-connect", ep)
        a2 = agent("agent2", 2, "--zenoh-connect", ep, ep1)
        children += [a1, a2]

        def state() -> dict[str, Any]:
            alive(*children)
            return dict(get(r["url"] + "api/state"))

        def connected() -> set[int]:
            return {a["id"] for a in state()["agents"] if a["connected"]}

        wait_until(lambda: connected() == {1, 2}, "both agents connected", DEADLINE)
        # the event lines on stdout follow the state the API shows: wait for them too
        wait_until(
            lambda: {"agent1 (1) connected", "agent2 (2) connected"} <= {e["text"] for e in logs(gcs)},
            "both connect events on stdout",
            DEADLINE,
        )
        leader = wait_until(lambda: state()["leader"], "the station to see a leader", DEADLINE)
        # real agents answer: the leader takes the swarm's FOLLOW; an agent with no
        # flight controller fails ARM with its reason
        st, body = post(r["url"] + "api/command", {"target": "swarm", "kind": "follow", "heading": 90})
        assert st == 200 and body["results"] == [
            {"agent": leader, "result": "ACCEPTED", "reason": "", "swarm": True}
        ], body
        st, body = post(r["url"] + "api/command", {"target": 2, "kind": "arm"})
        assert st == 200 and body["ok"] is False
        assert body["results"] == [
            {"agent": 2, "result": "FAILED", "reason": "no flight controller on this agent"}
        ]
        a2.proc.send_signal(signal.SIGKILL)
        a2.proc.wait(10)
        children.remove(a2)
        wait_until(lambda: connected() == {1}, "agent2 disconnected", DEADLINE)
        drop = wait_until(
            lambda: [e for e in logs(gcs) if e["kind"] == "disconnect"],
            "the disconnect event on stdout",
            DEADLINE,
        )
        assert [e["text"].split(" (silent")[0] for e in drop] == ["agent2 (2) disconnected"]
        st, body = post(r["url"] + "api/command", {"target": 2, "kind": "land"})
        assert st == 409 and body["error"] == "agent2 (2) is not connected"
        again = agent("agent2", 2, "--zenoh-connect", ep, ep1)
        children.append(again)
        wait_until(lambda: connected() == {1, 2}, "agent2 connected again", DEADLINE)
        wait_until(
            lambda: any(e["text"] == "agent2 (2) connected again" for e in logs(gcs)),
            "the reconnect event on stdout",
            DEADLINE,
        )
        one = get(r["url"] + "api/agents/2")
        assert one["name"] == "agent2" and one["connected"] is True and one["phase"] is not None
        st, body = post(r["url"] + "api/command", {"target": 7, "kind": "arm"})
        assert st == 404 and body["error"] == "unknown agent 7"
        gcs.proc.send_signal(signal.SIGTERM)
        assert gcs.proc.wait(10) == 0
        assert not [e for e in gcs.errors if "Traceback" in e], gcs.errors
    finally:
        for c in children:
            c.stop(grace=3)


@pytest.mark.processes
def test_over_the_radio_with_a_capture_then_replayed(tmp_path: Path) -> None:
    emu, links = start_emulator(2, tmp_path)
    cap = tmp_path / "gcs.tlog"
    children: list[Child] = []
    try:
        gcs = Child(
            [
                "gcs",
                "--radio",
                links[1],
                "--capture",
                str(cap),
                "--http",
                f"127.0.0.1:{free_port()}",
                "--json",
            ],
            name="gcs",
        )
        children.append(gcs)
        r = ready(gcs)
        assert r["link"] == f"radio={links[1]}"
        children.append(agent("agent1", 1, "--radio", links[0]))

        def state() -> dict[str, Any]:
            alive(*children)
            return dict(get(r["url"] + "api/state"))

        wait_until(
            lambda: any(a["connected"] and a["id"] == 1 and a["phase"] for a in state()["agents"]),
            "agent1 connected over the radio",
            60,
        )
        gcs.proc.send_signal(signal.SIGTERM)
        assert gcs.proc.wait(10) == 0
    finally:
        for c in children:
            c.stop(grace=3)
        emu.stop()
    assert cap.stat().st_size > 0
    play = Child(
        ["gcs", "--replay", str(cap), "--speed", "20", "--http", f"127.0.0.1:{free_port()}", "--json"],
        name="replay",
    )
    try:
        rr = ready(play)
        assert rr["replay"] is True and rr["records"] > 0 and rr["link"] == f"replay={cap}"
        replay = get(rr["url"] + "api/replay")
        assert replay["duration_s"] > 0 and replay["speed"] == 20.0

        def seen() -> bool:
            alive(play)
            s = get(rr["url"] + "api/state")
            return any(a["id"] == 1 and a["name"] == "agent1" for a in s["agents"])

        wait_until(seen, "agent1 in the replayed capture", 30)
        assert get(rr["url"] + "api/config")["replay"] is True
    finally:
        assert play.stop() == 0


@pytest.mark.parametrize(
    ("argv", "reason"),
    [
        ([], "give one of --radio URL"),
        (["--radio", "/dev/no-such-radio"], "/dev/no-such-radio"),
        # a radio and Zenoh together: the radio's channel and other stations (issue 16)
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--radio", "x"], "x: no such device"),
        (
            ["--zenoh-listen", "tcp/127.0.0.1:1", "--tiles-dir", "/no/such/dir"],
            "/no/such/dir: not a directory",
        ),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--tiles", "nothing"], "an http(s) URL template"),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--http", "localhost:http"], "HOST:PORT"),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--http", "127.0.0.1:70000"], "outside 0..65535"),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--speed", "2"], "--speed and --paused are for --replay"),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--capture", "x.tlog"], "it needs --radio"),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--id", "7"], "--id 7: ground stations use 251..255"),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--name", "bad name"], "--name"),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--ws-hz", "50"], "--ws-hz 50"),
        (["--zenoh-listen", "tcp/127.0.0.1:1", "--center", "91,0"], "--center"),
        (["--zenoh-listen", "not an endpoint"], "Zenoh"),
        (["--replay", "/no/such.tlog"], "/no/such.tlog"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(
    argv: list[str], reason: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert gcs_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("swarm gcs: error: ") and reason in err[0], err


def test_truncated_capture_and_port_in_use(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import socket

    from radios.mavlink import FrameBuilder
    from radios.tlog import TlogWriter

    path = tmp_path / "cut.tlog"
    with TlogWriter(path) as w:
        fb = FrameBuilder(1, 1)
        for k in range(5):
            w.write(fb.heartbeat(), 1_700_000_000.0 + k)
    path.write_bytes(path.read_bytes()[:-7])
    assert gcs_main(["--replay", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "damaged record" in err[0] and "after 4 whole records" in err[0]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert (
            gcs_main(["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}", "--http", f"127.0.0.1:{port}"]) == 2
        )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"cannot listen on 127.0.0.1:{port}" in err[0], err
