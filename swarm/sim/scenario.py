"""What one simulated run is: its scenario, its faults, its length and its result.

Theory of operation
-------------------
A :class:`Scenario` is everything a seeded run of :class:`swarm.sim.simulate.Sim`
depends on besides its seed: the number of agents, the loss models (uniform, bursty
Gilbert-Elliott), partitions (:class:`Partition`, ``T0-T1:1,2|3,4``: agents of
different groups cannot hear each other from T0 to T1, applied to the air as
:class:`PartitionLoss`), crashes and late starts (``ID@T``, :func:`parse_at`), the
profile, the agents' swarm size cap, the radio speeds and the run's length. :meth:`Scenario.command` is the
``swarm simulate`` command line that replays a seed. A run lasts ``duration``
virtual seconds at most; by default :func:`run_length`: 60 s, or 20 TDM rounds when
that is longer. :class:`RunResult` is what a run reports. Plain data: pickled as is
to the worker processes of :mod:`swarm.sim.parallel`.
"""

from __future__ import annotations

import random
import shlex
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Partition:
    t0: float
    t1: float
    groups: tuple[frozenset[int], ...]

    @classmethod
    def parse(cls, spec: str) -> Partition:
        """``T0-T1:1,2,3|4,5`` (seconds; agent ids, 1-based)."""
        try:
            times, groups = spec.split(":", 1)
            a, b = times.split("-", 1)
            gs = tuple(frozenset(int(x) for x in g.split(",") if x) for g in groups.split("|"))
            return cls(float(a), float(b), gs)
        except ValueError:
            raise ValueError(f"partition {spec!r}: expected T0-T1:1,2|3,4") from None

    def group_of(self, agent: int) -> int:
        for i, g in enumerate(self.groups):
            if agent in g:
                return i
        return -1


@dataclass
class PartitionLoss:
    """Drops every packet between agents of different groups during the partition."""

    parts: list[Partition]

    def lost(self, sender: int, receiver: int, t: float, rng: random.Random) -> bool:
        for p in self.parts:
            if p.t0 <= t < p.t1 and p.group_of(sender + 1) != p.group_of(receiver + 1):
                return True
        return False


@dataclass(frozen=True)
class Link:
    """``A>B:P`` or ``A>B:P@T0-T1``: frames agent A sends reach agent B with loss P (1:
    never; a one-way link), for the whole run or from T0 to T1 s."""

    src: int
    dst: int
    p: float
    t0: float = 0.0
    t1: float = float("inf")

    @classmethod
    def parse(cls, spec: str) -> Link:
        try:
            pair, _, rest = spec.partition(":")
            a, b = pair.split(">", 1)
            p, _, win = rest.partition("@")
            t0, t1 = (float(x) for x in win.split("-", 1)) if win else (0.0, float("inf"))
            link = cls(int(a), int(b), float(p), t0, t1)
        except ValueError:
            raise ValueError(f"link {spec!r}: expected A>B:P or A>B:P@T0-T1") from None
        if not 0 <= link.p <= 1 or not 0 <= link.t0 < link.t1 or link.src == link.dst:
            raise ValueError(f"link {spec!r}: P in 0..1, T0 < T1, A and B different")
        return link

    def spec(self) -> str:
        win = "" if self.t1 == float("inf") else f"@{self.t0!r}-{self.t1!r}"
        return f"{self.src}>{self.dst}:{self.p!r}{win}"


@dataclass
class LinkLoss:
    """Directed losses: what a sender's frames lose on the way to one receiver."""

    links: list[Link]

    def lost(self, sender: int, receiver: int, t: float, rng: random.Random) -> bool:
        for k in self.links:
            if k.src == sender + 1 and k.dst == receiver + 1 and k.t0 <= t < k.t1:
                if k.p >= 1 or rng.random() < k.p:
                    return True
        return False


def parse_span(spec: str) -> tuple[int, float, float]:
    """``ID@T0-T1`` (a restart or a pause: down from T0, up at T1)."""
    try:
        who, _, win = spec.partition("@")
        a, b = win.split("-", 1)
        agent, t0, t1 = int(who), float(a), float(b)
    except ValueError:
        raise ValueError(f"{spec!r}: expected ID@T0-T1") from None
    if not 0 <= t0 < t1:
        raise ValueError(f"{spec!r}: T0 < T1, both at least 0")
    return agent, t0, t1


def parse_drift(spec: str) -> tuple[int, float]:
    """``ID:PPM``: the agent's clock runs PPM parts per million fast (negative: slow)."""
    try:
        who, ppm = spec.split(":", 1)
        agent, d = int(who), float(ppm)
    except ValueError:
        raise ValueError(f"drift {spec!r}: expected ID:PPM") from None
    if not abs(d) <= 50_000:
        raise ValueError(f"drift {spec!r}: at most 50000 ppm either way")
    return agent, d


