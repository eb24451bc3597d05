"""Deterministic simulation: N protocol cores over the SiK air model, in virtual time.

Theory of operation
-------------------
Each simulated agent is a :class:`swarm.core.election.protocol.Core` behind a radio of
:class:`radios.air.AirModel` (the same model the pty emulator runs). What a core
sends is encoded exactly as the radio bridge does it: compact message in a
MAVLink 2 TUNNEL frame, payload type by key kind, identical P2P payloads to several
peers merged into one multicast frame. Frames go through the model's serial
pacing, TDM and loss; what a radio outputs is parsed, filtered by target and
decoded back into the core. There is no wall clock, so a run is exactly repeatable
for its seed (``tests/test_sim_golden.py`` pins its bytes and times).

The loop is event-driven: it steps only for what can change a core (a core's
deadline, a start or crash, the invariants' 100 ms sample, and the arrival at a
host of the first frame its agent handles, computed from the air model's
closed-form serial clock by :class:`swarm.sim.hoststream.HostStreams`); the air's
own events run between steps at their own times. A frame every receiver of a
broadcast gets is CRC-checked and decoded once (:meth:`Sim.tunnel_of`); one
message to many peers is encoded once. What a run is (:class:`Scenario`, its faults,
its length, :class:`RunResult`) lives in :mod:`swarm.sim.scenario`; seeds over
processes in :mod:`swarm.sim.parallel`.

Scenarios add loss (uniform, bursty, per directed link), partitions (groups that
cannot hear each other for a while; overlapping ones split each other's groups),
crashes (an agent stops for good; ``leader`` means whoever leads then) and late
starts; restarts, pauses, drift and the campaign's continuous invariants are
:mod:`swarm.sim.faultsim`'s. After each run the invariants are checked:

* converged: at some point every live agent was in one agreed swarm per
  connected group (one leader, every other agent its member and listed by it)
  and that held for ``settle`` seconds; a run that never gets there violates
  (with a size cap, sub-swarms of at most the cap: :mod:`swarm.sim.subswarms`);
* after convergence, two leaders in one connected group never coexist for more
  than SPLIT_LIMIT_S or SPLIT_ROUNDS TDM rounds, whichever is longer (the merge rule's
  time), each pair of leaders timed from when
  they are first in one group;
* no member follows a dead leader for longer than its leader timeout (+ a round);
* whether every live agent is in the agreed swarm at the end is reported
  (``stable_at_end``): under heavy loss members are expelled and re-join, so
  a run may end in the middle of a re-join without anything being wrong;
* the air time used stays within the channel's capacity.

A failing seed is reported with the exact command that replays it.
"""

from __future__ import annotations

import random
import statistics
from collections import defaultdict
from dataclasses import dataclass

from radios.air import AirModel, LossModel, RadioConfig
from radios.air.serial import drain
from radios.loss import GilbertElliott, UniformLoss
from radios.mavlink import HEADER_V2, MSG_TUNNEL, STX_V2, FrameBuilder, FrameParser, frame_length
from swarm.core.election.outbox import ADVERTIZE, Out
from swarm.core.election.profiles import profile_by_name
from swarm.core.election.protocol import Core
from swarm.core.wire.message_types import Advertize, Message, Phase, Pose
from swarm.core.wire.messages import decode, encode
from swarm.core.wire.tunnel import COMP_ID, Kind, group, pack, unpack_tunnel
from swarm.errors import DecodeError
from swarm.sim.hoststream import HostStreams
from swarm.sim.scenario import (
    Link,
    LinkLoss,
    Partition,
    PartitionLoss,
    RunResult,
    Scenario,
    parse_at,
    run_length,
)
from swarm.sim.subswarms import capped_agreement, split_pairs

