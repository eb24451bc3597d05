"""Issue 27: agents over IP (Wi-Fi) through a router with mutual TLS and the swarm's ACL.

A ``swarm router`` on ``tls/127.0.0.1`` with ``swarm certs``' ACL; two ``swarm agent``
processes and a ``swarm gcs``, each with its own certificate, connecting to it. The ACL
lets each agent put only its own keys and the inboxes, so this checks that what the
swarm really does over Zenoh fits in it: the agents elect one leader (P2P messages on
each other's inboxes), the station connects both (GSAdvertize, its inbox), a swarm
FOLLOW reaches the leader and an ARM reaches an agent without a flight controller
(both on the agents' command keys, which only stations may put on), and the router
refused none of it. An agent started with its certificate but another agent's name
refuses to start, in one line.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from swarm.cli.procs import Child, json_events
from swarm.runtime.pki import issue, make_ca, nodes, write_acl

pytestmark = pytest.mark.processes  # a router, two agents and a station over TLS

DEADLINE = 90.0


def post(url: str, body: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    req = urllib.request.Request(url, json.dumps(body).encode(), {"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def flags(d: Path, name: str) -> list[str]:
    return [
        "--tls-ca",
        str(d / "ca.pem"),
        "--tls-cert",
        str(d / f"{name}.pem"),
        "--tls-key",
        str(d / f"{name}.key"),
    ]


@pytest.mark.timeout(240)
def test_agents_and_a_station_over_a_tls_router_with_the_acl(tmp_path: Path) -> None:
    import time

    now = time.time()
    make_ca(tmp_path, now=now)
    issue(tmp_path, "r1", "router", now=now, hosts=["127.0.0.1"])
    for name, role in (("agent1", "agent"), ("agent2", "agent"), ("gcs", "station")):
        issue(tmp_path, name, role, now=now)
    acl = write_acl(tmp_path, nodes(tmp_path)[0])
    ep = f"tls/127.0.0.1:{free_port('tcp')}"
    router = Child(
        [
            "router",
            "--listen",
            ep,
            *flags(tmp_path, "r1"),
            "--acl",
            str(acl),
            "--json",
            "--report-every",
            "0",
        ],
        name="router",
    )
    children = [router]
    try:
        router.wait_lines(1, 30)
        for i in (1, 2):
            argv = ["agent", "--name", f"agent{i}", "--id", str(i), "--zenoh-connect", ep, "--json"]
            children.append(Child([*argv, *flags(tmp_path, f"agent{i}")], name=f"agent{i}"))
        http = free_port("tcp")
        argv = ["gcs", "--zenoh-connect", ep, *flags(tmp_path, "gcs"), "--http", f"127.0.0.1:{http}"]
        gcs = Child([*argv, "--tiles", "none", "--json"], name="gcs")
        children.append(gcs)
        url = f"http://127.0.0.1:{http}/"
        wait_until(lambda: json_events(gcs.lines, "ready"), "the station ready", DEADLINE, children=children)

        def state() -> dict[str, Any]:
            with urllib.request.urlopen(url + "api/state", timeout=30) as r:
                return dict(json.loads(r.read()))

        def led() -> int | None:
            agents = state()["agents"]
            leaders = {a["leader"] for a in agents if a["connected"]}
            ok = len(agents) == 2 and all(a["connected"] for a in agents) and len(leaders) == 1
            return leaders.pop() if ok and 0 not in leaders else None

        leader = wait_until(
            led, "both agents connected to the station, one leader", DEADLINE, 0.2, children=children
        )
        st, body = post(url + "api/command", {"target": "swarm", "kind": "follow", "heading": 90})
        assert st == 200 and body["results"] == [
            {"agent": leader, "result": "ACCEPTED", "reason": "", "swarm": True}
        ]
        st, body = post(url + "api/command", {"target": 2, "kind": "arm"})
        assert body["results"] == [
            {"agent": 2, "result": "FAILED", "reason": "no flight controller on this agent"}
        ]
        router.proc.terminate()
        assert router.proc.wait(30) == 0
        router.stop()
        final = json_events(router.lines, "refusals")[-1]
        assert final["total"] == 0, f"the router refused the swarm's own traffic: {final['counts']}"
    finally:
        for c in reversed(children):
            c.stop(grace=5)
    # an agent with another agent's certificate: one line, exit 2, before any network
    wrong = Child(
        ["agent", "--name", "agent2", "--id", "2", "--zenoh-connect", ep, *flags(tmp_path, "agent1")],
        name="wrong",
    )
    assert wrong.proc.wait(60) == 2
    wrong.stop()
    assert (
        len(wrong.errors) == 1 and "agent1.pem names 'agent1', but this node is 'agent2'" in wrong.errors[0]
    )
