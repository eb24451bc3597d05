"""Sphinx configuration of the documentation site (`make docs`; built strictly in `make test`).

Pages are Markdown (MyST). The command pages are generated at every build from the
commands' own parsers (each ``swarm.cli.commands.<module>.build_parser``), so they cannot
drift from ``swarm <command> --help``. The figures page is generated the same way from
the benchmarks' JSON output recorded in docs/figures/ (``tools/record_figures.py``): no
figure is copied by hand. docs/decisions/0001-docs-site.md says why Sphinx.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from swarm.cli import COMMANDS

project = "uav-swarm"
author = "the uav-swarm authors"
extensions = ["myst_parser", "sphinxarg.ext", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
html_theme = "furo"
html_title = "uav-swarm"
myst_heading_anchors = 3
nitpicky = True
# the API page documents the public entry points; their docstrings and signatures name
# internal and standard-library classes the site has no page for (no network at build
# time for intersphinx): those stay plain text. Every other reference (a page, a
# section, a command) must resolve.
nitpick_ignore_regex = [(r"py:.*", r".*")]
autodoc_typehints = "description"
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


def _cell(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "**no**"
    if value is None:
        return "none"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list):
        return ", ".join(_cell(v) for v in value)
    return str(value).replace("|", "\\|").replace("\n", " ")


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    """Scalars (and lists of scalars) by dotted key; lists of objects left out."""
    out: dict[str, Any] = {}
    if isinstance(value, dict):
        for k, v in value.items():
            out.update(_flat(v, f"{prefix}{k}."))
    elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        pass  # a table of its own
    else:
        out[prefix.rstrip(".")] = value
    return out


def _tables(value: Any, prefix: str = "") -> list[tuple[str, list[dict[str, Any]]]]:
    """Every list of objects inside ``value``, by dotted key, each row flattened."""
    found: list[tuple[str, list[dict[str, Any]]]] = []
    if isinstance(value, dict):
        for k, v in value.items():
            found += _tables(v, f"{prefix}{k}.")
    elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        found.append((prefix.rstrip("."), [_flat(v) for v in value]))
    return found


def _table(header: list[str], rows: list[list[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return [*lines, ""]


def figures_markdown(records: list[dict[str, Any]]) -> str:
    """The figures page from recorded bench output (``tools/record_figures.py``)."""
    out = [
        "# Figures",
        "",
        "What the benchmarks measured, rendered at every build from their own JSON output",
        "(`swarm bench AREA --json`), recorded in `docs/figures/` by `tools/record_figures.py`",
        "with the machine, its load and the commit: no figure here is copied by hand. A",
        "target a bench checks itself is in its *targets* table (**no**: missed). The",
        "figures' history, with the context of each change, is on the page",
        "[Figures: the history](figures-history.md).",
        "",
    ]
    if not records:
        out += ["No figures recorded yet: `tools/record_figures.py AREA...`.", ""]
    for r in sorted(records, key=lambda r: str(r["area"])):
        m = r["machine"]
        out += [
            f"## {r['area']}",
            "",
            f"`{r['command']}`, recorded {r['recorded'].replace('T', ' ')} on {m['system']} with "
            f"{m['cpus']} CPUs (load {m['load_1m_before']} before, {m['load_1m_after']} after), "
            f"commit `{r['commit']}`, {r['took_s']:g} s.",
            "",
        ]
        result = dict(r["result"])
        targets = result.pop("targets", None)
        if isinstance(targets, dict) and targets:
            out += ["Targets:", ""]
            out += _table(["target", "met"], [[k, v] for k, v in _flat(targets).items()])
        # dicts of scalars with the same keys (sizes by message, figures by case): one
        # table with a column each; everything else flattened into figure | value
        groups: dict[tuple[str, ...], list[str]] = {}
        for k, v in result.items():
            if isinstance(v, dict) and len(v) > 1 and not any(isinstance(x, dict | list) for x in v.values()):
                groups.setdefault(tuple(v), []).append(k)
        matrices = {k for keys, names in groups.items() if len(names) > 1 or len(keys) > 5 for k in names}
        scalars = _flat({k: v for k, v in result.items() if k not in matrices})
        if scalars:
            out += _table(["figure", "value"], [[k, v] for k, v in scalars.items()])
        for keys, names in groups.items():
            if names[0] in matrices:
                out += _table(["", *names], [[key, *(result[n][key] for n in names)] for key in keys])
        for key, rows in _tables(result):
            cols: list[str] = []
            for row in rows:
                cols += [c for c in row if c not in cols]
            out += [f"`{key}`:", ""]
            out += _table(cols, [[row.get(c, "") for c in cols] for row in rows])
    return "\n".join(out)


def figures_page(app: Any) -> None:
    """docs/figures.md from every docs/figures/*.json."""
    folder = Path(app.srcdir) / "figures"
    records = [json.loads(p.read_text(encoding="utf-8")) for p in sorted(folder.glob("*.json"))]
    _write(Path(app.srcdir) / "figures.md", figures_markdown(records))


def setup(app: Any) -> None:
    app.connect("builder-inited", command_pages)
    app.connect("builder-inited", figures_page)
