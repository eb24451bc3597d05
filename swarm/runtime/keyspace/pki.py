"""The swarm's certificates: a CA of its own, one certificate per node, the ACL file.

Theory of operation
-------------------
Zenoh over IP is authenticated with mutual TLS: every node (agent, station, router)
holds a certificate signed by the swarm's own certificate authority and proves it
holds the key; each side checks the other's against the CA's certificate. This
module makes and reads them with the ``cryptography`` package:

* :func:`make_ca` writes ``ca.key`` (the CA's private key: it signs new nodes, and
  stays on the machine where certificates are made) and ``ca.pem`` (its certificate:
  every node gets a copy). ECDSA P-256, self-signed, a CA for end certificates only
  (path length 0).
* :func:`issue` writes ``NAME.key`` and ``NAME.pem`` for one node: the subject's
  common name (CN) is the node's name, its organisational unit (OU) its role
  (``agent``, ``station`` or ``router``: :mod:`swarm.core.keyspace.acl` grants by both),
  the subject alternative names the name and any ``hosts`` (addresses or DNS names
  others connect to: a router's, a listening station's; Zenoh checks the name a
  client connects to), for server and client authentication both.
* :func:`nodes` lists the nodes whose certificates in a folder the CA signed;
  :func:`write_acl` writes ``acl.json5`` from them (Zenoh's ``access_control``).

Private keys are created with ``O_CREAT | O_EXCL | O_NOFOLLOW``, mode exactly 0600,
written and ``fsync``'d; nothing existing is ever overwritten (a key, a certificate);
a failure removes what was half written. The ACL file is derived, so it is replaced
(written beside, then renamed). Reading is careful too: at most :data:`MAX_PEM`
bytes, a regular file, one line for whatever is wrong (:class:`~swarm.errors.CertError`).
``now`` (Unix seconds) is passed in, so an expired certificate can be made on purpose.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import ipaddress
import json
import os
import stat
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from swarm.core.keyspace.acl import ROLES, Node, acl
from swarm.errors import CertError, SwarmError

CA_KEY, CA_CERT, ACL_FILE = "ca.key", "ca.pem", "acl.json5"
MAX_PEM = 64 * 1024  # bytes: a larger "certificate" is something else
CA_DAYS = 3650
NODE_DAYS = 365
SKEW_S = 300  # a certificate is valid from 5 minutes before it was made: clocks differ


class CertWriteError(SwarmError):
    """A file could not be written (a full disk, an I/O error): nothing is left behind."""


# -- writing ------------------------------------------------------------------------------


def _write_new(path: Path, data: bytes, mode: int) -> None:
    """Create ``path`` (never overwrite) with exactly ``mode``, write, fsync."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(path, flags, mode)
    except FileExistsError:
        raise CertError(f"{path} exists: never overwritten (remove it first to replace it)") from None
    except (FileNotFoundError, NotADirectoryError):
        raise CertError(f"{path}: the folder {path.parent} does not exist (create it first)") from None
    except OSError as exc:
        raise CertError(f"{path}: {exc.strerror or exc}") from None
    try:
        os.fchmod(fd, mode)
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    except BaseException as exc:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(path)
        if isinstance(exc, OSError):
            raise CertWriteError(f"{path}: {exc.strerror or exc}: nothing written") from None
        raise
    os.close(fd)


def _sync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems cannot sync a folder
    finally:
        os.close(fd)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _utc(t: float) -> dt.datetime:
    return dt.datetime.fromtimestamp(t, dt.UTC)


def _write_pair(
    folder: Path, stem: str, key: ec.EllipticCurvePrivateKey, cert: x509.Certificate
) -> tuple[Path, Path]:
    key_path, cert_path = folder / f"{stem}.key", folder / f"{stem}.pem"
    for p in (key_path, cert_path):  # both refused before either is written
        if os.path.lexists(p):
            raise CertError(f"{p} exists: never overwritten (remove it first to replace it)")
    _write_new(key_path, _key_pem(key), 0o600)
    try:
        _write_new(cert_path, _cert_pem(cert), 0o644)
    except BaseException:
        with contextlib.suppress(OSError):
            key_path.unlink()
        raise
    _sync_folder(folder)
    return key_path, cert_path


