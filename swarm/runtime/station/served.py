"""What the server reads from a station: the live one, a replay, or a fleet of several."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Protocol

from swarm.core.flight.geofence import Geofence
from swarm.core.station.commands import CommandSpec
from swarm.core.station.rows import AgentRow, AlertRow, EventRow, ReplayStatus, Snapshot

#: who hears a station's events as they happen (the WebSocket)
Listener = Callable[[EventRow], None]


class ReplayControl(Protocol):
    def status(self) -> ReplayStatus: ...

    def control(self, action: Any, value: Any) -> ReplayStatus: ...


class ServedStation(Protocol):
    """What the server reads from a station: the live one, a replay, or a fleet of several."""

    name: str
    id: int

    @property
    def replay(self) -> ReplayControl | None: ...

    @property
    def fence(self) -> Geofence: ...

    def describe(self) -> str: ...

    def snapshot(self) -> Snapshot: ...

    def snapshot_json(self) -> str: ...

    def agent(self, agent_id: int) -> AgentRow | None: ...

    def ack_alert(self, alert_id: Any) -> AlertRow: ...

    def shelve_alert(self, alert_id: Any, seconds: Any) -> AlertRow: ...

    def center(self) -> list[float] | None: ...

    def submit(self, spec: CommandSpec) -> Future[tuple[int, dict[str, Any]]]: ...

    def add_listener(self, fn: Listener) -> None: ...

    def remove_listener(self, fn: Listener) -> None: ...
