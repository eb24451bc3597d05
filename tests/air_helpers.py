"""Drivers for :class:`radios.air.AirModel` in virtual time (no sleeping, no threads).

:class:`AirBench` owns one model and a manual clock. :meth:`AirBench.run` moves the
clock forward in steps of at most ``max_step`` seconds, stopping early at every
deadline the model announces, so serial output is collected at the moment its
last byte leaves the radio. Every node's output is parsed into whole MAVLink
frames and kept with the virtual time at which it was complete; every packet put
on air is logged through the model's ``on_air`` callback.

Feeders are callables ``feed(bench)`` run at every step before the model
advances; :func:`saturate` keeps one radio's serial line busy with frames.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from radios.air import AirModel, LossModel, RadioConfig
from radios.mavlink import Frame, FrameBuilder, FrameParser


@dataclass(frozen=True)
class AirPacket:
    sender: int
    payload: bytes
    t_start: float
    t_end: float
    kind: str


@dataclass(frozen=True)
class RxFrame:
    t: float
    frame: Frame


Feeder = Callable[["AirBench"], None]


class AirBench:
    """One AirModel, a virtual clock, per-node frame parsers and an air log."""

    def __init__(
        self,
        configs: list[RadioConfig],
        *,
        seed: int = 0,
        losses: list[LossModel] | None = None,
        flow_control: bool = False,
        take_output: list[bool] | None = None,
    ) -> None:
        self.air: list[AirPacket] = []
        self.model = AirModel(
            configs,
            seed=seed,
            losses=losses,
            flow_control=flow_control,
            on_air=self._on_air,
        )
        self.configs = configs
        self.now = 0.0
        n = len(configs)
        self.parsers = [FrameParser() for _ in range(n)]
        self.rx: list[list[RxFrame]] = [[] for _ in range(n)]
        self.raw: list[bytearray] = [bytearray() for _ in range(n)]
        # a host that never reads its port leaves the radio's output buffer full
        self.reading = list(take_output) if take_output is not None else [True] * n
        self.lock_time: list[float | None] = [None] * n

    def _on_air(self, sender: int, payload: bytes, t0: float, t1: float, kind: str) -> None:
        self.air.append(AirPacket(sender, bytes(payload), t0, t1, kind))

    def write(self, node: int, data: bytes) -> None:
        self.model.host_write(node, data, self.now)

    def _collect(self) -> None:
        for i in range(len(self.rx)):
            if self.lock_time[i] is None and self.model.status(i)["locked"]:
                self.lock_time[i] = self.now
            if not self.reading[i]:
                continue
            out = self.model.take_output(i, self.now)
            if out:
                self.raw[i] += out
                for f in self.parsers[i].feed(out):
                    self.rx[i].append(RxFrame(self.now, f))

    def run(self, until: float, feed: Feeder | None = None, max_step: float = 0.001) -> None:
        """Advance virtual time to ``until``, calling ``feed`` at every step."""
        while True:
            if feed is not None:
                feed(self)
            self.model.advance(self.now)
            self._collect()
            if self.now >= until:
                return
            nxt = self.now + max_step
            dl = self.model.next_deadline()
            # a deadline at or before now (see test_next_deadline_is_in_the_future)
            # would stall the clock: ignore it and step on
            if dl is not None and self.now < dl < nxt:
                nxt = dl
            self.now = min(max(nxt, self.now + 1e-6), until)

    def locked_at(self) -> float:
        """When every radio had locked to the hopping sequence (inf if not yet)."""
        return max((t if t is not None else float("inf")) for t in self.lock_time)

    def frames(self, node: int, since: float = 0.0, until: float = float("inf")) -> list[Frame]:
        return [r.frame for r in self.rx[node] if since <= r.t < until]

    def status(self, node: int) -> dict[str, Any]:
        return self.model.status(node)


def tunnel_of_length(fb: FrameBuilder, frame_len: int, fill: int = 0x55) -> bytes:
    """A MAVLink 2 TUNNEL frame of exactly ``frame_len`` bytes (22..145)."""
    k = frame_len - 17  # 10 header + 5 fixed payload bytes + 2 CRC
    if not 5 <= k <= 128:
        raise ValueError(f"no TUNNEL frame is {frame_len} bytes long")
    raw = fb.tunnel(bytes([fill]) * k)
    assert len(raw) == frame_len
    return raw


def saturate(node: int, make_frame: Callable[[], bytes], ahead_s: float = 0.01) -> Feeder:
    """Keep ``node``'s serial line at least ``ahead_s`` seconds ahead with frames.
    With flow control the model reports an infinite backlog while CTS holds the
    host, so the host never overruns the radio."""

    def feed(bench: AirBench) -> None:
        m = bench.model
        while m.serial_backlog_s(node, bench.now) < ahead_s:
            m.host_write(node, make_frame(), bench.now)

    return feed


def sent_by(bench: AirBench, node: int, kind: str | None = "data") -> list[AirPacket]:
    return [p for p in bench.air if p.sender == node and (kind is None or p.kind == kind)]