def make_ca(
    folder: str | Path, *, now: float, days: int = CA_DAYS, name: str = "uav-swarm CA"
) -> tuple[Path, Path]:
    """Write ``ca.key`` and ``ca.pem`` in ``folder`` (which must exist); returns their
    paths. Raises CertError (a file exists, no folder) or CertWriteError."""
    folder = Path(folder)
    if days < 1:
        raise CertError(f"--days {days}: at least 1")
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(_utc(now - SKEW_S))
        .not_valid_after(_utc(now + days * 86400))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return _write_pair(folder, "ca", key, cert)


def _san(name: str, hosts: Sequence[str]) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = [x509.DNSName(name)]
    for h in hosts:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(h.strip("[]"))))
        except ValueError:
            if not h or any(c.isspace() or c in "/:@" for c in h):
                raise CertError(f"--host {h!r}: an IP address or a DNS name") from None
            out.append(x509.DNSName(h))
    return out


def issue(
    folder: str | Path,
    name: str,
    role: str,
    *,
    now: float,
    hosts: Sequence[str] = (),
    days: int = NODE_DAYS,
    valid_from: float | None = None,
) -> tuple[Path, Path]:
    """Write ``NAME.key`` and ``NAME.pem`` in ``folder``, signed by its CA (see the
    module docstring); ``valid_from`` (default ``now`` less 5 minutes) and ``days``
    give the validity. Returns the paths. Raises CertError or CertWriteError."""
    folder = Path(folder)
    try:
        Node(name, role)
    except ValueError as exc:
        raise CertError(str(exc)) from None
    if name == "ca":
        raise CertError("'ca' is the authority's own file name: give the node another name")
    if days < 1:
        raise CertError(f"--days {days}: at least 1")
    ca_key = load_key(folder / CA_KEY)
    ca_cert = load_cert(folder / CA_CERT)
    start = now - SKEW_S if valid_from is None else valid_from
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name(
        [
            x509.NameAttribute(NameOID.COMMON_NAME, name),
            x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, role),
        ]
    )
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(_utc(start))
        .not_valid_after(_utc(start + days * 86400))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(_san(name, hosts)), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    return _write_pair(folder, name, key, cert)


# -- reading ------------------------------------------------------------------------------


def _read(path: str | Path, what: str) -> bytes:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except (FileNotFoundError, ValueError):
        raise CertError(f"{path}: no such {what} file") from None
    except OSError as exc:
        raise CertError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise CertError(f"{path}: not a regular file (give the {what} file)")
        if st.st_size > MAX_PEM:
            raise CertError(f"{path}: {st.st_size} bytes: not a {what} file")
        with os.fdopen(os.dup(fd), "rb") as fh:
            return fh.read(MAX_PEM + 1)
    except OSError as exc:
        raise CertError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def load_cert(path: str | Path) -> x509.Certificate:
    """The PEM certificate at ``path``. Raises CertError."""
    data = _read(path, "certificate")
    try:
        return x509.load_pem_x509_certificate(data)
    except ValueError:
        raise CertError(f"{path}: not a PEM certificate") from None


def load_key(path: str | Path) -> ec.EllipticCurvePrivateKey:
    """The PEM private key at ``path`` (unencrypted, elliptic curve). Raises CertError."""
    data = _read(path, "private key")
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError):
        raise CertError(f"{path}: not an unencrypted PEM private key") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise CertError(f"{path}: not an elliptic-curve key (swarm certs makes P-256 keys)")
    return key


def _attr(name: x509.Name, oid: x509.ObjectIdentifier) -> str:
    values = name.get_attributes_for_oid(oid)
    return str(values[0].value) if values else ""


