"""``swarm router``: a Zenoh router, so ground stations on different machines meet.

Theory of operation
-------------------
Stations on radios join one Zenoh network over IP (``swarm gcs --radio ...
--zenoh-connect tcp/ROUTER:7447``): each connects to a router, and routers to each
other (``--connect``), Zenoh's own routing carries the stations' ``gcs/...`` key space
between them (README, "Several radios and stations"). This command is a Zenoh session
in router mode that takes messages of at most 2 MiB (a station's envelope is at most 1
MiB; Zenoh's own bound is 1 GiB): Eclipse's ``zenohd`` does the same job in the field
(``zenohd -l tcp/0.0.0.0:7447`` with ``transport.link.rx.max_message_size`` set so in its
configuration). It prints one ready line (``--json``:
``{"event": "ready", "listen", "connect", "zid"}``), then runs until SIGINT (exit 130)
or SIGTERM (exit 0). A bad endpoint or a port in use: one line, exit 2.
"""

from __future__ import annotations

import argparse

from swarm.cli.util import StopFlag, UsageError, guarded, parser, print_json
from swarm.errors import TransportError

PROG = "swarm router"
MAX_MESSAGE = 2 * 1024 * 1024


def build_parser() -> argparse.ArgumentParser:
    p = parser(
        PROG,
        "A Zenoh router for stations on different machines (swarm gcs --radio ... "
        "--zenoh-connect tcp/THIS_HOST:7447); zenohd does the same.",
    )
    p.add_argument(
        "--listen",
        nargs="+",
        required=True,
        metavar="EP",
        help="Zenoh endpoints to listen on (tcp/0.0.0.0:7447 for every address)",
    )
    p.add_argument("--connect", nargs="+", default=[], metavar="EP", help="other routers to connect to")
    p.add_argument("--json", action="store_true", help="a JSON ready line")
    return p


def open_router(listen: list[str], connect: list[str]) -> object:
    """A Zenoh session in router mode. Raises TransportError (bad endpoint, port in use)."""
    import zenoh

    from swarm.runtime.transport import session_config, zenoh_config_message, zenoh_open_message

    cfg = session_config(listen, connect)
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


@guarded(PROG)
def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    stop = StopFlag().install()
    try:
        return _serve(a, stop)
    finally:
        stop.restore()


def _serve(a: argparse.Namespace, stop: StopFlag) -> int:
    """The router until ``stop`` (one line and exit 2 if its endpoints will not open)."""
    try:
        session = open_router(a.listen, a.connect)
    except TransportError as exc:
        raise UsageError(str(exc)) from None
    try:
        zid = str(session.info.zid())  # type: ignore[attr-defined]
        if a.json:
            print_json({"event": "ready", "listen": a.listen, "connect": a.connect, "zid": zid})
        else:
            print(f"router {zid} listen={','.join(a.listen)} ready", flush=True)
        stop.wait()
    finally:
        session.close()  # type: ignore[attr-defined]
    return stop.exit_code()
