"""Reading recordings, also unfinished ones: :class:`RecordingReader`, :func:`info`, :func:`load_series`."""

from __future__ import annotations

import base64
import json
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import zenoh
from mcap.records import Attachment, Channel, Chunk, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from arena_common.core import wire
from arena_common.recording.codec import (
    JSON,
    META_DROPS,
    META_RECORDING,
    MSGPACK,
    NS,
    RAW_FIELD,
    RecordingError,
    _pack,
    from_json_map,
)

# -- reading ------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ChannelInfo:
    """A channel of a recording: its key, encodings and schema."""

    id: int
    key: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    metadata: Mapping[str, str]

    @property
    def zenoh_encoding(self) -> str:
        """The Zenoh encoding the samples had on the bus."""
        return self.metadata.get("zenoh_encoding", "")

    @property
    def undecodable(self) -> bool:
        """True for the raw channel of samples that did not decode."""
        return not self.scene and (self.metadata.get("undecodable") == "true" or not self.schema_name)

    @property
    def scene(self) -> bool:
        """True for a channel of the Foxglove 3D scene (derived from the samples, not a bus key)."""
        return self.metadata.get("arena_scene") == "true"

    @property
    def payload_type(self) -> type[wire.Payload] | None:
        """The arena payload type of the channel, if it has one."""
        name = self.metadata.get("arena_schema", "").partition("/")[0]
        if not name and self.schema_name.startswith("arena."):
            name = self.schema_name[len("arena.") :]
        return wire.REGISTRY.get(name) if name else None


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One message of a recording."""

    channel: ChannelInfo
    log_time: int
    publish_time: int
    sequence: int
    data: bytes

    def wire_bytes(self) -> bytes:
        """The payload's msgpack bytes as they travelled (re-encoded from JSON when recorded as JSON)."""
        return message_bytes(self.channel, self.data)

    def wire_map(self) -> dict[str, Any] | None:
        """The decoded wire map (times as integer ns); ``None`` for undecodable samples."""
        if self.channel.undecodable:
            return None
        return message_map(self.channel, self.data)


def message_bytes(channel: ChannelInfo, data: bytes) -> bytes:
    """The original msgpack bytes of a recorded message."""
    if channel.message_encoding != JSON or channel.undecodable:
        return data
    obj = json.loads(data)
    if RAW_FIELD in obj:
        return base64.b64decode(obj[RAW_FIELD])
    cls = channel.payload_type
    if cls is None:
        raise RecordingError(f"channel {channel.key}: JSON without a known arena schema")
    return _pack(from_json_map(cls, obj))


def message_map(channel: ChannelInfo, data: bytes) -> dict[str, Any]:
    """The wire map of a recorded message (times as integer ns, NaN restored)."""
    if channel.message_encoding == JSON:
        obj = json.loads(data)
        if RAW_FIELD in obj:
            return dict(msgpack.unpackb(base64.b64decode(obj[RAW_FIELD]), raw=False, strict_map_key=False))
        cls = channel.payload_type
        return from_json_map(cls, obj) if cls else obj
    if channel.message_encoding == MSGPACK:
        return dict(msgpack.unpackb(data, raw=False, strict_map_key=False))
    raise RecordingError(
        f"channel {channel.key}: cannot decode message encoding {channel.message_encoding!r}"
    )


