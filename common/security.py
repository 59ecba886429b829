"""Mutual TLS and role-based access control for slamlens sessions, in Zenoh's terms
(docs/security.md).

``--secure DIR --name NAME`` makes a session speak TLS only, with the identity ``NAME`` of the
authority in ``DIR`` (see :mod:`slamlens.common.certs`): the authority's ``ca.pem`` is the only root
trusted, the peer must present a certificate too (mutual TLS), and a client checks that the
router's certificate names the host it dialled.

A session that accepts links (a router, or a peer that listens) also enforces the roles of
every identity ``DIR`` holds with Zenoh's own ``access_control``, matched on the certificate's
common name, default deny:

* everyone may subscribe, query, query liveliness and subscribe to liveliness under the
  prefix, and receives whatever is routed to them there;
* ``robot-R`` may put, delete, reply, declare queryables and liveliness tokens under
  ``PREFIX/robot/R/**`` only; ``camera-C`` under ``PREFIX/camera/C/**`` only; ``monitor-R``
  on ``PREFIX/robot/R/health`` only; ``viewer-…`` only puts the frames of the browsers its
  ``/ar`` page serves, on ``PREFIX/camera/*/capture``; ``router-…`` links routers and may
  send anything under the prefix (a router enforces the roles of its own clients);
* ``ros2-R``, the ROS 2 bridge of robot R (``slamlens ros2``), may say the robot's
  ``state``, ``odometry``, ``observations`` and its estimator's liveliness token (what it
  takes in from ROS 2), and on the ROS 2 side (rmw_zenoh's keys, any domain) its exports
  ``*/slamlens/Rn/**`` and ``*/tf/**`` and the liveliness tokens of its node
  ``slamlens_Rn`` (Rn = R as a ROS 2 name); it may subscribe to the robot's ROS 2
  namespace ``*/Rn/**``;
* ``robot-R`` may also put in its ROS 2 namespace ``*/Rn/**`` (a ROS 2 robot's own topics);
  both are sent everything there (data and the subscriptions that make it flow);
* everyone may also read the bridges' exports (``*/slamlens/**``, ``*/tf/**``) and ROS 2's
  graph (``@ros2_lv/**``: liveliness queries and subscriptions), so RViz and ``ros2 topic
  list`` work with any identity;
* every identity ``NAME`` may also announce and answer its own status
  (:mod:`slamlens.common.status`):
  hold a liveliness token, declare a queryable and reply under ``PREFIX/status/NAME/**``.

Zenoh's advanced publishers and subscribers (docs/delivery.md) talk in key spaces under the data
key:
a publisher's cache queryable, heartbeat puts and detection token live on
``KEY/@adv/pub/<zid>/<eid>/_``; a subscriber queries ``KEY/@adv/**`` and
``KEY/@adv/pub/<zid>/<eid>/_`` (history, recovery), subscribes to ``KEY/@adv/pub/**``
(heartbeats), subscribes to and queries liveliness there (late publishers) and, with
subscriber detection, holds a token on ``KEY/@adv/sub/<zid>/<eid>/_``. Because ``**`` never
matches a verbatim ``@`` chunk, each scope above comes with its ``/**/@adv/**`` twin, and
every identity may hold ``@adv/sub`` tokens (they only announce a subscriber).
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slamlens.common.certs import (
    CA_CERT,
    Identity,
    common_name,
    identities_in,
    load_cert,
    load_key,
    parse_name,
)
from slamlens.common.endpoints import effective_endpoints
from slamlens.common.errors import ConfigError, SecurityError
from slamlens.common.keys import ros_name, ros_node

#: every message kind Zenoh's access control filters
ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")
#: what reading needs: subscriptions, queries and liveliness look-ups
READ_MESSAGES = ("declare_subscriber", "query", "liveliness_query",
                 "declare_liveliness_subscriber")
#: what saying something needs: data, answers, presence
WRITE_MESSAGES = ("put", "delete", "reply", "declare_queryable", "liveliness_token")
#: what announcing one's own status needs (common/status.py): presence and answers
STATUS_MESSAGES = ("liveliness_token", "declare_queryable", "reply")


@dataclass(frozen=True)
class IdentityFiles:
    """The three files one identity uses, checked to belong together."""

    ca: Path  #: the authority's certificate (the only trusted root)
    cert: Path  #: this identity's certificate (common name = the name)
    key: Path  #: its private key


def _scope(*keys: str) -> list[str]:
    """``keys`` and the advanced pub/sub key spaces below them (``**`` skips ``@adv``)."""
    out: list[str] = []
    for key in keys:
        out += [key, f"{key}/@adv/**"]  # P/x/** then gives P/x/**/@adv/**
    return out


#: what everyone may read of ROS 2 (rmw_zenoh keys): the bridges' exports and the graph
ROS_READ = ("*/slamlens/**", "*/tf/**", "@ros2_lv/**")


def write_scope(identity: Identity, prefix: str) -> list[str]:
    """Key expressions ``identity`` may put, reply and hold tokens on (docs/security.md roles)."""
    if identity.role == "robot":
        return _scope(f"{prefix}/robot/{identity.subject}/**") + \
            [f"*/{ros_name(identity.subject)}/**"]
    if identity.role == "ros2":
        robot = f"{prefix}/robot/{identity.subject}"
        node = f"@ros2_lv/*/*/*/*/*/*/*/{ros_node(identity.subject)}"
        return _scope(f"{robot}/state", f"{robot}/odometry", f"{robot}/observations",
                      f"{robot}/alive/estimator") + [
            f"*/slamlens/{ros_name(identity.subject)}/**", "*/tf/**", node, f"{node}/**"]
    if identity.role == "camera":
        return _scope(f"{prefix}/camera/{identity.subject}/**")
    if identity.role == "monitor":
        return _scope(f"{prefix}/robot/{identity.subject}/health")
    if identity.role == "router":
        return _scope(f"{prefix}/**")
    return []  # viewers say nothing


def frames_scope(identity: Identity, prefix: str) -> list[str]:
    """Where a viewer puts its AR pages' camera frames (plain puts: no advanced publisher)."""
    return [f"{prefix}/camera/*/capture"] if identity.role == "viewer" else []


