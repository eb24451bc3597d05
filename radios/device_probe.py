"""Reading a serial device's identity without disturbing it (the I/O of :mod:`radios.device_id`).

Theory of operation
-------------------
:func:`identify` resolves the path (a ``/dev/serial/by-id/...`` link, an emulator's
``DIR/radioK``), ``stat``\\ s the device node and reads what the kernel says of it:

* a USB adapter (or any device with sysfs facts): ``/sys/dev/char/MAJOR:MINOR`` leads
  to the tty's ``device``; for ``usb-serial`` (``ttyUSB``: FTDI, CP210x, CH340) that is
  the port under the USB interface, for ``usb`` (``ttyACM``: CDC ACM, a Pixhawk) the
  interface itself; above the interface is the USB device with ``idVendor``,
  ``idProduct``, ``serial``, ``product``, and its name is the port path (``1-1.2``).
  The same walk as pyserial's ``serial.tools.list_ports_linux.SysFS``, from the device
  number rather than the node's name (so a node of any name, and a symbolic link,
  work: pyserial's reads nothing for a link) and under a root the caller may choose
  (tests give a tree of files). Nothing is opened: opening a real serial port
  raises its DTR and RTS lines, which resets some devices. Other USB devices with the
  same ids and serial number (``/sys/bus/usb/devices``) make that serial number a
  shared one.
* a pseudo terminal (majors 136 to 143): opened for reading, without becoming the
  controlling terminal and without reading, for its window size only (the emulator's
  label), and closed; nothing is written.

:func:`confirm` checks, once pyserial has opened the path, that the node it opened is
the one identified (the path may change in between).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import stat
import struct
import termios
import time
from pathlib import Path
from typing import Any

from radios.device_id import DeviceIdentity, read_emulator_label, shared_serial
from radios.errors import LinkOpenError

#: Unix98 pty slaves (Documentation/admin-guide/devices.txt: 136-143 char)
PTY_MAJORS = range(136, 144)
MISSING = "no such device (is the radio plugged in / the emulator running?)"


def identify(path: str, *, sysfs: str = "/sys") -> DeviceIdentity:
    """The identity of the device ``path`` names now.

    Raises:
        LinkOpenError: no such device, not a character device, or it cannot be read.
    """
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        raise LinkOpenError(f"{path}: {MISSING}") from None
    except (OSError, ValueError) as exc:
        raise LinkOpenError(f"{path}: {getattr(exc, 'strerror', None) or exc}") from None
    if not stat.S_ISCHR(st.st_mode):
        raise LinkOpenError(f"{path} is not a serial device (not a tty)")
    node = os.path.realpath(path)
    instance = (st.st_rdev, st.st_ctime_ns)
    created = _when(st.st_ctime_ns)
    major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
    if major in PTY_MAJORS:
        return _pty(path, node, instance, created)
    facts = sysfs_facts(major, minor, sysfs=sysfs)
    if facts is None:
        return DeviceIdentity("node", node, instance, created)
    return DeviceIdentity(node=node, instance=instance, created=created, **facts)


def _when(ns: int) -> str:
    t = ns / 1e9
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t)) + f".{ns // 1_000_000 % 1000:03d}"


def _pty(path: str, node: str, instance: tuple[int, int], created: str) -> DeviceIdentity:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise LinkOpenError(f"{path}: {MISSING}") from None
    except OSError as exc:
        raise LinkOpenError(f"cannot open {path}: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if (st.st_rdev, st.st_ctime_ns) != instance:
            raise LinkOpenError(f"{path}: the device changed while it was being identified")
        ws = struct.unpack("HHHH", fcntl.ioctl(fd, termios.TIOCGWINSZ, bytes(8)))
    except OSError as exc:
        raise LinkOpenError(f"cannot read {path}'s window size: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    label = read_emulator_label((ws[0], ws[1], ws[2], ws[3]))
    if label is None:
        return DeviceIdentity("pty", node, instance, created)
    return DeviceIdentity("emulator", node, instance, created, emulator=label[0], radio=label[1])


def _read(d: Path, name: str) -> str | None:
    try:
        return (d / name).read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return None


def _hex(d: Path, name: str) -> int | None:
    text = _read(d, name)
    try:
        return int(text, 16) if text else None
    except ValueError:
        return None


def sysfs_facts(major: int, minor: int, *, sysfs: str = "/sys") -> dict[str, Any] | None:
    """The identity fields (``kind`` and the kind's facts) of character device
    ``major:minor`` from sysfs under ``sysfs``, or None if sysfs says nothing of it."""
    root = Path(sysfs)
    tty = root / "dev" / "char" / f"{major}:{minor}"
    dev_link = tty / "device"
    if not dev_link.exists():
        return None
    dev = dev_link.resolve()
    subsystem = (dev / "subsystem").resolve().name if (dev / "subsystem").exists() else ""
    if subsystem == "usb-serial":
        interface = dev.parent
    elif subsystem == "usb":
        interface = dev
    else:
        devices = (root / "devices").resolve()
        where = str(dev.relative_to(devices)) if dev.is_relative_to(devices) else dev.name
        return {"kind": "serial", "device": where}
    usb = interface.parent
    vid, pid, serial = _hex(usb, "idVendor"), _hex(usb, "idProduct"), _read(usb, "serial")
    if vid is None or pid is None:
        return None
    shared = shared_serial(serial) or _others_with(root, usb, vid, pid, serial)
    return {
        "kind": "usb",
        "vid": vid,
        "pid": pid,
        "serial": serial or None,
        "interface": _hex(interface, "bInterfaceNumber"),
        "port": usb.name,
        "shared_serial": shared,
        "product": _read(usb, "product") or "",
    }


def _others_with(root: Path, usb: Path, vid: int, pid: int, serial: str | None) -> bool:
    """Whether another attached USB device has the same ids and serial number."""
    bus = root / "bus" / "usb" / "devices"
    with contextlib.suppress(OSError):
        for entry in bus.iterdir():
            if ":" in entry.name:  # an interface, not a device
                continue
            other = entry.resolve()
            if other == usb:
                continue
            facts = (_hex(other, "idVendor"), _hex(other, "idProduct"), _read(other, "serial"))
            if facts == (vid, pid, serial):
                return True
    return False


def confirm(fd: int | None, identity: DeviceIdentity, path: str) -> None:
    """Check that the open file ``fd`` is the node ``identity`` was read from.

    Raises:
        LinkOpenError: it is another (the path changed between the two).
    """
    if fd is None:
        return
    st = os.fstat(fd)
    if (st.st_rdev, st.st_ctime_ns) != identity.instance:
        raise LinkOpenError(f"{path}: the device changed while it was being opened")


__all__ = ["PTY_MAJORS", "confirm", "identify", "sysfs_facts"]
