"""The SiK network emulator on real ptys, with pymavlink as an independent client.

In-process tests run :class:`~radios.emulator.Emulator` in a thread (emu_helpers);
real-process tests start ``python -m swarm.cli radio-emu`` and stop it with a
signal; ``swarm radio-config`` talks AT commands to the emulator's ptys with real
guard times (about 3 s to read, 6 s to write). Every wait is a poll with a generous
deadline; absence ("never heard") is checked over a bounded window *and* on the
emulator's own counters, which say whether anything was put on a radio's output.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from emu_helpers import (
    AIR_DEADLINE,
    FAST_LOCK_SEED,
    garbage,
    heartbeat,
    is_raw,
    opened,
    recv_until,
    running_emulator,
    tunnel,
)
from net_helpers import wait_until
from pymavlink import mavutil

from radios.air import RADIO_STATUS_COMPID, RADIO_STATUS_SYSID
from radios.link import open_link
from radios.mavlink import MSG_RADIO_STATUS, STX_V1, STX_V2, Frame, FrameBuilder, pack_frame
from radios.tlog import read_tlog

pytestmark = pytest.mark.processes  # the radio emulator, in real time and as a process

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def mav20() -> Iterator[Any]:
    """pymavlink speaking MAVLink 2 (its dialect is chosen from the environment)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MAVLINK20", "1")
        mavutil.set_dialect("ardupilotmega")
        yield mavutil
    mavutil.set_dialect("ardupilotmega")  # back to what the environment says


def mav_connect(path: str, sysid: int) -> Any:
    return mavutil.mavlink_connection(path, baud=57600, source_system=sysid)


def send_heartbeat(conn: Any) -> None:
    conn.mav.heartbeat_send(
        mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
    )


