"""Issue 27's IP edge without processes: the rules a node's endpoints and files are held
to, the access-control rules (checked by Zenoh's own parser), the reading of Zenoh's
log, ``swarm certs`` and the doctor's verdicts on certificates.

The log lines are Zenoh 1.10.2's own, as ``swarm router`` read them from a real router
refusing real clients (colours included)."""

from __future__ import annotations

import json
import logging
import stat
import time
from pathlib import Path

import pytest
import zenoh
from net_helpers import free_port

from swarm.cli.commands import agent as agent_cmd
from swarm.cli.commands import certs
from swarm.cli.commands import doctor as doctor_cmd
from swarm.cli.configfile import read_arguments
from swarm.cli.util import UsageError, node_options
from swarm.core.doctor.tls import SOON_S, AclFacts, CertFacts, TlsFacts, acl_check, tls_checks
from swarm.core.keyspace.acl import Node, acl
from swarm.core.keyspace.endpoints import endpoint_kind, key_over_ip, tls_needed
from swarm.core.keyspace.router_log import ANONYMOUS, Passed, Refusal, RefusalBook, ZenohLogReader
from swarm.errors import TransportError
from swarm.runtime.keyspace.pki import issue, make_ca
from swarm.runtime.keyspace.tls_probe import acl_facts, tls_facts
from swarm.runtime.keyspace.transport import open_session

# -- endpoints and the key -------------------------------------------------------------


@pytest.mark.parametrize(
    ("ep", "kind"),
    [
        ("tls/10.0.0.5:7447", "tls"),
        ("quic/[::]:7447", "tls"),
        ("tcp/127.0.0.1:7447", "local"),
        ("tcp/127.4.5.6:1", "local"),
        ("tcp/[::1]:7447", "local"),
        ("tcp/localhost:7447", "local"),
        ("udp/127.0.0.1:7447", "local"),
        ("unixsock-stream//tmp/z.sock", "local"),
        ("tcp/0.0.0.0:7447", "plain"),
        ("tcp/[::]:7447", "plain"),
        ("tcp/10.0.0.5:7447", "plain"),
        ("udp/192.168.1.2:7447#iface=wlan0", "plain"),
        ("ws/gcs.local:8000", "plain"),
        ("tcp/localhost.evil.example:7447", "plain"),
    ],
)
def test_endpoint_kind(ep: str, kind: str) -> None:
    assert endpoint_kind(ep) == kind


def test_the_key_over_plain_tcp_refuses_beyond_loopback_and_warns_on_it() -> None:
    assert key_over_ip(["tcp/10.0.0.5:7447"], has_key=False) is None  # no key: nothing promised
    assert key_over_ip(["tls/10.0.0.5:7447"], has_key=True) is None
    v = key_over_ip(["tcp/127.0.0.1:7447", "tcp/0.0.0.0:7448"], has_key=True)
    assert v is not None and v.level == "refuse"
    assert v.text.startswith(
        "--key signs radio frames, not Zenoh over IP: tcp/0.0.0.0:7448 is open to anyone"
    )
    v = key_over_ip(["tcp/127.0.0.1:7447"], has_key=True)
    assert v is not None and v.level == "warn" and "every user of this machine" in v.text


def test_tls_endpoints_need_all_three_files_and_only_tls_endpoints() -> None:
    assert tls_needed(["tcp/10.0.0.5:1"], has_ca=False, has_cert=False, has_key=False) is None
    assert tls_needed(["tls/10.0.0.5:1"], has_ca=True, has_cert=True, has_key=True) is None
    missing = tls_needed(["tls/10.0.0.5:1"], has_ca=True, has_cert=False, has_key=False)
    assert missing is not None and "needs --tls-cert, --tls-key" in missing
    assert "are for tls/ endpoints" in str(
        tls_needed(["tcp/10.0.0.5:1"], has_ca=True, has_cert=True, has_key=True)
    )
    bypass = tls_needed(["tls/10.0.0.5:1", "tcp/127.0.0.1:2"], has_ca=True, has_cert=True, has_key=True)
    assert bypass is not None and "tcp/127.0.0.1:2 would bypass" in bypass


def agent_args(*argv: str) -> object:
    return read_arguments(agent_cmd.build_parser(), ["--name", "agent1", "--id", "1", *argv])


