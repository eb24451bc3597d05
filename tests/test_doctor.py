"""``swarm doctor``'s verdicts (pure: facts in, checks out) and its quick local probes.

The verdicts are fed hand-made facts, a clock in 1970 included; the probes of files
and sockets run on real files, FIFOs, devices and sockets, each hostile in its own
way (a FIFO or ``/dev/zero`` given as the key, a listen port already taken, garbage
endpoints). The doctor against the radio emulator and the vehicle simulator is
``test_doctor_bench.py``.
"""

from __future__ import annotations

import os
import socket
import time
from dataclasses import replace
from pathlib import Path

import pytest
from net_helpers import free_port

from swarm.cli.commands import doctor
from swarm.core.doctor import Check, clean, exit_code, report_json, summary, text_line
from swarm.core.doctor.host import (
    CLOCK_FLOOR,
    DeviceFacts,
    DiskFacts,
    KeyFacts,
    ZenohFacts,
    clock_check,
    device_check,
    disk_check,
    key_checks,
    parse_zenoh_endpoint,
    utc_text,
    zenoh_check,
)
from swarm.core.doctor.radio import RadioFacts, RadioPlan, radio_checks
from swarm.core.doctor.vehicle import VehicleFacts, firmware_version, vehicle_checks
from swarm.runtime.doctor import Setup, examine
from swarm.runtime.doctor.host import disk_facts, key_facts, zenoh_facts
from swarm.runtime.doctor.radio import rti_wait

NOW = 1795555200.0  # 2026-11-24
GOOD_PARAMS = {"NETID": 25, "AIR_SPEED": 64, "SERIAL_SPEED": 57, "ECC": 0, "MAVLINK": 1}


def by_name(checks: list[Check]) -> dict[str, Check]:
    return {c.name: c for c in checks}


def statuses(checks: list[Check]) -> dict[str, str]:
    return {c.name: c.status for c in checks}


# -- output ---------------------------------------------------------------------------------


def test_text_line_and_json_shape() -> None:
    checks = [
        Check("pass", "radio NETID", "25 (expected 25)"),
        Check("fail", "key mode", "/k: mode 0644: readable by others", "chmod 600 /k"),
    ]
    assert text_line(checks[0]) == "PASS radio NETID 25 (expected 25)"
    assert text_line(checks[1]) == "FAIL key mode /k: mode 0644: readable by others; fix: chmod 600 /k"
    assert report_json(checks) == {
        "ok": False,
        "checks": [
            {"status": "pass", "name": "radio NETID", "seen": "25 (expected 25)", "fix": ""},
            {
                "status": "fail",
                "name": "key mode",
                "seen": "/k: mode 0644: readable by others",
                "fix": "chmod 600 /k",
            },
        ],
    }
    assert exit_code(checks) == 1 and exit_code(checks[:1]) == 0
    assert exit_code([Check("warn", "x", "y", "z"), Check("info", "a", "b")]) == 0  # warnings allowed
    assert summary(checks) == "1 passed, 0 warnings, 1 failure: not ready: fix the failures above"


def test_hostile_text_is_escaped_and_cut() -> None:
    """A radio banner or a file name holds what a hostile sender chose: escape
    sequences must not reach the terminal, and no line grows without bound."""
    line = text_line(Check("info", "radio firmware", "SiK\x1b[2J\x07 on \r\nHM-TRP\u202e" + "A" * 1000))
    assert "\x1b" not in line and "\x07" not in line and "\r" not in line and "\n" not in line
    assert "\u202e" not in line  # a right-to-left override would reorder what the user reads
    assert "\\x1b[2J\\x07" in line and "\\u202e" in line
    assert len(line) < 400
    assert clean("ok") == "ok"
    with pytest.raises(ValueError):
        Check("fine", "x", "y")  # type: ignore[arg-type]


# -- the radio ------------------------------------------------------------------------------


def radio(params: dict[str, int], *, baud: int = 57600, banner: str = "SiK 2.2 on HM-TRP") -> RadioFacts:
    return RadioFacts("/dev/ttyUSB0", baud, answered=True, banner=banner, params=params)


def test_radio_as_expected_passes() -> None:
    checks = radio_checks(radio(GOOD_PARAMS), RadioPlan(expected={"NETID": 25, "AIR_SPEED": 64}))
    s = statuses(checks)
    assert s["radio NETID"] == s["radio AIR_SPEED"] == s["radio baud"] == s["radio MAVLINK"] == "pass"
    assert exit_code(checks) == 0
    assert text_line(by_name(checks)["radio NETID"]) == "PASS radio NETID 25 (expected 25)"


