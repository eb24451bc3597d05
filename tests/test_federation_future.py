"""A state from the future (issue 27): stations joined through a real Zenoh router, a
hostile session on the same network publishes one state under station C's name stamped
in the year 2100. Before the fix unsigned states were not time-checked at all: the
forgery became C's newest, every real state of C after it was "not newer", and A's view
of C stayed frozen on the forgery for good. The forgery must be refused (and said once),
and C's real states keep updating A's view. Signed states more than the skew ahead are
refused the same way."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from concurrent.futures import Future
from typing import Any

import pytest
from net_helpers import free_port, wait_until

from swarm.cli.commands.router import open_router
from swarm.core.station.federation import KIND_STATE, fed_key, seal, state_key
from swarm.runtime.keyspace.transport import open_session
from swarm.runtime.station.federation import Federation

DEADLINE = 20.0
YEAR_2100_US = 4_102_444_800 * 1_000_000


class Side:
    def __init__(self, name: str, ep: str, key: bytes | None, agents: list[int]) -> None:
        self.events: list[tuple[str, str]] = []
        self.agents = [{"id": i, "name": f"a{i}", "connected": True, "leader": agents[0]} for i in agents]
        self.fed = Federation(
            name,
            connect=[ep],
            key=key,
            local=lambda: {"agents": list(self.agents), "events": [], "swarms": []},
            run_local=self.run,
            on_event=lambda k, t: self.events.append((k, t)),
            period=0.2,
            timeout=1.5,
            forget=4.0,
            command_timeout=3.0,
        )

    def run(self, body: Any) -> Future[tuple[int, dict[str, Any]]]:
        f: Future[tuple[int, dict[str, Any]]] = Future()
        f.set_result((200, {"ok": True}))
        return f

    def ids_of(self, name: str) -> list[int] | None:
        r = next((r for r, _alive in self.fed.remotes() if r.name == name), None)
        return None if r is None else [a["id"] for a in r.state["agents"]]


@pytest.fixture
def router() -> Iterator[str]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    session: Any = open_router([ep], [])
    try:
        yield ep
    finally:
        session.close()


@pytest.mark.processes
@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
def test_a_state_from_the_future_is_refused_and_the_real_states_keep_coming(
    router: str, signed: bool
) -> None:
    key = fed_key(b"k" * 32) if signed else None
    a, c = Side("gcsA", router, key, [1, 2]), Side("gcsC", router, key, [41, 42])
    a.fed.start()
    c.fed.start()
    evil = open_session(connect=[router])
    try:
        wait_until(lambda: a.ids_of("gcsC") == [41, 42], "A to hear C", DEADLINE)
        body = json.dumps({"agents": [{"id": 99, "name": "ghost", "connected": True}]}).encode()
        # unsigned: stamped in 2100; signed (a key holder's clock set wrong): 25 s ahead,
        # inside the 30 s window signed envelopes had
        t_us = YEAR_2100_US if not signed else int((time.time() + 25.0) * 1e6)
        forged = seal(KIND_STATE, "gcsC", 7, t_us, body, key, deflate=True)
        gate = a.fed.state_gate
        wait_until(
            lambda: evil.put(state_key("gcsC"), forged) or gate.refused.get("from the future"),
            "A to refuse the state from the future",
            DEADLINE,
            0.3,
        )
        c.agents.append({"id": 43, "name": "a43", "connected": True, "leader": 41})
        wait_until(lambda: a.ids_of("gcsC") == [41, 42, 43], "A to see C's real states go on", DEADLINE)
        assert 99 not in (a.ids_of("gcsC") or [])
        said = [t for k, t in a.events if "ahead of this station's clock" in t]
        assert len(said) == 1 and "gcsC" in said[0], a.events
    finally:
        evil.close()
        a.fed.stop()
        c.fed.stop()
