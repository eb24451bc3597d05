"""What MAVProxy costs on the swarm's shared radio: a stand-in measured through the emulator.

MAVProxy is not installed here, so a stand-in sends what MAVProxy (1.8, its
``mavproxy.py`` and default modules) sends on a link where no autopilot answers it,
as the swarm's radio is (the vehicles' autopilots are behind the agents):

* ``HEARTBEAT`` (type GCS) at ``--heartbeat-rate`` (1 Hz);
* ``REQUEST_DATA_STREAM`` (all streams, ``--streamrate`` 4 Hz) to each vehicle it
  heard, at start and every 15 s (none with ``--streamrate=-1``);
* the ``param`` module, once a second while it has no parameters: first a
  parameter download by MAVLink FTP (``FILE_TRANSFER_PROTOCOL``: terminate and open,
  two retries, terminate), then ``PARAM_REQUEST_LIST`` every second for ever;
* the ``wp`` module: ``COMMAND_LONG`` ``MAV_CMD_GET_HOME_POSITION`` every 2 s while
  it has no ``HOME_POSITION``.

The recommended set-up (README, "MAVProxy beside the swarm") drops the modules that
fetch (``param``, ``ftp``, ``wp``, ``fence``, ``rally``, ``terrain`` through
``--default-modules``) and the stream requests (``--streamrate=-1``), and takes its
own system id (``--source-system 254``): only its heartbeat stays.

:func:`measure` runs a three-radio emulator that captures every frame put on air; on
radio 1 the default MAVProxy (id 255), on radio 2 the recommended one (id 254), both
written with pymavlink's MAVLink 2 encoder into the radios' ptys in real time. Each
one's frames on air per second are counted from the capture, over the whole run
and after the first ``warmup`` seconds (the steady cost, paid for as long as MAVProxy
runs). Run ``python tests/mavproxy_air.py --seconds 60`` for the README's figures.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import serial
from emu_helpers import running_emulator

from radios.mavlink import dialect
from radios.tlog import read_tlog

VEHICLE = (1, 1)  # the one vehicle the stand-in heard (sysid, compid)
FTP_OPEN, FTP_TERMINATE = 4, 1  # MAVLink FTP opcodes (OpenFileRO, TerminateSession)


@dataclass
class StandIn:
    """MAVProxy's periodic sending on one link (see the module docstring)."""

    mav: Any
    fetches: bool = True  # the param, ftp and wp modules are loaded
    streamrate: int = 4  # -1: no stream requests
    heartbeat_hz: float = 1.0
    t0: float = 0.0
    sent: Counter[str] = field(default_factory=Counter)
    _next: dict[str, float] = field(default_factory=dict)
    _ftp_step: int = 0

    def start(self, now: float) -> None:
        self.t0 = now
        self._next = {"heartbeat": now, "streams": now, "param": now + 1.0, "home": now}

    def _due(self, task: str, now: float, period: float) -> bool:
        if now < self._next[task]:
            return False
        self._next[task] += period
        return True

    def _ftp(self, opcode: int) -> None:
        payload = [0] * 251
        payload[3] = opcode  # seq (2 bytes), session, opcode...
        self.mav.file_transfer_protocol_send(0, *VEHICLE, payload)
        self.sent["FILE_TRANSFER_PROTOCOL"] += 1

    def step(self, now: float) -> None:
        if self.heartbeat_hz > 0 and self._due("heartbeat", now, 1.0 / self.heartbeat_hz):
            self.mav.heartbeat_send(dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self.sent["HEARTBEAT"] += 1
        if self.streamrate != -1 and self._due("streams", now, 15.0):
            self.mav.request_data_stream_send(*VEHICLE, dialect.MAV_DATA_STREAM_ALL, self.streamrate, 1)
            self.sent["REQUEST_DATA_STREAM"] += 1
        if not self.fetches:
            return
        if self._due("param", now, 1.0):
            if self._ftp_step < 3:  # open (after cancelling), then two retries
                self._ftp(FTP_TERMINATE)
                self._ftp(FTP_OPEN)
                self._ftp_step += 1
            elif self._ftp_step == 3:  # the download failed
                self._ftp(FTP_TERMINATE)
                self._ftp_step += 1
            else:
                self.mav.param_request_list_send(*VEHICLE)
                self.sent["PARAM_REQUEST_LIST"] += 1
        if self._due("home", now, 2.0):
            self.mav.command_long_send(
                VEHICLE[0], 0, dialect.MAV_CMD_GET_HOME_POSITION, 0, 0, 0, 0, 0, 0, 0, 0
            )
            self.sent["COMMAND_LONG"] += 1


def _run(standins: list[StandIn], seconds: float, stop: threading.Event) -> None:
    now = time.time()
    for s in standins:
        s.start(now)
    end = now + seconds
    while not stop.is_set() and time.time() < end:
        t = time.time()
        for s in standins:
            s.step(t)
        stop.wait(0.01)


def _rates(
    records: list[tuple[float, int, str, int]], sysid: int, t0: float, t1: float, span: float
) -> dict[str, Any]:
    mine = [r for r in records if r[1] == sysid and t0 <= r[0] < t1]
    span = max(span, 1e-9)
    return {
        "frames_per_s": round(len(mine) / span, 3),
        "bytes_per_s": round(sum(r[3] for r in mine) / span, 1),
        "by_message": dict(sorted(Counter(r[2] for r in mine).items())),
    }


def measure(seconds: float = 60.0, warmup: float = 5.0) -> dict[str, Any]:
    """Frames (and bytes) per second each stand-in put on the air: whole run and steady."""
    with tempfile.TemporaryDirectory(prefix="mavproxy-air-") as d:
        capture = Path(d) / "air.tlog"
        ports: list[serial.Serial] = []
        (Path(d) / "radios").mkdir()
        with running_emulator(Path(d) / "radios", 3, capture=str(capture)) as emu:
            try:
                ports = [serial.Serial(p, 57600, timeout=0.1) for p in emu.paths]
                emu.wait_ready(0, 1, 2)
                default = StandIn(dialect.MAVLink(ports[1], srcSystem=255, srcComponent=230))
                quiet = StandIn(
                    dialect.MAVLink(ports[2], srcSystem=254, srcComponent=230), fetches=False, streamrate=-1
                )
                t0 = time.time()
                _run([default, quiet], seconds, threading.Event())
                t1 = time.time()
                time.sleep(1.0)  # the last frames cross the air (a few TDM rounds)
            finally:
                for p in ports:
                    p.close()
        records = [(r.t, r.frame.sysid, r.frame.name, len(r.raw)) for r in read_tlog(capture)]
    out: dict[str, Any] = {"seconds": round(t1 - t0, 1), "warmup_s": warmup}
    for name, sysid, s in (("default", 255, default), ("recommended", 254, quiet)):
        out[name] = {
            "sysid": sysid,
            "sent": dict(sorted(s.sent.items())),
            "whole_run": _rates(records, sysid, t0, t1 + 1.0, t1 - t0),  # the last ones in flight too
            "steady": _rates(records, sysid, t0 + warmup, t1, t1 - t0 - warmup),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--warmup", type=float, default=5.0)
    a = ap.parse_args()
    print(json.dumps(measure(a.seconds, a.warmup), indent=1))


if __name__ == "__main__":
    main()
