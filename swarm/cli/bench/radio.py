"""``swarm bench radio``: the emulator measured against the SiK model.

Everything runs for real: a ``swarm radio-emu`` process, pseudo terminals, and
hosts writing MAVLink 2 frames into them. Figures:

* goodput: one host saturates a radio pair (64 kbps air, 115200 serial so the air
  is the bottleneck, CTS flow control on as a properly wired radio has), the other
  counts whole frames; compared with :func:`radios.sik.timing.model_goodput`;
* latency: small frames sent at random moments on an idle pair at the default
  57600 serial rate, compared with :func:`radios.sik.timing.model_latency_s`;
* round: the TDM round for 3 radios (multipoint firmware, one window per node);
* CPU: the emulator process with 10 radios while every host saturates its radio.
"""

from __future__ import annotations

import os
import random
import select
import statistics
import struct
import tempfile
import time
import tty
from typing import Any

from radios.link import open_link
from radios.mavlink import FrameBuilder, FrameParser
from radios.sik.timing import model_goodput, model_latency_s, tdm_timing
from swarm.cli.procs import cpu_seconds, start_emulator

AIR_KBPS = 64
FILL = bytes(range(1, 39))  # a 55-byte TUNNEL frame (no zeros for MAVLink 2 to trim)


def _raw_open(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    return fd


def _pump(
    fds_out: list[int],
    fds_in: list[int],
    frame: bytes,
    seconds: float,
    warmup: float,
    stop_sending_at: float | None = None,
) -> dict[int, int]:
    """Write ``frame`` back to back into every fd of ``fds_out`` and count the frame
    bytes arriving on ``fds_in`` after ``warmup`` seconds. One thread, poll()."""
    parsers = {fd: FrameParser() for fd in fds_in}
    got = {fd: 0 for fd in fds_in}
    pending = {fd: b"" for fd in fds_out}
    start = time.monotonic()
    end = start + warmup + seconds
    poller = select.poll()
    for fd in set(fds_out) | set(fds_in):
        mask = (select.POLLOUT if fd in pending else 0) | (select.POLLIN if fd in parsers else 0)
        poller.register(fd, mask)
    while (now := time.monotonic()) < end:
        for fd, ev in poller.poll(100):
            if ev & select.POLLIN and fd in parsers:
                try:
                    data = os.read(fd, 4096)
                except BlockingIOError:
                    data = b""
                n = sum(len(f.raw) for f in parsers[fd].feed(data))
                if now - start >= warmup:
                    got[fd] += n
            if ev & select.POLLOUT and fd in pending:
                buf = pending[fd] or frame * 4
                try:
                    k = os.write(fd, buf)
                except BlockingIOError:
                    k = 0
                pending[fd] = buf[k:]
    return got


def bench_goodput(seconds: float, warmup: float) -> dict[str, Any]:
    frame = FrameBuilder(1, 1).tunnel(FILL)
    with tempfile.TemporaryDirectory() as d:
        emu, links = start_emulator(
            2, d, "--air-speed", str(AIR_KBPS), "--serial-speed", "115200", "--flow-control"
        )
        try:
            tx, rx = _raw_open(links[0]), _raw_open(links[1])
            try:
                got = _pump([tx], [rx], frame, seconds, warmup)
            finally:
                os.close(tx)
                os.close(rx)
        finally:
            emu.stop()
    measured = got[rx] / seconds
    model = model_goodput(tdm_timing(AIR_KBPS), len(frame), 115200)
    return {
        "goodput_bytes_per_s": round(measured),
        "model_goodput_bytes_per_s": round(model),
        "goodput_ratio": round(measured / model, 3),
        "frame_bytes": len(frame),
        "air_limit_bytes_per_s": AIR_KBPS * 1000 // 8,
    }


def bench_latency(samples: int) -> dict[str, Any]:
    builder = FrameBuilder(1, 1)
    rng = random.Random(1)
    lat: list[float] = []
    round_s = tdm_timing(AIR_KBPS).round_s(2)
    with tempfile.TemporaryDirectory() as d:
        emu, links = start_emulator(2, d, "--air-speed", str(AIR_KBPS))
        try:
            with open_link(links[0]) as a, open_link(links[1]) as b:
                # wait for the pair to lock onto each other's hopping sequence
                deadline = time.monotonic() + 30
                while time.monotonic() < deadline:
                    a.send(builder.tunnel(b"sync"))
                    if b.recv(0.5) is not None:
                        break
                while b.recv(0.3) is not None:
                    pass
                frame_len = 0
                for i in range(samples):
                    time.sleep(rng.uniform(0.05, 0.05 + 3 * round_s))  # phase uniform over the TDM round
                    tag = struct.pack("<I", i) + b"\xff"  # non-zero end: not trimmed
                    frame = builder.tunnel(tag)
                    frame_len = len(frame)
                    t0 = time.monotonic()
                    a.send(frame)
                    t_end = t0 + 2.0
                    while (left := t_end - time.monotonic()) > 0:
                        f = b.recv(left)
                        if f is not None and f.msgid == 385 and f.payload[5:10] == tag:
                            lat.append(time.monotonic() - t0)
                            break
        finally:
            emu.stop()
    model = model_latency_s(tdm_timing(AIR_KBPS), frame_len, 57600, peer_idle=True)
    lat.sort()
    p50 = statistics.median(lat) if lat else float("nan")
    p99 = lat[min(len(lat) - 1, int(0.99 * len(lat)))] if lat else float("nan")
    return {
        "latency_ms_p50": round(1000 * p50, 1),
        "latency_ms_p99": round(1000 * p99, 1),
        "model_latency_ms_p50": round(1000 * model["p50"], 1),
        "model_latency_ms_p99": round(1000 * model["p99"], 1),
        "latency_ratio_p50": round(p50 / model["p50"], 3),
        "latency_samples": len(lat),
        "latency_lost": samples - len(lat),
    }


def bench_cpu(nodes: int, seconds: float, warmup: float) -> dict[str, Any]:
    frame = FrameBuilder(1, 1).tunnel(FILL)
    with tempfile.TemporaryDirectory() as d:
        emu, links = start_emulator(
            nodes,
            d,
            "--air-speed",
            str(AIR_KBPS),
            "--flow-control",
            "--stats-json",
            os.path.join(d, "stats.json"),
        )
        fds = [_raw_open(p) for p in links]
        try:
            # warm up, then measure the emulator's CPU over the window
            _pump(fds, fds, frame, 0.0, warmup)
            c0, t0 = cpu_seconds(emu.pid), time.monotonic()
            got = _pump(fds, fds, frame, seconds, 0.0)
            c1, t1 = cpu_seconds(emu.pid), time.monotonic()
        finally:
            for fd in fds:
                os.close(fd)
            emu.stop()
            import json

            try:
                with open(os.path.join(d, "stats.json"), encoding="utf-8") as fh:
                    util = json.load(fh)["utilisation"]
            except (OSError, ValueError, KeyError):
                util = None
    return {
        "emulator_cpu_percent": round(100 * (c1 - c0) / (t1 - t0), 1),
        "cpu_radios": nodes,
        "cpu_channel_utilisation": util,
        "cpu_delivered_bytes_per_s": round(sum(got.values()) / seconds),
    }


def run(quick: bool = False) -> dict[str, Any]:
    out: dict[str, Any] = {"air_speed_kbps": AIR_KBPS}
    out.update(bench_goodput(seconds=4.0 if quick else 15.0, warmup=6.0 if quick else 8.0))
    out.update(bench_latency(samples=15 if quick else 100))
    out["round_s"] = round(tdm_timing(AIR_KBPS, max_window_ms=None).round_s(3), 4)
    out["round_s_pair"] = round(tdm_timing(AIR_KBPS).round_s(2), 4)
    out.update(bench_cpu(10, seconds=4.0 if quick else 15.0, warmup=3.0 if quick else 6.0))
    out["targets"] = {
        "goodput_within_10pct_of_model": abs(out["goodput_ratio"] - 1) <= 0.10,
        "goodput_below_air_rate": out["goodput_bytes_per_s"] <= out["air_limit_bytes_per_s"],
        "latency_p50_within_20pct_of_model": abs(out["latency_ratio_p50"] - 1) <= 0.20,
        "emulator_cpu_under_25pct": out["emulator_cpu_percent"] < 25.0,
    }
    return out
