"""Repair: a complete copy of everything readable in an unfinished recording."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType, Writer

from arena_common.recording.codec import RecordingError, software_version
from arena_common.recording.reader import RecordingReader

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
