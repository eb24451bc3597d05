"""``swarm bench messages``: message and frame sizes, bridge latency, JSON ratio.

Figures:

* ``payload_bytes``: the compact encoding of one representative instance of
  every message type; ``frame_bytes`` (signed) and ``frame_bytes_unsigned``: the
  bytes on air of the MAVLink 2 TUNNEL frame the radio bridge sends for it;
* bridge latency, for real: a ``swarm radio-emu`` process with two radios at
  64 kbps (idle channel), two isolated Zenoh sessions, a :class:`RadioBridge` on
  each radio link. A small P2P message is put on one session at random moments
  spread over several TDM rounds and timed to the subscriber callback on the
  other; compared with :func:`radios.sik.timing.model_latency_s` for that frame;
* ``naive_json_ratio``: one election's traffic and a minute of formation flight
  for five agents, as naive JSON (type name, fields by name, agent names instead
  of ids, floats as they are) over the compact bytes, both as TUNNEL payloads.
"""

from __future__ import annotations

import json
import random
import statistics
import tempfile
import threading
import time
from dataclasses import fields
from enum import IntEnum
from typing import Any

import swarm.core.wire.message_types as mt
import swarm.core.wire.messages as sm
from radios.link import open_link
from radios.sik.timing import model_latency_s, tdm_timing
from swarm.cli.procs import start_emulator
from swarm.runtime.bridge.radio_bridge import RadioBridge, bridge_message_frame_bytes
from swarm.runtime.keyspace.transport import Transport, open_session

AIR_KBPS = 64
SERIAL_BAUD = 57600
#: emulator seed whose radio pair locks onto the hopping sequence in well under a
#: second (tests/emu_helpers.FAST_LOCK_SEED); it changes nothing but the lock time
FAST_LOCK_SEED = "16"
LOCK_DEADLINE_S = 60.0
SAMPLE_DEADLINE_S = 3.0

POSE = mt.Pose(48.8566123, 2.3522219, 135.4, heading=271.5, vn=3.25, ve=-1.5, t=12.34)
POOL = frozenset({1, 2, 3, 4, 5})


def representative() -> dict[str, mt.Message]:
    """One typical instance of every message type (five agents, ids 1..5, GCS 255)."""
    task = mt.Task(
        mt.TaskKind.FOLLOW,
        heading=90.0,
        back_m=10.0,
        side_m=5.0,
        assignments=(
            mt.Assignment(2, 1, mt.Side.LEFT),
            mt.Assignment(3, 1, mt.Side.RIGHT),
            mt.Assignment(4, 2, mt.Side.LEFT),
            mt.Assignment(5, 3, mt.Side.RIGHT),
        ),
    )
    msgs: list[mt.Message] = [
        mt.Advertize(1, "agent1", flags=1),
        mt.GSAdvertize(255, "gcs"),
        mt.Heartbeat(1, epoch=3, seq=17, members=POOL, task=task),
        mt.HeartbeatAck(2, seq=17, pose=POSE),
        mt.StartPool(1),
        mt.StartPoolAck(2, mt.PoolStatus.ALREADY_IN_POOL, locked=False, members=POOL),
        mt.SyncPool(1, mt.pool_digest(POOL), locked=True),
        mt.SyncPoolAck(2, same=True, locked=True),
        mt.Selection(2, candidate=4, weight=870, epoch=3),
        mt.PoseReport(POSE),
        mt.AgentState(
            1,
            mt.Phase.LEADER,
            leader=1,
            candidate=1,
            weight=870,
            epoch=3,
            locked=True,
            pool=POOL,
            members=POOL,
        ),
        mt.GSConnect(255, seq=1),
        mt.GSConnectAck(1, seq=1, hb_interval_ms=1000),
        mt.Telemetry(
            1,
            POSE,
            mode=4,
            flags=0b0111,
            phase=mt.Phase.LEADER,
            leader=1,
            battery=87,
            rssi=180,
            remrssi=175,
            groundspeed=3.5,
            rel_alt=20.0,
            climb=0.5,
            gps_fix=3,
            satellites=14,
            home_dist=120.0,
        ),
        mt.GSHeartbeat(255, seq=9),
        mt.Command(255, seq=12, target=0, kind=mt.CommandKind.FOLLOW, heading=45.0),
        mt.CommandAck(1, seq=12, result=mt.AckResult.ACCEPTED),
        mt.NameConflict(3, "agent2", other_id=7),
        mt.AgentNotice(3, mt.NoticeSource.AUTOPILOT, 4, "PreArm: GPS not healthy", repeats=2),
    ]
    out = {type(m).__name__: m for m in msgs}
    missing = {t.__name__ for t in sm.message_types()} - set(out)
    assert not missing, f"no representative instance of {sorted(missing)}"
    return out


# -- naive JSON -------------------------------------------------------------------

ID_FIELDS = {"sender", "candidate", "leader", "target", "other_id", "member", "follows"}
ID_SET_FIELDS = {"members", "pool"}


def _agent_name(agent_id: int) -> str:
    return "gcs" if agent_id == 255 else f"agent{agent_id}"


