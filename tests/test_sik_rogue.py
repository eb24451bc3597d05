"""A rogue SiK radio reconfiguring the swarm's radios with RT commands (issue 11, item 3).

The attack seen on the bench: any radio in range enters command mode and sends
``RTS3=77``, ``RT&W``, ``RTZ`` (``,<node>`` in multipoint); the target moves to NETID
77, saved, for good. These tests drive the air model in virtual time with the real
AT interpreter on every radio (the same code the pty emulator runs), and the host
side writes the very bytes a terminal would.

What the firmware offers against it (tdm.c, packet.c, freq_hopping.c): nothing but
the NETID filter, and on AES builds a hopping sequence seeded by the key. ``RT``
commands travel in clear even with encryption on, so AES keeps out a rogue that
sends once (it is on the right channel one packet in NUM_CHANNELS), not one that
keeps sending. The last test shows that limit; the agent's radio guard
(:mod:`radios.sik.guard`) is what notices the result.
"""

from __future__ import annotations

from radios.air import AirModel, RadioConfig
from radios.emulator_config import radio_config_of
from radios.sik.at import ATEngine
from radios.sik.param_table import NETID
from radios.sik.params import SikParams

KEY = "00112233445566778899aabbccddeeff"
OTHER_KEY = "ffeeddccbbaa99887766554433221100"


class AtBench:
    """Radios with real AT interpreters on the air model, driven in virtual time."""

    def __init__(self, params: list[SikParams], *, seed: int = 1) -> None:
        self.params = params
        self.t = 0.0
        self.out = [bytearray() for _ in params]
        self.model = AirModel(
            [radio_config_of(p) for p in params],
            seed=seed,
            at_factory=self._at,
            on_reboot=lambda i: radio_config_of(params[i]),
        )

    def _at(self, i: int, _cfg: RadioConfig) -> ATEngine:
        p = self.params[i]
        return ATEngine(
            p,
            flavour=p.flavour,
            board="RFD900P" if p.aes else "HM-TRP",
            ati6=str,
            ati7=str,
            node_id=i if p.flavour == "multipoint" else None,
        )

    def run(self, seconds: float, step: float = 0.01) -> None:
        end = self.t + seconds
        while self.t < end:
            self.t = min(end, self.t + step)
            self.model.advance(self.t)
            for i in range(len(self.params)):
                self.out[i] += self.model.take_output(i, self.t)

    def write(self, node: int, data: bytes) -> None:
        self.model.host_write(node, data, self.t)

    def command_mode(self, node: int) -> None:
        self.run(1.5)
        self.write(node, b"+++")
        self.run(1.5)
        assert b"OK\r\n" in self.out[node], "the radio never entered command mode"

    def send(self, node: int, line: str, wait: float = 1.0) -> None:
        self.write(node, line.encode() + b"\r")
        self.run(wait)

    def netid(self, node: int) -> tuple[int, int]:
        """(NETID saved in flash, NETID the radio runs with)."""
        p = self.params[node]
        return p.eeprom[NETID], p.active[NETID]


def aes_radio(key: str | None, level: int = 1) -> SikParams:
    """An AES build that booted with ``key`` at ``level`` (None: encryption off)."""
    p = SikParams(
        "standard",
        aes=True,
        stored={"ENCRYPTION_LEVEL": level if key else 0},
        stored_key=bytes.fromhex(key) if key else None,
    )
    return p


def attack(bench: AtBench, rogue: int, target: str = "", repeat: int = 3) -> None:
    """The rogue's host: command mode, then each remote command ``repeat`` times."""
    bench.command_mode(rogue)
    for line in ("RTS3=77", "RT&W", "RTZ"):
        for _ in range(repeat):
            bench.send(rogue, line + target)
    bench.run(2.0)


def locked_pair(bench: AtBench) -> None:
    bench.run(30.0)
    assert bench.model.status(0)["locked"] and bench.model.status(1)["locked"]


def test_rogue_moves_a_multipoint_radio_to_another_netid() -> None:
    # The hole as found: multipoint firmware, rogue node 2 on the swarm's NETID.
    params = [SikParams("multipoint", stored={"NODECOUNT": 3, "NODEID": i}) for i in range(3)]
    bench = AtBench(params)
    bench.run(5.0)
    attack(bench, rogue=2, target=",1")
    assert bench.netid(1) == (77, 77)
    assert bench.netid(0) == (25, 25)


def test_rogue_moves_a_standard_radio_without_encryption() -> None:
    params = [SikParams("standard") for _ in range(3)]
    bench = AtBench(params)
    bench.run(30.0)  # the rogue finds the hopping sequence like any radio
    attack(bench, rogue=2, repeat=10)  # three standard radios collide: it insists
    assert bench.netid(0) == (77, 77) or bench.netid(1) == (77, 77)


def test_a_rogue_on_another_netid_changes_nothing() -> None:
    params = [SikParams("standard"), SikParams("standard"), SikParams("standard", stored={"NETID": 26})]
    bench = AtBench(params)
    bench.run(30.0)
    attack(bench, rogue=2)
    assert bench.netid(0) == (25, 25) and bench.netid(1) == (25, 25)


def test_aes_pair_ignores_a_rogue_without_the_key() -> None:
    for rogue_key in (None, OTHER_KEY):
        params = [aes_radio(KEY), aes_radio(KEY), aes_radio(rogue_key)]
        bench = AtBench(params, seed=3)
        locked_pair(bench)
        attack(bench, rogue=2)
        assert bench.netid(0) == (25, 25), rogue_key
        assert bench.netid(1) == (25, 25), rogue_key


def test_aes_pair_still_carries_data_and_a_keyless_radio_hears_garbage() -> None:
    params = [aes_radio(KEY), aes_radio(KEY), aes_radio(None)]
    bench = AtBench(params, seed=3)
    locked_pair(bench)
    bench.write(0, b"hello swarm")
    bench.run(2.0)
    assert b"hello swarm" in bench.out[1]
    assert b"hello swarm" not in bench.out[2]


def test_a_rogue_with_the_key_reconfigures_the_radio() -> None:
    # Encryption is only as good as the key: a radio holding it is a member.
    params = [aes_radio(KEY), aes_radio(KEY), aes_radio(KEY)]
    bench = AtBench(params, seed=3)
    bench.run(30.0)
    attack(bench, rogue=2)
    assert bench.netid(0) == (77, 77) or bench.netid(1) == (77, 77)


def test_a_persistent_rogue_gets_through_aes_by_chance() -> None:
    # RT commands are not encrypted: a rogue that repeats them lands one on the
    # target's channel about once in NUM_CHANNELS packets. AES does not close the hole.
    params = [aes_radio(KEY), aes_radio(KEY), aes_radio(None)]
    bench = AtBench(params, seed=5)
    locked_pair(bench)
    bench.command_mode(2)
    for line in ("RTS3=77", "RT&W", "RTZ"):
        for _ in range(600):
            bench.send(2, line, wait=0.3)
    assert bench.netid(0)[0] == 77 or bench.netid(1)[0] == 77
