"""The bench demo of the radio layer (``make demo`` until the swarm demo exists).

Starts ``swarm radio-emu`` with three radios and a capture, reads radio0's
parameters over AT commands exactly as on a real radio, has three "vehicles"
(plain pymavlink connections) send HEARTBEAT and GLOBAL_POSITION_INT through the
emulated air for a few seconds, prints what each one heard and its RADIO_STATUS,
stops the emulator and summarises the capture. Exits 0 only if every vehicle
heard the two others. Ctrl-C stops everything.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections import Counter
from typing import Any

from radios.errors import RadioError
from radios.sik.config import SikConfigurator, open_port
from radios.tlog import read_tlog
from swarm.procs import start_emulator


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m swarm.radio_demo", description=__doc__)
    p.add_argument("--seconds", type=float, default=8.0, help="traffic time (default 8)")
    p.add_argument("--loss", type=float, default=0.1, help="packet loss per receiver (default 0.1)")
    args = p.parse_args(argv)
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    workdir = tempfile.mkdtemp(prefix="swarm-radio-demo-")
    capture = os.path.join(workdir, "air.tlog")
    print(f"== starting 3 emulated SiK radios in {workdir} (10% loss, multipoint firmware)")
    emu, links = start_emulator(3, workdir, "--capture", capture, "--loss", str(args.loss))
    conns = []
    try:
        for line in emu.lines:
            print("  " + line)
        print("== radio0's parameters, read with AT commands (+++, ATI5) as on a real radio")
        port = open_port(links[0], 57600)
        try:
            cfg = SikConfigurator(port, flavour="multipoint", port_name=links[0])
            cfg.enter_command_mode()
            print("  " + cfg.version())
            params = cfg.read_params()
            print("  " + "  ".join(f"{k}={v}" for k, v in params.items()))
            cfg.exit_command_mode()
        finally:
            port.close()
        print(f"== three vehicles send HEARTBEAT and GLOBAL_POSITION_INT for {args.seconds:.0f} s")
        conns = [mavutil.mavlink_connection(link, baud=57600, source_system=i + 1)
                 for i, link in enumerate(links)]
        heard: list[Counter[int]] = [Counter() for _ in conns]
        status: list[Any] = [None for _ in conns]
        end = time.monotonic() + args.seconds
        next_send = 0.0
        while time.monotonic() < end:
            now = time.monotonic()
            if now >= next_send:
                next_send = now + 1.0
                for i, c in enumerate(conns):
                    c.mav.heartbeat_send(2, 12, 0, 0, 4)
                    c.mav.global_position_int_send(int(now * 1000) & 0xFFFFFFFF,
                                                   int((47.397 + 0.0001 * i) * 1e7),
                                                   int(8.545 * 1e7), 500000, 10000, 0, 0, 0, 0)
            for i, c in enumerate(conns):
                while (m := c.recv_match(blocking=False)) is not None:
                    if m.get_type() == "RADIO_STATUS":
                        status[i] = m
                    elif m.get_type() in ("HEARTBEAT", "GLOBAL_POSITION_INT"):
                        heard[i][m.get_srcSystem()] += 1
            time.sleep(0.02)
        ok = True
        for i in range(len(conns)):
            others = {j + 1 for j in range(len(conns)) if j != i}
            ok &= others <= set(heard[i])
            rs = status[i]
            radio = (f"rssi {rs.rssi}/{rs.remrssi} noise {rs.noise}/{rs.remnoise} "
                     f"txbuf {rs.txbuf}%") if rs is not None else "no RADIO_STATUS"
            print(f"  vehicle {i + 1}: heard " + ", ".join(
                f"sys{s}: {n} msgs" for s, n in sorted(heard[i].items())) + f"; radio {radio}")
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except RadioError as exc:
        print(f"radio demo: error: {exc}", file=sys.stderr)
        return 1
    finally:
        for c in conns:
            c.close()
        emu.stop()
    for line in emu.errors:
        print("  emulator: " + line)
    frames = Counter(rec.frame.name for rec in read_tlog(capture))
    print(f"== capture {capture}: " + ", ".join(f"{n} {k}" for k, n in frames.most_common()))
    print(f"   replay it: swarm replay {capture} --stats")
    print("== OK: every vehicle heard the others" if ok else "== FAILED: a vehicle heard nobody")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
