"""Strict register reads (radios/sik/readout.py): garbled, spliced, foreign and lost answers.

The remote answers come from a real ATEngine (``run_remote``), cut into the 32-byte
packets a SiK radio sends them in; a seeded loss drops whole packets, as the air does.
"""

from __future__ import annotations

import random

import pytest
from sik_pty_radio import make_engine

from radios.errors import ATError, ATTimeoutError
from radios.sik.readout import (
    DEFAULT_TRIES,
    parse_local,
    parse_register_line,
    parse_value,
    read_remote,
    register_table,
)

STANDARD = register_table("standard")
MULTIPOINT = register_table("multipoint")


class LossyRemote:
    """``ask`` for :func:`read_remote`: the real engine's answer in 32-byte packets, some lost."""

    def __init__(
        self, flavour: str = "standard", *, loss: float = 0.0, seed: int = 0, node: int | None = None
    ):
        self.engine = make_engine(flavour, node_id=node)
        self.rng = random.Random(seed)
        self.loss = loss
        self.asked: list[str] = []
        self.drop: set[int] = set()  # packet numbers of the next answer to drop, whatever the loss

    def __call__(self, line: str) -> list[str]:
        self.asked.append(line)
        if self.rng.random() < self.loss:
            raise ATTimeoutError("remote radio did not answer (command lost)")
        reply = self.engine.run_remote(line).output
        packets = [reply[i : i + 32] for i in range(0, len(reply), 32)]
        kept = b"".join(
            p for n, p in enumerate(packets) if n not in self.drop and self.rng.random() >= self.loss
        )
        self.drop = set()
        lines = [raw.decode("ascii", "replace").strip() for raw in kept.split(b"\n")]
        if not any(lines):
            raise ATTimeoutError("remote radio did not answer (reply lost)")
        return [line for line in lines if line]

    def truth(self) -> dict[str, int]:
        return self.engine.params.as_dict()


# -- one line -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "line",
    [
        "S4:TXER=20",  # a lost packet spliced two names together
        "S5:NETID=25",  # a real name under another register's number
        "S3:NETID=25S4:TXPOWER=20",
        "S3:NETID=",
        "S3:NETID=99999999999",
        "xS3:NETID=25",
        "[1] [1] S0:FORMAT=26",  # two prefixes
        "S3 :NETID=25",
        "S03:NETID=25x",
        "",
    ],
)
def test_a_garbled_line_is_not_a_register(line: str) -> None:
    assert parse_register_line(line, STANDARD) is None
    assert parse_register_line(line, STANDARD, known_only=False) is None


def test_whole_lines_in_every_form() -> None:
    assert parse_register_line("S3:NETID=25", STANDARD) == ("NETID", 3, 25)
    assert parse_register_line("S0: FORMAT=22", STANDARD) == ("FORMAT", 0, 22)  # before 2014
    assert parse_register_line("[2] S15:NODEID=2", MULTIPOINT, node=2) == ("NODEID", 15, 2)
    assert parse_register_line("[2] S15: NODEID=2", MULTIPOINT, node=2) == (
        "NODEID",
        15,
        2,
    )  # MP prints the space
    assert parse_register_line("[1] S15:NODEID=1", MULTIPOINT, node=2) is None  # another node's answer
    assert parse_register_line("S15:NODEID=1", MULTIPOINT, node=2) is None
    assert parse_register_line("S16:ENCRYPTION_LEVEL=1", STANDARD) == ("ENCRYPTION_LEVEL", 16, 1)
    # an extra register of a firmware variant: kept locally, never over the air
    assert parse_register_line("S17:ANT_MODE=0", STANDARD) is None
    assert parse_register_line("S17:ANT_MODE=0", STANDARD, known_only=False) == ("ANT_MODE", 17, 0)
    assert parse_register_line("S3:ANT_MODE=0", STANDARD, known_only=False) is None  # S3 is NETID
    assert parse_register_line("S17:GPI1_1R/CIN=0", STANDARD, known_only=False) == ("GPI1_1R/CIN", 17, 0)
    assert parse_register_line("S17:GPI1_1R/CIN=0", STANDARD) is None


def test_parse_value() -> None:
    assert parse_value(["25"], None) == 25
    assert parse_value(["[2] 25"], 2) == 25
    assert parse_value(["[1] 25"], 2) is None
    assert parse_value(["ERROR"], None) is None
    assert parse_value(["25", "26"], None) is None
    assert parse_value(["S3:NETID=25"], None) is None
    assert parse_value(["2x5"], None) is None


# -- a local ATI5 ---------------------------------------------------------------------------


