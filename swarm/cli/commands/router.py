"""``swarm router``: a Zenoh router, so ground stations (and agents over IP) on different machines meet.

Theory of operation
-------------------
Stations on radios join one Zenoh network over IP (``swarm gcs --radio ...
--zenoh-connect tls/ROUTER:7447``): each connects to a router, and routers to each
other (``--connect``), Zenoh's own routing carries the stations' ``gcs/...`` key space
between them (docs/station.md, "Several radios and stations"). This command is a Zenoh session
in router mode that takes messages of at most 2 MiB (a station's envelope is at most 1
MiB; Zenoh's own bound is 1 GiB): Eclipse's ``zenohd`` does the same job in the field
(``zenohd -l tls/0.0.0.0:7447`` with ``transport.link.rx.max_message_size`` set so, and
the same TLS and access-control sections, in its configuration).

With ``--tls-ca/--tls-cert/--tls-key`` every link is mutual TLS (a node without a
certificate of the swarm's CA, or with an expired one, is refused at the handshake)
and with ``--acl FILE`` Zenoh's access control decides what each certificate may do
(``swarm certs`` makes all four; the rules: :mod:`swarm.core.keyspace.acl`). What the
router refuses is read from Zenoh's own log (:mod:`swarm.runtime.keyspace.logwatch`):
each kind of refusal is said once (``--json``: ``{"event": "refused", "by": "tls",
"why"}`` or ``{"event": "refused", "by": "acl", "who", "what", "flow", "key"}``) and
counted; the counts are printed every ``--report-every`` seconds when they changed
and when the router stops (``{"event": "refusals", "total", "counts": [...]}``).

It prints one ready line (``--json``: ``{"event": "ready", "listen", "connect", "zid",
"tls", "acl"}``), then runs until SIGINT (exit 130) or SIGTERM (exit 0). A bad endpoint,
a port in use, a bad certificate or ACL file: one line, exit 2. Plain TCP beyond
loopback, or TLS without an ACL, starts with one warning line.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from typing import TYPE_CHECKING, Any

from swarm.cli.util import StopFlag, UsageError, guarded, parser, print_json
from swarm.errors import TransportError

if TYPE_CHECKING:
    from swarm.core.keyspace.router_log import Refusal
    from swarm.runtime.options import TlsFiles

PROG = "swarm router"
MAX_MESSAGE = 2 * 1024 * 1024
log = logging.getLogger("swarm.cli")


def build_parser() -> argparse.ArgumentParser:
    p = parser(
        PROG,
        "A Zenoh router for stations (and agents over IP) on different machines (swarm gcs --radio ... "
        "--zenoh-connect tls/THIS_HOST:7447); zenohd does the same.",
    )
    p.add_argument(
        "--listen",
        nargs="+",
        required=True,
        metavar="EP",
        help="Zenoh endpoints to listen on (tls/0.0.0.0:7447 for every address)",
    )
    p.add_argument("--connect", nargs="+", default=[], metavar="EP", help="other routers to connect to")
    tls = p.add_argument_group("mutual TLS and access control (swarm certs makes the files)")
    tls.add_argument("--tls-ca", metavar="FILE", help="the swarm CA's certificate (ca.pem)")
    tls.add_argument("--tls-cert", metavar="FILE", help="this router's certificate (NAME.pem, role router)")
    tls.add_argument("--tls-key", metavar="FILE", help="this router's private key (NAME.key, mode 0600)")
    tls.add_argument(
        "--acl", metavar="FILE", help="Zenoh access control: what each certificate may do (acl.json5)"
    )
    p.add_argument(
        "--report-every",
        type=float,
        default=60.0,
        metavar="S",
        help="print the refusal counts every S seconds when they changed (default 60; 0: only at exit)",
    )
    p.add_argument("--json", action="store_true", help="JSON lines")
    return p


def open_router(
    listen: list[str], connect: list[str], tls: TlsFiles | None = None, acl: str | None = None
) -> object:
    """A Zenoh session in router mode. Raises TransportError (bad endpoint, port in use)
    or CertError (the TLS or ACL files)."""
    import zenoh

    from swarm.core.keyspace.zenoh_errors import zenoh_config_message, zenoh_open_message
    from swarm.runtime.keyspace.transport import session_config

    acl_text = None
    if tls is not None:
        from swarm.runtime.keyspace import tls as zenoh_tls

        zenoh_tls.check_tls(tls)
        acl_text = zenoh_tls.load_acl(acl) if acl is not None else None
    cfg = session_config(listen, connect, tls=tls, acl_text=acl_text)
    try:
        cfg.insert_json5("mode", '"router"')
        # Zenoh takes messages of up to 1 GiB by default: a sender's larger than this
        # (twice a station's largest envelope) close its own link, here, at the router
        cfg.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE))
    except Exception as exc:
        raise TransportError(zenoh_config_message(str(exc))) from exc
    try:
        return zenoh.open(cfg)
    except Exception as exc:
        raise TransportError(zenoh_open_message(str(exc), listen, connect)) from exc


def _tls(a: argparse.Namespace) -> TlsFiles | None:
    """The router's TLS files once the rules allow them (UsageError otherwise); its
    warnings (plain TCP beyond loopback, TLS without an ACL) in ``a.warnings``, said
    once it runs."""
    from swarm.core.keyspace.endpoints import CERTS_HINT, endpoint_kind, tls_needed
    from swarm.runtime.options import TlsFiles

    if not a.report_every >= 0:
        raise UsageError(f"--report-every {a.report_every}: seconds, 0 for only at exit")
    endpoints = [*a.listen, *a.connect]
    missing = tls_needed(endpoints, has_ca=bool(a.tls_ca), has_cert=bool(a.tls_cert), has_key=bool(a.tls_key))
    if missing:
        raise UsageError(missing)
    if a.acl is not None and not a.tls_ca:
        raise UsageError("--acl needs TLS (--tls-ca, --tls-cert, --tls-key): certificates name who is who")
    plain = [ep for ep in a.listen if endpoint_kind(ep) == "plain"]
    a.warnings = []
    if plain:
        a.warnings.append(
            f"warning: {', '.join(plain)} lets anyone who reaches it into the key space; {CERTS_HINT}"
        )
    if a.tls_ca and a.acl is None:
        a.warnings.append("warning: no --acl: any certificate of the swarm's CA may publish anything here")
    return TlsFiles(a.tls_ca, a.tls_cert, a.tls_key, role="router") if a.tls_ca else None


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    tls = _tls(a)
    stop = StopFlag().install()
    try:
        return _serve(a, tls, stop)
    finally:
        stop.restore()


class _Out:
    """The router's lines: ready, each kind of refusal once, the counts."""

    def __init__(self, json: bool) -> None:
        self.json = json
        self.reported = 0

    def refused(self, r: Refusal, first: bool) -> None:
        if not first:
            return
        if self.json:
            print_json({"event": "refused", **r.as_dict()})
        else:
            print(f"router: {r.text()}; the same again is counted", flush=True)

    def warning(self, text: str) -> None:
        print(f"{PROG}: zenoh: {text}", file=sys.stderr, flush=True)

    def counts(self, total: int, counts: list[dict[str, object]], *, final: bool = False) -> None:
        if total == self.reported and not final:
            return
        self.reported = total
        if self.json:
            print_json({"event": "refusals", "total": total, "counts": counts})
            return
        parts = [
            f"{c['count']} {c['why']}"
            if c["by"] == "tls"
            else f"{c['count']} {c['who']} {c['what']} {c['key']}"
            for c in counts
        ]
        print(f"router: {total} refused" + (f" ({'; '.join(parts)})" if parts else ""), flush=True)


