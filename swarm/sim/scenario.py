"""What one simulated run is: its scenario, its faults, its length and its result.

Theory of operation
-------------------
A :class:`Scenario` is everything a seeded run of :class:`swarm.sim.simulate.Sim`
depends on besides its seed: the number of agents, the loss models (uniform, bursty
Gilbert-Elliott), partitions (:class:`Partition`, ``T0-T1:1,2|3,4``: agents of
different groups cannot hear each other from T0 to T1, applied to the air as
:class:`PartitionLoss`), crashes and late starts (``ID@T``, :func:`parse_at`), the
profile, the radio speeds and the run's length. :meth:`Scenario.command` is the
``swarm simulate`` command line that replays a seed. A run lasts ``duration``
virtual seconds at most; by default :func:`run_length`: 60 s, or 20 TDM rounds when
that is longer. :class:`RunResult` is what a run reports. Plain data: pickled as is
to the worker processes of :mod:`swarm.sim.parallel`.
"""

from __future__ import annotations

import random
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

    def command(self, seed: int) -> str:
        parts = [
            f"swarm simulate --agents {self.agents} --seeds 1 --seed {seed}",
            f"--profile {self.profile}",
        ]
        if self.loss:
            parts.append(f"--loss {self.loss}")
        if self.burst_loss:
            parts.append(f"--burst-loss {self.burst_loss}")
        parts += [f"--partition {p}" for p in self.partitions]
        parts += [f"--crash {c}" for c in self.crashes]
        parts += [f"--late {x}" for x in self.late]
        if self.duration is not None:
            parts.append(f"--duration {self.duration}")
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
    "Partition",
    "PartitionLoss",
    "RunResult",
    "Scenario",
    "parse_at",
    "run_length",
]
