"""The README's `swarm radio-config` examples run as written against the emulator they start.

The test reads the first ``sh`` block of README.md's radio-config section: its first
line starts `swarm radio-emu` in the background, the rest are the examples. Only the
directory changes (``/tmp/radios`` -> a fresh temporary one); the lines run in bash as
they stand, in separate processes like an operator's, and must all exit 0.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from net_helpers import wait_until

from radios.sik.guard import parse_expected

pytestmark = pytest.mark.processes  # an emulator process and radio-config processes on ptys

README = Path(__file__).resolve().parent.parent / "README.md"
RUN_DEADLINE = 240.0  # the examples take about 35 s on an idle machine


def readme_block() -> list[str]:
    """The lines of the first ``sh`` block after the radio-config heading."""
    section = README.read_text(encoding="utf-8").split("### `swarm radio-config`", 1)[1]
    block = section.split("```sh\n", 1)[1].split("```", 1)[0]
    return block.splitlines()


def test_the_block_starts_the_emulator_and_keeps_the_old_example_out() -> None:
    lines = readme_block()
    start = lines[0].split("#", 1)[0].strip()
    assert start.startswith("mkdir -p /tmp/radios && swarm radio-emu ") and start.endswith("&")
    assert all("swarm radio-config /tmp/radios/" in line for line in lines[1:] if "radio-config" in line)
    assert not any("MAX_WINDOW" in line for line in lines)  # multipoint has none


def test_readme_radio_config_examples_run_as_written(tmp_path: Path) -> None:
    directory = tmp_path / "radios"
    lines = [line.replace("/tmp/radios", str(directory)) for line in readme_block()]
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    start = lines[0].split("#", 1)[0].strip().removesuffix("&")
    log = (tmp_path / "emulator.log").open("wb")
    emulator = subprocess.Popen(
        ["bash", "-c", start], env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
    )
    try:
        links = [directory / f"radio{i}" for i in range(3)]
        wait_until(lambda: all(link.exists() for link in links), "the emulator's radio links", 30.0)
        script = "set -euo pipefail\nset -x\n" + "\n".join(lines[1:]) + "\n"
        run = subprocess.run(
            ["bash", "-c", script], env=env, capture_output=True, text=True, timeout=RUN_DEADLINE, check=False
        )
        assert run.returncode == 0, f"a README example failed:\n{run.stderr[-3000:]}"
        assert emulator.poll() is None, "the emulator died"
    finally:
        os.killpg(emulator.pid, signal.SIGTERM)
        emulator.wait(timeout=30)
        log.close()
    assert '"NODEID": 1' in run.stdout  # node 1's registers, read over the air
    for i in range(3):
        expected = parse_expected(str(directory / f"agent{i}.toml"))
        assert expected["NODEID"] == i and expected["NETID"] == 30 and expected["NODECOUNT"] == 3