def test_radio_wrong_netid_fails_with_the_command_that_fixes_it() -> None:
    checks = radio_checks(radio({**GOOD_PARAMS, "NETID": 77}), RadioPlan(expected={"NETID": 25}))
    c = by_name(checks)["radio NETID"]
    assert c.status == "fail" and c.seen == "77 (expected 25)"
    assert "swarm radio-config /dev/ttyUSB0 --set NETID=25" in c.fix
    assert [x.name for x in checks if x.status == "fail"] == ["radio NETID"]


def test_radio_missing_expected_parameter_fails() -> None:
    c = by_name(radio_checks(radio(GOOD_PARAMS), RadioPlan(expected={"ENCRYPTION_LEVEL": 1})))
    assert c["radio ENCRYPTION_LEVEL"].status == "fail"
    assert "missing" in c["radio ENCRYPTION_LEVEL"].seen


def test_radio_serial_speed_against_the_agents_baud() -> None:
    c = by_name(radio_checks(radio(GOOD_PARAMS, baud=115200), RadioPlan()))["radio baud"]
    assert c.status == "fail"
    assert "57600 baud, but the agent opens the radio at 115200" in c.seen
    assert "?baud=57600" in c.fix and "--baud 115200 --set SERIAL_SPEED=115" in c.fix
    ok = by_name(radio_checks(radio({**GOOD_PARAMS, "SERIAL_SPEED": 115}, baud=115200), RadioPlan()))
    assert ok["radio baud"].status == "pass"
    odd = by_name(radio_checks(radio({**GOOD_PARAMS, "SERIAL_SPEED": 3}), RadioPlan()))["radio baud"]
    assert odd.status == "fail" and "no valid rate" in odd.seen


def test_radio_without_expected_parameters_reports_them_and_checks_what_it_can() -> None:
    checks = radio_checks(radio({**GOOD_PARAMS, "MAVLINK": 0, "ECC": 1}), RadioPlan())
    c = by_name(checks)
    assert c["radio parameters"].status == "info"
    assert "NETID=25 AIR_SPEED=64" in c["radio parameters"].seen
    assert c["radio MAVLINK"].status == "fail" and "--set MAVLINK=1" in c["radio MAVLINK"].fix
    assert c["radio ECC"].status == "warn"
    assert "radio NETID" not in c


def test_radio_multipoint_nodeid() -> None:
    mp = {**GOOD_PARAMS, "NODEID": 2, "NODECOUNT": 3}
    c = by_name(radio_checks(radio(mp, banner="MP SiK 2.2 on HM-TRP"), RadioPlan()))
    assert c["radio NODEID"].status == "pass" and c["radio NODEID unique"].status == "info"
    bad = by_name(radio_checks(radio({**mp, "NODEID": 3}), RadioPlan()))["radio NODEID"]
    assert bad.status == "fail" and "NODECOUNT=4" in bad.fix
    fast = by_name(radio_checks(radio(mp), RadioPlan(slots=4, air_speed=128)))
    assert fast["radio NODECOUNT"].status == "warn" and "--slots 3" in fast["radio NODECOUNT"].fix
    assert fast["radio AIR_SPEED"].status == "warn" and "--air-speed 64" in fast["radio AIR_SPEED"].fix


