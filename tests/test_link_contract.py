"""One contract suite for every link backend (STYLE.md point 7, python-can's
back2back tests), a receive-only subset for replay, and open_link's errors.

A :class:`Pair` is two ends of one channel: what ``a`` sends, ``b`` receives;
``inject`` puts raw bytes into the stream that ``b`` receives. The backends:

* ``emulator``: radio0 and radio1 of an in-process emulator (real ptys, real air
  model, real time); injected bytes go over the emulated air;
* ``loop``: pyserial's ``loop://``, one link talking to itself;
* ``loop+capture``: the same wrapped by ``open_link(..., capture=PATH)``;
* ``pty``: a production link on the slave of a fresh pty, the test holding the
  master through a minimal test-only :class:`Link` backend;
* ``virtual``: two members of a ``virtual://`` bus; a third member injects bytes
  with ``write_bytes``.
"""

from __future__ import annotations

import os
import select
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from emu_helpers import (
    AIR_DEADLINE,
    garbage,
    heartbeat,
    opened,
    raw_pty,
    running_emulator,
    tunnel,
)
from net_helpers import ManualClock, wait_until

from radios.errors import (
    CaptureError,
    FrameError,
    LinkClosedError,
    LinkError,
    LinkOpenError,
    RadioError,
)
from radios.link import Link, open_link
from radios.mavlink import Frame, FrameBuilder, parse_one
from radios.replay import TlogLink
from radios.seriallink import SerialLink
from radios.tlog import TlogWriter, read_tlog
from radios.virtual import VirtualLink

# -- backends ---------------------------------------------------------------------------------


class FdLink(Link):
    """Test-only backend: a raw file descriptor (the master end of a pty)."""

    def __init__(self, fd: int) -> None:
        super().__init__(f"fd:{fd}")
        self.fd = fd

    def _read(self, timeout: float) -> bytes:
        if self._closed:
            raise LinkClosedError(f"{self.url} is closed")
        r, _, _ = select.select([self.fd], [], [], timeout)
        return os.read(self.fd, 4096) if r else b""

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.fd, view) :]

    def _close(self) -> None:
        os.close(self.fd)


@dataclass
class Pair:
    a: Link
    b: Link
    inject: Callable[[bytes], object]
    #: longest a frame may take from ``a`` to ``b`` (the emulator's air is slow)
    deadline: float = 5.0
    links: list[Link] = field(default_factory=list)


def _port_write(link: Link) -> Callable[[bytes], object]:
    inner = getattr(link, "inner", link)
    assert isinstance(inner, SerialLink)
    return inner.port.write


def bus_url(query: str = "") -> str:
    """A ``virtual://`` URL of a bus no other test uses (bus names are process-wide)."""
    return f"virtual://contract-{uuid.uuid4().hex}{query}"


@pytest.fixture(params=["emulator", "loop", "loop+capture", "pty", "virtual"])
def pair(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Pair]:
    kind = request.param
    if kind == "emulator":
        with running_emulator(tmp_path, 2) as emu, opened(emu.open(0), emu.open(1)) as (a, b):
            emu.wait_ready(0, 1)
            yield Pair(a, b, _port_write(a), deadline=AIR_DEADLINE)
    elif kind in ("loop", "loop+capture"):
        capture = tmp_path / "loop.tlog" if kind == "loop+capture" else None
        with opened(open_link("loop://", capture=capture)) as (link,):
            yield Pair(link, link, _port_write(link))
    elif kind == "virtual":
        url = bus_url()
        with opened(open_link(url), open_link(url), open_link(url)) as (a, b, tap):
            assert isinstance(tap, VirtualLink)
            yield Pair(a, b, tap.write_bytes)
    else:
        master, path = raw_pty()
        with opened(FdLink(master), open_link(path)) as (a, b):
            yield Pair(a, b, lambda data: os.write(master, data))


def frames(n: int, sysid: int = 7) -> list[bytes]:
    return [tunnel(sysid, bytes([k + 1]) * (10 + k), seq=k) for k in range(n)]


