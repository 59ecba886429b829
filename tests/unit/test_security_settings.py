"""Session security settings (docs/security.md): identity checks, TLS settings, the generated roles,
and how flags, files and --secure combine in the Zenoh config."""

from __future__ import annotations

import datetime as dt
import json

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from slamlens.common.certs import extend_authority, identities_in
from slamlens.common.endpoints import effective_endpoints
from slamlens.common.errors import ConfigError, SecurityError
from slamlens.common.security import access_control, check_identity
from slamlens.common.session import (
    BusSettings,
    build_config,
    listen_endpoints,
    router_settings,
    zenoh_reason,
)

NAMES = ["router-ws", "robot-r1", "camera-overhead", "monitor-r1", "viewer-lab"]


@pytest.fixture
def pki(tmp_path):
    extend_authority(tmp_path / "pki", NAMES)
    return tmp_path / "pki"


def _rule(acl: dict, rule_id: str) -> dict:
    (rule,) = [r for r in acl["rules"] if r["id"] == rule_id]
    return rule


def test_generated_roles(pki) -> None:
    acl = access_control("lab/slamlens", identities_in(pki))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert acl["subjects"] == [{"id": n, "cert_common_names": [n]} for n in sorted(NAMES)]
    writes = ["put", "delete", "reply", "declare_queryable", "liveliness_token"]
    assert _rule(acl, "say robot-r1") == {
        "id": "say robot-r1", "permission": "allow", "flows": ["ingress"], "messages": writes,
        "key_exprs": ["lab/slamlens/robot/r1/**", "lab/slamlens/robot/r1/**/@adv/**",
                      "*/r1/**"]}  # and its ROS 2 namespace (a ROS 2 robot's topics)
    assert _rule(acl, "say camera-overhead")["key_exprs"] == [
        "lab/slamlens/camera/overhead/**", "lab/slamlens/camera/overhead/**/@adv/**"]
    assert _rule(acl, "say monitor-r1")["key_exprs"] == [
        "lab/slamlens/robot/r1/health", "lab/slamlens/robot/r1/health/@adv/**"]
    assert _rule(acl, "say router-ws")["key_exprs"] == ["lab/slamlens/**",
                                                        "lab/slamlens/**/@adv/**"]
    assert len(_rule(acl, "say router-ws")["messages"]) == 9
    # a viewer says nothing but its AR pages' camera frames (puts on camera/*/capture) and
    # its own status; everyone may announce only their own
    assert [r["id"] for r in acl["rules"] if "viewer" in r["id"]] == [
        "frames viewer-lab", "status viewer-lab"]
    assert _rule(acl, "frames viewer-lab") == {
        "id": "frames viewer-lab", "permission": "allow", "flows": ["ingress"],
        "messages": ["put"], "key_exprs": ["lab/slamlens/camera/*/capture"]}
    assert _rule(acl, "status viewer-lab") == {
        "id": "status viewer-lab", "permission": "allow", "flows": ["ingress"],
        "messages": ["liveliness_token", "declare_queryable", "reply"],
        "key_exprs": ["lab/slamlens/status/viewer-lab/**"]}
    for name in NAMES:
        if not name.startswith("router-"):
            assert _rule(acl, f"status {name}")["key_exprs"] == [
                f"lab/slamlens/status/{name}/**"]
    assert not [r for r in acl["rules"] if r["id"] == "status router-ws"]  # says anything
    read = _rule(acl, "read")
    assert read["flows"] == ["ingress"] and "put" not in read["messages"]
    assert read["key_exprs"] == ["lab/slamlens/**", "lab/slamlens/**/@adv/**",
                                 "*/slamlens/**", "*/tf/**", "@ros2_lv/**"]
    assert _rule(acl, "announce-subscribers")["key_exprs"] == ["lab/slamlens/**/@adv/sub/**"]
    assert _rule(acl, "deliver")["flows"] == ["egress"]
    policies = {p["id"]: p for p in acl["policies"]}
    assert policies["everyone"]["subjects"] == sorted(NAMES)
    assert policies["robot-r1"] == {"id": "robot-r1",
                                    "rules": ["say robot-r1", "given robot-r1",
                                              "status robot-r1"],
                                    "subjects": ["robot-r1"]}
    assert _rule(acl, "given robot-r1")["key_exprs"] == ["*/r1/**"]
    assert policies["viewer-lab"] == {"id": "viewer-lab",
                                      "rules": ["frames viewer-lab", "status viewer-lab"],
                                      "subjects": ["viewer-lab"]}
    assert policies["router-ws"]["rules"] == ["say router-ws"]


