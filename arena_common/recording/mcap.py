"""Recordings: MCAP files of what crossed the bus, and the tools that read them back.

This module gathers the recording API; the parts live in :mod:`.codec` (the JSON form),
:mod:`.writer` (files and the recorder), :mod:`.reader` (reading, ``info``), :mod:`.repair`, :mod:`.replay`,
:mod:`.export` and :mod:`.scene` (the Foxglove 3D scene written beside the arena channels).

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

from arena_common.recording.codec import (
    CHUNK_SIZE,
    DEFAULT_NAME,
    ENCODINGS,
    JSON,
    META_DROPS,
    META_RECORDING,
    MSGPACK,
    NS,
    RAW_FIELD,
    SCHEMA_ENCODING,
    TIME_FIELDS,
    Decoded,
    RecordingError,
    Sample,
    decode_sample,
    encode_json,
    from_json_map,
    record_schema,
    software_version,
    time_from_json,
    time_to_json,
    to_json_map,
)
from arena_common.recording.export import (
    EXPORT_FORMATS,
    export,
    flatten,
    table_name,
)
from arena_common.recording.reader import (
    ChannelInfo,
    ChannelStats,
    RecordedMessage,
    RecordingInfo,
    RecordingReader,
    Series,
    channels,
    format_info,
    info,
    load_series,
    message_bytes,
    message_map,
)
from arena_common.recording.repair import (
    RepairReport,
    repair,
    repaired_path,
)
from arena_common.recording.replay import (
    CONTROL_KEYS,
    ReplayReport,
    key_filter,
    parse_remap,
    remap_key,
    replay,
)
from arena_common.recording.writer import (
    Recorder,
    RecordingWriter,
    file_name,
)

__all__ = [
    "CHUNK_SIZE",
    "CONTROL_KEYS",
    "DEFAULT_NAME",
    "ENCODINGS",
    "EXPORT_FORMATS",
    "JSON",
    "META_DROPS",
    "META_RECORDING",
    "MSGPACK",
    "NS",
    "RAW_FIELD",
    "SCHEMA_ENCODING",
    "TIME_FIELDS",
    "ChannelInfo",
    "ChannelStats",
    "Decoded",
    "RecordedMessage",
    "Recorder",
    "RecordingError",
    "RecordingInfo",
    "RecordingReader",
    "RecordingWriter",
    "RepairReport",
    "ReplayReport",
    "Sample",
    "Series",
    "channels",
    "decode_sample",
    "encode_json",
    "export",
    "file_name",
    "flatten",
    "format_info",
    "from_json_map",
    "info",
    "key_filter",
    "load_series",
    "message_bytes",
    "message_map",
    "parse_remap",
    "record_schema",
    "remap_key",
    "repair",
    "repaired_path",
    "replay",
    "software_version",
    "table_name",
    "time_from_json",
    "time_to_json",
    "to_json_map",
]
