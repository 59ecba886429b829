"""rmw_zenoh's wire format: key expressions, liveliness tokens, QoS and attachments (pure).

What a ROS 2 node using rmw_zenoh puts on Zenoh (rmw_zenoh's design document):

* a topic's data key is ``<domain>/<topic without its leading slash>/<DDS type name>/<type
  hash>``, e.g. ``0/slamlens/robot1/markers/visualization_msgs::msg::dds_::MarkerArray_/
  RIHS01_…``; the type hash is REP-2016's RIHS01 (jazzy and later) or
  ``TypeHashNotSupported`` (humble);
* the payload is CDR, little-endian, after its 4-byte encapsulation header ``00 01 00 00``;
* every publication carries a 33-byte attachment: int64 sequence number, int64 source
  timestamp (ns since the Unix epoch), both little-endian, the length byte 16 and the
  publisher's 16-byte GID;
* each node and each publisher / subscription holds a liveliness token under the hermetic
  ``@ros2_lv`` namespace, from which ``ros2 node list``, ``ros2 topic list`` and RViz's
  topic picker build the graph:
  ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>`` and
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP|MS/<enclave>/<namespace>/<node>/
  <topic, mangled>/<DDS type name>/<type hash>/<qos>``, mangled = every ``/`` as ``%``
  (an empty enclave or namespace is ``%``).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from slamlens.common.errors import ConfigError, MessageError
from slamlens.common.keys import ros_name

__all__ = ["ros_name"]

ADMIN_SPACE = "@ros2_lv"
HUMBLE_HASH = "TypeHashNotSupported"
DISTROS = ("jazzy", "humble")
#: the CDR encapsulation header of a little-endian plain CDR payload
CDR_LE = b"\x00\x01\x00\x00"
ATTACHMENT = struct.Struct("<qqB16s")  #: 33 bytes
GID_BYTES = 16
#: reliable, volatile, keep last 10, no deadline / lifespan, automatic liveliness: every
#: component empty but the depth, as rmw_zenoh writes its defaults
DEFAULT_QOS = "::,10:,:,:,,"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
_NAME = re.compile(r"^(/[A-Za-z_~{][A-Za-z0-9_{}]*)+$")


def dds_type_name(ros_type: str) -> str:
    """``pkg/msg/Name`` as DDS names it: ``pkg::msg::dds_::Name_``."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise ConfigError(f"ROS type {ros_type!r}: expected package/msg/Name")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str:
    """The inverse of :func:`dds_type_name` (``pkg::msg::dds_::Name_`` → ``pkg/msg/Name``)."""
    parts = dds_name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise MessageError("rmw_zenoh", "type", "pkg::msg::dds_::Name_", repr(dds_name))
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def check_topic(topic: str) -> str:
    """A fully qualified ROS 2 topic name (``/a/b``), or ConfigError naming it."""
    if not _NAME.match(topic):
        raise ConfigError(f"topic {topic!r} is not a fully qualified ROS 2 name "
                          "(/segment/segment, letters, digits and _)")
    return topic


def mangle(name: str) -> str:
    """A name in a liveliness token: every ``/`` as ``%`` (``""`` and ``/`` are ``%``)."""
    return name.replace("/", "%") if name not in ("", "/") else "%"


def topic_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The data key of ``topic``."""
    return f"{domain}/{check_topic(topic)[1:]}/{dds_type_name(ros_type)}/{type_hash}"


def subscription_key(domain: int, topics: list[str]) -> str:
    """One key expression for every data key of ``topics``, whatever their types and
    hashes: their common namespace and everything under it."""
    parts = [check_topic(t)[1:].split("/")[:-1] for t in topics]
    common: list[str] = []
    for chunks in zip(*parts, strict=False):
        if len(set(chunks)) != 1:
            break
        common.append(chunks[0])
    return "/".join([str(domain), *common, "**"])


@dataclass(frozen=True)
class DataKey:
    """A data key taken apart."""

    topic: str
    dds_type: str
    type_hash: str


def parse_topic_key(key: str, domain: int) -> DataKey:
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != str(domain):
        raise MessageError("rmw_zenoh", "key", f"DOMAIN/TOPIC/TYPE/HASH in domain {domain}",
                           repr(key))
    return DataKey("/" + "/".join(parts[1:-2]), parts[-2], parts[-1])


@dataclass(frozen=True)
class Node:
    """A ROS 2 node as rmw_zenoh announces it."""

    domain: int
    zid: str  #: the Zenoh session id, as zenoh-python prints it (hex)
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = ""

    def token(self) -> str:
        return (f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{self.node_id}/{self.node_id}/{NODE}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}")

    def endpoint_token(self, entity_id: int, kind: str, topic: str, ros_type: str,
                       type_hash: str, qos: str = DEFAULT_QOS) -> str:
        return (f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}/"
                f"{mangle(check_topic(topic))}/{dds_type_name(ros_type)}/{type_hash}/{qos}")


def attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of one publication."""
    if len(gid) != GID_BYTES:
        raise ConfigError(f"a publisher GID is {GID_BYTES} bytes, not {len(gid)}")
    return ATTACHMENT.pack(seq, stamp_ns, GID_BYTES, gid)


@dataclass(frozen=True)
class Attachment:
    seq: int
    stamp_ns: int
    gid: bytes


def parse_attachment(data: bytes | None) -> Attachment:
    """An attachment taken apart; MessageError if missing or malformed."""
    if data is None:
        raise MessageError("rmw_zenoh", "attachment", f"{ATTACHMENT.size} bytes", "none")
    if len(data) != ATTACHMENT.size:
        raise MessageError("rmw_zenoh", "attachment", f"{ATTACHMENT.size} bytes",
                           f"{len(data)} bytes")
    seq, stamp, n, gid = ATTACHMENT.unpack(data)
    if n != GID_BYTES:
        raise MessageError("rmw_zenoh", "attachment", f"GID length {GID_BYTES}", str(n))
    return Attachment(seq, stamp, gid)


def check_cdr(payload: bytes) -> None:
    """MessageError unless ``payload`` starts with the little-endian CDR header."""
    if bytes(payload[:4]) != CDR_LE:
        raise MessageError("rmw_zenoh", "payload", f"little-endian CDR header {CDR_LE.hex()}",
                           bytes(payload[:4]).hex() or "nothing")
