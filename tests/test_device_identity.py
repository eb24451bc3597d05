"""A device is the device it was (issue 27): identities, how they compare, how they are read.

The comparison (:mod:`radios.device_id`) is pure and tested on values; the USB facts
are read from sysfs, so they are tested on trees of files laid out as the kernel lays
out ``/sys`` for a CP2102, a Pixhawk (CDC ACM), an FT4232's second port and a Pi's UART
(the parsing of input, not a stand-in for a running part: no USB adapter is plugged
into this machine). Ptys are real: the emulator's (labelled) and bare ones, and a
:class:`~radios.seriallink.SerialLink` reopening them. The bridge and a real agent
facing a swapped device are in ``test_radio_reopen.py``.
"""

from __future__ import annotations

import os
import select
import time
from dataclasses import replace
from pathlib import Path

import pytest
from emu_helpers import heartbeat, raw_pty

from radios.device_id import (
    DeviceIdentity,
    emulator_label,
    mismatch,
    read_emulator_label,
    refusal,
    shared_serial,
)
from radios.device_probe import confirm, identify, sysfs_facts
from radios.emulator import Emulator
from radios.emulator_config import EmulatorConfig
from radios.errors import DeviceMismatchError, LinkOpenError
from radios.link import open_link

# -- the comparison (pure) ------------------------------------------------------------

CP2102 = DeviceIdentity(
    "usb", "/dev/ttyUSB0", (1, 1), vid=0x10C4, pid=0xEA60, serial="0001", interface=0, port="1-1.2",
    shared_serial=True,
)  # fmt: skip
FTDI = DeviceIdentity(
    "usb", "/dev/ttyUSB0", (1, 1), vid=0x0403, pid=0x6015, serial="DN04ABCD", interface=0, port="1-1.2"
)
EMU = DeviceIdentity("emulator", "/dev/pts/4", (2, 2), emulator=0x3FA2C8E1, radio=1)
PTY = DeviceIdentity("pty", "/dev/pts/7", (136 << 8 | 7, 123), created="2026-01-01 10:00:00.000")
UART = DeviceIdentity("serial", "/dev/ttyAMA0", (3, 3), device="platform/soc/fe201000.serial")


@pytest.mark.parametrize(
    ("expected", "found", "why"),
    [
        # a radio plugged back, with a new node, even in another port: its serial number says it
        (FTDI, replace(FTDI, node="/dev/ttyUSB1", instance=(9, 9), port="1-1.4"), None),
        (FTDI, replace(FTDI, serial="DN04ABCE"), "another serial number"),
        (FTDI, replace(FTDI, pid=0x6001), "another kind of USB adapter"),
        (FTDI, replace(FTDI, interface=1), "another interface of the adapter"),
        # a serial number many adapters share: only the same port brings it back
        (CP2102, replace(CP2102, node="/dev/ttyUSB3", instance=(8, 8)), None),
        (CP2102, replace(CP2102, port="1-1.3"), "another USB port"),
        (replace(CP2102, serial=None), replace(CP2102, serial=None, port="1-1.3"), "another USB port"),
        # the emulator's radio in a new pty after a replug, not another radio or emulator
        (EMU, replace(EMU, node="/dev/pts/9", instance=(5, 5)), None),
        (EMU, replace(EMU, radio=2), "another radio"),
        (EMU, replace(EMU, emulator=0x3FA2C8E2), "a radio of another emulator"),
        (EMU, PTY, "not an emulator radio"),
        (FTDI, PTY, "not a USB adapter"),
        (PTY, EMU, "not a pty"),
        # a bare pty or node: only the node that was opened (same number, same birth)
        (PTY, replace(PTY), None),
        (PTY, replace(PTY, instance=(PTY.instance[0], 456)), "another device (the one opened is gone)"),
        (UART, replace(UART, instance=(4, 4)), None),
        (UART, replace(UART, device="platform/soc/fe215040.serial"), "another serial port"),
    ],
)
def test_mismatch(expected: DeviceIdentity, found: DeviceIdentity, why: str | None) -> None:
    got = mismatch(expected, found)
    if why is None:
        assert got is None
    else:
        assert got is not None and got.startswith(why), got