def test_radio_peers_answering_rti() -> None:
    mp = {**GOOD_PARAMS, "NODEID": 1, "NODECOUNT": 3}
    banner = "MP SiK 2.2 on HM-TRP"

    def checks(peers: tuple[str, ...] | None, params: dict[str, int] = mp) -> dict[str, Check]:
        f = RadioFacts("/dev/ttyUSB0", 57600, answered=True, banner=banner, params=params, peers=peers)
        return by_name(radio_checks(f, RadioPlan()))

    heard = checks(("[2] [2] MP SiK 2.2 on HM-TRP", "[0] [0] MP SiK 2.2 on HM-TRP"))
    assert (
        heard["radio NODEID unique"].status == "pass"
        and "nodes 0, 2 answered" in heard["radio NODEID unique"].seen
    )
    assert heard["radio peers"].status == "pass"
    twin = checks(("[1] [1] MP SiK 2.2 on HM-TRP", "[0] MP SiK 2.2 on HM-TRP"))["radio NODEID unique"]
    assert twin.status == "fail" and "--set NODEID=2" in twin.fix
    alone = checks(())
    assert alone["radio NODEID unique"].status == "info" and alone["radio peers"].status == "info"
    older = checks(("[2] MP SiK 2.0 on HM-TRP",))["radio peers"]
    assert older.status == "warn" and "2.0" in older.seen
    assert "radio peers" not in checks(None)  # not asked
    standard = RadioFacts("/d", 57600, answered=True, banner="SiK 2.2 on HM-TRP", params=GOOD_PARAMS)
    pair = by_name(radio_checks(replace(standard, peers=("SiK 2.2 on HM-TRP",)), RadioPlan()))
    assert pair["radio peers"].status == "pass" and "radio NODEID unique" not in pair
    hostile_peers = ("[", "]]]", "[99999999999999999999] x", "[" + "9" * 5000 + "] y", "[\u0663] z")
    hostile = by_name(radio_checks(replace(standard, peers=hostile_peers), RadioPlan()))
    assert hostile["radio peers"].status == "warn"  # garbage is another firmware, not a crash
    mp_hostile = replace(standard, params=mp, peers=hostile_peers)
    assert by_name(radio_checks(mp_hostile, RadioPlan()))["radio NODEID unique"].status == "info"


def test_silent_radio_fails_with_the_baud_hint() -> None:
    f = RadioFacts(
        "/dev/ttyUSB0", 115200, answered=False, error="no answer to +++ on /dev/ttyUSB0 at 115200 baud"
    )
    (c,) = radio_checks(f, RadioPlan(expected={"NETID": 25}))
    assert c.status == "fail" and c.seen == f.error
    assert "--baud 57600 --show" in c.fix


# -- the flight controller ---------------------------------------------------------------------

READY_FC = VehicleFacts(
    "udpin:127.0.0.1:14540",
    "udpin",
    answered=True,
    sysid=1,
    autopilot=12,
    vehicle_type=2,
    version=1 << 24 | 14 << 16 | 3 << 8 | 255,
    gps_fix=3,
    satellites=12,
    home=True,
    origin=True,
)


def test_ready_flight_controller_passes() -> None:
    checks = vehicle_checks(READY_FC)
    assert exit_code(checks) == 0
    c = by_name(checks)
    assert c["fc"].seen.startswith("PX4 quadrotor, system id 1")
    assert c["fc firmware"].seen == "PX4 1.14.3"
    assert c["fc GPS"].seen == "3D fix, 12 satellites"
    assert firmware_version(4 << 24 | 6 << 16) == "4.6.0-dev"


@pytest.mark.parametrize(
    ("change", "name", "status"),
    [
        ({"gps_fix": 1}, "fc GPS", "fail"),
        ({"gps_fix": 2}, "fc GPS", "warn"),
        ({"gps_fix": None}, "fc GPS", "warn"),
        ({"home": False, "origin": False}, "fc home", "fail"),
        ({"armed": True}, "fc armed", "warn"),
        ({"autopilot": 0}, "fc", "warn"),
        ({"vehicle_type": 1}, "fc", "warn"),
        ({"version": None}, "fc firmware", "warn"),
        ({"kind": "serial", "baud": 9600}, "fc link", "warn"),
        ({"kind": "serial", "baud": 921600}, "fc link", "pass"),
        ({"clock_offset_s": 0.3}, "fc clock", "pass"),
        ({"clock_offset_s": -20.0}, "fc clock", "warn"),
        ({"clock_offset_s": 3600.0}, "fc clock", "fail"),
        ({"clock_offset_s": float("nan")}, "fc clock", "warn"),
    ],
)
def test_flight_controller_faults(change: dict[str, object], name: str, status: str) -> None:
    c = by_name(vehicle_checks(replace(READY_FC, **change)))  # type: ignore[arg-type]
    assert c[name].status == status


def test_no_flight_controller_fails_with_the_fix_for_its_link() -> None:
    serial = VehicleFacts(
        "/dev/ttyACM0", "serial", answered=False, error="no autopilot heartbeat", baud=57600
    )
    (c,) = vehicle_checks(serial)
    assert c.status == "fail" and "SERIALn_BAUD" in c.fix and "57600 baud" in c.fix
    (u,) = vehicle_checks(VehicleFacts("udpin:0.0.0.0:14540", "udpin", answered=False, error="x"))
    assert u.status == "fail" and "sends to this port" in u.fix


