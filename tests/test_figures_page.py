"""The docs' figures page is rendered from the benches' own JSON output
(tools/record_figures.py records it): no figure is copied by hand."""

from __future__ import annotations

import importlib.util
import json
import signal
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from net_helpers import wait_until

ROOT = Path(__file__).resolve().parent.parent


def _conf() -> ModuleType:
    spec = importlib.util.spec_from_file_location("docs_conf", ROOT / "docs" / "conf.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


RECORD: dict[str, Any] = {
    "area": "messages",
    "command": "swarm bench messages --json",
    "recorded": "2026-11-29T09:10Z",
    "took_s": 31.8,
    "commit": "abc1234",
    "machine": {
        "cpus": 2,
        "load_1m_before": 0.4,
        "load_1m_after": 0.9,
        "system": "Linux x86_64",
        "python": "3.11",
    },
    "result": {
        "payload_bytes": {"PoseReport": 16},
        "latency_ratio_p50": 0.979,
        "cases": [{"agents": 5, "elect_s": 7.1}, {"agents": 10, "elect_s": 9.5, "note": "a|b"}],
        "targets": {"pose_payload_le_16": True, "latency_within_model": False},
    },
}


def test_a_record_renders_its_figures_its_targets_and_its_tables() -> None:
    page = _conf().figures_markdown([RECORD])
    assert "## messages" in page and "`swarm bench messages --json`, recorded 2026-11-29 09:10Z" in page
    assert "| payload_bytes.PoseReport | 16 |" in page and "| latency_ratio_p50 | 0.979 |" in page
    assert "| pose_payload_le_16 | yes |" in page and "| latency_within_model | **no** |" in page
    assert "| agents | elect_s | note |" in page and "| 10 | 9.5 | a\\|b |" in page
    assert "| 5 | 7.1 |  |" in page  # a row without a column: an empty cell


def test_every_recorded_figure_file_is_a_bench_record() -> None:
    records = [
        json.loads(p.read_text(encoding="utf-8")) for p in sorted((ROOT / "docs" / "figures").glob("*.json"))
    ]
    assert records, "no figures recorded in docs/figures/"
    for r in records:
        assert set(r) >= {"area", "command", "recorded", "took_s", "commit", "machine", "result"}, r.keys()
        assert r["command"].startswith(
            (f"swarm bench {r['area']} ", f"tools/{r['area'].replace('-', '_')}.py")
        )
        assert isinstance(r["result"], dict) and r["result"]
    page = _conf().figures_markdown(records)
    assert all(f"## {r['area']}" in page for r in records)


def test_a_bench_that_fails_is_one_line_and_keeps_the_old_record(tmp_path: Path) -> None:
    (tmp_path / "nosuch.json").write_text("{}\n")
    run = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "record_figures.py"), "nosuch", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 1
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("record-figures: nosuch: swarm bench exited 2: "), lines
    assert (tmp_path / "nosuch.json").read_text() == "{}\n"


@pytest.mark.processes
def test_sigterm_stops_the_recording_and_its_bench(tmp_path: Path) -> None:
    """A long recording stopped by SIGTERM: exit 130 in one line, the bench stopped with
    it, nothing recorded."""
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "tools" / "record_figures.py"), "messages", "--out", str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        bench = wait_until(lambda: _children(proc.pid), "the bench to start", 60)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130 and err.strip().splitlines() == ["record-figures: interrupted"], err
    wait_until(lambda: not any(Path(f"/proc/{pid}").exists() for pid in bench), "the bench to stop", 30)
    assert not list(tmp_path.glob("*.json"))


def _children(pid: int) -> list[int]:
    """The pids of ``pid``'s children (from /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found
