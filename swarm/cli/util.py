"""Helpers shared by the subcommands: error reporting, signals, JSON output.

Every subcommand's ``main`` is wrapped by :func:`guarded` so that a user never sees a
traceback for an error the project raises on purpose: the message goes to stderr
and the exit code says what happened (1 failure, 2 bad usage or input, 130
interrupted).
"""

from __future__ import annotations

import argparse
import functools
import json
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

from radios.errors import ConfigError, LinkOpenError, RadioError

EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class UsageError(Exception):
    """Bad command-line input discovered after argument parsing (exit code 2)."""


def guarded(prog: str) -> Callable[[Callable[[list[str] | None], int]], Callable[[list[str] | None], int]]:
    """Decorate a subcommand ``main`` so project errors print cleanly."""

    def wrap(fn: Callable[[list[str] | None], int]) -> Callable[[list[str] | None], int]:
        @functools.wraps(fn)
        def inner(argv: list[str] | None = None) -> int:
            try:
                return fn(argv)
            except KeyboardInterrupt:
                return EXIT_INTERRUPTED
            except (UsageError, ConfigError, LinkOpenError) as exc:
                print(f"{prog}: error: {exc}", file=sys.stderr)
                return EXIT_USAGE
            except RadioError as exc:
                print(f"{prog}: error: {exc}", file=sys.stderr)
                return EXIT_FAILURE
            except BrokenPipeError:
                return EXIT_FAILURE

        return inner

    return wrap


def parser(prog: str, description: str) -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog=prog, description=description)


class StopFlag:
    """A stop request set by SIGINT or SIGTERM (install from the main thread)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None

    def install(self) -> StopFlag:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._handler)
        return self

    def _handler(self, signum: int, _frame: Any) -> None:
        self.signal = signum
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)


def print_json(obj: Any) -> None:
    print(json.dumps(obj, sort_keys=False), flush=True)