POSE = Pose(47.397742, 8.545594, 500.0)
_Tunnel = tuple[Kind, int, bytes, Message]
_CACHE_MAX = 4096  # decoded frames kept per run (a cache: its size changes no result)
#: two leaders of one connected group must merge within the longer of these: the
#: merge rule is three one-way steps (the smaller leader hears the larger's Advertize,
#: its Heartbeat reaches the larger, the larger's Heartbeat lists it), each at least one
#: TDM round; SPLIT_ROUNDS lets each be lost once. 20 s alone was 3.5 rounds on a
#: channel of 48 radios (5.7 s rounds), barely above the loss-free 3.
SPLIT_LIMIT_S = 20.0
SPLIT_ROUNDS = 6


@dataclass
class Watch:
    """What :meth:`Sim.run` has seen so far: agreement, election, crash and failover."""

    converged_since: float | None = None
    elect_s: float | None = None
    failover_s: float | None = None
    crash_time: float | None = None
    leader: int = 0
    last_conv_state: bool = False


class Sim:
    """One seeded run."""

    def __init__(self, sc: Scenario, seed: int) -> None:
        self.sc = sc
        self.seed = seed
        rng = random.Random(seed)
        n = sc.agents
        fw = "standard" if n <= 2 else "multipoint"
        cfgs = [
            RadioConfig(
                air_kbps=sc.air_kbps, serial_baud=sc.serial_baud, firmware=fw, node_id=i, node_count=max(n, 2)
            )
            for i in range(n)
        ]
        losses: list[LossModel] = []
        if sc.loss:
            losses.append(UniformLoss(sc.loss))
        if sc.burst_loss:
            losses.append(GilbertElliott.parse(sc.burst_loss))
        self.partitions = [Partition.parse(p) for p in sc.partitions]
        if self.partitions:
            losses.append(PartitionLoss(self.partitions))
        self.links = [Link.parse(x) for x in sc.links]
        if self.links:
            losses.append(LinkLoss(self.links))
        self.air = AirModel(cfgs, seed=rng.getrandbits(32), losses=losses)
        round_s = self.air.round_s(0)
        self.round_s = round_s
        self.split_limit_s = max(SPLIT_LIMIT_S, SPLIT_ROUNDS * round_s)
        self.duration = sc.duration if sc.duration is not None else run_length(round_s)
        profile = profile_by_name(sc.profile, round_s)
        self.cores = [
            Core(i + 1, f"agent{i + 1}", profile, rng=random.Random(rng.getrandbits(64)), cap=sc.cap)
            for i in range(n)
        ]
        for c in self.cores:
            c.set_pose(POSE)
        self.builders = [FrameBuilder(i + 1, COMP_ID) for i in range(n)]
        self.trusted: set[bytes] = set()  # frames whose CRC one receiver has checked
        self._decoded: dict[bytes, _Tunnel | None] = {}
        self.parsers = [FrameParser(trusted=self.trusted) for _ in range(n)]
        self.hosts = HostStreams(self)  # when each host next gets a frame it handles
        self.start_at = [0.0] * n
        for spec in sc.late:
            who, t = parse_at(spec)
            self.start_at[int(who) - 1] = t
        self.crash_at: list[tuple[str, float]] = [parse_at(s) for s in sc.crashes]
        self.alive = [True] * n
        self.started = [False] * n
        self.dead_at: dict[int, float] = {}
        self.sent = [0] * n
        self.violations: list[str] = []
        self.following_dead_since: dict[int, float] = {}
        self._due = [0.0] * n  # each core's next deadline (cached)
        self._check_at = 0.0  # the invariants' next sample
        self._split_since: dict[tuple[int, int], float] = {}  # leader pairs split since
        # a run goes on at least until its last partition heals and its last agent starts
        ends = [p.t1 for p in self.partitions] + [k.t1 for k in self.links if k.t1 != float("inf")]
        self._last_event = max(ends + self.start_at + [0.0])

    # -- wiring -------------------------------------------------------------------
    def _send(self, i: int, outs: list[Out], t: float) -> None:
        if not outs or not self.alive[i]:
            return
        p2p: list[tuple[int, bytes]] = []
        prev: Message | None = None
        data = b""
        for o in outs:
            if o.msg is not prev:  # one message to many peers is encoded once
                prev = o.msg
                data = encode(o.msg)
            if o.to == ADVERTIZE:
                kind = Kind.ADVERTIZE if isinstance(o.msg, Advertize) else Kind.GS_ADVERTIZE
                self._write(i, kind, (0,), data, t)
            else:
                p2p.append((o.to, data))
        for kind, targets, data in group(p2p):
            self._write(i, kind, targets, data, t)

    def _write(self, i: int, kind: Kind, targets: tuple[int, ...], body: bytes, t: float) -> None:
        target, ptype, payload = pack(kind, targets, body)
        frame = self.builders[i].tunnel(payload, target_system=target, payload_type=ptype)
        self.sent[i] += 1
        self.air.host_write(i, frame, t)

    def _receive(self, i: int, t: float) -> None:
        radio = self.air.radios[i]
        if not radio.host_ready and not radio.outbuf:
            return
        drain(radio, t)
        if not self._frame_ready(i, radio.host_ready):
            return  # the bytes wait in the radio's output: the parser could not finish a frame
        self.deliver(i, t)

    def deliver(self, i: int, t: float) -> None:
        """Feed what radio ``i`` has output to its parser, and the frames for agent
        ``i`` to its core."""
        data = self.air.take_output(i, t)
        if not data:
            return
        frames = self.parsers[i].feed(data)
        if not self.alive[i] or not self.started[i]:
            return
        # what the core answers to the frames of one read leaves together, as the
        # bridge's 5 ms hold sends it: identical payloads merge into one MULTI frame
        outs: list[Out] = []
        me = i + 1
        for f in frames:
            tun = self.tunnel_of(f.raw)
            if tun is None:
                continue
            kind, target, ids, msg = tun
            if target not in (0, me) or (kind == Kind.MULTI and me not in ids):
                continue
            outs += self._on_message(i, f.raw[5], kind, msg, t)
        self._send(i, outs, t)

    def _frame_ready(self, i: int, ready: bytearray) -> bool:
        """Whether the bytes the radio has output for the host (after those the parser
        holds) can complete a frame or need scanning: the parser yields the same frames
        at the same step whether it is fed every step or only then."""
        pend = self.parsers[i].held
        if len(pend) >= 3:
            head: bytes | bytearray = pend
        elif pend:
            head = bytes(pend) + bytes(ready[:3])
        else:
            head = ready
        if len(head) < 3:
            return False  # no frame is shorter than 8 bytes: nothing to yield yet
        flen = frame_length(head, 0)
        return flen is None or len(pend) + len(ready) >= flen

    def tunnel_of(self, raw: bytes) -> _Tunnel | None:
        """The swarm message a whole frame carries (kind, target, addressees, message),
        or None (not a TUNNEL frame, not the swarm's, not a valid message). Every
        receiver of a broadcast gets the same frame: it is decoded once (messages are
        frozen) and the answer shared."""
        cache = self._decoded
        if raw in cache:
            return cache[raw]
        if len(cache) > _CACHE_MAX or len(self.trusted) > 2 * _CACHE_MAX:
            cache.clear()
            self.trusted.clear()
        res: _Tunnel | None = None
        if raw[0] == STX_V2 and raw[7] | (raw[8] << 8) | (raw[9] << 16) == MSG_TUNNEL:
            try:
                tun = unpack_tunnel(raw[HEADER_V2 : HEADER_V2 + raw[1]])
                if tun is not None:
                    res = (tun[0], tun[1], tun[2], decode(tun[3]))
            except DecodeError:
                res = None
        cache[raw] = res
        return res

    def _on_message(self, i: int, sender: int, kind: Kind, msg: Message, t: float) -> list[Out]:
        """A message received by agent ``i`` (a subclass adds other streams)."""
        self._due[i] = t
        return self.cores[i].handle(msg, t)

    # -- running ------------------------------------------------------------------
    def _group_key(self, agent: int, t: float) -> int:
        """Which connected group ``agent`` is in at ``t``: the partitions' groups, each
        one splitting the others' when they overlap (a subclass with one-way links
        refines it)."""
        key = 0
        for p in self.partitions:
            if p.t0 <= t < p.t1:
                key = key * 256 + p.group_of(agent) + 1
        return key

    def _agreement(self) -> tuple[bool, int]:
        """(every live agent in one agreed swarm per connected group, a leader id)."""
        live = [c for i, c in enumerate(self.cores) if self.alive[i] and self.started[i]]
        if not live:
            return True, 0
        t = self.air.now
        if self.sc.cap:  # sub-swarms: every live agent in a led swarm of at most cap
            return capped_agreement(live, self.sc.cap, lambda a: self._group_key(a, t))
        groups: dict[int, list[Core]] = defaultdict(list)
        for c in live:
            groups[self._group_key(c.me, t)].append(c)
        leader_id = 0
        for members in groups.values():
            leaders = [c for c in members if c.phase == Phase.LEADER]
            if len(leaders) != 1:
                return False, 0
            lead = leaders[0]
            leader_id = lead.me
            for c in members:
                if c is lead:
                    continue
                if c.phase != Phase.MEMBER or c.leader != lead.me or c.me not in lead.members:
                    return False, 0
        return True, leader_id

    def run(self) -> RunResult:
        t = 0.0
        w = Watch()
        self.hosts.start()
        while t <= self.duration:
            self._start_and_crash(t, w)
            self.air.advance(t)
            self.hosts.serve_due(t)
            self._tick_cores(t)
            if t + 1e-9 >= self._check_at:
                self._check_at = t + 0.1
                if self._judge(t, w):
                    break
                self._check_dead_leaders(t)
                self._check_split(t, w.elect_s is not None or w.failover_s is not None)
            t = self._next_time(t, self.hosts.next_due())
        return self._run_result(t, w)

    def _start_and_crash(self, t: float, w: Watch) -> None:
        """The starts and the crash due at ``t`` (one crash per step)."""
        n = self.sc.agents
        for i in range(n) if not all(self.started) else ():
            if not self.started[i] and t >= self.start_at[i]:
                self.started[i] = True
                self._send(i, self.cores[i].start(t), t)
                self._due[i] = t
        for k, (who, when) in enumerate(list(self.crash_at)):
            if t >= when:
                victim = w.leader if who == "leader" else int(who)
                if who == "leader" and victim == 0:
                    continue  # no leader yet: wait
                self.crash_at.pop(k)
                if 1 <= victim <= n and self.alive[victim - 1]:
                    self.alive[victim - 1] = False
                    self._due[victim - 1] = float("inf")  # never ticks again
                    self.dead_at[victim] = t
                    w.crash_time = t
                    w.converged_since = None
                    w.last_conv_state = False
                break

    def _tick_cores(self, t: float) -> None:
        thr = t + 1e-9
        due = self._due
        if min(due) > thr:
            return  # no core is due (most steps are the air's)
        for i in [i for i, d in enumerate(due) if d <= thr]:
            if self.alive[i] and self.started[i]:
                core = self.cores[i]
                self._send(i, core.tick(t), t)
                d = core.next_deadline()
                self._due[i] = d if d is not None else float("inf")

    def _judge(self, t: float, w: Watch) -> bool:
        """Agreement at ``t``: the election and failover times once it has held for
        ``settle``; True when the run can end (nothing more is to happen)."""
        ok, lead = self._agreement()
        if ok and all(self.started):
            if not w.last_conv_state:
                w.converged_since = t
                w.leader = lead
            w.last_conv_state = True
            if w.converged_since is not None and t - w.converged_since >= self.sc.settle:
                if w.crash_time is None and w.elect_s is None:
                    w.elect_s = w.converged_since - max(self.start_at)
                if w.crash_time is not None and w.failover_s is None and w.converged_since >= w.crash_time:
                    w.failover_s = w.converged_since - w.crash_time
                if not self.crash_at and t >= self._last_event:
                    return True
        else:
            w.last_conv_state = False
        if ok:
            w.leader = lead
        return False

    def _run_result(self, t: float, w: Watch) -> RunResult:
        ok, lead = self._agreement()
        if w.elect_s is None and not (self.sc.crashes and w.failover_s is not None):
            self.violations.append("never converged (no agreed swarm held for the settle time)")
        util = self.air.utilisation(t)
        if util > 1.0:
            self.violations.append(f"air utilisation {util:.2f} above capacity")
        live = [i for i in range(self.sc.agents) if self.alive[i]]
        return RunResult(
            seed=self.seed,
            converged=ok,
            elect_s=w.elect_s,
            failover_s=w.failover_s,
            violations=self.violations,
            air_utilisation=util,
            messages_per_agent=sum(self.sent[i] for i in live) / max(len(live), 1),
            leader=lead,
            end_s=t,
            stable_at_end=ok,
        )

    def _check_split(self, t: float, converged_once: bool) -> None:
        """After convergence, two leaders in one connected group must not coexist for
        longer than ``split_limit_s`` (SPLIT_LIMIT_S, or SPLIT_ROUNDS TDM rounds if longer:
        the merge rule needs an Advertize and two Heartbeats).
        Each pair of leaders is timed from when they are first in one group: a split
        that partitions end and another that they start are two splits."""
        if not converged_once:
            return
        live = [c for i, c in enumerate(self.cores) if self.alive[i] and self.started[i]]
        pairs = split_pairs(live, self.sc.cap, lambda a: self._group_key(a, t))
        self._split_since = {p: self._split_since.get(p, t) for p in pairs}
        limit = self.split_limit_s
        if any(t - since > limit for since in self._split_since.values()):
            msg = f"two leaders in one connected group for over {limit:.0f} s"
            msg += " (their swarms fit under the cap)" if self.sc.cap else ""
            if msg not in self.violations:
                self.violations.append(msg)

    def _check_dead_leaders(self, t: float) -> None:
        limit = self.cores[0].profile.leader_timeout + 2 * self.round_s
        for i, c in enumerate(self.cores):
            if not self.alive[i] or c.phase != Phase.MEMBER:
                self.following_dead_since.pop(i, None)
                continue
            if c.leader in self.dead_at:
                since = max(self.dead_at[c.leader], self.following_dead_since.setdefault(i, t))
                if t - since > limit:
                    msg = f"agent {i + 1} followed dead leader {c.leader} for over {limit:.1f} s"
                    if msg not in self.violations:
                        self.violations.append(msg)

    def _next_time(self, t: float, out_dl: float | None) -> float:
        """The next step: the earliest of a core's deadline, a host's next frame
        (``out_dl``, :class:`~swarm.sim.hoststream.HostStreams`), a start, a crash and
        the next sample of the invariants (every 100 ms). The air's own events before it
        run at their own times meanwhile (``HostStreams.run_air``): only one that gives
        a host output can bring the step forward."""
        return max(self.hosts.run_air(t, self._deadline(t, out_dl)), t + 1e-4)

    def _deadline(self, t: float, out_dl: float | None) -> float:
        """The earliest deadline after ``t`` other than the air's (a subclass adds its own)."""
        thr = t + 1e-9
        nxt = self._check_at
        if out_dl is not None and thr < out_dl < nxt:
            nxt = out_dl
        due, alive, started, start_at = self._due, self.alive, self.started, self.start_at
        m = min(due)
        if thr < m and all(started):  # the common case: every core started (a dead one: inf)
            return min(m, nxt, *[x for _, x in self.crash_at if thr < x])
        for i in range(len(due)):
            if started[i]:
                if not alive[i]:
                    continue
                x = due[i]
            else:
                x = start_at[i]
            if thr < x < nxt:
                nxt = x
        for _, x in self.crash_at:
            if thr < x < nxt:
                nxt = x
        return nxt


def pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    s = sorted(values)
    k = min(len(s) - 1, max(0, round(q * (len(s) - 1))))
    return round(s[k], 3)


def pct2(values: list[float]) -> dict[str, float | None]:
    """The median and the 95th percentile of ``values`` (None: no values)."""
    return {"p50": pct(values, 0.5), "p95": pct(values, 0.95)}


def elect_stats(values: list[float]) -> dict[str, float | None]:
    return {"p50": statistics.median(values) if values else None}
