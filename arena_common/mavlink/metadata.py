"""PX4's own parameter metadata: from the vehicle (component metadata + MAVLink FTP) or a build's file.

Which parameters need a reboot (``rebootRequired``), their types, defaults and units are PX4's facts, not
ours: this module reads them where PX4 publishes them, never from a hand-kept list.

From the vehicle (:class:`MetadataClient`):

1. ``MAV_CMD_REQUEST_MESSAGE`` (512) for COMPONENT_METADATA (397), alternating with the older
   COMPONENT_INFORMATION (395), without waiting for COMMAND_ACK (the gateway's commander takes those);
   PX4 v1.16 answers both with the MAVLink FTP URI of its general metadata file,
   ``mftp://etc/extras/component_general.json.xz`` (a CRC32 of the *uncompressed* file beside it).
2. That file (xz-compressed JSON) lists the metadata types; type 1 (COMP_METADATA_TYPE_PARAMETER) is
   ``mftp://etc/extras/parameters.json.xz`` (PX4 v1.16 SITL: 68,036 bytes, 721,427 uncompressed; its
   ``fileCrc`` is the CRC32 of the *compressed* file).
3. Both files are read with MAVLink FTP (FILE_TRANSFER_PROTOCOL, 110): OpenFileRO, BurstReadFile (PX4
   streams 239-byte chunks, about 35 kB per burst, then sets ``burst_complete``; a NAK EOF ends the file),
   ReadFile for the holes a lossy link leaves (its ``size`` field says how much: PX4 v1.16 reads exactly
   that), TerminateSession.  Replies are matched by sequence number (reply = request + 1; a burst's
   packets continue from there), requests are resent with the same sequence number (PX4 then repeats
   its cached reply), stale, duplicated and out-of-order packets are dropped or placed by their offset.
   PX4 serves one FTP session per MAVLink link.  Against PX4 v1.16 SITL the whole fetch takes ~0.15 s.

The gateway's reader thread owns the link: it hands FILE_TRANSFER_PROTOCOL, COMPONENT_METADATA and
COMPONENT_INFORMATION (:data:`HANDLED_MESSAGES`) to :meth:`MetadataClient.on_message`, while another
thread blocks in :meth:`MetadataClient.fetch` (the pattern of
:class:`~arena_common.mavlink.protocols.ParamClient`).  :func:`fetch_parameter_metadata` runs its own
reader on a :class:`~arena_common.mavlink.link.MavlinkLink` nobody else reads.

From a file (:func:`load_parameters_json`): the build's ``parameters.json`` (or ``.json.xz``).

Both give ``{name: {"type", "rebootRequired", "default", "units"}}``; :func:`reboot_required` picks the
names that need a reboot.

pymavlink (2.4.x) knows neither COMPONENT_METADATA nor COMPONENT_INFORMATION: importing this module adds
both to the MAVLink 2 dialect :mod:`arena_common.mavlink.link` uses (:func:`register_messages`), so
their CRCs are checked and :meth:`~arena_common.mavlink.link.MavlinkLink.decode` returns them.
"""

from __future__ import annotations

import json
import lzma
import os
import random
import re
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Protocol, TypedDict

from arena_common.core.errors import ArenaError
from arena_common.mavlink.link import MavlinkLink, mavlink2

__all__ = [
    "COMPONENT_INFORMATION",
    "COMPONENT_METADATA",
    "FILE_TRANSFER_PROTOCOL",
    "HANDLED_MESSAGES",
    "FetchInfo",
    "FtpError",
    "FtpNak",
    "FtpReply",
    "MetadataClient",
    "MetadataError",
    "MetadataFormatError",
    "MetadataTimeout",
    "ParamMeta",
    "decode_ftp_payload",
    "encode_ftp_payload",
    "fetch_parameter_metadata",
    "load_parameters_json",
    "parse_general_metadata",
    "parse_mftp_uri",
    "parse_parameters_json",
    "reboot_required",
    "register_messages",
]

# --- MAVLink ids and enums --------------------------------------------------------------------------
FILE_TRANSFER_PROTOCOL: Final = 110
COMPONENT_INFORMATION: Final = 395
COMPONENT_METADATA: Final = 397
MAV_CMD_REQUEST_MESSAGE: Final = 512
#: The messages :meth:`MetadataClient.on_message` wants from the link's reader.
HANDLED_MESSAGES: Final = frozenset({FILE_TRANSFER_PROTOCOL, COMPONENT_INFORMATION, COMPONENT_METADATA})

COMP_METADATA_TYPE_PARAMETER: Final = 1

