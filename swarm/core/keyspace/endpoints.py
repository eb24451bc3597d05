"""What a node's Zenoh endpoints expose, and what a signing key can and cannot cover.

Theory of operation
-------------------
The swarm key (``--key``) signs the radio's MAVLink frames and the stations'
envelopes; it does nothing for a Zenoh link over IP, which anyone who reaches the
endpoint may join. Zenoh's own mutual TLS (``tls/`` endpoints with certificates,
:mod:`swarm.runtime.keyspace.pki`) and access control (:mod:`swarm.core.keyspace.acl`) are what
authenticate and authorise a node there. :func:`endpoint_kind` sorts an endpoint
into ``tls`` (Zenoh's TLS or QUIC: authenticated when certificates are given),
``local`` (loopback or a Unix socket: only this machine's users reach it) or
``plain`` (TCP, UDP or WebSocket beyond loopback: anyone on the network).

:func:`key_over_ip` is the rule for a node given the key and Zenoh endpoints: a
``plain`` endpoint refuses to start (the key would promise what it cannot keep), a
``local`` one starts with one warning, ``tls`` ones say nothing. A node without the
key promises nothing and is not judged here. :func:`tls_needed` names what a ``tls``
endpoint lacks (its certificates). Pure: no I/O, no name resolution (a host name
other than ``localhost`` is taken as beyond loopback).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

EndpointKind = Literal["tls", "local", "plain"]

#: Zenoh link protocols authenticated by TLS (with certificates)
TLS_PROTOCOLS = frozenset({"tls", "quic"})
#: link protocols only this machine reaches
LOCAL_PROTOCOLS = frozenset({"unixsock-stream", "unixpipe"})


def endpoint_host(endpoint: str) -> tuple[str, str]:
    """``(protocol, host)`` of ``tcp/127.0.0.1:7447`` (brackets of an IPv6 address
    dropped; the host is ``""`` when there is none to find)."""
    proto, _sep, rest = endpoint.partition("/")
    address = rest.split("?", 1)[0].split("#", 1)[0]
    host, colon, _port = address.rpartition(":")
    return proto.strip().lower(), (host if colon else address).strip("[]").lower()


def is_loopback(host: str) -> bool:
    if host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def endpoint_kind(endpoint: str) -> EndpointKind:
    """See the module docstring."""
    proto, host = endpoint_host(endpoint)
    if proto in TLS_PROTOCOLS:
        return "tls"
    if proto in LOCAL_PROTOCOLS or is_loopback(host):
        return "local"
    return "plain"


@dataclass(frozen=True)
class Verdict:
    """``refuse`` (one line, exit 2) or ``warn`` (one line, the node starts)."""

    level: Literal["refuse", "warn"]
    text: str


#: where the user is sent for certificates
CERTS_HINT = "use tls/ endpoints with certificates (swarm certs; docs/security.md, Zenoh over IP)"


def key_over_ip(endpoints: Sequence[str], *, has_key: bool) -> Verdict | None:
    """The rule for a node given the swarm key and these Zenoh endpoints (see the
    module docstring); None: nothing to say."""
    if not has_key or not endpoints:
        return None
    plain = [ep for ep in endpoints if endpoint_kind(ep) == "plain"]
    if plain:
        return Verdict(
            "refuse",
            f"--key signs radio frames, not Zenoh over IP: {', '.join(plain)} is open to anyone "
            f"on the network, without a key; {CERTS_HINT}",
        )
    local = [ep for ep in endpoints if endpoint_kind(ep) == "local"]
    if local:
        return Verdict(
            "warn",
            f"warning: --key does not cover Zenoh: {', '.join(local)} is reached by every user of "
            f"this machine, without a key; beyond loopback {CERTS_HINT}",
        )
    return None


def tls_needed(endpoints: Sequence[str], *, has_ca: bool, has_cert: bool, has_key: bool) -> str | None:
    """What is missing for these endpoints' TLS (one line), or None. A ``tls/``
    endpoint needs the CA's certificate and this node's certificate and key (mutual
    TLS: each side proves itself); certificates without a ``tls/`` endpoint are a
    mistake too (the user meant TLS and would get none)."""
    tls = [ep for ep in endpoints if endpoint_kind(ep) == "tls"]
    given = has_ca or has_cert or has_key
    if tls and not (has_ca and has_cert and has_key):
        missing = [
            f for f, ok in (("--tls-ca", has_ca), ("--tls-cert", has_cert), ("--tls-key", has_key)) if not ok
        ]
        return (
            f"{tls[0]} needs {', '.join(missing)} (mutual TLS: the swarm CA's certificate, this node's own)"
        )
    if given and not tls:
        return (
            "--tls-ca/--tls-cert/--tls-key are for tls/ endpoints: give --zenoh-listen or "
            "--zenoh-connect tls/HOST:PORT"
        )
    if given and len(tls) != len(endpoints):
        plain = [ep for ep in endpoints if endpoint_kind(ep) != "tls"]
        return f"{', '.join(plain)} would bypass the certificates: make every endpoint tls/"
    return None


__all__ = [
    "CERTS_HINT",
    "EndpointKind",
    "Verdict",
    "endpoint_host",
    "endpoint_kind",
    "is_loopback",
    "key_over_ip",
    "tls_needed",
]
