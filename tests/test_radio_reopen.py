"""A radio unplugged and plugged back (issue 11, item 8).

To the host an unplugged USB radio is a device node that disappears while reads
and writes fail; plugged back, a new node appears at the same path. The emulator
does exactly that to one radio (its control FIFO ``DIR/control`` or
:meth:`Emulator.unplug`), while the radio keeps its place on the air. Covered: the
emulator's unplug and replug; :meth:`SerialLink.reopen`; the bridge waiting for the
device, logging about once a second, reopening it and carrying traffic again with
its name table kept; and real ``swarm agent`` and ``swarm gcs`` processes that stay
up and return to the swarm, or with ``--exit-on-radio-loss`` exit 1 with one line.

Nothing sleeps to hope: waits poll for an outcome until a generous deadline; the
outage itself is a span of time the test chooses.
"""

from __future__ import annotations

import json
import logging
import os
import select
import signal
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from emu_helpers import AIR_DEADLINE, heartbeat, raw_pty, recv_until, running_emulator, tunnel
from net_helpers import free_port, wait_until

from radios.errors import LinkClosedError, LinkOpenError
from radios.link import open_link
from swarm.cli.procs import Child, json_events, start_emulator
from swarm.core.wire.message_types import Advertize, Selection
from swarm.core.wire.messages import encode
from swarm.runtime.bridge.radio_bridge import RadioBridge
from swarm.runtime.keyspace.transport import Transport, open_session

pytestmark = pytest.mark.processes  # radios unplugged and replugged under running processes

DEADLINE = 60.0  # a failing wait only; radios lock in seconds, elections take a few windows
OUTAGE_S = 3.0


def control(directory: Path, line: str) -> None:
    """Write one line to the emulator's control FIFO."""
    fd = os.open(directory / "control", os.O_WRONLY | os.O_NONBLOCK)
    try:
        os.write(fd, (line + "\n").encode())
    finally:
        os.close(fd)


# -- the emulator and the link ----------------------------------------------------------


def test_emulator_unplugs_and_replugs_a_radio_that_keeps_its_place(tmp_path: Path) -> None:
    events: list[str] = []
    with running_emulator(tmp_path, 2) as run, ExitStack() as stack:
        run.emu.on_event = events.append
        a = stack.enter_context(run.open(0))
        b = run.open(1)
        stack.callback(b.close)
        run.wait_ready(0, 1)
        b.send(tunnel(2, b"before"))
        assert recv_until(a, lambda f: f.sysid == 2) is not None
        run.emu.unplug(1)
        path = Path(run.paths[1])
        wait_until(lambda: not path.exists(), "radio1's device node to disappear", AIR_DEADLINE)
        with pytest.raises(LinkClosedError):  # reads fail, as on a pulled USB radio
            wait_until(lambda: b.recv(0.1) and False, "a failing read", AIR_DEADLINE)
        with pytest.raises(LinkOpenError, match="no such device"):
            b.reopen()
        assert run.radio(1)["locked"] and not run.radio(1)["plugged"]
        run.emu.replug(1)
        wait_until(path.exists, "radio1's device node back", AIR_DEADLINE)
        b.reopen()
        run.wait_connected(1)
        assert run.radio(1)["locked"], "a radio powered on its own keeps its lock"
        b.send(heartbeat(2))
        assert recv_until(a, lambda f: f.sysid == 2 and f.msgid == 0) is not None
        a.send(tunnel(1, b"after"))
        assert recv_until(b, lambda f: f.sysid == 1 and f.payload[5:10] == b"after") is not None
        # the control FIFO: an unplug for a while, and a bad line that changes nothing
        control(tmp_path, "unplug 0 1.5")
        control(tmp_path, "unplug seven")
        # (the node is gone for only 1.5 s: the event lines, not a poll, show the unplug)
        wait_until(lambda: len(events) >= 5, "an event line for each", AIR_DEADLINE)
        wait_until(lambda: Path(run.paths[0]).exists(), "radio0 back by itself", AIR_DEADLINE)
    assert events[0] == "radio1 unplugged" and events[1].startswith("radio1 plugged back: ")
    assert sorted(events[2:4]) == [
        "control: 'unplug seven': expected unplug I [FOR_S] | replug I | loss P",
        "radio0 unplugged for 1.5 s",
    ], events
    assert events[4].startswith("radio0 plugged back: ")
    assert not (tmp_path / "control").exists() and os.listdir(tmp_path) == []