def test_the_agent_refuses_its_key_on_plain_tcp_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    key = tmp_path / "swarm.key"
    key.write_bytes(bytes(32))
    key.chmod(0o600)
    code = agent_cmd.main(
        ["--name", "a1", "--id", "1", "--key", str(key), "--zenoh-connect", "tcp/10.0.0.5:7447"]
    )
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert err.startswith(
        "swarm agent: error: --key signs radio frames, not Zenoh over IP: tcp/10.0.0.5:7447"
    )
    assert "swarm certs" in err


def test_loopback_with_the_key_warns_once_and_tls_flags_are_checked(caplog: pytest.LogCaptureFixture) -> None:
    a = agent_args("--key", "k", "--zenoh-connect", "tcp/127.0.0.1:7447")
    node = node_options(a, "an agent")  # type: ignore[arg-type]
    warnings = a.zenoh_warnings  # type: ignore[attr-defined]
    assert node.tls is None and len(warnings) == 1
    assert warnings[0].startswith("warning: --key does not cover Zenoh: tcp/127.0.0.1:7447 is")
    # said once the node's session opens (after every other check passed), not before
    with caplog.at_level(logging.WARNING, logger="swarm.runtime.keyspace.transport"):
        session = open_session(listen=[f"tcp/127.0.0.1:{free_port()}"], signed=True)
        session.close()
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith("warning: --key does not cover Zenoh: tcp/127.0.0.1:")
    with pytest.raises(TransportError, match=r"--key signs radio frames, not Zenoh over IP: tcp/0\.0\.0\.0:"):
        open_session(listen=[f"tcp/0.0.0.0:{free_port()}"], signed=True)  # the Python API refuses too
    with pytest.raises(UsageError, match="needs --tls-ca, --tls-cert, --tls-key"):
        node_options(agent_args("--zenoh-connect", "tls/10.0.0.5:7447"), "an agent")  # type: ignore[arg-type]
    with pytest.raises(UsageError, match="needs --zenoh-listen"):
        node_options(
            agent_args(  # type: ignore[arg-type]
                *("--zenoh-connect", "tls/10.0.0.5:7447", "--zenoh-acl", "a.json5"),
                *("--tls-ca", "ca.pem", "--tls-cert", "agent1.pem", "--tls-key", "agent1.key"),
            ),
            "an agent",
        )
    node = node_options(
        agent_args(  # type: ignore[arg-type]
            *("--key", "k", "--zenoh-connect", "tls/10.0.0.5:7447"),
            *("--tls-ca", "ca.pem", "--tls-cert", "agent1.pem", "--tls-key", "agent1.key"),
        ),
        "an agent",
    )
    assert node.tls is not None and (node.tls.name, node.tls.role, node.tls.cert) == (
        "agent1",
        "agent",
        "agent1.pem",
    )


# -- the access-control rules ------------------------------------------------------------


def test_the_acl_grants_each_role_its_keys_and_zenoh_accepts_it() -> None:
    section = acl([Node("agent1", "agent"), Node("gcs1", "station"), Node("r1", "router")])
    assert section["enabled"] is True and section["default_permission"] == "deny"
    rules = {r["id"]: r for r in section["rules"]}
    put = rules["agent-agent1-put"]
    assert put["flows"] == ["ingress"] and put["messages"] == ["put"]
    assert set(put["key_exprs"]) == {
        "swarm/advertize",
        "swarm/GSAdvertize",
        "swarm/*",
        "swarm/agent1/pose",
        "swarm/agent1/state",
    }
    assert not any("command" in k or k.startswith("gcs") for k in put["key_exprs"])
    assert "swarm/*/command" in rules["station-gcs1-put"]["key_exprs"]
    assert {p["id"]: p["subjects"] for p in section["policies"]}["routers"] == ["router-r1"]
    assert {s["id"]: s["cert_common_names"] for s in section["subjects"]} == {
        "agent-agent1": ["agent1"],
        "station-gcs1": ["gcs1"],
        "router-r1": ["r1"],
    }
    cfg = zenoh.Config()
    cfg.insert_json5("access_control", json.dumps(section))  # Zenoh's own parser takes it
    with pytest.raises(ValueError, match="named twice"):
        acl([Node("a1", "agent"), Node("a1", "station")])
    with pytest.raises(ValueError, match="role"):
        Node("a1", "admin")


# -- Zenoh's log ---------------------------------------------------------------------------