# MAVLink FTP opcodes (MAV_FTP_OPCODE) and NAK error codes (MAV_FTP_ERR), https://mavlink.io/en/services/ftp.html
OP_NONE: Final = 0
OP_TERMINATE_SESSION: Final = 1
OP_RESET_SESSIONS: Final = 2
OP_OPEN_FILE_RO: Final = 4
OP_READ_FILE: Final = 5
OP_BURST_READ_FILE: Final = 15
OP_ACK: Final = 128
OP_NAK: Final = 129

OPCODE_NAMES: Final[Mapping[int, str]] = {
    0: "None",
    1: "TerminateSession",
    2: "ResetSessions",
    3: "ListDirectory",
    4: "OpenFileRO",
    5: "ReadFile",
    6: "CreateFile",
    7: "WriteFile",
    8: "RemoveFile",
    9: "CreateDirectory",
    10: "RemoveDirectory",
    11: "OpenFileWO",
    12: "TruncateFile",
    13: "Rename",
    14: "CalcFileCRC32",
    15: "BurstReadFile",
    128: "ACK",
    129: "NAK",
}

ERR_FAIL: Final = 1
ERR_FAIL_ERRNO: Final = 2
ERR_INVALID_SESSION: Final = 4
ERR_NO_SESSIONS_AVAILABLE: Final = 5
ERR_EOF: Final = 6
ERR_UNKNOWN_COMMAND: Final = 7
ERR_FILE_NOT_FOUND: Final = 10

ERROR_NAMES: Final[Mapping[int, str]] = {
    0: "None",
    1: "Fail",
    2: "FailErrno",
    3: "InvalidDataSize",
    4: "InvalidSession",
    5: "NoSessionsAvailable",
    6: "EOF",
    7: "UnknownCommand",
    8: "FileExists",
    9: "FileProtected",
    10: "FileNotFound",
}

FTP_PAYLOAD_LEN: Final = 251
FTP_HEADER_LEN: Final = 12
#: Data bytes one FTP message carries (PX4 always reads this much per ReadFile / burst packet).
FTP_DATA_MAX: Final = FTP_PAYLOAD_LEN - FTP_HEADER_LEN
_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, pad, offset
_XZ_MAGIC = b"\xfd7zXZ\x00"


# --- errors -----------------------------------------------------------------------------------------
class MetadataError(ArenaError):
    """PX4's parameter metadata could not be obtained; the message names what failed and where."""


class MetadataTimeout(MetadataError):
    """The vehicle did not answer in time (after retries): names the request, the system and component."""


class FtpError(MetadataError):
    """A MAVLink FTP transfer failed (a protocol violation, a file too large or changing under us)."""


class FtpNak(FtpError):
    """The vehicle's FTP server refused a request.

    ``op`` / ``op_name`` the request, ``code`` / ``code_name`` its MAV_FTP_ERR, ``errno`` the server's
    errno (FailErrno only), ``path`` the file.
    """

    def __init__(self, op: int, code: int, errno: int | None, path: str, target: str) -> None:
        self.op = op
        self.op_name = OPCODE_NAMES.get(op, f"opcode {op}")
        self.code = code
        self.code_name = ERROR_NAMES.get(code, f"error {code}")
        self.errno = errno
        self.path = path
        detail = self.code_name + (f" (errno {errno}: {os.strerror(errno)})" if errno is not None else "")
        super().__init__(f"MAVLink FTP {self.op_name} {path!r} refused by {target}: NAK {detail}")


class MetadataFormatError(MetadataError, ValueError):
    """A metadata file that is not what PX4 publishes (not xz/JSON, no parameters, malformed entry)."""


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


# --- the two messages pymavlink lacks ---------------------------------------------------------------
def _c_string(raw: bytes) -> str:
    return raw.split(b"\x00", 1)[0].decode("ascii", errors="replace")


class MAVLink_component_metadata_message(mavlink2.MAVLink_message):
    """COMPONENT_METADATA (397, common.xml): the MAVLink FTP URI and CRC32 of the general metadata file."""

    id = COMPONENT_METADATA
    msgname = "COMPONENT_METADATA"
    fieldnames = ["time_boot_ms", "file_crc", "uri"]  # noqa: RUF012 - pymavlink's class layout
    ordered_fieldnames = ["time_boot_ms", "file_crc", "uri"]  # noqa: RUF012
    fieldtypes = ["uint32_t", "uint32_t", "char"]  # noqa: RUF012
    fielddisplays_by_name: dict[str, str] = {}  # noqa: RUF012
    fieldenums_by_name: dict[str, str] = {}  # noqa: RUF012
    fieldunits_by_name: dict[str, str] = {"time_boot_ms": "ms"}  # noqa: RUF012
    native_format = bytearray(b"<IIc")
    orders = [0, 1, 2]  # noqa: RUF012
    lengths = [1, 1, 1]  # noqa: RUF012
    array_lengths = [0, 0, 100]  # noqa: RUF012
    crc_extra = 182
    unpacker = struct.Struct("<II100s")
    instance_field = None
    instance_offset = -1

    def __init__(self, time_boot_ms: int, file_crc: int, uri: bytes) -> None:
        super().__init__(COMPONENT_METADATA, "COMPONENT_METADATA")
        self._fieldnames = self.fieldnames
        self.time_boot_ms = time_boot_ms
        self.file_crc = file_crc
        self._uri_raw = uri
        self.uri = _c_string(uri)

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(self.time_boot_ms, self.file_crc, self._uri_raw)
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


