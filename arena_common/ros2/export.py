"""A recording as a ROS 2 MCAP: what ``ros2 bag play``, Foxglove and PlotJuggler open as a ROS 2 bag.

The same topics and conversions as the live bridge (:mod:`arena_common.ros2.messages`): schemas of
encoding ``ros2msg`` (the ``.msg`` text with its dependencies, as rosbag2's MCAP storage writes them),
messages of encoding ``cdr`` (little-endian, with the encapsulation header), each at the time it was
recorded (``log_time``) with the measurement time as ``publish_time``; ``/tf_static`` once at the start.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from arena_common.core import keys, wire
from arena_common.core.errors import ArenaError, PayloadError
from arena_common.recording.reader import RecordingReader
from arena_common.ros2 import messages, types

__all__ = ["export_ros2"]

PROFILE = "ros2"


class _Out:
    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.count = 0

    def write(self, topic: str, type_name: str, msg: Any, log_time: int, publish_time: int) -> None:
        if topic not in self.channels:
            if type_name not in self.schemas:
                t = types.msg_type(type_name)
                self.schemas[type_name] = self.writer.register_schema(
                    name=type_name, encoding="ros2msg", data=t.definition.encode()
                )
            self.channels[topic] = self.writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=self.schemas[type_name]
            )
        self.writer.add_message(
            self.channels[topic],
            log_time=log_time,
            data=types.serialize(msg, type_name),
            publish_time=publish_time,
            sequence=self.count,
        )
        self.count += 1


def export_ros2(path: str | Path, out: str | Path, node: str = "arena") -> tuple[Path, int]:
    """Write ``out`` (a ``.mcap`` file, or a directory to put ``<stem>.ros2.mcap`` in) from the recording
    at ``path``; the file and its number of messages."""
    src = Path(path)
    target = Path(out)
    if target.suffix != ".mcap":
        target = target / f"{src.stem}.ros2.mcap"
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ArenaError(f"{target.parent}: cannot create: {exc.strerror or exc}") from None
    with open(target, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile=PROFILE, library="flying-arena")
        o = _Out(writer)
        static_done = False
        for m in RecordingReader(src).messages():
            ptype = m.channel.payload_type
            if ptype is None or m.channel.undecodable:
                continue
            try:
                parsed = keys.parse(m.channel.key)
            except ArenaError:
                continue
            v = parsed.drone
            if v is None or parsed.kind not in ("pose", "vision", "state", "events"):
                continue
            try:
                payload = ptype.decode(m.wire_bytes(), m.channel.key)
            except PayloadError:
                continue
            if not static_done:
                o.write(
                    "/tf_static", types.TF_MESSAGE, messages.static_frames(m.log_time), m.log_time, m.log_time
                )
                static_done = True
            _write(o, parsed.kind, v, payload, m.log_time, node)
        writer.finish()
    return target, o.count


def _write(o: _Out, kind: str, v: str, payload: Any, log_time: int, node: str) -> None:
    if kind in ("pose", "vision") and isinstance(payload, wire.Pose):
        if not payload.ok:
            return
        if kind == "pose":
            o.write(
                messages.topic(v, "pose"),
                types.POSE_STAMPED,
                messages.pose_stamped(payload),
                log_time,
                payload.t,
            )
            o.write("/tf", types.TF_MESSAGE, messages.tf(v, payload), log_time, payload.t)
        else:
            o.write(
                messages.topic(v, "odom"), types.ODOMETRY, messages.odometry(v, payload), log_time, payload.t
            )
    elif kind == "state" and isinstance(payload, wire.State):
        o.write(
            messages.topic(v, "battery"),
            types.BATTERY_STATE,
            messages.battery(v, payload),
            log_time,
            payload.t,
        )
        o.write("/diagnostics", types.DIAGNOSTIC_ARRAY, messages.diagnostics(v, payload), log_time, payload.t)
    elif kind == "events" and isinstance(payload, wire.Event):
        o.write("/rosout", types.LOG, messages.log(v, payload, node), log_time, payload.t)