def test_shared_serial_numbers() -> None:
    for serial in (None, "", "0001", "1234", "A50285BI", "a50285bi", "000000", "11111111"):
        assert shared_serial(serial), serial
    for serial in ("DN04ABCD", "0123456789ab", "A9XK3LQ2"):
        assert not shared_serial(serial), serial


def test_one_line_names_both_devices() -> None:
    line = refusal("/dev/serial/by-id/usb-radio", CP2102, replace(CP2102, port="1-1.3"), "another USB port")
    assert line == (
        "/dev/serial/by-id/usb-radio: USB 10c4:ea60 serial 0001 in port 1-1.3 at /dev/ttyUSB0 is not the "
        "radio opened (USB 10c4:ea60 serial 0001 in port 1-1.2 at /dev/ttyUSB0): another USB port"
    )
    assert "\n" not in line
    assert EMU.describe() == "emulator 3fa2c8e1's radio 1 at /dev/pts/4"
    assert PTY.describe() == "pty /dev/pts/7 with no identity, made 2026-01-01 10:00:00.000"
    assert UART.describe() == "serial port /dev/ttyAMA0 at platform/soc/fe201000.serial"
    assert (
        replace(FTDI, serial=None, interface=2)
        .describe()
        .startswith("USB 0403:6015 no serial number interface 2")
    )


def test_emulator_label_round_trip() -> None:
    for emulator, radio in ((0, 0), (0x3FA2C8E1, 7), ((1 << 32) - 1, 65535)):
        assert read_emulator_label(emulator_label(emulator, radio)) == (emulator, radio)
    assert read_emulator_label((24, 80, 0, 0)) is None  # a terminal's window size is no label
    for bad in ((1 << 32, 0), (-1, 0), (0, 1 << 16)):
        with pytest.raises(ValueError):
            emulator_label(*bad)


# -- USB facts from sysfs (trees laid out as the kernel does) ---------------------------------


def _files(d: Path, **files: str) -> None:
    d.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (d / name).write_text(text + "\n")


def _link(at: Path, target: Path) -> None:
    at.parent.mkdir(parents=True, exist_ok=True)
    target.mkdir(parents=True, exist_ok=True)
    at.symlink_to(os.path.relpath(target, at.parent))


def _usb_device(sys: Path, port: str, **files: str) -> Path:
    d = sys / "devices/pci0000:00/0000:00:14.0/usb1" / port
    _files(d, **files)
    _link(sys / "bus/usb/devices" / port, d)
    return d


def _usb_serial_tty(sys: Path, usb: Path, intf: int, tty: str, dev: str) -> None:
    """``ttyUSB``: tty -> usb-serial port -> interface -> device (cp210x, ftdi_sio)."""
    interface = usb / f"{usb.name}:1.{intf}"
    _files(interface, bInterfaceNumber=f"{intf:02x}")
    _link(interface / "subsystem", sys / "bus/usb")
    port = interface / tty
    _link(port / "subsystem", sys / "bus/usb-serial")
    _link(port / "tty" / tty / "device", port)
    _link(sys / "dev/char" / dev, port / "tty" / tty)


def test_sysfs_facts_of_a_cp2102_and_its_shared_serial_number(tmp_path: Path) -> None:
    usb = _usb_device(
        tmp_path,
        "1-1.2",
        idVendor="10c4",
        idProduct="ea60",
        serial="0001",
        product="CP2102 USB to UART Bridge",
    )
    _usb_serial_tty(tmp_path, usb, 0, "ttyUSB0", "188:0")
    assert sysfs_facts(188, 0, sysfs=str(tmp_path)) == {
        "kind": "usb", "vid": 0x10C4, "pid": 0xEA60, "serial": "0001", "interface": 0, "port": "1-1.2",
        "shared_serial": True, "product": "CP2102 USB to UART Bridge",
    }  # fmt: skip