def test_a_router_config_carries_tls_and_the_roles(pki) -> None:
    conf = build_config(router_settings(["tls/127.0.0.1:7999"], secure=str(pki),
                                        name="router-ws", prefix="lab/slamlens"))
    tls = json.loads(conf.get_json("transport/link/tls"))
    assert tls["root_ca_certificate"] == str(pki / "ca.pem")
    assert tls["listen_certificate"] == tls["connect_certificate"] == str(pki / "router-ws.pem")
    assert tls["listen_private_key"] == str(pki / "router-ws.key")
    assert tls["enable_mtls"] is True and tls["verify_name_on_connect"] is True
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] is True
    assert _rule(acl, "say robot-r1")["key_exprs"][0] == "lab/slamlens/robot/r1/**"


def test_a_secure_client_defaults_to_tls_loopback_without_access_control(pki) -> None:
    conf = build_config(BusSettings(secure=str(pki), name="robot-r1"))
    assert effective_endpoints(conf, "connect", "client") == ["tls/127.0.0.1:7447"]
    assert json.loads(conf.get_json("access_control"))["enabled"] is False
    assert json.loads(conf.get_json("transport/link/tls/connect_certificate")) == str(
        pki / "robot-r1.pem")


def test_plain_endpoints_are_refused_with_secure(pki, tmp_path) -> None:
    with pytest.raises(ConfigError, match="endpoint tcp/127.0.0.1:7447 is not TLS"):
        build_config(BusSettings(connect=("tcp/127.0.0.1:7447",), secure=str(pki),
                                 name="robot-r1"))
    file = tmp_path / "router.json5"
    file.write_text('{ mode: "router", listen: { endpoints: ["tcp/127.0.0.1:7998"] } }')
    with pytest.raises(ConfigError, match="endpoint tcp/127.0.0.1:7998 is not TLS"):
        build_config(router_settings([], str(file), secure=str(pki), name="router-ws"))
    with pytest.raises(ConfigError, match="router-… name"):
        build_config(router_settings(["tls/127.0.0.1:7999"], secure=str(pki), name="robot-r1"))
    with pytest.raises(ConfigError, match="go together"):
        build_config(BusSettings(secure=str(pki)))
    with pytest.raises(ConfigError, match="go together"):
        build_config(BusSettings(name="robot-r1"))


def test_router_honours_its_zenoh_config_listen(tmp_path) -> None:
    file = tmp_path / "router.json5"
    file.write_text('{ mode: "router", listen: { endpoints: ["tcp/127.0.0.1:7998"] } }')
    assert listen_endpoints(router_settings([], str(file))) == ["tcp/127.0.0.1:7998"]
    # a flag overrides only what it names
    assert listen_endpoints(router_settings(["tcp/127.0.0.1:7997"], str(file))) == [
        "tcp/127.0.0.1:7997"]
    # a file that does not say where: loopback, never Zenoh's all-interfaces default
    bare = tmp_path / "bare.json5"
    bare.write_text('{ mode: "router", scouting: { multicast: { enabled: false } } }')
    assert listen_endpoints(router_settings([], str(bare))) == ["tcp/127.0.0.1:7447"]
    assert listen_endpoints(router_settings([])) == ["tcp/127.0.0.1:7447"]
    per_mode = tmp_path / "per_mode.json5"
    per_mode.write_text('{ listen: { endpoints: { router: ["tcp/127.0.0.1:7996"] } } }')
    assert listen_endpoints(router_settings([], str(per_mode))) == ["tcp/127.0.0.1:7996"]


def _files(pki, name):
    return pki / "ca.pem", pki / f"{name}.pem", pki / f"{name}.key"


