"""Several radio channels in one simulated run: ``swarm simulate --channels K``.

Theory of operation
-------------------
A deployment with more than a handful of aircraft splits them over several SiK
channels (each its own NETID): radios of different channels never hear each other,
and each channel is its own TDM ring whose round grows with its own radio count. A
:class:`ChannelScenario` is a :class:`~swarm.sim.scenario.Scenario` for every agent
(``agents`` is the whole deployment) plus how many channels there are and which agent
is on which (:func:`round_robin` by default, or an explicit ``--place`` such as
``1-50:1,51-100:2``, :func:`parse_place`).

Each channel is one plain :class:`~swarm.sim.simulate.Sim` run (its own
:class:`radios.air.AirModel`, so its own NETID and TDM round) of the channel's agents
with the scenario's loss, profile, air rate, cap and length. Every channel starts at
virtual time 0 and nothing couples two channels (no frame crosses), so running each
channel's loop on its own is exactly the same as interleaving all of them step by
step on one virtual clock: the times each reports are times on that one clock, and
"every agent of the deployment in a led swarm" happened at the latest of the
channels' agreement times. The per-channel runs are also what spreads over
``--jobs`` worker processes (:func:`swarm.sim.parallel.run_jobs`), in any order, with
the same figures.

Seeds: channel C of seed S runs with seed ``S + (C - 1) * SEED_STRIDE`` (channel 1
of seed S is the one-channel run of seed S), so a failing channel is replayed either
as the whole deployment (``--channels``) or on its own as a plain one-channel
``swarm simulate`` of its agents; both commands are in the report.

Ids: the shared rule is one system id per agent across a deployment. Inside a
channel's run its agents carry the ids 1..n in the order of their deployment ids
(the protocol compares ids only with each other, so the order is what matters), and
the report maps them back (a leader is named by its deployment id).

A station relaying between channels (``Scenario.command_at``, :mod:`swarm.sim.relay`):
each channel's run then has a station on it; the operator's swarm command reaches the
station of channel 1 at ``command_at`` and every other channel's station ``latency``
seconds later (stations joined over IP; nothing comes back before the figures are
taken, so the channels stay independent). :func:`relay_summary` counts the swarms
that answered and when the last answer came.

Faults that name agents (partitions, crashes, late starts, links, restarts, pauses,
drift) are not placed on channels yet: the command line refuses them with
``--channels``.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from swarm.sim.parallel import run_jobs
from swarm.sim.relay import RelayResult, RelaySim
from swarm.sim.scenario import RunResult, Scenario
from swarm.sim.simulate import Sim

#: at most this many channels in one run (a station holds one radio per channel)
MAX_CHANNELS = 16
#: channel C of seed S runs seed S + (C - 1) * SEED_STRIDE
SEED_STRIDE = 1_000_003
#: seconds a command takes from one station to another over the routers (``--relay-latency``)
DEFAULT_LATENCY_S = 0.05
MAX_LATENCY_S = 60.0
_PLACE_MAX_CHARS = 2000
_RANGE = re.compile(r"^\s*([0-9]{1,3})\s*(?:-\s*([0-9]{1,3}))?\s*:\s*([0-9]{1,2})\s*$")


def round_robin(agents: int, channels: int) -> tuple[int, ...]:
    """The channel (1-based) of each agent 1..``agents``: 1, 2, .., K, 1, 2, .."""
    return tuple(k % channels + 1 for k in range(agents))


def parse_place(spec: str, agents: int, channels: int) -> tuple[int, ...]:
    """The channel of each agent 1..``agents`` from ``A-B:C,D:C2,...`` (agents A to B on
    channel C, agent D on C2): every agent placed exactly once, every channel 1..K used.

    Raises:
        ValueError: the spec is malformed, names an agent or channel out of range,
            places an agent twice or leaves an agent or a channel out (one line).
    """
    if len(spec) > _PLACE_MAX_CHARS:
        raise ValueError(f"--place: at most {_PLACE_MAX_CHARS} characters")
    place = [0] * agents
    for part in spec.split(","):
        m = _RANGE.match(part)
        if m is None:
            raise ValueError(f"--place {part.strip()!r}: expected A-B:CHANNEL or A:CHANNEL")
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) else a
        c = int(m.group(3))
        if not 1 <= a <= b <= agents:
            raise ValueError(f"--place {part.strip()!r}: agents are 1..{agents}, A <= B")
        if not 1 <= c <= channels:
            raise ValueError(f"--place {part.strip()!r}: channels are 1..{channels}")
        for k in range(a, b + 1):
            if place[k - 1]:
                raise ValueError(f"--place: agent {k} is placed twice")
            place[k - 1] = c
    if 0 in place:
        raise ValueError(f"--place: agent {place.index(0) + 1} is on no channel")
    for c in range(1, channels + 1):
        if c not in place:
            raise ValueError(f"--place: channel {c} has no agent")
    return tuple(place)


def id_ranges(ids: list[int]) -> str:
    """``[1, 2, 3, 7]`` -> ``"1-3,7"``."""
    out: list[str] = []
    k = 0
    while k < len(ids):
        j = k
        while j + 1 < len(ids) and ids[j + 1] == ids[j] + 1:
            j += 1
        out.append(str(ids[k]) if j == k else f"{ids[k]}-{ids[j]}")
        k = j + 1
    return ",".join(out)


@dataclass(frozen=True)
class ChannelScenario:
    """A deployment's scenario (``base.agents`` is every agent) over ``channels``
    channels; ``place[k]`` is the channel of agent ``k + 1``; ``place_spec`` is the
    ``--place`` it came from (None: round robin)."""

    base: Scenario
    channels: int
    place: tuple[int, ...]
    place_spec: str | None = None
    #: seconds a command takes from one station to another (``base.command_at``)
    latency: float = DEFAULT_LATENCY_S

    @classmethod
    def make(
        cls, base: Scenario, channels: int, place_spec: str | None = None, latency: float = DEFAULT_LATENCY_S
    ) -> ChannelScenario:
        """Raises ValueError (one line) for a channel count, a placement or a latency
        that does not fit."""
        if not 1 <= channels <= min(MAX_CHANNELS, base.agents):
            raise ValueError(f"--channels: 1..{min(MAX_CHANNELS, base.agents)} (at most one per agent)")
        if not 0 <= latency <= MAX_LATENCY_S:
            raise ValueError(f"--relay-latency: 0..{MAX_LATENCY_S:g} seconds")
        if place_spec is None:
            return cls(base, channels, round_robin(base.agents, channels), None, latency)
        return cls(base, channels, parse_place(place_spec, base.agents, channels), place_spec, latency)

    def members(self, channel: int) -> list[int]:
        """The deployment ids of the agents on ``channel``, in order."""
        return [k + 1 for k, c in enumerate(self.place) if c == channel]

    def channel_scenario(self, channel: int) -> Scenario:
        """Channel ``channel``'s run: its agents; its station's command (if any) when it
        reaches that station (channel 1's at once, the others ``latency`` later)."""
        at = self.base.command_at
        if at is not None and channel > 1:
            at += self.latency
        return replace(self.base, agents=len(self.members(channel)), command_at=at)

    @staticmethod
    def channel_seed(seed: int, channel: int) -> int:
        return seed + (channel - 1) * SEED_STRIDE

    def command(self, seed: int) -> str:
        """The ``swarm simulate`` command that replays ``seed`` of the whole deployment."""
        cmd = self.base.command(seed) + f" --channels {self.channels}"
        if self.base.command_at is not None and self.latency != DEFAULT_LATENCY_S:
            cmd += f" --relay-latency {self.latency!r}"
        return cmd + (f" --place {self.place_spec.replace(' ', '')}" if self.place_spec else "")


def run_channels(
    cs: ChannelScenario, seeds: int, seed0: int = 0, jobs: int = 1, on_done: Callable[[], None] = lambda: None
) -> dict[str, Any]:
    """Seeds ``seed0 ..`` of the deployment (each channel a run, the runs over ``jobs``
    processes: the same figures for any number), summarised per channel and for the
    whole deployment. ``on_done`` is called once per finished channel run."""
    k = cs.channels
    work = [
        (cs.channel_scenario(c), cs.channel_seed(s, c))
        for s in range(seed0, seed0 + seeds)
        for c in range(1, k + 1)
    ]
    results = run_jobs(work, jobs, on_done)
    by_seed = [results[j * k : (j + 1) * k] for j in range(seeds)]
    all_led = [_all_led_s(rs) for rs in by_seed]
    out: dict[str, Any] = {
        "agents": cs.base.agents,
        "channels": k,
        "profile": cs.base.profile,
        "loss": cs.base.loss,
        "cap": cs.base.cap,
        "runs": seeds,
        "all_led": sum(x is not None for x in all_led),
        "all_led_s": {
            "p50": pct_none(all_led, 0.5),
            "p95": pct_none(all_led, 0.95),
            "max": pct_none(all_led, 1.0),
        },
        "air_utilisation_max": _round(max(r.air_utilisation for r in results)),
        "violations": sum(len(r.violations) for r in results),
        "per_channel": [_channel_summary(cs, c, [rs[c - 1] for rs in by_seed]) for c in range(1, k + 1)],
    }
    if cs.base.command_at is not None:
        out["relay"] = relay_summary(cs, by_seed)
    out["failing"] = _failing(cs, seed0, by_seed)[:10]
    return out


def relay_summary(cs: ChannelScenario, by_seed: list[list[RunResult]]) -> dict[str, Any]:
    """The swarm command of the station of channel 1 at ``command_at``, relayed to every
    channel's station: per run, how many channels' swarms answered it and how long after
    ``command_at`` the last answer came (None unless every swarm answered)."""
    at = cs.base.command_at or 0.0
    answered: list[int] = []
    accepted: list[int] = []
    last: list[float | None] = []
    refusals: dict[str, int] = {}
    for rs in by_seed:
        acks = [r.ack_s for r in rs if isinstance(r, RelayResult) and r.ack_s is not None]
        answered.append(len(acks))
        accepted.append(sum(isinstance(r, RelayResult) and r.ack_result == "ACCEPTED" for r in rs))
        last.append(max(acks) - at if len(acks) == len(rs) else None)
        for r in rs:
            if isinstance(r, RelayResult) and r.refused:
                refusals[r.refused] = refusals.get(r.refused, 0) + 1
    return {
        "command_at": at,
        "latency_s": cs.latency,
        "swarms": cs.channels,
        "answered": {"min": min(answered), "max": max(answered)},
        "accepted": {"min": min(accepted), "max": max(accepted)},
        "all_answered": sum(n == cs.channels for n in answered),
        "all_answered_s": {
            "p50": pct_none(last, 0.5),
            "p95": pct_none(last, 0.95),
            "max": pct_none(last, 1.0),
        },
        "refused_at_once": refusals,
    }


def _all_led_s(rs: list[RunResult]) -> float | None:
    """When every agent of the deployment was in a led swarm (the latest channel's
    agreement; None if a channel never agreed)."""
    if any(r.elect_s is None for r in rs):
        return None
    return max(r.elect_s for r in rs if r.elect_s is not None)


def pct_none(values: list[float | None], q: float) -> float | None:
    """The ``q`` quantile, a run that never got there (None) counting as longer than any:
    None when the quantile falls on one."""
    s = sorted(values, key=lambda v: (v is None, v or 0.0))
    if not s:
        return None
    v = s[min(len(s) - 1, max(0, round(q * (len(s) - 1))))]
    return None if v is None else round(v, 3)


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 4)


