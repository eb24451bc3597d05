"""Free local ports for benches, the demo and the tests: never from the kernel's
ephemeral range, where any port-0 bind or outgoing connection on the machine could be
handed the port before the child meant to listen on it binds it (CI failed on that)."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

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
        assert not ports.bindable(s.getsockname()[1], "tcp")
    monkeypatch.setattr(ports, "ephemeral_range", lambda: (12000, 40000))
    assert ports.candidates() == range(40001, 65000)
    assert 40001 <= ports.free_port("udp") < 65000


_DRAW = """
import sys, time
from radios import ports
ports.candidates = lambda: range(int(sys.argv[1]), int(sys.argv[1]) + 300)
ports.REGISTRY = __import__("pathlib").Path(sys.argv[2]) if sys.argv[2] else None
while time.time() < float(sys.argv[3]):  # both start drawing at the same moment
    time.sleep(0.001)
print(" ".join(str(ports.free_port("tcp")) for _ in range(100)))
"""


def _draw_side_by_side(tmp_path: Path, registry: str) -> tuple[set[int], set[int]]:
    base = ports.free_port_range(300, "tcp", registry=None)  # 300 ports nobody listened on
    start = f"{time.time() + 3:.3f}"
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _DRAW, str(base), registry, start], stdout=subprocess.PIPE, text=True
        )
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=120)[0].split() for p in procs]
    assert all(p.returncode == 0 for p in procs) and all(len(o) == 100 for o in outs), outs
    return {int(p) for p in outs[0]}, {int(p) for p in outs[1]}


def test_two_processes_drawing_at_once_never_get_the_same_port(tmp_path: Path) -> None:
    """Drawn but not yet bound (a child still starting), a port passes the bind check
    in every other process: CI's station failed with "port in use" when another test's
    draw gave it the same one. The registry hands each port to one process only."""
    first, second = _draw_side_by_side(tmp_path, str(tmp_path / "ports"))
    assert len(first) == 100 and len(second) == 100 and not first & second
    # without the registry the same two draws from 300 ports collide (the CI failure)
    first, second = _draw_side_by_side(tmp_path, "")
    assert first & second


def test_a_registry_that_is_not_ours_is_ignored_with_the_ports_still_drawn(tmp_path: Path) -> None:
    """Another user's file, or a symlink planted where the registry goes, is never
    written through: the draw goes on without it (bind-checked, as before)."""
    target = tmp_path / "victim"
    target.write_text("keep\n")
    link = tmp_path / "ports"
    link.symlink_to(target)
    assert ports.free_port("tcp", registry=link) >= ports.LOWEST
    assert target.read_text() == "keep\n"


def test_leases_expire_and_the_registry_stays_small(tmp_path: Path) -> None:
    reg = tmp_path / "ports"
    now = [1000.0]
    taken = [ports.free_port("udp", registry=reg, now=lambda: now[0]) for _ in range(20)]
    assert len(set(taken)) == 20 and len(reg.read_text().splitlines()) == 20
    now[0] += ports.LEASE_S + 1
    ports.free_port("udp", registry=reg, now=lambda: now[0])
    assert len(reg.read_text().splitlines()) == 1  # the expired leases went
