"""Errors of the swarm layer.

Every error raised on purpose by ``swarm`` derives from :class:`SwarmError`.
:class:`DecodeError` says a peer sent bytes that are not a valid message (the peer's
fault); :class:`MessageError` says we tried to build an invalid message (our own);
:class:`VersionMismatch` says the peer speaks another protocol version.
"""

from __future__ import annotations


class SwarmError(Exception):
    """Base of every error the swarm layer raises on purpose."""


class MessageError(SwarmError, ValueError):
    """A message we tried to build has an invalid field (our own misuse)."""


class DecodeError(SwarmError, ValueError):
    """Bytes received are not exactly one valid swarm message (the peer's fault)."""


class VersionMismatch(DecodeError):
    """The peer speaks another version of the swarm protocol."""

    def __init__(self, theirs: int, ours: int) -> None:
        super().__init__(
            f"peer speaks swarm protocol v{theirs}, this agent speaks v{ours}: upgrade one of them"
        )
        self.theirs = theirs
        self.ours = ours


class TransportError(SwarmError):
    """The Zenoh session or the radio bridge cannot do what was asked."""


class CertError(SwarmError):
    """A certificate, private key or access-control file is missing, malformed,
    expired, unsafe or not of this swarm (the user's input: exit 2)."""
