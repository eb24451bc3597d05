"""The MAVLink parameter protocol of the simulated autopilot, as each real one answers it.

Theory of operation
-------------------
A standard MAVLink client (QGroundControl, MAVProxy, a script) reads and sets
parameters with PARAM_REQUEST_READ (by name, or by index with an empty name),
PARAM_REQUEST_LIST and PARAM_SET, and expects PARAM_VALUE back: the value as it now
is, its type, the parameter's index and the count. What the real autopilots do,
measured on ArduCopter 4.7 and PX4 v1.15 SITL:

* a PARAM_SET of a known name is answered at once with its PARAM_VALUE (the new
  value); an unknown name, read or set, gets no answer at all;
* ArduPilot answers a read by name and a set with index 65535 and sends every value as a
  float (an integer parameter's value converted); its list starts with
  FORMAT_VERSION at index 0;
* PX4 answers a read with the parameter's index and sends an integer parameter's
  bits in the float field (int32 bytewise: 10040 reads as 1.4e-41 as a float); its
  list starts with ``_HASH_CHECK`` (index 65535, not counted).

:class:`ParamTable` holds one vehicle's parameters in index order (a flavour's
:attr:`~firmware_bridge.sim.flavour.Flavour.params`: a small set with the real
names, types and defaults, some of which the simulation reads: PX4's COM_OF_LOSS_T,
ArduPilot's GUID_TIMEOUT) and builds the PARAM_VALUE fields; the autopilot core
sends them. Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

__all__ = [
    "MAV_PARAM_TYPE_INT8",
    "MAV_PARAM_TYPE_INT16",
    "MAV_PARAM_TYPE_INT32",
    "MAV_PARAM_TYPE_REAL32",
    "ParamTable",
    "ParamValue",
]

MAV_PARAM_TYPE_INT8, MAV_PARAM_TYPE_INT16, MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32 = 2, 4, 6, 9
_INT_RANGES = {
    MAV_PARAM_TYPE_INT8: (-(2**7), 2**7 - 1),
    MAV_PARAM_TYPE_INT16: (-(2**15), 2**15 - 1),
    MAV_PARAM_TYPE_INT32: (-(2**31), 2**31 - 1),
}
NO_INDEX = 65535


@dataclass(frozen=True)
class ParamValue:
    """The fields of one PARAM_VALUE."""

    name: str
    value: float  # as on the wire (PX4's integers bytewise)
    type: int
    count: int
    index: int


class ParamTable:
    """One vehicle's parameters: ``(name, default, MAV_PARAM_TYPE)`` in index order.
    ``bytewise``: integers travel as their bits (PX4), else converted (ArduPilot);
    ``read_index``: a read by name reports the index (PX4), else 65535 (ArduPilot);
    ``hash_first``: a list starts with PX4's ``_HASH_CHECK``."""

    def __init__(
        self,
        params: tuple[tuple[str, float, int], ...],
        *,
        bytewise: bool,
        read_index: bool,
        hash_first: bool,
    ) -> None:
        self._names = [p[0] for p in params]
        self._values = {name: float(v) for name, v, _t in params}
        self._types = {name: t for name, _v, t in params}
        self.bytewise, self.read_index, self.hash_first = bytewise, read_index, hash_first

    def __len__(self) -> int:
        return len(self._names)

    def get(self, name: str, default: float = math.nan) -> float:
        """The value (a number, not its wire form); ``default`` if there is no such parameter."""
        return self._values.get(name, default)

    def _wire(self, name: str, index: int) -> ParamValue:
        t, v = self._types[name], self._values[name]
        if self.bytewise and t in _INT_RANGES:
            v = struct.unpack("<f", struct.pack("<i", int(v)))[0]
        return ParamValue(name, v, t, len(self._names), index)

    def read(self, name: str, index: int) -> ParamValue | None:
        """PARAM_REQUEST_READ: by ``name``, or by ``index`` when the name is empty
        (index -1 means by name); None (no answer) when there is no such parameter."""
        if not name:
            if 0 <= index < len(self._names):
                return self._wire(self._names[index], index)
            return None
        if name not in self._values:
            return None
        return self._wire(name, self._names.index(name) if self.read_index else NO_INDEX)

    def set(self, name: str, wire_value: float, wire_type: int) -> ParamValue | None:
        """PARAM_SET: the new value's PARAM_VALUE, or None for an unknown name (no
        answer). A value that is not a number, or an integer out of its type's range,
        leaves the parameter as it was (the answer says its value)."""
        if name not in self._values:
            return None
        t = self._types[name]
        v = wire_value
        if t in _INT_RANGES:
            if self.bytewise and wire_type in _INT_RANGES:
                v = float(struct.unpack("<i", struct.pack("<f", wire_value))[0])
            lo, hi = _INT_RANGES[t]
            if math.isfinite(v) and lo <= round(v) <= hi:
                self._values[name] = float(round(v))
        elif math.isfinite(v):
            self._values[name] = float(v)
        return self._wire(name, self._names.index(name) if self.read_index else NO_INDEX)

    def listing(self) -> list[ParamValue]:
        """PARAM_REQUEST_LIST: every parameter in index order (PX4: its hash first)."""
        out = [self._wire(n, i) for i, n in enumerate(self._names)]
        if self.hash_first:
            h = sum((i + 1) * ord(c) for n in self._names for i, c in enumerate(n)) & 0x7FFFFFFF
            out.insert(0, ParamValue("_HASH_CHECK", float(h), 5, len(self._names), NO_INDEX))
        return out
