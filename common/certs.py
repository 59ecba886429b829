"""A small certificate authority for slamlens identities (docs/security.md), with ``cryptography``.

A directory holds the authority and the identities it issued::

    DIR/ca.pem  DIR/ca.key          the authority (self-signed; its key never leaves DIR)
    DIR/NAME.pem  DIR/NAME.key      one identity per name (common name = NAME)

Keys are ECDSA P-256 in PKCS#8 PEM, written 0600; certificates are PEM, 0644. Every identity
certificate serves both ends of a TLS link (extended key usage serverAuth + clientAuth) and
names itself as a DNS subject alternative name; ``router-*`` identities also carry
``localhost``, ``127.0.0.1``, ``::1`` and the ``--host`` names (DNS or IP), because clients
check the router's name against the address they dial; so do ``viewer-*`` identities
issued with ``--host`` (a browser checks the viewer's HTTPS certificate the same way), and
they are valid 825 days (iOS trusts no longer TLS server certificate).

:func:`extend_authority` is idempotent: an existing authority and existing identities are
kept as they are (their files are not rewritten), so adding a name never invalidates a
certificate already copied to another machine. Only a router identity asked for a host it
does not cover yet is re-issued, with the same key and the union of its hosts.

The role of an identity is its name's form (``robot-R``, ``camera-C``, ``monitor-R``, ``ros2-R``,
``viewer-…``, ``router-…``), see :mod:`slamlens.common.security`.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from slamlens.common.errors import ConfigError, SecurityError
from slamlens.common.keys import check_name

CA_CERT = "ca.pem"
CA_KEY = "ca.key"
CA_COMMON_NAME = "slamlens CA"
CA_DAYS = 3650  #: ten years: a lab's authority should outlive its robots
IDENTITY_DAYS = 1825  #: five years: within the CA's life, long enough never to surprise a lab
#: a viewer's certificate also serves its HTTPS page to phones, and iOS trusts no TLS
#: server certificate valid for more than 825 days
VIEWER_DAYS = 825
ROLES = ("robot", "camera", "monitor", "viewer", "router", "ros2")
ROUTER_DEFAULT_HOSTS = ("localhost", "127.0.0.1", "::1")
_LABEL = re.compile(r"^[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?$")


@dataclass(frozen=True)
class Identity:
    """A name split into its role and the robot / camera / free label it stands for."""

    name: str  #: the certificate's common name, e.g. ``robot-r1``
    role: str  #: one of :data:`ROLES`
    subject: str  #: ``r1`` for ``robot-r1``; the free label for viewers and routers


def parse_name(name: str) -> Identity:
    """The role of ``name``; a name of no known role is a :class:`ConfigError`."""
    role, sep, subject = name.partition("-")
    if not sep or role not in ROLES or not subject:
        raise ConfigError(f"identity name {name!r} must be ROLE-NAME with ROLE one of "
                          f"{', '.join(ROLES)} (e.g. robot-r1, viewer-lab)")
    if role in ("robot", "monitor", "ros2"):
        check_name("robot", subject)
    elif role == "camera":
        check_name("camera", subject)
    # a name is also a file name and a DNS name in its own certificate
    if not _LABEL.match(name):
        raise ConfigError(f"identity name {name!r} must be letters, digits and '-' "
                          "(at most 63, not starting or ending with '-')")
    return Identity(name=name, role=role, subject=subject)


def _host_name(host: str):  # -> x509.GeneralName
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        pass
    if not host or not all(_LABEL.match(label) for label in host.rstrip(".").split(".")):
        raise ConfigError(f"host {host!r} is neither an IP address nor a DNS name")
    return x509.DNSName(host)


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` atomically with ``mode`` (the file never exists with wider rights)."""
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.fchmod(fd, mode)
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)


def _key_pem(key) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _new_key():  # -> ec.EllipticCurvePrivateKey
    from cryptography.hazmat.primitives.asymmetric import ec

    # P-256: accepted by every TLS stack (rustls/webpki included), small and fast to verify
    return ec.generate_private_key(ec.SECP256R1())


