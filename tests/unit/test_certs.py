"""The certificate authority of docs/security.md: files, extensions, extending, bad input."""

from __future__ import annotations

import stat

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from slamlens.common.certs import extend_authority, identities_in, parse_name
from slamlens.common.errors import ConfigError, SecurityError


def _cert(path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def _mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _sans(cert: x509.Certificate) -> tuple[list[str], list[str]]:
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return (san.get_values_for_type(x509.DNSName),
            [str(ip) for ip in san.get_values_for_type(x509.IPAddress)])


def test_creates_authority_and_identities(tmp_path) -> None:
    root = tmp_path / "pki"
    report = extend_authority(root, ["router-ws", "robot-r1"], hosts=["ws.lab", "10.1.2.3"])
    assert report[0] == f"created authority {root / 'ca.pem'}"
    assert [line.split()[1] for line in report[1:]] == ["router-ws", "robot-r1"]
    assert _mode(root) == 0o700
    for name in ("ca", "router-ws", "robot-r1"):
        assert _mode(root / f"{name}.key") == 0o600
        assert _mode(root / f"{name}.pem") == 0o644
        key_pem = (root / f"{name}.key").read_bytes()
        # PKCS#8 ("BEGIN PRIVATE KEY"), not SEC1 ("BEGIN EC PRIVATE KEY"), unencrypted
        assert key_pem.startswith(b"-----BEGIN PRIVATE KEY-----\n")
        key = serialization.load_pem_private_key(key_pem, password=None)
        assert isinstance(key, ec.EllipticCurvePrivateKey)
        assert key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption()) == key_pem
        assert _cert(root / f"{name}.pem").public_key() == key.public_key()

    ca = _cert(root / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    ca_usage = ca.extensions.get_extension_for_class(x509.KeyUsage).value
    assert ca_usage.key_cert_sign and not ca_usage.digital_signature

    router = _cert(root / "router-ws.pem")
    assert router.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "router-ws"
    router.verify_directly_issued_by(ca)  # raises if not
    assert not router.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    usage = router.extensions.get_extension_for_class(x509.KeyUsage).value
    assert usage.digital_signature and not usage.key_cert_sign
    eku = router.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    dns, ips = _sans(router)
    assert dns == ["router-ws", "localhost", "ws.lab"]
    assert ips == ["127.0.0.1", "::1", "10.1.2.3"]

    robot = _cert(root / "robot-r1.pem")
    robot.verify_directly_issued_by(ca)
    assert _sans(robot) == (["robot-r1"], [])  # --host is for routers only
    assert set(robot.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value) == {
        ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    assert robot.not_valid_after_utc <= ca.not_valid_after_utc


def test_extending_keeps_every_existing_file(tmp_path) -> None:
    extend_authority(tmp_path, ["router-ws", "robot-r1"])
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    report = extend_authority(tmp_path, ["robot-r1", "viewer-lab"])
    assert report == [f"kept authority {tmp_path / 'ca.pem'}",
                      f"kept robot-r1 ({tmp_path / 'robot-r1.pem'})",
                      f"created viewer-lab ({tmp_path / 'viewer-lab.pem'}, "
                      f"{tmp_path / 'viewer-lab.key'})"]
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert {k: after[k] for k in before} == before  # byte for byte
    ca = _cert(tmp_path / "ca.pem")
    for name in ("router-ws", "robot-r1", "viewer-lab"):
        _cert(tmp_path / f"{name}.pem").verify_directly_issued_by(ca)
    assert [i.name for i in identities_in(tmp_path)] == ["robot-r1", "router-ws", "viewer-lab"]


def test_a_new_router_host_reissues_only_that_router_with_its_key(tmp_path) -> None:
    extend_authority(tmp_path, ["router-ws", "robot-r1"], hosts=["10.0.0.1"])
    robot_before = (tmp_path / "robot-r1.pem").read_bytes()
    key_before = (tmp_path / "router-ws.key").read_bytes()
    report = extend_authority(tmp_path, ["router-ws", "robot-r1"], hosts=["10.0.0.2"])
    assert report[1].startswith("re-issued router-ws with hosts 10.0.0.2 added")
    assert (tmp_path / "router-ws.key").read_bytes() == key_before
    assert (tmp_path / "robot-r1.pem").read_bytes() == robot_before
    dns, ips = _sans(_cert(tmp_path / "router-ws.pem"))
    assert {"10.0.0.1", "10.0.0.2", "127.0.0.1"} <= set(ips)
    # asking again for hosts it has changes nothing
    again = (tmp_path / "router-ws.pem").read_bytes()
    assert extend_authority(tmp_path, ["router-ws"], hosts=["10.0.0.2", "::1"])[1].startswith(
        "kept router-ws")
    assert (tmp_path / "router-ws.pem").read_bytes() == again


@pytest.mark.parametrize("name", ["robot", "robot-", "admin-x", "robot-a/b", "viewer-a b",
                                  "camera-*", "router--", "-robot-r1"])
def test_names_of_no_role_are_refused(tmp_path, name) -> None:
    with pytest.raises(ConfigError, match="identity name|name"):
        extend_authority(tmp_path / "pki", [name])
    assert not (tmp_path / "pki").exists()  # nothing written for a bad request


def test_roles_by_name() -> None:
    assert parse_name("robot-r1").role == "robot"
    assert parse_name("monitor-r1").subject == "r1"
    assert parse_name("camera-overhead").role == "camera"
    assert parse_name("viewer-lab-2").subject == "lab-2"


def test_bad_hosts_are_refused(tmp_path) -> None:
    with pytest.raises(ConfigError, match="not_a host"):
        extend_authority(tmp_path, ["router-ws"], hosts=["not_a host"])
    extend_authority(tmp_path, ["router-ws"], hosts=["fd00::7"])
    assert "fd00::7" in _sans(_cert(tmp_path / "router-ws.pem"))[1]


def test_a_foreign_certificate_in_the_folder_is_named(tmp_path) -> None:
    extend_authority(tmp_path / "ours", ["robot-r1"])
    extend_authority(tmp_path / "theirs", ["robot-r2"])
    (tmp_path / "ours" / "robot-r2.pem").write_bytes(
        (tmp_path / "theirs" / "robot-r2.pem").read_bytes())
    with pytest.raises(SecurityError, match=r"robot-r2\.pem was not issued by .*ca\.pem"):
        identities_in(tmp_path / "ours")
    (tmp_path / "ours" / "robot-r2.key").write_bytes(
        (tmp_path / "theirs" / "robot-r2.key").read_bytes())
    with pytest.raises(SecurityError, match="was not issued by"):
        extend_authority(tmp_path / "ours", ["robot-r2"])


def test_a_mismatched_ca_key_is_refused(tmp_path) -> None:
    extend_authority(tmp_path / "a", ["robot-r1"])
    extend_authority(tmp_path / "b", ["robot-r1"])
    (tmp_path / "a" / "ca.key").write_bytes((tmp_path / "b" / "ca.key").read_bytes())
    with pytest.raises(SecurityError, match=r"ca\.key is not the key of .*ca\.pem"):
        extend_authority(tmp_path / "a", ["robot-r2"])


def test_a_copy_without_the_authority_key_cannot_issue(tmp_path) -> None:
    extend_authority(tmp_path, ["robot-r1"])
    (tmp_path / "ca.key").unlink()  # as on a robot, which only got ca.pem
    with pytest.raises(SecurityError, match="holds ca.pem but not ca.key"):
        extend_authority(tmp_path, ["robot-r2"])
    assert not (tmp_path / "robot-r2.pem").exists()
