"""A station on a simulated channel that sends one swarm command: the relay between channels.

Theory of operation
-------------------
The real station holds one radio per channel and hands a command for the swarms of
channel C to C's radio. In the simulator each channel is its own run
(:mod:`swarm.sim.channels`); with ``Scenario.command_at`` set, the channel's run is a
:class:`RelaySim`: its agents are the agent's whole pure node
(:class:`swarm.core.agent.node.AgentNode`, no flight controller), and one more radio on the
channel is a station, the real pure :class:`swarm.core.station.core.StationCore` (station
id 255): it advertises itself, connects the agents (GSConnect, heartbeats,
Telemetry), learns the leader from their AgentState, and at ``command_at`` submits a
swarm FOLLOW (heading 90), which goes to the leader it sees with the station's own
retries. The station's radio counts in the channel's TDM ring, as the real one does.
What the run adds to its :class:`~swarm.sim.scenario.RunResult` is a
:class:`RelayResult`: when the command was submitted, whether it was refused at once
(no leader, nothing connected), and the first answer from an agent (its virtual time,
result and the agent).

Without a cap a channel holds one swarm. With several swarms on a channel (a cap), the
station core sends a swarm command to the one leader it sees (most agents follow it)
until the station learns to address each swarm: the figure is then per channel.

Stations join each other over IP (Zenoh routers) with a fixed latency: the command
the operator gives the station of channel 1 at T reaches channel C's station at
T + latency (:meth:`swarm.sim.channels.ChannelScenario.channel_scenario` sets each
channel's ``command_at``). Nothing travels back before the figures are taken, so the
channels stay independent runs on one virtual clock.

Stand-ins, documented: an agent's AgentState (on the radio a state frame) goes to the
station as one addressed frame of the same message; frames addressed to the station
id 255 are addressed on the air to the station's radio (its slot in the run, after the
agents'). Agreement is judged over the agents only. The run goes on until the command
has had its station's whole retry window (``command_give_up``) and a round more.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from swarm.core.agent.node import AgentNode, NodeOut, PublishState, Send
from swarm.core.election.outbox import ADVERTIZE, Out
from swarm.core.election.protocol import Core
from swarm.core.station.commands import CommandRefused, CommandSpec
from swarm.core.station.core import StationCore
from swarm.core.station.model import StOut
from swarm.core.wire.message_types import GCS_ID, CommandAck, CommandKind, Message, Phase
from swarm.core.wire.tunnel import Kind
from swarm.sim.scenario import RunResult, Scenario
from swarm.sim.simulate import POSE, Sim

#: the swarm command the station sends
COMMAND = CommandSpec(target=None, kind=CommandKind.FOLLOW, heading=90.0)


@dataclass
class RelayResult(RunResult):
    """A channel run's result with its station's swarm command: submitted at
    ``command_s`` (virtual time), ``refused`` at once (the station's reason) or first
    answered at ``ack_s`` by agent ``ack_by`` (channel id) with ``ack_result``."""

    command_s: float | None = None
    refused: str = ""
    ack_s: float | None = None
    ack_result: str = ""
    ack_by: int = 0


class _AgentPort:
    """An :class:`AgentNode` where the simulator expects a protocol core: what the
    node sends becomes the core's :class:`Out`; the election state is its core's."""

    def __init__(self, node: AgentNode) -> None:
        self.node = node
        self.core: Core = node.core

    @property
    def me(self) -> int:
        return self.core.me

    @property
    def phase(self) -> Phase:
        return self.core.phase

    @property
    def leader(self) -> int:
        return self.core.leader

    @property
    def members(self) -> dict[int, float]:
        return self.core.members

    @property
    def profile(self) -> object:
        return self.core.profile

    def start(self, now: float) -> list[Out]:
        return self._air(self.node.start(now))

    def tick(self, now: float) -> list[Out]:
        return self._air(self.node.tick(now))

    def handle(self, msg: Message, now: float) -> list[Out]:
        return self._air(self.node.handle(msg, now))

    def next_deadline(self) -> float:
        return self.node.next_deadline()

    @staticmethod
    def _air(outs: list[NodeOut]) -> list[Out]:
        air: list[Out] = []
        for o in outs:
            if isinstance(o, Send):
                air.append(Out(ADVERTIZE if o.to == 0 else o.to, o.msg))
            elif isinstance(o, PublishState):
                air.append(Out(GCS_ID, o.state))
        return air


class _StationPort:
    """The channel's :class:`StationCore` where the simulator expects a core: never in
    the election (IDLE, no leader); submits :data:`COMMAND` once at ``command_at``."""

    phase = Phase.IDLE
    leader = 0

    def __init__(self, me: int, profile: object, command_at: float) -> None:
        self.me = me
        self.profile = profile
        self.members: dict[int, float] = {}  # never in a swarm
        self.station = StationCore("gcs", GCS_ID)
        self.command_at = command_at
        self.command_s: float | None = None
        self.refused = ""
        self.ack: tuple[float, str, int] | None = None  # virtual time, result, agent
        self._seqs: set[int] = set()

    def start(self, now: float) -> list[Out]:
        return self.tick(now)

    def tick(self, now: float) -> list[Out]:
        outs = self.station.tick(now)
        if self.command_s is None and now >= self.command_at:
            self.command_s = now
            try:
                req, sent = self.station.submit(COMMAND, now)
            except CommandRefused as exc:
                self.refused = exc.reason
            else:
                self._seqs = {p.msg.seq for p in req.pending}
                outs += sent
        return self._air(outs)

    def handle(self, msg: Message, now: float) -> list[Out]:
        if isinstance(msg, CommandAck) and msg.seq in self._seqs and self.ack is None:
            self.ack = (now, msg.result.name, msg.sender)
        sender = getattr(msg, "sender", 0)
        return self._air(self.station.handle(msg, now, f"agent{sender}"))

    def next_deadline(self) -> float:
        d = self.station.next_deadline()
        return min(d, self.command_at) if self.command_s is None else d

    @staticmethod
    def _air(outs: list[StOut]) -> list[Out]:
        return [Out(ADVERTIZE if o.to == 0 else o.to, o.msg) for o in outs]


class RelaySim(Sim):
    """A channel's run with a station on it (see the module docstring)."""

    def __init__(self, sc: Scenario, seed: int) -> None:
        if sc.command_at is None:
            raise ValueError("RelaySim: the scenario has no command_at")
        n = sc.agents
        super().__init__(replace(sc, agents=n + 1), seed)  # the last radio is the station's
        self.n_agents = n
        ports: list[object] = []
        for c in self.cores[:n]:
            node = AgentNode(c.me, c.name, c.profile, rng=c.rng, has_fc=False)
            node.core.set_pose(POSE)
            ports.append(_AgentPort(node))
        self.station = _StationPort(n + 1, self.cores[0].profile, sc.command_at)
        ports.append(self.station)
        self.cores = ports  # type: ignore[assignment]  # duck-typed as the loop reads them
        give_up = self.station.station.cfg.command_give_up
        self._last_event = max(self._last_event, sc.command_at + give_up + self.round_s)
        self.duration = max(self.duration, self._last_event + sc.settle + 1.0)

    def _write(self, i: int, kind: Kind, targets: tuple[int, ...], body: bytes, t: float) -> None:
        """Frames to the station id go to the station's radio."""
        if GCS_ID in targets:
            targets = tuple(self.n_agents + 1 if x == GCS_ID else x for x in targets)
        super()._write(i, kind, targets, body, t)

    def _agreement(self) -> tuple[bool, int]:
        """Agreement among the agents (the station is in no swarm)."""
        everyone = self.cores
        self.cores = everyone[: self.n_agents]
        try:
            return super()._agreement()
        finally:
            self.cores = everyone

    def run(self) -> RelayResult:
        res = super().run()
        st = self.station
        ack_s, result, by = st.ack if st.ack is not None else (None, "", 0)
        return RelayResult(
            **res.__dict__,
            command_s=st.command_s,
            refused=st.refused,
            ack_s=ack_s,
            ack_result=result,
            ack_by=by,
        )