class RecordingReader:
    """Reads a recording front to back, also one its recorder never finished (killed, power cut).

    Iterate :meth:`messages`; meanwhile :attr:`channels`, :attr:`metadata` and :attr:`attachments` fill
    in, and at the end :attr:`complete` says whether the file had its footer and :attr:`error` why
    reading stopped early (a torn last chunk is expected after a crash).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"{self.path}: no such file")
        self.header: Header | None = None
        self.channels: dict[int, ChannelInfo] = {}
        self.metadata: list[tuple[str, dict[str, str]]] = []
        self.attachments: list[Attachment] = []
        self.complete = False
        self.error: str | None = None
        self.chunks = 0
        self.orphans = 0  # messages on a channel never declared

    def file_metadata(self) -> dict[str, str]:
        """The ``arena.recording`` metadata (host, name, version, config…), read from the file's head."""
        if not self.metadata:
            for _ in self.messages():
                if self.metadata:
                    break
        for name, data in self.metadata:
            if name == META_RECORDING:
                return data
        return {}

    def messages(self) -> Iterator[RecordedMessage]:
        """Every readable message, in file order (the order they were received)."""
        self.channels, self.metadata, self.attachments = {}, [], []
        self.complete, self.error, self.chunks, self.orphans = False, None, 0, 0
        schemas: dict[int, Schema] = {}
        with open(self.path, "rb") as f:
            reader = StreamReader(f, emit_chunks=True, record_size_limit=1 << 30)
            records = reader.records
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    break
                except Exception as exc:  # a torn or corrupt tail: stop here
                    self.error = _describe(exc, self.path)
                    return
                if isinstance(rec, Chunk):
                    try:
                        inner = breakup_chunk(rec, validate_crc=True)
                    except Exception as exc:
                        self.error = f"chunk {self.chunks + 1} unreadable: {_describe(exc, self.path)}"
                        return
                    self.chunks += 1
                    for r in inner:
                        yield from self._record(r, schemas)
                elif isinstance(rec, Footer):
                    self.complete = True
                else:
                    yield from self._record(rec, schemas)

    def _record(self, rec: Any, schemas: dict[int, Schema]) -> Iterator[RecordedMessage]:
        if isinstance(rec, Message):
            ch = self.channels.get(rec.channel_id)
            if ch is None:
                self.orphans += 1
                return
            yield RecordedMessage(ch, rec.log_time, rec.publish_time, rec.sequence, rec.data)
        elif isinstance(rec, Schema):
            schemas.setdefault(rec.id, rec)
        elif isinstance(rec, Channel):
            if rec.id not in self.channels:
                s = schemas.get(rec.schema_id)
                self.channels[rec.id] = ChannelInfo(
                    rec.id,
                    rec.topic,
                    rec.message_encoding,
                    s.name if s else "",
                    s.encoding if s else "",
                    bytes(s.data) if s else b"",
                    dict(rec.metadata),
                )
        elif isinstance(rec, Metadata):
            self.metadata.append((rec.name, dict(rec.metadata)))
        elif isinstance(rec, Attachment):
            self.attachments.append(rec)
        elif isinstance(rec, Header):
            self.header = rec


def _describe(exc: BaseException, path: Path) -> str:
    text = str(exc) or type(exc).__name__
    if "magic" in text.lower() or type(exc).__name__ == "InvalidMagic":
        return f"{path}: not an MCAP file"
    return f"{type(exc).__name__}: {text}"


# -- info ---------------------------------------------------------------------------------------------------


@dataclass(slots=True)
class ChannelStats:
    """Counts and timing of one channel."""

    key: str
    schema: str
    encoding: str
    zenoh_encoding: str
    undecodable: bool
    scene: bool = False
    count: int = 0
    first: int = 0
    last: int = 0
    max_gap: int = 0  # ns, largest log_time step
    max_gap_at: int = 0  # log_time where that gap ended

    @property
    def rate(self) -> float:
        """Mean rate over the channel's own span (Hz)."""
        span = (self.last - self.first) / NS
        return (self.count - 1) / span if self.count > 1 and span > 0 else 0.0


@dataclass(slots=True)
class RecordingInfo:
    """What ``arena rec info`` shows."""

    path: Path
    size: int
    complete: bool
    error: str | None
    chunks: int
    start: int
    end: int
    messages: int
    channels: list[ChannelStats]
    drops: list[dict[str, str]]
    meta: dict[str, str]

    @property
    def duration(self) -> float:
        """Seconds from the first to the last message."""
        return (self.end - self.start) / NS if self.messages else 0.0

    @property
    def dropped(self) -> int:
        """Samples the recorder lost (queue full), per the file's drop records."""
        return sum(int(d.get("count", "0")) for d in self.drops)

    def counts_by_key(self) -> dict[str, int]:
        """Messages per bus key, decodable and undecodable together (the 3D scene's topics left out)."""
        out: dict[str, int] = {}
        for c in self.channels:
            if c.scene:
                continue
            out[c.key] = out.get(c.key, 0) + c.count
        return out


def info(path: str | Path) -> RecordingInfo:
    """Scan a recording: channels, counts, rates, largest gaps, drop records, metadata."""
    reader = RecordingReader(path)
    stats: dict[int, ChannelStats] = {}
    start, end, n = 0, 0, 0
    for m in reader.messages():
        s = stats.get(m.channel.id)
        if s is None:
            c = m.channel
            s = stats[c.id] = ChannelStats(
                c.key, c.schema_name or "-", c.message_encoding, c.zenoh_encoding, c.undecodable, c.scene
            )
            s.first = m.log_time
        else:
            gap = m.log_time - s.last
            if gap > s.max_gap:
                s.max_gap, s.max_gap_at = gap, m.log_time
        s.last = m.log_time
        s.count += 1
        start = m.log_time if n == 0 else min(start, m.log_time)
        end = max(end, m.log_time)
        n += 1
    meta = next((d for name, d in reader.metadata if name == META_RECORDING), {})
    return RecordingInfo(
        path=reader.path,
        size=reader.path.stat().st_size,
        complete=reader.complete,
        error=reader.error,
        chunks=reader.chunks,
        start=start,
        end=end,
        messages=n,
        channels=sorted(stats.values(), key=lambda c: (c.key, c.undecodable)),
        drops=[d for name, d in reader.metadata if name == META_DROPS],
        meta=meta,
    )


