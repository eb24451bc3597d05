"""The README's flight-controller driver example runs exactly as written against a
simulated ArduCopter started at the same moment, with the boot a real one has.

The test reads the README's driver section: the ``python`` block (``fly.py``) and the
``sh`` line that starts ``swarm sim --realistic-boot`` in the background and runs the
script at once. Both run unchanged, in bash, in a fresh folder, with this checkout's
``swarm`` and ``python3`` first on PATH. The script must exit 0: it connected while the
autopilot booted, waited until arming was allowed (about 42 s: "Arm: Need Position
Estimate" and the others before), took off to 10 m, flew 20 m north within 0.5 m and
landed (``land(wait=True)`` returns on the ground).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.processes  # swarm sim and a python process, real TCP, real time

# the README's section, moved to the docs site
README = Path(__file__).resolve().parent.parent / "docs" / "autopilots.md"
RUN_DEADLINE = 300.0  # about 70 s on an idle machine: a 41.5 s boot, take-off, 20 m, landing
PORT = 5760  # as written: the simulator's first ArduPilot port


def section() -> str:
    return README.read_text(encoding="utf-8").split("## Flight-controller driver (Python API)", 1)[1]


def blocks() -> tuple[str, str]:
    s = section()
    script = s.split("```python\n", 1)[1].split("```", 1)[0]
    shell = s.split("```sh\n", 1)[1].split("```", 1)[0]
    return script, shell


def test_the_example_is_the_cold_start_one() -> None:
    script, shell = blocks()
    assert script.startswith("# fly.py\n") and f'connect("tcp:127.0.0.1:{PORT}"' in script
    assert "v.takeoff(10)" in script and "v.land(wait=True)" in script
    lines = [line for line in shell.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("swarm sim ") and "--realistic-boot &" in lines[0]
    assert "python3 fly.py" in lines[0]


def test_readme_driver_example_runs_as_written_against_a_booting_autopilot(tmp_path: Path) -> None:
    with socket.socket() as s:  # the README's fixed port: say so plainly if something holds it
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", PORT))
        except OSError as exc:
            pytest.fail(f"TCP {PORT} is in use on this machine; the README example needs it: {exc}")
    script, shell = blocks()
    (tmp_path / "fly.py").write_text(script, encoding="utf-8")
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env["PYTHONUNBUFFERED"] = "1"
    proc = subprocess.Popen(
        ["bash", "-c", "set -e\n" + shell],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        out, _ = proc.communicate(timeout=RUN_DEADLINE)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        pytest.fail(f"the README example did not finish within {RUN_DEADLINE:g} s:\n{out[-3000:]}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, f"the README example failed:\n{out[-3000:]}"
    assert "Traceback" not in out, out[-3000:]
