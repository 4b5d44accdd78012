"""Writing recordings: one MCAP file (:class:`RecordingWriter`) and the recorder that rotates files
(:class:`Recorder`: experiments, splits, disk guard).
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer

from arena_common.core import keys, wire
from arena_common.core.config import ArenaSpec, RecorderSpec
from arena_common.core.errors import InvalidName, PayloadError
from arena_common.recording.codec import (
    CHUNK_SIZE,
    DEFAULT_NAME,
    ENCODINGS,
    JSON,
    META_DROPS,
    META_RECORDING,
    SCHEMA_ENCODING,
    Decoded,
    RecordingError,
    Sample,
    _message_encoding_of_raw,
    _publish_time,
    decode_sample,
    encode_json,
    record_schema,
    software_version,
)
from arena_common.recording.scene import ENCODING as SCENE_ENCODING
from arena_common.recording.scene import Scene, SceneMessage, arena_from_config_text
from arena_common.recording.scene import schemas as scene_schemas

# -- writing one file ---------------------------------------------------------------------------------------


class RecordingWriter:
    """One MCAP file being written: channels per key, schemas per type, crash-safe :meth:`flush`.

    With a ``scene`` (:class:`~arena_common.recording.scene.Scene`), the Foxglove 3D scene built from
    the decoded samples is written beside them, on its own ``protobuf`` channels (metadata
    ``arena_scene = "true"``).  Not thread-safe: :class:`Recorder` serialises calls.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        encoding: str = JSON,
        metadata: Mapping[str, str] | None = None,
        chunk_size: int = CHUNK_SIZE,
        compression: CompressionType = CompressionType.ZSTD,
        scene: Scene | None = None,
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
        self.scene = scene
        self.scene_messages = 0
        self._last_recv = 0
        self._scene_schemas: dict[str, int] = {}
        self._scene_channels: dict[str, int] = {}
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
        self._last_recv = max(self._last_recv, sample.t_recv)
        if self.scene is not None:
            out = self.scene.add(sample.key, decoded.payload, sample.t_recv) if decoded is not None else []
            for m in out + self.scene.tick(sample.t_recv):
                self.write_scene(m)

    def write_scene(self, m: SceneMessage) -> None:
        """Add one Foxglove scene message on its topic's channel."""
        cid = self._scene_channels.get(m.topic)
        if cid is None:
            sid = self._scene_schemas.get(m.schema)
            if sid is None:
                s = scene_schemas()[m.schema]
                sid = self._scene_schemas[m.schema] = self._writer.register_schema(s.name, s.encoding, s.data)
            cid = self._scene_channels[m.topic] = self._writer.register_channel(
                m.topic, SCENE_ENCODING, sid, {"arena_scene": "true"}
            )
        seq = self._seq.get(cid, 0)
        self._seq[cid] = seq + 1
        self._writer.add_message(cid, log_time=m.log_time, data=m.data, publish_time=m.log_time, sequence=seq)
        self.scene_messages += 1

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
            if self.scene is not None and self._last_recv:
                for m in self.scene.flush(self._last_recv):
                    self.write_scene(m)
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
    ``on_event(text, severity)`` is told about file changes and disk trouble.  Each file carries the
    Foxglove 3D scene of ``arena`` (else the arena of ``config_text``) unless ``scene`` is false.
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
        arena: ArenaSpec | None = None,
        scene: bool = True,
    ) -> None:
        self.spec = spec
        self.host = keys.validate_name(host, "host name")
        self.directory = Path(directory if directory is not None else spec.directory)
        self.config_path = config_path
        self.config_text = config_text
        # the room drawn in each file's 3D scene: the given arena, else the config text's
        self.arena = arena or arena_from_config_text(config_text, config_path)
        self.scene = scene
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
        self.writer = RecordingWriter(
            path, encoding=self.spec.encoding, metadata=meta, scene=Scene(self.arena) if self.scene else None
        )
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
