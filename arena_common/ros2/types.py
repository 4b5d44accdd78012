"""ROS 2 message types: their definitions, DDS names, RIHS01 hashes and CDR, from ``rosbags``.

The message definitions are those of ROS 2 Jazzy as ``rosbags`` ships them (the types the arena uses are
the same in Kilted and Rolling: their RIHS01 hashes are equal).  Hashes are computed from those
definitions (REP-2016's RIHS01: SHA-256 of the type description), never written down by hand; the test
suite checks them against the hashes ROS 2 itself prints (``ros2 topic info -v``) and rmw_zenoh's docs.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

__all__ = [
    "BATTERY_STATE",
    "DIAGNOSTIC_ARRAY",
    "LOG",
    "ODOMETRY",
    "POSE_STAMPED",
    "TF_MESSAGE",
    "TWIST",
    "MsgType",
    "deserialize",
    "msg_type",
    "serialize",
    "stamp",
    "store",
]

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
BATTERY_STATE = "sensor_msgs/msg/BatteryState"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
LOG = "rcl_interfaces/msg/Log"
TWIST = "geometry_msgs/msg/Twist"


@functools.cache
def store() -> Typestore:
    """The type store (ROS 2 Jazzy's message definitions)."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True, slots=True)
class MsgType:
    """One message type by its three names."""

    name: str  # geometry_msgs/msg/PoseStamped
    dds: str  # geometry_msgs::msg::dds_::PoseStamped_ (what rmw_zenoh puts in keys)
    hash: str  # RIHS01_<64 hex digits>

    @property
    def definition(self) -> str:
        """The ``.msg`` text with its dependencies, as ROS 2 bags store it (``ros2msg`` schema)."""
        text, _ = store().generate_msgdef(self.name, ros_version=2)
        return text


@functools.cache
def msg_type(name: str) -> MsgType:
    """The :class:`MsgType` of ``pkg/msg/Name``; its hash computed from its definition."""
    pkg, kind, base = name.split("/")
    return MsgType(name, f"{pkg}::{kind}::dds_::{base}_", store().hash_rihs01(name))


def serialize(msg: Any, name: str) -> bytes:
    """CDR, little-endian, with its 4-byte encapsulation header (``00 01 00 00``)."""
    return bytes(store().serialize_cdr(msg, name))


def deserialize(data: bytes, name: str) -> Any:
    """A message back from CDR (either byte order, by its encapsulation header)."""
    return store().deserialize_cdr(data, name)


def stamp(t_ns: int) -> Any:
    """``builtin_interfaces/msg/Time`` of a time in ns since the epoch."""
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return cls("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def cls(name: str) -> Any:
    """The message class of ``name`` (``store().types``)."""
    return store().types[name]


def header(t_ns: int, frame_id: str) -> Any:
    """``std_msgs/msg/Header``."""
    return cls("std_msgs/msg/Header")(stamp=stamp(t_ns), frame_id=frame_id)


def nan_or(value: float | None) -> float:
    """A float field ROS reads as "unknown" when NaN."""
    return math.nan if value is None else float(value)