def recv_n(link: Link, n: int, deadline: float) -> list[bytes]:
    out: list[bytes] = []
    end = time.monotonic() + deadline
    while len(out) < n and time.monotonic() < end:
        f = link.recv(0.2)
        if f is not None:
            out.append(f.raw)
    return out


# -- the contract ------------------------------------------------------------------------------


def test_peer_receives_identical_bytes_in_order(pair: Pair) -> None:
    sent = frames(5)
    for raw in sent:
        pair.a.send(raw)
    assert recv_n(pair.b, len(sent), pair.deadline) == sent


def test_send_accepts_frame_objects(pair: Pair) -> None:
    raw = tunnel(9, b"frame object")
    pair.a.send(parse_one(raw))
    got = pair.b.recv(pair.deadline)
    assert isinstance(got, Frame)
    assert got.raw == raw


def test_recv_times_out_with_none(pair: Pair) -> None:
    for timeout in (0.05, 0.3):
        t0 = time.monotonic()
        assert pair.b.recv(timeout) is None
        elapsed = time.monotonic() - t0
        assert elapsed >= timeout - 0.01, f"recv({timeout}) gave up after {elapsed:.3f} s"
        assert elapsed < timeout + 2.0, f"recv({timeout}) took {elapsed:.3f} s"


def test_recv_zero_polls(pair: Pair) -> None:
    t0 = time.monotonic()
    assert pair.b.recv(0) is None
    assert time.monotonic() - t0 < 1.0
    raw = tunnel(3, b"polled")
    pair.a.send(raw)
    got = wait_until(lambda: pair.b.recv(0), "the frame by polling", pair.deadline, interval=0.01)
    assert got is not None and got.raw == raw


def test_frame_arriving_in_pieces_is_received_whole(pair: Pair) -> None:
    raw = tunnel(4, b"in two pieces")
    pair.inject(raw[:9])
    assert pair.b.recv(0.3) is None  # half a frame is not a frame
    pair.inject(raw[9:])
    got = pair.b.recv(pair.deadline)
    assert got is not None and got.raw == raw


def test_stats_count_frames_and_bytes_both_ways(pair: Pair) -> None:
    sent = frames(3)
    for raw in sent:
        pair.a.send(raw)
    assert recv_n(pair.b, 3, pair.deadline) == sent
    n = sum(map(len, sent))
    sa, sb = pair.a.stats, pair.b.stats
    assert (sa.frames_out, sa.bytes_out, sa.drops) == (3, n, 0)
    assert (sb.frames_in, sb.bytes_in) == (3, n)
    assert (sb.crc_errors, sb.unknown_msgid, sb.bytes_skipped) == (0, 0, 0)
    assert sb.as_dict()["frames_in"] == 3


def test_send_of_non_frames_raises_and_writes_nothing(pair: Pair) -> None:
    hb = heartbeat(5)
    bad_crc = hb[:-1] + bytes((hb[-1] ^ 0xFF,))
    for junk in (b"", b"hello", hb[:-1], hb + hb, hb + b"\x00", bad_crc, bytes(300)):
        with pytest.raises(FrameError):
            pair.a.send(junk)
    assert (pair.a.stats.frames_out, pair.a.stats.bytes_out) == (0, 0)
    good = tunnel(5, b"after the junk")
    pair.a.send(good)
    got = pair.b.recv(pair.deadline)
    assert got is not None and got.raw == good
    # the first bytes to arrive are the good frame: nothing of the junk was written
    assert (pair.b.stats.bytes_in, pair.b.stats.bytes_skipped) == (len(good), 0)


def test_garbage_is_skipped_counted_and_does_not_stop_the_next_frames(pair: Pair) -> None:
    junk = garbage(500, seed=7)  # random, with false starts claiming long frames
    pair.inject(junk)
    # what follows is longer than the longest frame, so every false start is disproved
    after = [tunnel(6, bytes(range(1, 129)), seq=k) for k in range(2)]
    assert sum(map(len, after)) >= 280
    for raw in after:
        pair.a.send(raw)
    assert recv_n(pair.b, 2, pair.deadline) == after
    st = pair.b.stats
    assert st.bytes_skipped == len(junk)
    assert st.bytes_in == len(junk) + sum(map(len, after))
    assert st.crc_errors + st.unknown_msgid >= junk.count(0xFD)


