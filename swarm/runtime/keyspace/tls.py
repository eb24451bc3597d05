"""A Zenoh session's mutual TLS and access control, from the swarm's files.

Theory of operation
-------------------
:func:`check_tls` reads a node's CA certificate, certificate and key before its
session opens and refuses, with one line (:class:`~swarm.errors.CertError`, exit 2),
what ``swarm doctor`` would fail (:func:`swarm.core.doctor.tls.tls_checks`): a file
missing or unreadable, a key others can read, a key not the certificate's, a
certificate of another CA, expired or not yet valid, or naming another node. Zenoh
would refuse most of these too, but at the other end, silently for this node, which
would then try for ever. :func:`apply` writes the files' paths into a Zenoh config:
the CA to check the other side with, this node's certificate and key for both sides
of a link (``listen_*`` when it listens, ``connect_*`` when it connects), client
certificates required (``enable_mtls``), links closed when the other side's
certificate expires (``close_link_on_expiration``), only the ``tls`` and ``quic``
protocols; and the access-control section (:func:`load_acl`: the file as Zenoh
reads it) when one is given.
"""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING, Any

from swarm.core.doctor.tls import failures, tls_checks
from swarm.errors import CertError

if TYPE_CHECKING:
    from swarm.runtime.options import TlsFiles


def check_tls(tls: TlsFiles, now: float | None = None) -> None:
    """Raise CertError with the first failing check's line (``seen; fix: ...``)."""
    from swarm.runtime.keyspace.tls_probe import tls_facts

    facts = tls_facts(tls.ca, tls.cert, tls.key, expect_name=tls.name, expect_role=tls.role)
    bad = failures(tls_checks(facts, time.time() if now is None else now))
    if bad:
        raise CertError(f"{bad[0].seen}; fix: {bad[0].fix}")


def load_acl(path: str) -> str:
    """The access-control file's text once Zenoh accepts it. Raises CertError."""
    from swarm.runtime.keyspace.tls_probe import parse_acl, read_acl

    text = read_acl(path)
    obj = parse_acl(path, text)
    if obj.get("enabled") is not True:
        raise CertError(f'{path}: access control is not enabled ("enabled": true): nothing would be checked')
    return text


def apply(cfg: Any, tls: TlsFiles, *, listening: bool, acl_text: str | None = None) -> None:
    """Write ``tls`` (and ``acl_text``) into the Zenoh config ``cfg`` (see the module
    docstring). Raises what ``cfg.insert_json5`` raises."""
    base = "transport/link/tls"
    cfg.insert_json5(f"{base}/root_ca_certificate", json.dumps(tls.ca))
    cfg.insert_json5(f"{base}/enable_mtls", "true")
    cfg.insert_json5(f"{base}/connect_certificate", json.dumps(tls.cert))
    cfg.insert_json5(f"{base}/connect_private_key", json.dumps(tls.key))
    if listening:
        cfg.insert_json5(f"{base}/listen_certificate", json.dumps(tls.cert))
        cfg.insert_json5(f"{base}/listen_private_key", json.dumps(tls.key))
    cfg.insert_json5(f"{base}/close_link_on_expiration", "true")
    cfg.insert_json5("transport/link/protocols", json.dumps(["tls", "quic"]))
    if acl_text is not None:
        cfg.insert_json5("access_control", acl_text)


__all__ = ["apply", "check_tls", "load_acl"]
