"""Recordings: MCAP files of what crossed the bus, and the tools that read them back.

A recording is an MCAP file (https://mcap.dev) that Foxglove, PlotJuggler and the ``mcap`` tools open:

- one **channel per Zenoh key** (created the first time the key is seen), whose metadata keeps the
  sample's Zenoh encoding (``zenoh_encoding``) and the arena schema (``arena_schema``, e.g. ``Pose/1``);
- one **schema per payload type** (``arena.Pose``…), a JSON Schema (``jsonschema`` encoding);
- messages in ``json`` (default) or ``msgpack`` (the bytes as they travelled) message encoding;
  ``log_time`` is when the recorder received the sample, ``publish_time`` the payload's own ``tp``
  (else its ``t``);
- samples that do not decode to their type are kept, byte for byte, on a second, schema-less channel of
  the same key (``undecodable = "true"`` in its metadata) and counted;
- file metadata ``arena.recording``: host, experiment name, part, software version, the config file's
  path and text; metadata ``arena.drops`` each time samples were lost because the disk fell behind.

**The JSON form** of a payload is its msgpack wire map with two changes, so that it is valid JSON and
readable in JavaScript tools: absolute times (``t``, ``tp``: integer ns since the epoch, ≈1.7e18, above
JSON's exact-integer range of 2^53) become ``{"sec": s, "nsec": ns}`` objects — the form Foxglove reads
as a time — and NaN becomes ``null``.  Replay turns the JSON back into msgpack; when that would not
reproduce the original bytes exactly (NaN inside a map, binary data, a producer's unusual msgpack
packing), the message also carries ``"_raw"``: the original msgpack, base64.  So every recording
replays byte for byte.

Crash safety: :class:`Recorder` closes the open chunk, flushes and fsyncs every ``flush_s``; after a
``kill -9`` or a power cut everything up to the last flush is readable with :class:`RecordingReader`
(which reads what it can and stops at the first torn record) and :func:`repair` writes a complete copy.
"""

from __future__ import annotations

import base64
import csv
import importlib
import importlib.metadata
import json
import logging
import math
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgpack
import zenoh
from mcap.records import Attachment, Channel, Chunk, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from arena_common.core import keys, wire
from arena_common.core.config import RecorderSpec
from arena_common.core.errors import ArenaError, InvalidName, PayloadError

JSON = "json"
MSGPACK = "msgpack"
ENCODINGS = (JSON, MSGPACK)
SCHEMA_ENCODING = "jsonschema"
META_RECORDING = "arena.recording"
META_DROPS = "arena.drops"
TIME_FIELDS = frozenset({"t", "tp"})  # absolute times (ns since the epoch) in every payload type
RAW_FIELD = "_raw"
CHUNK_SIZE = 256 * 1024
DEFAULT_NAME = "rec"
NS = 1_000_000_000

log = logging.getLogger("arena.recording")


class RecordingError(ArenaError):
    """A recording that cannot be written, read, repaired or exported; the message names the file."""


def software_version() -> str:
    """The installed ``flying-arena`` version (``unknown`` when run from an uninstalled tree)."""
    try:
        return importlib.metadata.version("flying-arena")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


# -- the JSON form ----------------------------------------------------------------------------------------


def time_to_json(ns: int) -> dict[str, int]:
    """Integer nanoseconds → ``{"sec", "nsec"}`` with ``0 <= nsec < 1e9``."""
    sec, nsec = divmod(ns, NS)
    return {"sec": sec, "nsec": nsec}


def time_from_json(value: Any) -> Any:
    """``{"sec", "nsec"}`` → integer nanoseconds; anything else is returned unchanged."""
    if isinstance(value, dict) and set(value) == {"sec", "nsec"}:
        return int(value["sec"]) * NS + int(value["nsec"])
    return value


_TIME_SCHEMA = {
    "type": "object",
    "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": NS - 1},
    },
    "required": ["sec", "nsec"],
}


def _time_fields(cls: type[wire.Payload]) -> tuple[str, ...]:
    return tuple(s.wire for _, s in cls._specs if s.wire in TIME_FIELDS and s.kind == "int")