class _Node:
    def __init__(self, bridge: RadioBridge, transport: Transport, inbox: list[Any]) -> None:
        self.bridge, self.t, self.inbox = bridge, transport, inbox


def _two_bridged_nodes(
    run: Any, stack: ExitStack, link_options: Callable[[str], dict[str, Any]] = lambda _name: {}
) -> tuple[_Node, _Node]:
    """Two radio bridges ("a1", "a2") on the emulator's radios 0 and 1, each with its own
    Zenoh session and transport, that have learnt each other's names."""
    nodes = []
    for i, name in enumerate(("a1", "a2")):
        session = open_session()
        stack.callback(session.close)
        link = run.open(i, **link_options(name))
        stack.callback(link.close)
        bridge = RadioBridge(session, link, name=name, agent_id=i + 1).start()
        stack.callback(bridge.close)
        t = Transport(name, session)
        stack.callback(t.close)
        inbox: list[Any] = []
        t.on_inbox(inbox.append)
        nodes.append(_Node(bridge, t, inbox))
    n1, n2 = nodes

    def learnt() -> bool:
        n1.t.advertise(Advertize(1, "a1"))
        n2.t.advertise(Advertize(2, "a2"))
        return "a2" in n1.bridge.peers() and "a1" in n2.bridge.peers()

    wait_until(learnt, "both bridges to learn the other's name", DEADLINE, 0.5)
    return n1, n2


def test_bridge_lends_its_radio_for_an_at_check_and_takes_it_back(tmp_path: Path) -> None:
    """An agent in flight checks its radio's registers (AT commands need the port to
    themselves) without stopping: the bridge lends the port and takes it back."""
    from radios.sik.guard import check_radio

    heard: list[tuple[str, str]] = []
    with running_emulator(tmp_path, 2) as run, ExitStack() as stack:
        n1, n2 = _two_bridged_nodes(run, stack)
        b2, t1, in2 = n2.bridge, n1.t, n2.inbox
        b2.add_listener(lambda what, text: heard.append((what, text)))
        report = b2.lend_radio(lambda: check_radio(run.paths[1], {"NETID": 25}), why="radio check")
        assert report.ok and report.values["NETID"] == 25
        wait_until(lambda: b2.stats.radio_reopens == 1, "a2's radio taken back", AIR_DEADLINE)
        assert not b2.link_lost and heard[0] == ("paused", "radio check") and heard[1][0] == "back"
        wait_until(
            lambda: (t1.send("a2", Selection(1, 2, 9, 3)), any(m == Selection(1, 2, 9, 3) for m in in2))[1],
            "a1 -> a2 after the check",
            AIR_DEADLINE,
            0.5,
        )
        assert "a1" in b2.peers()  # the name table survived
        b2.cfg.reopen_radio = False  # --exit-on-radio-loss: a lend is not a loss
        with pytest.raises(ValueError):  # what the borrower raises comes out; the radio comes back
            b2.lend_radio(lambda: (_ for _ in ()).throw(ValueError("boom")))
        wait_until(lambda: b2.stats.radio_reopens == 2, "a2's radio taken back again", AIR_DEADLINE)
        assert not b2.link_lost and b2.stats.radio_losses == 0