# -- devices, key, clock, Zenoh, disk --------------------------------------------------------


def test_device_verdicts() -> None:
    missing = device_check(DeviceFacts("radio", "/dev/ttyUSB9", exists=False))
    assert missing.status == "fail" and "/dev/serial/by-id" in missing.fix
    denied = DeviceFacts("radio", "/dev/ttyUSB0", True, True, "permission", "pilot", "dialout", False, False)
    assert "usermod -aG dialout pilot" in device_check(denied).fix
    stale = DeviceFacts("radio", "/dev/ttyUSB0", True, True, "permission", "pilot", "dialout", False, True)
    assert "log out and in again" in device_check(stale).fix and "usermod" not in device_check(stale).fix
    busy = device_check(DeviceFacts("fc", "/dev/ttyACM0", True, True, "busy", "pilot"))
    assert busy.status == "fail" and "swarm agent" in busy.fix
    assert device_check(DeviceFacts("radio", "/dev/x", True, True, "", "pilot")).status == "pass"
    assert device_check(DeviceFacts("radio", "/tmp/f", True, False)).status == "fail"


def key(**kw: object) -> KeyFacts:
    base: dict[str, object] = {"path": "/k", "exists": True, "is_file": True, "mode": 0o100600}
    base.update(owner=0, uid=0, size=32, kind="raw")
    base.update(kw)
    return KeyFacts(**base)  # type: ignore[arg-type]


def test_key_verdicts() -> None:
    assert statuses(key_checks(key(), on_radio=True)) == {"key mode": "pass", "key": "pass"}
    world = by_name(key_checks(key(mode=0o100644), on_radio=True))["key mode"]
    assert world.status == "fail" and "mode 0644: readable by others" in world.seen
    assert world.fix == "chmod 600 /k"
    group = by_name(key_checks(key(mode=0o100640), on_radio=True))["key mode"]
    assert group.status == "fail" and "its group" in group.seen
    assert by_name(key_checks(key(mode=0o100400), on_radio=True))["key mode"].status == "pass"
    assert by_name(key_checks(key(kind="hex", size=65), on_radio=True))["key"].status == "pass"
    assert by_name(key_checks(key(kind="passphrase", size=12), on_radio=True))["key"].status == "warn"
    assert by_name(key_checks(key(kind="empty", size=0), on_radio=True))["key"].status == "fail"
    assert by_name(key_checks(key(size=1 << 20, kind=""), on_radio=True))["key"].status == "fail"
    assert by_name(key_checks(key(owner=1000), on_radio=True))["key owner"].status == "warn"
    assert key_checks(key(exists=False), on_radio=True)[0].status == "fail"
    assert key_checks(None, on_radio=True)[0].status == "warn"
    assert key_checks(None, on_radio=False)[0].status == "info"


def test_clock_in_the_past_fails() -> None:
    """A companion without a real-time clock boots in 1970: signing breaks."""
    c = clock_check(0.0)
    assert c.status == "fail" and c.seen.startswith("1970-01-01 00:00 UTC: before 2026-01-01")
    assert "NTP" in c.fix
    assert clock_check(1500000000.0).status == "fail"  # 2017: after signing's epoch, still wrong
    assert clock_check(CLOCK_FLOOR - 1).status == "fail"
    assert clock_check(NOW).status == "pass"
    assert clock_check(CLOCK_FLOOR + 21 * 365.25 * 86400).status == "warn"
    assert clock_check(5e9).status == "fail"  # past the 48-bit signing timestamps (2104)
    for bad in (float("nan"), float("inf"), -1e300):
        assert clock_check(bad).status == "fail"
    assert utc_text(951782400) == "2000-02-29 00:00 UTC"


def test_clock_injected_into_the_whole_check() -> None:
    """examine() takes ``now``: the same check with the clock at 1970 fails on it alone."""
    port = free_port("tcp")
    setup = Setup(zenoh_listen=(f"tcp/127.0.0.1:{port}",))
    good = examine(setup, now=NOW)
    past = examine(setup, now=0.0)
    assert exit_code(good) == 0
    assert [c.name for c in past if c.status == "fail"] == ["clock"]


