"""A ROS 2 node on a Zenoh session, as rmw_zenoh_cpp makes one: liveliness tokens, publishers with their
attachment, subscriptions that read it.

No ROS 2 installation is involved: the node speaks rmw_zenoh's protocol (:mod:`arena_common.ros2.names`)
with ``eclipse-zenoh`` and serializes with ``rosbags`` (:mod:`arena_common.ros2.types`), so ``ros2 topic
list/echo/hz``, RViz2 and ``ros2 bag record`` on ``rmw_zenoh_cpp`` connected to the same router see its
topics, and their publishers reach its subscriptions.

- A publisher is a Zenoh publisher on the topic's key expression (congestion control DROP; reliable
  unless the QoS says best effort), an *advanced* publisher with a cache of ``depth`` samples and
  publisher detection for TRANSIENT_LOCAL (what rmw_zenoh's late-joining subscriptions query), plus
  sample-miss heartbeats when also RELIABLE — as ``PublisherData::make``.
- A subscription is a Zenoh subscriber on the key expression; a sample without a valid attachment is
  dropped, as rmw_zenoh does.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext

from arena_common.ros2 import names, types
from arena_common.ros2.names import Durability, EntityKind, QoS, Reliability

__all__ = ["Node", "RosPublisher", "RosSubscription"]

log = logging.getLogger("arena.ros2")

SAMPLE_MISS_HEARTBEAT_S = 0.5  # rmw_zenoh's SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD (500 ms)


class RosPublisher:
    """One ROS 2 publisher: serializes, attaches, puts."""

    def __init__(self, node: Node, topic: str, type_name: str, qos: QoS, entity_id: int) -> None:
        self.topic = topic
        self.type = types.msg_type(type_name)
        self.qos = qos
        self.keyexpr = names.topic_keyexpr(node.domain, topic, self.type.dds, self.type.hash)
        self.token_key = node.entity_token(entity_id, EntityKind.PUBLISHER, topic, self.type, qos)
        self.gid = names.gid(self.token_key)
        self.sent = 0
        self._seq = 1
        self._lock = threading.Lock()
        session = node.session
        reliability = zenoh.Reliability.RELIABLE if qos.reliable else zenoh.Reliability.BEST_EFFORT
        self._pub: Any
        if qos.durability == Durability.TRANSIENT_LOCAL:
            miss = (
                zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=SAMPLE_MISS_HEARTBEAT_S)
                if qos.reliability == Reliability.RELIABLE
                else None
            )
            self._pub = zenoh.ext.declare_advanced_publisher(
                session,
                self.keyexpr,
                congestion_control=zenoh.CongestionControl.DROP,
                reliability=reliability,
                cache=zenoh.ext.CacheConfig(qos.depth),
                publisher_detection=True,
                sample_miss_detection=miss,
            )
        else:
            self._pub = session.declare_publisher(
                self.keyexpr, congestion_control=zenoh.CongestionControl.DROP, reliability=reliability
            )
        self._token = session.liveliness().declare_token(self.token_key)

    def publish(self, msg: Any) -> None:
        """Serialize ``msg`` (CDR) and publish it with its attachment."""
        self.publish_raw(types.serialize(msg, self.type.name))

    def publish_raw(self, cdr: bytes) -> None:
        """Publish already serialized CDR bytes."""
        with self._lock:
            seq, self._seq = self._seq, self._seq + 1
            attachment = names.encode_attachment(seq, time.time_ns(), self.gid)
            self._pub.put(cdr, attachment=attachment)
            self.sent += 1

    def close(self) -> None:
        """Undeclare the token, then the publisher."""
        for obj in (self._token, self._pub):
            try:
                obj.undeclare()
            except Exception:  # gone with its session
                pass


class RosSubscription:
    """One ROS 2 subscription: hands each decoded message (and its attachment) to ``callback`` on the Zenoh
    thread."""

    def __init__(
        self,
        node: Node,
        topic: str,
        type_name: str,
        qos: QoS,
        entity_id: int,
        callback: Callable[[Any, names.Attachment], None],
    ) -> None:
        self.topic = topic
        self.type = types.msg_type(type_name)
        self.qos = qos
        self.keyexpr = names.topic_keyexpr(node.domain, topic, self.type.dds, self.type.hash)
        self.token_key = node.entity_token(entity_id, EntityKind.SUBSCRIPTION, topic, self.type, qos)
        self.received = 0
        self.dropped = 0
        self._callback = callback
        self._sub = node.session.declare_subscriber(self.keyexpr, self._on_sample)
        self._token = node.session.liveliness().declare_token(self.token_key)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            if sample.attachment is None:
                raise ValueError("no attachment")
            att = names.decode_attachment(sample.attachment.to_bytes())
            msg = types.deserialize(sample.payload.to_bytes(), self.type.name)
        except Exception as exc:  # rmw_zenoh drops such samples too
            self.dropped += 1
            log.warning("%s: sample dropped: %s", self.topic, exc)
            return
        self.received += 1
        try:
            self._callback(msg, att)
        except Exception:
            log.exception("%s: handler failed", self.topic)

    def close(self) -> None:
        """Undeclare the token, then the subscriber."""
        for obj in (self._token, self._sub):
            try:
                obj.undeclare()
            except Exception:
                pass


class Node:
    """A ROS 2 node (``namespace``/``name``) in ROS domain ``domain`` on an open Zenoh ``session``.

    Entity ids count from 1 within the node, as a context's ids do in rmw_zenoh; the node's own token is
    declared at once and lives until :meth:`close`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        name: str,
        *,
        namespace: str = "/",
        domain: int = 0,
        node_id: int = 0,
        enclave: str = "/",
    ) -> None:
        self.session = session
        self.name = name
        self.namespace = namespace
        self.domain = domain
        self.node_id = node_id
        self.enclave = enclave
        self.zid = str(session.info.zid())
        self._next_id = node_id + 1
        self._lock = threading.Lock()
        self._entities: list[RosPublisher | RosSubscription] = []
        self.token_key = names.node_token(domain, self.zid, node_id, namespace, name, enclave)
        self._token = session.liveliness().declare_token(self.token_key)

    def entity_token(self, entity_id: int, kind: EntityKind, topic: str, t: types.MsgType, qos: QoS) -> str:
        """The liveliness token of one of this node's entities."""
        return names.entity_token(
            self.domain,
            self.zid,
            self.node_id,
            entity_id,
            kind,
            self.namespace,
            self.name,
            topic,
            t.dds,
            t.hash,
            qos,
            self.enclave,
        )

    @property
    def entities(self) -> tuple[RosPublisher | RosSubscription, ...]:
        """The node's publishers and subscriptions, in the order they were declared."""
        return tuple(self._entities)

    def _id(self) -> int:
        with self._lock:
            i, self._next_id = self._next_id, self._next_id + 1
            return i

    def publisher(self, topic: str, type_name: str, qos: QoS = names.DEFAULT) -> RosPublisher:
        """Declare a publisher of ``type_name`` (``pkg/msg/Name``) on the absolute ``topic``."""
        pub = RosPublisher(self, topic, type_name, qos, self._id())
        self._entities.append(pub)
        return pub

    def subscription(
        self,
        topic: str,
        type_name: str,
        callback: Callable[[Any, names.Attachment], None],
        qos: QoS = names.DEFAULT,
    ) -> RosSubscription:
        """Declare a subscription; ``callback(msg, attachment)`` runs on a Zenoh thread: keep it short."""
        sub = RosSubscription(self, topic, type_name, qos, self._id(), callback)
        self._entities.append(sub)
        return sub

    def close(self) -> None:
        """Undeclare every entity, then the node's token."""
        for e in reversed(self._entities):
            e.close()
        self._entities.clear()
        try:
            self._token.undeclare()
        except Exception:
            pass