def record_schema(cls: type[wire.Payload], encoding: str = JSON) -> dict[str, Any]:
    """The JSON Schema of ``cls`` as recorded in ``encoding``: times as ``{sec, nsec}`` in JSON."""
    schema = json.loads(json.dumps(wire.json_schema(cls)))
    props = schema["properties"]
    if encoding == JSON:
        for name in _time_fields(cls):
            props[name] = {"description": props[name].get("description", ""), **_TIME_SCHEMA}
        props[RAW_FIELD] = {
            "type": "string",
            "contentEncoding": "base64",
            "description": "The original msgpack bytes, present when the JSON form cannot reproduce them "
            "exactly (NaN inside a map, binary data, unusual packing)",
        }
    return schema


def _plain(value: Any) -> Any:
    """A msgpack value as JSON-able Python (NaN → None, bytes → base64 text, keys → text)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (bytes, bytearray)):
        return base64.b64encode(value).decode()
    return value


def to_json_map(cls: type[wire.Payload], wire_map: Mapping[str, Any]) -> dict[str, Any]:
    """The JSON form of a wire map (see the module doc); may lose what JSON cannot say."""
    times = _time_fields(cls)
    out: dict[str, Any] = {}
    for k, v in wire_map.items():
        if k in times and isinstance(v, int) and not isinstance(v, bool):
            out[k] = time_to_json(v)
        else:
            out[str(k)] = _plain(v)
    return out


def from_json_map(cls: type[wire.Payload], obj: Mapping[str, Any]) -> dict[str, Any]:
    """The wire map of a JSON form (the inverse of :func:`to_json_map` where it is faithful)."""
    nan_ok = {s.wire for _, s in cls._specs if s.nan_ok}
    times = _time_fields(cls)
    out: dict[str, Any] = {}
    for k, v in obj.items():
        if k == RAW_FIELD:
            continue
        if k in times:
            v = time_from_json(v)
        elif v is None and k in nan_ok:
            v = math.nan
        out[k] = v
    return out


def _pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False, ensure_ascii=False).encode()


def encode_json(cls: type[wire.Payload], wire_map: Mapping[str, Any], raw: bytes) -> bytes:
    """The JSON message of one sample; carries ``_raw`` when the JSON form would not replay ``raw``."""
    obj = to_json_map(cls, wire_map)
    if _pack(from_json_map(cls, obj)) != raw:
        obj[RAW_FIELD] = base64.b64encode(raw).decode()
    return _dumps(obj)


# -- decoding a sample --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Sample:
    """One sample as it came off the bus: key, payload bytes, Zenoh encoding, receive time (ns)."""

    key: str
    raw: bytes
    encoding: str
    t_recv: int


@dataclass(frozen=True, slots=True)
class Decoded:
    """A sample that decoded: its type, its msgpack map (unknown fields kept) and the typed payload."""

    cls: type[wire.Payload]
    wire_map: dict[str, Any]
    payload: wire.Payload


def decode_sample(key: str, raw: bytes, encoding: str = "") -> Decoded:
    """Decode a sample by its encoding (else its key); raise :class:`PayloadError` when it does not."""
    cls = wire.type_for_encoding(encoding) if encoding else None
    if cls is None:
        cls = wire.type_for_key(key)
    try:
        m = msgpack.unpackb(bytes(raw), raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types on bad input
        raise PayloadError(f"not valid msgpack: {exc}", key=key, type_name=cls.SCHEMA) from None
    payload = cls.from_dict(m, key)
    return Decoded(cls, m, payload)


def _publish_time(m: Mapping[str, Any], fallback: int) -> int:
    for name in ("tp", "t"):
        v = m.get(name)
        if isinstance(v, int) and not isinstance(v, bool) and 0 < v < 2**63:
            return v
    return fallback


def _message_encoding_of_raw(zenoh_encoding: str) -> str:
    return MSGPACK if zenoh_encoding.startswith(wire.ENCODING_PREFIX.rstrip(";")) else zenoh_encoding or "raw"


# -- writing one file ---------------------------------------------------------------------------------------


class RecordingWriter:
    """One MCAP file being written: channels per key, schemas per type, crash-safe :meth:`flush`.

    Not thread-safe: :class:`Recorder` serialises calls.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        encoding: str = JSON,
        metadata: Mapping[str, str] | None = None,
        chunk_size: int = CHUNK_SIZE,
        compression: CompressionType = CompressionType.ZSTD,
    ) -> None:
        if encoding not in ENCODINGS:
            raise RecordingError(f"unknown message encoding {encoding!r} (use {' or '.join(ENCODINGS)})")
        self.path = Path(path)
        self.encoding = encoding
        try:
            self._file: IO[bytes] = open(self.path, "xb")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot create: {exc.strerror or exc}") from None
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=compression)
        self._writer.start(profile="", library=f"flying-arena/{software_version()}")
        self._schemas: dict[type[wire.Payload], int] = {}
        self._channels: dict[tuple[str, str, str], int] = {}
        self._seq: dict[int, int] = {}
        self.counts: dict[str, int] = {}
        self.messages = 0
        self.undecodable = 0
        self.closed = False
        self._writer.add_metadata(META_RECORDING, dict(metadata or {}))
        self.flush()
        _fsync_dir(self.path.parent)

    @property
    def size(self) -> int:
        """Bytes handed to the file so far (the open chunk not included)."""
        return self._file.tell()

    def _schema(self, cls: type[wire.Payload]) -> int:
        sid = self._schemas.get(cls)
        if sid is None:
            data = json.dumps(record_schema(cls, self.encoding), separators=(",", ":")).encode()
            sid = self._writer.register_schema(f"arena.{cls.SCHEMA}", SCHEMA_ENCODING, data)
            self._schemas[cls] = sid
        return sid

    def _channel(self, key: str, zenoh_encoding: str, cls: type[wire.Payload] | None) -> int:
        ident = (key, zenoh_encoding, cls.SCHEMA if cls else "")
        cid = self._channels.get(ident)
        if cid is None:
            meta = {
                "zenoh_encoding": zenoh_encoding,
                "arena_schema": f"{cls.SCHEMA}/{cls.VERSION}" if cls else "",
                "undecodable": "false" if cls else "true",
            }
            if cls is None:
                cid = self._writer.register_channel(key, _message_encoding_of_raw(zenoh_encoding), 0, meta)
            else:
                cid = self._writer.register_channel(key, self.encoding, self._schema(cls), meta)
            self._channels[ident] = cid
        return cid

    def write(self, sample: Sample, decoded: Decoded | None) -> None:
        """Add one sample: decoded ones on the key's typed channel, the others raw on its raw channel."""
        if decoded is None:
            cid = self._channel(sample.key, sample.encoding, None)
            data, pt = sample.raw, sample.t_recv
            self.undecodable += 1
        else:
            cid = self._channel(sample.key, sample.encoding, decoded.cls)
            pt = _publish_time(decoded.wire_map, sample.t_recv)
            if self.encoding == JSON:
                data = encode_json(decoded.cls, decoded.wire_map, sample.raw)
            else:
                data = sample.raw
        seq = self._seq.get(cid, 0)
        self._seq[cid] = seq + 1
        self._writer.add_message(cid, log_time=sample.t_recv, data=data, publish_time=pt, sequence=seq)
        self.messages += 1
        self.counts[sample.key] = self.counts.get(sample.key, 0) + 1

    def record(self, sample: Sample) -> Decoded | None:
        """Decode and :meth:`write` one sample; returns its decoded form (``None``: kept raw)."""
        try:
            decoded: Decoded | None = decode_sample(sample.key, sample.raw, sample.encoding)
        except PayloadError:
            decoded = None
        self.write(sample, decoded)
        return decoded

    def add_drops(self, count: int, first_ns: int, last_ns: int, reason: str = "queue full") -> None:
        """Record that ``count`` samples were lost between ``first_ns`` and ``last_ns``."""
        self._writer.add_metadata(
            META_DROPS,
            {"count": str(count), "first_ns": str(first_ns), "last_ns": str(last_ns), "reason": reason},
        )

    def flush(self, fsync: bool = True) -> None:
        """Close the open chunk and push everything to the file (and to the disk with ``fsync``)."""
        self._writer.flush()
        if fsync:
            os.fsync(self._file.fileno())

    def close(self) -> None:
        """Write the summary and index, fsync and close.  Idempotent."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._file.close()


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# -- the recorder (files, splits, experiments, disk guard) ------------------------------------------------


def file_name(name: str, host: str, when: float, part: int = 1) -> str:
    """``<name>_<host>_<UTC yyyymmddThhmmssZ>[_pN].mcap``."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(when))
    return f"{name}_{host}_{stamp}" + (f"_p{part}" if part > 1 else "") + ".mcap"