@dataclass(frozen=True)
class CertInfo:
    """What a certificate says: its name (CN), role (OU), issuer, validity (Unix
    seconds), whether it is a CA, its alternative names."""

    name: str
    role: str
    issuer: str
    not_before: float
    not_after: float
    is_ca: bool
    hosts: tuple[str, ...]


def cert_info(cert: x509.Certificate) -> CertInfo:
    try:
        is_ca = bool(cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca)
    except x509.ExtensionNotFound:
        is_ca = False
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        hosts = tuple(
            [*san.get_values_for_type(x509.DNSName), *map(str, san.get_values_for_type(x509.IPAddress))]
        )
    except x509.ExtensionNotFound:
        hosts = ()
    return CertInfo(
        _attr(cert.subject, NameOID.COMMON_NAME),
        _attr(cert.subject, NameOID.ORGANIZATIONAL_UNIT_NAME),
        _attr(cert.issuer, NameOID.COMMON_NAME),
        cert.not_valid_before_utc.timestamp(),
        cert.not_valid_after_utc.timestamp(),
        is_ca,
        hosts,
    )


def signed_by(cert: x509.Certificate, ca: x509.Certificate) -> bool:
    """True when ``ca``'s key signed ``cert`` (and names it as issuer)."""
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def key_matches(key: Any, cert: x509.Certificate) -> bool:
    der = serialization.Encoding.DER
    spki = serialization.PublicFormat.SubjectPublicKeyInfo
    return bool(key.public_key().public_bytes(der, spki) == cert.public_key().public_bytes(der, spki))


# -- the nodes a CA signed, and their ACL ---------------------------------------------------


def nodes(folder: str | Path) -> tuple[list[Node], list[str]]:
    """The nodes whose certificates (``*.pem`` but ``ca.pem``) in ``folder`` its CA
    signed, with a role, and one line for each other certificate skipped."""
    folder = Path(folder)
    ca = load_cert(folder / CA_CERT)
    found: list[Node] = []
    skipped: list[str] = []
    for path in sorted(folder.glob("*.pem")):
        if path.name == CA_CERT:
            continue
        try:
            cert = load_cert(path)
        except CertError as exc:
            skipped.append(str(exc))
            continue
        info = cert_info(cert)
        if not signed_by(cert, ca):
            skipped.append(f"{path}: not signed by {folder / CA_CERT}")
        elif info.role not in ROLES:
            skipped.append(f"{path}: no swarm role (OU {info.role!r})")
        else:
            try:
                found.append(Node(info.name, info.role))
            except ValueError as exc:
                skipped.append(f"{path}: {exc}")
    return found, skipped


def acl_text(members: Iterable[Node]) -> str:
    """The ACL file's text: the ``access_control`` section, JSON (which is JSON5)."""
    return json.dumps(acl(members), indent=1) + "\n"


def write_acl(folder: str | Path, members: Iterable[Node], out: str | Path | None = None) -> Path:
    """Write (replace) the ACL file, ``folder/acl.json5`` unless ``out``; mode 0644.
    Raises CertError (no folder, duplicate names) or CertWriteError."""
    path = Path(out) if out is not None else Path(folder) / ACL_FILE
    try:
        text = acl_text(members)
    except ValueError as exc:
        raise CertError(str(exc)) from None
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    _write_new(tmp, text.encode(), 0o644)
    try:
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise CertWriteError(f"{path}: {exc.strerror or exc}") from None
    _sync_folder(path.parent)
    return path


__all__ = [
    "ACL_FILE",
    "CA_CERT",
    "CA_KEY",
    "CertInfo",
    "CertWriteError",
    "acl_text",
    "cert_info",
    "issue",
    "key_matches",
    "load_cert",
    "load_key",
    "make_ca",
    "nodes",
    "signed_by",
    "write_acl",
]
