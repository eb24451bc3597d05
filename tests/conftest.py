"""Fixtures every test module may use; the helpers behind them live in
``net_helpers`` (one polling wait, free ports, the manual clock) so that test modules
can import them by name for their annotations.

Markers (registered in pyproject.toml): ``processes`` marks the tests that start
processes, radios emulated in real time, Zenoh sessions or a browser and take
seconds each; ``make test-quick`` leaves them out, ``make test`` runs them all.

``make test`` runs three pytest sessions side by side (``tests/run_all.sh``). The
process tests run in real time and some judge rates, formation errors or recovery on
a shared machine, so they stay one after another in one session, as they always
ran; the other session runs the tests that start no process, then the light process
tests (:data:`LIGHT`, marked ``light`` here: AT commands over ptys, a wheel build,
the pre-flight check, pages and stations checked for what they show: no rates or
durations judged), balancing the two sessions' lengths. A third session runs the few
long process tests marked ``waits`` in their modules: they mostly wait out a fixed
stretch of real time (a recorded 41.5 s boot, a minute of uptime) with little CPU,
and the README's runnable examples, which share the README's fixed ports.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from net_helpers import ManualClock

#: process-test modules light enough to run beside the real-time ones (marked ``light``)
LIGHT = frozenset(
    {
        "test_sik_guard.py",
        "test_radio_config_readme.py",
        "test_radio_config.py",
        "test_sik_aes_config.py",
        "test_sik_config.py",
        "test_doctor_bench.py",
        "test_packaging.py",
        "test_readme_driver.py",  # one simulated vehicle, mostly waiting out its boot
        "test_readme_examples.py",  # small emulators, agents and simulators for seconds each; no rates judged
        "test_cold_start.py",  # the same, with an agent and a station
        "test_federation.py",  # stations' Zenoh sessions in one process: what crosses, not how fast
        "test_fleet_view.py",  # two stations' sessions in one process: the merged view
        "test_fleet_stations_page.py",  # 3 stations, a router, a browser: what they show
        "test_fleet_processes.py",  # 2 channels, 2 stations, a router: what the API shows and answers
        # the IP edge: routers, TLS and the ACL, attacks: what gets in, not how fast
        "test_ip_edge_deployment.py",
        "test_ip_edge_attack.py",
        "test_zenoh_tls.py",
        "test_zenoh_tls_agents.py",
        "test_federation_restart.py",
        "test_federation_future.py",
        "test_secret_files.py",  # refused at start: one line and the exit code
        "test_gcs_connections.py",
        # pages and stations checked for what they show and answer, not for how fast
        "test_fleet_page.py",
        "test_altitude_page.py",
        "test_alerts_processes.py",
        "test_command_results_processes.py",
        "test_gcs_push.py",
        "test_geofence_api.py",
        "test_gcs_sysid.py",
        "test_gcs_offline_map.py",
        "test_replay_capture_processes.py",
        "test_plan_page.py",
        "test_sim_parallel.py",  # virtual time: the figures do not depend on the machine
        "test_sim_campaign.py",  # the same
        "test_tdm_election.py",  # virtual time, in-process
        "test_station_swarms.py",
        "test_swarms_page.py",
        "test_caps.py",  # the size cap: virtual time and in-process commands only
        "test_subswarm_processes.py",  # six agents, one channel: what the station shows
        "test_sim_channels.py",  # virtual time: channels, the relay, the scale bench's quick shape
        "test_sim_events.py",  # in-process, virtual time
        "test_own_ack.py",  # the core alone and three replays, virtual time
    }
)


@pytest.hookimpl(tryfirst=True)  # before ``-m`` selects by markers
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The process tests of :data:`LIGHT`'s modules are ``light`` too."""
    for item in items:
        if item.path.name in LIGHT and item.get_closest_marker("processes") is not None:
            item.add_marker(pytest.mark.light)


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