def test_identity_checks_name_the_file_and_the_reason(pki, tmp_path) -> None:
    assert check_identity(str(pki), "robot-r1").cert == pki / "robot-r1.pem"
    with pytest.raises(SecurityError, match=r"security directory .*nowhere does not exist"):
        check_identity(str(tmp_path / "nowhere"), "robot-r1")
    with pytest.raises(SecurityError, match=r"certificate .*robot-r9\.pem does not exist "
                                            r"\(issue it with: slamlens certs"):
        check_identity(str(pki), "robot-r9")
    (pki / "robot-r9.pem").write_text("not a certificate")
    with pytest.raises(SecurityError, match=r"robot-r9\.pem is not a PEM certificate"):
        check_identity(str(pki), "robot-r9")
    (pki / "robot-r9.pem").write_bytes((pki / "robot-r1.pem").read_bytes())
    with pytest.raises(SecurityError, match=r"robot-r9\.pem names 'robot-r1', not 'robot-r9'"):
        check_identity(str(pki), "robot-r9")
    (pki / "viewer-lab.key").write_bytes((pki / "robot-r1.key").read_bytes())
    with pytest.raises(SecurityError, match=r"viewer-lab\.key is not the key of .*viewer-lab"):
        check_identity(str(pki), "viewer-lab")
    (pki / "monitor-r1.key").unlink()
    with pytest.raises(SecurityError, match=r"private key .*monitor-r1\.key does not exist"):
        check_identity(str(pki), "monitor-r1")
    extend_authority(tmp_path / "other", ["camera-overhead"])
    (pki / "camera-overhead.pem").write_bytes(
        (tmp_path / "other" / "camera-overhead.pem").read_bytes())
    with pytest.raises(SecurityError, match=r"camera-overhead\.pem was not issued by .*ca\.pem"):
        check_identity(str(pki), "camera-overhead")
    (pki / "ca.pem").unlink()
    with pytest.raises(SecurityError, match=r"certificate .*ca\.pem does not exist"):
        check_identity(str(pki), "robot-r1")


def test_an_expired_certificate_is_named(pki) -> None:
    ca = x509.load_pem_x509_certificate((pki / "ca.pem").read_bytes())
    ca_key = serialization.load_pem_private_key((pki / "ca.key").read_bytes(), None)
    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "robot-old")]))
            .issuer_name(ca.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(days=30))
            .not_valid_after(now - dt.timedelta(days=1))
            .sign(ca_key, hashes.SHA256()))  # type: ignore[arg-type]
    (pki / "robot-old.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (pki / "robot-old.key").write_bytes(key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption()))
    with pytest.raises(SecurityError, match=r"robot-old\.pem expired on \d{4}-\d\d-\d\d"):
        check_identity(str(pki), "robot-old")


def test_zenoh_errors_lose_their_rust_locations() -> None:
    raw = ("Unable to connect to any of [Single(tcp/127.0.0.1:1)]. Timeout! at "
           "/root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/cc83980/zenoh/src/net/runtime/"
           "orchestrator.rs:388.")
    assert zenoh_reason(RuntimeError(raw)) == (
        "Unable to connect to any of [Single(tcp/127.0.0.1:1)]. Timeout!")


def test_a_router_links_to_the_routers_it_is_told_to() -> None:
    conf = build_config(router_settings([], connect=["tcp/10.0.0.2:7447"]))
    assert effective_endpoints(conf, "connect", "router") == ["tcp/10.0.0.2:7447"]
    assert effective_endpoints(conf, "listen", "router") == ["tcp/127.0.0.1:7447"]


def test_the_ros2_bridge_role_says_exactly_what_it_publishes(tmp_path) -> None:
    extend_authority(tmp_path / "pki", ["router-ws", "ros2-robot-1", "viewer-rviz"])
    acl = access_control("slamlens", identities_in(tmp_path / "pki"))
    say = _rule(acl, "say ros2-robot-1")
    assert say["messages"] == ["put", "delete", "reply", "declare_queryable", "liveliness_token"]
    assert say["key_exprs"] == [
        "slamlens/robot/robot-1/state", "slamlens/robot/robot-1/state/@adv/**",
        "slamlens/robot/robot-1/odometry", "slamlens/robot/robot-1/odometry/@adv/**",
        "slamlens/robot/robot-1/observations", "slamlens/robot/robot-1/observations/@adv/**",
        "slamlens/robot/robot-1/alive/estimator",
        "slamlens/robot/robot-1/alive/estimator/@adv/**",
        "*/slamlens/robot_1/**", "*/tf/**",
        "@ros2_lv/*/*/*/*/*/*/*/slamlens_robot_1", "@ros2_lv/*/*/*/*/*/*/*/slamlens_robot_1/**"]
    assert _rule(acl, "take ros2-robot-1") == {
        "id": "take ros2-robot-1", "permission": "allow", "flows": ["ingress"],
        "messages": ["declare_subscriber"], "key_exprs": ["*/robot_1/**"]}
    given = _rule(acl, "given ros2-robot-1")
    assert given["flows"] == ["egress"] and given["key_exprs"] == ["*/robot_1/**"]
    policies = {p["id"]: p for p in acl["policies"]}
    assert policies["ros2-robot-1"]["rules"] == ["say ros2-robot-1", "given ros2-robot-1",
                                                 "take ros2-robot-1", "status ros2-robot-1"]