def test_zenoh_endpoint_grammar() -> None:
    assert parse_zenoh_endpoint("tcp/127.0.0.1:7447") == ("tcp", "127.0.0.1", 7447)
    assert parse_zenoh_endpoint("udp/[::1]:7447#iface=lo") == ("udp", "::1", 7447)
    assert parse_zenoh_endpoint("TCP/host.local:0?prio=1") == ("tcp", "host.local", 0)
    long_port = "tcp/h:" + "9" * 5000
    for bad in (
        "",
        "tcp",
        "tcp/",
        "tcp/127.0.0.1",
        "tcp/127.0.0.1:99999",
        "tcp/:7447",
        "tcp/h:x",
        "foo/h:1",
        long_port,
    ):
        with pytest.raises(ValueError, match=r"expected|protocol|no host"):  # our message, not int()'s
            parse_zenoh_endpoint(bad)
    for digit in ("\u00b2", "\u0663"):  # a superscript two, an Arabic-Indic three: str.isdigit() says yes
        with pytest.raises(ValueError, match="expected"):
            parse_zenoh_endpoint("tcp/h:" + digit)


def test_zenoh_probe_sees_a_taken_port_and_garbage() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        c = zenoh_check(zenoh_facts(f"tcp/127.0.0.1:{port}", "listen"))
        assert c.status == "fail" and "cannot bind" in c.seen
    assert zenoh_check(zenoh_facts(f"tcp/127.0.0.1:{free_port('tcp')}", "listen")).status == "pass"
    assert zenoh_check(zenoh_facts("tcp/192.0.2.1:7447", "connect")).status == "pass"
    assert zenoh_check(zenoh_facts("tcp/no-such-host.invalid:7447", "connect")).status == "fail"
    assert zenoh_check(zenoh_facts("tcp/203.0.113.9:7447", "listen")).status == "fail"  # not ours
    assert zenoh_check(zenoh_facts("\x1b[2J/;rm -rf", "listen")).status == "fail"
    assert zenoh_check(zenoh_facts("unixsock-stream//tmp/z.sock", "listen")).status == "info"
    assert zenoh_check(ZenohFacts("tcp/h:1", "connect", error="cannot resolve")).status == "fail"


def test_disk_probe(tmp_path: Path) -> None:
    here = disk_facts(str(tmp_path / "not" / "yet"))
    assert here.path == str(tmp_path) and here.writable and here.free > 0
    assert disk_check(DiskFacts("/d", free=50 << 20, writable=True)).status == "fail"
    assert disk_check(DiskFacts("/d", free=500 << 20, writable=True)).status == "warn"
    assert disk_check(DiskFacts("/d", free=5 << 30, writable=True)).status == "pass"
    assert disk_check(DiskFacts("/d", free=5 << 30, writable=False)).status == "fail"


# -- the key probe, against hostile files ----------------------------------------------------


def test_key_probe_reads_a_good_key(tmp_path: Path) -> None:
    path = tmp_path / "swarm.key"
    path.write_bytes(os.urandom(32))
    path.chmod(0o600)
    f = key_facts(str(path))
    assert (f.kind, f.size, f.mode & 0o777) == ("raw", 32, 0o600)
    path.write_text("ab" * 32 + "\n")
    assert key_facts(str(path)).kind == "hex"
    path.write_text("correct horse battery staple\n")
    assert key_facts(str(path)).kind == "passphrase"
    path.write_text("  \n")
    assert key_facts(str(path)).kind == "empty"
    assert not key_facts(str(tmp_path / "nothing")).exists


def test_key_probe_world_readable(tmp_path: Path) -> None:
    path = tmp_path / "swarm.key"
    path.write_bytes(os.urandom(32))
    path.chmod(0o644)
    c = by_name(key_checks(key_facts(str(path)), on_radio=True))
    assert c["key mode"].status == "fail" and f"chmod 600 {path}" == c["key mode"].fix
    assert c["key"].status == "pass"


@pytest.mark.timeout(20)
def test_key_probe_never_hangs_on_a_fifo_or_floods_on_a_device(tmp_path: Path) -> None:
    """A FIFO given as the key would block an open() or read() forever; /dev/zero
    and /dev/urandom would never end: the probe stats first and refuses them."""
    fifo = tmp_path / "key.fifo"
    os.mkfifo(fifo, 0o600)
    for path in (str(fifo), "/dev/zero", "/dev/urandom"):
        t0 = time.monotonic()
        f = key_facts(path)
        assert time.monotonic() - t0 < 5.0
        assert f.exists and not f.is_file
        assert by_name(key_checks(f, on_radio=True))["key"].status == "fail"
    link = tmp_path / "link.key"
    link.symlink_to("/dev/zero")
    assert not key_facts(str(link)).is_file
    big = tmp_path / "big.key"
    big.write_bytes(b"x" * 100_000)
    big.chmod(0o600)
    assert by_name(key_checks(key_facts(str(big)), on_radio=True))["key"].status == "fail"


