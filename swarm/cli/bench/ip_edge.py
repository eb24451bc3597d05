"""``swarm bench ip-edge``: stations on two machines joined by a router over mutual TLS with
access control, and an attacker on every listener.

Theory of operation
-------------------
Two "machines": this host (A) and, when this process may make one (root, iproute2), a
network namespace (B) joined to A by a veth pair on a /24 of 10.200.0.0/16, so B
reaches A's router over a real interface, not loopback; otherwise B is this host too
(``machines: loopback``, said in the figures). The swarm's CA, the router's
certificate (with A's address) and each station's are made with ``swarm certs``' code;
the ACL by its rules. Then, all real processes:

* on A: ``swarm router --listen tls/A:PORT`` with the certificates and ``--acl``; one
  emulator per channel (the air: ptys are files, any namespace opens them);
  channel 0's two agents and station ``st0`` (``--zenoh-connect tls/A:PORT``);
* on B: channel 1's two agents and station ``st1``, likewise.

Measured: how long until st0's API lists both channels' swarms, led (B's over the
router); a command from st0 to one of B's agents (carried by st1 on its radio, the
agent's own answer back) and a FOLLOW to B's swarm; then an attacker (A's side) on
every socket every process listens on (:mod:`swarm.cli.bench.ip_attack`: plain, TLS
without a certificate), and with real certificates: another CA's station, an expired
agent's, and a valid agent's asking st1's command queryable (only stations may). What
the router refused is its own count (``swarm router``'s lines); none of the stations'
own traffic may be among it. Then the router restarts (SIGTERM, down 2 s, started
again on the same endpoint): how long until st0 shows st1 gone, and back once the
router is (the stations' Zenoh clients reconnect by themselves), and a command across
again. Last, what the access control costs a router (:func:`router_load`: it reads
Zenoh's decisions from its log at ``TRACE``).
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from radios.ports import free_port
from swarm.cli.bench.ip_attack import attack, describe, listeners
from swarm.cli.bench.scale_procs import http, led_swarms, poll
from swarm.cli.procs import Child, cpu_seconds, json_events, start_emulator

AGENTS = 2  # per channel
DEADLINE = 90.0


class MachineChild(Child):
    """:class:`~swarm.cli.procs.Child` run inside network namespace ``ns`` (None: here)."""

    def __init__(self, argv: Sequence[str], *, name: str, ns: str | None) -> None:
        self.name = name
        prefix = ["ip", "netns", "exec", ns] if ns else []
        self.argv = [*prefix, sys.executable, "-m", "swarm.cli", *argv]
        self.proc = subprocess.Popen(
            self.argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
        )
        self.lines: list[str] = []
        self.errors: list[str] = []
        self._cond = threading.Condition()
        self._threads = [
            threading.Thread(target=self._pump, args=(self.proc.stdout, self.lines), daemon=True),
            threading.Thread(target=self._pump, args=(self.proc.stderr, self.errors), daemon=True),
        ]
        for t in self._threads:
            t.start()


def _ip(*args: str, ns: str | None = None) -> None:
    cmd = ["ip", "netns", "exec", ns, "ip", *args] if ns else ["ip", *args]
    subprocess.run(cmd, check=True, capture_output=True, timeout=20)


@contextlib.contextmanager
def second_machine() -> Iterator[tuple[str | None, str, str]]:
    """``(namespace, A's address, B's address)``: a namespace B joined to this host by
    a veth pair, or ``(None, 127.0.0.1, 127.0.0.1)`` when none can be made here."""
    tag = os.getpid() % 10000
    ns, va, vb = f"swarm-ipe{tag}", f"ipea{tag}", f"ipeb{tag}"
    net = f"10.200.{os.getpid() % 250}"
    try:
        _ip("netns", "add", ns)
    except (OSError, subprocess.SubprocessError):
        yield None, "127.0.0.1", "127.0.0.1"
        return
    try:
        _ip("link", "add", va, "type", "veth", "peer", "name", vb)
        _ip("link", "set", vb, "netns", ns)
        _ip("addr", "add", f"{net}.1/24", "dev", va)
        _ip("link", "set", va, "up")
        _ip("addr", "add", f"{net}.2/24", "dev", vb, ns=ns)
        _ip("link", "set", vb, "up", ns=ns)
        _ip("link", "set", "lo", "up", ns=ns)
        yield ns, f"{net}.1", f"{net}.2"
    finally:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            _ip("link", "del", va)
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            _ip("netns", "del", ns)


def make_pki(d: Path, router_host: str) -> dict[str, Path]:
    """The swarm's CA and certificates (router, st0, st1; an agent's, an expired
    agent's) in ``d``, another CA's station in ``d/other``, the ACL."""
    from swarm.runtime.keyspace.pki import issue, make_ca, nodes, write_acl

    now = time.time()
    make_ca(d, now=now)
    issue(d, "r1", "router", now=now, hosts=[router_host])
    for name, role in (("st0", "station"), ("st1", "station"), ("a1", "agent")):
        issue(d, name, role, now=now)
    issue(d, "old", "agent", now=now, valid_from=now - 10 * 86400, days=2)
    other = d / "other"
    other.mkdir()
    make_ca(other, now=now)
    issue(other, "st1", "station", now=now)
    members, _ = nodes(d)
    return {"dir": d, "other": other, "acl": write_acl(d, members)}


def _tls_flags(d: Path, name: str) -> list[str]:
    return [
        "--tls-ca",
        str(d / "ca.pem"),
        "--tls-cert",
        str(d / f"{name}.pem"),
        "--tls-key",
        str(d / f"{name}.key"),
    ]


def _cert_attacks(ep: str, pki: dict[str, Path]) -> dict[str, dict[str, Any]]:
    """Real certificates used wrongly: another CA's station, an expired agent, a valid
    agent asking a station's command queryable. What each reached."""
    from swarm.runtime.keyspace.transport import ClientSession, session_config
    from swarm.runtime.options import TlsFiles

    d = pki["dir"]
    cases = {
        "another CA's station": TlsFiles(
            str(d / "ca.pem"), str(pki["other"] / "st1.pem"), str(pki["other"] / "st1.key")
        ),
        "expired agent": TlsFiles(str(d / "ca.pem"), str(d / "old.pem"), str(d / "old.key")),
        "agent asking a station": TlsFiles(str(d / "ca.pem"), str(d / "a1.pem"), str(d / "a1.key")),
    }
    out: dict[str, dict[str, Any]] = {}
    for label, files in cases.items():
        s = ClientSession(session_config(connect=[ep], tls=files), [ep])
        heard: list[str] = []
        try:
            s.declare_subscriber("**", lambda sample, heard=heard: heard.append(str(sample.key_expr)))
            end = time.monotonic() + 3.0
            replies = 0
            while time.monotonic() < end:
                with contextlib.suppress(Exception):
                    replies += sum(1 for _ in s.get("gcs/st1/command", payload=b"{}", timeout=0.5))
                time.sleep(0.3)
            out[label] = {"opened": s.opened, "received": len(heard), "replies": replies}
        finally:
            s.close()
    return out


