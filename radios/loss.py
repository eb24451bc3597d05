"""Packet loss on the emulated air, per receiver.

Theory of operation
-------------------
SiK radios lose whole packets (the firmware has no ACK and no retransmission), so loss is
decided once per (packet, receiver). Three models compose; a packet is lost if any
of them loses it:

* :class:`UniformLoss`: independent loss with probability p;
* :class:`GilbertElliott`: bursty loss, a two-state Markov chain per directed
  link (good/bad) stepped once per packet, with a loss probability in each state;
* :class:`RangeLoss`: loss and RSSI from the distance between the nodes, whose
  positions come from a callback or a JSON file that is re-read when it changes
  (``{"0": [x, y, z], "1": [...]}`` in metres, node index as key).

Every model draws from the ``random.Random`` it is given, so a seeded run is
exactly repeatable.
"""

from __future__ import annotations

import json
import math
import os
import random
from collections.abc import Callable
from dataclasses import dataclass, field

from radios.errors import ConfigError

Position = tuple[float, float, float]


@dataclass
class UniformLoss:
    p: float

    def __post_init__(self) -> None:
        if not 0.0 <= self.p <= 1.0:
            raise ConfigError(f"loss probability {self.p} is outside 0..1")

    def lost(self, sender: int, receiver: int, t: float, rng: random.Random) -> bool:
        return self.p > 0.0 and rng.random() < self.p


@dataclass
class GilbertElliott:
    """Bursty loss. ``p_gb``: chance per packet to go good->bad, ``p_bg``: bad->good;
    ``loss_good``/``loss_bad``: loss probability in each state. The mean burst
    length is 1/p_bg packets and the long-run share of time in the bad state is
    p_gb/(p_gb+p_bg)."""

    p_gb: float
    p_bg: float
    loss_good: float = 0.0
    loss_bad: float = 1.0
    _bad: dict[tuple[int, int], bool] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        for name in ("p_gb", "p_bg", "loss_good", "loss_bad"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"burst loss {name}={v} is outside 0..1")
        if self.p_bg == 0.0 and self.p_gb > 0.0:
            raise ConfigError("burst loss p_bg must be > 0 (otherwise a link never recovers)")

    @classmethod
    def parse(cls, spec: str) -> GilbertElliott:
        """``P_GB,P_BG[,LOSS_GOOD,LOSS_BAD]``, e.g. ``0.05,0.3``.

        Raises:
            ConfigError: malformed spec.
        """
        try:
            parts = [float(x) for x in spec.split(",")]
        except ValueError:
            raise ConfigError(f"burst loss {spec!r}: expected P_GB,P_BG[,LOSS_GOOD,LOSS_BAD]") from None
        if len(parts) not in (2, 4):
            raise ConfigError(f"burst loss {spec!r}: expected 2 or 4 numbers")
        if len(parts) == 2:
            return cls(parts[0], parts[1])
        return cls(parts[0], parts[1], parts[2], parts[3])

    def mean_loss(self) -> float:
        if self.p_gb + self.p_bg == 0:
            return self.loss_good
        bad = self.p_gb / (self.p_gb + self.p_bg)
        return bad * self.loss_bad + (1 - bad) * self.loss_good

    def lost(self, sender: int, receiver: int, t: float, rng: random.Random) -> bool:
        key = (sender, receiver)
        bad = self._bad.get(key, False)
        if bad:
            bad = rng.random() >= self.p_bg
        else:
            bad = rng.random() < self.p_gb
        self._bad[key] = bad
        p = self.loss_bad if bad else self.loss_good
        return p > 0.0 and rng.random() < p