class Recorder:
    """Writes samples into the current file; rotates files per experiment, by size and by duration.

    Thread-safe: the writer loop calls :meth:`write` and :meth:`tick`; a control thread may call
    :meth:`start`, :meth:`stop` and :meth:`status` (or :meth:`handle` with a command) at any time.
    ``on_event(text, severity)`` is told about file changes and disk trouble.
    """

    def __init__(
        self,
        spec: RecorderSpec,
        host: str,
        *,
        directory: str | Path | None = None,
        config_path: str = "",
        config_text: str = "",
        on_event: Callable[[str, int], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.spec = spec
        self.host = keys.validate_name(host, "host name")
        self.directory = Path(directory if directory is not None else spec.directory)
        self.config_path = config_path
        self.config_text = config_text
        self.on_event = on_event or (lambda text, sev: None)
        self.clock = clock
        self.writer: RecordingWriter | None = None
        self.name = DEFAULT_NAME
        self.part = 1
        self.state = "idle"  # idle, recording, disk_full, error
        self.reason = ""
        self.files: list[Path] = []
        self.messages = 0
        self.undecodable = 0
        self.dropped = 0
        self.lost = 0  # samples that arrived while the disk guard held writing
        self._lock = threading.RLock()
        self._last_flush = self._opened_at = clock()
        self._last_disk_check = -1e9
        self._armed: dict[str, bool] = {}
        self._drop_mark = time.time_ns()
        self._last_drop_event = -1e9

    # -- control --------------------------------------------------------------------------------------
    def start(self, name: str | None = None) -> Path | None:
        """Close the current file and start ``<name>_<host>_<time>.mcap``; ``None`` if the disk is full."""
        name = keys.validate_name(name or DEFAULT_NAME, "experiment name")
        with self._lock:
            self._close_file()
            self.name, self.part = name, 1
            return self._open()

    def stop(self) -> Path | None:
        """Close the current file and stop recording; returns the file closed, if any."""
        with self._lock:
            path = self._close_file()
            self.state, self.reason = "idle", ""
            return path

    def close(self) -> None:
        """Stop and close (on shutdown)."""
        self.stop()

    def status(self) -> dict[str, Any]:
        """What the recorder is doing: state, file, counters, keys seen in the current file."""
        with self._lock:
            w = self.writer
            return {
                "state": self.state,
                "reason": self.reason,
                "host": self.host,
                "file": str(w.path) if w else "",
                "name": self.name,
                "part": self.part,
                "messages": self.messages,
                "undecodable": self.undecodable,
                "dropped": self.dropped,
                "lost": self.lost,
                "file_messages": w.messages if w else 0,
                "file_bytes": w.size if w else 0,
                "keys": sorted(w.counts) if w else [],
                "files": [str(p) for p in self.files],
            }

    def handle(self, key: str, command: wire.Command) -> wire.CommandResult:
        """Serve the control queryable: ``start`` {name}, ``stop``, ``ping`` (status)."""
        try:
            if command.op == "start":
                name = command.args.get("name") or DEFAULT_NAME
                if not isinstance(name, str):
                    return wire.CommandResult(False, "ERROR", "start: 'name' must be a string")
                path = self.start(name)
                if path is None:
                    return wire.CommandResult(False, "FAILED", self.reason, value=self.status())
                return wire.CommandResult(True, "ACCEPTED", f"recording to {path}", value=self.status())
            if command.op == "stop":
                path = self.stop()
                text = f"closed {path}" if path else "was not recording"
                return wire.CommandResult(True, "ACCEPTED", text, value=self.status())
            if command.op == "ping":
                return wire.CommandResult(True, "ACCEPTED", self.state, value=self.status())
        except InvalidName as exc:
            return wire.CommandResult(False, "ERROR", str(exc))
        except RecordingError as exc:
            return wire.CommandResult(False, "FAILED", str(exc))
        return wire.CommandResult(False, "UNSUPPORTED", f"the recorder does not do {command.op!r}")

    # -- the writer loop ------------------------------------------------------------------------------
    def write(self, sample: Sample) -> Decoded | None:
        """Record one sample (decoded, or raw when it does not decode); returns the decoded form.

        While idle (and not watching for arming) the sample is only counted as not recorded.
        """
        if self.writer is None and not self.spec.auto_on_arm:
            with self._lock:
                if self.writer is None:
                    if self.state == "disk_full":
                        self.lost += 1
                    return None
        try:
            decoded: Decoded | None = decode_sample(sample.key, sample.raw, sample.encoding)
        except PayloadError:
            decoded = None
        with self._lock:
            if decoded is None:
                self.undecodable += 1
            elif self.spec.auto_on_arm and isinstance(decoded.payload, wire.State):
                self._watch_arming(sample.key, decoded.payload.armed)
            if self.writer is None:
                if self.state == "disk_full":
                    self.lost += 1
                return decoded
            try:
                self.writer.write(sample, decoded)
            except OSError as exc:
                self._fail(f"write failed: {exc}")
                self.lost += 1
                return decoded
            self.messages += 1
        return decoded

    def note_drops(self, total_dropped: int) -> int:
        """Tell the recorder the queue's drop counter; new drops are written into the file. Returns them."""
        with self._lock:
            new = total_dropped - self.dropped
            now = time.time_ns()
            if new <= 0:
                self._drop_mark = now
                return 0
            self.dropped = total_dropped
            if self.writer is not None:
                self.writer.add_drops(new, self._drop_mark, now)
            self._drop_mark = now
            t = self.clock()
            if t - self._last_drop_event >= 5.0:  # once per episode, not once per loop
                self._last_drop_event = t
                self.on_event(f"recorder fell behind: {new} samples dropped ({total_dropped} so far)", 4)
            return new

    def tick(self) -> None:
        """Periodic work: flush+fsync every ``flush_s``, split files, guard the disk."""
        now = self.clock()
        with self._lock:
            if now - self._last_disk_check >= min(self.spec.flush_s, 1.0):
                self._last_disk_check = now
                self._guard_disk()
            w = self.writer
            if w is None or now - self._last_flush < self.spec.flush_s:
                return
            self._last_flush = now
            try:
                w.flush()
            except OSError as exc:
                self._fail(f"flush failed: {exc}")
                return
            if w.size >= self.spec.split_mb * 1e6 or now - self._opened_at >= self.spec.split_s:
                self._close_file()
                self.part += 1
                self._open()

    # -- internals ------------------------------------------------------------------------------------
    def _free_mb(self) -> float:
        probe = self.directory
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        return shutil.disk_usage(probe).free / 1e6

    def _guard_disk(self) -> None:
        free = self._free_mb()
        if self.state == "recording" and free < self.spec.min_free_mb:
            self._close_file()
            self.state = "disk_full"
            self.reason = (
                f"only {free:.0f} MB free in {self.directory} (min_free_mb {self.spec.min_free_mb:g})"
            )
            self.on_event(f"recording stopped: {self.reason}", 2)
        elif self.state == "disk_full" and free >= self.spec.min_free_mb * 1.1 + 1:
            self.on_event(f"{free:.0f} MB free again: recording resumes", 5)
            self.part += 1
            self._open()

    def _open(self) -> Path | None:
        free = self._free_mb()
        if free < self.spec.min_free_mb:
            self.state = "disk_full"
            self.reason = (
                f"only {free:.0f} MB free in {self.directory} (min_free_mb {self.spec.min_free_mb:g})"
            )
            self.on_event(f"recording not started: {self.reason}", 2)
            return None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"{self.directory}: cannot create: {exc.strerror or exc}") from None
        now = time.time()
        path = self.directory / file_name(self.name, self.host, now, self.part)
        n = 1
        while path.exists():
            n += 1
            path = self.directory / file_name(f"{self.name}-{n}", self.host, now, self.part)
        meta = {
            "host": self.host,
            "name": self.name,
            "part": str(self.part),
            "started_ns": str(time.time_ns()),
            "version": software_version(),
            "encoding": self.spec.encoding,
            "keys": json.dumps(list(self.spec.keys)),
            "config_path": self.config_path,
            "config": self.config_text,
        }
        self.writer = RecordingWriter(path, encoding=self.spec.encoding, metadata=meta)
        self.files.append(path)
        self.state, self.reason = "recording", ""
        self._last_flush = self._opened_at = self.clock()
        self.on_event(f"recording to {path}", 6)
        return path

    def _close_file(self) -> Path | None:
        w, self.writer = self.writer, None
        if w is None:
            return None
        try:
            w.close()
        except OSError as exc:
            self.on_event(f"closing {w.path} failed: {exc}", 3)
        return w.path

    def _fail(self, reason: str) -> None:
        w, self.writer = self.writer, None
        if w is not None:
            try:
                w.close()
            except OSError:
                pass
        self.state, self.reason = "error", reason
        self.on_event(f"recording stopped: {reason}", 2)

    def _watch_arming(self, key: str, armed: bool) -> None:
        try:
            parsed = keys.parse(key)
        except InvalidName:
            return
        drone = parsed.drone or ""
        was_any = any(self._armed.values())
        known = key in self._armed
        previous = self._armed.get(key, False)
        self._armed[key] = armed
        if armed and known and not previous and not was_any:
            self._close_file()
            self.name, self.part = keys.validate_name(f"arm-{drone}", "experiment name"), 1
            self._open()


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
        return self.metadata.get("undecodable") == "true" or not self.schema_name

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
        """Messages per key, decodable and undecodable together."""
        out: dict[str, int] = {}
        for c in self.channels:
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
                c.key, c.schema_name or "-", c.message_encoding, c.zenoh_encoding, c.undecodable
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


# -- repair -------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RepairReport:
    """What :func:`repair` did."""

    source: Path
    output: Path
    messages: int
    channels: int
    source_complete: bool
    source_error: str | None


def repaired_path(path: str | Path) -> Path:
    """``x.mcap`` → ``x.repaired.mcap`` beside it."""
    p = Path(path)
    return p.with_name(p.stem + ".repaired.mcap")


def repair(path: str | Path, output: str | Path | None = None, *, force: bool = False) -> RepairReport:
    """Write a complete copy (summary, indexes) of everything readable in ``path``, beside it."""
    src = Path(path)
    out = Path(output) if output is not None else repaired_path(src)
    if out.resolve() == src.resolve():
        raise RecordingError(f"{out}: the repaired copy must not overwrite the original")
    if out.exists() and not force:
        raise RecordingError(f"{out}: exists (use --force to overwrite)")
    reader = RecordingReader(src)
    tmp = out.with_name(out.name + ".tmp")
    channel_map: dict[int, int] = {}
    schema_map: dict[tuple[str, str, bytes], int] = {}
    seen_meta = 0
    n = 0
    try:
        with open(tmp, "wb") as f:
            w = Writer(f, chunk_size=1024 * 1024, compression=CompressionType.ZSTD)
            w.start(profile="", library=f"flying-arena/{software_version()} (repaired)")

            def copy_meta() -> None:
                nonlocal seen_meta
                for name, data in reader.metadata[seen_meta:]:
                    w.add_metadata(name, data)
                seen_meta = len(reader.metadata)

            for m in reader.messages():
                copy_meta()
                c = m.channel
                cid = channel_map.get(c.id)
                if cid is None:
                    sid = 0
                    if c.schema_name:
                        skey = (c.schema_name, c.schema_encoding, c.schema_data)
                        sid = schema_map.get(skey, 0)
                        if not sid:
                            sid = schema_map[skey] = w.register_schema(*skey)
                    cid = channel_map[c.id] = w.register_channel(
                        c.key, c.message_encoding, sid, dict(c.metadata)
                    )
                w.add_message(
                    cid, log_time=m.log_time, data=m.data, publish_time=m.publish_time, sequence=m.sequence
                )
                n += 1
            copy_meta()
            for a in reader.attachments:
                w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
            w.finish()
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"{out}: cannot write: {exc.strerror or exc}") from None
    if n == 0 and reader.error and reader.header is None:
        out.unlink(missing_ok=True)
        raise RecordingError(f"{src}: nothing readable ({reader.error})")
    return RepairReport(src, out, n, len(channel_map), reader.complete, reader.error)


