"""What a node is given: where it meets the others, and how an agent behaves.

Theory of operation
-------------------
:class:`NodeOptions` is a node's way into the key space, the same for an agent and
a ground station: exactly one of a radio (a link URL, or a link the caller already
opened) or Zenoh endpoints (listen and/or connect, with :class:`TlsFiles` for
``tls/`` ones and an access-control file for a listener), and the swarm's signing
key file. Its constructor is the one place that checks "a radio or Zenoh, not both";
the command line builds one from its shared node options
(:func:`swarm.cli.util.add_node_arguments`) and turns the ValueError into a usage
error.

:class:`AgentConfig` is how an agent behaves: its timing profile and TDM round,
its vote policy, its pose rate, how long it waits for a flight controller, a seed
for its random draws and its pilot's settings. Both are plain frozen data, checked
when built, with no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from swarm.core.election.caps import check_cap
from swarm.core.election.profiles import PROFILE_NAMES
from swarm.core.flight.pilot import PilotConfig
from swarm.core.wire.message_types import NAME_RE

if TYPE_CHECKING:
    from radios.link import Link

VOTES = ("random", "battery", "link")
PROFILES = PROFILE_NAMES


@dataclass(frozen=True)
class TlsFiles:
    """Mutual TLS for ``tls/`` Zenoh endpoints: the swarm CA's certificate, this
    node's certificate and private key (``swarm certs``); ``name`` and ``role`` what
    the certificate must say this node is ("": not checked)."""

    ca: str
    cert: str
    key: str
    name: str = ""
    role: str = ""


@dataclass(frozen=True)
class NodeOptions:
    """Where a node meets the others: ``radio`` (a link URL: serial device, emulator
    pty...), ``link`` (a :class:`radios.link.Link` already open: the node bridges it
    but does not close it, its opener does), or Zenoh endpoints to listen on and
    connect to. ``key_file``: the swarm's signing key for the radio's frames;
    ``signing_state``: the file that keeps the node's signing clock across restarts
    (:mod:`radios.signing_state`; None: none kept, replays refused from the wall clock
    at start only). ``tls``: the certificates of ``tls/`` endpoints; ``acl_file``:
    Zenoh's access control for the nodes that connect to this one's listen endpoints.

    Raises:
        ValueError: none or more than one way in.
    """

    radio: str | None = None
    link: Link | None = None
    zenoh_listen: Sequence[str] = ()
    zenoh_connect: Sequence[str] = ()
    key_file: str | None = None
    signing_state: str | None = None
    tls: TlsFiles | None = None
    acl_file: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "zenoh_listen", tuple(self.zenoh_listen))
        object.__setattr__(self, "zenoh_connect", tuple(self.zenoh_connect))
        if self.radio is not None and self.link is not None:
            raise ValueError("give a radio URL or an open link, not both")
        if self.on_radio and self.on_zenoh:
            raise ValueError("a node meets others either through a radio or over Zenoh endpoints")
        if not (self.on_radio or self.on_zenoh):
            raise ValueError("give a radio or at least one Zenoh endpoint (listen or connect)")

    @property
    def on_radio(self) -> bool:
        return self.radio is not None or self.link is not None

    @property
    def on_zenoh(self) -> bool:
        return bool(self.zenoh_listen or self.zenoh_connect)

    @property
    def radio_url(self) -> str | None:
        """The radio's URL (an open link's own), None over Zenoh."""
        return self.link.url if self.link is not None else self.radio

    def describe(self) -> str:
        """Where the node meets others, for a ready line: ``radio=URL`` or ``zenoh ...``."""
        if self.on_radio:
            return f"radio={self.radio_url}"
        parts = []
        if self.zenoh_listen:
            parts.append("listen=" + ",".join(self.zenoh_listen))
        if self.zenoh_connect:
            parts.append("connect=" + ",".join(self.zenoh_connect))
        return "zenoh " + " ".join(parts)


@dataclass(frozen=True)
class AgentConfig:
    """How an agent behaves (see :mod:`swarm.runtime.agent.live`): ``profile`` ``paper``,
    ``fast`` or ``tdm`` (the last two: windows from ``round_s``, the radio network's TDM round: None for a
    SiK pair at 64 kbit/s), ``vote`` ``random``, ``battery`` or ``link``, ``pose_hz``
    with a flight controller, ``fc_timeout`` to hear it first, ``seed`` for the random
    draws (None: unseeded), ``pilot`` the formation and flight settings and the
    geofence (:class:`~swarm.core.flight.geofence.Geofence`, ``pilot.fence``), ``swarm_cap``
    the most agents in its swarm (0: no cap; :mod:`swarm.core.election.caps`), ``swarm_name``
    the only swarm name it pools with ("": agents without one).

    Raises:
        ValueError: an unknown profile or vote, a round, pose rate or cap out of range.
    """

    profile: str = "paper"
    round_s: float | None = None
    vote: str = "random"
    pose_hz: float = 4.0
    fc_timeout: float = 10.0
    seed: int | None = None
    pilot: PilotConfig = field(default_factory=PilotConfig)
    swarm_cap: int = 0  # the most agents in its swarm (swarm.core.election.caps); 0: no cap
    swarm_name: str = ""  # pools only with agents of this swarm name; "": with unnamed ones

    def __post_init__(self) -> None:
        if self.vote not in VOTES:
            raise ValueError(f"unknown vote policy {self.vote!r}: {', '.join(VOTES)}")
        if self.profile not in PROFILES:
            raise ValueError(f"unknown profile {self.profile!r}: {', '.join(PROFILES)}")
        r = self.round_s
        if r is not None and not (math.isfinite(r) and r > 0):
            raise ValueError(f"round_s {r!r} must be a positive number of seconds")
        if not (math.isfinite(self.pose_hz) and 0 < self.pose_hz <= 50):
            raise ValueError(f"pose_hz {self.pose_hz!r} must be in (0, 50]")
        check_cap(self.swarm_cap)
        if self.swarm_name and not NAME_RE.match(self.swarm_name):
            raise ValueError(f"swarm_name {self.swarm_name!r}: 1 to 16 letters, digits, '_' or '-'")


__all__ = ["PROFILES", "VOTES", "AgentConfig", "NodeOptions", "TlsFiles"]