def test_parse_local_refuses_a_garbled_line_by_name() -> None:
    lines = ["S0:FORMAT=26", "S1:SERIAL_SPEED=57", "S2:AIR_SPEED=64junk"]
    with pytest.raises(
        ATError, match=r"ATI5 on tty: 'S2:AIR_SPEED=64junk' is not a standard SiK register line"
    ):
        parse_local(lines, "standard", "tty")
    with pytest.raises(ATError, match="is a second"):
        parse_local(["S3:NETID=25", "S3:NETID=26"], "standard", "tty")
    with pytest.raises(ATError, match="no parameter lines"):
        parse_local([], "standard", "tty")
    assert parse_local(["S0:FORMAT=26", "S17:ANT_MODE=0"], "standard", "tty") == {
        "FORMAT": (0, 26),
        "ANT_MODE": (17, 0),
    }


# -- over the air ---------------------------------------------------------------------------


def test_remote_read_without_loss_confirms_every_register_once() -> None:
    remote = LossyRemote()
    readout = read_remote(remote, "standard")
    assert {n: v for n, (_, v) in readout.values.items()} == remote.truth()
    assert readout.unreadable == [] and readout.garbled == 0
    assert remote.asked == ["RTI5"] + [f"RTS{n}?" for n in range(16)]


def test_a_spliced_line_that_looks_whole_is_not_believed() -> None:
    """'S3:NETID=2' + a lost packet + '0' of a later line reads 'S3:NETID=20': whole in
    form, wrong in value. Only a value a second answer confirms is shown."""
    remote = LossyRemote()

    def ask(line: str) -> list[str]:
        if line == "RTI5":
            return ["S0:FORMAT=26", "S1:SERIAL_SPEED=57", "S2:AIR_SPEED=64", "S3:NETID=20", "S4:TXER=20"]
        return remote(line)

    readout = read_remote(ask, "standard")
    assert readout.garbled == 1  # S4:TXER
    assert readout.values["NETID"] == (3, 25)
    assert {n: v for n, (_, v) in readout.values.items()} == remote.truth()
    assert remote.asked.count("RTS3?") == 2  # 20 from RTI5, then 25 twice
    assert remote.asked.count("RTS1?") == 1


def test_packets_lost_from_rti5_only_cost_questions() -> None:
    remote = LossyRemote()
    remote.drop = {1, 3}
    readout = read_remote(remote, "standard")
    assert readout.garbled >= 1
    assert {n: v for n, (_, v) in readout.values.items()} == remote.truth()


def test_a_stale_or_flapping_answer_is_never_taken() -> None:
    answers = iter(["7", "8", "9", "10", "11", "12"] * 20)

    def ask(line: str) -> list[str]:
        if line == "RTI5":
            return ["S0:FORMAT=26", "S3:NETID=25"]
        return [next(answers)]

    readout = read_remote(ask, "standard")
    # FORMAT and NETID were seen once in RTI5 and never again: nothing agrees
    assert readout.values == {}
    assert readout.unreadable == list(STANDARD)[:16]


@pytest.mark.parametrize("seed", range(40))
def test_lossy_remote_never_shows_a_wrong_value(seed: int) -> None:
    remote = LossyRemote(loss=0.3, seed=seed)
    try:
        readout = read_remote(remote, "standard")
    except ATTimeoutError:
        return  # RTI5 and RTS0? both lost: "link down", nothing shown
    truth = remote.truth()
    for name, (index, value) in readout.values.items():
        assert value == truth[name] and STANDARD[name] == index
    assert set(readout.values) | set(readout.unreadable) == set(truth)
    assert len(remote.asked) <= 1 + 16 * DEFAULT_TRIES


def test_link_down_is_said_after_two_questions() -> None:
    asked: list[str] = []

    def ask(line: str) -> list[str]:
        asked.append(line)
        raise ATTimeoutError("remote radio did not answer")

    with pytest.raises(ATTimeoutError, match=r"answered neither RTI5 nor RTS0\? \(link down\?\)"):
        read_remote(ask, "standard")
    assert asked == ["RTI5", "RTS0?"]


def test_multipoint_takes_only_the_target_nodes_answers() -> None:
    target = LossyRemote("multipoint", node=2)
    other = make_engine("multipoint", node_id=1)

    def ask(line: str) -> list[str]:
        # node 1 answers too (an RT line that reached it): its lines come first
        theirs = other.run_remote(line).output.decode().splitlines()
        return theirs + target(line)

    readout = read_remote(ask, "multipoint", node=2)
    assert readout.unreadable == []
    assert {n: v for n, (_, v) in readout.values.items()} == target.truth()
    assert target.asked[0] == "RTI5,2" and target.asked[-1] == "RTS18?,2"
