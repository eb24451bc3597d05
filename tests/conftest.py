"""Fixtures every test module may use; the helpers behind them live in
``net_helpers`` (one polling wait, free ports, the manual clock) so that test modules
can import them by name for their annotations.

Markers (registered in pyproject.toml): ``processes`` marks the tests that start
processes, radios emulated in real time, Zenoh sessions or a browser and take
seconds each; ``make test-quick`` leaves them out, ``make test`` runs them all.
"""

from __future__ import annotations

import pytest
from net_helpers import ManualClock


@pytest.fixture
def manual_clock() -> ManualClock:
    """A clock at 1000.0 s that moves only when the test (or a sleep on it) moves it."""
    return ManualClock(1000.0)
