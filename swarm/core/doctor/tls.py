"""Verdicts on a node's TLS files for Zenoh over IP: the CA, its certificate, its key, the ACL.

Theory of operation
-------------------
A node on ``tls/`` endpoints holds the swarm CA's certificate (``--tls-ca``), its own
certificate (``--tls-cert``) and private key (``--tls-key``); a router or listening
node also the access-control file (``--zenoh-acl``, ``swarm router --acl``). The
probe (:mod:`swarm.runtime.keyspace.tls_probe`) reads them into :class:`TlsFacts` and
:class:`AclFacts`; :func:`tls_checks` and :func:`acl_check` judge them with ``now``:

* the CA: readable, a CA, valid now; a warning within :data:`SOON_S` of its end;
* the certificate: readable, signed by that CA, valid now (not expired, not yet
  valid: a clock behind), a warning within :data:`SOON_S` of its end; its name and
  role those of the node (the ACL grants by both: an agent holding another's
  certificate would have its own keys refused);
* the key: readable by this user only (mode 0600 or 0400), the certificate's key;
* the ACL: readable, Zenoh accepts it, access control on and denying by default.

A ``fail`` is what the node refuses to start with (:mod:`swarm.runtime.keyspace.tls`
uses these same verdicts), a ``warn`` is flyable. Pure: facts and ``now`` in.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from swarm.core.doctor import Check, fail, passed, warn
from swarm.core.doctor.host import utc_text

SOON_S = 30 * 86400  # a certificate ending within 30 days warns


@dataclass(frozen=True)
class CertFacts:
    """One certificate file: ``error`` why it could not be read (else empty), and
    what it says."""

    path: str
    error: str = ""
    name: str = ""
    role: str = ""
    issuer: str = ""
    not_before: float = 0.0
    not_after: float = 0.0
    is_ca: bool = False
    hosts: tuple[str, ...] = ()


@dataclass(frozen=True)
class TlsFacts:
    """A node's three TLS files. ``signed_by_ca``: the CA's key signed the
    certificate; ``key_matches``: the key is the certificate's; ``key_mode`` its
    permission bits; ``expect_name``/``expect_role`` what the node is (empty: any)."""

    ca: CertFacts
    cert: CertFacts
    key_path: str
    key_error: str = ""
    key_mode: int = 0
    signed_by_ca: bool = False
    key_matches: bool = False
    expect_name: str = ""
    expect_role: str = ""


def _validity(name: str, c: CertFacts, now: float, renew: str) -> Check:
    if now < c.not_before:
        return fail(
            name,
            f"{c.path}: not valid before {utc_text(c.not_before)} (the clock reads {utc_text(now)})",
            "set the clock (NTP: timedatectl set-ntp true), or make the certificate again",
        )
    if now >= c.not_after:
        return fail(name, f"{c.path}: expired {utc_text(c.not_after)}", renew)
    days = (c.not_after - now) / 86400
    if c.not_after - now < SOON_S:
        return warn(name, f"{c.path}: expires {utc_text(c.not_after)} (in {days:.0f} days)", renew)
    return passed(name, f"{c.path}: {c.name or c.issuer} until {utc_text(c.not_after)}")


def tls_checks(f: TlsFacts, now: float) -> list[Check]:
    """The TLS files' checks (see the module docstring)."""
    out: list[Check] = []
    ca = f.ca
    if ca.error:
        out.append(fail("tls ca", ca.error, "copy the swarm's ca.pem here (swarm certs ca makes it)"))
    elif not ca.is_ca:
        out.append(
            fail("tls ca", f"{ca.path}: not a CA's certificate", "give the swarm's ca.pem as --tls-ca")
        )
    else:
        out.append(
            _validity("tls ca", ca, now, "make a new CA and new certificates for every node (swarm certs)")
        )
    c = f.cert
    renew = (
        f"swarm certs node DIR {c.name or 'NAME'} --role {c.role or 'ROLE'} (after moving the old files away)"
    )
    if c.error:
        out.append(fail("tls cert", c.error, "copy this node's NAME.pem here (swarm certs node makes it)"))
    elif not ca.error and not f.signed_by_ca:
        out.append(
            fail(
                "tls cert",
                f"{c.path}: not signed by {ca.path} (another CA's)",
                "give the certificate the swarm's CA made for this node, and the swarm's ca.pem",
            )
        )
    else:
        out.append(_validity("tls cert", c, now, renew))
        out += _identity(f)
    out += _key_checks(f)
    return out


def _identity(f: TlsFacts) -> list[Check]:
    c = f.cert
    if f.expect_name and c.name != f.expect_name:
        return [
            fail(
                "tls name",
                f"{c.path} names {c.name!r}, but this node is {f.expect_name!r}: its own keys would be "
                "refused",
                f"give {f.expect_name}'s certificate, or make one: swarm certs node DIR "
                f"{f.expect_name} --role {f.expect_role or c.role}",
            )
        ]
    if f.expect_role and c.role != f.expect_role:
        return [
            fail(
                "tls role",
                f"{c.path}: role {c.role!r}, but this node is {f.expect_role!r}",
                f"make one for a {f.expect_role}: swarm certs node DIR {c.name} --role {f.expect_role}",
            )
        ]
    return [passed("tls name", f"{c.name} ({c.role})")] if f.expect_name or f.expect_role else []


def _key_checks(f: TlsFacts) -> list[Check]:
    if f.key_error:
        return [fail("tls key", f.key_error, "copy this node's NAME.key here, mode 0600 (scp -p)")]
    out = []
    perm = f.key_mode & 0o777
    if perm & 0o077:
        who = "others" if perm & 0o007 else "its group"
        out.append(
            fail(
                "tls key mode", f"{f.key_path}: mode {perm:04o}: readable by {who}", f"chmod 600 {f.key_path}"
            )
        )
    else:
        out.append(passed("tls key mode", f"{f.key_path}: mode {perm:04o}"))
    if not f.cert.error and not f.key_matches:
        out.append(
            fail(
                "tls key",
                f"{f.key_path} is not the key of {f.cert.path}",
                "give the key file made with the certificate (NAME.key beside NAME.pem)",
            )
        )
    elif not f.cert.error:
        out.append(passed("tls key", f"{f.key_path}: the certificate's key"))
    return out


@dataclass(frozen=True)
class AclFacts:
    """The access-control file: ``error`` why it could not be read or Zenoh refused it;
    ``enabled``, ``default`` (permission) and the number of ``subjects`` it names."""

    path: str
    error: str = ""
    enabled: bool = False
    default: str = ""
    subjects: int = 0


def acl_check(f: AclFacts) -> Check:
    if f.error:
        return fail("zenoh acl", f.error, "make it again: swarm certs acl DIR")
    if not f.enabled:
        return warn(
            "zenoh acl", f"{f.path}: access control not enabled", 'set "enabled": true (swarm certs acl)'
        )
    if f.default != "deny":
        return warn(
            "zenoh acl",
            f"{f.path}: allows by default: any certificate of the CA may do anything not listed",
            'set "default_permission": "deny" (swarm certs acl does)',
        )
    return passed("zenoh acl", f"{f.path}: {f.subjects} certificates named, default deny")


def failures(checks: Sequence[Check]) -> list[Check]:
    return [c for c in checks if c.status == "fail"]


__all__ = ["SOON_S", "AclFacts", "CertFacts", "TlsFacts", "acl_check", "failures", "tls_checks"]
