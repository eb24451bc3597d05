"""The campaign's fault kinds and its continuous invariants, over :class:`swarm.sim.simulate.Sim`.

Theory of operation
-------------------
:class:`FaultSim` is the simulator with what a scenario's ``restarts``, ``pauses``,
``drift`` and ``strict`` ask for (:class:`swarm.sim.scenario.Scenario`); a scenario
without them runs on the plain :class:`Sim` (:func:`make_sim`), so the golden digests
of those runs cannot move.

* A **restart** (``ID@T0-T1``) takes the agent's process down at T0 (nothing it had
  queued is sent, its radio keeps running) and starts a fresh core, parser and
  MAVLink sequence at T1: a real agent keeps no protocol state across a restart (its
  epoch is the pool's digest, its heartbeat sequence starts again, its signing
  timestamps follow the wall clock), so a fresh core is what a restart is.
* A **pause** (``ID@T0-T1``) freezes the core and resumes it with all its state, as
  SIGSTOP and SIGCONT do: the one way a process comes back with state.
* **Drift** (``ID:PPM``) runs an agent's clock fast or slow (:class:`DriftCore`): the
  core sees ``t * (1 + ppm/1e6)``. The radios' TDM clocks do not drift: the air
  model keeps one time base (its hopping sync is not modelled), so drift is the
  hosts' clocks only.
* While a one-way link is cut, agreement is not judged (:meth:`FaultSim._group_key`);
  the swarm must settle after it heals.

``strict`` checks, every virtual second (:meth:`FaultSim._continuous`), besides the
plain run's checks: no agent listed by two leaders for longer than a leader keeps a
silent member (not while a link is cut one way: a leader that cannot hear the other
never lets go of the members they share, see docs/design/simulation.md); no live agent idle (in
no swarm and not electing) for longer than its alone timeout without hearing a
leader to join (the protocol's "Alone" rule); no election (pooling, locked,
electing) longer than ELECT_BOUND_ROUNDS rounds plus its windows; with a size cap, no
pool or swarm larger than the cap (:mod:`swarm.core.election.caps`); every message an
agent sends decodes to itself; and at the end, that the swarm agreed and held after
the last fault healed. A violation names its virtual time.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Any

from radios.mavlink import FrameBuilder, FrameParser
from swarm.core.election.outbox import Out
from swarm.core.election.profiles import profile_by_name
from swarm.core.election.protocol import Core
from swarm.core.wire.message_types import Phase
from swarm.core.wire.messages import decode, encode
from swarm.core.wire.tunnel import COMP_ID, Kind
from swarm.errors import DecodeError
from swarm.sim.scenario import RunResult, Scenario, parse_drift, parse_span
from swarm.sim.simulate import POSE, Sim, Watch

#: an election (pooling, locked, electing) lasting longer than this many TDM rounds
#: plus the profile's windows and its alone timeout violates (N=50 paper: ~70 s)
ELECT_BOUND_ROUNDS = 40
CHECK_EVERY_S = 1.0


@dataclass
class DriftCore(Core):
    """A core whose clock runs ``rate`` times as fast as virtual time."""

    rate: float = 1.0

    def start(self, now: float) -> list[Out]:
        return super().start(now * self.rate)

    def handle(self, msg: Any, now: float) -> list[Out]:
        return super().handle(msg, now * self.rate)

    def tick(self, now: float) -> list[Out]:
        return super().tick(now * self.rate)

    def next_deadline(self) -> float | None:
        d = super().next_deadline()
        return None if d is None else d / self.rate


def make_sim(sc: Scenario, seed: int) -> Sim:
    """The simulator a scenario needs: :class:`FaultSim` only for its own fault kinds."""
    return FaultSim(sc, seed) if sc.extended else Sim(sc, seed)


class FaultSim(Sim):
    """A run with restarts, pauses, drift and (``strict``) continuous invariants."""

    def __init__(self, sc: Scenario, seed: int) -> None:
        super().__init__(sc, seed)
        self.rates = [1.0] * sc.agents
        for spec in sc.drift:
            who, ppm = parse_drift(spec)
            self.rates[who - 1] = 1.0 + ppm / 1e6
        self.cores = [self._new_core(i, c.rng) for i, c in enumerate(self.cores)]
        # (time, agent index, "down"|"up", fresh core?) in time order
        self.spans: list[tuple[float, int, str, bool]] = []
        for specs, fresh in ((sc.restarts, True), (sc.pauses, False)):
            for spec in specs:
                who, t0, t1 = parse_span(spec)
                self.spans += [(t0, who - 1, "down", fresh), (t1, who - 1, "up", fresh)]
        self.spans.sort()
        self._last_event = max([self._last_event] + [s[0] for s in self.spans])
        self._restarts = 0
        self._down: set[int] = set()  # agents down for a restart or a pause
        self._next_check = 0.0
        self._since: dict[tuple[str, int], float] = {}
        self._sent_ok: set[bytes] = set()
        self._seen: set[str] = set()
        self._ended_settled = False
        p = self.cores[0].profile
        windows = p.lock_window + (p.confirm_window or p.lock_window) + p.vote_window
        self.elect_bound = ELECT_BOUND_ROUNDS * self.round_s + 4 * windows + p.alone_timeout
        self.idle_bound = p.alone_timeout + 2 * self.round_s + 1.0
        self.dual_bound = p.ack_timeout + 4 * self.round_s + 1.0

    def _new_core(self, i: int, rng: random.Random) -> Core:
        prof = profile_by_name(self.sc.profile, self.round_s)
        core = DriftCore(i + 1, f"agent{i + 1}", prof, rng=rng, rate=self.rates[i], cap=self.sc.cap)
        core.set_pose(POSE)
        return core

    # -- faults ---------------------------------------------------------------------
    def _start_and_crash(self, t: float, w: Watch) -> None:
        for who, when in self.crash_at:  # a crash while down: it stays down for good
            if when <= t and who.isdigit() and int(who) - 1 in self._down:
                self._down.discard(int(who) - 1)
        while self.spans and self.spans[0][0] <= t:
            _, i, what, fresh = self.spans.pop(0)
            if what == "down" and self.alive[i]:
                self._down.add(i)
                self.alive[i] = False
                self._due[i] = float("inf")
                self.dead_at[i + 1] = t
                w.converged_since = None
                w.last_conv_state = False
            elif what == "up" and i in self._down:
                self._down.discard(i)
                self.alive[i] = True
                self.dead_at.pop(i + 1, None)
                self._since = {k: v for k, v in self._since.items() if k[1] != i}
                if fresh:  # a new process: new core, parser, MAVLink sequence
                    self._restarts += 1
                    seed = (self.seed * 1_000_003 + i * 7919 + self._restarts) & 0xFFFFFFFFFFFF
                    self.cores[i] = self._new_core(i, random.Random(seed))
                    self.parsers[i] = FrameParser(trusted=self.trusted)
                    self.builders[i] = FrameBuilder(i + 1, COMP_ID)
                    self.started[i] = False
                    self.start_at[i] = t
                else:
                    self._due[i] = t
        super()._start_and_crash(t, w)

    def _deadline(self, t: float, out_dl: float | None) -> float:
        nxt = super()._deadline(t, out_dl)
        if self.spans and t + 1e-9 < self.spans[0][0] < nxt:
            nxt = self.spans[0][0]
        return nxt

    # -- connected groups -------------------------------------------------------------
    def _group_key(self, agent: int, t: float) -> int:
        """While a link is cut one way, each agent is its own group: agreement is not
        judged (a swarm is a star: an agent its leader cannot hear is outside it, and
        two leaders may lead side by side) until the link heals; then the run must
        settle again (:meth:`_run_result`)."""
        for k in self.links:
            if k.p >= 1 and k.t0 <= t < k.t1:
                return -agent
        return super()._group_key(agent, t)

    # -- continuous invariants --------------------------------------------------------
    def _write(self, i: int, kind: Kind, targets: tuple[int, ...], body: bytes, t: float) -> None:
        if self.sc.strict and body not in self._sent_ok:
            try:
                ok = encode(decode(body)) == body
            except DecodeError:
                ok = False
            if not ok:
                self._violate(f"agent {i + 1} sent a message that does not decode: {body.hex()}", t)
            elif len(self._sent_ok) < 100_000:
                self._sent_ok.add(body)
        super()._write(i, kind, targets, body, t)

    def _check_dead_leaders(self, t: float) -> None:
        super()._check_dead_leaders(t)
        if self.sc.strict and t >= self._next_check:
            self._next_check = t + CHECK_EVERY_S
            self._continuous(t)

    def _held(self, key: tuple[str, int], cond: bool, t: float, bound: float) -> bool:
        """Whether ``cond`` has held for longer than ``bound`` at ``t``."""
        if not cond:
            self._since.pop(key, None)
            return False
        return t - self._since.setdefault(key, t) > bound

    def _continuous(self, t: float) -> None:
        live = [i for i in range(self.sc.agents) if self.alive[i] and self.started[i]]
        listed: dict[int, int] = {}
        for i in live:
            c = self.cores[i]
            if c.phase == Phase.LEADER:
                for m in c.members:
                    listed[m] = listed.get(m, 0) + 1
        electing = (Phase.POOLING, Phase.LOCKED, Phase.ELECTING)
        cut = any(k.p >= 1 and k.t0 <= t < k.t1 for k in self.links)
        for i in live:
            c = self.cores[i]
            if self._held(("dual", i), listed.get(c.me, 0) > 1 and not cut, t, self.dual_bound):
                self._violate(f"agent {c.me} listed by two leaders for over {self.dual_bound:.1f} s", t)
            alone = c.phase == Phase.IDLE and t * self.rates[i] - c.idle_since > self.idle_bound
            if alone:
                self._violate(
                    f"agent {c.me} in no swarm and not electing for over {self.idle_bound:.1f} s", t
                )
            if self.sc.cap and max(len(c.pool), len(c.members) + 1) > self.sc.cap:
                self._violate(f"agent {c.me}'s pool or swarm holds more than the cap of {self.sc.cap}", t)
            if self._held(("elect", i), c.phase in electing, t, self.elect_bound):
                self._violate(f"agent {c.me}: election not over after {self.elect_bound:.0f} s", t)

    def _violate(self, what: str, t: float) -> None:
        if what not in self._seen:  # each violation once, at its first time
            self._seen.add(what)
            self.violations.append(f"{what} (at t={t:.1f} s)")

    def _judge(self, t: float, w: Watch) -> bool:
        done = super()._judge(t, w)
        self._ended_settled = done
        return done

    def _run_result(self, t: float, w: Watch) -> RunResult:
        long_enough = t >= self._last_event + self.sc.settle_tail_s()  # else: cut short on purpose
        if self.sc.strict and long_enough and not self._ended_settled and not self.violations:
            self.violations.append(
                f"membership did not converge after the last fault (t={self._last_event:.1f} s) "
                f"by the end of the run (t={t:.1f} s)"
            )
        return super()._run_result(t, w)


__all__ = ["CHECK_EVERY_S", "ELECT_BOUND_ROUNDS", "DriftCore", "FaultSim", "make_sim"]