def load_cert(path: Path):  # -> x509.Certificate
    """A PEM certificate; a missing or unreadable file is a :class:`SecurityError` naming it."""
    from cryptography import x509

    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SecurityError(f"certificate {path} does not exist") from None
    except OSError as exc:
        raise SecurityError(f"certificate {path} cannot be read: {exc.strerror}") from None
    try:
        return x509.load_pem_x509_certificate(data)
    except ValueError as exc:
        raise SecurityError(f"certificate {path} is not a PEM certificate: {exc}") from None


def load_key(path: Path):  # -> PrivateKeyTypes
    """A PEM private key; missing, unreadable or malformed is a :class:`SecurityError`."""
    from cryptography.hazmat.primitives import serialization

    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SecurityError(f"private key {path} does not exist") from None
    except OSError as exc:
        raise SecurityError(f"private key {path} cannot be read: {exc.strerror}") from None
    try:
        return serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise SecurityError(f"private key {path} is not an unencrypted PEM key: {exc}") from None


def common_name(cert) -> str:
    from cryptography.x509.oid import NameOID

    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else ""


def san_hosts(cert) -> list[str]:
    """The DNS names and IP addresses of a certificate's subject alternative names."""
    from cryptography import x509

    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return []
    return [*san.get_values_for_type(x509.DNSName),
            *(str(ip) for ip in san.get_values_for_type(x509.IPAddress))]


def _ca_certificate(key):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, CA_COMMON_NAME),
                      x509.NameAttribute(NameOID.ORGANIZATION_NAME, "slamlens")])
    now = _now()
    return (x509.CertificateBuilder()
            .subject_name(name).issuer_name(name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))  # tolerate small clock skew
            .not_valid_after(now + dt.timedelta(days=CA_DAYS))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(
                digital_signature=False, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True,
                crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                           critical=False)
            .sign(key, hashes.SHA256()))


def _identity_certificate(identity: Identity, key, hosts: Sequence[str],
                          ca_cert, ca_key):
    days = VIEWER_DAYS if identity.role == "viewer" else IDENTITY_DAYS
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = _now()
    alt_names = [x509.DNSName(identity.name), *(_host_name(h) for h in hosts)]
    ski = ca_cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    return (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, identity.name),
                                     x509.NameAttribute(NameOID.ORGANIZATION_NAME,
                                                        "slamlens")]))
            .issuer_name(ca_cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(min(now + dt.timedelta(days=days),
                                 ca_cert.not_valid_after_utc))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=True, key_cert_sign=False,
                crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(alt_names), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ski),
                           critical=False)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))


def _cert_pem(cert) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return cert.public_bytes(serialization.Encoding.PEM)


def _load_or_create_ca(directory: Path, report: list[str]):
    cert_path, key_path = directory / CA_CERT, directory / CA_KEY
    if cert_path.exists() and not key_path.exists():
        raise SecurityError(f"{directory} holds {CA_CERT} but not {CA_KEY}: identities are "
                            "issued on the machine that keeps the authority's key")
    if cert_path.exists() or key_path.exists():
        ca_cert, ca_key = load_cert(cert_path), load_key(key_path)
        if ca_cert.public_key().public_numbers() != ca_key.public_key().public_numbers():
            raise SecurityError(f"{key_path} is not the key of {cert_path}")
        report.append(f"kept authority {cert_path}")
        return ca_cert, ca_key
    ca_key = _new_key()
    ca_cert = _ca_certificate(ca_key)
    _write(key_path, _key_pem(ca_key), 0o600)
    _write(cert_path, _cert_pem(ca_cert), 0o644)
    report.append(f"created authority {cert_path}")
    return ca_cert, ca_key


def _issued_by(cert, ca_cert) -> bool:
    from cryptography.exceptions import InvalidSignature

    try:
        cert.verify_directly_issued_by(ca_cert)
    except (InvalidSignature, ValueError, TypeError):
        return False
    return True