class MAVLink_component_information_message(mavlink2.MAVLink_message):
    """COMPONENT_INFORMATION (395, common.xml, deprecated for COMPONENT_METADATA): the same URI and CRC."""

    id = COMPONENT_INFORMATION
    msgname = "COMPONENT_INFORMATION"
    fieldnames = [  # noqa: RUF012 - pymavlink's class layout
        "time_boot_ms",
        "general_metadata_file_crc",
        "general_metadata_uri",
        "peripherals_metadata_file_crc",
        "peripherals_metadata_uri",
    ]
    ordered_fieldnames = [  # noqa: RUF012
        "time_boot_ms",
        "general_metadata_file_crc",
        "peripherals_metadata_file_crc",
        "general_metadata_uri",
        "peripherals_metadata_uri",
    ]
    fieldtypes = ["uint32_t", "uint32_t", "char", "uint32_t", "char"]  # noqa: RUF012
    fielddisplays_by_name: dict[str, str] = {}  # noqa: RUF012
    fieldenums_by_name: dict[str, str] = {}  # noqa: RUF012
    fieldunits_by_name: dict[str, str] = {"time_boot_ms": "ms"}  # noqa: RUF012
    native_format = bytearray(b"<IIIcc")
    orders = [0, 1, 3, 2, 4]  # noqa: RUF012
    lengths = [1, 1, 1, 1, 1]  # noqa: RUF012
    array_lengths = [0, 0, 100, 0, 100]  # noqa: RUF012
    crc_extra = 0
    unpacker = struct.Struct("<III100s100s")
    instance_field = None
    instance_offset = -1

    def __init__(
        self,
        time_boot_ms: int,
        general_metadata_file_crc: int,
        general_metadata_uri: bytes,
        peripherals_metadata_file_crc: int = 0,
        peripherals_metadata_uri: bytes = b"",
    ) -> None:
        super().__init__(COMPONENT_INFORMATION, "COMPONENT_INFORMATION")
        self._fieldnames = self.fieldnames
        self.time_boot_ms = time_boot_ms
        self.general_metadata_file_crc = general_metadata_file_crc
        self.peripherals_metadata_file_crc = peripherals_metadata_file_crc
        self._general_raw = general_metadata_uri
        self._peripherals_raw = peripherals_metadata_uri
        self.general_metadata_uri = _c_string(general_metadata_uri)
        self.peripherals_metadata_uri = _c_string(peripherals_metadata_uri)

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(
            self.time_boot_ms,
            self.general_metadata_file_crc,
            self.peripherals_metadata_file_crc,
            self._general_raw,
            self._peripherals_raw,
        )
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


def register_messages(dialect: Any = mavlink2) -> None:
    """Teach a pymavlink dialect module COMPONENT_METADATA and COMPONENT_INFORMATION (if it lacks them).

    Idempotent; a dialect that defines them already keeps its own.  Done at import for the dialect of
    :mod:`arena_common.mavlink.link`, whose frame splitter would otherwise drop them in byte streams
    (unknown id) and never decode them on UDP (CRC not checkable).
    """
    for cls in (MAVLink_component_metadata_message, MAVLink_component_information_message):
        dialect.mavlink_map.setdefault(cls.id, cls)


register_messages()


# --- FTP payloads -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class FtpReply:
    """One decoded FILE_TRANSFER_PROTOCOL payload (a reply, or a request in a test's responder)."""

    seq: int
    session: int
    opcode: int
    size: int
    req_opcode: int
    burst_complete: bool
    offset: int
    data: bytes

    @property
    def nak(self) -> bool:
        return self.opcode == OP_NAK

    @property
    def error(self) -> int:
        """The NAK's MAV_FTP_ERR (Fail when the NAK carries none)."""
        return self.data[0] if self.data else ERR_FAIL

    @property
    def errno(self) -> int | None:
        """The server's errno for a FailErrno NAK, else None."""
        return self.data[1] if self.error == ERR_FAIL_ERRNO and len(self.data) >= 2 else None