def test_close_is_safe_twice_and_use_after_close_raises(pair: Pair) -> None:
    link = pair.b
    link.close()
    link.close()
    assert link.closed
    assert "closed" in repr(link)
    with pytest.raises(LinkClosedError):
        link.send(tunnel(1, b"x"))
    with pytest.raises(LinkClosedError):
        link.recv(0)
    with pytest.raises(LinkClosedError):
        link.recv(0.1)
    assert issubclass(LinkClosedError, LinkError) and issubclass(LinkError, RadioError)


def test_context_manager_closes(pair: Pair) -> None:
    with pair.a as link:
        assert link is pair.a
        assert not link.closed
    assert pair.a.closed
    with pytest.raises(LinkClosedError):
        pair.a.send(tunnel(1, b"x"))


def test_context_manager_closes_on_error(pair: Pair) -> None:
    with pytest.raises(ZeroDivisionError), pair.b:
        1 / 0  # noqa: B018
    assert pair.b.closed


# -- the base class's deadline ----------------------------------------------------------------


class Firehose(Link):
    """A backend that always has more garbage: recv must still honour its timeout.
    It stops after ``limit`` seconds so that a failing test ends."""

    def __init__(self, limit: float) -> None:
        super().__init__("firehose:")
        self.until = time.monotonic() + limit

    def _read(self, timeout: float) -> bytes:
        if time.monotonic() < self.until:
            return b"\x00" * 64
        time.sleep(timeout)
        return b""

    def _write(self, data: bytes) -> None:
        pass


def test_recv_honours_its_timeout_while_garbage_keeps_arriving() -> None:
    """A noisy line (bytes that never make a frame) must not keep recv(0.1) from
    returning None: the deadline is checked only when a read comes back empty."""
    link = Firehose(limit=3.0)
    t0 = time.monotonic()
    assert link.recv(0.1) is None
    elapsed = time.monotonic() - t0
    assert elapsed < 1.5, f"recv(0.1) returned after {elapsed:.1f} s"


# -- capture wrapper -------------------------------------------------------------------------


def test_capture_records_both_directions(tmp_path: Path) -> None:
    path = tmp_path / "c.tlog"
    sent = frames(3)
    with open_link("loop://", capture=path) as link:
        for raw in sent:
            link.send(raw)
        assert recv_n(link, 3, 5.0) == sent
    recorded = [rec.raw for rec in read_tlog(path)]
    assert recorded == sent + sent  # each frame once sent, once received


# -- replay: the receive-only subset -----------------------------------------------------------


RECORDED = [
    (1_700_000_000.0, heartbeat(1)),
    (1_700_000_000.5, tunnel(2, b"second")),
    (1_700_000_002.5, FrameBuilder(3).heartbeat()),
]


@pytest.fixture
def capture_file(tmp_path: Path) -> Path:
    path = tmp_path / "flight.tlog"
    with TlogWriter(path) as w:
        for t, raw in RECORDED:
            w.write(raw, t)
    return path


@pytest.mark.parametrize("url_form", ["plain", "tlog:"])
def test_replay_yields_recorded_frames_in_order_with_their_gaps(
    capture_file: Path, url_form: str, manual_clock: ManualClock
) -> None:
    url = str(capture_file) if url_form == "plain" else f"tlog:{capture_file}"
    with open_link(url, clock=manual_clock, sleep=manual_clock.sleep) as link:
        assert isinstance(link, TlogLink)
        got = [link.recv() for _ in RECORDED]
        assert [f.raw for f in got if f is not None] == [raw for _, raw in RECORDED]
        assert manual_clock.sleeps == pytest.approx([0.5, 2.0])
        assert (link.stats.frames_in, link.stats.bytes_in) == (3, sum(len(raw) for _, raw in RECORDED))
        with pytest.raises(LinkClosedError, match="end of capture"):
            link.recv(0)


