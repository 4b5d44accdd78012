"""The wire contract for other languages, generated from the code: JSON Schemas, golden vectors, ``wire.md``.

``python -m tools.wiredoc`` writes

* ``docs/schemas/arena.<Type>.json`` — each payload's JSON Schema (:func:`arena_common.core.wire.json_schema`);
* ``tests/golden/<name>.json`` — golden vectors: representative payloads as msgpack bytes (hex) beside their
  decoded JSON value, for checking a decoder written in another language;
* ``docs/wire.md`` — the document for someone subscribing from C, Rust or JavaScript: keys, QoS, encodings,
  conventions, one field table and worked example per payload type, commands and presence.

The vectors themselves are in :mod:`tools.vectors`.

``python -m tools.wiredoc --check`` writes nothing and exits 1 listing the files that drift from
the code (changed, missing or stale), so CI catches a payload change without its documentation.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import struct
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from arena_common.bus import sequence
from arena_common.core import keys, wire
from arena_common.core.ops import OPS
from tools.vectors import Vector, WireDocError, vectors

ROOT = Path(__file__).resolve().parent.parent
SCHEMA_DIR = "docs/schemas"
GOLDEN_DIR = "tests/golden"
WIRE_MD = "docs/wire.md"
_REGENERATE = "python -m tools.wiredoc"


# -- file generation -----------------------------------------------------------------------------------


def _dump(obj: Any) -> str:
    return json.dumps(obj, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def _compact(v: Any) -> str:
    return json.dumps(v, ensure_ascii=False, allow_nan=False, separators=(", ", ": "))


def payload_json(data: dict[str, Any], indent: str = "") -> str:
    """A payload's JSON with one field per line (values on one line), as in the vectors and ``wire.md``;
    an array of maps (an ``items`` field) has one element per line."""
    if not data:
        return "{}"
    body = ",\n".join(f"{indent}  {_compact(k)}: {_field_json(v, indent + '  ')}" for k, v in data.items())
    return "{\n" + body + "\n" + indent + "}"


def _field_json(v: Any, indent: str) -> str:
    if not (isinstance(v, list) and v and all(isinstance(e, dict) for e in v)):
        return _compact(v)
    return "[\n" + ",\n".join(f"{indent}  {_compact(e)}" for e in v) + "\n" + indent + "]"


def _vector_text(vec: Vector) -> str:
    doc = vec.as_json()
    lines = [
        f"  {_compact(k)}: {payload_json(v, '  ') if k == 'json' else _compact(v)}" for k, v in doc.items()
    ]
    return "{\n" + ",\n".join(lines) + "\n}\n"


def schema_files() -> dict[str, str]:
    """``docs/schemas/arena.<Type>.json`` for every registered payload type."""
    return {
        f"{SCHEMA_DIR}/arena.{name}.json": _dump(wire.json_schema(cls)) for name, cls in wire.REGISTRY.items()
    }


def vector_files() -> dict[str, str]:
    """``tests/golden/<name>.json`` for every golden vector."""
    return {f"{GOLDEN_DIR}/{v.name}.json": _vector_text(v) for v in vectors()}


def generated() -> dict[str, str]:
    """Every generated file: path relative to the repository root → content."""
    return {**schema_files(), **vector_files(), WIRE_MD: render_wire_md()}


def _owned(root: Path) -> set[str]:
    """Generated-looking files already on disk (stale ones are reported and removed)."""
    found = {p.relative_to(root).as_posix() for p in (root / SCHEMA_DIR).glob("arena.*.json")}
    found |= {p.relative_to(root).as_posix() for p in (root / GOLDEN_DIR).glob("*.json")}
    return found


def drift(root: Path = ROOT) -> list[str]:
    """Files that differ from what the code generates now, each with why (changed, missing, stale)."""
    want = generated()
    out = []
    for rel, text in sorted(want.items()):
        path = root / rel
        if not path.is_file():
            out.append(f"{rel} (missing)")
        elif path.read_text(encoding="utf-8") != text:
            out.append(f"{rel} (changed)")
    out.extend(f"{rel} (stale)" for rel in sorted(_owned(root) - set(want)))
    return out


def write(root: Path = ROOT) -> list[str]:
    """Write every generated file that changed and remove stale ones; return the paths touched."""
    want = generated()
    touched = []
    for rel, text in sorted(want.items()):
        path = root / rel
        if path.is_file() and path.read_text(encoding="utf-8") == text:
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        touched.append(rel)
    for rel in sorted(_owned(root) - set(want)):
        (root / rel).unlink()
        touched.append(rel)
    return touched


# -- msgpack annotation (for the worked example) -------------------------------------------------------


def annotate(raw: bytes) -> list[tuple[int, bytes, int, str]]:
    """Walk msgpack bytes: ``(offset, bytes of the item's header and scalar body, depth, meaning)`` rows."""
    rows: list[tuple[int, bytes, int, str]] = []
    pos = _annotate_item(raw, 0, 0, rows)
    if pos != len(raw):
        raise WireDocError(f"{len(raw) - pos} trailing bytes after the msgpack value")
    return rows


_FIXED = {
    0xCA: (">f", 4, "float32"),
    0xCB: (">d", 8, "float64"),
    0xCC: (">B", 1, "uint8"),
    0xCD: (">H", 2, "uint16"),
    0xCE: (">I", 4, "uint32"),
    0xCF: (">Q", 8, "uint64"),
    0xD0: (">b", 1, "int8"),
    0xD1: (">h", 2, "int16"),
    0xD2: (">i", 4, "int32"),
    0xD3: (">q", 8, "int64"),
}


def _annotate_item(raw: bytes, pos: int, depth: int, rows: list[tuple[int, bytes, int, str]]) -> int:
    if pos >= len(raw):
        raise WireDocError("msgpack value truncated")
    b = raw[pos]
    start = pos

    def emit(end: int, text: str) -> None:
        if end > len(raw):
            raise WireDocError(f"msgpack value truncated at offset {start}")
        rows.append((start, raw[start:end], depth, text))

    def length(fmt: str, size: int) -> int:
        if pos + 1 + size > len(raw):
            raise WireDocError("msgpack value truncated")
        return int(struct.unpack_from(fmt, raw, pos + 1)[0])

    if b <= 0x7F:
        emit(pos + 1, f"positive fixint {b}")
        return pos + 1
    if b >= 0xE0:
        emit(pos + 1, f"negative fixint {b - 256}")
        return pos + 1
    if 0x80 <= b <= 0x8F or b in (0xDE, 0xDF):
        n, head = (
            (b & 0x0F, 1) if b <= 0x8F else ((length(">H", 2), 3) if b == 0xDE else (length(">I", 4), 5))
        )
        emit(pos + head, f"map, {n} entries")
        pos += head
        for _ in range(n):
            pos = _annotate_item(raw, pos, depth + 1, rows)
            pos = _annotate_item(raw, pos, depth + 2, rows)
        return pos
    if 0x90 <= b <= 0x9F or b in (0xDC, 0xDD):
        n, head = (
            (b & 0x0F, 1) if b <= 0x9F else ((length(">H", 2), 3) if b == 0xDC else (length(">I", 4), 5))
        )
        emit(pos + head, f"array, {n} items")
        pos += head
        for _ in range(n):
            pos = _annotate_item(raw, pos, depth + 1, rows)
        return pos
    if 0xA0 <= b <= 0xBF or b in (0xD9, 0xDA, 0xDB):
        if b <= 0xBF:
            n, head, name = b & 0x1F, 1, "fixstr"
        else:
            size = {0xD9: 1, 0xDA: 2, 0xDB: 4}[b]
            n, head, name = length({1: ">B", 2: ">H", 4: ">I"}[size], size), 1 + size, f"str{8 * size}"
        end = pos + head + n
        if end > len(raw):
            raise WireDocError("msgpack string truncated")
        try:
            text = raw[pos + head : end].decode("utf-8")
        except UnicodeDecodeError:
            raise WireDocError(f"msgpack string at offset {pos} is not UTF-8") from None
        emit(end, f"{name} {json.dumps(text, ensure_ascii=False)}")
        return end
    if b in (0xC4, 0xC5, 0xC6):
        size = {0xC4: 1, 0xC5: 2, 0xC6: 4}[b]
        n = length({1: ">B", 2: ">H", 4: ">I"}[size], size)
        emit(pos + 1 + size + n, f"bin{8 * size}, {n} bytes")
        return pos + 1 + size + n
    if b == 0xC0:
        emit(pos + 1, "nil")
        return pos + 1
    if b in (0xC2, 0xC3):
        emit(pos + 1, "false" if b == 0xC2 else "true")
        return pos + 1
    if b in _FIXED:
        fmt, size, name = _FIXED[b]
        if pos + 1 + size > len(raw):
            raise WireDocError("msgpack value truncated")
        value = struct.unpack_from(fmt, raw, pos + 1)[0]
        emit(pos + 1 + size, f"{name} {_num(value)}")
        return pos + 1 + size
    raise WireDocError(f"msgpack type byte 0x{b:02x} at offset {pos} is not used by the arena")


def _num(v: float | int) -> str:
    if isinstance(v, float) and math.isnan(v):
        return "NaN"
    return repr(v)


# -- wire.md -------------------------------------------------------------------------------------------

_QOS: dict[str, tuple[str, str]] = {
    "stream": (
        "put with `CongestionControl.DROP`, `Priority.DATA`, `Reliability.BEST_EFFORT`",
        "Real-time data: only the newest sample matters. Samples may be dropped under congestion and are "
        "never re-sent; a silent stream means the source stopped (never resend a stale sample). "
        "Subscribers should keep the latest sample, not queue them.",
    ),
    "reliable": (
        "put with `CongestionControl.BLOCK`, `Priority.INTERACTIVE_HIGH`, `Reliability.RELIABLE`",
        "Every sample matters (events, emergency stop): the publisher waits rather than drops.",
    ),
    "query": (
        "queryable; callers use `get` with a Command payload, congestion control `BLOCK`",
        "Request/response: one CommandResult reply per query (see *Commands* below).",
    ),
    "liveliness": (
        "liveliness token, no payload",
        "Presence: the token exists while the process's session lives (see *Presence* below).",
    ),
}

_RESULT_MEANING = {
    "ACCEPTED": "it succeeded (MAV_RESULT).",
    "TEMPORARILY_REJECTED": "valid, but not now; retry later (MAV_RESULT).",
    "DENIED": "the autopilot refused it (MAV_RESULT).",
    "UNSUPPORTED": "the autopilot does not know it (MAV_RESULT).",
    "FAILED": "valid, but executing it failed (MAV_RESULT).",
    "IN_PROGRESS": "accepted, still running (MAV_RESULT).",
    "CANCELLED": "cancelled before it completed (MAV_RESULT).",
    "TIMEOUT": "no answer in time, from the autopilot or from anyone (no gateway serves the key).",
    "REFUSED": "the gateway refused it under the arena's safety rules; `reason` says which.",
    "ERROR": "a malformed request or an internal failure; `reason` says what.",
}

_KIND_TYPE = {
    "int": "int",
    "float": "float64",
    "bool": "bool",
    "str": "str",
    "vec3": "float64[3]",
    "quat": "float64[4]",
    "strs": "str[]",
    "map": "map",
}  # and kind ``items``: ``<element type>[]`` (see _type_name)

# Rules the field specs alone do not express (each payload's ``check`` and key-specific meaning).
_RULES: dict[str, list[str]] = {
    "MocapPose": [
        "`q` must have unit norm (±0.001) when `ok` is true; when `ok` is false `p` and `q` mean nothing.",
        "`p` and `q` are in Motive's frame (Y-up or Z-up, set in the configuration), not the arena's.",
    ],
    "Pose": [
        "`q` must have unit norm (±0.001) when `ok` is true; an invalid pose must never reach an autopilot.",
        "On `vision` the stream is decimated for the autopilot (e.g. 50 Hz); silence means the pose is lost.",
        "`rc` changes (modulo 256) whenever the pose jumps, like MAVLink ODOMETRY's reset_counter.",
    ],
    "State": ["`q`, when present, must have unit norm (±0.001)."],
    "Telemetry": [
        "`f` holds the MAVLink message's fields by their MAVLink names, as pymavlink decodes them "
        "(integers, floats, strings, arrays of numbers).",
        "The key's last chunk is the message name: subscribe to `arena/<drone>/telemetry/HEARTBEAT`, or "
        "`arena/<drone>/telemetry/*` for every message.",
    ],
    "Command": [
        "Sent as the payload of a Zenoh query (`get`), never published; see *Commands* below.",
    ],
    "CommandResult": ["Sent only as the reply to a Command query; `ok` is true exactly when it succeeded."],
    "Setpoint": [
        "At least one of `p` (position) and `v` (velocity) must be present.",
        "Give `yaw` or `yr` (yaw rate), not both; neither keeps the current heading.",
        "The gateway forwards a setpoint only while `t + lease` has not passed; stream at ≥ 2 Hz "
        "(typically 20–50 Hz) before and during offboard flight.",
    ],
    "Estop": ["Every gateway acts on it, whatever vehicle it serves; publish it reliably."],
    "Stats": ["Published every second by every service on `arena/sys/stats/<host>/<service>`."],
    "MocapFrame": [
        "At most one message per Motive frame, with one element in `b` per rigid body a vehicle claims: "
        "`b[i].v` names the vehicle (a valid vehicle name). A decoder accepts an empty `b`.",
        "`b[i].q` must have unit norm (±0.001) when `b[i].ok` is true; when `ok` is false `p` and `q` "
        "mean nothing.",
        "`p` and `q` are in Motive's frame (Y-up or Z-up, set in the configuration), not the arena's.",
        "Each element with the frame's `t`, `fn`, `lat`, `mts`, `tsrc` and `tp` says what that vehicle's "
        "`MocapPose` on `arena/<drone>/mocap` says for the same frame.",
        "A decoder names a wrong field inside an element by its path: `b[1].q`.",
    ],
}


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _json_value(v: Any) -> str:
    if isinstance(v, float) and math.isnan(v):
        return "NaN"
    if isinstance(v, tuple):
        v = list(v)
    return json.dumps(v, ensure_ascii=False)


def _range(spec: wire.Spec) -> str:
    parts = []
    if spec.choices:
        parts.append("one of " + ", ".join(f"`{c}`" for c in spec.choices))
    if spec.lo is not None and spec.hi is not None:
        parts.append(f"{_num(spec.lo)} … {_num(spec.hi)}")
    elif spec.lo is not None:
        parts.append(f"≥ {_num(spec.lo)}")
    elif spec.hi is not None:
        parts.append(f"≤ {_num(spec.hi)}")
    if spec.kind == "quat":
        parts.append("unit norm")
    if spec.kind == "int" and not parts:
        parts.append("int64")
    if spec.kind in ("float", "vec3", "quat"):
        parts.append("NaN = unknown" if spec.nan_ok else "finite")
    if spec.kind == "str" and not spec.choices:
        parts.append("≤ 4096 chars")
    if spec.kind == "bool":
        parts.append("true, false")
    if spec.kind == "strs":
        parts.append("≤ 256 items")
    if spec.kind == "map":
        parts.append("string keys")
    if spec.kind == "items":
        if spec.max_items is not None:
            parts.append(f"≤ {spec.max_items} items")
        parts.append("each a map, fields below")
    return "; ".join(parts)


def _type_name(spec: wire.Spec) -> str:
    if spec.item is not None:
        return f"{spec.item.SCHEMA}[]"
    return _KIND_TYPE[spec.kind]


def _field_table(cls: type[wire.Payload]) -> list[str]:
    """The field table of one type, then one table per ``items`` field for its elements' fields."""
    out = ["| wire name | type | unit | range | required | description |", "|---|---|---|---|---|---|"]
    for name, spec in cls._specs:
        out.append(
            f"| `{spec.wire}` | {_type_name(spec)} | {spec.unit or '—'} | {_md_escape(_range(spec))} | "
            f"{_required(cls, name, spec)} | {_md_escape(spec.doc)} |"
        )
    out.append("")
    for _, spec in cls._specs:
        if spec.item is not None:
            out += [
                f"Each element of `{spec.wire}` is a map, `{spec.item.SCHEMA}`: {spec.item.DOC} Its fields:",
                "",
                *_field_table(spec.item),
            ]
    return out


def _required(cls: type[wire.Payload], name: str, spec: wire.Spec) -> str:
    if spec.optional:
        return "no — omitted when unknown"
    if spec.required:
        return "**yes**"
    return f"no — default `{_json_value(wire.default_of(cls, name))}`"


def _keys_for(schema: str) -> list[keys.KeySpec]:
    return [k for k in keys.KEYS if schema in re.findall(r"[A-Za-z]+", k.payload)]


def _hexdump(raw: bytes) -> str:
    lines = []
    for off in range(0, len(raw), 16):
        chunk = raw[off : off + 16]
        lines.append(f"{off:04x}  {chunk.hex(' ')}")
    return "\n".join(lines)


def _annotated(raw: bytes) -> str:
    lines = []
    for off, chunk, depth, text in annotate(raw):
        shown = chunk.hex(" ")
        if len(chunk) > 9:
            shown = chunk[:9].hex(" ") + " …"
        lines.append(f"{off:04x}  {shown:<29} {'  ' * depth}{text}")
    return "\n".join(lines)


def _example(vec: Vector, annotated: bool = False) -> list[str]:
    raw = vec.raw()
    out = [
        f"Golden vector `{GOLDEN_DIR}/{vec.name}.json` on `{vec.key}` — {vec.note}",
        "",
        f"msgpack, {len(raw)} bytes:",
        "",
        "```text",
        _hexdump(raw),
        "```",
        "",
    ]
    if annotated:
        out += [
            "The same bytes, item by item (offset, bytes, meaning):",
            "",
            "```text",
            _annotated(raw),
            "```",
            "",
        ]
    out += [
        "Decoded (JSON; NaN is written as null):",
        "",
        "```json",
        payload_json(wire.to_jsonable(vec.payload)),
        "```",
        "",
    ]
    return out


def _type_section(cls: type[wire.Payload], annotated: bool) -> list[str]:
    out = [f"### `arena.{cls.SCHEMA}/{cls.VERSION}`", "", cls.DOC, ""]
    out.append(f"- Encoding: `{cls.encoding()}`")
    out.append(f"- JSON Schema: [`schemas/arena.{cls.SCHEMA}.json`](schemas/arena.{cls.SCHEMA}.json)")
    ks = _keys_for(cls.SCHEMA)
    if ks:
        out.append("- Keys: " + ", ".join(f"`{k.pattern}` ({k.qos})" for k in ks))
    out += ["", *_field_table(cls)]
    rules = _RULES.get(cls.SCHEMA, [])
    if rules:
        out += ["Rules:", ""] + [f"- {r}" for r in rules] + [""]
    vecs = [v for v in vectors() if type(v.payload) is cls]
    if vecs:
        out += ["Worked example:", "", *_example(vecs[0], annotated)]
        if len(vecs) > 1:
            out += ["More vectors: " + ", ".join(f"`{v.name}.json` ({v.note})" for v in vecs[1:]), ""]
    return out


def _intro() -> list[str]:
    return [
        "# The arena's wire contract",
        "",
        f"<!-- Generated by `{_REGENERATE}` from arena_common/core/wire.py and arena_common/core/keys.py. "
        f"Do not edit: change the code and regenerate; `{_REGENERATE} --check` fails on drift. -->",
        "",
        "Every arena process talks over [Eclipse Zenoh](https://zenoh.io) 1.x. A program in C (zenoh-c, "
        "zenoh-pico), Rust (zenoh) or JavaScript can join the arena by connecting to the arena's Zenoh "
        "router (`arena router`; it listens on the configuration's `[zenoh] router_listen`, by default "
        "`tcp/127.0.0.1:7447`), subscribing to the keys below and decoding msgpack maps. Nothing in this "
        "document depends on Python.",
        "",
        "Files beside this one:",
        "",
        "- `docs/schemas/arena.<Type>.json` — a JSON Schema (draft 2020-12) per payload type, describing its "
        "JSON rendering (MCAP recordings, tools).",
        "- `tests/golden/<name>.json` — golden vectors: msgpack bytes (`hex`) beside their decoded value "
        "(`json`), with the `key` and `encoding` they travel with. Decode every `hex` with your code and "
        "compare with `json`: `tests/js/decode.mjs` does it in JavaScript with `@msgpack/msgpack`.",
        "",
    ]


def _keys_section() -> list[str]:
    out = [
        "## Keys",
        "",
        "`<drone>` is a vehicle name from the configuration; `<host>` a host name; `<service>` a service id "
        "(`transform`, `recorder`, or `<name>.<drone>` for per-vehicle services such as `gateway.d1`). "
        "Names are 1–63 characters of letters, digits, `_`, `-` and `.`; `sys` and `estop` are reserved. "
        "Use Zenoh wildcards to subscribe to many vehicles: `arena/*/pose`, `arena/*/telemetry/**`.",
        "",
        "| key | payload | QoS | description |",
        "|---|---|---|---|",
    ]
    for k in keys.KEYS:
        out.append(f"| `{k.pattern}` | {k.payload} | {k.qos} | {_md_escape(k.description)} |")
    out += ["", "### QoS classes", "", "| QoS | Zenoh | meaning |", "|---|---|---|"]
    for qos, (how, meaning) in _QOS.items():
        out.append(f"| {qos} | {how} | {meaning} |")
    out += [
        "",
        "### Sequence numbers",
        "",
        "Every sample an arena publisher sends carries a Zenoh attachment of "
        f"{sequence.STAMP.size} bytes: the publisher's id (a random u64, new each time a publisher is "
        "declared) and the sample's number within that publisher, from 1 (u64), both little-endian "
        f"(`struct` format `{sequence.STAMP.format}`). A subscriber that keeps the last number seen per "
        "key and publisher id counts what the bus lost: a jump from n to n + k lost k − 1 samples. The first "
        "sample of an id starts its count (a late subscriber, a restarted publisher); a number at or below "
        "the last one is late, not a loss undone. Every arena service publishes what it counted this way in "
        "`Stats.lost`, per key. One-off puts (an emergency stop) are numbered per key within the session "
        "that puts them. A sample without this attachment (a replay of a recording, another program) is "
        "unnumbered.",
        "",
    ]
    return out


def _encoding_section() -> list[str]:
    out = [
        "## Encoding",
        "",
        "Every sample carries a Zenoh encoding naming the payload's schema and version: "
        f"`{wire.ENCODING_PREFIX}arena.<Type>/<version>`. Build it from that exact string (Rust "
        '`Encoding::from("…")`, C `z_encoding_from_str`). Zenoh has no predefined msgpack encoding, so it '
        "travels as a custom encoding whose schema is the whole string; Zenoh 1.10 "
        "gives the same string back, but other releases may render it with a prefix (`zenoh/bytes;…` or "
        "`unknown(65535);…`), so match on the part from `application/msgpack;arena.` on. A receiver should "
        "decode by this encoding when present, and by the key table otherwise; a version it does not know "
        "is an error, not a guess. The version changes only on an incompatible "
        "change: new fields with defaults may appear within a version, so ignore map keys you do not know.",
        "",
        "| type | encoding |",
        "|---|---|",
    ]
    for cls in wire.REGISTRY.values():
        out.append(f"| {cls.SCHEMA} | `{cls.encoding()}` |")
    out.append("")
    return out


def _conventions_section() -> list[str]:
    return [
        "## Conventions",
        "",
        "- **msgpack maps with short names.** A payload is one msgpack map whose keys are the short wire "
        "names below (msgpack `str`, UTF-8). Key order carries no meaning. Strings are msgpack `str`, "
        "never `bin`; booleans are msgpack `true`/`false`, never 0/1.",
        "- **Numbers.** `int` fields hold msgpack integers of any width (the encoder picks the smallest: "
        "fixint, uint8 … uint64, int8 … int64); a reader must accept all of them, and a float is refused. "
        "`float64` fields are written as msgpack float64; a reader should also accept float32 and integers "
        "there. `float64[3]` and `float64[4]` are msgpack arrays of exactly 3 or 4 numbers. `<Type>[]` "
        "is a msgpack array of maps, each with the fields of the table below the type's own.",
        "- **SI units**: metres, seconds, radians, m/s, rad/s, volts, hertz, bytes; the unit column says "
        "which. Fractions are 0–1, not percent (except `Stats.cpu`).",
        "- **Times** are integer nanoseconds since the Unix epoch (UTC wall clock): `t` is when the value "
        "was measured or happened, `tp` when it was published. They exceed 2^53: keep them in 64-bit "
        "integers (`int64_t`, `i64`, JavaScript `BigInt` via `@msgpack/msgpack`'s `useBigInt64: true`); "
        "a plain JavaScript number silently loses the last digits, and so does `JSON.parse` of the golden "
        "vectors' `json` field.",
        "- **Quaternions** are `(w, x, y, z)`, Hamilton, and rotate **body → world** "
        "(`v_world = q ⊗ v_body ⊗ q*`).",
        "- **Frames.** The arena frame is **NED** (north along the long side, east, down into the floor; "
        "origin at the floor's centre); vehicle bodies are **FRD** (forward, right, down). Angular "
        "velocities are in the body frame. Only `MocapPose` and `MocapFrame` are in Motive's own frame.",
        "- **Unknown values.** Where a field says so, NaN means unknown (msgpack float64 NaN; JSON "
        "renderings, including the golden vectors' `json`, write it as `null`). Optional fields are "
        "**omitted** when unknown (a reader should treat `nil` like an absent field). A field with a "
        "default may be omitted by a sender; the reader then uses the default. Fields marked required "
        "must be present.",
        "- **Limits.** Strings are at most 4096 characters, string arrays at most 256 items, arrays of maps "
        "at most what their range says; a decoder refuses a payload that breaks a field's type or range and "
        "names the field (`b[1].q` for a field of an array's element).",
        "",
    ]


def _languages_section() -> list[str]:
    return [
        "## Decoding in other languages",
        "",
        "- **JavaScript / TypeScript**: `decode(bytes, { useBigInt64: true })` from `@msgpack/msgpack` gives "
        "a plain object per payload; times come out as `BigInt`. `tests/js/decode.mjs` decodes every golden "
        "vector this way and the test suite checks it against the Python decoder, value by value.",
        "- **Rust**: `rmp-serde` with a serde struct per payload: `i64` for `int`, `f64` for `float64`, "
        "`[f64; 3]` / `[f64; 4]` for vectors and quaternions, `Option<…>` for optional fields, "
        "`#[serde(default)]` on fields that have a default, `HashMap<String, rmpv::Value>` for maps, "
        "`Vec<T>` of a struct per element type for arrays of maps (`MocapBody[]`); serde "
        "ignores unknown keys unless told otherwise, which is what the contract wants.",
        "- **C**: any msgpack reader (msgpack-c, mpack, cmp): read the map, look fields up by name, keep "
        "times in `int64_t`, skip keys you do not know. Take the payload bytes with zenoh-c's "
        "`z_bytes_to_slice` (or zenoh-pico's equivalent).",
        "",
    ]


def _commands_section() -> list[str]:
    ops = ", ".join(f"`{op}`" for op in wire.COMMAND_OPS)
    return [
        "## Commands",
        "",
        "A command is a Zenoh **query**, not a publication:",
        "",
        "1. `get` on `arena/<drone>/cmd` (or `arena/sys/rec/<host>` for a recorder) with the msgpack bytes "
        f"of a `Command` as the query payload and encoding `{wire.Command.encoding()}`. Use query target "
        "`BEST_MATCHING` and a query timeout a little longer than the command's own `timeout` (the "
        "Python client adds 0.5 s).",
        "2. The vehicle's gateway answers with exactly one reply on the same key: a sample whose payload "
        f"is a `CommandResult` with encoding `{wire.CommandResult.encoding()}`. `ok` is true exactly when "
        "the command succeeded; `result` says how it ended and `reason` why, in words.",
        "3. An error reply (Zenoh `reply.err`) carries a text; treat it as `ERROR`. No reply at all when "
        "the query ends means nobody serves that key (the vehicle's gateway is not running): the Python "
        "client reports it as `TIMEOUT` at once, without waiting.",
        "",
        f"Operations (`op`): {ops}. Their arguments (`args`, a map), checked at both ends against one "
        "table (`arena_common/core/ops.py`; an argument it does not name, or out of its type or range, "
        "is an `ERROR` naming it):",
        "",
        "| op | answered by | args | what it does | Python |",
        "|---|---|---|---|---|",
        *(
            f"| `{o.name}` | {', '.join(o.targets)} | "
            + ("<br>".join(_md_escape(a.describe()) for a in o.args) or "—")
            + f" | {_md_escape(o.doc)} | "
            + (f"`vehicle.{o.client}()`" if o.client else "—")
            + " |"
            for o in OPS.values()
        ),
        "",
        "Results (`result`):",
        "",
        *(f"- `{r}` — {_RESULT_MEANING.get(r, '')}".rstrip(" —") for r in wire.RESULTS),
        "",
        "Setpoints are not commands: stream `Setpoint` samples on `arena/<drone>/setpoint` (each valid for "
        "its `lease`). The emergency stop is a reliable put of an `Estop` on `arena/estop`.",
        "",
    ]


def _presence_section() -> list[str]:
    return [
        "## Presence",
        "",
        "Every running service declares a Zenoh **liveliness token** `arena/sys/alive/<host>/<service>` "
        "(no payload). To list who is up now, make a liveliness `get` on `arena/sys/alive/**`; to follow "
        "changes, declare a liveliness subscriber on the same key expression (with history, to also "
        "receive the tokens alive now): a `PUT` sample means the service appeared, a `DELETE` sample that "
        "it went away. A process that exits or is killed disappears within milliseconds; one whose link "
        "froze disappears after the Zenoh lease (the configuration's `[zenoh] lease_ms`, 10 s by default). "
        "A service's counters arrive every second as `Stats` on `arena/sys/stats/<host>/<service>`.",
        "",
        "A program of your own should declare a token the same way (e.g. `arena/sys/alive/<host>/myprog`) "
        "so the arena's tools see it.",
        "",
    ]


def render_wire_md() -> str:
    """The full text of ``docs/wire.md``."""
    out = _intro() + _keys_section() + _encoding_section() + _conventions_section()
    out += ["## Payload types", ""]
    out += [
        "Columns: `wire name` is the msgpack map key; `type` as in *Conventions*; `range` lists the "
        "values a decoder accepts; `required` says whether a sender may omit the field (and the default "
        "a reader then uses).",
        "",
    ]
    for cls in wire.REGISTRY.values():
        out += _type_section(cls, annotated=cls is wire.Pose)
    out += _commands_section() + _presence_section() + _languages_section()
    return "\n".join(out).rstrip("\n") + "\n"


# -- command line --------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """Generate (or ``--check``) the wire documentation; return the process exit code."""
    parser = argparse.ArgumentParser(prog=_REGENERATE, description=__doc__.split("\n", 1)[0])
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if any file drifts")
    parser.add_argument("--root", type=Path, default=ROOT, help="repository root (default: this checkout)")
    args = parser.parse_args(argv)
    root: Path = args.root
    if args.check:
        stale = drift(root)
        for line in stale:
            print(line, file=sys.stderr)
        if stale:
            print(f"{len(stale)} file(s) drift from the code: run `{_REGENERATE}`", file=sys.stderr)
            return 1
        print("wire documentation is up to date")
        return 0
    for rel in write(root):
        print(f"wrote {rel}" if (root / rel).exists() else f"removed {rel}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
