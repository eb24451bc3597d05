"""Helpers of the ground station's security tests: a live station with two scripted
agents that record every Command they receive, raw HTTP requests with exactly the
headers a test gives, and a count of the commands that reached the swarm."""

from __future__ import annotations

import http.client
import json
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from net_helpers import free_port, wait_until
from test_gcs_api import ScriptedAgent

from swarm.core.wire.message_types import Phase
from swarm.runtime.station.live import Station


@dataclass
class Swarm:
    station: Station
    agents: dict[int, ScriptedAgent]

    def commands(self) -> int:
        """Commands the agents received plus the command events the station logged."""
        received = sum(len(a.commands) for a in self.agents.values())
        logged = sum(1 for e in self.station.snapshot()["events"] if e["kind"] == "command")
        return received + logged

    def settled_commands(self, quiet_s: float = 1.0, timeout: float = 30.0) -> int:
        """:meth:`commands` once the swarm is quiet: nothing in flight at the station
        and the count unchanged for ``quiet_s`` (a command an earlier test sent may still
        be retried or answered; what a test then sends is measured from here)."""
        last = [-1, 0.0]

        def quiet() -> tuple[int] | None:  # a tuple: a count of 0 is an answer too
            n = self.commands()
            now = time.monotonic()
            if self.station.core.commands.in_flight or n != last[0]:
                last[0], last[1] = n, now
                return None
            return (n,) if now - last[1] >= quiet_s else None

        return int(wait_until(quiet, "the swarm to be quiet", timeout, 0.1)[0])


@contextmanager
def live_swarm(agents: int = 2) -> Iterator[Swarm]:
    """A station over Zenoh with ``agents`` connected scripted agents (1 leads)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    station = Station("gcs", zenoh_listen=[ep]).start()
    crew: dict[int, ScriptedAgent] = {}
    try:
        for k in range(1, agents + 1):
            crew[k] = ScriptedAgent(ep, k, phase=Phase.LEADER if k == 1 else Phase.MEMBER, leader=1)
        if agents:
            wait_until(
                lambda: (
                    len(station.snapshot()["agents"]) == agents
                    and all(a["connected"] for a in station.snapshot()["agents"])
                ),
                f"{agents} connected agents",
                30,
            )
        yield Swarm(station, crew)
    finally:
        for a in crew.values():
            a.close()
        station.stop()


@dataclass
class Answer:
    status: int
    headers: http.client.HTTPMessage
    body: bytes

    @property
    def json(self) -> Any:
        return json.loads(self.body)

    def error(self) -> str:
        """The one-line reason of a JSON error answer (asserts its form)."""
        assert "application/json" in self.headers.get("Content-Type", ""), (self.status, self.body[:200])
        obj = json.loads(self.body)
        assert isinstance(obj, dict) and isinstance(obj.get("error"), str), obj
        reason: str = obj["error"]
        assert "\n" not in reason and len(reason) < 400, reason
        return reason


def request(
    port: int,
    method: str,
    path: str,
    body: bytes | None = None,
    headers: Mapping[str, str] | None = None,
    timeout: float = 30.0,
) -> Answer:
    """One request to 127.0.0.1:``port`` with exactly ``headers`` (plus Host, unless given,
    and Content-Length for a body)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        hdrs = dict(headers or {})
        conn.request(method, path, body=body, headers=hdrs)
        r = conn.getresponse()
        return Answer(r.status, r.headers, r.read())
    finally:
        conn.close()


JSON = {"Content-Type": "application/json"}
TAKEOFF = json.dumps({"target": "swarm", "kind": "takeoff", "alt": 10}).encode()