LOAD_AGENTS, LOAD_HZ = 10, 4.0


def _wait_open(sessions: Sequence[Any]) -> None:
    poll(lambda: all(s.opened for s in sessions), "the load's clients connected", 30)


def router_load(d: Path, seconds: float) -> dict[str, Any]:
    """What the access control costs the router: :data:`LOAD_AGENTS` agents (clients
    with their certificates) each putting its pose at :data:`LOAD_HZ` Hz and hearing
    everyone's, for ``seconds``, through a router without and with ``--acl`` (whose
    decisions it reads from Zenoh's log): the router's CPU, in % of one core."""
    from swarm.runtime.keyspace.pki import issue, make_ca, nodes, write_acl
    from swarm.runtime.keyspace.transport import open_session
    from swarm.runtime.options import TlsFiles

    now = time.time()
    d.mkdir()
    make_ca(d, now=now)
    issue(d, "r1", "router", now=now, hosts=["127.0.0.1"])
    for i in range(LOAD_AGENTS):
        issue(d, f"a{i}", "agent", now=now)
    acl = write_acl(d, nodes(d)[0])
    out: dict[str, Any] = {"agents": LOAD_AGENTS, "pose_hz": LOAD_HZ, "seconds": seconds}
    for label, extra in (("no_acl", []), ("acl", ["--acl", str(acl)])):
        ep = f"tls/127.0.0.1:{free_port('tcp')}"
        router = Child(
            ["router", "--listen", ep, *_tls_flags(d, "r1"), *extra, "--report-every", "0"], name="router"
        )
        sessions: list[Any] = []
        try:
            router.wait_lines(1, 30)
            heard = [0]

            def count(_sample: Any, heard: list[int] = heard) -> None:
                heard[0] += 1

            for i in range(LOAD_AGENTS):
                s = open_session(
                    connect=[ep], tls=TlsFiles(str(d / "ca.pem"), str(d / f"a{i}.pem"), str(d / f"a{i}.key"))
                )
                sessions.append(s)
                s.declare_subscriber("swarm/*/pose", count)
            _wait_open(sessions)
            time.sleep(1.0)
            cpu0, heard[0], t0 = cpu_seconds(router.proc.pid), 0, time.monotonic()
            payload = bytes(20)  # a PoseReport's size
            while time.monotonic() - t0 < seconds:
                for i, s in enumerate(sessions):
                    s.put(f"swarm/a{i}/pose", payload)
                time.sleep(1.0 / LOAD_HZ)
            wall = time.monotonic() - t0
            out[label] = {
                "router_cpu_pct": round(100 * (cpu_seconds(router.proc.pid) - cpu0) / wall, 2),
                "delivered_per_s": round(heard[0] / wall),
            }
        finally:
            for s in sessions:
                s.close()
            router.stop(grace=5)
    return out


