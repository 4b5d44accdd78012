"""A recording as a ROS 2 MCAP: what ``ros2 bag play``, Foxglove and PlotJuggler open as a ROS 2 bag.

The same topics and conversions as the live bridge (the published rows of :mod:`arena_common.ros2.topics`,
looped over here as the bridge loops over them): schemas of
encoding ``ros2msg`` (the ``.msg`` text with its dependencies, as rosbag2's MCAP storage writes them),
messages of encoding ``cdr`` (little-endian, with the encapsulation header), each at the time it was
recorded (``log_time``) with the measurement time as ``publish_time``; the bridge's own topics
(``/tf_static``) once at the start.  A recorded sample that does not decode, or carries another payload
type than its key's, is left out, counted, and reported (a warning naming its key and why).
"""

from __future__ import annotations

import functools
import logging
from collections import Counter
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from arena_common.bus.session import Received, typed
from arena_common.core import keys
from arena_common.core.errors import ArenaError, PayloadError
from arena_common.recording.reader import RecordingReader
from arena_common.ros2 import topics, types

__all__ = ["export_ros2"]

PROFILE = "ros2"
log = logging.getLogger("arena.ros2.export")


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
    sources = topics.sources()
    own = sources.pop(None, ())
    skipped: Counter[tuple[str, str]] = Counter()  # (key, bad_payload | wrong_type) → samples
    first: dict[tuple[str, str], str] = {}  # … → the first one's detail

    def skip(key: str, kind: str, detail: str) -> None:
        skipped[key, kind] += 1
        first.setdefault((key, kind), detail)

    with open(target, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile=PROFILE, library="flying-arena")
        o = _Out(writer)
        own_done = False
        for m in RecordingReader(src).messages():
            if m.channel.scene:
                continue
            key = m.channel.key
            try:
                parsed = keys.parse(key)
            except ArenaError:
                continue
            v, rows = parsed.drone, sources.get(parsed.kind, ())
            expected = rows[0].payload if rows else None
            if v is None or expected is None:
                continue
            ptype = m.channel.payload_type
            if ptype is None or m.channel.undecodable:
                skip(key, "bad_payload", "recorded as undecodable (its raw bytes kept, no payload type)")
                continue
            try:
                item: Received[Any] = Received(key, ptype.decode(m.wire_bytes(), key), m.log_time)
            except PayloadError as exc:
                item = Received(key, None, m.log_time, exc)
            payload: Any = typed(item, expected, functools.partial(skip, key))  # Pose, State, Event: a .t
            if payload is None:
                continue
            if not own_done:
                for row in own:
                    o.write(
                        row.topic(), row.msg_type, row.convert("", m.log_time, node), m.log_time, m.log_time
                    )
                own_done = True
            if not topics.published(payload):
                continue
            for row in rows:
                o.write(row.topic(v), row.msg_type, row.convert(v, payload, node), m.log_time, payload.t)
        writer.finish()
    for (key, kind), n in sorted(skipped.items()):
        log.warning("%s: %d sample(s) not exported (%s): %s", key, n, kind, first[key, kind])
    return target, o.count
