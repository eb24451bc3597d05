"""Free local ports for benches, the demo and the tests: never from the kernel's
ephemeral range, where any port-0 bind or outgoing connection on the machine could be
handed the port before the child meant to listen on it binds it (CI failed on that)."""

from __future__ import annotations

import socket

import pytest

from radios import ports


@pytest.mark.parametrize("kind", ["tcp", "udp"])
def test_a_free_port_is_outside_the_ephemeral_range_and_bindable(kind: ports.PortKind) -> None:
    lo, hi = ports.ephemeral_range()
    for _ in range(50):
        p = ports.free_port(kind)
        assert not lo <= p <= hi and p >= ports.LOWEST
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM if kind == "udp" else socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", p))


def test_a_port_range_is_free_step_apart_and_outside_the_ephemeral_range() -> None:
    lo, hi = ports.ephemeral_range()
    base = ports.free_port_range(4, "tcp", step=10)
    held = []
    try:
        for i in range(4):
            assert not lo <= base + 10 * i <= hi
            s = socket.socket()
            s.bind(("127.0.0.1", base + 10 * i))
            held.append(s)
    finally:
        for s in held:
            s.close()


def test_a_held_port_is_not_bindable_and_a_narrow_low_range_draws_above_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", ports.free_port("tcp")))
        s.listen()
        assert not ports._bindable(s.getsockname()[1], "tcp")
    monkeypatch.setattr(ports, "ephemeral_range", lambda: (12000, 40000))
    assert ports.candidates() == range(40001, 65000)
    assert 40001 <= ports.free_port("udp") < 65000