def mav_recv_until(conn: Any, match: Any, timeout: float, seen: list[Any] | None = None) -> Any:
    """pymavlink messages until one matches ``match(msg)`` or ``timeout`` passes."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        msg = conn.recv_match(blocking=True, timeout=min(left, 0.5))
        if msg is None:
            continue
        if seen is not None:
            seen.append(msg)
        if match(msg):
            return msg
    return None


def from_sys(sysid: int, kind: str = "HEARTBEAT") -> Any:
    return lambda m: m.get_type() == kind and m.get_srcSystem() == sysid


# -- delivery -----------------------------------------------------------------------------------


def test_heartbeat_reaches_the_peer_only_and_the_sender_gets_radio_status(tmp_path: Path, mav20: Any) -> None:
    with running_emulator(tmp_path, 2) as emu:
        m0, m1 = mav_connect(emu.paths[0], 1), mav_connect(emu.paths[1], 2)
        try:
            emu.wait_ready(0, 1)
            send_heartbeat(m0)
            hb = mav_recv_until(m1, from_sys(1), AIR_DEADLINE)
            assert hb is not None, "radio1's host never got radio0's heartbeat"
            assert hb.get_msgbuf()[0] == STX_V2

            seen0: list[Any] = []
            rs = mav_recv_until(m0, lambda m: m.get_type() == "RADIO_STATUS", AIR_DEADLINE, seen0)
            assert rs is not None, "no RADIO_STATUS after the host's HEARTBEAT"
            assert (rs.get_srcSystem(), rs.get_srcComponent()) == (51, 68)
            assert rs.get_msgbuf()[0] == STX_V2  # MAVLink 2, as the heartbeat was
            assert 90 <= rs.txbuf <= 100  # % free of radio0's serial input buffer: ~empty

            # nothing comes back to the sender: not on its serial output (the radio's
            # own counter) and not seen by its host over a further second
            mav_recv_until(m0, lambda m: False, 1.0, seen0)
            assert not [m for m in seen0 if m.get_type() == "HEARTBEAT"]
            assert emu.radio(0)["rx_bytes"] == 0
            assert emu.radio(1)["rx_bytes"] == len(hb.get_msgbuf())
        finally:
            m0.close()
            m1.close()


@pytest.mark.parametrize("version", [1, 2])
def test_radio_status_uses_the_heartbeat_s_mavlink_version(tmp_path: Path, version: int) -> None:
    if version == 2:
        hb = heartbeat(9)
    else:
        body = bytes(4) + bytes((18, 8, 0, 4, 3))
        hb = pack_frame(0, body, sysid=9, compid=0, seq=0, version=1)
    with running_emulator(tmp_path, 2) as emu, opened(emu.open(0)) as (link,):
        emu.wait_ready(0)
        link.send(hb)
        rs = recv_until(link, lambda f: f.msgid == MSG_RADIO_STATUS)
        assert rs is not None
        assert rs.raw[0] == (STX_V2 if version == 2 else STX_V1)
        assert (rs.sysid, rs.compid) == (RADIO_STATUS_SYSID, RADIO_STATUS_COMPID)


def test_different_netids_never_hear_each_other(tmp_path: Path) -> None:
    with running_emulator(tmp_path, 2, netids=[25, 26]) as emu, opened(emu.open(0), emu.open(1)) as (l0, l1):
        emu.wait_connected(0, 1)
        seen: list[Frame] = []
        for k in range(5):
            l0.send(tunnel(1, b"anyone on 26?", seq=k))
            l1.send(tunnel(2, b"anyone on 25?", seq=k))
            recv_until(l1, lambda f: False, 0.3, seen)
        recv_until(l0, lambda f: False, 0.3, seen)
        assert seen == []
        r0, r1 = emu.radio(0), emu.radio(1)
        assert r0["tx_bytes"] > 0 and r1["tx_bytes"] > 0  # they did transmit
        assert r0["rx_bytes"] == r1["rx_bytes"] == 0
        assert not r0["locked"] and not r1["locked"]


def test_multipoint_frame_reaches_every_other_radio(tmp_path: Path, mav20: Any) -> None:
    with running_emulator(tmp_path, 3) as emu:
        assert emu.emu.firmware == "multipoint"
        conns = [mav_connect(p, 10 + i) for i, p in enumerate(emu.paths)]
        try:
            emu.wait_ready(0, 1, 2)
            send_heartbeat(conns[0])
            for i in (1, 2):
                assert mav_recv_until(conns[i], from_sys(10), AIR_DEADLINE) is not None, (
                    f"radio{i} never heard radio0"
                )
            assert emu.radio(0)["rx_bytes"] == 0  # not delivered back to the sender
        finally:
            for c in conns:
                c.close()


def test_bytes_written_right_after_opening_the_port_are_delivered(tmp_path: Path) -> None:
    """A host that opens the port and writes at once (pymavlink sends a heartbeat
    straight away) must not lose those bytes, although the emulator notices a new
    host only every 0.1 s (it used to discard them as "stale input")."""
    with running_emulator(tmp_path, 2) as emu, opened(emu.open(1)) as (l1,):
        emu.wait_ready(1)
        emu.wait_locked(0)
        raw = tunnel(1, b"first words")
        with opened(emu.open(0)) as (l0,):
            l0.send(raw)
            got = recv_until(l1, lambda f: True, 5.0)
            assert got is not None and got.raw == raw, (
                f"lost: radio0 serial_in={emu.radio(0)['serial_in']} (the emulator never read it)"
            )


# -- bad input ------------------------------------------------------------------------------


def _bad_frames() -> bytes:
    """Oversized claims, bad CRCs (some on heartbeats), truncations: no valid frame."""
    hb = heartbeat(66)
    bad_crc = hb[:-2] + bytes((hb[-2] ^ 0xFF, hb[-1]))
    big = tunnel(66, bytes(range(1, 129)))
    out = bytearray()
    for k in range(40):
        out += bad_crc + b"\xfd\xff\x00\x00" + bytes(50) + big[: 40 + k] + big[:-1] + bytes((big[-1] ^ 1,))
    return bytes(out)


def test_garbage_and_flood_on_one_port_hurt_only_that_radio(tmp_path: Path) -> None:
    """20 kB of garbage and bad frames written into radio0 as fast as the serial
    line takes them, never reading radio0: the emulator survives, radio1 keeps
    talking to radio2, and only radio0 loses bytes (its input buffer overflows)."""
    flood = garbage(20_000, seed=5) + _bad_frames()
    with (
        running_emulator(tmp_path, 3) as emu,
        opened(emu.open(1), emu.open(2)) as (l1, l2),
        opened(open_link(emu.paths[0] + "?write_timeout=60")) as (l0,),
    ):
        emu.wait_ready(0, 1, 2)
        done = threading.Event()
        errors: list[BaseException] = []

        def write_flood() -> None:
            try:
                l0.port.write(flood)  # type: ignore[attr-defined]
            except BaseException as exc:  # reported below
                errors.append(exc)
            finally:
                done.set()

        writer = threading.Thread(target=write_flood, daemon=True)
        writer.start()
        delivered = 0
        try:
            k = 0
            while not done.is_set() or k < 2:
                raw = tunnel(2, b"still here", seq=k)
                l1.send(raw)
                assert recv_until(l2, is_raw(raw)) is not None, (
                    f"radio2 missed frame {k} from radio1 during the flood"
                )
                assert emu.alive
                delivered += 1
                k += 1
        finally:
            writer.join(timeout=60)
        assert not writer.is_alive() and errors == []
        assert delivered >= 3
        # and a heartbeat after the flood still gets through
        l1.send(heartbeat(2))
        assert recv_until(l2, lambda f: f.sysid == 2 and f.msgid == 0) is not None
        assert emu.alive
        assert l2.stats.bytes_skipped > 0  # radio2 did hear radio0's garbage, skipped it
        # the last bytes written may still sit in the pty: wait until radio0 has them all
        wait_until(
            lambda: emu.radio(0)["serial_in"] == len(flood), "the whole flood to reach radio0", AIR_DEADLINE
        )
        r = [emu.radio(i) for i in range(3)]
        assert r[0]["srx"] > 0, "radio0's host wrote faster than the air carries: it must lose bytes"
        assert r[1]["srx"] == r[2]["srx"] == 0


# -- capture and statistics -------------------------------------------------------------------


def test_capture_holds_every_frame_sent_and_pymavlink_reads_it(tmp_path: Path, mav20: Any) -> None:
    tlog = tmp_path / "air.tlog"
    b0, b1 = FrameBuilder(1), FrameBuilder(2)
    sent: list[bytes] = []
    t_start = time.time()
    with (
        running_emulator(tmp_path, 2, capture=str(tlog)) as emu,
        opened(emu.open(0), emu.open(1)) as (l0, l1),
    ):
        emu.wait_ready(0, 1)
        for k in range(4):
            for src, dst, b in ((l0, l1, b0), (l1, l0, b1)):
                raw = b.tunnel(f"frame {k}".encode()) if k % 2 else b.heartbeat()
                src.send(raw)
                sent.append(raw)
                assert recv_until(dst, is_raw(raw)) is not None
        wait_until(lambda: emu.emu.frames_captured >= len(sent), "the capture", AIR_DEADLINE)
        st = emu.emu.stats()
        assert st["frames_captured"] == len(sent)
    t_end = time.time()

    assert [rec.raw for rec in read_tlog(tlog)] == sent
    log = mavutil.mavlink_connection(str(tlog))
    try:
        msgs = []
        while (m := log.recv_match()) is not None:
            msgs.append(m)
    finally:
        log.close()
    assert [bytes(m.get_msgbuf()) for m in msgs] == sent
    assert [(m.get_srcSystem(), m.get_type()) for m in msgs[:4]] == [
        (1, "HEARTBEAT"),
        (2, "HEARTBEAT"),
        (1, "TUNNEL"),
        (2, "TUNNEL"),
    ]
    assert all(t_start - 1 <= m._timestamp <= t_end + 1 for m in msgs)  # noqa: SLF001 (pymavlink's receive time)


def test_stats_report_round_and_utilisation(tmp_path: Path) -> None:
    with running_emulator(tmp_path, 2) as emu, opened(emu.open(0), emu.open(1)) as (l0, l1):
        emu.wait_ready(0, 1)
        sent = [tunnel(1, bytes(100) + b"x", seq=k) for k in range(5)]
        for raw in sent:
            l0.send(raw)
        for raw in sent:
            assert recv_until(l1, is_raw(raw)) is not None
        st = emu.emu.stats()
        assert st["nodes"] == 2 and st["firmware"] == "standard"
        assert 0.0 < st["round_s"] < 2.0
        assert 0.0 < st["utilisation"] <= 1.0
        assert st["radios"][0]["tx_bytes"] == sum(map(len, sent))
        assert json.loads(json.dumps(st)) == st  # JSON-ready for --stats-json


# -- the real process --------------------------------------------------------------------------


def swarm(*args: str, **kw: Any) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "swarm.cli", *args],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        **kw,
    )


def read_lines(proc: subprocess.Popen[str], n: int, timeout: float) -> list[str]:
    """The first ``n`` lines of ``proc``'s stdout, waiting at most ``timeout`` s."""
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    buf = b""
    deadline = time.monotonic() + timeout
    while buf.count(b"\n") < n:
        left = deadline - time.monotonic()
        if left <= 0 or (proc.poll() is not None and not select.select([fd], [], [], 0)[0]):
            raise AssertionError(f"got {buf!r} of {n} readiness lines (exit {proc.poll()})")
        if select.select([fd], [], [], min(left, 0.5))[0]:
            chunk = os.read(fd, 4096)
            if not chunk:
                raise AssertionError(f"stdout closed after {buf!r}")
            buf += chunk
    return buf.decode().splitlines()[:n]


