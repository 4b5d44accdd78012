"""PX4's parameter metadata files: parse ``parameters.json`` (or ``.json.xz``) and the general metadata that
points to it; which parameters need a reboot."""

from __future__ import annotations

import json
import lzma
import os
import re
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypedDict

from arena_common.mavlink.metadata._errors import MetadataError, MetadataFormatError
from arena_common.mavlink.metadata.ftp import _XZ_MAGIC


# --- output shape -----------------------------------------------------------------------------------
class ParamMeta(TypedDict):
    """PX4's metadata of one parameter: ``type`` as PX4 names it ("Int32", "Float"), ``rebootRequired``
    (False when PX4 omits it), ``default`` (None when absent), ``units`` ("" when absent)."""

    type: str
    rebootRequired: bool
    default: int | float | None
    units: str


def reboot_required(meta: Mapping[str, ParamMeta]) -> frozenset[str]:
    """The names of the parameters that take effect only after the autopilot reboots."""
    return frozenset(name for name, m in meta.items() if m["rebootRequired"])


def _decompress(data: bytes, what: str, limit: int = 64 << 20) -> bytes:
    """``data`` itself, or its xz decompression when it starts with the xz magic (bounded to ``limit``)."""
    if not data.startswith(_XZ_MAGIC):
        return data
    dec = lzma.LZMADecompressor(format=lzma.FORMAT_XZ)
    try:
        out = dec.decompress(data, max_length=limit)
    except lzma.LZMAError as exc:
        raise MetadataFormatError(f"{what}: not a valid xz file ({exc})") from None
    if not dec.eof:
        more = "truncated" if dec.needs_input else f"more than {limit} bytes uncompressed"
        raise MetadataFormatError(f"{what}: xz stream {more}")
    return out


def _unpack(raw: bytes, crc: int | None, what: str) -> tuple[bytes, bool | None]:
    """``(decompressed content, whether the CRC32 published for it matches)``.

    PX4 publishes the CRC of the compressed parameter file but of the uncompressed general file: either
    matching will do (None without a CRC).  A mismatch alone is not fatal (xz checks its own content);
    with content that does not decompress it is named in the error.
    """
    ok = None if crc is None else crc == px4_crc32(raw)
    try:
        content = _decompress(raw, what)
    except MetadataFormatError as exc:
        if ok is False:
            got = px4_crc32(raw)
            raise _CorruptFile(f"{exc}; its CRC32 {got:#010x} is not the {crc:#010x} published") from None
        raise
    if ok is False and content is not raw:
        ok = crc == px4_crc32(content)
    return content, ok


class _CorruptFile(MetadataFormatError):
    """A file that neither decompresses nor matches its published CRC32."""


def _json(data: bytes | str, what: str) -> Any:
    raw = _decompress(data, what) if isinstance(data, bytes) else data
    try:
        return json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise MetadataFormatError(f"{what}: not JSON ({exc})") from None


def parse_parameters_json(
    data: bytes | str | Mapping[str, Any], what: str = "parameters.json"
) -> dict[str, ParamMeta]:
    """PX4's ``parameters.json`` (bytes, possibly xz-compressed; text; or the parsed document) as
    ``{name: ParamMeta}``.  :class:`MetadataFormatError` names the entry that is wrong."""
    doc = data if isinstance(data, Mapping) else _json(data, what)
    params = doc.get("parameters") if isinstance(doc, Mapping) else None
    if not isinstance(params, list):
        raise MetadataFormatError(f"{what}: no 'parameters' list (is this PX4's parameter metadata?)")
    out: dict[str, ParamMeta] = {}
    for i, p in enumerate(params):
        name = p.get("name") if isinstance(p, Mapping) else None
        if not isinstance(name, str) or not name:
            raise MetadataFormatError(f"{what}: parameters[{i}] has no name")
        ptype = p.get("type")
        if not isinstance(ptype, str):
            raise MetadataFormatError(f"{what}: parameter {name} has no type")
        reboot = p.get("rebootRequired", False)
        if not isinstance(reboot, bool):
            raise MetadataFormatError(f"{what}: parameter {name}: rebootRequired={reboot!r} is not a boolean")
        default = p.get("default")
        if default is not None and (isinstance(default, bool) or not isinstance(default, int | float)):
            raise MetadataFormatError(f"{what}: parameter {name}: default={default!r} is not a number")
        units = p.get("units", "")
        out[name] = ParamMeta(
            type=ptype, rebootRequired=reboot, default=default, units=units if isinstance(units, str) else ""
        )
    if not out:
        raise MetadataFormatError(f"{what}: the parameter list is empty")
    return out


def load_parameters_json(path: str | os.PathLike[str]) -> dict[str, ParamMeta]:
    """A PX4 build's ``parameters.json`` (or ``parameters.json.xz``) from disk, as ``{name: ParamMeta}``."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise MetadataError(f"cannot read PX4 parameter metadata {p}: {exc.strerror or exc}") from None
    return parse_parameters_json(data, str(p))


@dataclass(frozen=True, slots=True)
class MetadataType:
    """One entry of the general metadata file: COMP_METADATA_TYPE, its URI and CRC32 (None if absent)."""

    type: int
    uri: str
    crc: int | None
    uri_fallback: str = ""


def parse_general_metadata(
    data: bytes | str, what: str = "component_general.json"
) -> dict[int, MetadataType]:
    """The metadata types a component's general metadata file lists, by COMP_METADATA_TYPE."""
    doc = _json(data, what)
    types = doc.get("metadataTypes") if isinstance(doc, Mapping) else None
    if not isinstance(types, list):
        raise MetadataFormatError(f"{what}: no 'metadataTypes' list")
    out: dict[int, MetadataType] = {}
    for i, t in enumerate(types):
        if not (isinstance(t, Mapping) and isinstance(t.get("type"), int) and isinstance(t.get("uri"), str)):
            raise MetadataFormatError(f"{what}: metadataTypes[{i}] has no integer 'type' and string 'uri'")
        crc = t.get("fileCrc")
        fallback = t.get("uriFallback")
        out[t["type"]] = MetadataType(
            t["type"],
            t["uri"],
            crc if isinstance(crc, int) else None,
            fallback if isinstance(fallback, str) else "",
        )
    return out


_MFTP = re.compile(r"^mftp://(?:\[;comp=(?P<comp>\d{1,3})\])?(?P<path>.+)$", re.IGNORECASE)


def parse_mftp_uri(uri: str) -> tuple[int | None, str]:
    """``(component id or None, absolute path)`` of a MAVLink FTP URI ``mftp://[;comp=<id>]<path>``.

    A relative path is made absolute (as QGroundControl does: PX4 resolves it from its root either way).
    :class:`MetadataError` for any other scheme (an https metadata URI would need the internet).
    """
    m = _MFTP.match(uri.strip())
    if m is None:
        raise MetadataError(
            f"metadata URI {uri!r} is not on the vehicle (expected mftp://[;comp=<id>]<path>)"
        )
    comp = int(m["comp"]) if m["comp"] is not None else None
    if comp is not None and not 1 <= comp <= 255:
        raise MetadataError(f"metadata URI {uri!r}: component id {comp} out of 1..255")
    path = m["path"]
    return comp, path if path.startswith("/") else "/" + path


def px4_crc32(data: bytes) -> int:
    """PX4's ``crc32part(data, len, 0)``: the reflected CRC-32 polynomial, initial value 0, no final XOR.

    It is the ``fileCrc`` PX4 publishes for its metadata files (of the compressed parameters file, of
    the uncompressed general file).
    """
    return zlib.crc32(data, 0xFFFFFFFF) ^ 0xFFFFFFFF