def parse_at(spec: str) -> tuple[str, float]:
    """``ID@T`` or ``leader@T``."""
    who, _, t = spec.partition("@")
    if not t:
        raise ValueError(f"{spec!r}: expected ID@SECONDS or leader@SECONDS")
    return who, float(t)


@dataclass
class Scenario:
    agents: int = 5
    loss: float = 0.0
    burst_loss: str | None = None
    partitions: list[str] = field(default_factory=list)
    crashes: list[str] = field(default_factory=list)
    late: list[str] = field(default_factory=list)
    profile: str = "paper"
    air_kbps: int = 64
    serial_baud: int = 57600
    #: virtual seconds a run lasts at most; None: MIN_DURATION_S or DURATION_ROUNDS
    #: TDM rounds, whichever is longer (an N=50 election takes about ten rounds)
    duration: float | None = None
    settle: float = 3.0  # converged state must hold this long
    links: list[str] = field(default_factory=list)
    restarts: list[str] = field(default_factory=list)
    pauses: list[str] = field(default_factory=list)
    drift: list[str] = field(default_factory=list)
    strict: bool = False  # the campaign's continuous invariants (swarm.sim.faultsim)
    #: agents per swarm at most (swarm.core.election.caps; 0: no cap, one swarm); each channel's run takes it
    cap: int = 0
    #: a station on the channel sends one swarm command at this virtual time (None: no
    #: station; swarm.sim.relay)
    command_at: float | None = None

    def last_fault_s(self) -> float:
        """When the last fault with an end ends (a partition heals, a link, a restart or
        a pause is over, the last late agent starts); 0 if none."""
        ends = [Partition.parse(p).t1 for p in self.partitions]
        ends += [k.t1 for k in map(Link.parse, self.links) if k.t1 != float("inf")]
        ends += [parse_span(x)[2] for x in self.restarts + self.pauses]
        ends += [parse_at(x)[1] for x in self.late]
        return max(ends, default=0.0)

    def settle_tail_s(self) -> float:
        """How long after its last fault a strict run must go on before it may be called
        unsettled: a minute, and 3 s per agent (an N=50 paper election takes ~70 s)."""
        return 60.0 + 3.0 * self.agents

    @property
    def extended(self) -> bool:
        """Whether the run needs :class:`swarm.sim.faultsim.FaultSim`."""
        return bool(self.restarts or self.pauses or self.drift or self.strict)

    def command(self, seed: int) -> str:
        """The ``swarm simulate`` command that replays ``seed`` (quoted for a POSIX shell)."""
        parts = [
            f"swarm simulate --agents {self.agents} --seeds 1 --seed {seed}",
            f"--profile {self.profile}",
        ]
        if self.loss:
            parts.append(f"--loss {self.loss}")
        if self.burst_loss:
            parts.append(f"--burst-loss {shlex.quote(self.burst_loss)}")
        parts += [f"--partition {shlex.quote(p)}" for p in self.partitions]
        parts += [f"--crash {shlex.quote(c)}" for c in self.crashes]
        parts += [f"--late {shlex.quote(x)}" for x in self.late]
        parts += [f"--link {shlex.quote(x)}" for x in self.links]
        parts += [f"--restart {shlex.quote(x)}" for x in self.restarts]
        parts += [f"--pause {shlex.quote(x)}" for x in self.pauses]
        parts += [f"--drift {shlex.quote(x)}" for x in self.drift]
        if self.air_kbps != 64:
            parts.append(f"--air-speed {self.air_kbps}")
        if self.duration is not None:
            parts.append(f"--duration {self.duration}")
        if self.strict:
            parts.append("--strict")
        if self.cap:
            parts.append(f"--cap {self.cap}")
        if self.command_at is not None:
            parts.append(f"--command-at {self.command_at!r}")
        return " ".join(parts)


@dataclass
class RunResult:
    seed: int
    converged: bool
    elect_s: float | None
    failover_s: float | None
    violations: list[str]
    air_utilisation: float
    messages_per_agent: float
    leader: int
    end_s: float
    stable_at_end: bool = True


MIN_DURATION_S = 60.0
DURATION_ROUNDS = 20


def run_length(round_s: float) -> float:
    """A run's default length: 60 s, or 20 TDM rounds when that is longer. The paper
    profile's windows grow with the round (multipoint: one window per radio), so an
    election of 50 radios at 64 kbps (5.92 s rounds) takes 50-70 s; a fixed 60 s cut
    such runs short and called them unconverged."""
    return max(MIN_DURATION_S, DURATION_ROUNDS * round_s)


__all__ = [
    "DURATION_ROUNDS",
    "MIN_DURATION_S",
    "Link",
    "LinkLoss",
    "Partition",
    "PartitionLoss",
    "RunResult",
    "Scenario",
    "parse_at",
    "parse_drift",
    "parse_span",
    "run_length",
]
