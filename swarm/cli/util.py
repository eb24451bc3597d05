"""Helpers shared by the subcommands: error reporting, signals, JSON output.

Every subcommand's ``main`` is wrapped by :func:`guarded` so that a user never sees a
traceback for an error the project raises on purpose: the message goes to stderr
and the exit code says what happened (1 failure, 2 bad usage or input, 130
interrupted). The guard knows the three error roots, one per package
(:class:`radios.errors.RadioError`, :class:`firmware_bridge.errors.BridgeError`,
:class:`swarm.errors.SwarmError`); :func:`exit_code` maps an error to its code in one
place. With ``swarm --log-level DEBUG`` the guard also logs the traceback it hides.

Logging: :func:`configure_logging` sends log lines to stderr as text or, with
``--log-format json``, as one JSON object a line (:class:`JsonLogFormatter`);
:func:`add_log_arguments` gives a long-running command its ``--log-level`` and
``--log-format`` and :func:`apply_log_arguments` acts on them once parsed.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from firmware_bridge.errors import BridgeError, ConnectError
from radios.errors import CaptureDamagedError, ConfigError, LinkOpenError, RadioError
from swarm.errors import CertError, SwarmError, TransportError

if TYPE_CHECKING:
    from swarm.runtime.options import NodeOptions, TlsFiles

log = logging.getLogger("swarm.cli")

EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class UsageError(SwarmError):
    """Bad command-line input discovered after argument parsing (exit code 2)."""


#: the errors every package raises on purpose: anything else is a bug (a traceback)
ERROR_ROOTS: tuple[type[Exception], ...] = (RadioError, BridgeError, SwarmError)
#: the kinds that mean the user's input is wrong (exit 2): a command-line value, a
#: parameter or key file, a link URL or missing device, a flight-controller URL or
#: port, a Zenoh endpoint, a certificate or access-control file, a capture that is
#: damaged or not a capture at all. A timeout among them (no heartbeat) is a failure
#: instead.
BAD_INPUT: tuple[type[Exception], ...] = (
    UsageError,
    ConfigError,
    CaptureDamagedError,
    LinkOpenError,
    ConnectError,
    TransportError,
    CertError,
)


def exit_code(exc: BaseException) -> int:
    """The exit code for an error of one of the :data:`ERROR_ROOTS` (2 bad input, else 1)."""
    if isinstance(exc, BAD_INPUT) and not isinstance(exc, TimeoutError):
        return EXIT_USAGE
    return EXIT_FAILURE


def capture_damage(exc: CaptureDamagedError) -> str:
    """The one line for a damaged capture; a file with no whole record is named as not
    a capture at all (a text file given by mistake)."""
    if exc.records == 0:
        return f"not a capture (.tlog), or damaged from its first byte: {exc}"
    return str(exc)


def guarded(prog: str) -> Callable[[Callable[[list[str] | None], int]], Callable[[list[str] | None], int]]:
    """Decorate a subcommand ``main`` so project errors print cleanly."""

    def wrap(fn: Callable[[list[str] | None], int]) -> Callable[[list[str] | None], int]:
        @functools.wraps(fn)
        def inner(argv: list[str] | None = None) -> int:
            try:
                return fn(argv)
            except KeyboardInterrupt:
                return EXIT_INTERRUPTED
            except ERROR_ROOTS as exc:
                print(f"{prog}: error: {exc}", file=sys.stderr, flush=True)
                log.debug("%s: %s", prog, type(exc).__name__, exc_info=True)  # the bug report's
                return exit_code(exc)
            except BrokenPipeError:
                return EXIT_FAILURE

        return inner

    return wrap


def parser(prog: str, description: str) -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog=prog, description=description)


# -- the node options every node command shares (agent, gcs) ----------------------


def add_node_arguments(p: argparse.ArgumentParser, *, title: str | None = None, radios: bool = False) -> Any:
    """Where a node meets the others (``--radio``, ``--zenoh-listen``, ``--zenoh-connect``
    in a group ``title`` if given, which is returned), its Zenoh TLS and access
    control (``--tls-ca``, ``--tls-cert``, ``--tls-key``, ``--zenoh-acl``), its signing
    key (``--key``) and ``--exit-on-radio-loss``. :func:`node_options` reads them back. ``radios``:
    ``--radio [NAME=]URL`` may be repeated (a list; the station's channels)."""
    where = p.add_argument_group(title) if title else p
    if radios:
        where.add_argument(
            "--radio",
            action="append",
            metavar="[NAME=]URL",
            help="radio link: serial device or emulator pty (DIR/radioK); repeat it for one "
            "radio per channel (NETID), named NAME (default net1, net2, ...)",
        )
    else:
        where.add_argument(
            "--radio", metavar="URL", help="radio link: serial device or emulator pty (DIR/radioK)"
        )
    for flag, what in (
        ("--zenoh-listen", "listen on (tcp/127.0.0.1:7447)"),
        ("--zenoh-connect", "connect to"),
    ):
        also = (
            ": the agents' (no --radio), other stations' (with --radio)" if radios else ", instead of a radio"
        )
        where.add_argument(flag, nargs="+", default=[], metavar="EP", help=f"Zenoh endpoints to {what}{also}")
    tls = p.add_argument_group(
        "Zenoh over IP: mutual TLS and access control (tls/ endpoints; swarm certs makes the files)"
    )
    tls.add_argument("--tls-ca", metavar="FILE", help="the swarm CA's certificate (ca.pem)")
    tls.add_argument(
        "--tls-cert", metavar="FILE", help="this node's certificate (NAME.pem; its name is --name)"
    )
    tls.add_argument("--tls-key", metavar="FILE", help="this node's private key (NAME.key, mode 0600)")
    tls.add_argument(
        "--zenoh-acl",
        metavar="FILE",
        help="Zenoh access control for the nodes that connect to --zenoh-listen (acl.json5)",
    )
    p.add_argument("--key", metavar="FILE", help="swarm signing key (32 bytes, 64 hex digits or passphrase)")
    p.add_argument(
        "--exit-on-radio-loss",
        action="store_true",
        help="exit 1 when the radio goes away, instead of waiting for it to come "
        "back (for a service manager that restarts the program)",
    )
    return where


def node_options(a: argparse.Namespace, who: str, *, others: str = "") -> NodeOptions:
    """The :class:`~swarm.runtime.options.NodeOptions` of :func:`add_node_arguments`'
    values; ``who`` names the node in a message ("an agent"), ``others`` lists the
    command's other ways in (", --replay CAPTURE").

    Raises:
        UsageError: no way in or two, or --exit-on-radio-loss without a radio.
    """
    from swarm.runtime.options import NodeOptions

    tls, acl = zenoh_security(a, "agent" if who == "an agent" else "station")
    try:
        node = NodeOptions(
            radio=a.radio,
            zenoh_listen=a.zenoh_listen,
            zenoh_connect=a.zenoh_connect,
            key_file=a.key,
            tls=tls,
            acl_file=acl,
        )
    except ValueError:
        raise UsageError(f"give one of --radio URL, --zenoh-listen/--zenoh-connect EP...{others}") from None
    if a.exit_on_radio_loss and not node.on_radio:
        raise UsageError(f"--exit-on-radio-loss is for {who} on a radio (--radio)")
    return node


def zenoh_security(a: argparse.Namespace, role: str) -> tuple[TlsFiles | None, str | None]:
    """The TLS files and ACL file of :func:`add_node_arguments`' values, for a node of
    ``role`` named ``a.name``, once the rules of :mod:`swarm.core.keyspace.endpoints` allow
    them: a ``tls/`` endpoint needs the three files, the files need ``tls/``
    endpoints only, an ACL needs TLS and a listen endpoint; ``--key`` with a plain
    endpoint beyond loopback is refused. The warnings (``--key`` on loopback, TLS
    listening without an ACL) are kept in ``a.zenoh_warnings`` (the doctor's lines):
    the node says them when its session opens, once every other check passed.

    Raises:
        UsageError: what the rules refuse.
    """
    from swarm.core.keyspace.endpoints import key_over_ip, tls_needed
    from swarm.runtime.options import TlsFiles

    endpoints = [*(a.zenoh_listen or []), *(a.zenoh_connect or [])]
    ca, cert, key = a.tls_ca, a.tls_cert, a.tls_key
    missing = tls_needed(endpoints, has_ca=bool(ca), has_cert=bool(cert), has_key=bool(key))
    if missing:
        raise UsageError(missing)
    if a.zenoh_acl is not None and not (ca and a.zenoh_listen):
        raise UsageError(
            "--zenoh-acl rules the nodes that connect to this one: it needs --zenoh-listen tls/... "
        )
    verdict = key_over_ip(endpoints, has_key=a.key is not None)
    if verdict is not None and verdict.level == "refuse":
        raise UsageError(verdict.text)
    warnings = [verdict.text] if verdict is not None else []
    if ca and a.zenoh_listen and a.zenoh_acl is None:
        warnings.append(
            f"warning: no --zenoh-acl: any certificate of the swarm's CA that connects to "
            f"{', '.join(a.zenoh_listen)} may publish anything (swarm certs writes acl.json5)"
        )
    a.zenoh_warnings = (
        warnings  # said when the session opens (swarm.runtime.keyspace.transport); the doctor's lines
    )
    tls = (
        TlsFiles(ca, cert, key, name=getattr(a, "name", None) or "", role=role)
        if ca and cert and key
        else None
    )
    return tls, a.zenoh_acl


def radio_loss_message(bridge: Any) -> str:
    """The one line for a radio lost for good (``bridge`` may be None)."""
    reason = getattr(bridge, "loss_reason", "")
    return "radio link lost" + (f": {reason}" if reason else "")


def exit_when_stopped(prog: str, node: Any, what: str) -> int:
    """A node (agent or station) stopped on its own: say why on stderr, exit 1."""
    bridge = getattr(node, "bridge", None)
    why = radio_loss_message(bridge) if bridge is not None and bridge.link_lost else f"{what} stopped"
    print(f"{prog}: error: {why}", file=sys.stderr)
    return EXIT_FAILURE


#: how long a ``--zenoh-connect`` node may have no peer before it says so, seconds
PEER_GRACE_S = 3.0


class PeerWatch:
    """Whether the ``--zenoh-connect`` peers are reached, as lines for the user: fed
    with "connected?" and ``now``, :meth:`update` returns the line to print or None.
    No peer for :data:`PEER_GRACE_S` (from the start or from a loss): say so once
    (Zenoh keeps retrying); a peer again after that: say it is connected."""

    def __init__(self, endpoints: list[str], now: float, grace: float = PEER_GRACE_S) -> None:
        self.where = ", ".join(endpoints)
        self.grace = grace
        self.connected = False
        self.warned = False
        self.alone_since = now

    def update(self, connected: bool, now: float) -> str | None:
        if connected and not self.connected:
            self.connected = True
            if self.warned:
                self.warned = False
                return f"connected to a Zenoh peer ({self.where})"
            return None
        if not connected and self.connected:
            self.connected, self.alone_since = False, now
        if not connected and not self.warned and now - self.alone_since >= self.grace:
            self.warned = True
            return f"warning: no Zenoh peer reachable at {self.where}; still trying"
        return None


def peer_watch(prog: str, a: argparse.Namespace, node: Any) -> Callable[[], None]:
    """A check to call every half second or so in a node command's loop: prints
    :class:`PeerWatch`'s lines on stderr. A no-op without ``--zenoh-connect``."""
    session = getattr(node, "session", None)
    if not getattr(a, "zenoh_connect", None) or session is None:
        return lambda: None
    from swarm.runtime.keyspace.transport import has_peer

    watch = PeerWatch(list(a.zenoh_connect), time.monotonic())

    def check() -> None:
        line = watch.update(has_peer(session), time.monotonic())
        if line is not None:
            print(f"{prog}: {line}", file=sys.stderr, flush=True)

    return check


class StopFlag:
    """A stop request set by SIGINT or SIGTERM (install from the main thread)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        self._previous: dict[int, Any] = {}

    def install(self) -> StopFlag:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def restore(self) -> None:
        """The handlers from before :meth:`install` (a command run in-process, e.g. by a
        test, leaves Ctrl-C as it found it)."""
        for sig, old in self._previous.items():
            signal.signal(sig, old)
        self._previous.clear()

    def _handler(self, signum: int, _frame: Any) -> None:
        self.signal = signum
        self.event.set()

    def exit_code(self) -> int:
        """How a command stopped by this flag exits: 130 after Ctrl-C (SIGINT), 0 after
        SIGTERM (a service manager's orderly stop, which systemd counts as success)."""
        return EXIT_INTERRUPTED if self.signal == signal.SIGINT else 0

    def is_set(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)


def print_json(obj: Any) -> None:
    print(json.dumps(obj, sort_keys=False), flush=True)


#: ``--log-level`` names, quietest last
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
#: ``--log-format`` names: text lines, or one JSON object a line
LOG_FORMATS = ("text", "json")
LOG_FORMAT = "%(asctime)s %(name)s %(levelname)s: %(message)s"


class JsonLogFormatter(logging.Formatter):
    """One JSON object a line: ``time`` (UTC, ISO 8601, milliseconds), ``level``,
    ``logger``, ``message``, and ``exc`` (the traceback) when there is one. Newlines in
    a message or a traceback are escaped, so a record is always exactly one line."""

    def format(self, record: logging.LogRecord) -> str:
        t = time.gmtime(record.created)
        obj: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", t) + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info:
            obj["exc"] = self.formatException(record.exc_info)
        elif record.exc_text:
            obj["exc"] = record.exc_text
        return json.dumps(obj, ensure_ascii=False)


def configure_logging(level: str, fmt: str = "text") -> None:
    """Send the project's loggers at ``level`` and above to stderr, one line each:
    ``fmt`` "text" (time, logger name, level, message) or "json"
    (:class:`JsonLogFormatter`). Replaces any earlier configuration."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonLogFormatter() if fmt == "json" else logging.Formatter(LOG_FORMAT))
    logging.basicConfig(level=level, handlers=[handler], force=True)


def add_log_arguments(p: argparse.ArgumentParser) -> None:
    """``--log-level`` and ``--log-format`` for a long-running command (agent, gcs,
    radio-emu, sim, demo); :func:`apply_log_arguments` acts on them."""
    g = p.add_argument_group("log lines (stderr)")
    g.add_argument(
        "--log-level",
        type=str.upper,
        choices=LOG_LEVELS,
        metavar="LEVEL",
        help=f"log lines at LEVEL and above ({', '.join(LOG_LEVELS)}); default: only "
        "warnings and errors, as bare lines",
    )
    g.add_argument(
        "--log-format",
        choices=LOG_FORMATS,
        help="text (time, logger, level, message) or json (one object a line: time, "
        "level, logger, message); default text",
    )


def apply_log_arguments(a: argparse.Namespace) -> None:
    """Configure logging as :func:`add_log_arguments`' values ask (WARNING when only a
    format is given); neither given: leave logging as it is."""
    level, fmt = getattr(a, "log_level", None), getattr(a, "log_format", None)
    if level is not None or fmt is not None:
        configure_logging(level or "WARNING", fmt or "text")