def stop(proc: subprocess.Popen[str], sig: int) -> tuple[int, str]:
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=15)
    return proc.returncode, err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_radio_emu_process_runs_until_a_signal(tmp_path: Path, sig: int) -> None:
    proc = swarm("radio-emu", "--nodes", "2", "--dir", str(tmp_path), "--seed", str(FAST_LOCK_SEED))
    try:
        lines = read_lines(proc, 2, timeout=30)
        links = [tmp_path / f"radio{i}" for i in range(2)]
        for i, line in enumerate(lines):
            assert line.startswith(f"radio{i} {links[i]} -> /dev/pts/"), line
        assert os.path.realpath(links[0]).startswith("/dev/pts/")
        with opened(open_link(str(links[0])), open_link(str(links[1]))) as (l0, l1):
            # the radios need to find each other: keep sending until one gets through
            deadline = time.monotonic() + 60
            got = None
            while got is None and time.monotonic() < deadline:
                l0.send(heartbeat(1))
                got = recv_until(l1, lambda f: f.sysid == 1 and f.msgid == 0, 1.0)
            assert got is not None, "no heartbeat crossed the emulated air in 60 s"
        code, err = stop(proc, sig)
        assert code == (130 if sig == signal.SIGINT else 0), err  # Ctrl-C: 130, an orderly stop: 0
        assert "Traceback" not in err
        assert "stopped after" in err
        assert not any(os.path.lexists(link) for link in links)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def test_radio_emu_bad_input_exits_2_with_a_message(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    d = str(tmp_path / "empty")
    cases = {  # name -> (arguments, what the message must mention)
        "missing --dir": (["--nodes", "2"], "--dir"),
        "missing directory": (["--nodes", "2", "--dir", str(tmp_path / "nope")], "nope"),
        "capture into a missing directory": (
            ["--nodes", "2", "--dir", d, "--capture", str(tmp_path / "nope" / "c.tlog")],
            "nope",
        ),
        "capture onto a directory": (["--nodes", "2", "--dir", d, "--capture", str(tmp_path)], "--capture"),
        "3 netids for 2 radios": (["--nodes", "2", "--dir", d, "--netid", "1", "2", "3"], "--netid"),
        "unknown parameter": (["--nodes", "2", "--dir", d, "--param", "NOPE=1"], "NOPE"),
        "value out of range": (["--nodes", "2", "--dir", d, "--param", "AIR_SPEED=999"], "AIR_SPEED"),
    }
    procs = {name: swarm("radio-emu", *args) for name, (args, _) in cases.items()}
    try:
        for name, proc in procs.items():
            out, err = proc.communicate(timeout=60)
            assert proc.returncode == 2, f"{name}: exit {proc.returncode}\n{err}"
            assert "error" in err.lower() and cases[name][1] in err, f"{name}: {err!r}"
            assert "Traceback" not in err, f"{name}: {err}"
            assert out == "", f"{name}: printed {out!r}"
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
    assert os.listdir(d) == []  # no links left behind


# -- radio-config against the emulator ----------------------------------------------------------


def radio_config(*args: str) -> dict[str, int]:
    r = subprocess.run(
        [sys.executable, "-m", "swarm.cli", "radio-config", *args, "--json"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=90,
    )
    assert r.returncode == 0, r.stderr
    values: dict[str, int] = json.loads(r.stdout)
    return values


def test_radio_config_reads_and_writes_the_emulated_radio(tmp_path: Path) -> None:
    with running_emulator(tmp_path, 2) as emu:
        emu.wait_locked(0, 1)
        shown = radio_config(emu.paths[0], "--show")
        assert shown["NETID"] == 25
        assert shown["AIR_SPEED"] == 64 and shown["SERIAL_SPEED"] == 57
        assert {"ECC", "MAVLINK", "TXPOWER", "MAX_WINDOW"} <= set(shown)

        after = radio_config(emu.paths[0], "--set", "NETID=30")
        assert after["NETID"] == 30
        assert {k: v for k, v in after.items() if k != "NETID"} == {
            k: v for k, v in shown.items() if k != "NETID"
        }
        assert emu.emu.radio_config(0).netid == 30  # saved and rebooted into it

        with opened(emu.open(0), emu.open(1)) as (l0, l1):
            emu.wait_connected(0, 1)
            tx0, rx1 = emu.radio(0)["tx_bytes"], emu.radio(1)["rx_bytes"]
            seen: list[Frame] = []
            for k in range(4):
                l0.send(tunnel(1, b"on 30 now", seq=k))
                recv_until(l1, lambda f: False, 0.4, seen)
            assert seen == []
            assert emu.radio(0)["tx_bytes"] > tx0  # radio0 did transmit them
            assert emu.radio(1)["rx_bytes"] == rx1  # radio1 (NETID 25) heard none