# -- replay -------------------------------------------------------------------------------------------------

# Left out of a replay unless asked for: they would command live vehicles (estop, setpoints) or pass
# for the system's own state (recorder control, past services' stats).
CONTROL_KEYS = ("arena/estop", "arena/*/setpoint", "arena/sys/**")


@dataclass(slots=True)
class ReplayReport:
    """What :func:`replay` sent."""

    sent: int = 0
    skipped: int = 0
    passes: int = 0
    late_max: float = 0.0  # s, the worst lateness against the schedule


def parse_remap(items: Iterable[str]) -> dict[str, str]:
    """``["arena/d1=arena/r1", …]`` → ``{"arena/d1": "arena/r1"}``; :class:`RecordingError` if malformed."""
    out: dict[str, str] = {}
    for item in items:
        a, sep, b = item.partition("=")
        a, b = a.strip().strip("/"), b.strip().strip("/")
        if not sep or not a or not b or any(c in a + b for c in "*$?#"):
            raise RecordingError(f"--remap {item!r}: expected FROM=TO with concrete key prefixes")
        out[a] = b
    return out


def remap_key(key: str, remap: Mapping[str, str]) -> str:
    """Replace the longest matching prefix (on whole chunks) of ``key``."""
    for a in sorted(remap, key=len, reverse=True):
        if key == a or key.startswith(a + "/"):
            return remap[a] + key[len(a) :]
    return key


