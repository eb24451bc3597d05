"""The ``virtual://NAME`` backend beyond the contract suite (test_link_contract.py runs
that on it too): a bus of any size, isolation between names, a closed link waking
its reader, repeatable loss, a bounded queue, capture, and bad URLs.
"""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path

import pytest
from emu_helpers import heartbeat, opened, tunnel

from radios.errors import LinkClosedError, LinkOpenError
from radios.link import Link, open_link
from radios.tlog import read_tlog
from radios.virtual import MAX_PENDING, VirtualLink


def bus(query: str = "") -> str:
    return f"virtual://test-{uuid.uuid4().hex}{query}"


def drain(link: Link) -> list[bytes]:
    out: list[bytes] = []
    while (f := link.recv(0)) is not None:
        out.append(f.raw)
    return out


def test_every_other_member_hears_each_frame_in_order() -> None:
    url = bus()
    with opened(open_link(url), open_link(url), open_link(url)) as (a, b, c):
        sa = [tunnel(1, bytes([k]) * 5, seq=k) for k in range(3)]
        sb = [tunnel(2, b"from b")]
        for raw in sa:
            a.send(raw)
        for raw in sb:
            b.send(raw)
        assert drain(a) == sb, "a hears b, never itself"
        assert drain(b) == sa
        assert drain(c) == sa + sb
        assert (a.stats.frames_out, c.stats.frames_in) == (3, 4)


def test_buses_of_other_names_do_not_hear_each_other_nor_late_joiners_the_past() -> None:
    one, two = bus(), bus()
    with opened(open_link(one), open_link(two), open_link(one)) as (a, other, b):
        a.send(heartbeat(1))
        late = open_link(one)
        try:
            assert late.recv(0.1) is None
            assert other.recv(0.1) is None
            got = b.recv(1.0)
            assert got is not None and got.raw == heartbeat(1)
        finally:
            late.close()


def test_close_wakes_a_blocked_reader() -> None:
    link = open_link(bus())
    errors: list[BaseException] = []

    def reader() -> None:
        try:
            link.recv(None)
        except BaseException as exc:  # the test inspects what came out
            errors.append(exc)

    t = threading.Thread(target=reader)
    t.start()
    time.sleep(0.1)  # let it block (the outcome does not depend on it)
    link.close()
    t.join(10.0)
    assert not t.is_alive(), "recv(None) did not return after close()"
    assert len(errors) == 1 and isinstance(errors[0], LinkClosedError)
    with pytest.raises(LinkClosedError):
        link.send(heartbeat(1))
    with pytest.raises(LinkClosedError):
        assert isinstance(link, VirtualLink)
        link.write_bytes(b"x")


def test_a_closed_member_no_longer_receives_and_the_others_go_on() -> None:
    url = bus()
    with opened(open_link(url), open_link(url), open_link(url)) as (a, b, c):
        b.close()
        a.send(tunnel(1, b"after b left"))
        assert drain(c) == [tunnel(1, b"after b left")]


def test_loss_is_drawn_per_receiver_and_repeatable() -> None:
    def pattern(seed: int) -> list[int]:
        url = bus()
        with opened(open_link(f"{url}?loss=0.5&seed={seed}"), open_link(url)) as (a, b):
            for k in range(200):
                a.send(tunnel(1, b"n", seq=k % 256))
            return [f[4] for f in drain(b)]  # the sequence numbers that got through

    first = pattern(1)
    assert 40 < len(first) < 160
    assert pattern(1) == first
    assert pattern(2) != first
    url = bus()
    with opened(open_link(f"{url}?loss=1"), open_link(url)) as (a, b):
        a.send(heartbeat(1))
        assert b.recv(0.1) is None
        assert a.stats.frames_out == 1


def test_an_unread_member_drops_the_newest_frames_and_counts_them() -> None:
    url = bus()
    with opened(open_link(url), open_link(url)) as (a, b):
        raw = heartbeat(1)
        for _ in range(MAX_PENDING + 10):
            a.send(raw)
        assert b.stats.drops == 10
        assert len(drain(b)) == MAX_PENDING
        assert a.stats.drops == 0


def test_capture_wraps_a_virtual_link(tmp_path: Path) -> None:
    url = bus()
    path = tmp_path / "v.tlog"
    with opened(open_link(url, capture=path), open_link(url)) as (a, b):
        a.send(heartbeat(1))
        b.send(heartbeat(2))
        got = a.recv(1.0)
        assert got is not None and got.raw == heartbeat(2)
    assert [r.raw for r in read_tlog(path)] == [heartbeat(1), heartbeat(2)]


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("virtual://", "no bus name"),
        ("virtual://x?loss=2", "loss must be between 0 and 1"),
        ("virtual://x?loss=-0.1", "loss must be between 0 and 1"),
        ("virtual://x?loss=nan", "loss must be between 0 and 1"),
        ("virtual://x?loss=lots", "loss must be a number"),
        ("virtual://x?seed=1.5", "seed must be an integer"),
        ("virtual://x?baud=57600", r"unknown option\(s\) baud \(known: loss, seed\)"),
    ],
)
def test_bad_virtual_urls(url: str, message: str) -> None:
    with pytest.raises(LinkOpenError, match=message) as info:
        open_link(url)
    assert "\n" not in str(info.value)


def test_virtual_takes_no_keyword_options() -> None:
    with pytest.raises(LinkOpenError, match="unexpected options for a virtual link: clock"):
        open_link(bus(), clock=time.monotonic)
