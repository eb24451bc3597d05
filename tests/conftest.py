"""Fixtures every test module may use; the helpers behind them live in
``net_helpers`` (one polling wait, free ports, the manual clock) so that test modules
can import them by name for their annotations.

Markers (registered in pyproject.toml): ``processes`` marks the tests that start
processes, radios emulated in real time, Zenoh sessions or a browser and take
seconds each; ``make test-quick`` leaves them out, ``make test`` runs them all.
``timing`` marks the tests that judge time: a rate, a duration, a latency, CPU, or an
error measured while flying in real time.

``make test`` (``tests/run_all.sh``) runs every test that judges no time in parallel
pytest-xdist workers, then the ``timing`` tests one after another beside the tests of
the real autopilots (``sitl``), one after another too. In the workers, the tests of a
module that starts processes stay together on one worker, in their order
(:func:`pytest_collection_modifyitems`: they share module-wide benches, and some stop a
part of one), and the tests that need fixed ports are grouped so that no two of them
run at once.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from net_helpers import ManualClock

#: modules whose tests need the same fixed ports (TCP 5760, the docs' simulator example
#: on 5760-5790 and 14540-14542): one worker runs them one after another
FIXED_PORTS = frozenset({"test_readme_driver.py", "test_readme_examples.py"})


#: tests of a minute or more: started with the first, not last
LONG = frozenset(
    {
        "test_bounded_campaign_has_no_violation",
        "test_a_cold_start_sends_no_pose_before_the_fix_and_reports_the_refusals_it_met",
    }
)


def _group(item: pytest.Item, with_processes: set[Path]) -> str | None:
    if item.path.name in FIXED_PORTS:
        return "fixed-ports"
    if item.path in with_processes:
        return item.path.stem
    return None


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Groups for pytest-xdist's ``--dist loadgroup``: the fixed-port tests together and
    each module that starts processes on one worker; every other test goes wherever a
    worker is free. The longest come first (the fixed ports, the tests of a minute or
    more, then the process modules), so that they start at once instead of ending the
    session; the order is the same in every worker, as xdist requires."""
    with_processes = {i.path for i in items if i.get_closest_marker("processes") is not None}
    rank: dict[str, int] = {"fixed-ports": 1}
    keyed = []
    for index, item in enumerate(items):
        group = None if item.get_closest_marker("xdist_group") is not None else _group(item, with_processes)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
        long = getattr(item, "originalname", item.name) in LONG
        keyed.append((2 if long else rank.get(group or "", 3 if group else 4), index, item))
    items[:] = [item for _, _, item in sorted(keyed, key=lambda k: (k[0], k[1]))]


class _SitlGate:
    """Without a SITL folder (``$SITL_DIR``, else ``../shared/sitl``) the tests against
    real autopilots (marker ``sitl``) cannot run: they are left out after ``-m`` chose
    the session's tests, and the session says so at its end (never silently). A
    ``$SITL_DIR`` that is set but wrong fails them instead."""

    def __init__(self) -> None:
        self.left_out = 0

    @pytest.hookimpl(trylast=True)
    def pytest_collection_modifyitems(self, config: pytest.Config, items: list[pytest.Item]) -> None:
        from firmware_bridge.sitl import find_sitl

        sitl = [i for i in items if i.get_closest_marker("sitl") is not None]
        if sitl and find_sitl() is None:
            config.hook.pytest_deselected(items=sitl)
            items[:] = [i for i in items if i.get_closest_marker("sitl") is None]
            self.left_out = len(sitl)

    def pytest_terminal_summary(self, terminalreporter: pytest.TerminalReporter) -> None:
        if self.left_out:
            terminalreporter.write_line(
                f"real autopilots: none found (SITL_DIR unset, no ../shared/sitl): {self.left_out} tests "
                "against real ArduCopter and PX4 not run "
                "(docs/autopilots.md, 'Real autopilots', says how to build them)"
            )


def pytest_configure(config: pytest.Config) -> None:
    config.pluginmanager.register(_SitlGate(), "sitl-gate")


@pytest.fixture(autouse=True, scope="session")
def _state_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Signed nodes the tests start (in process or as children, which inherit it) keep
    their state (``swarm.cli.state_dir``) in a folder of the session, never in the home
    of whoever runs the tests."""
    mp = pytest.MonkeyPatch()
    mp.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("xdg-state")))
    mp.delenv("STATE_DIRECTORY", raising=False)
    yield
    mp.undo()


@pytest.fixture
def manual_clock() -> ManualClock:
    """A clock at 1000.0 s that moves only when the test (or a sleep on it) moves it."""
    return ManualClock(1000.0)