def _utc(ns: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ns / NS)) + f".{(ns % NS) // 1_000_000:03d} UTC"


def format_info(ri: RecordingInfo) -> str:
    """Human-readable report of :func:`info`."""
    lines = [f"file:      {ri.path} ({ri.size / 1e6:.2f} MB, {ri.chunks} chunks)"]
    if ri.complete:
        lines.append("state:     complete")
    else:
        why = f": {ri.error}" if ri.error else ""
        lines.append(
            f"state:     NOT finalized (recorder running or killed){why}; `arena rec repair` fixes it"
        )
    if ri.meta:
        lines.append(
            f"recorded:  by {ri.meta.get('host', '?')} ({ri.meta.get('name', '?')} part "
            f"{ri.meta.get('part', '?')}), flying-arena {ri.meta.get('version', '?')}, "
            f"encoding {ri.meta.get('encoding', '?')}, config {ri.meta.get('config_path') or '-'}"
        )
    if ri.messages:
        lines.append(f"time:      {_utc(ri.start)} → {_utc(ri.end)} ({ri.duration:.3f} s)")
    lines.append(f"messages:  {ri.messages} on {len(ri.channels)} channels")
    width = max([len(c.key) for c in ri.channels] + [3])
    lines.append(
        f"  {'key':<{width}}  {'schema':<20} {'enc':<11} {'count':>8} {'rate Hz':>9} {'max gap s':>10}"
    )
    for c in ri.channels:
        schema = "(undecodable)" if c.undecodable else c.schema
        lines.append(
            f"  {c.key:<{width}}  {schema:<20} {c.encoding:<11} {c.count:>8} {c.rate:>9.1f} "
            f"{c.max_gap / NS:>10.3f}"
        )
    scene = [c for c in ri.channels if c.scene]
    if scene:
        lines.append(
            f"3D scene:  {sum(c.count for c in scene)} Foxglove messages on {len(scene)} topics "
            "(open the file in Foxglove: docs/viewer.md)"
        )
    bad = sum(c.count for c in ri.channels if c.undecodable)
    if bad:
        lines.append(f"undecodable: {bad} samples kept raw")
    if ri.drops:
        lines.append(f"DROPS:     {ri.dropped} samples lost in {len(ri.drops)} episodes (disk too slow)")
        for d in ri.drops:
            lines.append(
                f"  {d.get('count')} between {_utc(int(d.get('first_ns', '0')))} and "
                f"{_utc(int(d.get('last_ns', '0')))} ({d.get('reason', '')})"
            )
    else:
        lines.append("drops:     none")
    return "\n".join(lines)


def channels(path: str | Path) -> list[ChannelInfo]:
    """Every channel of a recording (reads it through)."""
    reader = RecordingReader(path)
    for _ in reader.messages():
        pass
    return list(reader.channels.values())


# -- helpers for analysis (plots) ---------------------------------------------------------------------------


@dataclass(slots=True)
class Series:
    """The decoded messages of one key: receive times (ns) and wire maps, in file order."""

    key: str
    log_time: list[int] = field(default_factory=list)
    maps: list[dict[str, Any]] = field(default_factory=list)


def load_series(
    path: str | Path, key_exprs: Sequence[str] = ("arena/**",)
) -> tuple[dict[str, Series], dict[str, str]]:
    """Every decodable message of the keys matching ``key_exprs``, grouped by key; and the file metadata."""
    exprs = [zenoh.KeyExpr(k) for k in key_exprs]
    reader = RecordingReader(path)
    out: dict[str, Series] = {}
    verdict: dict[str, bool] = {}
    for m in reader.messages():
        key = m.channel.key
        ok = verdict.get(key)
        if ok is None:
            try:
                ok = verdict[key] = any(e.includes(zenoh.KeyExpr(key)) for e in exprs)
            except Exception:
                ok = verdict[key] = False
        if not ok or m.channel.undecodable or m.channel.scene:
            continue
        s = out.get(key)
        if s is None:
            s = out[key] = Series(key)
        s.log_time.append(m.log_time)
        s.maps.append(m.wire_map() or {})
    meta = next((d for name, d in reader.metadata if name == META_RECORDING), {})
    return out, meta
