"""The ROS 2 side of the bridge's tests: an independent rmw_zenoh client (zenoh-ros2-sdk).

``zenoh-ros2-sdk`` speaks rmw_zenoh on its own (its keys, tokens, attachments, type hashes
and rosbags' CDR): it stands in for ROS 2 nodes, so the bridge is never checked against its
own encoder. Offline it reads message definitions from a folder laid out as
``pkg/msg/Name.msg``: :func:`messages_dir` writes it from ``rosbags``' type store (the
standard types) and the bridge's shipped ``.msg`` files (its own two).

The SDK keeps one Zenoh session per process (a singleton), so every test that uses it runs
it in a child process: ``python -m tests.ros2_side listen|publish …`` (one JSON line per
message received; ``ready`` once it is subscribed or publishing).
"""

from __future__ import annotations

import argparse
import base64
import json
import re
import sys
import threading
import time
from pathlib import Path
from typing import Any

from slamlens.services.ros2.rostypes import OWN_TYPES, msg_file, typestore

STANDARD = ("visualization_msgs/msg/MarkerArray", "geometry_msgs/msg/PoseWithCovarianceStamped",
            "nav_msgs/msg/Path", "tf2_msgs/msg/TFMessage", "diagnostic_msgs/msg/DiagnosticArray",
            "nav_msgs/msg/Odometry", "std_msgs/msg/String", "geometry_msgs/msg/Pose2D")


def messages_dir(root: Path, distro: str = "jazzy") -> Path:
    """Write every definition the tests' types need under ``root`` (pkg/msg/Name.msg)."""
    store = typestore(distro)
    for name in STANDARD:
        text, _ = store.generate_msgdef(name)
        sections = re.split(r"\n=+\nMSG: ", "\n" + text)
        first, rest = sections[0], sections[1:]
        parts = [(name, first.strip("\n"))]
        for section in rest:
            dep, _, body = section.partition("\n")
            pkg, _, leaf = dep.strip().partition("/")
            parts.append((f"{pkg}/msg/{leaf}", body))
        for full, body in parts:
            path = root / f"{full}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            body = re.sub(r"^time ", "builtin_interfaces/Time ", body, flags=re.M)
            body = re.sub(r"^duration ", "builtin_interfaces/Duration ", body, flags=re.M)
            path.write_text(body.strip("\n") + "\n")
    for leaf in ("Time", "Duration"):
        path = root / f"builtin_interfaces/msg/{leaf}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("int32 sec\nuint32 nanosec\n")
    for name in OWN_TYPES:
        path = root / f"{name}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(msg_file(name).read_text())
    return root


def _plain(value: Any) -> Any:
    """A rosbags message as JSON-able data (arrays as lists, bytes as base64)."""
    import numpy as np

    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (bytes, bytearray)):
        return base64.b64encode(bytes(value)).decode()
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if hasattr(value, "__dataclass_fields__"):
        return {k: _plain(getattr(value, k)) for k in value.__dataclass_fields__
                if k != "__msgtype__"}
    return value


def _sdk(router: str, messages: Path) -> None:
    from zenoh_ros2_sdk.message_registry import get_registry

    get_registry(str(messages))
    host, port = router.split("/", 1)[1].rsplit(":", 1)
    _sdk.router = (host, int(port))  # type: ignore[attr-defined]


def listen(args: argparse.Namespace) -> None:
    from zenoh_ros2_sdk import ROS2Subscriber

    host, port = _sdk.router  # type: ignore[attr-defined]
    lock = threading.Lock()
    count = [0]

    def on_message(msg: Any) -> None:
        with lock:
            count[0] += 1
            print(json.dumps({"n": count[0], "msg": _plain(msg)}), flush=True)

    subs = []
    for topic, msg_type in zip(args.topic, args.type, strict=True):
        subs.append(ROS2Subscriber(topic=topic, msg_type=msg_type, callback=on_message,
                                   domain_id=args.domain, router_ip=host, router_port=port,
                                   type_hash=args.type_hash or None,
                                   node_name=args.node))
    print("ready", flush=True)
    deadline = time.monotonic() + args.seconds
    while time.monotonic() < deadline and (not args.count or count[0] < args.count):
        time.sleep(0.05)
    for sub in subs:
        sub.close()


def publish(args: argparse.Namespace) -> None:
    """Publish the messages of a JSON-lines file: ``{"topic", "type", "fields"}`` each,
    with fields as the SDK's keyword arguments (nested messages as dicts)."""
    from zenoh_ros2_sdk import ROS2Publisher, get_message_class

    host, port = _sdk.router  # type: ignore[attr-defined]
    pubs: dict[str, Any] = {}
    lines = [json.loads(line) for line in Path(args.file).read_text().splitlines() if line]
    for item in lines:
        if item["topic"] not in pubs:
            pubs[item["topic"]] = ROS2Publisher(topic=item["topic"], msg_type=item["type"],
                                                domain_id=args.domain, router_ip=host,
                                                router_port=port,
                                                type_hash=args.type_hash or None,
                                                node_name=args.node)
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline and not all(
            p.pub.matching_status.matching for p in pubs.values()):
        time.sleep(0.01)  # until the bridge's subscriptions are known to this session
    print("ready", flush=True)
    sys.stdin.readline()  # the test says when
    for item in lines:
        pubs[item["topic"]].publish(**_build(item["type"], item["fields"], get_message_class))
        print(f"sent {item['topic']}", flush=True)
    sys.stdin.readline()
    for pub in pubs.values():
        pub.close()


def _build(msg_type: str, fields: dict[str, Any], get_class: Any) -> dict[str, Any]:
    """SDK keyword arguments: nested dicts become message objects, lists of floats / ints
    numpy arrays (rosbags' CDR wants arrays for primitive sequences)."""
    import numpy as np

    store = typestore("jazzy")
    cls = store.types[msg_type]
    out: dict[str, Any] = {}
    for name, value in fields.items():
        out[name] = _value(cls, name, value, store, np)
    return out


def _value(cls: Any, name: str, value: Any, store: Any, np: Any) -> Any:
    from rosbags.typesys.base import Nodetype

    fields = dict(store.fielddefs[cls.__msgtype__][1])
    kind = fields[name]
    if kind[0] == Nodetype.NAME:
        sub = store.types[kind[1]]
        return sub(**{k: _value(sub, k, v, store, np) for k, v in value.items()})
    if kind[0] in (Nodetype.SEQUENCE, Nodetype.ARRAY) and kind[1][0][0] == Nodetype.BASE:
        dtype = {"float64": np.float64, "float32": np.float32, "int64": np.int64,
                 "uint8": np.uint8, "int32": np.int32}[kind[1][0][1][0]]
        return np.array(value, dtype=dtype)
    return value


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=("listen", "publish"))
    parser.add_argument("--router", required=True)
    parser.add_argument("--messages", required=True)
    parser.add_argument("--domain", type=int, default=0)
    parser.add_argument("--topic", action="append", default=[])
    parser.add_argument("--type", action="append", default=[])
    parser.add_argument("--type-hash", default="")
    parser.add_argument("--node", default=None)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--count", type=int, default=0)
    parser.add_argument("--file", default="")
    args = parser.parse_args()
    _sdk(args.router, Path(args.messages))
    listen(args) if args.mode == "listen" else publish(args)


if __name__ == "__main__":
    main()
