"""Issue 27's acceptance: a swarm with stations on two machines joined by a router runs
with mutual TLS and access control, and an attacker on every listener gets nothing.

``swarm bench ip-edge`` (:mod:`swarm.cli.bench.ip_edge`), run whole: machine B is a
network namespace joined to this host by a veth pair (as root with iproute2, which this
project's machines and CI have; elsewhere B falls back to this host and the figures say
``loopback``). Station A lists B's swarm over the router, a command from A reaches one of
B's agents through B and is answered, B's swarm takes a FOLLOW from A; every socket of
every process is found and attacked; another CA's certificate and an expired one are
refused at the handshake, an agent's certificate asking a station's command queryable
is refused by the ACL; the router refused none of the stations' own traffic, and the
swarm is still led on both channels after all of it. The router restarts: st1 is shown
gone, then back, and a command crosses again.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from swarm.cli.bench.ip_edge import run

pytestmark = pytest.mark.processes  # a router, two emulators, four agents, two stations


@pytest.mark.timeout(300)
def test_two_machines_a_tls_router_with_an_acl_and_an_attacker_everywhere(tmp_path: Path) -> None:
    f = run(directory=tmp_path, load_s=0)
    assert f["remote_agents"] == [21, 22], f
    assert f["command_across"]["status"] == 200
    assert f["command_across"]["results"] == ["agent 22 FAILED (no flight controller on this agent) via st1"]
    assert f["follow_across"] == ["ACCEPTED"], f
    assert f["led_after_attacks"] == ["c0", "c1"], f
    # nothing listens but the router (TLS) and each station's page on its own loopback
    assert all(v == [] for k, v in f["listeners"].items() if k.startswith("a")), f["listeners"]
    assert [x.split(":")[0] for k in ("st0", "st1") for x in f["listeners"][k]] == ["tcp 127.0.0.1"] * 2
    assert len(f["listeners"]["router"]) == 1
    assert len(f["ip_attacks"]) == 2, f  # the router's TLS port and st0's page (A's side reaches them)
    assert set(f["ip_attacks"].values()) == {"Zenoh sessions opened 0, samples received 0"}, f
    certs = f["cert_attacks"]
    assert certs["another CA's station"]["opened"] is False and certs["expired agent"]["opened"] is False
    assert certs["agent asking a station"] == {"opened": True, "received": 0, "replies": 0}
    assert {
        "tls: an expired certificate",
        "tls: a certificate of another CA, or forged (bad signature)",
        "acl: a1 query (ingress) gcs/st1/command",
    } <= set(f["router_refusals"]), f["router_refusals"]
    assert f["legit_refused"] == []
    # a router restart: st1 shown gone, back once the router is, commands cross again
    r = f["router_restart"]
    assert r["command_across_after"] == ["agent 22 FAILED via st1"] and r["status"] == 200, r
    assert r["st1_shown_gone_s"] < 10 and r["st1_back_s"] < 15, r
    assert f["ok"] is True
