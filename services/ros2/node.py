"""A ROS 2 node on Zenoh as rmw_zenoh makes one: its token, publishers and subscriptions.

Runs on the bridge's own Zenoh session (the bus's). The node announces itself with its
``NN`` liveliness token; each publisher holds an ``MP`` token and puts CDR payloads with the
33-byte attachment (sequence number from 1, source time, its random GID); each
subscription holds an ``MS`` token for the type it expects; the topics taken in are
subscribed to as one (their common namespace, every type and hash), so a message of
another type or hash is seen, and counted, instead of silently never arriving, and
messages one node publishes on several topics keep its order. Nothing waits in a Zenoh callback:
a subscription checks the attachment, copies the payload and queues it for the bridge's
worker (:mod:`slamlens.common.channel`'s ``QueueChannel``: never blocks, bounded in bytes). A
large payload (≥ 1 MB: an estimate of a big map) is not copied there — copying 32 MB on
Zenoh's thread held up the router's link and it dropped the next ones — but when the
worker takes it; if a newer one of its topic arrives first, the older is skipped (counted
as superseded), as the viewer skips to the newest state.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from slamlens.common.bus import Sample
from slamlens.common.channel import QueueChannel
from slamlens.common.errors import MessageError
from slamlens.services.ros2.rostypes import RosType
from slamlens.services.ros2.wire import (
    PUBLISHER,
    SUBSCRIPTION,
    Node,
    attachment,
    parse_attachment,
    subscription_key,
    topic_key,
)

log = logging.getLogger("slamlens.ros2")
#: a message at least this big (an estimate of some 180 landmarks and more) waits in Zenoh's
#: buffer until the bridge takes it, and only the newest of its topic waits
LARGE = 1 << 20


class RosPublisher:
    """One topic's publisher (``put`` may be called from one thread at a time)."""

    def __init__(self, session: Any, node: Node, entity_id: int, topic: str,
                 ros_type: RosType) -> None:
        import zenoh

        self.topic = topic
        self.key = topic_key(node.domain, topic, ros_type.name, ros_type.hash)
        self.gid = os.urandom(16)
        self.seq = 0
        self.sent = 0
        self._pub = session.declare_publisher(
            self.key, congestion_control=zenoh.CongestionControl.DROP,
            reliability=zenoh.Reliability.RELIABLE)
        self._token = session.liveliness().declare_token(node.endpoint_token(
            entity_id, PUBLISHER, topic, ros_type.name, ros_type.hash))

    def put(self, payload: bytes) -> None:
        self.seq += 1
        self._pub.put(payload, attachment=attachment(self.seq, time.time_ns(), self.gid))
        self.sent += 1

    def undeclare(self) -> None:
        for entity in (self._token, self._pub):
            try:
                entity.undeclare()
            except Exception:  # the session may already be closing
                pass


class RosSubscription:
    """The subscriptions of several topics as one Zenoh subscriber (module docstring): one
    subscriber keeps the order in which one publishing session put them, across topics
    (two subscribers' callbacks may run on two threads, out of that order)."""

    def __init__(self, session: Any, node: Node, first_id: int, topics: dict[str, RosType],
                 queue: QueueChannel, drop: Callable[[str, str], None]) -> None:
        self.topics = dict(topics)
        self.key = subscription_key(node.domain, list(topics))
        wanted = {topic[1:] for topic in topics}

        def on_sample(sample: Any) -> None:
            key = str(sample.key_expr)
            topic = key.split("/", 1)[1].rsplit("/", 2)[0] if key.count("/") >= 3 else ""
            if topic not in wanted:
                return  # another topic of the namespace: not ours, not copied
            raw = sample.attachment
            try:
                parse_attachment(None if raw is None else raw.to_bytes())
            except MessageError as exc:
                drop("/" + topic, f"{key}: {exc}")
                return
            size = len(sample.payload)
            if size >= LARGE:  # copied when taken, not on Zenoh's thread; newest only
                queue.push_newest(Sample(key, b""), sample.payload.to_bytes, size)
            else:
                queue.push(Sample(key, sample.payload.to_bytes()))

        self._sub = session.declare_subscriber(self.key, on_sample)
        self._tokens = [session.liveliness().declare_token(node.endpoint_token(
            first_id + k, SUBSCRIPTION, topic, t.name, t.hash))
            for k, (topic, t) in enumerate(topics.items())]

    def undeclare(self) -> None:
        for entity in (*self._tokens, self._sub):
            try:
                entity.undeclare()
            except Exception:
                pass


class RosNode:
    """The bridge's ROS 2 node (module docstring)."""

    def __init__(self, session: Any, *, domain: int, name: str, namespace: str = "/") -> None:
        self.session = session
        self.node = Node(domain=domain, zid=str(session.info.zid()), node_id=0, name=name,
                         namespace=namespace)
        self._token = session.liveliness().declare_token(self.node.token())
        self._entities: list[RosPublisher | RosSubscription] = []
        self._ids = 0
        self._lock = threading.Lock()

    def _next_ids(self, count: int = 1) -> int:
        with self._lock:
            first = self._ids + 1
            self._ids += count
            return first

    def publisher(self, topic: str, ros_type: RosType) -> RosPublisher:
        pub = RosPublisher(self.session, self.node, self._next_ids(), topic, ros_type)
        self._entities.append(pub)
        return pub

    def subscription(self, topics: dict[str, RosType], queue: QueueChannel,
                     drop: Callable[[str, str], None]) -> RosSubscription:
        sub = RosSubscription(self.session, self.node, self._next_ids(len(topics)), topics,
                              queue, drop)
        self._entities.append(sub)
        return sub

    def close(self) -> None:
        for entity in reversed(self._entities):
            entity.undeclare()
        self._entities = []
        try:
            self._token.undeclare()
        except Exception:
            pass