def test_sysfs_facts_a_serial_number_held_twice_is_shared(tmp_path: Path) -> None:
    usb = _usb_device(tmp_path, "1-1.2", idVendor="0403", idProduct="6015", serial="DN04ABCD")
    _usb_serial_tty(tmp_path, usb, 0, "ttyUSB0", "188:0")
    facts = sysfs_facts(188, 0, sysfs=str(tmp_path))
    assert facts is not None and facts["shared_serial"] is False and facts["serial"] == "DN04ABCD"
    _usb_device(tmp_path, "1-1.3", idVendor="0403", idProduct="6015", serial="DN04ABCD")  # a clone, attached
    facts = sysfs_facts(188, 0, sysfs=str(tmp_path))
    assert facts is not None and facts["shared_serial"] is True


def test_sysfs_facts_of_a_pixhawk_on_cdc_acm(tmp_path: Path) -> None:
    usb = _usb_device(tmp_path, "1-1.3", idVendor="26ac", idProduct="0011", serial="3E0031000B51353233343932")
    interface = usb / "1-1.3:1.0"
    _files(interface, bInterfaceNumber="00")
    _link(interface / "subsystem", tmp_path / "bus/usb")
    _link(interface / "tty/ttyACM0/device", interface)  # ttyACM: the interface is the device
    _link(tmp_path / "dev/char/166:0", interface / "tty/ttyACM0")
    facts = sysfs_facts(166, 0, sysfs=str(tmp_path))
    assert facts is not None
    assert (facts["kind"], facts["vid"], facts["pid"], facts["port"]) == ("usb", 0x26AC, 0x0011, "1-1.3")
    assert facts["serial"] == "3E0031000B51353233343932" and not facts["shared_serial"]


def test_sysfs_facts_of_a_quad_adapters_second_port(tmp_path: Path) -> None:
    usb = _usb_device(tmp_path, "2-1", idVendor="0403", idProduct="6011", serial="FT4Q7Z21")
    _usb_serial_tty(tmp_path, usb, 0, "ttyUSB0", "188:0")
    _usb_serial_tty(tmp_path, usb, 1, "ttyUSB1", "188:1")
    first, second = sysfs_facts(188, 0, sysfs=str(tmp_path)), sysfs_facts(188, 1, sysfs=str(tmp_path))
    assert first is not None and second is not None
    assert (first["interface"], second["interface"]) == (0, 1) and second["port"] == "2-1"


def test_sysfs_facts_of_a_built_in_uart_and_of_nothing(tmp_path: Path) -> None:
    uart = tmp_path / "devices/platform/soc/fe201000.serial"
    _link(uart / "subsystem", tmp_path / "bus/amba")
    _link(uart / "tty/ttyAMA0/device", uart)
    _link(tmp_path / "dev/char/204:64", uart / "tty/ttyAMA0")
    assert sysfs_facts(204, 64, sysfs=str(tmp_path)) == {
        "kind": "serial",
        "device": "platform/soc/fe201000.serial",
    }
    _files(tmp_path / "devices/virtual/tty/tty0")  # a virtual console: no device
    _link(tmp_path / "dev/char/4:0", tmp_path / "devices/virtual/tty/tty0")
    assert sysfs_facts(4, 0, sysfs=str(tmp_path)) is None
    assert sysfs_facts(188, 7, sysfs=str(tmp_path)) is None  # not there at all
    broken = _usb_device(tmp_path, "3-1", idProduct="ea60")  # no idVendor: no USB identity
    _usb_serial_tty(tmp_path, broken, 0, "ttyUSB5", "188:5")
    assert sysfs_facts(188, 5, sysfs=str(tmp_path)) is None