def test_emulator_loss_can_be_changed_while_running(tmp_path: Path) -> None:
    """``loss P`` on the control FIFO: a fault bench raises the loss of a running swarm."""
    events: list[str] = []
    with running_emulator(tmp_path, 2) as run, ExitStack() as stack:
        run.emu.on_event = events.append
        a = stack.enter_context(run.open(0))
        b = stack.enter_context(run.open(1))
        run.wait_ready(0, 1)
        control(tmp_path, "loss 1")
        wait_until(lambda: "loss 1" in events, "the loss change reported", AIR_DEADLINE)
        lost_before = run.radio(0).get("lost", 0)
        for k in range(5):
            b.send(tunnel(2, b"gone%d" % k))
        time.sleep(1.0)
        assert [f for f in drain_frames(a) if f.sysid == 2 and f.msgid == 385] == []
        control(tmp_path, "loss 0")
        control(tmp_path, "loss 1.5")  # refused: changes nothing
        wait_until(lambda: len(events) >= 3, "both lines answered", AIR_DEADLINE)
        b.send(tunnel(2, b"back"))
        assert recv_until(a, lambda f: f.sysid == 2 and f.payload[5:9] == b"back") is not None
        assert lost_before is not None
    assert events[1] == "loss 0" and events[2].startswith("control: 'loss 1.5': ")


def drain_frames(link: Any) -> list[Any]:
    out = []
    while (f := link.recv(0.2)) is not None:
        out.append(f)
    return out


def test_a_link_that_cannot_be_reopened_says_so(tmp_path: Path) -> None:
    with open_link("loop://") as loop:
        assert loop.can_reopen
    from radios.tlog import TlogWriter

    cap = tmp_path / "x.tlog"
    with TlogWriter(cap) as w:
        w.write(heartbeat(1), 1.0)
    with open_link(str(cap)) as replay:
        assert not replay.can_reopen
        with pytest.raises(LinkOpenError, match="cannot be reopened"):
            replay.reopen()
    link = open_link("loop://")
    link.close()
    with pytest.raises(LinkClosedError):
        link.reopen()


# -- the bridge -----------------------------------------------------------------------


def test_bridge_waits_for_the_radio_and_reopens_it(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="swarm.runtime.bridge.radio_bridge")
    heard: list[tuple[str, str]] = []
    with running_emulator(tmp_path, 2) as run, ExitStack() as stack:
        n1, n2 = _two_bridged_nodes(
            run, stack, link_options=lambda name: {"capture": str(tmp_path / f"{name}.tlog")}
        )
        t1, in1 = n1.t, n1.inbox
        b2, t2, in2 = n2.bridge, n2.t, n2.inbox
        b2.add_listener(lambda what, text: heard.append((what, text)))
        t0 = time.monotonic()
        run.emu.unplug(1, OUTAGE_S)
        # link_down holds only for the outage: wait for what stays (the loss counted)
        wait_until(lambda: b2.stats.radio_losses >= 1, "a2's bridge to notice its radio gone", AIR_DEADLINE)
        t1.send("a2", Selection(1, 2, 7, 3))  # goes on air into nowhere; nothing breaks
        wait_until(lambda: b2.stats.radio_reopens == 1, "a2's radio reopened", AIR_DEADLINE + OUTAGE_S)
        away = time.monotonic() - t0
        assert not b2.link_lost and b2.stats.radio_losses == 1
        wait_until(
            lambda: len(heard) >= 2, "the listener told of both", AIR_DEADLINE
        )  # it comes after the count
        assert heard[0][0] == "lost" and heard[1][0] == "back" and heard[1][1].startswith("after ")
        # traffic both ways again, and the name table survived (no new Advertize)
        t2.send("a1", Selection(2, 1, 8, 3))
        wait_until(lambda: any(m == Selection(2, 1, 8, 3) for m in in1), "a2 -> a1", AIR_DEADLINE)
        wait_until(
            lambda: (t1.send("a2", Selection(1, 2, 9, 3)), any(m == Selection(1, 2, 9, 3) for m in in2))[1],
            "a1 -> a2",
            AIR_DEADLINE,
            0.5,
        )
        wait_until(lambda: b2.stats.radio_status_accepted > 0, "RADIO_STATUS again", AIR_DEADLINE)
    lines = [
        r.getMessage()
        for r in caplog.records
        if r.name == "swarm.runtime.bridge.radio_bridge" and "a2" in r.getMessage()
    ]
    assert sum("lost" in x for x in lines) == 1 and sum("back after" in x for x in lines) == 1, lines
    waiting = [x for x in lines if "still away" in x]
    assert len(waiting) <= away + 1, f"about one line a second while waiting, not a flood: {lines}"
    # the capture went on in the same file across the reopen
    from radios.tlog import TlogReader

    with TlogReader(tmp_path / "a2.tlog") as reader:
        sent = [r.frame for r in reader if r.frame.sysid == 2]
    assert any(encode(Selection(2, 1, 8, 3)).rstrip(b"\0") in f.payload for f in sent), "sent after reopening"
    assert any(f.msgid == 0 for f in sent[:3]), "and what was sent before it"