def extend_authority(directory: str | os.PathLike[str], names: Iterable[str], *,
                     hosts: Sequence[str] = ()) -> list[str]:
    """Create or extend the authority in ``directory`` with ``names``; one line per action.

    ``hosts`` are added to the subject alternative names of ``router-*`` identities, and of
    ``viewer-*`` ones (the viewer's HTTPS page, ``slamlens viewer --tls-cert``).
    """
    identities = [parse_name(n) for n in dict.fromkeys(names)]
    if not identities:
        raise ConfigError("name at least one identity (--name NAME)")
    for host in hosts:
        _host_name(host)  # reject a bad host before writing anything
    root = Path(directory)
    if root.exists() and not root.is_dir():
        raise ConfigError(f"{root} exists and is not a directory")
    if not root.exists():
        root.mkdir(parents=True, mode=0o700)
    report: list[str] = []
    ca_cert, ca_key = _load_or_create_ca(root, report)
    for identity in identities:
        report.append(_issue(root, identity, hosts, ca_cert, ca_key))
    return report


def _issue(root: Path, identity: Identity, hosts: Sequence[str], ca_cert, ca_key) -> str:
    cert_path, key_path = root / f"{identity.name}.pem", root / f"{identity.name}.key"
    # clients dial a router, and phones a viewer's HTTPS page, by these names
    wanted = list(dict.fromkeys([*ROUTER_DEFAULT_HOSTS, *hosts])) if (
        identity.role == "router" or (identity.role == "viewer" and hosts)) else []
    if cert_path.exists():
        cert = load_cert(cert_path)
        key = load_key(key_path)
        if not _issued_by(cert, ca_cert):
            raise SecurityError(f"certificate {cert_path} was not issued by {root / CA_CERT}; "
                                "move it away to issue a new one")
        if cert.public_key().public_numbers() != key.public_key().public_numbers():
            raise SecurityError(f"{key_path} is not the key of {cert_path}")
        have = {h.lower() for h in san_hosts(cert)}
        missing = [h for h in wanted if _canonical(h) not in have]
        if not missing:
            return f"kept {identity.name} ({cert_path})"
        covered = [h for h in san_hosts(cert) if h != identity.name]
        new = _identity_certificate(identity, key, list(dict.fromkeys([*covered, *missing])),
                                    ca_cert, ca_key)
        _write(cert_path, _cert_pem(new), 0o644)
        return f"re-issued {identity.name} with hosts {', '.join(missing)} added ({cert_path})"
    if key_path.exists():
        raise SecurityError(f"private key {key_path} exists without {cert_path}; "
                            "move it away to issue a new identity")
    key = _new_key()
    cert = _identity_certificate(identity, key, wanted, ca_cert, ca_key)
    _write(key_path, _key_pem(key), 0o600)
    _write(cert_path, _cert_pem(cert), 0o644)
    return f"created {identity.name} ({cert_path}, {key_path})"


def _canonical(host: str) -> str:
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        return host.lower()


def identities_in(directory: str | os.PathLike[str]) -> list[Identity]:
    """Every identity whose certificate ``directory`` holds (sorted by name).

    A ``*.pem`` that is not an identity of this authority (another CA's certificate, a
    name of no role) is a :class:`SecurityError` naming the file: the router must never
    silently skip a name it was asked to enforce.
    """
    root = Path(directory)
    ca_path = root / CA_CERT
    ca_cert = load_cert(ca_path)
    out = []
    for path in sorted(root.glob("*.pem")):
        if path.name == CA_CERT:
            continue
        cert = load_cert(path)
        name = common_name(cert)
        if name != path.stem:
            raise SecurityError(f"certificate {path} names {name!r}, not {path.stem!r}")
        if not _issued_by(cert, ca_cert):
            raise SecurityError(f"certificate {path} was not issued by {ca_path}")
        try:
            out.append(parse_name(name))
        except ConfigError as exc:
            raise SecurityError(f"certificate {path}: {exc}") from None
    return out