# -- real ptys ------------------------------------------------------------------------------


def test_identify_an_emulator_radio_and_a_bare_pty(tmp_path: Path) -> None:
    emu = Emulator(EmulatorConfig(nodes=2, directory=str(tmp_path)))
    try:
        emu.open()
        radios = [identify(str(tmp_path / f"radio{i}")) for i in range(2)]
        assert [(r.kind, r.emulator, r.radio) for r in radios] == [
            ("emulator", emu.instance, 0),
            ("emulator", emu.instance, 1),
        ]
        assert radios[1].node == emu.slave_names[1]
        assert mismatch(radios[0], radios[1]) == "another radio"
        assert emu.stats()["emulator"] == f"{emu.instance:08x}"
    finally:
        emu.close()
    master, name = raw_pty()
    try:
        bare = identify(name)
        assert (
            bare.kind == "pty"
            and bare.node == name
            and bare.describe().startswith(f"pty {name} with no identity")
        )
        assert mismatch(bare, identify(name)) is None  # the same pty, identified again
    finally:
        os.close(master)
    with pytest.raises(LinkOpenError, match="no such device"):
        identify(str(tmp_path / "radio0"))  # the emulator is gone
    (tmp_path / "file").write_text("x")
    with pytest.raises(LinkOpenError, match="not a serial device"):
        identify(str(tmp_path / "file"))


def test_confirm_catches_a_path_changed_while_opening() -> None:
    m1, n1 = raw_pty()
    m2, n2 = raw_pty()
    fd = os.open(n2, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        confirm(fd, identify(n2), n2)
        with pytest.raises(LinkOpenError, match="changed while it was being opened"):
            confirm(fd, identify(n1), n1)
    finally:
        for x in (fd, m1, m2):
            os.close(x)


def _arrived(master: int, seconds: float) -> bytes:
    got = bytearray()
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        if select.select([master], [], [], left)[0]:
            try:
                got += os.read(master, 4096)
            except OSError:  # nobody holds the slave open
                time.sleep(0.02)
    return bytes(got)


def test_serial_link_reopens_its_own_pty_and_refuses_another(tmp_path: Path) -> None:
    """A link on a bare pty (a socat bridge, a test): released and reopened, it takes the
    same pty back (the radio check's lend); a new pty at its path is refused unopened."""
    master, name = raw_pty()
    path = tmp_path / "radio"
    path.symlink_to(name)
    other_master = -1
    link = open_link(str(path), capture=str(tmp_path / "c.tlog"))  # through the capture wrapper too
    try:
        assert link.identity is not None and link.identity.kind == "pty" and link.identity.node == name
        link.check_device()
        link.release()
        link.reopen()
        link.send(heartbeat(1))
        assert _arrived(master, 0.5) == heartbeat(1)
        link.release()
        other_master, other = raw_pty()
        path.unlink()
        path.symlink_to(other)
        with pytest.raises(DeviceMismatchError) as info:
            link.check_device()
        for _ in range(3):
            with pytest.raises(DeviceMismatchError) as info:
                link.reopen()
        text = str(info.value)
        assert (
            text.startswith(f"{path}: pty {other} with no identity") and f"radio opened (pty {name} " in text
        )
        assert info.value.found is not None and info.value.expected == link.identity
        assert _arrived(other_master, 0.3) == b""
        path.unlink()
        path.symlink_to(name)
        link.reopen()  # its own pty again
        link.send(heartbeat(2))
        assert _arrived(master, 0.5) == heartbeat(2)
        assert _arrived(other_master, 0.1) == b""
    finally:
        link.close()
        os.close(master)
        if other_master >= 0:
            os.close(other_master)


def test_a_pyserial_url_has_no_identity() -> None:
    with open_link("loop://") as link:
        assert link.identity is None
        link.check_device()  # nothing to check
        link.reopen()
