"""Issue 27: Zenoh over IP authenticated (mutual TLS) and authorised (access control),
tried against a real ``swarm router`` as an attacker would.

The swarm's CA, a router's, two agents' and a station's certificates, an expired
agent certificate and another CA's station certificate are made with the real code
(:mod:`swarm.runtime.keyspace.pki`), the ACL by ``swarm certs``' rules. A router listens on
``tls/127.0.0.1`` with the ACL; agent2 is connected with its own certificate and
listens on its inbox and command key. Then, each several times: a client with no
certificate, plain TCP to the TLS port, another CA's certificate, an expired
certificate, and agent1's valid certificate putting a station's Command on agent2's
command key. None reaches agent2; the station's own Command does (so the path works
and the refusals are not for want of a route). The router says each kind of refusal
once and counts every one.

Without TLS (before the fix, and still with plain endpoints) any of these clients
reached agent2's keys: the issue's first finding.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from swarm.cli.procs import Child, json_events
from swarm.core.wire.message_types import Command, CommandKind
from swarm.core.wire.messages import decode, encode
from swarm.errors import CertError
from swarm.runtime.keyspace.pki import issue, make_ca, nodes, write_acl
from swarm.runtime.keyspace.transport import ClientSession, open_session, session_config
from swarm.runtime.options import TlsFiles

DEADLINE = 30.0
DAY = 86400.0


def make_pki(d: Path) -> dict[str, Path]:
    """The swarm's CA and certificates in ``d``, another CA's in ``d/other``."""
    now = time.time()
    make_ca(d, now=now)
    issue(d, "r1", "router", now=now, hosts=["127.0.0.1"])
    for name, role in (("agent1", "agent"), ("agent2", "agent"), ("gcs1", "station")):
        issue(d, name, role, now=now)
    issue(d, "old", "agent", now=now, valid_from=now - 10 * DAY, days=2)  # expired 8 days ago
    other = d / "other"
    other.mkdir()
    make_ca(other, now=now)
    issue(other, "gcs1", "station", now=now)  # the same name, another CA
    members, _skipped = nodes(d)
    return {"dir": d, "other": other, "acl": write_acl(d, members)}


def tls(d: Path, name: str, ca: Path | None = None) -> TlsFiles:
    return TlsFiles(str((ca or d) / "ca.pem"), str(d / f"{name}.pem"), str(d / f"{name}.key"))


def client(ep: str, files: TlsFiles | None, *, ca_only: str | None = None) -> ClientSession:
    """A client session with ``files`` as given (not checked first: an attacker's)."""
    cfg = session_config(connect=[ep], tls=files)
    if ca_only is not None:  # TLS, the CA to check the router with, no certificate of its own
        cfg.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(ca_only))
    return ClientSession(cfg, [ep])


def plain_client(ep: str) -> ClientSession:
    return ClientSession(session_config(connect=[ep]), [ep])