# -- another device at the radio's path (issue 27) ---------------------------------------


def arriving(master: int, seconds: float) -> bytes:
    """What a program writes into the pty whose master is ``master`` over ``seconds``
    (an EIO while nobody holds the slave open is no byte: wait and read again)."""
    got = bytearray()
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        r, _, _ = select.select([master], [], [], min(left, 0.1))
        if not r:
            continue
        try:
            got += os.read(master, 4096)
        except OSError:
            time.sleep(min(0.05, max(0.0, end - time.monotonic())))
    return bytes(got)


def arriving_until(master: int, done: Callable[[], Any], what: str, timeout: float = DEADLINE) -> bytes:
    """What arrives on ``master`` until ``done()`` (failing after ``timeout`` s)."""
    got = bytearray()
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, f"timed out after {timeout} s waiting for {what}"
        got += arriving(master, 0.2)
    return bytes(got)


def point(path: Path, target: str) -> None:
    """Make ``path`` a symbolic link to ``target`` (what a reassigned device node is)."""
    if path.is_symlink() or path.exists():
        path.unlink()
    os.symlink(target, path)


def test_bridge_never_writes_to_another_device_at_its_radios_path(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """While a2's radio is unplugged its path is made to point at another device, first a
    fresh pty (a reassigned /dev/ttyUSB0, a reused /dev/pts/N), then another radio of the
    same emulator: the bridge opens neither for writing, says so once per device, keeps
    waiting, and takes its own radio back when it returns."""
    caplog.set_level(logging.WARNING, logger="swarm.runtime.bridge.radio_bridge")
    heard: list[tuple[str, str]] = []
    with running_emulator(tmp_path, 3) as run, ExitStack() as stack:
        n1, n2 = _two_bridged_nodes(run, stack)
        b2 = n2.bridge
        b2.add_listener(lambda what, text: heard.append((what, text)))
        path = Path(run.paths[1])
        run.emu.unplug(1)
        wait_until(lambda: b2.stats.radio_losses == 1, "a2's bridge to notice its radio gone", AIR_DEADLINE)
        wait_until(lambda: not path.is_symlink(), "radio1's link removed", AIR_DEADLINE)

        def refused() -> list[str]:
            return [text for what, text in heard if what == "refused"]

        # 1. a fresh pty where the radio was
        master, other = raw_pty()
        stack.callback(os.close, master)
        point(path, other)
        wait_until(
            lambda: refused() or b2.stats.radio_reopens, "a2's bridge to try the device at its path", DEADLINE
        )
        assert b2.stats.radio_reopens == 0, "the bridge took another device as its radio"
        attempts = b2.stats.radio_refused
        wrote = arriving_until(master, lambda: b2.stats.radio_refused >= attempts + 3, "three more attempts")
        assert wrote == b"", f"the bridge wrote {len(wrote)} bytes to a device that is not its radio"
        assert len(refused()) == 1, heard
        assert other in refused()[0] and "radio 1" in refused()[0], refused()
        # 2. another radio of the same emulator, which nobody holds
        before = run.radio(2)["serial_in"]
        point(path, run.emu.slave_names[2])
        wait_until(lambda: len(refused()) == 2, "the second device refused", DEADLINE)
        attempts = b2.stats.radio_refused
        wait_until(lambda: b2.stats.radio_refused >= attempts + 2, "two more attempts on it", DEADLINE)
        assert run.radio(2)["serial_in"] == before, "bytes written into another radio"
        assert len(refused()) == 2 and "radio 2" in refused()[1], heard
        assert b2.stats.radio_reopens == 0 and not b2.link_lost
        # 3. its own radio back
        path.unlink()
        run.emu.replug(1)
        wait_until(lambda: b2.stats.radio_reopens == 1, "a2's own radio taken back", DEADLINE)
        assert heard[-1][0] == "back"
        wait_until(
            lambda: (
                n1.t.send("a2", Selection(1, 2, 9, 3)),
                any(m == Selection(1, 2, 9, 3) for m in n2.inbox),
            )[1],
            "a1 -> a2 after its radio came back",
            DEADLINE,
            0.5,
        )
    lines = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(lines) == 2, f"one line per device refused, not one per attempt: {lines}"


def test_a_device_swapped_while_the_radio_is_lent_is_not_taken_back(tmp_path: Path) -> None:
    """The radio check borrows the port. A path that already names another device is not
    lent (the check would talk to it); one that comes to name another device while lent
    is not taken back; with --exit-on-radio-loss (no reopening) the bridge stops, the
    refusal as its reason."""
    heard: list[tuple[str, str]] = []
    with running_emulator(tmp_path, 2) as run, ExitStack() as stack:
        _n1, n2 = _two_bridged_nodes(run, stack)
        b2 = n2.bridge
        b2.add_listener(lambda what, text: heard.append((what, text)))
        master, other = raw_pty()
        stack.callback(os.close, master)
        path = Path(run.paths[1])
        # 1. swapped before the check: the borrower is not called, the radio waited for
        point(path, other)
        called: list[bool] = []
        with pytest.raises(LinkOpenError, match=f"{other} .* is not the radio opened") as info:
            b2.lend_radio(lambda: called.append(True), why="radio check")
        assert not called and type(info.value).__name__ == "DeviceMismatchError"
        wait_until(lambda: b2.stats.radio_refused, "the other device refused", DEADLINE)
        assert arriving(master, 1.0) == b""
        point(path, run.emu.slave_names[1])  # its radio back at the path
        wait_until(lambda: b2.stats.radio_reopens == 1, "a2's radio taken back", DEADLINE)
        assert [what for what, _ in heard] == ["paused", "refused", "back"], heard
        # 2. swapped during the check, with --exit-on-radio-loss
        b2.cfg.reopen_radio = False
        b2.lend_radio(lambda: point(path, other), why="radio check")
        wait_until(lambda: b2.link_lost, "a2's bridge to give up the radio", DEADLINE)
        assert b2.stats.radio_reopens == 1
        assert other in b2.loss_reason and "radio 1" in b2.loss_reason, b2.loss_reason
        assert arriving(master, 1.0) == b""
        assert [what for what, _ in heard][3:] == ["paused", "lost"], heard


# -- real processes --------------------------------------------------------------------


def last(child: Child, event: str) -> dict[str, Any] | None:
    for line in reversed(list(child.lines)):
        obj = json.loads(line)
        if obj.get("event") == event:
            return dict(obj)
    return None


def events(child: Child, event: str) -> list[dict[str, Any]]:
    return [o for o in map(json.loads, list(child.lines)) if o.get("event") == event]


def up(*children: Child) -> Callable[[], None]:
    def check() -> None:
        for c in children:
            assert c.proc.poll() is None, f"{c.name} exited {c.proc.returncode}: {c.errors[-5:]}"

    return check


def settled(a1: Child, a2: Child) -> tuple[int, frozenset[int]] | None:
    """(leader, members) when both agents agree, the leader leading the other."""
    s1, s2 = last(a1, "state"), last(a2, "state")
    if s1 is None or s2 is None or s1["leader"] != s2["leader"] or not s1["leader"]:
        return None
    lead = s1 if s1["phase"] == "LEADER" else s2
    other = s2 if lead is s1 else s1
    if lead["phase"] != "LEADER" or other["phase"] != "MEMBER" or set(lead["members"]) != {other["id"]}:
        return None
    return int(lead["id"]), frozenset(lead["members"])


def get(url: str) -> Any:
    import urllib.request

    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


def test_agent_and_station_stay_up_and_return_after_an_unplug(tmp_path: Path) -> None:
    emu, paths = start_emulator(3, tmp_path, "--seed", "16")
    children: list[Child] = []
    try:
        a1 = Child(["agent", "--name", "agent1", "--id", "1", "--radio", paths[0], "--json"], name="agent1")
        a2 = Child(["agent", "--name", "agent2", "--id", "2", "--radio", paths[1], "--json"], name="agent2")
        gcs = Child(
            ["gcs", "--radio", paths[2], "--http", f"127.0.0.1:{free_port()}", "--tiles", "none", "--json"],
            name="gcs",
        )
        children += [a1, a2, gcs]
        alive = up(*children)
        url = json.loads(gcs.wait_lines(1, 30)[0])["url"]
        for c in (a1, a2):
            c.wait_lines(1, 30)

        def swarm() -> tuple[int, frozenset[int]] | None:
            alive()
            return settled(a1, a2)

        def connected() -> set[int]:
            alive()
            return {a["id"] for a in get(url + "api/state")["agents"] if a["connected"]}

        before = wait_until(swarm, "agent1 and agent2 to agree on a leader", DEADLINE, 0.1)
        wait_until(lambda: connected() == {1, 2}, "the station to connect both", DEADLINE, 0.2)
        # agent2's radio is pulled out for a few seconds
        control(tmp_path, f"unplug 1 {OUTAGE_S}")
        lost = wait_until(lambda: (alive(), events(a2, "radio"))[1], "agent2: radio lost", DEADLINE, 0.1)
        assert lost[0]["state"] == "lost" and lost[0]["name"] == "agent2"
        wait_until(lambda: len(events(a2, "radio")) >= 2, "agent2: radio back", DEADLINE, 0.1)
        assert events(a2, "radio")[1]["state"] == "back"
        after = wait_until(swarm, "agent1 and agent2 to agree again", DEADLINE, 0.1)
        print(
            f"\nbefore the unplug: leader {before[0]} members {set(before[1])}; "
            f"after: leader {after[0]} members {set(after[1])}"
        )
        assert after == before or set(after[1]) | {after[0]} == {1, 2}
        # the station's radio next
        control(tmp_path, f"unplug 2 {OUTAGE_S}")
        wait_until(
            lambda: (alive(), [e for e in events(gcs, "log") if e["kind"] == "radio"])[1],
            "gcs: radio lost",
            DEADLINE,
            0.1,
        )
        wait_until(
            lambda: len([e for e in events(gcs, "log") if e["kind"] == "radio"]) >= 2,
            "gcs: radio back",
            DEADLINE,
            0.1,
        )
        radio = [e["text"] for e in events(gcs, "log") if e["kind"] == "radio"]
        assert radio[0].startswith("radio lost: ") and radio[1].startswith("radio back after "), radio
        wait_until(lambda: connected() == {1, 2}, "the station to see both agents again", DEADLINE, 0.2)
        for c in children:
            c.proc.send_signal(signal.SIGTERM)
        for c in children:
            assert c.proc.wait(10) == 0, f"{c.name}: {c.errors[-5:]}"
            assert not [e for e in c.errors if "Traceback" in e], c.errors
    finally:
        for c in children:
            c.stop(grace=3)
        emu.stop()


def test_exit_on_radio_loss_exits_1_with_one_line(tmp_path: Path) -> None:
    emu, paths = start_emulator(2, tmp_path, "--seed", "16")
    children: list[Child] = []
    try:
        agent = Child(
            ["agent", "--name", "agent1", "--id", "1", "--radio", paths[0], "--exit-on-radio-loss"],
            name="agent1",
        )
        gcs = Child(
            [
                "gcs",
                "--radio",
                paths[1],
                "--http",
                f"127.0.0.1:{free_port()}",
                "--tiles",
                "none",
                "--exit-on-radio-loss",
            ],
            name="gcs",
        )
        children += [agent, gcs]
        for c in children:
            c.wait_lines(1, 30)
        control(tmp_path, "unplug 0")
        control(tmp_path, "unplug 1")
        for c, prog in ((agent, "swarm agent"), (gcs, "swarm gcs")):
            assert c.proc.wait(30) == 1, c.errors
            c.stop()
            assert c.errors == [c.errors[0]] and c.errors[0].startswith(f"{prog}: error: radio link lost"), (
                c.errors
            )
    finally:
        for c in children:
            c.stop(grace=3)
        emu.stop()


def test_exit_on_radio_loss_needs_a_radio(capsys: pytest.CaptureFixture[str]) -> None:
    from swarm.cli.commands.agent import main as agent_main
    from swarm.cli.commands.gcs import main as gcs_main

    assert gcs_main(["--zenoh-listen", "tcp/127.0.0.1:1", "--exit-on-radio-loss"]) == 2
    assert (
        agent_main(["--name", "a", "--id", "1", "--zenoh-listen", "tcp/127.0.0.1:1", "--exit-on-radio-loss"])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "swarm gcs: error: --exit-on-radio-loss is for a station on a radio (--radio)",
        "swarm agent: error: --exit-on-radio-loss is for an agent on a radio (--radio)",
    ]


def test_agent_refuses_another_device_at_its_radio_path_with_one_line(tmp_path: Path) -> None:
    """A real ``swarm agent``: its radio unplugged, the path made to point at a fresh pty,
    then the radio plugged back. Nothing reaches the other pty; stdout has one
    ``refused`` event naming both devices, stderr one line; the agent takes its radio back."""
    emu, paths = start_emulator(1, tmp_path, "--seed", "16")
    agent = Child(["agent", "--name", "agent1", "--id", "1", "--radio", paths[0], "--json"], name="agent1")
    master, other = raw_pty()
    try:
        agent.wait_lines(1, 30)
        path = Path(paths[0])

        def radio_events() -> list[dict[str, Any]]:
            up(agent)()
            return json_events(agent.lines, "radio")

        control(tmp_path, "unplug 0")
        wait_until(lambda: radio_events() and not path.is_symlink(), "agent1: radio lost", DEADLINE, 0.1)
        point(path, other)
        wait_until(lambda: len(radio_events()) >= 2, "agent1: the device at its path tried", DEADLINE, 0.1)
        assert radio_events()[1]["state"] == "refused", radio_events()
        wrote = arriving(master, 3.0)
        assert wrote == b"", f"the agent wrote {len(wrote)} bytes to a device that is not its radio"
        refused = radio_events()[1]
        assert len(radio_events()) == 2 and other in refused["text"] and "radio 0" in refused["text"], refused
        assert len([e for e in agent.errors if "refused" in e]) == 1, agent.errors
        path.unlink()
        control(tmp_path, "replug 0")
        wait_until(lambda: len(radio_events()) >= 3, "agent1: radio back", DEADLINE, 0.1)
        assert radio_events()[2]["state"] == "back"
        agent.proc.send_signal(signal.SIGTERM)
        assert agent.proc.wait(10) == 0, agent.errors
        assert not [e for e in agent.errors if "Traceback" in e], agent.errors
    finally:
        os.close(master)
        agent.stop(grace=3)
        emu.stop()