def key_filter(
    key_exprs: Sequence[str] = ("arena/**",), include_control: bool = False
) -> Callable[[str], bool]:
    """A predicate on keys: matches one of ``key_exprs``, and is no control key unless ``include_control``."""
    try:
        exprs = [zenoh.KeyExpr(k) for k in key_exprs]
    except Exception as exc:
        raise RecordingError(f"bad key expression in {list(key_exprs)}: {exc}") from None
    control = [zenoh.KeyExpr(k) for k in CONTROL_KEYS]
    verdict: dict[str, bool] = {}

    def wanted(key: str) -> bool:
        ok = verdict.get(key)
        if ok is None:
            try:
                ke = zenoh.KeyExpr(key)
            except Exception:
                ok = False
            else:
                ok = any(e.includes(ke) for e in exprs) and (
                    include_control or not any(c.includes(ke) for c in control)
                )
            verdict[key] = ok
        return ok

    return wanted


def channels(path: str | Path) -> list[ChannelInfo]:
    """Every channel of a recording (reads it through)."""
    reader = RecordingReader(path)
    for _ in reader.messages():
        pass
    return list(reader.channels.values())


def _sleep_until(due: float, stop: threading.Event, clock: Callable[[], float]) -> bool:
    """Sleep until ``clock() >= due``; True if ``stop`` was set meanwhile.  (``time.sleep`` wakes up more
    punctually than ``Event.wait`` on a loaded machine; the stop flag is looked at every 50 ms.)"""
    while True:
        if stop.is_set():
            return True
        left = due - clock()
        if left <= 0:
            return False
        time.sleep(min(left, 0.05))