def decode_ftp_payload(payload: bytes | bytearray | list[int]) -> FtpReply:
    """Split a FILE_TRANSFER_PROTOCOL payload into its header fields and ``size`` data bytes."""
    raw = bytes(payload)
    if len(raw) < FTP_HEADER_LEN:
        raise FtpError(f"MAVLink FTP payload of {len(raw)} bytes, less than a {FTP_HEADER_LEN}-byte header")
    seq, session, opcode, size, req_opcode, burst_complete, _pad, offset = _HEADER.unpack_from(raw)
    size = min(size, FTP_DATA_MAX)
    data = raw[FTP_HEADER_LEN : FTP_HEADER_LEN + size].ljust(size, b"\x00")  # MAVLink 2 cuts trailing zeros
    return FtpReply(seq, session, opcode, size, req_opcode, bool(burst_complete), offset, data)


def encode_ftp_payload(
    seq: int,
    opcode: int,
    *,
    session: int = 0,
    offset: int = 0,
    data: bytes = b"",
    size: int | None = None,
    req_opcode: int = 0,
    burst_complete: bool = False,
) -> list[int]:
    """A 251-byte FILE_TRANSFER_PROTOCOL payload (``size`` defaults to ``len(data)``)."""
    if len(data) > FTP_DATA_MAX:
        raise FtpError(f"MAVLink FTP data of {len(data)} bytes exceeds {FTP_DATA_MAX}")
    n = len(data) if size is None else size
    head = _HEADER.pack(seq & 0xFFFF, session, opcode, n, req_opcode, int(burst_complete), 0, offset)
    return list((head + data).ljust(FTP_PAYLOAD_LEN, b"\x00"))


# --- the client -------------------------------------------------------------------------------------
class _Link(Protocol):
    """What the client needs of a link: a pymavlink encoder (``mav``, with ``srcSystem``) and ``send``."""

    mav: Any

    def send(self, msg: Any) -> bool: ...


@dataclass
class FetchInfo:
    """How the last :meth:`MetadataClient.fetch` went: what PX4 answered, sizes, CRCs, counts, times."""

    source_message: str = ""  # COMPONENT_METADATA or COMPONENT_INFORMATION
    general_uri: str = ""
    general_size: int = 0  # bytes transferred
    general_crc_ok: bool | None = None
    parameter_uri: str = ""
    parameter_size: int = 0
    parameter_json_size: int = 0
    parameter_crc_ok: bool | None = None
    parameters: int = 0
    reboot_required: int = 0
    requests: int = 0  # REQUEST_MESSAGE commands sent
    seconds: dict[str, float] = field(default_factory=dict)  # per phase: request, general, parameters, total
    ftp: dict[str, int] = field(default_factory=dict)  # counters, see MetadataClient.stats


_STAT_NAMES: Final = (
    "sent",
    "resent",
    "send_failed",
    "bursts",
    "burst_packets",
    "reads",
    "duplicates",
    "stale",
    "naks",
    "resets",
)


