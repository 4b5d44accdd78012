"""An independent reader of Foxglove scenes, for tests: protobuf classes built from the schema each file
(or WebSocket advertisement) carries, decoded with Google's ``protobuf``, frames composed with numpy.

Nothing here uses the arena's recording code or the Foxglove SDK that wrote the messages.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

_classes: dict[tuple[str, bytes], Any] = {}


def message_class(name: str, fds: bytes) -> Any:
    """The protobuf class of ``name`` from a serialized ``FileDescriptorSet``."""
    cls = _classes.get((name, fds))
    if cls is None:
        pool = descriptor_pool.DescriptorPool()
        files = descriptor_pb2.FileDescriptorSet.FromString(fds)
        for f in files.file:
            pool.Add(f)
        cls = _classes[(name, fds)] = message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
    return cls


@dataclass
class Decoded:
    """The Foxglove messages of one recording, by topic: (log_time, schema name, decoded message)."""

    topics: dict[str, list[tuple[int, str, Any]]] = field(default_factory=dict)
    schemas: dict[str, str] = field(default_factory=dict)  # topic → schema name

    def last(self, topic: str) -> Any:
        """The last message of ``topic``."""
        return self.topics[topic][-1][2]


def read_foxglove(path: Path) -> Decoded:
    """Every protobuf message of a recording, decoded with the schema the file carries."""
    out = Decoded()
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding != "protobuf" or schema is None:
                continue
            assert schema.encoding == "protobuf"
            msg = message_class(schema.name, schema.data).FromString(message.data)
            out.topics.setdefault(channel.topic, []).append((message.log_time, schema.name, msg))
            out.schemas[channel.topic] = schema.name
    return out


# -- frames -----------------------------------------------------------------------------------------------


def rotation(q: Any) -> np.ndarray:
    """The 3×3 rotation matrix of a Foxglove ``Quaternion`` (x, y, z, w)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if n == 0:
        return np.eye(3)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


class Frames:
    """The latest transform of each child frame; maps points of any frame to its root."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.pose: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # child → (R, t) in its parent

    def add(self, frame_transforms: Any) -> None:
        """Take every transform of a ``FrameTransforms`` message."""
        for tf in frame_transforms.transforms:
            t = np.array([tf.translation.x, tf.translation.y, tf.translation.z])
            self.parent[tf.child_frame_id] = tf.parent_frame_id
            self.pose[tf.child_frame_id] = (rotation(tf.rotation), t)

    def to_root(self, frame: str, p: Sequence[float], *, vector: bool = False) -> np.ndarray:
        """A point (or, with ``vector``, a direction) of ``frame`` in the root frame."""
        v = np.asarray(p, dtype=float)
        while frame in self.parent:
            r, t = self.pose[frame]
            v = r @ v + (0.0 if vector else t)
            frame = self.parent[frame]
        return v

    def root(self, frame: str) -> str:
        """The root above ``frame``."""
        while frame in self.parent:
            frame = self.parent[frame]
        return frame


def entity_points(entity: Any, frames: Frames) -> np.ndarray:
    """Every line point of a ``SceneEntity`` in the root frame (pose of each line applied)."""
    pts: list[np.ndarray] = []
    for line in entity.lines:
        r = rotation(line.pose.orientation) if line.pose.HasField("orientation") else np.eye(3)
        t = np.array([line.pose.position.x, line.pose.position.y, line.pose.position.z])
        for p in line.points:
            local = r @ np.array([p.x, p.y, p.z]) + t
            pts.append(frames.to_root(entity.frame_id, local))
    return np.array(pts).reshape(-1, 3)