def _round_s(sc: Scenario) -> float:
    """The channel's TDM round (a station's radio counts in it)."""
    return (RelaySim(sc, 0) if sc.command_at is not None else Sim(sc, 0)).round_s


def _channel_summary(cs: ChannelScenario, c: int, rs: list[RunResult]) -> dict[str, Any]:
    ids = cs.members(c)
    elect = [r.elect_s for r in rs]
    air = sorted(r.air_utilisation for r in rs)
    leaders = sorted({ids[r.leader - 1] for r in rs if 1 <= r.leader <= len(ids)})
    return {
        "channel": c,
        "agents": len(ids),
        "ids": id_ranges(ids),
        "round_s": round(_round_s(cs.channel_scenario(c)), 4),
        "converged": sum(x is not None for x in elect),
        "elect_s": {"p50": pct_none(elect, 0.5), "p95": pct_none(elect, 0.95), "max": pct_none(elect, 1.0)},
        "air_utilisation": {"p50": _round(air[len(air) // 2]), "max": _round(air[-1])},
        "violations": sum(len(r.violations) for r in rs),
        "leaders_seen": leaders[:10],
    }


def _failing(cs: ChannelScenario, seed0: int, by_seed: list[list[RunResult]]) -> list[dict[str, Any]]:
    """Each channel run with a violation: its seed, channel, what, and the two commands
    that replay it (the deployment; the channel alone)."""
    out: list[dict[str, Any]] = []
    for j, rs in enumerate(by_seed):
        for c, r in enumerate(rs, start=1):
            if r.violations:
                out.append(
                    {
                        "seed": seed0 + j,
                        "channel": c,
                        "violations": r.violations,
                        "replay": cs.command(seed0 + j),
                        "replay_channel": cs.channel_scenario(c).command(r.seed),
                    }
                )
    return out


__all__ = [
    "DEFAULT_LATENCY_S",
    "MAX_CHANNELS",
    "SEED_STRIDE",
    "ChannelScenario",
    "id_ranges",
    "parse_place",
    "pct_none",
    "relay_summary",
    "round_robin",
    "run_channels",
]
