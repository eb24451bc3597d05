"""PX4's reasons, as PX4 sends them: the MAVLink events protocol, decoded.

Theory of operation
-------------------
PX4 (v1.12 and later) says why it refuses to arm, and what its health and arming
checks find, not in STATUSTEXT but in EVENT messages (id 410): an event id, a
log level and up to 40 bytes of arguments; the words are in PX4's event metadata
(``all_events.json``, built with the firmware: ``etc/extras/all_events.json.xz`` of a
PX4 build, served by the vehicle over MAVLink FTP), keyed by the id's low 24 bits
within the component named by its high 8 bits (1: ``px4``). The dialect the driver
reads with knows neither the EVENT message nor its neighbours, so pymavlink hands
them over as unknown frames; this module checks such a frame's CRC itself
(:data:`CRC_EXTRA`), unpacks it (:func:`parse_event`) and writes its text
(:meth:`EventCatalog.text`: the template's ``{1}``, ``{2:.1}`` filled from the
arguments by their types, an enum's value by its description, a bitfield's set bits
joined, markup such as ``<param>`` dropped). Without metadata an event still counts:
``PX4 event 0x0198bf7d`` at its log level, so a refusal is never explained by
nothing. The session turns each event into a
:class:`~firmware_bridge.telemetry.StatusText` at the event's external log level (the
same scale as STATUSTEXT severities), so refusals and ``NotReady`` carry PX4's words.

Pure: no I/O, no clock (the metadata is handed in as the parsed JSON).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Any

from pymavlink.generator.mavcrc import x25crc

STX_V2 = 0xFD

__all__ = ["CRC_EXTRA", "EVENT_PAYLOAD", "MSG_EVENT", "Event", "EventCatalog", "parse_event"]

MSG_EVENT, MSG_CURRENT_EVENT_SEQUENCE, MSG_REQUEST_EVENT, MSG_RESPONSE_EVENT_ERROR = 410, 411, 412, 413
#: CRC_EXTRA of the events protocol's messages (from their definitions in MAVLink's
#: common.xml, computed with pymavlink's own generator)
CRC_EXTRA = {
    MSG_EVENT: 160,
    MSG_CURRENT_EVENT_SEQUENCE: 106,
    MSG_REQUEST_EVENT: 33,
    MSG_RESPONSE_EVENT_ERROR: 77,
}
EVENT_PAYLOAD = struct.Struct(
    "<IIHBBB40s"
)  # id, time_boot_ms, sequence, dest comp, dest sys, log levels, args
_HEADER_V2 = 10
_TYPES = {
    "uint8_t": "<B",
    "int8_t": "<b",
    "uint16_t": "<H",
    "int16_t": "<h",
    "uint32_t": "<I",
    "int32_t": "<i",
    "uint64_t": "<Q",
    "int64_t": "<q",
    "float": "<f",
}
_FIELD = re.compile(r"\{(\d+)(?::([^}]*))?\}")
_TAG = re.compile(r"</?[a-zA-Z][^>]*>")


@dataclass(frozen=True)
class Event:
    """One EVENT as PX4 sent it."""

    id: int
    time_boot_ms: int
    sequence: int
    destination_component: int
    destination_system: int
    log_levels: int
    arguments: bytes

    @property
    def level(self) -> int:
        """The external log level (0 emergency ... 4 warning ... 7 debug), as STATUSTEXT's severity."""
        return self.log_levels & 0x0F


def parse_event(frame: bytes) -> Event | None:
    """The EVENT in the whole MAVLink 2 frame ``frame``, or None when the frame is not
    an EVENT or its CRC does not check out."""
    if len(frame) < _HEADER_V2 + 2 or frame[0] != STX_V2:
        return None
    n = frame[1]
    msgid = frame[7] | frame[8] << 8 | frame[9] << 16
    end = _HEADER_V2 + n
    if msgid != MSG_EVENT or len(frame) < end + 2 or n > EVENT_PAYLOAD.size:
        return None
    crc = x25crc(bytes(frame[1:end]))
    crc.accumulate(bytes([CRC_EXTRA[MSG_EVENT]]))
    if crc.crc != frame[end] | frame[end + 1] << 8:
        return None
    payload = bytes(frame[_HEADER_V2:end]).ljust(EVENT_PAYLOAD.size, b"\0")  # MAVLink 2 trims trailing zeros
    return Event(*EVENT_PAYLOAD.unpack(payload))


