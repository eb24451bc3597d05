"""A small swarm node for the real-process tests (tests/test_bridge_processes.py).

    python tests/bridge_node.py --name a1 --id 1 (--radio PATH | --listen EP | --connect EP ...)
        --peers a2,a3 --seconds S [--linger L] [--start-deadline D]

Opens a Zenoh session (isolated when it has a radio), bridges it to the radio link
if given, advertises every 0.5 s, and once it has heard every peer's Advertize
(or after ``--start-deadline`` s) sends a numbered P2P message (Selection, weight =
sequence number, candidate = addressee id) to each peer every 0.5 s for
``--seconds`` s; then keeps listening ``--linger`` s and prints one JSON line:
``{"name", "id", "sent": {peer: n}, "advertized": n, "received": {peer: [seq, ...]}, "heard": [...],
"stray": n, "bridge": {...stats}}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from radios.link import open_link
from swarm.core.wire.message_types import Advertize, Message, Selection
from swarm.runtime.bridge.radio_bridge import RadioBridge
from swarm.runtime.keyspace.transport import Transport, open_session

EPOCH = 11  # marks this program's numbered messages


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bridge_node")
    p.add_argument("--name", required=True)
    p.add_argument("--id", type=int, required=True)
    p.add_argument("--radio")
    p.add_argument("--listen", action="append", default=[])
    p.add_argument("--connect", action="append", default=[])
    p.add_argument("--peers", required=True)
    p.add_argument("--seconds", type=float, required=True)
    p.add_argument("--linger", type=float, default=3.0)
    p.add_argument("--start-deadline", type=float, default=30.0)
    args = p.parse_args(argv)
    peers = [x for x in args.peers.split(",") if x]

    lock = threading.Lock()
    names: dict[int, str] = {}
    received: dict[str, list[int]] = {}
    stray = 0

    def on_advertize(m: Advertize) -> None:
        with lock:
            names[m.sender] = m.name

    def on_inbox(m: Message) -> None:
        nonlocal stray
        with lock:
            if isinstance(m, Selection) and m.epoch == EPOCH and m.candidate == args.id:
                received.setdefault(names.get(m.sender, str(m.sender)), []).append(m.weight)
            else:
                stray += 1

    session = open_session(args.listen, args.connect)
    link = open_link(args.radio) if args.radio else None
    bridge = RadioBridge(session, link, name=args.name, agent_id=args.id).start() if link else None
    transport = Transport(args.name, session)
    sent = {peer: 0 for peer in peers}
    advertized = 0
    try:
        transport.on_advertize(on_advertize)
        transport.on_inbox(on_inbox)
        me = Advertize(args.id, args.name)

        def advertise() -> None:
            nonlocal advertized
            transport.advertise(me)
            advertized += 1

        ids: dict[str, int] = {}
        start_deadline = time.monotonic() + args.start_deadline
        while time.monotonic() < start_deadline:
            advertise()
            with lock:
                ids = {n: i for i, n in names.items()}
            if all(peer in ids for peer in peers):
                break
            time.sleep(0.5)
        end = time.monotonic() + args.seconds
        seq = 0
        while time.monotonic() < end:
            advertise()
            with lock:
                ids = {n: i for i, n in names.items()}
            for peer in peers:
                if peer in ids:
                    transport.send(peer, Selection(args.id, ids[peer], seq, EPOCH))
                    sent[peer] += 1
            seq += 1
            time.sleep(0.5)
        linger_end = time.monotonic() + args.linger
        while time.monotonic() < linger_end:
            advertise()  # peers still sending may still need our name
            time.sleep(0.5)
        with lock:
            report: dict[str, Any] = {
                "name": args.name,
                "id": args.id,
                "sent": sent,
                "advertized": advertized,
                "received": received,
                "heard": sorted(names.values()),
                "stray": stray,
                "decode_errors": transport.decode_errors,
                "bridge": bridge.stats.as_dict() if bridge else None,
            }
        print(json.dumps(report), flush=True)
    finally:
        transport.close()
        if bridge is not None:
            bridge.close()
        if link is not None:
            link.close()
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
