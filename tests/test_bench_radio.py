"""`swarm bench radio --json --quick` runs end to end and prints every field the
issue names. Figures are not asserted tightly here (noisy machines); the
benchmark's own `targets` say whether they are met, and the README records them."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# timing: the radio benchmark: goodput, latency, CPU
pytestmark = [pytest.mark.processes, pytest.mark.timing]  # the radio benchmark's processes

FIELDS = (
    "air_speed_kbps",
    "goodput_bytes_per_s",
    "model_goodput_bytes_per_s",
    "latency_ms_p50",
    "latency_ms_p99",
    "round_s",
    "emulator_cpu_percent",
)


def test_bench_radio_quick_prints_all_fields() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "swarm.cli", "bench", "radio", "--json", "--quick"],
        capture_output=True,
        text=True,
        timeout=170,
        check=True,
    )
    result = json.loads(out.stdout)
    for key in FIELDS:
        assert key in result, key
    assert result["air_speed_kbps"] == 64
    # physical sanity that cannot depend on machine load: goodput never above the air rate,
    # the pair moved real traffic, every latency probe arrived, the TDM round is the formula's
    assert 0 < result["goodput_bytes_per_s"] <= 64000 / 8
    assert result["latency_lost"] == 0
    assert result["latency_ms_p50"] > 0
    assert result["round_s"] == 0.3552
    assert result["emulator_cpu_percent"] > 0