class MetadataClient:
    """PX4's parameter metadata from the vehicle: component metadata request, then MAVLink FTP.

    ``link`` is anything with a pymavlink encoder ``mav`` and ``send(msg)`` (a
    :class:`~arena_common.mavlink.link.MavlinkLink`); whoever reads the link hands every message of
    :data:`HANDLED_MESSAGES` to :meth:`on_message`; :meth:`fetch` blocks in another thread.

    Each FTP request waits ``timeout`` s for its answer and is sent up to ``attempts`` times; the
    component metadata request asks for ``request_messages`` in turn (COMPONENT_METADATA, then the
    older COMPONENT_INFORMATION), each attempt waiting ``request_timeout`` s.  A burst silent for
    ``timeout`` s is over; the holes it left are read with ReadFile (or a new burst from the first hole
    when there are more than ``max_hole_reads``; two bursts in a row that bring nothing, or a server
    without BurstReadFile, switch to ReadFile for the rest).  An open refused with NoSessionsAvailable
    (PX4 serves one FTP session per link, e.g. one left behind by an earlier client, or a ground
    station's through the gateway's forwarder) resets the link's sessions and opens again when
    ``reset_busy`` is true.  Never targets system 0.
    """

    def __init__(
        self,
        link: _Link,
        target_system: int,
        target_component: int = 1,
        *,
        timeout: float = 0.5,
        attempts: int = 6,
        request_timeout: float = 1.0,
        request_attempts: int = 6,
        request_messages: tuple[int, ...] = (COMPONENT_METADATA, COMPONENT_INFORMATION),
        burst: bool = True,
        max_hole_reads: int = 32,
        reset_busy: bool = True,
        max_file_size: int = 16 << 20,
        initial_seq: int | None = None,
    ) -> None:
        if not 1 <= int(target_system) <= 255:
            raise MetadataError(f"target system must be 1..255 (never 0, broadcast), got {target_system}")
        if not 1 <= int(target_component) <= 255:
            raise MetadataError(f"target component must be within 1..255, got {target_component}")
        self.link = link
        self.target_system = int(target_system)
        self.target_component = int(target_component)
        self.timeout = timeout
        self.attempts = max(1, attempts)
        self.request_timeout = request_timeout
        self.request_attempts = max(1, request_attempts)
        if not request_messages or not set(request_messages) <= {COMPONENT_METADATA, COMPONENT_INFORMATION}:
            raise MetadataError(
                f"request_messages must name COMPONENT_METADATA (397) and/or COMPONENT_INFORMATION (395), "
                f"got {request_messages!r}"
            )
        self.request_messages = tuple(request_messages)
        self.burst = burst
        self.max_hole_reads = max_hole_reads
        self.reset_busy = reset_busy
        self.max_file_size = max_file_size
        self._cond = threading.Condition()
        self._op = threading.Lock()  # one fetch / file read at a time
        self._inbox: deque[FtpReply] = deque(maxlen=4096)
        self._ftp_component: int | None = None  # the FTP server being talked to, while a read runs
        self._general: tuple[str, str, int, int] | None = None  # (message, uri, crc, serial)
        self._serial = 0
        # A random first sequence number: PX4 repeats its cached last reply to a request whose number
        # is that reply's minus one, which must never be an earlier client's reply.
        self._seq = random.randrange(0x10000) if initial_seq is None else initial_seq & 0xFFFF
        # Touched by the fetching thread only; the reader counts in _foreign (under _cond).
        self._stats: dict[str, int] = dict.fromkeys(_STAT_NAMES, 0)
        self._foreign = 0
        self.info = FetchInfo()

    @property
    def stats(self) -> dict[str, int]:
        """Counters over this client's life: FTP messages ``sent``, ``resent``, ``send_failed``; ``bursts``,
        ``burst_packets``, ``reads`` (ReadFile), ``duplicates``, ``stale`` (replies to no current request),
        ``naks``, ``resets`` (ResetSessions), ``foreign`` (FTP messages for someone else)."""
        with self._cond:
            return {**self._stats, "foreign": self._foreign}

    @property
    def _target(self) -> str:
        comp = self._ftp_component if self._ftp_component is not None else self.target_component
        return f"system {self.target_system} component {comp}"

    # -- reader side ---------------------------------------------------------------------------------
    def on_message(self, msg: Any, now: float) -> None:
        """Take one decoded message from the link's reader (any message; only ours are kept)."""
        mid = msg.get_msgId()
        if mid == FILE_TRANSFER_PROTOCOL:
            self._on_ftp(msg)
        elif mid in (COMPONENT_METADATA, COMPONENT_INFORMATION):
            self._on_component_metadata(msg)

    def _from_target(self, msg: Any, component: int) -> bool:
        return bool(msg.get_srcSystem() == self.target_system and msg.get_srcComponent() == component)

    def _addressed_to_us(self, msg: Any) -> bool:
        mav = self.link.mav
        return getattr(msg, "target_system", 0) in (0, mav.srcSystem) and getattr(
            msg, "target_component", 0
        ) in (0, mav.srcComponent)

    def _on_ftp(self, msg: Any) -> None:
        with self._cond:
            comp = self._ftp_component
            if comp is None:
                return  # no transfer running: nothing of it is wanted
            if not self._from_target(msg, comp) or not self._addressed_to_us(msg):
                self._foreign += 1  # e.g. a ground station's transfer through the same link
                return
            try:
                reply = decode_ftp_payload(msg.payload)
            except FtpError:
                self._foreign += 1
                return
            self._inbox.append(reply)
            self._cond.notify_all()

    def _on_component_metadata(self, msg: Any) -> None:
        if not self._from_target(msg, self.target_component):
            return  # another component (a camera, a gimbal) describing itself
        if msg.get_msgId() == COMPONENT_METADATA:
            entry = ("COMPONENT_METADATA", str(msg.uri), int(msg.file_crc))
        else:
            uri, crc = str(msg.general_metadata_uri), int(msg.general_metadata_file_crc)
            entry = ("COMPONENT_INFORMATION", uri, crc)
        if not entry[1]:
            return
        with self._cond:
            self._serial += 1
            self._general = (*entry, self._serial)
            self._cond.notify_all()

    # -- public API ----------------------------------------------------------------------------------
    def general_metadata_uri(self, deadline: float) -> tuple[str, str, int]:
        """``(message name, URI, CRC32)`` of the general metadata file, asked of the vehicle now.

        Sends MAV_CMD_REQUEST_MESSAGE for each of ``request_messages`` in turn until one answers
        (whatever COMMAND_ACK says: the reader may give ACKs to someone else).
        """
        with self._cond:
            start = self._serial
        asked = unsent = 0
        for attempt in range(self.request_attempts):
            if time.monotonic() >= deadline:
                break
            n = len(self.request_messages)
            wanted = self.request_messages[attempt % n]
            msg = self.link.mav.command_long_encode(
                self.target_system,
                self.target_component,
                MAV_CMD_REQUEST_MESSAGE,
                attempt // n,
                float(wanted),
                0,
                0,
                0,
                0,
                0,
                0,
            )
            if not self.link.send(msg):
                unsent += 1
            asked += 1
            self.info.requests += 1
            until = min(deadline, time.monotonic() + self.request_timeout)
            with self._cond:
                while True:
                    got = self._general
                    if got is not None and got[3] > start:
                        return got[0], got[1], got[2]
                    left = until - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
        raise MetadataTimeout(
            f"no COMPONENT_METADATA (397) or COMPONENT_INFORMATION (395) from system {self.target_system} "
            f"component {self.target_component} after {asked} MAV_CMD_REQUEST_MESSAGE"
            + (" (the link could not send)" if unsent == asked > 0 else "")
        )

    def fetch(self, deadline: float) -> dict[str, ParamMeta]:
        """PX4's parameter metadata, read from the vehicle before ``deadline`` (:func:`time.monotonic`).

        Raises :class:`MetadataTimeout`, :class:`FtpNak`, :class:`FtpError` or
        :class:`MetadataFormatError`; :attr:`info` tells how it went.
        """
        with self._op:
            info = self.info = FetchInfo()
            t0 = time.monotonic()
            stats0 = self.stats
            msg_name, uri, crc = self.general_metadata_uri(deadline)
            t1 = time.monotonic()
            info.source_message, info.general_uri = msg_name, uri
            comp, path = parse_mftp_uri(uri)
            raw = self._read_file(path, comp, deadline)
            info.general_size = len(raw)
            general_json, info.general_crc_ok = self._unpack(raw, crc, uri, "general_crc_ok")
            types = parse_general_metadata(general_json, uri)
            t2 = time.monotonic()
            entry = types.get(COMP_METADATA_TYPE_PARAMETER)
            if entry is None:
                raise MetadataFormatError(
                    f"{uri}: lists no parameter metadata (type {COMP_METADATA_TYPE_PARAMETER}); "
                    f"types {sorted(types)}"
                )
            info.parameter_uri = entry.uri
            pcomp, ppath = parse_mftp_uri(entry.uri)
            raw = self._read_file(ppath, pcomp if pcomp is not None else comp, deadline)
            info.parameter_size = len(raw)
            params_json, info.parameter_crc_ok = self._unpack(raw, entry.crc, entry.uri, "parameter_crc_ok")
            info.parameter_json_size = len(params_json)
            meta = parse_parameters_json(params_json, entry.uri)
            t3 = time.monotonic()
            info.parameters = len(meta)
            info.reboot_required = len(reboot_required(meta))
            info.seconds = {
                "request": t1 - t0,
                "general": t2 - t1,
                "parameters": t3 - t2,
                "total": t3 - t0,
            }
            info.ftp = {k: v - stats0[k] for k, v in self.stats.items()}
            return meta

    def _unpack(self, raw: bytes, crc: int | None, uri: str, crc_field: str) -> tuple[bytes, bool | None]:
        try:
            return _unpack(raw, crc, uri)
        except _CorruptFile:
            setattr(self.info, crc_field, False)
            raise

    def read_file(self, path: str, deadline: float, component: int | None = None) -> bytes:
        """One whole file from the vehicle's MAVLink FTP server (``component`` defaults to the target's)."""
        with self._op:
            return self._read_file(path, component, deadline)

    # -- FTP -----------------------------------------------------------------------------------------
    def _read_file(self, path: str, component: int | None, deadline: float) -> bytes:
        with self._cond:
            self._inbox.clear()
            self._ftp_component = component if component is not None else self.target_component
        try:
            session, size = self._open(path, deadline)
            try:
                return self._download(path, session, size, deadline)
            finally:
                self._terminate(path, session, deadline)
        finally:
            with self._cond:
                self._ftp_component = None
                self._inbox.clear()

    def _next_seq(self, skip: int = 1) -> int:
        seq = self._seq
        self._seq = (self._seq + skip) & 0xFFFF
        return seq

    def _send_ftp(self, payload: list[int]) -> bool:
        comp = self._ftp_component if self._ftp_component is not None else self.target_component
        msg = self.link.mav.file_transfer_protocol_encode(0, self.target_system, comp, payload)
        self._stats["sent"] += 1
        if self.link.send(msg):
            return True
        self._stats["send_failed"] += 1
        return False

    def _take(self, until: float) -> FtpReply | None:
        """The next reply received, waiting until ``until``; None when none came."""
        with self._cond:
            while not self._inbox:
                left = until - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._inbox.popleft()

    def _exchange(
        self,
        op: int,
        path: str,
        deadline: float,
        *,
        session: int = 0,
        offset: int = 0,
        data: bytes = b"",
        size: int | None = None,
        attempts: int | None = None,
    ) -> FtpReply:
        """Send one request (resent with the same sequence number) until its ACK or NAK comes back."""
        seq = self._next_seq()
        want = (seq + 1) & 0xFFFF
        payload = encode_ftp_payload(seq, op, session=session, offset=offset, data=data, size=size)
        sent = unsent = 0
        for _ in range(self.attempts if attempts is None else attempts):
            now = time.monotonic()
            if now >= deadline:
                break
            if not self._send_ftp(payload):
                unsent += 1
            if sent:
                self._stats["resent"] += 1
            sent += 1
            until = min(deadline, now + self.timeout)
            while True:
                reply = self._take(until)
                if reply is None:
                    break
                if reply.seq == want and reply.req_opcode == op and reply.opcode in (OP_ACK, OP_NAK):
                    if reply.nak:
                        self._stats["naks"] += 1
                    return reply
                self._stats["stale"] += 1  # an answer to an earlier request, a burst's tail
        what = f"MAVLink FTP {OPCODE_NAMES.get(op, op)} {path!r}: no answer from {self._target}"
        if not sent:
            raise MetadataTimeout(f"{what}: the deadline passed before it could be sent")
        why = " (the link could not send)" if unsent == sent else ""
        raise MetadataTimeout(f"{what} after {sent} tries of {self.timeout:g} s{why}")

    def _refused(self, reply: FtpReply, op: int, path: str) -> FtpNak:
        return FtpNak(op, reply.error, reply.errno, path, self._target)

    def _open(self, path: str, deadline: float) -> tuple[int, int]:
        name = path.encode()
        if len(name) >= FTP_DATA_MAX:
            raise FtpError(f"MAVLink FTP path {path!r} longer than {FTP_DATA_MAX - 1} bytes")
        reset = False
        while True:
            reply = self._exchange(OP_OPEN_FILE_RO, path, deadline, data=name)
            if reply.nak and reply.error == ERR_NO_SESSIONS_AVAILABLE and self.reset_busy and not reset:
                reset = True
                self._stats["resets"] += 1
                self._exchange(OP_RESET_SESSIONS, path, deadline)  # always ACKed
                continue
            if reply.nak:
                raise self._refused(reply, OP_OPEN_FILE_RO, path)
            if reply.size < 4:
                raise FtpError(f"MAVLink FTP OpenFileRO {path!r}: {self._target} sent no file size")
            size = int.from_bytes(reply.data[:4], "little")
            if size > self.max_file_size:
                raise FtpError(
                    f"MAVLink FTP {path!r} on {self._target}: {size} bytes, more than {self.max_file_size}"
                )
            return reply.session, size

    def _terminate(self, path: str, session: int, deadline: float) -> None:
        """Close the session; never raises (PX4 closes an idle session after 10 s anyway)."""
        try:
            self._exchange(
                OP_TERMINATE_SESSION,
                path,
                max(deadline, time.monotonic() + self.timeout),
                session=session,
                attempts=min(self.attempts, 2),
            )
        except MetadataError:
            pass

    def _download(self, path: str, session: int, size: int, deadline: float) -> bytes:
        buf = _Assembly(size, path, self._target)
        use_burst = self.burst
        useless = 0  # bursts in a row that brought nothing new (a lost request, or every packet lost)
        stalls = 0
        while True:
            gaps = buf.gaps()
            if not gaps:
                return bytes(buf.data)
            if time.monotonic() >= deadline:
                raise MetadataTimeout(
                    f"MAVLink FTP {path!r} from {self._target}: {buf.have} of {size} bytes by the deadline"
                )
            before = buf.have
            holes = [g for g in gaps if g[1] < size]  # missing ranges before the (missing) tail
            hole_reads = sum(-(-(e - s) // FTP_DATA_MAX) for s, e in holes)
            if use_burst and useless >= 2:
                use_burst = False  # bursting does not get through: read chunk by chunk
            if use_burst and (not holes or hole_reads > self.max_hole_reads):
                try:
                    self._burst(path, session, gaps[0][0], buf, deadline)
                except FtpNak as exc:
                    if exc.code != ERR_UNKNOWN_COMMAND:
                        raise
                    use_burst = False  # a server without BurstReadFile: read chunk by chunk
                else:
                    useless = 0 if buf.have > before else useless + 1
            else:
                for start, end in holes if use_burst else gaps:
                    self._read_range(path, session, start, end, buf, deadline)
            stalls = 0 if buf.have > before else stalls + 1
            if stalls >= self.attempts:
                raise MetadataTimeout(
                    f"MAVLink FTP {path!r} from {self._target}: no data for {stalls} tries "
                    f"({buf.have} of {size} bytes)"
                )

    def _read_range(
        self, path: str, session: int, start: int, end: int, buf: _Assembly, deadline: float
    ) -> None:
        offset = start
        while offset < end:
            # The request's size says how much to read (PX4 v1.16 reads exactly that: 0 gives nothing).
            n = min(FTP_DATA_MAX, end - offset)
            reply = self._exchange(OP_READ_FILE, path, deadline, session=session, offset=offset, size=n)
            self._stats["reads"] += 1
            if reply.nak:
                if reply.error == ERR_EOF:
                    raise FtpError(
                        f"MAVLink FTP {path!r} on {self._target}: EOF at {offset} of the {buf.size} bytes "
                        f"announced (the file changed?)"
                    )
                raise self._refused(reply, OP_READ_FILE, path)
            if not reply.data:
                raise FtpError(f"MAVLink FTP {path!r} on {self._target}: empty read at {offset}/{buf.size}")
            if not buf.put(offset, reply.data):
                self._stats["duplicates"] += 1
            offset += len(reply.data)

    def _burst(self, path: str, session: int, start: int, buf: _Assembly, deadline: float) -> None:
        """One BurstReadFile from ``start``: take its packets until burst complete, EOF or silence."""
        window = -(-(buf.size - start) // FTP_DATA_MAX) + 2  # packets (and sequence numbers) it may use
        seq = self._next_seq(skip=window + 1)  # the next request's number lies beyond this burst
        self._send_ftp(encode_ftp_payload(seq, OP_BURST_READ_FILE, session=session, offset=start))
        self._stats["bursts"] += 1
        while True:
            now = time.monotonic()
            if now >= deadline:
                return
            reply = self._take(min(deadline, now + self.timeout))
            if reply is None:
                return  # silence: the burst (or its request, or its last packet) is over or lost
            d = (reply.seq - seq) & 0xFFFF
            if reply.req_opcode != OP_BURST_READ_FILE or not 1 <= d <= window:
                self._stats["stale"] += 1
                continue
            if reply.nak:
                self._stats["naks"] += 1
                if reply.error == ERR_EOF:
                    return
                raise self._refused(reply, OP_BURST_READ_FILE, path)
            if reply.opcode != OP_ACK:
                self._stats["stale"] += 1
                continue
            self._stats["burst_packets"] += 1
            if not buf.put(reply.offset, reply.data):
                self._stats["duplicates"] += 1
            if reply.burst_complete:
                return


class _Assembly:
    """A file being put together from chunks at offsets, in any order, each byte checked once written."""

    def __init__(self, size: int, path: str, target: str) -> None:
        self.size = size
        self.path = path
        self.target = target
        self.data = bytearray(size)
        self._got = bytearray(size)  # 1 where a byte arrived
        self.have = 0

    def put(self, offset: int, chunk: bytes) -> bool:
        """Store a chunk; False when it brought nothing new (a duplicate).  Bytes past the end are dropped."""
        end = min(self.size, offset + len(chunk))
        if offset >= end:
            return False
        chunk = chunk[: end - offset]
        got = self._got[offset:end]
        known = got.count(1)
        if known:
            for i, flag in enumerate(got):
                if flag and self.data[offset + i] != chunk[i]:
                    raise FtpError(
                        f"MAVLink FTP {self.path!r} from {self.target}: two values at offset {offset + i}"
                    )
        if known == len(chunk):
            return False
        self.data[offset:end] = chunk
        self._got[offset:end] = b"\x01" * (end - offset)
        self.have += len(chunk) - known
        return True

    def gaps(self) -> list[tuple[int, int]]:
        """The missing ``[start, end)`` ranges, in order."""
        out: list[tuple[int, int]] = []
        pos = self._got.find(0)
        while pos >= 0:
            end = self._got.find(1, pos)
            end = self.size if end < 0 else end
            out.append((pos, end))
            pos = self._got.find(0, end)
        return out


def fetch_parameter_metadata(
    link: MavlinkLink,
    target_system: int,
    deadline: float,
    target_component: int = 1,
    *,
    client: MetadataClient | None = None,
    on_frame: Callable[[Any, float], None] | None = None,
) -> dict[str, ParamMeta]:
    """:meth:`MetadataClient.fetch` on an open link nobody else reads: a reader thread runs meanwhile.

    ``on_frame(frame, now)`` sees every frame read (e.g. to keep a heartbeat's bookkeeping).
    """
    client = client or MetadataClient(link, target_system, target_component)
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            for frame in link.read(0.05):
                now = time.monotonic()
                if on_frame is not None:
                    on_frame(frame, now)
                if frame.msgid in HANDLED_MESSAGES:
                    msg = link.decode(frame)
                    if msg is not None:
                        client.on_message(msg, now)

    thread = threading.Thread(target=reader, name="px4-metadata-reader", daemon=True)
    thread.start()
    try:
        return client.fetch(deadline)
    finally:
        stop.set()
        thread.join(timeout=1.0)
