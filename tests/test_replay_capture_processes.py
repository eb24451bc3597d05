"""A real station capture (emulated radios, a station and an agent as processes) read back
by ``swarm replay``: the swarm's messages decoded (text and JSON), and the station radio's
RADIO_STATUS in the capture, so a replay shows link quality."""

from __future__ import annotations

import json
import signal
import urllib.request
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from radios.replay import capture_stats
from radios.tlog import read_tlog
from swarm.cli.commands.replay import main as replay_main
from swarm.cli.procs import Child, start_emulator


def get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


def _fly(links: list[str], cap: Path, procs: list[Child]) -> None:
    """A station capturing its radio (links[1]) and agent1 (links[0]) until connected;
    the processes go into ``procs`` as they start (the caller stops them)."""
    http = f"127.0.0.1:{free_port()}"
    gcs = Child(["gcs", "--radio", links[1], "--capture", str(cap), "--http", http, "--json"], name="gcs")
    procs.append(gcs)
    url = json.loads(gcs.wait_lines(1, 30)[0])["url"]
    procs.append(Child(["agent", "--name", "agent1", "--id", "1", "--radio", links[0], "--json"], name="a1"))

    def agent1_connected() -> bool:
        agents = get(url + "api/state")["agents"]
        return any(a["id"] == 1 and a["connected"] and a["phase"] for a in agents)

    wait_until(agent1_connected, "agent1 connected over the radio", 60, children=procs)
    gcs.proc.send_signal(signal.SIGTERM)  # the station closes its capture
    assert gcs.proc.wait(10) == 0


@pytest.fixture(scope="module")
def station_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("station-capture")
    cap = d / "gcs.tlog"
    emu, links = start_emulator(2, d)
    procs: list[Child] = []
    try:
        _fly(links, cap, procs)
    finally:
        for c in procs:
            c.stop(grace=3)
        emu.stop()
    return cap


@pytest.mark.processes
def test_station_capture_holds_its_radios_status(station_capture: Path) -> None:
    names = Counter(rec.frame.msgid for rec in read_tlog(station_capture))
    assert names[109] >= 1, names  # RADIO_STATUS from the station's own radio (sysid 51)
    radio = [r.frame for r in read_tlog(station_capture) if r.frame.msgid == 109]
    assert {(f.sysid, f.compid) for f in radio} == {(51, 68)}
    # the radio's reports to its host never went on air: no share of the air time
    stats = capture_stats(read_tlog(station_capture))
    shares = {s["sysid"]: s["airtime_share"] for s in stats["systems"]}
    assert shares[51] == 0.0 and sum(shares.values()) == pytest.approx(1.0)


@pytest.mark.processes
def test_replay_decodes_a_real_capture(station_capture: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert replay_main([str(station_capture), "--json"]) == 0
    objs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    swarm = [o for o in objs if o.get("kind")]
    kinds = Counter(o["kind"] for o in swarm)
    # the station's side of a connection: announce, connect, heartbeats; the agent's answers
    assert {"GSAdvertize", "GSConnect", "Advertize", "GSConnectAck", "Telemetry"} <= kinds.keys(), kinds
    assert not [o for o in objs if o.get("tunnel") and o["kind"] is None], "undecodable swarm frames"
    tel = next(o for o in swarm if o["kind"] == "Telemetry")
    assert tel["from"] == 1 and tel["to"] == [255] and tel["fields"]["sender"] == 1
    assert {"lat", "lon", "alt"} <= tel["fields"]["pose"].keys()
    rs = [o for o in objs if o["msg"] == "RADIO_STATUS"]
    assert rs and {"rssi", "remrssi", "txbuf"} <= rs[0]["fields"].keys()
    # text: one line per record, the same messages by name
    assert replay_main([str(station_capture)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(objs)
    assert any(" Telemetry 1 -> 255 {sender : 1, pose : {lat : " in line for line in lines)
    assert any(" GSAdvertize 255 -> all {" in line for line in lines)