def _serve(a: argparse.Namespace, tls: TlsFiles | None, stop: StopFlag) -> int:
    """The router until ``stop`` (one line and exit 2 if its endpoints will not open)."""
    out = _Out(a.json)
    watch: Any = None
    if tls is not None:
        from swarm.runtime.keyspace.tls import check_tls

        check_tls(tls)  # before Zenoh's log is taken over: a bad file is one plain line
        from swarm.runtime.keyspace.logwatch import LogWatch

        watch = LogWatch(out.refused, out.warning).start()
    try:
        session = open_router(a.listen, a.connect, tls, a.acl)
    except TransportError as exc:
        raise UsageError(str(exc)) from None
    for text in a.warnings:
        log.warning("%s", text)
    try:
        zid = str(session.info.zid())  # type: ignore[attr-defined]
        if a.json:
            print_json(
                {
                    "event": "ready",
                    "listen": a.listen,
                    "connect": a.connect,
                    "zid": zid,
                    "tls": tls is not None,
                    "acl": a.acl,
                }
            )
        else:
            extra = (" tls" if tls else "") + (f" acl={a.acl}" if a.acl else "")
            print(f"router {zid} listen={','.join(a.listen)}{extra} ready", flush=True)
        period = a.report_every or None
        next_report = time.monotonic() + (period or 0)
        while not stop.wait(0.5):
            if watch is not None and period and time.monotonic() >= next_report:
                next_report += period
                out.counts(*watch.counts())
    finally:
        session.close()  # type: ignore[attr-defined]
        if watch is not None:
            time.sleep(0.1)  # the log's last lines
            out.counts(*watch.counts(), final=True)
    return stop.exit_code()
