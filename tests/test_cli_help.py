"""Every option of every ``swarm`` subcommand has help text (issue 18).

The parsers are found by running each command's ``--help`` (and each bench area's,
each sub-command's) and collecting every :class:`argparse.ArgumentParser` built on
the way; the test then walks their actions. No process is started.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
from collections.abc import Iterator

import pytest

from swarm.cli import COMMANDS
from swarm.cli.commands.bench import AREAS

_SKIP = (argparse._HelpAction, argparse._SubParsersAction, argparse._VersionAction)  # noqa: SLF001 (argparse keeps its actions private)


@contextlib.contextmanager
def _collect() -> Iterator[list[argparse.ArgumentParser]]:
    made: list[argparse.ArgumentParser] = []
    real = argparse.ArgumentParser.parse_known_args

    def spy(self: argparse.ArgumentParser, *args: object, **kw: object) -> object:
        made.append(self)
        for act in self._actions:
            if isinstance(act, argparse._SubParsersAction):  # noqa: SLF001 (argparse keeps its actions private)
                made.extend(act.choices.values())
        return real(self, *args, **kw)  # type: ignore[arg-type]

    argparse.ArgumentParser.parse_known_args = spy  # type: ignore[method-assign]
    try:
        yield made
    finally:
        argparse.ArgumentParser.parse_known_args = real  # type: ignore[method-assign]


def _parsers(command: str, argv: list[str]) -> list[argparse.ArgumentParser]:
    module = importlib.import_module(f"swarm.cli.commands.{COMMANDS[command][0]}")
    with _collect() as made, contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
        code = module.main(argv)
        assert code in (0, None), f"swarm {command} {' '.join(argv)} exited {code}"
    assert made, f"swarm {command}: no parser seen"
    return made


CASES = [(c, ["--help"]) for c in COMMANDS] + [("bench", [area, "--help"]) for area in AREAS]


@pytest.mark.parametrize(("command", "argv"), CASES, ids=[f"{c}-{'-'.join(a)}" for c, a in CASES])
def test_every_option_has_help(command: str, argv: list[str]) -> None:
    missing = [
        f"{p.prog}: {'/'.join(act.option_strings) or act.dest}"
        for p in _parsers(command, argv)
        for act in p._actions  # noqa: SLF001 (argparse keeps its actions private)
        if not isinstance(act, _SKIP) and not (act.help and act.help.strip())
    ]
    assert not missing, "options without help: " + ", ".join(missing)