def replay(
    path: str | Path,
    publish: Callable[[str, bytes, str], None],
    *,
    speed: float = 1.0,
    key_exprs: Sequence[str] = ("arena/**",),
    remap: Mapping[str, str] | None = None,
    loop: bool = False,
    include_control: bool = False,
    stop: threading.Event | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> ReplayReport:
    """Send every matching message with ``publish(key, msgpack_bytes, zenoh_encoding)`` on its original
    schedule (by ``log_time``, divided by ``speed``), until the end (or forever with ``loop``).

    Setpoints, emergency stops and ``arena/sys/**`` are left out unless ``include_control``: replaying
    them on a live arena would command real vehicles or pass for the system's current state.
    """
    if not speed > 0 or not math.isfinite(speed):
        raise RecordingError(f"replay speed must be a positive number, got {speed}")
    stop = stop or threading.Event()
    remap = dict(remap or {})
    wanted = key_filter(key_exprs, include_control)
    report = ReplayReport()
    reader = RecordingReader(path)
    while not stop.is_set():
        t0 = 0.0
        first: int | None = None
        for m in reader.messages():
            if stop.is_set():
                break
            if not wanted(m.channel.key):
                report.skipped += 1
                continue
            data = m.wire_bytes()
            if first is None:
                first, t0 = m.log_time, clock()
            due = t0 + (m.log_time - first) / NS / speed
            if _sleep_until(due, stop, clock):
                break
            report.late_max = max(report.late_max, clock() - due)
            publish(remap_key(m.channel.key, remap), data, m.channel.zenoh_encoding)
            report.sent += 1
        report.passes += 1
        if reader.error and report.passes == 1:
            log.warning("%s: read stopped early: %s", reader.path, reader.error)
        if not loop or first is None:
            break
    return report


# -- export -------------------------------------------------------------------------------------------------

EXPORT_FORMATS = ("csv", "parquet")


def flatten(value: Any, prefix: str = "", out: dict[str, Any] | None = None) -> dict[str, Any]:
    """Nested maps and arrays as flat columns: ``{"p": [1, 2, 3]}`` → ``{"p.0": 1, "p.1": 2, "p.2": 3}``."""
    out = {} if out is None else out
    if isinstance(value, dict):
        for k, v in value.items():
            flatten(v, f"{prefix}.{k}" if prefix else str(k), out)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            flatten(v, f"{prefix}.{i}" if prefix else str(i), out)
    elif isinstance(value, (bytes, bytearray)):
        out[prefix] = bytes(value).hex()
    else:
        out[prefix] = value
    return out


def table_name(channel: ChannelInfo) -> str:
    """File stem of a channel's table: ``arena/d1/pose`` → ``arena.d1.pose``."""
    stem = channel.key.replace("/", ".")
    return stem + (".undecodable" if channel.undecodable else "")


def export(path: str | Path, out_dir: str | Path, fmt: str = "csv") -> list[Path]:
    """One table per key (``<key with dots>.csv`` or ``.parquet``) with ``log_time``, ``publish_time``
    (ns), ``t_rel`` (s since the recording's first message) and the payload's fields flattened."""
    if fmt not in EXPORT_FORMATS:
        raise RecordingError(f"unknown export format {fmt!r} (use {' or '.join(EXPORT_FORMATS)})")
    pa: Any = None
    pq: Any = None
    if fmt == "parquet":
        try:
            pa = importlib.import_module("pyarrow")
            pq = importlib.import_module("pyarrow.parquet")
        except ImportError:
            raise RecordingError(
                "parquet export needs pyarrow (pip install pyarrow); use --format csv"
            ) from None
    out = Path(out_dir)
    tables: dict[str, list[dict[str, Any]]] = {}
    columns: dict[str, dict[str, None]] = {}
    first: int | None = None
    for m in RecordingReader(path).messages():
        first = m.log_time if first is None else min(first, m.log_time)
        name = table_name(m.channel)
        row: dict[str, Any] = {"log_time": m.log_time, "publish_time": m.publish_time}
        if m.channel.undecodable:
            row["raw"] = m.data.hex()
        else:
            flatten(m.wire_map(), "", row)
        tables.setdefault(name, []).append(row)
        cols = columns.setdefault(name, {"log_time": None, "publish_time": None, "t_rel": None})
        for k in row:
            cols.setdefault(k, None)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"{out}: cannot create: {exc.strerror or exc}") from None
    written: list[Path] = []
    for name, rows in sorted(tables.items()):
        fieldnames = list(columns[name])
        for r in rows:
            r["t_rel"] = (r["log_time"] - (first or 0)) / NS
        target = out / f"{name}.{fmt}"
        if fmt == "csv":
            with open(target, "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=fieldnames, restval="", extrasaction="ignore")
                w.writeheader()
                w.writerows(rows)
        else:
            assert pa is not None and pq is not None
            arrays = {}
            for c in fieldnames:
                values = [r.get(c) for r in rows]
                try:
                    arrays[c] = pa.array(values)
                except (pa.ArrowInvalid, pa.ArrowTypeError):
                    arrays[c] = pa.array([None if v is None else str(v) for v in values])
            pq.write_table(pa.table(arrays), target)
        written.append(target)
    return written


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
        if not ok or m.channel.undecodable:
            continue
        s = out.get(key)
        if s is None:
            s = out[key] = Series(key)
        s.log_time.append(m.log_time)
        s.maps.append(m.wire_map() or {})
    meta = next((d for name, d in reader.metadata if name == META_RECORDING), {})
    return out, meta
