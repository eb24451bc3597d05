"""The election's settings: timing profiles and vote policies.

Theory of operation
-------------------
A :class:`Profile` holds every window, rate and timeout of
:class:`swarm.core.election.protocol.Core` in seconds. :data:`PAPER` is the paper's values;
:func:`paper_profile` stretches them only where a SiK radio's TDM round makes them
impossible, :func:`fast_profile` derives every interval and window from the
round, and :func:`tdm_profile` adds the ``tdm`` election's rules (votes exchanged
while pooling, :mod:`swarm.core.election.tdm`); :func:`profile_by_name` picks one
of the three by name (the ``--profile`` option, :data:`PROFILE_NAMES`).

A :class:`VotePolicy` gives an agent's vote its weight: random (the paper),
battery, or link quality, each in the high byte with random low bits, so ties are
rare and broken by the candidate id. Pure: no I/O, no clock (the battery and RSSI
come from callables the driver passes).
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol


@dataclass(frozen=True)
class Profile:
    """Windows, rates and timeouts (seconds)."""

    name: str = "paper"
    advertize_interval: float = 1.0
    startpool_retry: float = 1.0
    sync_interval: float = 0.5
    lock_window: float = 2.0
    confirm_window: float | None = None  # locked and unchanged this long: vote (None: lock_window)
    vote_interval: float = 0.5
    vote_window: float = 2.0
    heartbeat_interval: float = 0.5
    ack_timeout: float = 3.0
    leader_timeout: float = 3.0
    alone_timeout: float = 8.0
    state_interval: float = 1.0
    vehicle_grace: float = 3.0  # a leader without its vehicle this long steps down
    tdm: bool = False  # vote while pooling, one SyncPool per round (swarm.core.election.tdm)


PAPER = Profile()


def fast_profile(round_s: float) -> Profile:
    """Windows derived from the link's TDM round: a message needs about one round to
    reach everyone, so every interval is one round and every window 1.5 rounds
    (2 rounds measured 20% slower with no gain in agreement; 1 round leaves no
    margin for a lost packet). No second lock window: the agent votes as soon as
    the pool locks and the lock spreads with its Selection (N=10, 10% loss: p95
    8.3 s -> 6.3 s, no violation). Timeouts: six rounds, at least 1 s."""
    r = max(round_s, 0.05)
    return Profile(
        name="fast",
        advertize_interval=r,
        startpool_retry=r,
        sync_interval=r,
        lock_window=1.5 * r,
        confirm_window=0.0,
        vote_interval=r,
        vote_window=1.5 * r,
        heartbeat_interval=r,
        ack_timeout=max(6 * r, 1.0),
        leader_timeout=max(6 * r, 1.0),
        alone_timeout=8 * r,
        state_interval=max(r, 0.5),
    )


def tdm_profile(round_s: float, lock_rounds: float = 1.25, vote_rounds: float = 1.5) -> Profile:
    """The ``tdm`` profile (:mod:`swarm.core.election.tdm`): the fast profile's
    intervals and timeouts, the vote exchanged while pooling, and windows of a round
    plus a margin for a lost frame."""
    r = max(round_s, 0.05)
    return replace(
        fast_profile(round_s),
        name="tdm",
        lock_window=lock_rounds * r,
        confirm_window=0.0,
        vote_window=vote_rounds * r,
        tdm=True,
    )


def paper_profile(round_s: float = 0.0) -> Profile:
    """The paper's values, stretched only where the radio makes them impossible.

    The paper's 2 s windows and 0.5 s rates assume a network where a message
    reaches everyone well within a window. On a SiK radio each node speaks once
    per TDM round (multipoint: N windows per round, 2.37 s for 20 radios at
    64 kbps); a vote window shorter than a round ends before any other vote can
    arrive, and every agent elects itself (seen in simulation). So windows are
    at least 1.5 rounds, send intervals at least one round (sending faster only
    queues duplicates in the radio), and timeouts, which the paper leaves open,
    at least five rounds. With up to 8 radios at 64 kbps these are the paper's
    own values.
    """
    r = max(round_s, 0.0)
    window = max(PAPER.lock_window, 1.5 * r)
    interval = max(PAPER.sync_interval, r)
    timeout = max(PAPER.ack_timeout, 5 * r)
    return replace(
        PAPER,
        sync_interval=interval,
        vote_interval=interval,
        heartbeat_interval=interval,
        lock_window=window,
        vote_window=window,
        advertize_interval=max(PAPER.advertize_interval, r),
        startpool_retry=max(PAPER.startpool_retry, r),
        ack_timeout=timeout,
        leader_timeout=timeout,
        alone_timeout=max(PAPER.alone_timeout, 2 * timeout),
    )


#: the names :func:`profile_by_name` knows (the ``--profile`` choices)
PROFILE_NAMES = ("paper", "fast", "tdm")


def profile_by_name(name: str, round_s: float) -> Profile:
    if name == "paper":
        return paper_profile(round_s)
    if name == "fast":
        return fast_profile(round_s)
    if name == "tdm":
        return tdm_profile(round_s)
    raise ValueError(f"unknown profile {name!r}: paper, fast or tdm")


class VotePolicy(Protocol):
    def weight(self, rng: random.Random) -> int: ...


@dataclass
class RandomVote:
    """The paper: a random weight."""

    def weight(self, rng: random.Random) -> int:
        return rng.getrandbits(32)


@dataclass
class BatteryVote:
    """The fullest battery leads (percent in the high byte, random below)."""

    battery: Callable[[], int]

    def weight(self, rng: random.Random) -> int:
        return (max(0, min(255, self.battery())) << 24) | rng.getrandbits(24)


@dataclass
class LinkQualityVote:
    """The best-heard radio leads (RSSI in the high byte, random below)."""

    rssi: Callable[[], int]

    def weight(self, rng: random.Random) -> int:
        return (max(0, min(255, self.rssi())) << 24) | rng.getrandbits(24)
