"""Probes of a node's TLS files and its Zenoh access-control file (facts, no verdicts).

:func:`tls_facts` reads the CA's certificate, the node's certificate and private key
(:mod:`swarm.runtime.keyspace.pki`: regular files of at most 64 KiB, read without blocking) and
notes what they say, whether the CA signed the certificate and whether the key is the
certificate's; :func:`acl_facts` hands the access-control file to Zenoh's own parser
(it is JSON5) and notes what it says. Nothing is judged here
(:mod:`swarm.core.doctor.tls`), nothing raises for what is found.
"""

from __future__ import annotations

import json
import os
import stat

from swarm.core.doctor.tls import AclFacts, CertFacts, TlsFacts
from swarm.errors import CertError

ACL_MAX = 4 * 1024 * 1024  # bytes: a swarm of 250 agents' rules take ~0.4 MB


def _cert(path: str) -> tuple[CertFacts, object | None]:
    from swarm.runtime.keyspace.pki import cert_info, load_cert

    try:
        cert = load_cert(path)
    except CertError as exc:
        return CertFacts(path, error=str(exc)), None
    i = cert_info(cert)
    return CertFacts(path, "", i.name, i.role, i.issuer, i.not_before, i.not_after, i.is_ca, i.hosts), cert


def tls_facts(ca: str, cert: str, key: str, *, expect_name: str = "", expect_role: str = "") -> TlsFacts:
    """What the three files are (see the module docstring)."""
    from swarm.runtime.keyspace.pki import key_matches, load_key, signed_by

    ca_facts, ca_cert = _cert(ca)
    cert_facts, node_cert = _cert(cert)
    signed = ca_cert is not None and node_cert is not None and signed_by(node_cert, ca_cert)  # type: ignore[arg-type]
    try:
        mode = os.stat(key).st_mode
    except (OSError, ValueError):
        mode = 0
    try:
        private = load_key(key)
    except CertError as exc:
        return TlsFacts(ca_facts, cert_facts, key, str(exc), mode, signed, False, expect_name, expect_role)
    matches = node_cert is not None and key_matches(private, node_cert)  # type: ignore[arg-type]
    return TlsFacts(ca_facts, cert_facts, key, "", mode, signed, matches, expect_name, expect_role)


def read_acl(path: str) -> str:
    """The access-control file's text. Raises CertError (missing, not a file, too big,
    not UTF-8)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except (FileNotFoundError, ValueError):
        raise CertError(f"{path}: no such access-control file") from None
    except OSError as exc:
        raise CertError(f"{path}: cannot read the access-control file: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise CertError(f"{path}: not a regular file (give the access-control file)")
        if st.st_size > ACL_MAX:
            raise CertError(f"{path}: {st.st_size} bytes: not an access-control file")
        with os.fdopen(os.dup(fd), "rb") as fh:
            return fh.read(ACL_MAX + 1).decode("utf-8")
    except UnicodeDecodeError:
        raise CertError(f"{path}: not text (UTF-8)") from None
    except OSError as exc:
        raise CertError(f"{path}: cannot read the access-control file: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def parse_acl(path: str, text: str) -> dict[str, object]:
    """The ``access_control`` section as Zenoh reads it (JSON5). Raises CertError with
    Zenoh's own reason."""
    import zenoh

    from swarm.core.keyspace.zenoh_errors import zenoh_config_message

    cfg = zenoh.Config()
    try:
        cfg.insert_json5("access_control", text)
        value = cfg.get_json("access_control")
    except Exception as exc:
        detail = zenoh_config_message(str(exc)).removeprefix("bad Zenoh endpoint: ").split(" (for example")[0]
        raise CertError(f"{path}: Zenoh refuses it: {detail}") from None
    obj = json.loads(value) if isinstance(value, str) else value
    if not isinstance(obj, dict):
        raise CertError(f"{path}: not an access_control object")
    return obj


def acl_facts(path: str) -> AclFacts:
    try:
        obj = parse_acl(path, read_acl(path))
    except CertError as exc:
        return AclFacts(path, error=str(exc))
    subjects = obj.get("subjects")
    return AclFacts(
        path,
        enabled=obj.get("enabled") is True,
        default=str(obj.get("default_permission", "deny")),
        subjects=len(subjects) if isinstance(subjects, list) else 0,
    )


__all__ = ["acl_facts", "parse_acl", "read_acl", "tls_facts"]
