"""The import contracts (pyproject.toml, ``[tool.importlinter]``; ``make test`` runs
``lint-imports``) hold for the tree, and catch what they are there to catch: an
upward import (between layers, and between the feature folders inside one), and a
pure core reaching for a clock, a thread or the radio."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = str(Path(sys.executable).with_name("lint-imports"))


def lint(tree: Path, *contracts: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    only = [a for c in contracts for a in ("--contract", c)]
    return subprocess.run(
        [LINT, str(tree / "pyproject.toml"), "--no-cache", "--no-logo", *only],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    for pkg in ("radios", "firmware_bridge", "swarm"):
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "static"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def plant(path: Path, line: str) -> None:
    text = path.read_text()
    head, sep, rest = text.partition("from __future__ import annotations\n")
    assert sep, path
    path.write_text(head + sep + line + "\n" + rest)


def test_the_tree_keeps_its_contracts(tree: Path) -> None:
    p = lint(tree)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    assert "0 broken" in p.stdout


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        (
            "swarm/core/election/protocol.py",
            "import swarm.runtime.agent.live",
            "pure-core",
        ),  # core -> runtime
        ("swarm/core/agent/node.py", "import time", "pure-core"),  # a clock in the core
        ("swarm/core/flight/pilot.py", "import threading", "pure-core"),
        ("swarm/core/wire/messages.py", "import radios.link", "pure-core"),  # I/O through another package
        ("swarm/core/wire/tunnel.py", "import swarm.sim.tracks", "swarm-layers"),  # upward, inside swarm
        ("swarm/runtime/agent/live.py", "import swarm.cli.demo", "swarm-layers"),  # runtime -> commands
        (
            "swarm/sim/simulate.py",
            "import swarm.runtime.bridge.radio_bridge",
            "swarm-layers",
        ),  # siblings stay apart
        ("swarm/core/station/core.py", "import swarm.core.agent.node", "core-features"),  # station -> agent
        ("swarm/core/agent/node.py", "import swarm.core.station.alerts", "core-features"),  # agent -> station
        (
            "swarm/core/wire/codes.py",
            "import swarm.core.election.profiles",
            "core-features",
        ),  # wire -> election
        ("swarm/core/bridge/names.py", "import swarm.core.flight.geofence", "core-edges"),
        ("swarm/runtime/keyspace/transport.py", "import swarm.runtime.bridge.stats", "runtime-features"),
        ("swarm/runtime/bridge/rx.py", "import swarm.runtime.station.fleet", "runtime-features"),
        ("radios/mavlink.py", "import swarm.core.wire.messages", "packages"),  # radios knows no swarm
        ("firmware_bridge/modes.py", "import swarm.errors", "packages"),
        ("firmware_bridge/telemetry.py", "import time", "driver-pure-core"),  # a clock in the driver's core
        ("radios/link.py", "import firmware_bridge.errors", "packages"),
        ("radios/replay.py", "import radios.link", "link-backends"),  # the old import circle
        ("firmware_bridge/sim/flavour.py", "import time", "vehicle-sim-core"),  # a clock in the simulator
    ],
)
def test_a_planted_import_breaks_its_contract(tree: Path, module: str, line: str, contract: str) -> None:
    assert lint(tree, contract).returncode == 0  # kept before
    plant(tree / module, line)
    p = lint(tree, contract)
    assert p.returncode != 0, f"{line} in {module} was not caught:\n{p.stdout[-2000:]}"
    assert "BROKEN" in p.stdout and "1 broken" in p.stdout, p.stdout[-2000:]


def test_no_import_circle_inside_swarm_but_the_noted_ones() -> None:
    """Inside ``swarm/``: no module imports itself back when the program runs, and the
    circles of type annotations alone (imports under ``TYPE_CHECKING``) are the two that
    their modules' docstrings explain: the election's strategies and its state, the
    simulator and its host streams."""
    import grimp

    def circles(graph: grimp.ImportGraph) -> list[set[str]]:
        """The strongly connected groups of more than one module (Tarjan's algorithm)."""
        mods = {m for m in graph.modules if m.startswith("swarm.")}
        edges = {m: sorted(graph.find_modules_directly_imported_by(m) & mods) for m in mods}
        index: dict[str, int] = {}
        low: dict[str, int] = {}
        stack: list[str] = []
        found: list[set[str]] = []

        def visit(v: str) -> None:
            index[v] = low[v] = len(index)
            stack.append(v)
            for w in edges[v]:
                if w not in index:
                    visit(w)
                    low[v] = min(low[v], low[w])
                elif w in stack:
                    low[v] = min(low[v], index[w])
            if low[v] == index[v]:
                ring = set()
                while True:
                    w = stack.pop()
                    ring.add(w)
                    if w == v:
                        break
                if len(ring) > 1:
                    found.append(ring)

        for m in sorted(mods):
            if m not in index:
                visit(m)
        return found

    assert circles(grimp.build_graph("swarm", exclude_type_checking_imports=True)) == []
    noted = [
        {"swarm.core.election." + m for m in ("protocol", "rules", "tdm", "caps", "liveness")},
        {"swarm.sim.simulate", "swarm.sim.hoststream"},
    ]
    typed = circles(grimp.build_graph("swarm"))
    assert sorted(map(sorted, typed)) == sorted(map(sorted, noted)), typed
    for ring in noted:  # the note is in a module docstring of the ring
        docs = [(ROOT / (m.replace(".", "/") + ".py")).read_text().split('"""')[1] for m in ring]
        assert any("TYPE_CHECKING" in d for d in docs), ring


def test_no_module_or_test_imports_another_modules_private_name() -> None:
    """``from M import _name`` across modules (a name ``M`` keeps to itself) is refused
    in the packages, the tests and the tools: what another module needs is public under
    its own name. (The linter's private-member rule covers ``obj._name``.)"""
    import ast

    ours = ("radios", "firmware_bridge", "swarm")
    found = []
    for folder in (*ours, "tests", "tools"):
        for f in sorted((ROOT / folder).rglob("*.py")):
            if "vendor" in f.parts:
                continue
            for node in ast.walk(ast.parse(f.read_text(), str(f))):
                if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in ours:
                    found += [
                        f"{f.relative_to(ROOT)}:{node.lineno} {node.module}.{a.name}"
                        for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")
                    ]
    assert found == [], found


def test_the_packages_never_import_the_projects_tools() -> None:
    """``tools/`` (the project's own benches and scripts) is not in the wheel: nothing
    the wheel carries may import it."""
    import ast

    found = []
    for folder in ("radios", "firmware_bridge", "swarm"):
        for f in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(f.read_text(), str(f))):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
                if isinstance(node, ast.ImportFrom) and node.module:
                    names = [node.module]
                found += [
                    f"{f.relative_to(ROOT)}:{node.lineno} {n}" for n in names if n.split(".")[0] == "tools"
                ]
    assert found == [], found
