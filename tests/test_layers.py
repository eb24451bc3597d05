"""The import contracts (pyproject.toml, ``[tool.importlinter]``; ``make test`` runs
``lint-imports``) hold for the tree, and catch what they are there to catch: an
upward import, and a pure core reaching for a clock, a thread or the radio."""

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