def test_replay_timeouts_use_the_injected_clock(capture_file: Path, manual_clock: ManualClock) -> None:
    with open_link(f"tlog:{capture_file}?speed=2", clock=manual_clock, sleep=manual_clock.sleep) as link:
        assert link.recv(0) is not None  # the first frame is due at once
        assert link.recv(0) is None  # the next is due in 0.25 s: polling does not wait
        assert manual_clock.sleeps == []
        assert link.recv(0.1) is None  # waits the timeout, not more
        assert manual_clock.sleeps == pytest.approx([0.1])
        f = link.recv(1.0)
        assert f is not None and f.raw == RECORDED[1][1]
        assert manual_clock.now == pytest.approx(1000.25)


def test_replay_is_receive_only(capture_file: Path, manual_clock: ManualClock) -> None:
    before = capture_file.read_bytes()
    link = open_link(str(capture_file), clock=manual_clock, sleep=manual_clock.sleep)
    with pytest.raises(LinkClosedError, match="receive-only"):
        link.send(heartbeat(1))
    assert link.stats.frames_out == 0
    link.close()
    link.close()
    with pytest.raises(LinkClosedError):
        link.recv(0)
    assert capture_file.read_bytes() == before


# -- open_link errors ------------------------------------------------------------------------


def test_unknown_scheme() -> None:
    with pytest.raises(LinkOpenError, match="unknown link scheme 'foo'"):
        open_link("foo://x")
    with pytest.raises(LinkOpenError, match="unknown link scheme 'foo'"):
        open_link("foo:bar")


def test_missing_device_names_the_path(tmp_path: Path) -> None:
    missing = tmp_path / "ttyUSB9"
    for url in (str(missing), f"{missing}?baud=57600", f"serial:{missing}"):
        with pytest.raises(LinkOpenError, match="no such device") as info:
            open_link(url)
        assert str(missing) in str(info.value)


@pytest.mark.parametrize(
    ("query", "message"),
    [
        ("baud=abc", "baud must be an integer"),
        ("baud=0", "baud must be positive"),
        ("bogus=1", "unknown option.*bogus"),
        ("write_timeout=x", "write_timeout must be a number"),
    ],
)
def test_bad_serial_options(query: str, message: str) -> None:
    master, path = raw_pty()
    try:
        with pytest.raises(LinkOpenError, match=message):
            open_link(f"{path}?{query}")
    finally:
        os.close(master)


def test_other_bad_urls(tmp_path: Path) -> None:
    for url, message in [
        ("", "empty"),
        ("serial:", "no device path"),
        (str(tmp_path / "none.tlog"), "none.tlog"),
        (f"tlog:{tmp_path / 'x.tlog'}?pace=2", "unknown option.*pace"),
        ("tlog:", "no capture file path"),
        ("loop://?baud=x", "baud must be an integer"),
    ]:
        with pytest.raises(LinkOpenError, match=message):
            open_link(url)
    with pytest.raises(LinkOpenError, match="unexpected options"):
        open_link("loop://", clock=time.monotonic)


def test_serial_url_forms_and_baud(tmp_path: Path) -> None:
    master, path = raw_pty()
    try:
        for url in (f"{path}?baud=115200", f"serial:{path}?baud=115200", f"serial://{path}?baud=115200"):
            with open_link(url) as link:
                assert isinstance(link, SerialLink)
                assert link.port.baudrate == 115200
                assert link.url == url
    finally:
        os.close(master)


def test_capture_that_cannot_be_created_closes_the_link(tmp_path: Path) -> None:
    master, path = raw_pty()
    try:
        with pytest.raises(CaptureError):
            open_link(path, capture=tmp_path / "missing" / "c.tlog")
        # the serial link opened first was closed again: nobody holds the slave
        p = select.poll()
        p.register(master, select.POLLIN)
        wait_until(lambda: any(ev & select.POLLHUP for _, ev in p.poll(0)), "the pty hang-up", 5.0)
    finally:
        os.close(master)
