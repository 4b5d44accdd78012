"""Export: one table (CSV or Parquet) per key of a recording."""

from __future__ import annotations

import csv
import importlib
import importlib.metadata
from pathlib import Path
from typing import Any

from arena_common.recording.codec import NS, RecordingError
from arena_common.recording.reader import ChannelInfo, RecordingReader

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
        if m.channel.scene:
            continue  # the 3D scene (protobuf) is not a table; its data are the keys' own
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
