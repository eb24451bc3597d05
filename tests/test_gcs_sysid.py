"""A system id collision on the station's radio: MAVProxy or QGroundControl left at
their default id 255 beside ``swarm gcs`` (also 255 by default).

A real station on radio 0 of the emulator; on radio 1, pymavlink's MAVLink 2 encoder
writes what such a program sends (HEARTBEAT as a GCS, PARAM_REQUEST_LIST...) into
the radio's pty. The station says so once (one ``radio`` event naming the flag to
change, one log line), however many frames follow; another id does not trigger it."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import serial
from emu_helpers import AIR_DEADLINE, LOCK_DEADLINE, running_emulator
from net_helpers import wait_until

from radios.mavlink import dialect
from swarm.core.wire.tunnel import PAYLOAD_TYPE_BASE, Kind
from swarm.runtime.station.live import Station

pytestmark = pytest.mark.processes  # real ptys, an emulator thread, a Zenoh session


class Sender:
    """A program on the radio: pymavlink's encoder writing to the radio's serial port."""

    def __init__(self, path: str) -> None:
        self.port = serial.Serial(path, 57600, timeout=0.1)
        self.markers = 0

    def as_(self, sysid: int, compid: int) -> Any:
        return dialect.MAVLink(self.port, srcSystem=sysid, srcComponent=compid)

    def marker(self) -> None:
        """A frame the station counts on its own (a TUNNEL for someone else): once the
        station counted it, everything written before it has been through the air."""
        payload = [0] * 128
        self.as_(7, 1).tunnel_send(99, 0, PAYLOAD_TYPE_BASE + Kind.P2P, 1, payload)
        self.markers += 1

    def close(self) -> None:
        self.port.close()


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[tuple[Station, Sender, list[dict[str, Any]]]]:
    with running_emulator(tmp_path, 2) as emu:
        station = Station("gcs", 255, radio=emu.paths[0]).start()
        events: list[dict[str, Any]] = []
        lock = threading.Lock()

        def on_event(ev: dict[str, Any]) -> None:
            with lock:
                events.append(ev)

        station.add_listener(on_event)
        sender = Sender(emu.paths[1])
        try:
            emu.wait_connected(0, 1)
            emu.wait_locked(0, 1)
            yield station, sender, events
        finally:
            sender.close()
            station.stop()


def _through(station: Station, sender: Sender) -> None:
    """Wait until the station counted every marker sent so far (loss is possible on
    the air: send the marker again until it is counted)."""
    want = sender.markers

    def counted() -> bool:
        if station.bridge.stats.not_for_us >= want:
            return True
        sender.marker()
        return False

    sender.marker()
    wait_until(counted, "the marker through the air", LOCK_DEADLINE, 0.5)


def collisions(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [e for e in list(events) if e["kind"] == "radio" and "collision" in e["text"]]


def test_another_sender_with_the_station_id_is_reported_once(
    bench: tuple[Station, Sender, list[dict[str, Any]]], caplog: pytest.LogCaptureFixture
) -> None:
    station, sender, events = bench
    caplog.set_level(logging.WARNING, logger="swarm.runtime.bridge.radio_bridge")
    # MAVProxy given another id (--source-system 254): nothing to say
    other = sender.as_(254, 190)
    for _ in range(3):
        other.heartbeat_send(dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    _through(station, sender)
    assert collisions(events) == []

    # MAVProxy at its default id 255 (component 230, MAV_COMP_ID_MISSIONPLANNER... any)
    same = sender.as_(255, 190)
    same.heartbeat_send(dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    wait_until(lambda: collisions(events), "the collision reported", AIR_DEADLINE * 3)
    for _ in range(5):
        same.heartbeat_send(dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        same.param_request_list_send(1, 1)
        same.request_data_stream_send(1, 1, 0, 4, 1)
    _through(station, sender)
    found = collisions(events)
    assert len(found) == 1, found
    text = found[0]["text"]
    assert "system id 255 collision" in text and "HEARTBEAT from component 190" in text, text
    assert "swarm gcs --id 254" in text and "--source-system" in text, text
    logged = [r for r in caplog.records if "collision" in r.getMessage()]
    assert len(logged) == 1, [r.getMessage() for r in logged]
    # in the history a page opened later reads
    assert any("collision" in e["text"] for e in station.snapshot()["events"])