def _naive(obj: Any, name: str = "") -> Any:
    if isinstance(obj, IntEnum):
        return obj.name
    if isinstance(obj, bool | str | float) or obj is None:
        return obj
    if isinstance(obj, int):
        return _agent_name(obj) if name in ID_FIELDS and obj else obj
    if isinstance(obj, frozenset | set):
        return [_agent_name(i) for i in sorted(obj)] if name in ID_SET_FIELDS else sorted(obj)
    if isinstance(obj, tuple | list):
        return [_naive(o) for o in obj]
    out: dict[str, Any] = {}
    for f in fields(obj):
        out[f.name] = _naive(getattr(obj, f.name), f.name)
    return out


def naive_json(msg: mt.Message) -> bytes:
    """A message as a naive implementation would send it: JSON with the type name."""
    return json.dumps({"type": type(msg).__name__, **_naive(msg)}).encode("utf-8")


def election_traffic(
    agents: int = 5, seconds: float = 60.0, pose_hz: float = 4.0, seed: int = 1
) -> list[mt.Message]:
    """One election's messages and a minute of formation flight for ``agents`` agents."""
    rng = random.Random(seed)
    ids = list(range(1, agents + 1))
    pool = frozenset(ids)
    leader = ids[-1]
    members = frozenset(i for i in ids if i != leader)
    out: list[mt.Message] = [mt.Advertize(i, _agent_name(i), flags=1) for i in ids]
    # pooling: agent 1 starts, everyone acks, pools synced until unchanged and locked
    out += [mt.StartPool(1) for _ in ids[1:]]
    out += [mt.StartPoolAck(i, mt.PoolStatus.SUCCESS, members=pool) for i in ids[1:]]
    for locked in (False, True):
        for i in ids:
            for _ in ids[1:]:
                out.append(mt.SyncPool(i, mt.pool_digest(pool), locked=locked))
                out.append(mt.SyncPoolAck(i, same=True, locked=locked))
    # votes: everyone to everyone
    out += [
        mt.Selection(i, candidate=leader, weight=rng.randrange(100, 1000), epoch=1)
        for i in ids
        for _ in ids[1:]
    ]
    task = mt.Task(
        mt.TaskKind.FOLLOW,
        heading=90.0,
        assignments=tuple(
            mt.Assignment(m, leader, mt.Side.LEFT if m % 2 else mt.Side.RIGHT) for m in sorted(members)
        ),
    )

    def pose(i: int, t: float) -> mt.Pose:
        return mt.Pose(
            48.8566 + 1e-4 * i + rng.uniform(-1e-5, 1e-5),
            2.3522 + 1e-4 * t + rng.uniform(-1e-5, 1e-5),
            135.0 + rng.uniform(-0.5, 0.5),
            heading=90.0 + rng.uniform(-3, 3),
            vn=rng.uniform(-0.3, 0.3),
            ve=3.0 + rng.uniform(-0.3, 0.3),
            t=t,
        )

    for s in range(int(seconds)):
        for m in sorted(members):
            out.append(mt.Heartbeat(leader, epoch=1, seq=s & 0xFF, members=members, task=task))
            out.append(mt.HeartbeatAck(m, seq=s & 0xFF, pose=pose(m, float(s))))
    for k in range(int(seconds * pose_hz)):
        out += [mt.PoseReport(pose(i, k / pose_hz)) for i in ids]
    return out


def json_ratio(msgs: list[mt.Message]) -> tuple[int, int]:
    """(compact bytes, naive JSON bytes) of ``msgs`` as TUNNEL payloads."""
    return sum(len(sm.encode(m)) for m in msgs), sum(len(naive_json(m)) for m in msgs)


# -- bridge latency ------------------------------------------------------------------


def _probe(i: int) -> mt.Selection:
    # epoch 257 ends the payload with a non-zero byte: MAVLink 2 trims nothing
    return mt.Selection(1, candidate=2, weight=i, epoch=257)


class _Probes:
    """When each probe (a Selection of epoch 257, numbered by its weight) arrived."""

    def __init__(self) -> None:
        self.arrivals: dict[int, float] = {}
        self.cond = threading.Condition()

    def on_inbox(self, msg: mt.Message) -> None:
        if isinstance(msg, mt.Selection) and msg.epoch == 257:
            with self.cond:
                self.arrivals.setdefault(msg.weight, time.monotonic())
                self.cond.notify_all()

    def wait_for(self, i: int, timeout: float) -> float | None:
        deadline = time.monotonic() + timeout
        with self.cond:
            while i not in self.arrivals:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(left)
            return self.arrivals[i]