def status_scope(identity: Identity, prefix: str) -> list[str]:
    """Key expressions where ``identity`` announces and answers its own status."""
    return [f"{prefix}/status/{identity.name}/**"]


def access_control(prefix: str, identities: Iterable[Identity]) -> dict[str, Any]:
    """Zenoh's ``access_control`` config enforcing the roles of ``identities``."""
    people = sorted({i.name: i for i in identities}.values(), key=lambda i: i.name)
    everything = _scope(f"{prefix}/**") + list(ROS_READ)
    rules: list[dict[str, Any]] = [
        {"id": "read", "permission": "allow", "flows": ["ingress"],
         "messages": list(READ_MESSAGES), "key_exprs": everything},
        {"id": "announce-subscribers", "permission": "allow", "flows": ["ingress"],
         "messages": ["liveliness_token"], "key_exprs": [f"{prefix}/**/@adv/sub/**"]},
        {"id": "deliver", "permission": "allow", "flows": ["egress"],
         "messages": list(ALL_MESSAGES), "key_exprs": everything},
    ]
    policies: list[dict[str, Any]] = []
    if people:
        policies.append({"id": "everyone", "rules": ["read", "announce-subscribers", "deliver"],
                         "subjects": [i.name for i in people]})
    for identity in people:
        own: list[str] = []
        scope = write_scope(identity, prefix)
        if scope:
            rule = f"say {identity.name}"
            messages = ALL_MESSAGES if identity.role == "router" else WRITE_MESSAGES
            rules.append({"id": rule, "permission": "allow", "flows": ["ingress"],
                          "messages": list(messages), "key_exprs": scope})
            own.append(rule)
        if identity.role in ("robot", "ros2"):  # the robot's ROS 2 namespace reaches them
            namespace = [f"*/{ros_name(identity.subject)}/**"]
            rules.append({"id": f"given {identity.name}", "permission": "allow",
                          "flows": ["egress"], "messages": list(ALL_MESSAGES),
                          "key_exprs": namespace})
            own.append(f"given {identity.name}")
        if identity.role == "ros2":  # and the bridge subscribes to it
            rules.append({"id": f"take {identity.name}", "permission": "allow",
                          "flows": ["ingress"], "messages": ["declare_subscriber"],
                          "key_exprs": [f"*/{ros_name(identity.subject)}/**"]})
            own.append(f"take {identity.name}")
        frames = frames_scope(identity, prefix)
        if frames:
            rule = f"frames {identity.name}"
            rules.append({"id": rule, "permission": "allow", "flows": ["ingress"],
                          "messages": ["put"], "key_exprs": frames})
            own.append(rule)
        if identity.role != "router":  # a router may say anything under the prefix anyway
            rule = f"status {identity.name}"
            rules.append({"id": rule, "permission": "allow", "flows": ["ingress"],
                          "messages": list(STATUS_MESSAGES),
                          "key_exprs": status_scope(identity, prefix)})
            own.append(rule)
        policies.append({"id": identity.name, "rules": own, "subjects": [identity.name]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": i.name, "cert_common_names": [i.name]} for i in people],
        "policies": policies,
    }


def check_identity(directory: str, name: str) -> IdentityFiles:
    """The files of ``name`` in ``directory``, checked with the reason named on failure:
    present, PEM, issued by ``ca.pem``, naming ``name``, valid now, key matching."""
    parse_name(name)
    root = Path(directory)
    if not root.is_dir():
        raise SecurityError(f"security directory {root} does not exist "
                            f"(create it with: slamlens certs {root} --name {name})")
    files = IdentityFiles(ca=root / CA_CERT, cert=root / f"{name}.pem", key=root / f"{name}.key")
    ca = load_cert(files.ca)
    if not files.cert.exists():
        raise SecurityError(f"certificate {files.cert} does not exist "
                            f"(issue it with: slamlens certs {root} --name {name})")
    cert = load_cert(files.cert)
    if common_name(cert) != name:
        raise SecurityError(f"certificate {files.cert} names {common_name(cert)!r}, "
                            f"not {name!r}")
    from cryptography.exceptions import InvalidSignature

    try:
        cert.verify_directly_issued_by(ca)
    except (InvalidSignature, ValueError, TypeError):
        raise SecurityError(f"certificate {files.cert} was not issued by {files.ca}") from None
    now = dt.datetime.now(dt.UTC)
    for path, c in ((files.ca, ca), (files.cert, cert)):
        if now < c.not_valid_before_utc:
            raise SecurityError(f"certificate {path} is not valid before "
                                f"{c.not_valid_before_utc:%Y-%m-%d %H:%M} UTC (check the clock)")
        if now > c.not_valid_after_utc:
            raise SecurityError(f"certificate {path} expired on "
                                f"{c.not_valid_after_utc:%Y-%m-%d} UTC")
    key = load_key(files.key)
    if key.public_key().public_numbers() != cert.public_key().public_numbers():  # type: ignore[union-attr]
        raise SecurityError(f"private key {files.key} is not the key of {files.cert}")
    return files


def tls_settings(files: IdentityFiles) -> dict[str, Any]:
    """``transport/link/tls`` entries for mutual TLS with the identity of ``files``."""
    return {
        "root_ca_certificate": str(files.ca),
        "listen_certificate": str(files.cert),
        "listen_private_key": str(files.key),
        "connect_certificate": str(files.cert),
        "connect_private_key": str(files.key),
        "enable_mtls": True,  # the other end must prove an identity of this authority too
        "verify_name_on_connect": True,  # the router's certificate must name the dialled host
    }


def check_tls_only(endpoints: Sequence[str]) -> None:
    for endpoint in endpoints:
        if not endpoint.startswith("tls/"):
            raise ConfigError(f"endpoint {endpoint} is not TLS: with --secure every endpoint "
                              "must be tls/HOST:PORT")


def apply(conf: Any, *, directory: str, name: str, prefix: str, mode: str | None) -> None:
    """Make ``conf`` TLS-only with identity ``name``; a router or listening peer also
    enforces the roles of every identity in ``directory``."""
    files = check_identity(directory, name)
    listen = effective_endpoints(conf, "listen", mode)
    check_tls_only([*effective_endpoints(conf, "connect", mode), *listen])
    if mode == "router" and parse_name(name).role != "router":
        raise ConfigError(f"a router's identity must be a router-… name, not {name!r}")
    for key, value in tls_settings(files).items():
        conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
    if mode == "router" or listen:
        identities = identities_in(directory)
        conf.insert_json5("access_control", json.dumps(access_control(prefix, identities)))
