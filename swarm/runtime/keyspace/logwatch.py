"""Zenoh's own log, read inside the process: what a router refused, counted and told once.

Theory of operation
-------------------
zenoh-python writes Zenoh's log (Rust's ``tracing``) to file descriptor 1, and tells
of refused TLS handshakes and access-control denials only there
(:mod:`swarm.core.keyspace.router_log`). :meth:`LogWatch.start` turns that on at the levels
that carry them (:data:`DIRECTIVES`: warnings, the TLS link's refusals, the access
control's decisions) and reads it: descriptor 1 becomes a pipe read by a thread,
and ``sys.stdout`` moves to a copy of the real standard output, so the program's own
lines go where they always went and Zenoh's never reach the user raw. Each line is
read by :class:`~swarm.core.keyspace.router_log.ZenohLogReader`; a refusal is counted in a
:class:`~swarm.core.keyspace.router_log.RefusalBook` and handed to ``on_refusal(refusal,
first)``, any other warning to ``on_warning(text)`` once per distinct text.

``RUST_LOG`` is ignored here (it would change what is counted). Zenoh's logging is
set up once per process, so one watch per process: the router's
(``swarm router``), started just before its session opens. The access control's
decisions are ``TRACE`` lines, one or two per message the router passes: measured
in the docs/security.md ("Zenoh over IP"). Zenoh's threads wait on a full pipe, so the reader
must keep up: the pipe holds 1 MiB of lines for a burst.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import sys
import threading
from collections.abc import Callable

from swarm.core.keyspace.router_log import Passed, Refusal, RefusalBook, ZenohLogReader

log = logging.getLogger(__name__)

DIRECTIVES = "warn,zenoh_link_tls=warn,zenoh::net::routing::interceptor::access_control=trace"
MAX_WARNINGS = 1000  # distinct warning texts remembered (and each shown once)
PIPE_BYTES = 1 << 20  # the log pipe's buffer: Zenoh's threads wait when it is full


class LogWatch:
    """See the module docstring."""

    def __init__(
        self,
        on_refusal: Callable[[Refusal, bool], None],
        on_warning: Callable[[str], None] = lambda text: None,
    ) -> None:
        self.on_refusal, self.on_warning = on_refusal, on_warning
        self.reader = ZenohLogReader()
        self.book = RefusalBook()
        self.lock = threading.Lock()
        self.lines = 0
        self._warned: set[str] = set()
        self._thread: threading.Thread | None = None

    def start(self) -> LogWatch:
        import zenoh

        sys.stdout.flush()
        read_fd, write_fd = os.pipe()
        with contextlib.suppress(OSError, AttributeError):  # Linux: room for a burst of lines
            fcntl.fcntl(write_fd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
        real = os.dup(1)
        os.dup2(write_fd, 1)
        os.close(write_fd)
        sys.stdout = os.fdopen(real, "w", buffering=1, encoding="utf-8", closefd=True)
        self._thread = threading.Thread(target=self._read, args=(read_fd,), name="zenoh-log", daemon=True)
        self._thread.start()
        os.environ.pop("RUST_LOG", None)
        try:
            zenoh.init_log_from_env_or(DIRECTIVES)
        except Exception:  # already set up in this process: counted as it is
            log.debug("zenoh log: already initialised", exc_info=True)
        return self

    def _read(self, fd: int) -> None:
        with os.fdopen(fd, "r", encoding="utf-8", errors="replace") as pipe:
            for raw in pipe:
                try:
                    self.feed(raw)
                except Exception:  # a line we cannot read must not stop the reading
                    log.debug("zenoh log: unreadable line", exc_info=True)

    def feed(self, raw: str) -> None:
        """One line of Zenoh's log (public for tests)."""
        with self.lock:
            self.lines += 1
            got = self.reader.line(raw)
            first = self.book.note(got) if isinstance(got, Refusal) else False
            fresh = (
                isinstance(got, Passed) and got.text not in self._warned and len(self._warned) < MAX_WARNINGS
            )
            if fresh and isinstance(got, Passed):
                self._warned.add(got.text)
        if isinstance(got, Refusal):
            self.on_refusal(got, first)
        elif fresh and isinstance(got, Passed):
            self.on_warning(got.text)

    def counts(self) -> tuple[int, list[dict[str, object]]]:
        with self.lock:
            return self.book.total, self.book.counts()


__all__ = ["DIRECTIVES", "LogWatch"]