def _radio_pair(d: str, closers: list[Any]) -> tuple[Transport, Transport, list[RadioBridge]]:
    """Two bridged nodes ``a1`` and ``a2`` on the emulator's radios (in ``d``); each
    thing opened is added to ``closers``."""
    emu, paths = start_emulator(2, d, "--air-speed", str(AIR_KBPS), "--seed", FAST_LOCK_SEED)
    closers.append(emu.stop)
    links = [open_link(p) for p in paths]
    closers += [lk.close for lk in links]
    sessions = [open_session(), open_session()]  # no endpoints: isolated
    closers += [s.close for s in sessions]
    bridges = [
        RadioBridge(s, lk, name=f"a{i + 1}", agent_id=i + 1).start()
        for i, (s, lk) in enumerate(zip(sessions, links, strict=True))
    ]
    closers += [b.close for b in bridges]
    ta, tb = Transport("a1", sessions[0]), Transport("a2", sessions[1])
    closers += [ta.close, tb.close]
    return ta, tb, bridges


def _lock(ta: Transport, tb: Transport, bridges: list[RadioBridge], probes: _Probes) -> None:
    """Advertise until each bridge knows the other, then one probe through.

    Raises:
        RuntimeError: not within LOCK_DEADLINE_S.
    """
    deadline = time.monotonic() + LOCK_DEADLINE_S
    while time.monotonic() < deadline and not all(len(b.peers()) == 2 for b in bridges):
        ta.advertise(mt.Advertize(1, "a1"))
        tb.advertise(mt.Advertize(2, "a2"))
        time.sleep(0.3)
    warm = 1_000_000
    while time.monotonic() < deadline:
        ta.send("a2", _probe(warm))
        if probes.wait_for(warm, 1.0) is not None:
            return
        warm += 1
    raise RuntimeError(f"the radio pair did not lock within {LOCK_DEADLINE_S:.0f} s")


def bench_latency(samples: int) -> dict[str, Any]:
    rng = random.Random(1)
    round_s = tdm_timing(AIR_KBPS).round_s(2)
    probes = _Probes()
    lat: list[float] = []
    lost = 0
    with tempfile.TemporaryDirectory() as d:
        closers: list[Any] = []
        try:
            ta, tb, bridges = _radio_pair(d, closers)
            tb.on_inbox(probes.on_inbox)
            _lock(ta, tb, bridges, probes)
            for i in range(samples):
                time.sleep(rng.uniform(0.05, 0.05 + 3 * round_s))  # uniform over the TDM round
                t0 = time.monotonic()
                ta.send("a2", _probe(i))
                t1 = probes.wait_for(i, SAMPLE_DEADLINE_S)
                if t1 is None:
                    lost += 1
                else:
                    lat.append(t1 - t0)
        finally:
            for close in reversed(closers):
                try:
                    close()
                except Exception:  # best effort: every resource gets its chance
                    pass
    return _latency_figures(lat, lost, samples)


def _latency_figures(lat: list[float], lost: int, samples: int) -> dict[str, Any]:
    """The measured latencies against the TDM model's for the probe's frame."""
    frame_len = bridge_message_frame_bytes(_probe(samples), signed=False)
    model = model_latency_s(tdm_timing(AIR_KBPS), frame_len, SERIAL_BAUD)
    lat.sort()
    p50 = statistics.median(lat) if lat else float("nan")
    p99 = lat[min(len(lat) - 1, int(0.99 * len(lat)))] if lat else float("nan")
    return {
        "bridge_latency_ms_p50": round(1000 * p50, 1),
        "bridge_latency_ms_p99": round(1000 * p99, 1),
        "model_latency_ms_p50": round(1000 * model["p50"], 1),
        "model_latency_ms_p99": round(1000 * model["p99"], 1),
        "latency_ratio_p50": round(p50 / model["p50"], 3),
        "latency_frame_bytes": frame_len,
        "latency_samples": len(lat),
        "latency_lost": lost,
    }


def run(quick: bool = False) -> dict[str, Any]:
    msgs = representative()
    out: dict[str, Any] = {
        "payload_bytes": {k: len(sm.encode(m)) for k, m in msgs.items()},
        "frame_bytes": {k: bridge_message_frame_bytes(m, signed=True) for k, m in msgs.items()},
        "frame_bytes_unsigned": {k: bridge_message_frame_bytes(m, signed=False) for k, m in msgs.items()},
    }
    out.update(bench_latency(samples=15 if quick else 60))
    traffic = election_traffic()
    compact, naive = json_ratio(traffic)
    out.update(
        {
            "traffic_messages": len(traffic),
            "traffic_compact_bytes": compact,
            "traffic_json_bytes": naive,
            "naive_json_ratio": round(naive / compact, 2),
        }
    )
    unchanged = mt.SyncPool(1, mt.pool_digest(POOL), locked=False)
    out["targets"] = {
        "pose_payload_le_16": out["payload_bytes"]["PoseReport"] <= 16,
        "heartbeat_ack_payload_le_18": out["payload_bytes"]["HeartbeatAck"] <= 18,
        "unchanged_syncpool_le_8": len(sm.encode(unchanged)) <= 8,
        "signed_heartbeat_ack_frame_le_48": out["frame_bytes"]["HeartbeatAck"] <= 48,
        "latency_p50_within_1_5x_model": out["latency_ratio_p50"] <= 1.5,
        "naive_json_ratio_ge_4": out["naive_json_ratio"] >= 4,
    }
    return out