class PositionFile:
    """Node positions from a JSON file, re-read when its mtime changes (checked at
    most every ``check_s`` seconds of model time)."""

    def __init__(self, path: str, check_s: float = 0.5) -> None:
        self.path = path
        self.check_s = check_s
        self._mtime = -1.0
        self._checked = -math.inf
        self._pos: dict[int, Position] = {}
        self._load()  # fail early on a bad file

    def _load(self) -> None:
        try:
            st = os.stat(self.path)
        except OSError as exc:
            raise ConfigError(f"positions file {self.path}: {exc.strerror}") from None
        if st.st_mtime == self._mtime:
            return
        try:
            with open(self.path, encoding="utf-8") as fh:
                raw = json.load(fh)
            pos = {
                int(k): (float(v[0]), float(v[1]), float(v[2]) if len(v) > 2 else 0.0) for k, v in raw.items()
            }
        except (OSError, ValueError, TypeError, IndexError, AttributeError) as exc:
            if self._pos:
                return  # keep the last good positions while a writer is mid-update
            raise ConfigError(f"positions file {self.path}: {exc}") from None
        self._pos = pos
        self._mtime = st.st_mtime

    def __call__(self, node: int, t: float) -> Position | None:
        if t - self._checked >= self.check_s:
            self._checked = t
            try:
                self._load()
            except ConfigError:
                pass
        return self._pos.get(node)


def sensitivity_dbm(air_kbps: int) -> float:
    """Receiver sensitivity of a Si1000-class radio: about -121 dBm at 2 kbps,
    3 dB worse per doubling of the air rate (-106 dBm at 64 kbps)."""
    return -121.0 + 10.0 * math.log10(max(air_kbps, 2) / 2.0)


@dataclass
class RangeLoss:
    """Loss and RSSI from distance.

    Received power: ``txpower_dbm`` plus antenna gains minus path loss, which is
    free-space (915 MHz) up to ``breakpoint_m`` and then grows with
    ``exponent`` (3 near the ground: terrain, bodies, multipath), minus a
    ``fade_margin_db``. The loss probability is a logistic curve of the margin
    over the receiver's sensitivity (50% at the sensitivity, ``slope_db`` wide).
    At 64 kbps and 20 dBm this puts the 50% point near 4 km, in line with the
    "several km" quoted for SiK radios with small antennas. Nodes without a known
    position are treated as close (no range loss)."""

    positions: Callable[[int, float], Position | None]
    txpower_dbm: float = 20.0
    freq_mhz: float = 915.0
    sensitivity_dbm: float = -106.0  # Si1000 at 64 kbps, see sensitivity_dbm()
    slope_db: float = 2.0
    antenna_gain_db: float = 4.0  # two 2 dBi whips
    breakpoint_m: float = 100.0
    exponent: float = 3.0
    fade_margin_db: float = 10.0

    def distance(self, a: int, b: int, t: float) -> float | None:
        pa, pb = self.positions(a, t), self.positions(b, t)
        if pa is None or pb is None:
            return None
        return math.dist(pa, pb)

    def path_loss_db(self, d: float) -> float:
        d = max(d, 1.0)
        near = min(d, self.breakpoint_m)
        fspl = 20 * math.log10(near / 1000.0) + 20 * math.log10(self.freq_mhz) + 32.44
        if d > self.breakpoint_m:
            fspl += 10 * self.exponent * math.log10(d / self.breakpoint_m)
        return fspl

    def rx_dbm(self, a: int, b: int, t: float) -> float | None:
        d = self.distance(a, b, t)
        if d is None:
            return None
        return self.txpower_dbm + self.antenna_gain_db - self.path_loss_db(d) - self.fade_margin_db

    def lost(self, sender: int, receiver: int, t: float, rng: random.Random) -> bool:
        p = self.rx_dbm(sender, receiver, t)
        if p is None:
            return False
        margin = p - self.sensitivity_dbm
        x = -margin / self.slope_db
        x = max(min(x, 60.0), -60.0)
        return rng.random() < 1.0 / (1.0 + math.exp(-x))


def dbm_to_rssi(dbm: float) -> int:
    """SiK RSSI units: dBm ~ RSSI/1.9 - 127 (ArduPilot's SiK radio documentation)."""
    return max(0, min(255, round((dbm + 127.0) * 1.9)))
