"""Sphinx configuration of the documentation site (`make docs`; built strictly in `make test`).

Pages are Markdown (MyST). The command pages are generated at every build from the
commands' own parsers (each ``swarm.cli.commands.<module>.build_parser``), so they cannot
drift from ``swarm <command> --help``. docs/decisions/0001-docs-site.md says why Sphinx.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from swarm.cli import COMMANDS

project = "uav-swarm"
author = "the uav-swarm authors"
extensions = ["myst_parser", "sphinxarg.ext"]
html_theme = "furo"
html_title = "uav-swarm"
myst_heading_anchors = 3
nitpicky = True
exclude_patterns = ["_build"]
source_suffix = {".md": "markdown"}


def _write(path: Path, text: str) -> None:
    if not path.exists() or path.read_text(encoding="utf-8") != text:  # unchanged: not rebuilt
        path.write_text(text, encoding="utf-8")


def command_pages(app: Any) -> None:
    """docs/commands/: an index and one page per command, from ``swarm.cli.COMMANDS``."""
    out = Path(app.srcdir) / "commands"
    out.mkdir(exist_ok=True)
    index = [
        "# Commands",
        "",
        "One page per command of `swarm`, generated from the command's own parser: what",
        "`swarm <command> --help` prints, with every option.",
        "",
        "```{toctree}",
        ":maxdepth: 1",
        "",
    ]
    for name, (module, summary) in COMMANDS.items():
        index.append(name)
        _write(
            out / f"{name}.md",
            f"# swarm {name}\n\n{summary[0].upper()}{summary[1:]}.\n\n"
            f"```{{argparse}}\n:module: swarm.cli.commands.{module}\n:func: build_parser\n"
            f":prog: swarm {name}\n```\n",
        )
    index.append("```")
    _write(out / "index.md", "\n".join(index) + "\n")


def setup(app: Any) -> None:
    app.connect("builder-inited", command_pages)