def run(quick: bool = False, directory: Path | None = None, load_s: float | None = None) -> dict[str, Any]:
    """The figures (see the module docstring); ``directory`` for the files (a temporary
    folder by default); ``load_s`` how long the router's load runs (0: not at all;
    default 20 s, 5 s quick)."""
    import tempfile

    with contextlib.ExitStack() as stack:
        d = directory if directory is not None else Path(stack.enter_context(tempfile.TemporaryDirectory()))
        with second_machine() as (ns, a_addr, b_addr):
            figures = _run(d, ns, a_addr, b_addr)
        seconds = (5.0 if quick else 20.0) if load_s is None else load_s
        if seconds > 0:
            figures["router_load"] = router_load(d / "load", seconds)
        return figures


def _run(d: Path, ns: str | None, a_addr: str, b_addr: str) -> dict[str, Any]:
    pki_dir = d / "pki"
    pki_dir.mkdir()
    pki = make_pki(pki_dir, a_addr)
    key = d / "swarm.key"
    key.write_bytes(os.urandom(32))
    key.chmod(0o600)
    ep = f"tls/{a_addr}:{free_port('tcp')}"
    children: list[Child] = []
    try:
        router = MachineChild(
            [
                *("router", "--listen", ep, *_tls_flags(pki_dir, "r1")),
                *("--acl", str(pki["acl"]), "--json", "--report-every", "0"),
            ],
            name="router",
            ns=None,
        )
        children.append(router)
        router.wait_lines(1, 30)
        t_router = time.monotonic()
        stations: list[Child] = []
        agents: dict[str, Child] = {}
        urls: list[str] = []
        for n, where in enumerate((None, ns)):
            cd = d / f"ch{n}"
            cd.mkdir()
            emu, links = start_emulator(AGENTS + 1, cd, "--netid", str(25 + n), "--seed", str(16 + n))
            children.append(emu)
            for i in range(AGENTS):
                aid = n * 20 + i + 1
                argv = [
                    "agent",
                    "--name",
                    f"a{aid}",
                    "--id",
                    str(aid),
                    "--radio",
                    links[i + 1],
                    "--key",
                    str(key),
                ]
                argv += ["--profile", "fast", "--slots", str(AGENTS + 1), "--json"]
                agents[f"a{aid}"] = MachineChild(argv, name=f"a{aid}", ns=where)
                children.append(agents[f"a{aid}"])
            argv = ["gcs", "--name", f"st{n}", "--radio", f"c{n}={links[0]}", "--zenoh-connect", ep]
            argv += [*_tls_flags(pki_dir, f"st{n}"), "--key", str(key)]
            argv += ["--http", f"127.0.0.1:{free_port('tcp')}", "--tiles", "none", "--json"]
            station = MachineChild(argv, name=f"st{n}", ns=where)
            children.append(station)
            stations.append(station)
        urls += [json.loads(x.wait_lines(1, 60)[0])["url"] for x in stations]
        t_ready = time.monotonic()

        def state() -> dict[str, Any]:
            for ch in children:
                if ch.proc.poll() is not None:
                    raise RuntimeError(f"{ch.name} exited {ch.proc.returncode}: {ch.errors[-3:]}")
            return dict(http(urls[0] + "api/state")[1])

        # both swarms led, and every agent of the other machine listed: a swarm is led
        # before its station has heard each member (a busy machine showed one missing)
        poll(
            lambda: (
                len(led_swarms(s := state())) == 2
                and len([a for a in s["agents"] if a.get("station") == "st1"]) == AGENTS
            ),
            "st0 to list both channels' swarms, led, and the other machine's agents",
            DEADLINE,
        )
        listing_s = round(time.monotonic() - t_ready, 2)
        s = state()
        remote = sorted(a["id"] for a in s["agents"] if a.get("station") == "st1")
        st_arm, body_arm = http(urls[0] + "api/command", {"target": 22, "kind": "arm"})
        leader_b = next(a["leader"] for a in s["agents"] if a.get("station") == "st1")
        _st, body_f = http(
            urls[0] + "api/command", {"target": "swarm", "swarm": leader_b, "kind": "follow", "heading": 90}
        )
        follow = [r["result"] for r in body_f.get("results", []) if r.get("agent") == leader_b]
        # the attacker: every socket of every process (A's side reaches A's and the router's)
        pids = {ch.name: ch.proc.pid for ch in children if ch.name != "radio emulator"}
        found = {name: listeners(pid) for name, pid in pids.items()}
        agent_names = {n: int(n[1:]) for n in agents}
        reachable = [
            lst for name in found for lst in found[name] if name == "router" or name in ("st0", "a1", "a2")
        ]
        reports = [attack(lst, agent_names, duration_s=1.5, rounds=3) for lst in reachable]
        certs = _cert_attacks(ep, pki)
        # and the swarm still works after it all
        still = sorted(led_swarms(state()))
        cpu = round(cpu_seconds(router.proc.pid), 2)
        run_s = round(time.monotonic() - t_router, 1)
        # a router restart: SIGTERM (its counts are its last line), down 2 s, started again
        router.stop(grace=10)
        children.remove(router)  # stopped on purpose: state() must not take it for a crash
        t_down = time.monotonic()
        poll(lambda: not _alive(state(), "st1"), "st0 to show st1 gone", DEADLINE)
        gone_s = round(time.monotonic() - t_down, 2)
        time.sleep(max(0.0, 2.0 - (time.monotonic() - t_down)))
        again = MachineChild(router.argv[3:], name="router again", ns=None)
        children.append(again)
        again.wait_lines(1, 30)
        t_up = time.monotonic()
        poll(lambda: _alive(state(), "st1") and len(led_swarms(state())) == 2, "st1 back on st0", DEADLINE)
        back_s = round(time.monotonic() - t_up, 2)
        st_again, body_again = http(urls[0] + "api/command", {"target": 22, "kind": "arm"})
        restart = {
            "down_s": round(t_up - t_down, 1),
            "st1_shown_gone_s": gone_s,
            "st1_back_s": back_s,
            "command_across_after": [
                f"agent {r['agent']} {r['result']} via {r.get('station')}"
                for r in body_again.get("results", [])
            ],
            "status": st_again,
        }
        for ch in reversed(children):
            ch.stop(grace=5)
        refused = json_events(router.lines, "refusals")
        counts = refused[-1]["counts"] if refused else []
        legit = [
            _refusal_label(c) for c in counts if c.get("by") == "acl" and c.get("who") in ("st0", "st1", "r1")
        ]
        by_station_b = [e for e in json_events(stations[1].lines) if e.get("event") == "ready"]
        figures: dict[str, Any] = {
            "machines": "netns" if ns else "loopback",
            "router": ep,
            "station_b": f"{b_addr} ({'network namespace ' + ns if ns else 'this host'})",
            "listing_s": listing_s,
            "remote_agents": remote,
            "command_across": {
                "status": st_arm,
                "results": [
                    f"agent {r['agent']} {r['result']} ({r['reason']}) via {r.get('station')}"
                    for r in body_arm.get("results", [])
                ],
            },
            "follow_across": follow,
            "led_after_attacks": still,
            "listeners": {name: describe(v) for name, v in found.items()},
            # for people and programs alike: one line per listener, per kind of refusal
            "ip_attacks": {
                r.listener: f"Zenoh sessions opened {len(r.opened)}, samples received {len(r.received)}"
                for r in reports
            },
            "cert_attacks": certs,
            "router_refusals": {_refusal_label(c): c["count"] for c in counts},
            "legit_refused": legit,
            "router_cpu_s": cpu,
            "router_run_s": run_s,
            "station_b_ready": bool(by_station_b),
            "router_restart": restart,
        }
        figures["ok"] = _ok(figures)
        return figures
    finally:
        for c in reversed(children):
            c.stop(grace=5)


def _alive(state: dict[str, Any], station: str) -> bool:
    return any(x["name"] == station and x["alive"] for x in state.get("stations", []))


def _refusal_label(c: dict[str, Any]) -> str:
    if c["by"] == "tls":
        return f"tls: {c['why']}"
    return f"acl: {c['who']} {c['what']} ({c['flow']}) {c['key']}"


def _ok(f: dict[str, Any]) -> bool:
    results = f["command_across"]["results"]
    return (
        f["remote_agents"] == [21, 22]
        and len(results) == 1
        and results[0].endswith("via st1")
        and f["follow_across"] == ["ACCEPTED"]
        and f["led_after_attacks"] == ["c0", "c1"]
        and all(v.endswith("opened 0, samples received 0") for v in f["ip_attacks"].values())
        and not any(c["received"] or c["replies"] for c in f["cert_attacks"].values())
        and f["legit_refused"] == []
        and f["router_restart"]["command_across_after"] == ["agent 22 FAILED via st1"]
    )


__all__ = ["MachineChild", "make_pki", "run", "second_machine"]
