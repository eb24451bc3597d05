"""What a serial device is, so that a radio reopened after an unplug is the same radio (pure).

Theory of operation
-------------------
A path such as ``/dev/ttyUSB0`` names whatever device the kernel gave that name last:
the radio unplugged, another USB adapter plugged in gets it; a pty's ``/dev/pts/N`` is
handed to the next program that asks. So a link notes its device's identity
(:class:`DeviceIdentity`) when it first opens it and compares the device it finds at
the same path before every reopen (:func:`mismatch`); another device is refused
before it is opened, and never gets a byte. The facts are read by
:mod:`radios.device_probe` (udev's sysfs, ``stat``); this module only compares and
describes them, with no I/O.

What counts, by kind of device:

* ``usb``: the USB vendor and product ids, the serial number and the interface
  number, the facts ``/dev/serial/by-id`` names are made of. A serial number that many
  adapters share (none, fewer than six characters such as the CP210x default
  ``0001``, a known cloned one, or one held by another device attached at the first
  open) tells units apart no better than the model does: the USB port (``1-1.2``)
  counts too, so only the same port brings the radio back.
* ``emulator``: a pty of ``swarm radio-emu``, which labels each of its ptys with its
  own instance number and the radio's index (the pty's window size, see
  :func:`emulator_label`), as a USB adapter states its ids and serial number: the
  same radio of the same emulator, in a new pty after a replug, is accepted.
* ``pty`` (any other pseudo terminal: socat, a test) and ``node`` (a character
  device with no facts, such as one in a container without sysfs): nothing but the
  node itself (its device number and the time it was made), so only the node that
  was opened comes back (a port lent to a radio check and taken back); a new one is
  refused.
* ``serial``: a built-in port (a Pi's ``ttyAMA0``, a PC's ``ttyS0``): its place in
  the system (the sysfs device), which does not come and go.

Not covered: two adapters whose ids and serial numbers are equal, swapped in the same
USB port (SiK radios have no identity of their own to ask: ``ATI`` to ``ATI4`` are
the same for every unit of a model, and asking costs command mode, which writes to a
device not yet known); a device that lies about its ids (a USB descriptor is what the
device says); pyserial URLs (``socket://``: whatever answers at that address).
"""

from __future__ import annotations

from dataclasses import dataclass

#: Kinds of device (see the module docstring), as messages name them.
KIND_NAMES = {
    "usb": "USB adapter",
    "emulator": "emulator radio",
    "pty": "pty",
    "node": "device",
    "serial": "built-in serial port",
}
KINDS = tuple(KIND_NAMES)

#: ``ws_xpixel`` of an emulator pty's window size: the label's mark ("SW")
EMULATOR_MARK = 0x5357

#: Serial numbers sold on many adapters at once (besides any shorter than
#: :data:`MIN_SERIAL_LEN`): FTDI FT232R clones all carry A50285BI.
SHARED_SERIALS = frozenset({"A50285BI"})
MIN_SERIAL_LEN = 6


@dataclass(frozen=True)
class DeviceIdentity:
    """One device's identity (see the module docstring for what each kind compares).

    ``node`` (the device node the path named) and ``instance`` (that node's device
    number and change time, ns) say which node was opened; they are compared across a
    reopen only for the ``pty`` and ``node`` kinds. ``created`` is ``instance``'s time
    as text, for messages.
    """

    kind: str
    node: str
    instance: tuple[int, int]
    created: str = ""
    vid: int | None = None
    pid: int | None = None
    serial: str | None = None
    interface: int | None = None
    port: str | None = None  # the USB port path, e.g. 1-1.2
    shared_serial: bool = False  # the serial number does not tell units apart: the port counts
    product: str = ""
    emulator: int | None = None  # the emulator's instance number
    radio: int | None = None  # the emulator's radio index
    device: str | None = None  # a built-in port's sysfs device

    def describe(self) -> str:
        """One short phrase naming this device, for messages."""
        if self.kind == "usb":
            serial = f"serial {self.serial}" if self.serial else "no serial number"
            text = f"USB {self.vid or 0:04x}:{self.pid or 0:04x} {serial}"
            if self.interface:
                text += f" interface {self.interface}"
            if self.port:
                text += f" in port {self.port}"
            return f"{text} at {self.node}"
        if self.kind == "emulator":
            return f"emulator {self.emulator or 0:08x}'s radio {self.radio} at {self.node}"
        if self.kind == "serial":
            return f"serial port {self.node} at {self.device}"
        made = f", made {self.created}" if self.created else ""
        return f"{KIND_NAMES.get(self.kind, 'device')} {self.node} with no identity{made}"


def shared_serial(serial: str | None) -> bool:
    """Whether a USB serial number is one many adapters share (see the module docstring)."""
    s = (serial or "").strip()
    return len(s) < MIN_SERIAL_LEN or s.upper() in SHARED_SERIALS or len(set(s)) == 1


def mismatch(expected: DeviceIdentity, found: DeviceIdentity) -> str | None:
    """Why ``found`` is not the device ``expected`` names (a short phrase), or None when
    it is the same device."""
    if found.kind != expected.kind:
        return f"not {_a(KIND_NAMES.get(expected.kind, expected.kind))}"
    if expected.kind == "usb":
        if (found.vid, found.pid) != (expected.vid, expected.pid):
            return "another kind of USB adapter"
        if found.serial != expected.serial:
            return "another serial number"
        if found.interface != expected.interface:
            return "another interface of the adapter"
        if (expected.shared_serial or found.shared_serial) and found.port != expected.port:
            shown = expected.serial or "none"
            return f"another USB port (serial number {shown} is shared by many adapters, so the port counts)"
        return None
    if expected.kind == "emulator":
        if found.emulator != expected.emulator:
            return "a radio of another emulator"
        if found.radio != expected.radio:
            return "another radio"
        return None
    if expected.kind == "serial":
        return None if found.device == expected.device else "another serial port"
    # pty, node: no identity but the node itself
    return None if found.instance == expected.instance else "another device (the one opened is gone)"


def _a(noun: str) -> str:
    return ("an " if noun[:1] in "aeiou" else "a ") + noun


def refusal(path: str, expected: DeviceIdentity, found: DeviceIdentity, why: str) -> str:
    """The one line that refuses ``found`` at ``path`` (both devices named)."""
    return f"{path}: {found.describe()} is not the radio opened ({expected.describe()}): {why}"


def emulator_label(emulator: int, radio: int) -> tuple[int, int, int, int]:
    """The window size (rows, columns, x pixels, y pixels) that labels radio ``radio`` of
    emulator ``emulator`` (a 32-bit number) on its pty."""
    if not 0 <= emulator < 1 << 32 or not 0 <= radio < 1 << 16:
        raise ValueError(f"emulator {emulator} radio {radio}: out of range")
    return emulator >> 16, emulator & 0xFFFF, EMULATOR_MARK, radio


def read_emulator_label(winsize: tuple[int, int, int, int]) -> tuple[int, int] | None:
    """``(emulator, radio)`` from a pty's window size, or None if it bears no label."""
    rows, cols, xpixel, ypixel = winsize
    if xpixel != EMULATOR_MARK:
        return None
    return rows << 16 | cols, ypixel


__all__ = [
    "EMULATOR_MARK",
    "KINDS",
    "KIND_NAMES",
    "DeviceIdentity",
    "emulator_label",
    "mismatch",
    "read_emulator_label",
    "refusal",
    "shared_serial",
]