class EventCatalog:
    """PX4's event metadata (``all_events.json`` parsed), by component and id."""

    def __init__(self, metadata: dict[str, Any] | None = None) -> None:
        self._events: dict[tuple[int, int], dict[str, Any]] = {}
        self._groups: dict[tuple[int, int], str] = {}
        self._enums: dict[int, dict[str, Any]] = {}
        comps = metadata.get("components", {}) if isinstance(metadata, dict) else {}
        for key, comp in comps.items() if isinstance(comps, dict) else ():
            if not (isinstance(key, str) and key.isdigit() and isinstance(comp, dict)):
                continue
            c = int(key)
            enums = comp.get("enums")
            self._enums[c] = enums if isinstance(enums, dict) else {}
            groups = comp.get("event_groups")
            for gname, group in groups.items() if isinstance(groups, dict) else ():
                events = group.get("events") if isinstance(group, dict) else None
                for sub, ev in events.items() if isinstance(events, dict) else ():
                    if isinstance(sub, str) and sub.isdigit() and isinstance(ev, dict):
                        self._events[(c, int(sub))] = ev
                        self._groups[(c, int(sub))] = str(gname)

    def __len__(self) -> int:
        return len(self._events)

    def group(self, event: Event) -> str:
        """The metadata's group of the event (``arming_check``, ``health``, ``default``), or ``""``."""
        return self._groups.get((event.id >> 24, event.id & 0xFFFFFF), "")

    def text(self, event: Event) -> str:
        """The event's words with its arguments filled in; ``PX4 event 0x...`` when the
        metadata does not have it."""
        comp, sub = event.id >> 24, event.id & 0xFFFFFF
        ev = self._events.get((comp, sub))
        if ev is None or not isinstance(ev.get("message"), str):
            return f"PX4 event 0x{event.id:08x}"
        values = self._arguments(comp, ev.get("arguments") or [], event.arguments)

        def fill(m: re.Match[str]) -> str:
            i = int(m.group(1)) - 1
            if not 0 <= i < len(values):
                return m.group(0)
            v = values[i]
            fmt = m.group(2) or ""
            if isinstance(v, float) and fmt.startswith("."):
                digits = fmt[1:].rstrip("f")
                if digits.isdigit():
                    return f"{v:.{int(digits)}f}"
            return str(v)

        return _TAG.sub("", _FIELD.sub(fill, ev["message"])).strip()

    def _arguments(self, comp: int, specs: list[Any], raw: bytes) -> list[object]:
        out: list[object] = []
        at = 0
        for spec in specs:
            if not isinstance(spec, dict):
                break
            typ = spec.get("type")
            # PX4 names its enums with the component's namespace: "px4::arm_disarm_reason_t"
            name = typ.rpartition("::")[2] if isinstance(typ, str) else None
            enum = self._enums.get(comp, {}).get(name) if name else None
            base = enum.get("type") if isinstance(enum, dict) else typ
            fmt = _TYPES.get(base) if isinstance(base, str) else None
            if fmt is None:
                break
            size = struct.calcsize(fmt)
            if at + size > len(raw):
                break
            (value,) = struct.unpack_from(fmt, raw, at)
            at += size
            out.append(_enum_text(enum, value) if isinstance(enum, dict) else value)
        return out


def _enum_text(enum: dict[str, Any], value: int | float) -> str:
    entries = enum.get("entries") if isinstance(enum.get("entries"), dict) else {}
    assert isinstance(entries, dict)

    def name(v: int) -> str:
        e = entries.get(str(v))
        if isinstance(e, dict):
            return str(e.get("description") or e.get("name") or v)
        return str(v)

    if not isinstance(value, int):
        return str(value)
    if enum.get("is_bitfield"):
        bits = [name(1 << b) for b in range(64) if value >> b & 1]
        return ", ".join(bits) if bits else "none"
    return name(value)
