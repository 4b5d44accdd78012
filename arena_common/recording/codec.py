"""The JSON form of payloads and the decoding of samples (see :mod:`arena_common.recording.mcap`)."""

from __future__ import annotations

import base64
import importlib
import importlib.metadata
import json
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgpack

from arena_common.core import wire
from arena_common.core.errors import ArenaError, PayloadError

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
    items = {s.wire: s.item for _, s in cls._specs if s.item is not None}
    out: dict[str, Any] = {}
    for k, v in obj.items():
        if k == RAW_FIELD:
            continue
        if k in times:
            v = time_from_json(v)
        elif v is None and k in nan_ok:
            v = math.nan
        elif k in items and isinstance(v, list):  # elements' own NaN fields
            v = [from_json_map(items[k], e) if isinstance(e, Mapping) else e for e in v]
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
