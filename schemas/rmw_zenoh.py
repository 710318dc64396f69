"""ROS 2's Zenoh middleware (rmw_zenoh) on our own zenoh session: a ROS 2 robot on the same router
sees our topics with ``ros2 topic list`` and reads them, with no bridge and no ROS on our side.

What rmw_zenoh puts on the wire (ros2/rmw_zenoh ``docs/design.md``, as ros-z and zenoh-ros2-sdk
implement it), and what this module builds:

- data key: ``<domain>/<topic without its leading slash>/<DDS type name>/<type hash>``, e.g.
  ``0/tf/tf2_msgs::msg::dds_::TFMessage_/RIHS01_e369...`` (Humble: ``TypeHashNotSupported``);
- payload: the message in CDR (little endian, with its 4-byte encapsulation header);
- attachment: u64 sequence number, u64 source time stamp (ns), u8 GID length, the GID (16 bytes);
- liveliness tokens under ``@ros2_lv``: one for the node (``NN``) and one per publisher (``MP``),
  names mangled (``/`` -> ``%``), the publisher's with its type, hash and QoS.
"""

from __future__ import annotations

import itertools
import struct
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

import zenoh

from schemas.ros2 import Ros2Types

ADMIN_SPACE = "@ros2_lv"
#: rmw_zenoh's QoS token fields: reliability:durability:history,depth:deadline:lifespan:liveliness
#: (empty = the default: reliable, volatile, keep last).
QOS_DEFAULT = "::,10:,:,:,,"
QOS_TF = "::,100:,:,:,,"
QOS_LATCHED = ":1:,1:,:,:,,"  # transient local, depth 1: /tf_static


def dds_type_name(typename: str) -> str:
    """``tf2_msgs/msg/TFMessage`` -> ``tf2_msgs::msg::dds_::TFMessage_``."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A ROS name inside a liveliness token: ``/`` becomes ``%``; empty or root is ``%``."""
    return "%" if not name or name == "/" else name.replace("/", "%")


def topic_key(domain_id: int, topic: str, typename: str, type_hash: str) -> str:
    """The data key expression of a ROS 2 topic."""
    return f"{domain_id}/{topic.lstrip('/')}/{dds_type_name(typename)}/{type_hash}"


def attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """What rmw_zenoh attaches to every sample: u64 sequence, u64 source time (ns), u8 len, GID."""
    return struct.pack("<QQB", sequence, stamp_ns, len(gid)) + gid


@dataclass(frozen=True)
class NodeName:
    """Where a node sits in the ROS graph: domain, namespace and name."""

    domain_id: int
    name: str
    namespace: str = "/"


@dataclass
class Ros2Node:
    """A ROS 2 node on an open zenoh session: its liveliness token, and publishers (``publisher``)
    that put CDR with rmw_zenoh's attachment. Close it to withdraw it from the graph."""

    session: zenoh.Session
    node: NodeName
    types: Ros2Types
    _zid: str = ""
    _tokens: list[Any] = field(default_factory=list)
    _entities: itertools.count = field(default_factory=lambda: itertools.count(1))

    def __post_init__(self) -> None:
        self._zid = str(self.session.info.zid())
        self._node_id = 0
        key = f"{ADMIN_SPACE}/{self.node.domain_id}/{self._zid}/{self._node_id}/{self._node_id}/NN/%/{mangle(self.node.namespace)}/{mangle(self.node.name)}"
        self._tokens.append(self.session.liveliness().declare_token(key))

    def publisher(self, topic: str, typename: str, qos: str = QOS_DEFAULT) -> Ros2Publisher:
        """A publisher on ``topic`` (absolute, e.g. ``/tf``) of ``typename`` (``tf2_msgs/msg/TFMessage``)."""
        type_hash = self.types.type_hash(typename)
        entity = next(self._entities)
        token = (
            f"{ADMIN_SPACE}/{self.node.domain_id}/{self._zid}/{self._node_id}/{entity}/MP/%/{mangle(self.node.namespace)}/"
            f"{mangle(self.node.name)}/{mangle(topic)}/{dds_type_name(typename)}/{type_hash}/{qos}"
        )
        self._tokens.append(self.session.liveliness().declare_token(token))
        key = topic_key(self.node.domain_id, topic, typename, type_hash)
        return Ros2Publisher(self.session.declare_publisher(key), typename, self.types, uuid.uuid4().bytes)

    def close(self) -> None:
        for token in self._tokens:
            token.undeclare()
        self._tokens.clear()


@dataclass
class Ros2Publisher:
    """Puts ROS 2 messages (``rosbags`` objects) on one topic."""

    publisher: Any
    typename: str
    types: Ros2Types
    gid: bytes
    sequence: int = 0

    def put(self, msg: object, stamp_ns: int | None = None) -> None:
        self.sequence += 1
        att = attachment(self.sequence, time.time_ns() if stamp_ns is None else stamp_ns, self.gid)
        self.publisher.put(self.types.serialize(msg, self.typename), attachment=att)