@pytest.mark.processes
@pytest.mark.timeout(180)
def test_the_router_refuses_strangers_and_an_agent_commanding_and_says_so_once(tmp_path: Path) -> None:
    pki = make_pki(tmp_path)
    d = pki["dir"]
    port = free_port("tcp")
    ep = f"tls/127.0.0.1:{port}"
    r1 = tls(d, "r1")
    router = Child(
        [
            *("router", "--listen", ep, "--tls-ca", r1.ca, "--tls-cert", r1.cert, "--tls-key", r1.key),
            *("--acl", str(pki["acl"]), "--json", "--report-every", "0"),
        ],
        name="router",
    )
    sessions: list[Any] = []
    try:
        ready = json.loads(router.wait_lines(1, DEADLINE)[0])
        assert ready["event"] == "ready" and ready["tls"] is True and ready["acl"] == str(pki["acl"])
        got: list[tuple[str, bytes]] = []
        lock = threading.Lock()

        def on(sample: Any) -> None:
            with lock:
                got.append((str(sample.key_expr), sample.payload.to_bytes()))

        agent2 = open_session(connect=[ep], tls=tls(d, "agent2"))
        sessions.append(agent2)
        for key in ("swarm/agent2", "swarm/agent2/command"):
            agent2.declare_subscriber(key, on)
        wait_until(lambda: agent2.opened, "agent2 connected to the router", DEADLINE, children=[router])
        station = open_session(connect=[ep], tls=tls(d, "gcs1"))
        sessions.append(station)
        wait_until(lambda: station.opened, "the station connected", DEADLINE, children=[router])
        good = encode(Command(255, 1, 2, CommandKind.ARM))

        def arrived() -> bool:  # a client's first puts may race the route to agent2
            with lock:
                if ("swarm/agent2/command", good) in got:
                    return True
            station.put("swarm/agent2/command", good)
            return False

        wait_until(arrived, "the station's Command at agent2", DEADLINE, 0.2, children=[router])

        forged = encode(Command(255, 66, 2, CommandKind.TAKEOFF, alt=10.0))
        attackers = {
            "no certificate": client(ep, None, ca_only=r1.ca),
            "plain TCP": plain_client(f"tcp/127.0.0.1:{port}"),
            "another CA": client(ep, tls(pki["other"], "gcs1", ca=d)),
            "expired": client(ep, tls(d, "old")),
            "agent1": client(ep, tls(d, "agent1")),
        }
        sessions += attackers.values()
        wait_until(lambda: attackers["agent1"].opened, "agent1 connected", DEADLINE, children=[router])
        time.sleep(1.0)  # the refused ones tried several times meanwhile (every second)
        for _ in range(3):
            for s in attackers.values():
                s.put("swarm/agent2/command", forged)
            time.sleep(0.3)

        def refused() -> list[dict[str, Any]]:
            return json_events(router.lines, "refused")

        want = [
            {"by": "tls", "why": "no client certificate"},
            {"by": "tls", "why": "a certificate of another CA, or forged (bad signature)"},
            {"by": "tls", "why": "an expired certificate"},
            {"by": "tls", "why": "not TLS (a plain TCP client?)"},
            {"by": "acl", "who": "agent1", "what": "put", "flow": "ingress", "key": "swarm/agent2/command"},
        ]
        wait_until(
            lambda: all({"event": "refused", **w} in refused() for w in want),
            "each refusal said",
            DEADLINE,
            children=[router],
            detail=refused,
        )
        assert [a for a, s in attackers.items() if s.opened] == ["agent1"]  # the rest never got in
        with lock:
            at_agent2 = [(k, decode(p)) for k, p in got if p != good]
        assert at_agent2 == [], f"forged commands reached agent2: {at_agent2}"
        for s in sessions:
            s.close()
        sessions.clear()
        router.proc.terminate()
        assert router.proc.wait(DEADLINE) == 0
        router.stop()
        # each kind said once, however often it came; every one counted
        said = [{k: v for k, v in e.items() if k != "event"} for e in refused()]
        assert all(w in said for w in want) and len(said) == len({str(x) for x in said}), said
        final = json_events(router.lines, "refusals")[-1]
        counts = {(c["by"], c.get("why") or c.get("key")): c["count"] for c in final["counts"]}
        assert counts[("acl", "swarm/agent2/command")] == 3, final
        for why in ("no client certificate", "an expired certificate"):
            assert counts[("tls", why)] >= 2, final  # tried again and again: counted, not said again
        assert final["total"] == sum(c["count"] for c in final["counts"])
        assert not [e for e in router.errors if "Traceback" in e], router.errors
    finally:
        for s in sessions:
            s.close()
        router.stop()


def test_a_node_refuses_to_start_on_files_it_would_be_refused_for(tmp_path: Path) -> None:
    pki = make_pki(tmp_path)
    d = pki["dir"]
    ep = f"tls/127.0.0.1:{free_port('tcp')}"
    cases = [
        (tls(d, "old"), "old.pem: expired"),
        (tls(pki["other"], "gcs1", ca=d), "gcs1.pem: not signed by"),
        (
            TlsFiles(str(d / "ca.pem"), str(d / "agent1.pem"), str(d / "agent2.key")),
            "agent2.key is not the key of",
        ),
        (
            TlsFiles(str(d / "ca.pem"), str(d / "agent1.pem"), str(d / "agent1.key"), name="agent2"),
            "its own keys",
        ),
        (
            TlsFiles(str(d / "ca.pem"), str(d / "gcs1.pem"), str(d / "gcs1.key"), role="agent"),
            "role 'station', but this node is 'agent'",
        ),
        (
            TlsFiles(str(d / "nope.pem"), str(d / "agent1.pem"), str(d / "agent1.key")),
            "no such certificate file",
        ),
    ]
    for files, why in cases:
        with pytest.raises(CertError, match=why):
            open_session(connect=[ep], tls=files)
    (d / "agent1.key").chmod(0o640)
    with pytest.raises(CertError, match="mode 0640: readable by its group; fix: chmod 600"):
        open_session(connect=[ep], tls=tls(d, "agent1"))
