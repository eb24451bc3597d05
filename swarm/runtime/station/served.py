"""What the server reads from a station: the live one, a replay, or a fleet of several."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Protocol

from swarm.core.station.commands import CommandSpec


class ReplayControl(Protocol):
    def status(self) -> dict[str, Any]: ...

    def control(self, action: Any, value: Any) -> dict[str, Any]: ...


class ServedStation(Protocol):
    """What the server reads from a station: the live one, a replay, or a fleet of several."""

    name: str
    id: int

    @property
    def replay(self) -> ReplayControl | None: ...

    def describe(self) -> str: ...

    def snapshot(self) -> dict[str, Any]: ...

    def snapshot_json(self) -> str: ...

    def agent(self, agent_id: int) -> dict[str, Any] | None: ...

    def ack_alert(self, alert_id: Any) -> dict[str, Any]: ...

    def center(self) -> list[float] | None: ...

    def submit(self, spec: CommandSpec) -> Future[tuple[int, dict[str, Any]]]: ...

    def add_listener(self, fn: Callable[[dict[str, Any]], None]) -> None: ...

    def remove_listener(self, fn: Callable[[dict[str, Any]], None]) -> None: ...
