"""The README's `swarm radio-config` examples run as written against the emulator they start.

The test reads the first ``sh`` block of README.md's radio-config section: it starts
`swarm radio-emu` in the background in a folder ``radios`` of the working directory,
runs the examples and stops the emulator (``kill $!; wait $!``). It runs unchanged in
bash, in a fresh temporary folder, and must exit 0 with the emulator gone; then node
1's registers (read over the air) and the three agents' parameter files are checked.
(tests/test_readme_examples.py counts it as covered here.)
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

# the README's section, moved to the docs site
README = Path(__file__).resolve().parent.parent / "docs" / "radios.md"
RUN_DEADLINE = 240.0  # the examples take about 35 s on an idle machine


def readme_block() -> list[str]:
    """The lines of the first ``sh`` block after the radio-config heading."""
    section = README.read_text(encoding="utf-8").split("## `swarm radio-config`", 1)[1]
    block = section.split("```sh\n", 1)[1].split("```", 1)[0]
    return block.splitlines()


def test_the_block_starts_the_emulator_and_keeps_the_old_example_out() -> None:
    lines = [line.split("#", 1)[0].strip() for line in readme_block()]
    assert (
        lines[0] == "mkdir -p radios" and lines[1].startswith("swarm radio-emu ") and lines[1].endswith("&")
    )
    assert lines[-1] == "kill $!; wait $!"  # the emulator itself, not a subshell, is stopped
    assert all("swarm radio-config radios/" in line for line in lines if "radio-config" in line)
    assert not any("MAX_WINDOW" in line for line in lines)  # multipoint has none


def test_readme_radio_config_examples_run_as_written(tmp_path: Path) -> None:
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    script = "set -euo pipefail\nset -x\n" + "\n".join(readme_block()) + "\n"
    log_path = tmp_path / "run.log"
    with log_path.open("w+b") as log:  # a file, not a pipe: a leftover emulator would hold a pipe open
        run = subprocess.Popen(
            ["bash", "-c", script],
            cwd=tmp_path,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            run.wait(timeout=RUN_DEADLINE)
        finally:
            if run.poll() is None:
                os.killpg(run.pid, signal.SIGKILL)
                run.wait()
        log.seek(0)
        out = log.read().decode(errors="replace")
    assert run.returncode == 0, f"a README example failed:\n{out[-3000:]}"
    assert '"NODEID": 1' in out  # node 1's registers, read over the air
    directory = tmp_path / "radios"
    wait_until(lambda: not (directory / "radio0").exists(), "the emulator removing its links", 10.0)
    for i in range(3):
        expected = parse_expected(str(directory / f"agent{i}.toml"))
        assert expected["NODEID"] == i and expected["NETID"] == 30 and expected["NODECOUNT"] == 3
