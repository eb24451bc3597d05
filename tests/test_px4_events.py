"""PX4's events protocol decoded (firmware_bridge.px4_events): PX4 says why it refuses
to arm in EVENT messages, which the dialect here does not know; a refusal used to come
with no reason at all. Real bytes built as PX4 builds them; metadata shaped as PX4's
``all_events.json``."""

from __future__ import annotations

import struct
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega

from firmware_bridge.commands import CommandExchange, Rejected
from firmware_bridge.px4_events import CRC_EXTRA, MSG_EVENT, Event, EventCatalog, parse_event
from firmware_bridge.telemetry import StatusText, TelemetryFolder
from radios.mavlink import x25_crc

META: dict[str, Any] = {
    "version": 2,
    "components": {
        "1": {
            "namespace": "px4",
            "enums": {
                "navigation_mode_group_t": {
                    "type": "uint32_t",
                    "is_bitfield": True,
                    "entries": {
                        "1": {"name": "manual", "description": "Manual"},
                        "4": {"description": "Position"},
                    },
                },
                "arm_disarm_reason_t": {"type": "uint8_t", "entries": {"3": {"description": "command"}}},
            },
            "event_groups": {
                "arming_check": {
                    "events": {
                        "10011251": {
                            "name": "check_modes_global_pos",
                            "message": "No valid global position estimate",
                            "arguments": [
                                {"name": "modes", "type": "navigation_mode_group_t"},
                                {"name": "health_component_index", "type": "uint8_t"},
                            ],
                        }
                    }
                },
                "default": {
                    "events": {
                        "133277": {"message": "Arming denied: Resolve system health failures first"},
                        "500": {
                            "message": "Battery at {1:.1}V (<param>BAT_LOW_THR</param>), {2}, modes {3}",
                            "arguments": [
                                {"name": "v", "type": "float"},
                                {"name": "why", "type": "arm_disarm_reason_t"},
                                {"name": "m", "type": "navigation_mode_group_t"},
                            ],
                        },
                    }
                },
            },
        }
    },
}


def event_frame(
    event_id: int, level: int = 4, args: bytes = b"", *, sysid: int = 1, to: int = 0, crc_extra: int = 160
) -> bytes:
    """An EVENT as PX4 puts it on the wire (for system ``to``, 0: everyone): MAVLink 2,
    trailing zeros trimmed."""
    payload = struct.pack("<IIHBBB", event_id, 1234, 7, 0, to, level << 4 | level) + args.ljust(40, b"\0")
    payload = payload.rstrip(b"\0") or b"\0"
    head = bytes([0xFD, len(payload), 0, 0, 5, sysid, 1, MSG_EVENT & 0xFF, MSG_EVENT >> 8, 0])
    crc = x25_crc(head[1:] + payload, crc_extra)
    return head + payload + struct.pack("<H", crc)


def test_an_event_is_unpacked_and_written_in_pxs_words() -> None:
    cat = EventCatalog(META)
    assert len(cat) == 3 and CRC_EXTRA[MSG_EVENT] == 160
    ev = parse_event(event_frame(1 << 24 | 10011251, 4, struct.pack("<IB", 5, 0)))
    assert ev is not None and ev.level == 4 and ev.sequence == 7
    assert cat.text(ev) == "No valid global position estimate"
    ev = parse_event(event_frame(1 << 24 | 500, 3, struct.pack("<fBI", 14.87, 3, 5)))
    assert (
        ev is not None and cat.text(ev) == "Battery at 14.9V (BAT_LOW_THR), command, modes Manual, Position"
    )
    # PX4's real metadata names an enum with its namespace ("px4::arm_disarm_reason_t"):
    # the value is still written by its description, not left as "{1}"
    meta = {
        "components": {
            "1": {
                "namespace": "px4",
                "enums": META["components"]["1"]["enums"],
                "event_groups": {
                    "default": {
                        "events": {
                            "9482995": {
                                "message": "Armed by {1}",
                                "arguments": [{"name": "arg0", "type": "px4::arm_disarm_reason_t"}],
                            }
                        }
                    }
                },
            }
        }
    }
    ev = parse_event(event_frame(1 << 24 | 9482995, 6, b"\x03"))
    assert ev is not None and EventCatalog(meta).text(ev) == "Armed by command"
    # an id the metadata lacks, or no metadata at all: still an event, at its level
    ev = parse_event(event_frame(2 << 24 | 99, 2))
    assert ev is not None and ev.level == 2 and EventCatalog().text(ev) == "PX4 event 0x02000063"


def test_a_frame_that_is_not_a_good_event_is_none() -> None:
    good = event_frame(1 << 24 | 133277)
    assert parse_event(good) is not None
    assert parse_event(event_frame(1 << 24 | 133277, crc_extra=161)) is None  # bad CRC
    assert parse_event(good[:-3]) is None and parse_event(b"") is None
    assert parse_event(bytes([0xFE]) + good[1:]) is None
    # hostile metadata: wrong shapes are ignored, never raised
    for meta in ({"components": 5}, {"components": {"x": {}}}, {"components": {"1": {"event_groups": 3}}}):
        try:
            EventCatalog(meta)
        except (AttributeError, TypeError):
            raise AssertionError(f"raised on {meta}") from None
    cut = EventCatalog(
        {"components": {"1": {"event_groups": {"g": {"events": {"500": {"message": "v={1}"}}}}}}}
    )
    assert cut.text(Event(1 << 24 | 500, 0, 0, 0, 0, 4, b"")) == "v={1}"  # no argument: left as written


def test_a_px4_refusal_carries_the_events_words() -> None:
    """PX4 refuses an early arm with TEMPORARILY_REJECTED and no STATUSTEXT: its events
    explain it, and the refusal says so."""
    mav = ardupilotmega.MAVLink(None)
    f = TelemetryFolder("px4", 1, 1, own_system=1, events=EventCatalog(META))
    heard = f.fold(mav.parse_buffer(event_frame(1 << 24 | 133277, 4))[0], 10.0)
    assert heard.text == StatusText(10.0, 4, "Arming denied: Resolve system health failures first")
    ex = CommandExchange(400, (1, 0), 9.9, target_system=1, target_component=1, tries=3, per_try=1.0)
    ex.start()
    ack = ardupilotmega.MAVLink_command_ack_message(400, 1, 0, 0, 1, 191)
    rx = ardupilotmega.MAVLink(None)
    heard_ack = f.fold(rx.parse_buffer(ack.pack(ardupilotmega.MAVLink(None, 1, 1)))[0], 10.05)
    assert heard_ack.ack is not None
    ex.handle(heard_ack.ack, 10.05)
    assert heard.text is not None
    ex.handle(heard.text, 10.05)
    assert ex.outcome == Rejected(1, "Arming denied: Resolve system health failures first")
    # an event for another system is not ours, nor one from another vehicle
    assert f.fold(mav.parse_buffer(event_frame(1 << 24 | 133277, 4, to=9))[0], 11.0).text is None
    assert f.fold(mav.parse_buffer(event_frame(1 << 24 | 133277, 4, sysid=2))[0], 11.0).text is None
    assert f.fold(mav.parse_buffer(event_frame(1 << 24 | 133277, 4, to=1))[0], 11.0).text is not None