# -- the command line -----------------------------------------------------------------------


def test_doctor_takes_the_agents_flags_without_name_and_id() -> None:
    a = doctor.parse_args(["--zenoh-listen", "tcp/127.0.0.1:7447"])
    assert a.name is None and a.id is None and a.expected is None
    a = doctor.parse_args(["--name", "a1", "--id", "3", "--radio", "/dev/x", "--radio-params", "NETID=25"])
    assert a.expected == {"NETID": 25} and a.plan.slots is None
    a = doctor.parse_args(["--radio", "/dev/x", "--profile", "fast", "--slots", "4", "--air-speed", "128"])
    assert (a.plan.slots, a.plan.air_speed) == (4, 128)
    a = doctor.parse_args(["--radio", "/dev/x", "--profile", "fast", "--round-s", "0.3"])
    assert a.plan.slots is None  # a given round is not computed from the radio's slots


@pytest.mark.parametrize(
    "argv",
    [
        [],  # no way in
        ["--radio", "/dev/x", "--zenoh-listen", "tcp/127.0.0.1:7447"],  # two
        ["--radio", "/dev/x", "--radio-params", "NETID=abc"],
        ["--radio", "/dev/x", "--radio-params", "NOPE=1"],
        ["--radio", "/dev/x", "--radio-params", "/no/such/file.toml"],
        ["--zenoh-listen", "tcp/127.0.0.1:7447", "--id", "251"],
        ["--zenoh-listen", "tcp/127.0.0.1:7447", "--bogus"],
        ["--zenoh-listen", "tcp/127.0.0.1:7447", "--name", "a b\x1b[2J"],
        ["--zenoh-listen", "tcp/127.0.0.1:7447", "--speed", "-5"],
        ["--zenoh-listen", "tcp/127.0.0.1:7447", "--pose-hz", "nan"],
    ],
)
def test_bad_arguments_exit_2_with_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:  # argparse's own refusals
        code = doctor.main(argv)
        raise SystemExit(code)
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert "Traceback" not in err and err.strip()


@pytest.mark.parametrize(
    "setup",
    [
        Setup(radio="/dev/x\x00y"),
        Setup(fc="/dev/x\x00y"),
        Setup(fc="/dev/" + "x" * 5000),
        Setup(key="/k\x00y", zenoh_connect=("tcp/127.0.0.1:7447",)),
        Setup(capture="/tmp\x00/c", zenoh_connect=("tcp/127.0.0.1:7447",)),
        Setup(zenoh_listen=("tcp/" + "9" * 5000 + ":1", "\x00/\x00:\x00")),
    ],
)
def test_hostile_config_values_become_lines_not_tracebacks(setup: Setup) -> None:
    """Values a config file could carry (a NUL, 5000 characters): each one becomes a
    checklist line; nothing escapes as an exception."""
    checks = examine(setup, now=NOW)
    assert checks and any(c.status in ("fail", "warn") for c in checks)
    assert all(len(text_line(c)) < 1000 for c in checks)


def test_rti_wait_follows_the_radio_network() -> None:
    """Three TDM rounds of the radio's own network, between 1 and 10 s; parameters no
    firmware boots with (a hostile or broken radio) give the longest wait, no error."""
    assert rti_wait({"AIR_SPEED": 64}) == 1.0  # a pair: 0.24 s rounds
    assert 7.0 < rti_wait({"AIR_SPEED": 64, "NODECOUNT": 20}) < 7.2  # 2.37 s rounds
    assert rti_wait({"AIR_SPEED": 2, "NODECOUNT": 32}) == 10.0
    for odd in ({"AIR_SPEED": 0}, {"AIR_SPEED": -1, "NODECOUNT": -5}, {"AIR_SPEED": 10**30}):
        assert 1.0 <= rti_wait(odd) <= 10.0


def test_capture_disk_in_the_whole_check(tmp_path: Path) -> None:
    setup = Setup(zenoh_connect=("tcp/127.0.0.1:7447",), capture=str(tmp_path / "captures"))
    disk = by_name(examine(setup, now=NOW))["disk"]
    assert disk.status in ("pass", "warn") and disk.seen.startswith(str(tmp_path))
