"""Fixtures every test module may use; the helpers behind them live in
``net_helpers`` (one polling wait, free ports, the manual clock) so that test modules
can import them by name for their annotations.

Markers (registered in pyproject.toml): ``processes`` marks the tests that start
processes, radios emulated in real time, Zenoh sessions or a browser and take
seconds each; ``make test-quick`` leaves them out, ``make test`` runs them all.

``make test`` runs two pytest-xdist workers: every ``processes`` test is in one
xdist group, so they run one after another on one worker (as they always did: they
run in real time and share two cores), while the other worker takes the tests that
start no process. The suite's wall time is then about that of the process tests.
"""

from __future__ import annotations

import pytest
from net_helpers import ManualClock


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every process test in one xdist group (one worker, one after another)."""
    for item in items:
        if item.get_closest_marker("processes") is not None:
            item.add_marker(pytest.mark.xdist_group("processes"))


@pytest.fixture
def manual_clock() -> ManualClock:
    """A clock at 1000.0 s that moves only when the test (or a sleep on it) moves it."""
    return ManualClock(1000.0)