AC = "zenoh::net::routing::interceptor::access_control"
T = "2026-11-28T19:48:14.346694Z"
SUBJECT = "Interface(lo)+CertCommonName(agent1)+Transport(Tls)+d3f59f65"


def trace(thread: str, msg: str) -> str:
    dim, end = "\x1b[2m", "\x1b[0m"
    return f"{dim}{T}{end} \x1b[35mTRACE{end}  rx-0 ThreadId({thread}) {dim}{AC}{end}{dim}:{end} {msg}"


def test_the_log_reader_finds_real_attempts_only() -> None:
    r = ZenohLogReader()
    # what agent1 would be allowed on a key it declared: not attempts
    assert r.line(trace("09", "ACL (ingress): caching permissions for `swarm` ...")) is None
    for action in ("Query", "Reply", "Put", "Delete", "Declare/Undeclare Queryable"):
        assert (
            r.line(trace("09", f"d3f59f65 on {SUBJECT} is unauthorized to {action} (ingress) on swarm"))
            is None
        )
    assert (
        r.line(
            trace(
                "09",
                f"d3f59f65 on {SUBJECT} is authorized to Declare/Undeclare Subscriber (ingress) on swarm",
            )
        )
        is None
    )
    # an attempt on another thread, and the same again from the cache (its id only)
    first = r.line(
        trace("10", f"d3f59f65 on {SUBJECT} is unauthorized to Put (ingress) on swarm/agent2/command")
    )
    assert first == Refusal("acl", who="agent1", what="put", flow="ingress", key="swarm/agent2/command")
    again = r.line(
        trace("10", "Using cached result: d3f59f65 is unauthorized to Put (ingress) on swarm/agent2/command")
    )
    assert again == first
    assert (
        r.line(
            trace("10", "Using cached result: d3f59f65 is authorized to Put (ingress) on swarm/agent1/pose")
        )
        is None
    )
    anon = r.line(
        trace("11", "0abc on Interface(lo)+Transport(Tcp)+0abc is unauthorized to Put (ingress) on swarm/x")
    )
    assert isinstance(anon, Refusal) and anon.who == ANONYMOUS
    tls = f"{T}  WARN acc-0 ThreadId(05) zenoh_link_tls::unicast: "
    hint = ". Hint: increase the system open file limit."
    assert r.line(tls + "peer sent no certificates" + hint) == Refusal("tls", why="no client certificate")
    assert r.line(tls + "invalid peer certificate: UnknownIssuer" + hint) == Refusal(
        "tls", why="a certificate of another CA (unknown issuer)"
    )
    expired = "invalid peer certificate: certificate expired: verification time 1795895296 (UNIX), but ..."
    assert r.line(tls + expired + hint) == Refusal("tls", why="an expired certificate")
    assert r.line(tls + "received corrupt message of type InvalidContentType") == Refusal(
        "tls", why="not TLS (a plain TCP client?)"
    )
    assert r.line(tls + "received fatal alert: UnknownCA") == Refusal(
        "tls", why="a client without the swarm's CA (UnknownCA)"
    )
    other = r.line(f"{T}  WARN ThreadId(01) zenoh::net::runtime::orchestrator: Unable to connect to tls/x:1!")
    assert other == Passed("WARN", "zenoh::net::runtime::orchestrator: Unable to connect to tls/x:1!")
    assert (
        r.line(f"{T} DEBUG ThreadId(01) zenoh_link_tls::utils: Loading user-generated certificates.") is None
    )
    assert r.line("router 1234 ready") is None
    book = RefusalBook()
    assert [book.note(first), book.note(again), book.note(Refusal("tls", why="x"))] == [True, False, True]
    assert book.total == 3 and {"by": "acl", "who": "agent1", "what": "put", "flow": "ingress",
                                 "key": "swarm/agent2/command", "count": 2} in book.counts()  # fmt: skip


# -- swarm certs and the doctor's verdicts -------------------------------------------------


