"""Flight logs on the aircraft (:mod:`radios.rotating`, ``swarm agent --capture``,
``swarm replay DIR``): names, rotation by size and age, the budget, hostile folders,
a torn last record at every byte offset, a full disk (a real EFBIG from the kernel),
and a real agent writing its radio traffic and its flight controller's messages.

The writer thread runs on real time (it wakes every 50 ms); records are stamped by an
injected clock, so rotation by age is driven by the test. Waits poll for outcomes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import pytest
from net_helpers import ManualClock, free_port, free_port_range, wait_until

from radios.capture import CaptureLink
from radios.errors import CaptureDamagedError, ConfigError
from radios.link import open_link
from radios.mavlink import MSG_RADIO_STATUS, FrameBuilder, decode, pack_frame
from radios.rotating import FlightLog, RotationPolicy
from radios.tlog import read_tlog
from radios.tlogset import flight_log_files, read_flight_log
from swarm.cli.commands.agent import main as agent_main
from swarm.cli.commands.replay import main as replay_main

T0 = 1_795_000_000.0  # 2026-11-18T11:06:40Z
STAMP0 = "20261118T110640Z"
SMALL = RotationPolicy(max_bytes=4096, rotate_s=600.0, budget_bytes=5 * 4096)


def frames(n: int, sysid: int = 3) -> list[bytes]:
    b = FrameBuilder(sysid, 191)
    out = []
    for i in range(n):
        if i % 5 == 4:
            out.append(pack_frame(MSG_RADIO_STATUS, bytes(range(9)), sysid=51, compid=68, seq=i, version=1))
        else:
            out.append(b.tunnel(bytes([i % 251]) * (i % 40)))
    return out


def put_all(log: FlightLog, raws: list[bytes], source: str = "radio", dt: float = 0.01) -> None:
    for i, raw in enumerate(raws):
        log.put(source, raw, T0 + dt * i)


def names(d: Path) -> list[str]:
    return sorted(os.listdir(d))


# -- names, sources, rotation -------------------------------------------------------------


def test_names_sort_by_time_say_who_and_keep_sources_apart(tmp_path: Path) -> None:
    clock = ManualClock(T0)
    radio, fc = frames(20), frames(7, sysid=1)
    with FlightLog(str(tmp_path / "logs"), "agent3", clock=clock) as log:
        put_all(log, radio)
        put_all(log, fc, "fc")
    assert names(tmp_path / "logs") == [f"agent3-{STAMP0}-0001.fc.tlog", f"agent3-{STAMP0}-0001.tlog"]
    got = list(read_flight_log(str(tmp_path / "logs")))
    assert [r.raw for r in got] == radio and [r.t for r in got] == [T0 + 0.01 * i for i in range(20)]
    assert [r.raw for r in read_flight_log(str(tmp_path / "logs"), source="fc")] == fc
    assert log.stats.records == 27 and log.stats.dropped == 0 and log.stats.syncs >= 1


def test_rotation_by_size_never_splits_a_record_and_reads_as_one(tmp_path: Path) -> None:
    raws = frames(400)
    with FlightLog(str(tmp_path), "a1", SMALL, clock=ManualClock(T0)) as log:
        put_all(log, raws)
    files = flight_log_files(str(tmp_path))
    assert len(files) >= 4
    assert all(os.path.getsize(f) <= 4096 for f in files)
    assert [os.path.basename(f) for f in files] == sorted(os.path.basename(f) for f in files)
    seen = [r.raw for f in files for r in read_tlog(f)]  # every file whole on its own
    assert seen == raws[-len(seen) :]  # the budget may have removed the oldest
    assert [r.raw for r in read_flight_log(str(tmp_path))] == seen


def test_rotation_by_age_from_the_clock(tmp_path: Path) -> None:
    clock = ManualClock(T0)
    with FlightLog(str(tmp_path), "a1", RotationPolicy(rotate_s=60.0), clock=clock) as log:
        log.put("radio", frames(1)[0])
        wait_until(lambda: log.stats.records == 1, "the first record written", 10)
        clock.advance(61)
        log.put("radio", frames(2)[1])
        wait_until(lambda: log.stats.records == 2, "the second record written", 10)
    assert names(tmp_path) == [f"a1-{STAMP0}-0001.tlog", "a1-20261118T110741Z-0002.tlog"]


def test_a_clock_that_jumps_starts_a_new_file_each_readable_alone(tmp_path: Path) -> None:
    raws = frames(6)
    stamps = [T0, T0 + 1, T0 + 3 * 86400, T0 + 3 * 86400 + 1, T0 - 86400, T0 - 86399]  # GPS time, then back
    clock = ManualClock(T0)
    with FlightLog(str(tmp_path), "a1", clock=clock) as log:
        for raw, t in zip(raws, stamps, strict=True):
            clock.now = t
            log.put("radio", raw, t)
    files = flight_log_files(str(tmp_path))
    assert len(files) == 3
    got = sorted([r.t for r in read_tlog(f)] for f in files)  # names sort by a clock that jumped
    assert got == sorted([stamps[0:2], stamps[2:4], stamps[4:6]])


def test_budget_removes_the_oldest_only_ours_never_open_nor_through_links(tmp_path: Path) -> None:
    d = tmp_path / "logs"
    d.mkdir()
    other = d / f"agent9-{STAMP0}-0001.tlog"
    other.write_bytes(b"x" * 50_000)  # another agent's: not ours to remove
    outside = tmp_path / "precious"
    outside.write_bytes(b"y" * 50_000)
    (d / "a1-20000101T000000Z-0001.tlog").symlink_to(outside)  # a link named like ours
    for k in range(6):  # an earlier flight of ours: 6 files of 4000 bytes
        (d / f"a1-20250101T00000{k}Z-0001.tlog").write_bytes(b"z" * 4000)
    with FlightLog(str(d), "a1", SMALL, clock=ManualClock(T0)) as log:
        put_all(log, frames(1000))  # about 35 kB: more than the budget
        wait_until(lambda: log.stats.records == 1000, "records written", 10)
        current = log.current
    ours = [n for n in names(d) if n.startswith("a1-") and not (d / n).is_symlink()]
    assert sum((d / n).stat().st_size for n in ours) <= SMALL.budget_bytes
    assert not any(n.startswith("a1-2025") for n in ours)  # the oldest went first
    assert set(current) <= set(ours)
    assert other.stat().st_size == 50_000 and outside.read_bytes() == b"y" * 50_000
    assert log.stats.removed >= 6


def test_a_link_planted_at_the_next_name_is_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_bytes(b"keep")
    d = tmp_path / "logs"
    d.mkdir()
    (d / f"a1-{STAMP0}-0001.tlog").symlink_to(victim)
    with FlightLog(str(d), "a1", clock=ManualClock(T0)) as log:
        put_all(log, frames(5))
    assert victim.read_bytes() == b"keep"
    assert [r.raw for r in read_tlog(d / f"a1-{STAMP0}-0002.tlog")] == frames(5)


def test_hostile_folders_and_values_are_refused_with_one_line(tmp_path: Path) -> None:
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    (tmp_path / "file").write_bytes(b"")
    for path, reason in (
        (tmp_path / "link", "is a symbolic link"),
        (tmp_path / "file", "is not a folder"),
        (tmp_path / "file" / "sub", "cannot create flight log folder"),
    ):
        with pytest.raises(ConfigError, match=reason):
            FlightLog(str(path), "a1")
    with pytest.raises(ConfigError, match="prefix"):
        FlightLog(str(tmp_path / "real"), "../x")
    with pytest.raises(ConfigError, match="smaller than one file"):
        RotationPolicy(max_bytes=1 << 20, budget_bytes=1 << 19)
    with pytest.raises(ConfigError, match="positive"):
        RotationPolicy(rotate_s=float("nan"))
    with FlightLog(str(tmp_path / "new" / "deep"), "a1") as log:  # created when missing
        pass
    assert log.directory == str(tmp_path / "new" / "deep")


def test_put_never_raises_and_counts_what_it_drops(tmp_path: Path) -> None:
    log = FlightLog(str(tmp_path), "a1", RotationPolicy(max_queue=10), clock=ManualClock(T0))
    log.put("radio", b"\xfd\x01garbage")  # not one frame
    log.put("nosuch", frames(1)[0])
    log.put("radio", frames(1)[0], float("nan"))
    assert log.stats.dropped == 3
    log.close()
    log.put("radio", frames(1)[0])  # after close
    assert log.stats.dropped == 4 and log.stats.records == 0
    log.close()  # twice


def test_capture_link_writes_both_directions_to_the_sink(tmp_path: Path) -> None:
    a, b = open_link("virtual://fl-both"), open_link("virtual://fl-both")
    with FlightLog(str(tmp_path), "a1") as log:
        link = CaptureLink(a, log.sink("radio"))
        out, back = frames(3), frames(2, sysid=7)
        for raw in out:
            link.send(raw)
        for raw in back:
            b.send(raw)
        got = [wait_until(lambda: link.recv(0.1), "a frame back", 10) for _ in back]
        assert [f.raw for f in got] == back
        link.close()
        b.close()
    assert sorted(r.raw for r in read_flight_log(str(tmp_path))) == sorted(out + back)


# -- reading: a torn last record ---------------------------------------------------------


def _two_file_set(d: Path) -> tuple[list[str], list[bytes]]:
    raws = frames(150)
    with FlightLog(str(d), "a1", RotationPolicy(max_bytes=4096), clock=ManualClock(T0)) as log:
        put_all(log, raws)
    return flight_log_files(str(d)), raws


def test_a_torn_last_record_is_skipped_at_every_byte_offset(tmp_path: Path) -> None:
    files, raws = _two_file_set(tmp_path)
    first = files[0]
    whole = Path(first).read_bytes()
    records = list(read_tlog(first))
    last = records[-1]
    for cut in range(last.offset + 1, len(whole)):
        Path(first).write_bytes(whole[:cut])
        reader = read_flight_log(str(tmp_path))
        got = [r.raw for r in reader]
        assert got == raws[: len(records) - 1] + raws[len(records) :], cut
        assert reader.torn == [(first, last.offset)], cut
    Path(first).write_bytes(whole[: last.offset + 20])
    assert replay_main([str(tmp_path), "--stats", "--json"]) == 0


def test_damage_that_is_not_a_torn_tail_still_ends_the_reading(tmp_path: Path) -> None:
    files, _raws = _two_file_set(tmp_path)
    data = bytearray(Path(files[0]).read_bytes())
    data[30] ^= 0xFF  # inside the first frame: a bad CRC, not a power cut
    Path(files[0]).write_bytes(bytes(data))
    with pytest.raises(CaptureDamagedError):
        list(read_flight_log(str(tmp_path)))


def test_a_fifo_or_folder_named_like_a_log_is_not_read(tmp_path: Path) -> None:
    with FlightLog(str(tmp_path), "a1", clock=ManualClock(T0)) as log:
        put_all(log, frames(3))
    os.mkfifo(tmp_path / "a1-20990101T000000Z-0001.tlog")  # opening it would block for ever
    (tmp_path / "a1-20990101T000000Z-0002.tlog").mkdir()
    assert [r.raw for r in read_flight_log(str(tmp_path))] == frames(3)


def test_replay_reads_a_folder_its_sources_and_agents(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    radio, fc = frames(12), frames(4, sysid=1)
    with FlightLog(str(tmp_path), "agent3", clock=ManualClock(T0)) as log:
        put_all(log, radio)
        put_all(log, fc, "fc")
    assert replay_main([str(tmp_path), "--json"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(lines) == 12 and lines[0]["msg"] == "TUNNEL" and lines[4]["msg"] == "RADIO_STATUS"
    assert replay_main([str(tmp_path), "--fc", "--stats", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 4
    with FlightLog(str(tmp_path), "agent4", clock=ManualClock(T0)) as log:
        put_all(log, frames(2))
    for argv, reason in (
        ([str(tmp_path)], "holds the flight logs of agent3, agent4: choose one"),
        ([str(tmp_path), "--agent", "agent5"], "no radio flight log of agent5"),
        ([str(tmp_path), "--plot", str(tmp_path / "x.png")], "--plot reads one capture file"),
        ([str(tmp_path / f"agent3-{STAMP0}-0001.tlog"), "--fc"], "give the folder"),
    ):
        assert replay_main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and reason in err[0], err
    assert replay_main([str(tmp_path), "--agent", "agent4", "--stats", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 2


# -- the agent's flags ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("extra", "reason"),
    [
        (["--capture-max-mb", "4"], "--capture-max-mb need --capture"),
        (["--capture", "{d}/log", "--capture-max-mb", "0"], "--capture-max-mb 0: must be a positive"),
        (["--capture", "{d}/log", "--capture-budget-mb", "1"], "smaller than one file"),
        (["--capture", "{d}/link"], "is a symbolic link"),
        (["--capture", "{d}/file"], "is not a folder"),
    ],
)
def test_agent_refuses_bad_capture_flags_and_folders_with_exit_2(
    tmp_path: Path, extra: list[str], reason: str, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    (tmp_path / "file").write_bytes(b"")
    argv = ["--name", "a1", "--id", "1", "--zenoh-listen", "tcp/127.0.0.1:1"]
    assert agent_main(argv + [x.format(d=tmp_path) for x in extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and reason in err[0], err


# -- processes: a real full disk, a folder without permission, a real agent ------------------

EFBIG_SCRIPT = textwrap.dedent(
    """
    import resource, signal, sys, time
    from radios.mavlink import FrameBuilder
    from radios.rotating import FlightLog, RotationPolicy
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, (6000, 6000))  # the kernel refuses bigger files
    said = []
    log = FlightLog(sys.argv[1], "a1", RotationPolicy(max_bytes=1 << 20, retry_s=0.3), on_error=said.append)
    b = FrameBuilder(1, 191)
    deadline = time.monotonic() + 30
    while len(said) < 3 and time.monotonic() < deadline:
        log.put("radio", b.tunnel(bytes(100)))  # never raises
        time.sleep(0.002)
    log.close()
    print("\\n".join(said))
    print(log.stats.records, log.stats.lost, log.stats.errors)
    """
)


@pytest.mark.processes
def test_a_full_disk_pauses_with_one_line_and_resumes(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-c", EFBIG_SCRIPT, str(tmp_path)], capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 0, run.stderr
    said = run.stdout.splitlines()
    assert said[0].startswith("flight log paused: cannot write in ") and "File too large" in said[0]
    assert said[1].startswith("flight log resumed after ") and "records lost so far" in said[1]
    assert said[2].startswith("flight log paused")  # and so on: one line per pause and resume
    records, lost, errors = map(int, said[3].split())
    assert records > 0 and lost > 0 and errors >= 2
    assert len(flight_log_files(str(tmp_path))) >= 2
    assert list(read_flight_log(str(tmp_path)))  # what was written reads (tails torn at most)


# the interpreter lives where nobody may not read: import first, then become nobody
AS_NOBODY = textwrap.dedent(
    """
    import json, os, sys
    import radios.rotating
    from swarm.cli.commands.agent import main
    os.setgid(65534)
    os.setuid(65534)  # nobody: root could write anywhere
    sys.exit(main(json.loads(sys.argv[1])))
    """
)


@pytest.mark.processes
def test_a_folder_without_permission_is_exit_2_for_another_user() -> None:
    base = tempfile.mkdtemp(prefix="fl-perm-", dir="/tmp")
    try:
        os.chmod(base, 0o755)
        ro = os.path.join(base, "ro")
        os.mkdir(ro, 0o555)
        argv = [
            "--name",
            "a1",
            "--id",
            "1",
            "--zenoh-listen",
            f"tcp/127.0.0.1:{free_port()}",
            "--capture",
            ro,
        ]
        run = subprocess.run(
            [sys.executable, "-c", AS_NOBODY, json.dumps(argv)],
            capture_output=True,
            text=True,
            timeout=60,
            cwd="/",
        )
        assert run.returncode == 2, run.stderr
        err = run.stderr.strip().splitlines()
        assert err == [f"swarm agent: error: flight log folder {ro}: permission denied"], err
    finally:
        os.chmod(os.path.join(base, "ro"), 0o755)
        for root, dirs, files in os.walk(base, topdown=False):
            for n in files:
                os.unlink(os.path.join(root, n))
            for n in dirs:
                os.rmdir(os.path.join(root, n))
        os.rmdir(base)


# the agent's command in a process of its own, stopped (SIGTERM) once its flight log holds
# what the test looks for (however long a loaded machine took to get there); then the
# modules it loaded that it must not need
AGENT_RUN = textwrap.dedent(
    """
    import json, os, signal, sys, threading, time
    from swarm.cli import main
    from radios.tlogset import read_flight_log
    folder = sys.argv[2]
    FC_WANTED = {"HEARTBEAT", "GLOBAL_POSITION_INT", "SYS_STATUS"}

    def logged():
        try:
            fc = {r.frame.name for r in read_flight_log(folder, source="fc")}
            radio = {(r.frame.name, r.frame.sysid, r.frame.compid) for r in read_flight_log(folder)}
        except Exception:  # not there yet, or a record half written
            return False
        names = {n for n, _, _ in radio}
        return (
            FC_WANTED <= fc
            and ("RADIO_STATUS", 51, 68) in radio
            and ("HEARTBEAT", 1, 191) in radio
            and "TUNNEL" in names
        )

    def stop_when_logged():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not logged():
            time.sleep(0.2)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=stop_when_logged, daemon=True).start()
    code = main(json.loads(sys.argv[1]))
    loaded = {m.split(".")[0] for m in sys.modules}
    print(json.dumps({"code": code, "heavy": sorted(loaded & {"matplotlib", "aiohttp", "PIL"})}))
    """
)


FC_KEPT = {
    "HEARTBEAT",
    "SYS_STATUS",
    "GPS_RAW_INT",
    "GLOBAL_POSITION_INT",
    "COMMAND_ACK",
    "BATTERY_STATUS",
    "HOME_POSITION",
    "EXTENDED_SYS_STATE",
    "STATUSTEXT",
}


@pytest.mark.processes
def test_a_real_agent_logs_its_radio_both_ways_and_its_flight_controller(tmp_path: Path) -> None:
    from swarm.cli.procs import Child, start_emulator
    from swarm.core.wire.tunnel import PAYLOAD_TYPE_BASE, Kind

    emu, links = start_emulator(2, tmp_path)
    port = free_port_range(1, "udp")
    sim = Child(["sim", "--vehicles", "1", "--base-port", str(port)], name="vehicle")
    logs = tmp_path / "logs"
    try:
        sim.wait_lines(2, 60)
        argv = [
            "agent",
            "--name",
            "agent1",
            "--id",
            "1",
            "--radio",
            links[0],
            "--fc",
            f"udpin:127.0.0.1:{port}",
        ]
        run = subprocess.run(
            [sys.executable, "-c", AGENT_RUN, json.dumps([*argv, "--capture", str(logs)]), str(logs)],
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        sim.stop()
        emu.stop()
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout.splitlines()[-1]) == {"code": 0, "heavy": []}
    radio = [r.frame for r in read_flight_log(str(logs))]
    sent_advertize = [
        f
        for f in radio
        if f.sysid == 1
        and f.compid == 191
        and f.name == "TUNNEL"
        and decode(f).payload_type == PAYLOAD_TYPE_BASE + Kind.ADVERTIZE
    ]
    assert sent_advertize, "the agent's own Advertize, as sent"
    assert any(f.name == "RADIO_STATUS" and f.sysid == 51 for f in radio), "the radio's reports, as received"
    assert any(f.name == "HEARTBEAT" and f.compid == 191 for f in radio), (
        "the bridge's HEARTBEAT to its radio"
    )
    fc = {f.name for f in (r.frame for r in read_flight_log(str(logs), source="fc"))}
    assert {"HEARTBEAT", "GLOBAL_POSITION_INT", "SYS_STATUS"} <= fc, fc
    assert fc <= FC_KEPT, fc


@pytest.mark.processes
def test_a_full_disk_never_stops_a_real_agent(tmp_path: Path) -> None:
    import resource

    from swarm.cli.procs import Child, json_events

    def paused() -> list[dict[str, str]]:
        return [
            e for e in json_events(agent.lines, "flight-log") if e["text"].startswith("flight log paused")
        ]

    port = free_port_range(1, "udp")
    sim = Child(["sim", "--vehicles", "1", "--base-port", str(port)], name="vehicle")
    argv = ["agent", "--name", "a1", "--id", "1", "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"]
    argv += ["--fc", f"udpin:127.0.0.1:{port}", "--json", "--capture", str(tmp_path / "logs")]
    try:
        sim.wait_lines(2, 60)
        agent = Child(argv, name="agent")
        agent.wait_lines(1, 60)  # ready: its Zenoh session has made its shared-memory file
        # the kernel now refuses its files past 1000 bytes (EFBIG), as a full card would;
        # Python ignores SIGXFSZ, so the write fails instead of killing it
        resource.prlimit(agent.pid, resource.RLIMIT_FSIZE, (1000, 1000))
        try:
            wait_until(paused, "the flight log to pause", 60, children=[agent])
            seen = len(agent.lines)
            wait_until(lambda: len(agent.lines) > seen, "the agent going on", 60, children=[agent])
            assert agent.proc.poll() is None
        finally:
            code = agent.stop()
    finally:
        sim.stop()
    assert code == 0 and agent.errors == [], agent.errors
    assert "File too large" in paused()[0]["text"]
    # one line when it pauses and one when a new file takes records again (each new
    # file here fills its 1000 bytes too): never a line per failed write
    said = [e["text"].split(" ")[2] for e in json_events(agent.lines, "flight-log")]
    assert said == ["paused:", "resumed"] * (len(said) // 2) + ["paused:"] * (len(said) % 2), said
