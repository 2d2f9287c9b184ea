"""CRTK over ROS 2: the message types, their CDR codec and type hashes, and the conversions
between telesurg messages and ROS 2 messages.

The ROS 2 types come from rosbags' Jazzy typestore (``sensor_msgs``, ``geometry_msgs``,
``std_msgs``); the two ``crtk_msgs`` types the bridge needs are registered from their ``.msg``
text (fields of the CRTK specification, collaborative-robotics ``crtk_msgs``; constants do not
enter the CDR nor the type hash). CDR (with its encapsulation header) and the RIHS01 type hashes
(REP-2016) are rosbags' (:meth:`serialize_cdr`, :meth:`deserialize_cdr`, :meth:`hash_rihs01`).

Example::

    >>> codec = Codec()
    >>> codec.type_hash("sensor_msgs/msg/JointState")[:13]
    'RIHS01_a13ee3'
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

#: crtk_msgs definitions used by the bridge: field lists of the CRTK spec
CRTK_MSGS = {
    "crtk_msgs/msg/OperatingState": "std_msgs/Header header\nstring state\nbool is_homed\nbool is_busy\n",
    "crtk_msgs/msg/StringStamped": "std_msgs/Header header\nstring string\n",
}
JOINT_STATE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
OPERATING_STATE = "crtk_msgs/msg/OperatingState"
STRING_STAMPED = "crtk_msgs/msg/StringStamped"


@dataclass(frozen=True)
class Topic:
    """One CRTK topic of an arm: ROS 2 name suffix, type, direction."""

    name: str  # after /<arm>/
    typename: str
    inbound: bool  # ROS 2 → telesurg


#: The bridge's topics, per arm (``/<arm>/<name>``)
TOPICS = (
    Topic("measured_js", JOINT_STATE, False),
    Topic("measured_cp", POSE_STAMPED, False),
    Topic("setpoint_js", JOINT_STATE, False),
    Topic("operating_state", OPERATING_STATE, False),
    Topic("servo_jp", JOINT_STATE, True),
    Topic("servo_cp", POSE_STAMPED, True),
    Topic("state_command", STRING_STAMPED, True),
)


class Codec:
    """rosbags' Jazzy typestore plus the crtk_msgs types: build, encode, decode, hash."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.store = get_typestore(Stores.ROS2_JAZZY)
        types: dict[str, Any] = {}
        for name, text in CRTK_MSGS.items():
            types.update(get_types_from_msg(text, name))
        self.store.register(types)

    def type_hash(self, typename: str) -> str:
        """REP-2016 type hash, ``RIHS01_<hex>``."""
        out: str = self.store.hash_rihs01(typename)
        return out

    def encode(self, msg: Any, typename: str) -> bytes:
        """CDR with its encapsulation header (little endian)."""
        return bytes(self.store.serialize_cdr(msg, typename))

    def decode(self, payload: bytes, typename: str) -> Any:
        """A ROS 2 message from CDR; ValueError on any malformed payload."""
        try:
            return self.store.deserialize_cdr(payload, typename)
        except Exception as exc:  # rosbags raises struct / index / unicode / its own errors
            raise ValueError(f"malformed CDR for {typename} ({len(payload)} bytes): {exc!r}") from None

    @cached_property
    def _t(self) -> dict[str, Any]:
        return self.store.types

    def header(self, stamp_ns: int, frame_id: str = "") -> Any:
        """``std_msgs/Header`` with a stamp in ns since the epoch."""
        t = self._t
        stamp = t["builtin_interfaces/msg/Time"](
            sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
        )
        return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def joint_state(
        self,
        stamp_ns: int,
        names: tuple[str, ...],
        position: tuple[float, ...],
        velocity: tuple[float, ...] = (),
        effort: tuple[float, ...] = (),
    ) -> Any:
        """``sensor_msgs/JointState``."""
        import numpy as np

        return self._t[JOINT_STATE](
            header=self.header(stamp_ns),
            name=list(names),
            position=np.array(position, dtype=np.float64),
            velocity=np.array(velocity, dtype=np.float64),
            effort=np.array(effort, dtype=np.float64),
        )

    def pose_stamped(
        self,
        stamp_ns: int,
        frame: str,
        position: tuple[float, float, float],
        quat: tuple[float, float, float, float],
    ) -> Any:
        """``geometry_msgs/PoseStamped`` (quaternion ``[x, y, z, w]``)."""
        t = self._t
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=position[0], y=position[1], z=position[2]),
            orientation=t["geometry_msgs/msg/Quaternion"](x=quat[0], y=quat[1], z=quat[2], w=quat[3]),
        )
        return t[POSE_STAMPED](header=self.header(stamp_ns, frame), pose=pose)

    def operating_state(self, stamp_ns: int, state: str, is_homed: bool, is_busy: bool) -> Any:
        """``crtk_msgs/OperatingState``."""
        return self._t[OPERATING_STATE](
            header=self.header(stamp_ns), state=state, is_homed=is_homed, is_busy=is_busy
        )

    def string_stamped(self, stamp_ns: int, text: str) -> Any:
        """``crtk_msgs/StringStamped``."""
        return self._t[STRING_STAMPED](header=self.header(stamp_ns), string=text)


def stamp_ns(header: Any) -> int:
    """ns since the epoch of a decoded ``std_msgs/Header``."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