def test_swarm_certs_makes_keys_0600_never_overwrites_and_rewrites_the_acl(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = str(tmp_path)
    assert certs.main(["node", d, "agent1", "--role", "agent"]) == 2  # no CA yet
    assert "ca.key: no such private key file" in capsys.readouterr().err
    assert certs.main(["ca", d]) == 0
    assert certs.main(["node", d, "r1", "--role", "router", "--host", "10.0.0.5", "--host", "gcs.local"]) == 0
    assert certs.main(["node", d, "agent1", "--role", "agent"]) == 0
    out = capsys.readouterr().out
    assert "wrote " + str(tmp_path / "acl.json5") + ": agents agent1; stations -; routers r1" in out
    for name in ("ca", "r1", "agent1"):
        assert stat.S_IMODE((tmp_path / f"{name}.key").stat().st_mode) == 0o600
    before = (tmp_path / "agent1.pem").read_bytes()
    assert certs.main(["node", d, "agent1", "--role", "station"]) == 2
    assert "agent1.key exists: never overwritten" in capsys.readouterr().err
    assert (tmp_path / "agent1.pem").read_bytes() == before
    assert certs.main(["ca", d]) == 2
    facts = tls_facts(f"{d}/ca.pem", f"{d}/r1.pem", f"{d}/r1.key", expect_role="router")
    assert facts.cert.hosts == ("r1", "gcs.local", "10.0.0.5") and facts.signed_by_ca and facts.key_matches
    assert all(c.status == "pass" for c in tls_checks(facts, time.time())), tls_checks(facts, time.time())
    assert acl_check(acl_facts(f"{d}/acl.json5")).seen.endswith("2 certificates named, default deny")


def test_the_doctor_judges_expiry_mode_key_and_ca(tmp_path: Path) -> None:
    now = 1_800_000_000.0
    ca = CertFacts(
        "ca.pem", name="uav-swarm CA", is_ca=True, not_before=now - 10, not_after=now + 3650 * 86400
    )
    cert = CertFacts("a1.pem", name="a1", role="agent", not_before=now - 10, not_after=now + 365 * 86400)
    good = TlsFacts(
        ca, cert, "a1.key", key_mode=0o100600, signed_by_ca=True, key_matches=True, expect_name="a1"
    )
    assert [c.status for c in tls_checks(good, now)] == ["pass"] * 5

    def status(f: TlsFacts, t: float = now) -> dict[str, str]:
        return {c.name: c.status for c in tls_checks(f, t)}

    ending = CertFacts("a1.pem", name="a1", role="agent", not_after=now + SOON_S - 86400)
    soon = TlsFacts(ca, ending, "a1.key", key_mode=0o600, signed_by_ca=True, key_matches=True)
    assert status(soon)["tls cert"] == "warn"
    assert status(good, now + 366 * 86400)["tls cert"] == "fail"  # expired
    assert status(good, now - 3600)["tls cert"] == "fail"  # a clock behind
    assert (
        status(TlsFacts(ca, cert, "a1.key", key_mode=0o644, signed_by_ca=True, key_matches=True))[
            "tls key mode"
        ]
        == "fail"
    )
    assert status(TlsFacts(ca, cert, "a1.key", key_mode=0o600, signed_by_ca=True))["tls key"] == "fail"
    assert status(TlsFacts(ca, cert, "a1.key", key_mode=0o600, key_matches=True))["tls cert"] == "fail"
    assert status(TlsFacts(ca, cert, "k", 0, 0o600, True, True, expect_name="a2"))["tls name"] == "fail"
    assert (
        status(TlsFacts(CertFacts("ca.pem", error="ca.pem: no such certificate file"), cert, "k"))["tls ca"]
        == "fail"
    )
    assert acl_check(AclFacts("acl", enabled=True, default="allow")).status == "warn"
    assert (
        acl_check(AclFacts("acl", error="acl: Zenoh refuses it: missing field `key_exprs`")).status == "fail"
    )


def test_swarm_doctor_reports_an_expired_certificate_as_a_failure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    now = time.time()
    make_ca(tmp_path, now=now)
    issue(tmp_path, "agent1", "agent", now=now, valid_from=now - 3 * 86400, days=1)
    d = str(tmp_path)
    code = doctor_cmd.main(
        [
            *("--name", "agent1", "--zenoh-connect", "tls/127.0.0.1:7447", "--json"),
            *("--tls-ca", f"{d}/ca.pem", "--tls-cert", f"{d}/agent1.pem", "--tls-key", f"{d}/agent1.key"),
        ]
    )
    report = json.loads(capsys.readouterr().out)
    assert code == 1 and report["ok"] is False
    checks = {c["name"]: c for c in report["checks"]}
    assert checks["tls cert"]["status"] == "fail" and "expired" in checks["tls cert"]["seen"]
    assert checks["tls key"]["status"] == "pass" and checks["tls name"]["status"] == "pass"
