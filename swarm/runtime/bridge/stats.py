"""What a radio bridge counts, both ways: frames, drops, refusals, the radio's losses."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass
class BridgeStats:
    frames_out: int = 0
    frames_in: int = 0
    bytes_out: int = 0
    published: int = 0
    multicast_merged: int = 0
    queue_drops: int = 0
    oversize: int = 0
    unroutable: int = 0
    unknown_sender: int = 0
    not_for_us: int = 0
    overheard: int = 0  # a station: leaders' Heartbeats to their members (swarm.runtime.bridge.rx)
    decode_errors: int = 0
    version_mismatch: int = 0
    conflicts: int = 0
    send_errors: int = 0
    throttled: int = 0  # send-loop passes that held telemetry back (txbuf back-off)
    poses_thinned: int = 0  # poses skipped by the bounded txbuf back-off
    radio_status_accepted: int = 0
    radio_status_rejected: int = 0  # RADIO_STATUS not plausibly from the local radio
    radio_losses: int = 0  # the radio's device went away
    radio_reopens: int = 0  # ... and was opened again
    radio_refused: int = 0  # attempts that found another device at the radio's path
    dropped_radio_down: int = 0  # frames dropped while the radio was away
    heartbeats: int = 0
    vehicle_forwarded: int = 0
    unsigned: int = 0
    bad_signature: int = 0
    replayed: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)
