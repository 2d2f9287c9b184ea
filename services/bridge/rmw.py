"""The rmw_zenoh wire format: what a ROS 2 node running ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` puts on
zenoh, so a bridge can be one of its peers (ros2/rmw_zenoh ``docs/design.md``).

* **Data**: a topic is the key expression ``<domain>/<topic>/<dds type>/<type hash>`` — the fully
  qualified topic without its leading ``/``, the DDS type name (``sensor_msgs::msg::dds_::JointState_``)
  and the type's REP-2016 hash (``RIHS01_<sha256 hex>``); the payload is the message in CDR with its
  4-byte encapsulation header (``00 01 00 00``, little endian).
* **Attachment** of every sample, in zenoh-ext serialization: the publisher's sequence number
  (int64), the source timestamp (int64, ns since the Unix epoch) and the publisher's 16-byte GID
  (a length-prefixed byte array).
* **Discovery**: each node and each publisher / subscription holds a liveliness token under
  ``@ros2_lv/<domain>/<zenoh session id>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>``
  (kind ``NN`` node, ``MP`` publisher, ``MS`` subscription), an endpoint's followed by
  ``/<topic>/<dds type>/<type hash>/<qos>``; ``/`` inside a name is written ``%`` and an empty
  name (the root namespace, no enclave) is ``%``. The QoS is
  ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>``
  with an empty field for each default (reliable, volatile, keep-last).

Pure functions: no session, no I/O (the bridge, :mod:`telesurg.services.bridge.ros2`, declares them).

Example::

    >>> topic_key(0, "/arm1/measured_js", "sensor_msgs/msg/JointState", "RIHS01_ab")
    '0/arm1/measured_js/sensor_msgs::msg::dds_::JointState_/RIHS01_ab'
"""

from __future__ import annotations

import re
import secrets
from dataclasses import dataclass

from telesurg.shared.errors import ConfigError

ADMIN_SPACE = "@ros2_lv"
#: GID size of rmw_zenoh (``RMW_GID_STORAGE_SIZE``), bytes
GID_BYTES = 16
#: QoS of every bridge endpoint: reliable, volatile, keep-last 10 (rmw_zenoh's default profile,
#: written as empty fields except the depth)
DEFAULT_QOS = "::,10:,:,:,,"
ENTITY_KINDS = ("NN", "MP", "MS", "SS", "SC")
_TYPENAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/msg/([A-Za-z][A-Za-z0-9_]*)$")
_TOPIC = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/JointState`` → ``sensor_msgs::msg::dds_::JointState_``."""
    m = _TYPENAME.match(typename)
    if not m:
        raise ConfigError(f"ROS 2 type {typename!r} must look like pkg/msg/Name")
    return f"{m.group(1)}::msg::dds_::{m.group(2)}_"


def check_topic(topic: str) -> str:
    """A fully qualified ROS 2 topic name (``/arm1/measured_js``); ConfigError otherwise."""
    if not _TOPIC.match(topic):
        raise ConfigError(f"ROS 2 topic {topic!r} must be fully qualified: /name[/name...]")
    return topic


def mangle(name: str) -> str:
    """A name inside a liveliness key: ``/`` → ``%``; empty (or ``/``) → ``%``."""
    return name.replace("/", "%") if name not in ("", "/") else "%"


def topic_key(domain: int, topic: str, typename: str, type_hash: str) -> str:
    """Data key expression of ``topic`` (``<domain>/<topic>/<dds type>/<hash>``)."""
    return f"{domain}/{check_topic(topic)[1:]}/{dds_type_name(typename)}/{type_hash}"


def new_gid() -> bytes:
    """A fresh publisher GID (16 random bytes)."""
    return secrets.token_bytes(GID_BYTES)


def encode_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """The attachment of one sample: sequence number, source timestamp, GID (zenoh-ext serialized)."""
    from zenoh.ext import Int64, z_serialize

    if len(gid) != GID_BYTES:
        raise ValueError(f"a GID is {GID_BYTES} bytes, got {len(gid)}")
    out: bytes = z_serialize((Int64(seq), Int64(stamp_ns), gid)).to_bytes()
    return out


#: bytes of an attachment: two int64, the GID's length (one LEB128 byte) and the GID
ATTACHMENT_BYTES = 8 + 8 + 1 + GID_BYTES


def decode_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """``(sequence number, source timestamp ns, gid)`` of an attachment; ValueError if malformed.
    Bytes after the first :data:`ATTACHMENT_BYTES` are ignored (seen on a loaded host: an
    attachment padded to a multiple of 8 bytes in transit; nothing the bridge uses is in them)."""
    from zenoh import ZBytes
    from zenoh.ext import Int64, ZDeserializeError, z_deserialize

    if len(raw) < ATTACHMENT_BYTES:
        raise ValueError(f"rmw_zenoh attachment of {len(raw)} bytes, expected {ATTACHMENT_BYTES}")
    try:
        seq, ts, gid = z_deserialize(tuple[Int64, Int64, bytes], ZBytes(raw[:ATTACHMENT_BYTES]))
    except (ZDeserializeError, TypeError) as exc:
        raise ValueError(f"malformed rmw_zenoh attachment ({len(raw)} bytes): {exc}") from None
    if len(gid) != GID_BYTES:
        raise ValueError(f"attachment GID is {len(gid)} bytes, not {GID_BYTES}")
    return int(seq), int(ts), bytes(gid)


@dataclass(frozen=True)
class RosNode:
    """One ROS 2 node as rmw_zenoh announces it: domain, zenoh session id, node id, names."""

    domain: int
    zid: str
    node_id: int
    name: str
    namespace: str = ""  # "" or "/": the root namespace
    enclave: str = ""

    def _prefix(self, entity_id: int, kind: str) -> str:
        if kind not in ENTITY_KINDS:
            raise ValueError(f"entity kind {kind!r}; valid: {', '.join(ENTITY_KINDS)}")
        return (
            f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(self.name)}"
        )

    def token(self) -> str:
        """The node's own liveliness token (kind ``NN``, entity id = node id)."""
        return self._prefix(self.node_id, "NN")

    def endpoint_token(
        self, entity_id: int, kind: str, topic: str, typename: str, type_hash: str, qos: str = DEFAULT_QOS
    ) -> str:
        """Liveliness token of a publisher (``MP``) or subscription (``MS``) of this node."""
        return (
            f"{self._prefix(entity_id, kind)}/{mangle(check_topic(topic))}/{dds_type_name(typename)}/"
            f"{type_hash}/{qos}"
        )
