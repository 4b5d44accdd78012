"""NatNet, the streaming protocol of OptiTrack Motive: decode and encode its messages, without any I/O.

Every NatNet datagram is ``u16 message id, u16 payload length, payload`` (little-endian). Use
:func:`split_packet` to get the id and payload of a received datagram, then the ``decode_*`` function of that
message; the ``encode_*`` functions return whole datagrams, ready to send.

Frames and model definitions depend on the server's NatNet version (taken from its SERVERINFO): pass it as a
:class:`Version`. Versions 2.0 through 4.x are understood (the layouts of 2.5, 2.7, 2.9 and 3.0 are checked
against real Motive captures, 4.0 and 4.1 follow the protocol description).

The decoders never raise anything but :class:`NatNetError`, whatever the input; its message names the message,
the section and the byte offset (counted from the start of the payload) where decoding failed.

:func:`decode_frame` is on the hot path (120–360 Hz): by default it decodes the rigid bodies and the frame's
timing and only counts and steps over the other sections; ``full=True`` also keeps markers, skeletons, assets,
force plates and devices, which is what :func:`encode_frame` needs to reproduce a frame byte for byte.
"""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass
from enum import IntEnum
from struct import Struct
from typing import ClassVar

__all__ = [
    "COMMAND_PORT",
    "DATA_PORT",
    "MULTICAST_GROUP",
    "Analog",
    "Asset",
    "AssetDef",
    "CameraDef",
    "ConnectRequest",
    "DataSetDef",
    "DeviceDef",
    "ForcePlateDef",
    "Frame",
    "LabeledMarker",
    "MarkerDef",
    "MarkerSet",
    "MarkerSetDef",
    "MessageId",
    "ModelDefs",
    "NatNetError",
    "Quat",
    "Response",
    "RigidBody",
    "RigidBodyDef",
    "RigidBodyMarker",
    "ServerInfo",
    "Skeleton",
    "SkeletonDef",
    "Vec3",
    "Version",
    "bench_decode",
    "decode_connect",
    "decode_echo_request",
    "decode_echo_response",
    "decode_frame",
    "decode_message_string",
    "decode_model_defs",
    "decode_request_text",
    "decode_response",
    "decode_server_info",
    "encode_connect",
    "encode_disconnect",
    "encode_discovery",
    "encode_echo_request",
    "encode_echo_response",
    "encode_frame",
    "encode_keepalive",
    "encode_message_string",
    "encode_model_defs",
    "encode_packet",
    "encode_request",
    "encode_request_frame",
    "encode_request_model_defs",
    "encode_response",
    "encode_server_info",
    "encode_unrecognized",
    "split_packet",
]

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

#: Default ports and multicast group of a Motive server.
COMMAND_PORT = 1510
DATA_PORT = 1511
MULTICAST_GROUP = "239.255.42.99"

#: Size of the application-name field of CONNECT and SERVERINFO payloads.
NAME_FIELD_SIZE = 256


class MessageId(IntEnum):
    """NatNet message ids (the first u16 of every datagram)."""

    CONNECT = 0
    SERVERINFO = 1
    REQUEST = 2
    RESPONSE = 3
    REQUEST_MODELDEF = 4
    MODELDEF = 5
    REQUEST_FRAMEOFDATA = 6
    FRAMEOFDATA = 7
    MESSAGESTRING = 8
    DISCONNECT = 9
    KEEPALIVE = 10
    DISCONNECTBYTIMEOUT = 11
    ECHOREQUEST = 12
    ECHORESPONSE = 13
    DISCOVERY = 14
    UNRECOGNIZED_REQUEST = 100


class NatNetError(ValueError):
    """A NatNet message could not be decoded (or a value could not be encoded)."""


# ------------------------------------------------------------------------------------------------------------
# Precompiled layouts
# ------------------------------------------------------------------------------------------------------------

_HEADER = Struct("<HH")
_I16 = Struct("<h")
_I32 = Struct("<i")
_I32X2 = Struct("<ii")
_U32X2 = Struct("<II")
_U64 = Struct("<Q")
_U64X2 = Struct("<QQ")
_U64X3 = Struct("<QQQ")
_F32 = Struct("<f")
_F64 = Struct("<d")
_VEC3 = Struct("<3f")
_QUAT = Struct("<4f")
_VERSION_BYTES = Struct("<4B")
_RB_HEAD = Struct("<i7f")  # id, x y z, qx qy qz qw
_RB30 = Struct("<i7ffh")  # 3.0+: head, mean error, params
_RB_TAIL_26 = Struct("<fh")  # 2.6-2.x, after the per-body marker block: mean error, params
_LM23 = Struct("<i4f")  # id, x y z, size
_LM26 = Struct("<i4fh")  # + params
_LM30 = Struct("<i4fhf")  # + residual
_MARKER_DEF = Struct("<i3ffh")  # asset marker description after its name: id, x y z, size, params
_SERVER_INFO_3 = Struct("<QHB4B")  # clock frequency, data port, multicast flag, group
_FP_CAL_MATRIX = Struct("<144f")
_FP_CORNERS = Struct("<12f")
_FP_TAIL = Struct("<iii")  # plate type, channel data type, channel count

_MAX_DATAGRAM = 65507  # largest UDP payload over IPv4


class _Bad(Exception):
    """Internal: a malformed field, with the payload offset where it was found."""

    def __init__(self, detail: str, offset: int) -> None:
        super().__init__(detail)
        self.detail = detail
        self.offset = offset


def _check_count(count: int, min_item: int, off: int, end: int, what: str) -> None:
    """Reject a negative count, or one whose items (at least ``min_item`` bytes each) cannot fit."""
    if count < 0 or count * min_item > end - off:
        raise _Bad(f"{what} count {count} does not fit in the {end - off} bytes left", off)


def _cstring(data: bytes, off: int, end: int) -> tuple[str, int]:
    """Read a NUL-terminated string starting at ``off``; return it and the offset after its NUL."""
    nul = data.find(b"\0", off, end)
    if nul < 0:
        raise _Bad("string without its terminating NUL", off)
    return data[off:nul].decode("utf-8", "replace"), nul + 1


def _put_cstring(out: bytearray, text: str) -> None:
    raw = text.encode("utf-8")
    if b"\0" in raw:
        raise NatNetError(f"cannot encode a string containing NUL: {text!r}")
    out += raw
    out += b"\0"


def _as_bytes(payload: bytes | bytearray | memoryview) -> bytes:
    return payload if type(payload) is bytes else bytes(payload)


# ------------------------------------------------------------------------------------------------------------
# Versions and per-version layouts
# ------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, order=True)
class Version:
    """A NatNet (or application) version ``major.minor.build.revision``; compares like a tuple."""

    major: int
    minor: int = 0
    build: int = 0
    revision: int = 0

    @classmethod
    def parse(cls, text: str) -> Version:
        """Parse ``"4.1"`` or ``"3.0.0.0"`` (one to four dot-separated numbers, each 0–255)."""
        parts = text.strip().split(".")
        if not 1 <= len(parts) <= 4 or not all(p.isdigit() for p in parts):
            raise NatNetError(f"not a NatNet version: {text!r}")
        numbers = [int(p) for p in parts] + [0] * (4 - len(parts))
        if any(n > 255 for n in numbers):
            raise NatNetError(f"version component above 255: {text!r}")
        return cls(*numbers)

    @classmethod
    def from_bytes(cls, raw: bytes) -> Version:
        """Decode the ``u8[4]`` form used on the wire."""
        if len(raw) != 4:
            raise NatNetError(f"a version takes 4 bytes, got {len(raw)}")
        return cls(*raw)

    def to_bytes(self) -> bytes:
        """Encode as the ``u8[4]`` wire form."""
        try:
            return _VERSION_BYTES.pack(self.major, self.minor, self.build, self.revision)
        except struct.error:
            raise NatNetError(f"version component outside 0–255: {self}") from None

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.build}.{self.revision}"


@dataclass(frozen=True, slots=True)
class _Layout:
    """What a given NatNet version puts in frames and model definitions."""

    label: str
    sizes: bool  # 4.1+: every frame section count and every data set type is followed by an i32 byte count
    rb_markers: bool  # < 3.0: per-body marker block in frames
    rb_params: bool  # 2.6+: i16 params after each rigid body (and labeled marker)
    skeletons: bool  # 2.1+
    assets: bool  # 4.1+
    labeled: bool  # 2.3+
    lm: Struct  # labeled marker record
    force_plates: bool  # 2.9+
    devices: bool  # 2.11+
    latency: bool  # < 3.0: a float "latency" before the timecode
    timestamp: Struct | None  # f32 in 2.6, f64 from 2.7, absent before
    ticks: bool  # 3.0+: three u64 tick stamps
    precision_by_length: bool  # 4.x: the precision stamp is present when 14 bytes remain after the ticks
    precision: bool  # 4.1+: the encoder writes the precision stamp
    frame_params: bool  # 2.6+: i16 frame params
    def_markers: bool  # 3.0+: marker offsets and active labels in rigid body descriptions
    def_marker_names: bool  # 4.0+: marker names in rigid body descriptions
    def_extended: bool  # 3.0+: force plate and device descriptions


_LAYOUTS: dict[tuple[int, int], _Layout] = {}


def _layout(version: Version) -> _Layout:
    try:
        return _LAYOUTS[version.major, version.minor]
    except KeyError:
        pass
    except AttributeError:
        raise NatNetError(f"expected a Version, got {version!r}") from None
    major, minor = version.major, version.minor
    if not 2 <= major <= 4:
        raise NatNetError(f"unsupported NatNet version {version} (2.0 through 4.x are understood)")

    def at_least(ma: int, mi: int) -> bool:
        return (major, minor) >= (ma, mi)

    lay = _Layout(
        label=f"NatNet {major}.{minor}",
        sizes=at_least(4, 1),
        rb_markers=not at_least(3, 0),
        rb_params=at_least(2, 6),
        skeletons=at_least(2, 1),
        assets=at_least(4, 1),
        labeled=at_least(2, 3),
        lm=_LM30 if at_least(3, 0) else _LM26 if at_least(2, 6) else _LM23,
        force_plates=at_least(2, 9),
        devices=at_least(2, 11),
        latency=not at_least(3, 0),
        timestamp=_F64 if at_least(2, 7) else _F32 if at_least(2, 6) else None,
        ticks=at_least(3, 0),
        precision_by_length=major >= 4,
        precision=at_least(4, 1),
        frame_params=at_least(2, 6),
        def_markers=at_least(3, 0),
        def_marker_names=at_least(4, 0),
        def_extended=at_least(3, 0),
    )
    _LAYOUTS[major, minor] = lay
    return lay


# ------------------------------------------------------------------------------------------------------------
# Packets
# ------------------------------------------------------------------------------------------------------------


def split_packet(data: bytes | bytearray | memoryview) -> tuple[int, bytes]:
    """Split a datagram into ``(message id, payload)``.

    The datagram's own length is trusted, not the u16 length field (it wraps above 64 KiB); a length field
    larger than the payload means the datagram was truncated.
    """
    raw = _as_bytes(data)
    if len(raw) < 4:
        raise NatNetError(f"NatNet packet: header needs 4 bytes, got {len(raw)}")
    message_id, length = _HEADER.unpack_from(raw, 0)
    payload = raw[4:]
    if length > len(payload):
        name = _message_name(message_id)
        raise NatNetError(f"{name}: length field says {length} bytes, datagram holds {len(payload)}")
    return message_id, payload


def _message_name(message_id: int) -> str:
    try:
        return MessageId(message_id).name
    except ValueError:
        return f"message {message_id}"


def encode_packet(message_id: int, payload: bytes | bytearray = b"") -> bytes:
    """Prefix ``payload`` with the NatNet header; refuse payloads no UDP datagram can carry."""
    if len(payload) + 4 > _MAX_DATAGRAM:
        raise NatNetError(f"{_message_name(message_id)}: {len(payload)} bytes do not fit in a UDP datagram")
    if not 0 <= message_id <= 0xFFFF:
        raise NatNetError(f"message id {message_id} outside 0–65535")
    return _HEADER.pack(message_id, len(payload) & 0xFFFF) + bytes(payload)


# ------------------------------------------------------------------------------------------------------------
# CONNECT / DISCOVERY / SERVERINFO
# ------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ServerInfo:
    """SERVERINFO: who the server is and, from NatNet 3.0, where it streams frames."""

    app_name: str
    app_version: Version
    natnet_version: Version
    clock_frequency: int | None = None  # ticks per second of the frame tick stamps (3.0+)
    data_port: int | None = None  # 3.0+
    is_multicast: bool | None = None  # 3.0+
    multicast_group: str | None = None  # dotted quad, 3.0+


@dataclass(frozen=True, slots=True)
class ConnectRequest:
    """CONNECT or DISCOVERY from a client; fields a client left out are ``None``."""

    app_name: str
    app_version: Version | None
    natnet_version: Version | None


def _name_field(name: str) -> bytes:
    raw = name.encode("utf-8")
    if b"\0" in raw:
        raise NatNetError(f"application name contains NUL: {name!r}")
    if len(raw) >= NAME_FIELD_SIZE:
        raise NatNetError(f"application name longer than {NAME_FIELD_SIZE - 1} bytes: {name!r}")
    return raw.ljust(NAME_FIELD_SIZE, b"\0")


def _read_name_field(data: bytes) -> str:
    field = data[:NAME_FIELD_SIZE]
    nul = field.find(b"\0")
    return (field if nul < 0 else field[:nul]).decode("utf-8", "replace")


def decode_server_info(payload: bytes | bytearray | memoryview) -> ServerInfo:
    """Decode a SERVERINFO payload: the 264-byte pre-3.0 layout or the 279-byte 3.0+ one.

    The name stops at the first NUL (Motive leaves garbage after it).
    """
    data = _as_bytes(payload)
    if len(data) < NAME_FIELD_SIZE + 8:
        raise NatNetError(f"SERVERINFO: versions at byte 256: payload has {len(data)} bytes, needs 264")
    app_version = Version(*data[256:260])
    natnet_version = Version(*data[260:264])
    if natnet_version.major < 3:
        return ServerInfo(_read_name_field(data), app_version, natnet_version)
    if len(data) < 264 + _SERVER_INFO_3.size:
        raise NatNetError(
            f"SERVERINFO: NatNet {natnet_version} clock/port/multicast fields at byte 264: "
            f"payload has {len(data)} bytes, needs {264 + _SERVER_INFO_3.size}"
        )
    clock, port, multicast, a, b, c, d = _SERVER_INFO_3.unpack_from(data, 264)
    return ServerInfo(
        _read_name_field(data),
        app_version,
        natnet_version,
        clock_frequency=clock,
        data_port=port,
        is_multicast=bool(multicast),
        multicast_group=f"{a}.{b}.{c}.{d}",
    )


def encode_server_info(info: ServerInfo) -> bytes:
    """Encode a SERVERINFO datagram; from NatNet 3.0 the clock, port and multicast fields are required."""
    payload = _name_field(info.app_name) + info.app_version.to_bytes() + info.natnet_version.to_bytes()
    if info.natnet_version.major >= 3:
        if info.clock_frequency is None or info.data_port is None or info.is_multicast is None:
            raise NatNetError("SERVERINFO for NatNet 3.0+ needs clock_frequency, data_port and is_multicast")
        group = info.multicast_group or "0.0.0.0"
        try:
            octets = [int(p) for p in group.split(".")]
            payload += _SERVER_INFO_3.pack(info.clock_frequency, info.data_port, info.is_multicast, *octets)
        except (ValueError, struct.error):
            raise NatNetError(f"SERVERINFO: cannot encode {info}") from None
    return encode_packet(MessageId.SERVERINFO, payload)


def decode_connect(payload: bytes | bytearray | memoryview) -> ConnectRequest:
    """Decode a CONNECT (or DISCOVERY) payload: 256-byte name, u8[4] app version, u8[4] NatNet version.

    Clients may send less (an empty payload is common). The NatNet SDK's Python sample puts the requested
    NatNet version at bytes 265–268 instead, after a zero version block; that form is understood too.
    """
    data = _as_bytes(payload)
    name = _read_name_field(data)
    app_version = Version(*data[256:260]) if len(data) >= 260 else None
    natnet_version = Version(*data[260:264]) if len(data) >= 264 else None
    if natnet_version == Version(0) and len(data) >= 269 and data[265] != 0:
        natnet_version = Version(*data[265:269])
    return ConnectRequest(name, app_version, natnet_version)


def _connect_payload(app_name: str, app_version: Version | None, natnet_version: Version | None) -> bytes:
    app = app_version if app_version is not None else Version(3)
    natnet = natnet_version if natnet_version is not None else Version(3)
    return _name_field(app_name) + app.to_bytes() + natnet.to_bytes()


def encode_connect(
    app_name: str = "NatNetLib",
    app_version: Version | None = None,
    natnet_version: Version | None = None,
) -> bytes:
    """Encode a CONNECT datagram as the NatNet library does (264-byte payload; versions default to 3.0)."""
    payload = _connect_payload(app_name, app_version, natnet_version)
    return encode_packet(MessageId.CONNECT, payload)


def encode_discovery(
    app_name: str = "NatNetLib",
    app_version: Version | None = None,
    natnet_version: Version | None = None,
) -> bytes:
    """Encode the discovery broadcast (message 14, same payload as CONNECT)."""
    payload = _connect_payload(app_name, app_version, natnet_version)
    return encode_packet(MessageId.DISCOVERY, payload)


# ------------------------------------------------------------------------------------------------------------
# Text requests, responses, echo
# ------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Response:
    """A RESPONSE payload. Motive answers with text, a 4-byte number (int or float, depending on the
    command: ``FrameRate`` is a float) or opaque bytes; the accessors interpret it."""

    raw: bytes

    @property
    def text(self) -> str | None:
        """The NUL-terminated UTF-8 text, or ``None`` when the payload is not text."""
        nul = self.raw.find(b"\0")
        if nul <= 0:
            return None
        try:
            text = self.raw[:nul].decode("utf-8")
        except UnicodeDecodeError:
            return None
        return text if text.isprintable() else None

    @property
    def int_value(self) -> int | None:
        """The payload as an i32, when it is 4 bytes long."""
        return _I32.unpack(self.raw)[0] if len(self.raw) == 4 else None

    @property
    def float_value(self) -> float | None:
        """The payload as an f32, when it is 4 bytes long."""
        return _F32.unpack(self.raw)[0] if len(self.raw) == 4 else None


def decode_request_text(payload: bytes | bytearray | memoryview) -> str:
    """Decode the command of a REQUEST: text up to the first NUL (or the end), invalid UTF-8 replaced."""
    data = _as_bytes(payload)
    nul = data.find(b"\0")
    return (data if nul < 0 else data[:nul]).decode("utf-8", "replace")


def decode_message_string(payload: bytes | bytearray | memoryview) -> str:
    """Decode a MESSAGESTRING payload (NUL-terminated text)."""
    return decode_request_text(payload)


def decode_response(payload: bytes | bytearray | memoryview) -> Response:
    """Wrap a RESPONSE payload; see :class:`Response` for its interpretations."""
    return Response(_as_bytes(payload))


def encode_request(command: str) -> bytes:
    """Encode a REQUEST datagram carrying a text command (NUL-terminated)."""
    out = bytearray()
    _put_cstring(out, command)
    return encode_packet(MessageId.REQUEST, out)


def encode_response(value: str | bytes | int | float) -> bytes:
    """Encode a RESPONSE: text (NUL-terminated), raw bytes, an i32 or an f32."""
    if isinstance(value, str):
        out = bytearray()
        _put_cstring(out, value)
        return encode_packet(MessageId.RESPONSE, out)
    if isinstance(value, bytes | bytearray):
        return encode_packet(MessageId.RESPONSE, bytes(value))
    try:
        raw = _I32.pack(value) if isinstance(value, int) else _F32.pack(value)
    except struct.error:
        raise NatNetError(f"RESPONSE: cannot encode {value!r}") from None
    return encode_packet(MessageId.RESPONSE, raw)


def encode_message_string(text: str) -> bytes:
    """Encode a MESSAGESTRING datagram."""
    out = bytearray()
    _put_cstring(out, text)
    return encode_packet(MessageId.MESSAGESTRING, out)


def encode_unrecognized(payload: bytes = b"") -> bytes:
    """Encode UNRECOGNIZED_REQUEST, the answer to an unknown command (Motive fills the payload with whatever
    its buffer held; clients ignore it)."""
    return encode_packet(MessageId.UNRECOGNIZED_REQUEST, payload)


def encode_keepalive() -> bytes:
    """Encode KEEPALIVE (NatNet 4.x unicast clients send it periodically)."""
    return encode_packet(MessageId.KEEPALIVE)


def encode_disconnect() -> bytes:
    """Encode DISCONNECT."""
    return encode_packet(MessageId.DISCONNECT)


def encode_request_model_defs() -> bytes:
    """Encode REQUEST_MODELDEF."""
    return encode_packet(MessageId.REQUEST_MODELDEF)


def encode_request_frame() -> bytes:
    """Encode REQUEST_FRAMEOFDATA."""
    return encode_packet(MessageId.REQUEST_FRAMEOFDATA)


def decode_echo_request(payload: bytes | bytearray | memoryview) -> int:
    """Decode ECHOREQUEST: the client's u64 timestamp."""
    data = _as_bytes(payload)
    if len(data) < 8:
        raise NatNetError(f"ECHOREQUEST: client timestamp at byte 0: payload has {len(data)} bytes, needs 8")
    return _U64.unpack_from(data, 0)[0]


def decode_echo_response(payload: bytes | bytearray | memoryview) -> tuple[int, int]:
    """Decode ECHORESPONSE: ``(echoed client timestamp, server ticks)`` (ticks at the SERVERINFO clock)."""
    data = _as_bytes(payload)
    if len(data) < 16:
        raise NatNetError(f"ECHORESPONSE: timestamps at byte 0: payload has {len(data)} bytes, needs 16")
    client, server = _U64X2.unpack_from(data, 0)
    return client, server


def encode_echo_request(client_timestamp: int) -> bytes:
    """Encode ECHOREQUEST with the client's u64 timestamp."""
    try:
        return encode_packet(MessageId.ECHOREQUEST, _U64.pack(client_timestamp))
    except struct.error:
        raise NatNetError(f"ECHOREQUEST: client timestamp {client_timestamp} is not a u64") from None


def encode_echo_response(client_timestamp: int, server_ticks: int) -> bytes:
    """Encode ECHORESPONSE: the echoed client timestamp and the server's tick count."""
    try:
        return encode_packet(MessageId.ECHORESPONSE, _U64X2.pack(client_timestamp, server_ticks))
    except struct.error:
        raise NatNetError(f"ECHORESPONSE: {client_timestamp}, {server_ticks} are not u64") from None


# ------------------------------------------------------------------------------------------------------------
# Model definitions
# ------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class MarkerSetDef:
    """Data set type 0: a named marker set and its marker names."""

    TYPE: ClassVar[int] = 0
    name: str
    marker_names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class RigidBodyDef:
    """Data set type 1: a rigid body. Marker offsets and active labels exist from 3.0, names from 4.0."""

    TYPE: ClassVar[int] = 1
    name: str
    id: int
    parent_id: int = -1
    offset: Vec3 = (0.0, 0.0, 0.0)
    marker_offsets: tuple[Vec3, ...] = ()
    marker_labels: tuple[int, ...] = ()
    marker_names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class SkeletonDef:
    """Data set type 2: a skeleton and its bones."""

    TYPE: ClassVar[int] = 2
    name: str
    id: int
    rigid_bodies: tuple[RigidBodyDef, ...] = ()


@dataclass(frozen=True, slots=True)
class ForcePlateDef:
    """Data set type 3 (3.0+): a force plate."""

    TYPE: ClassVar[int] = 3
    id: int
    serial: str
    width: float = 0.0
    length: float = 0.0
    origin: Vec3 = (0.0, 0.0, 0.0)
    cal_matrix: tuple[float, ...] = (0.0,) * 144  # 12×12, row-major
    corners: tuple[float, ...] = (0.0,) * 12  # 4 corners × xyz
    plate_type: int = 0
    channel_data_type: int = 0
    channel_names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class DeviceDef:
    """Data set type 4 (3.0+): an analog device."""

    TYPE: ClassVar[int] = 4
    id: int
    name: str
    serial: str = ""
    device_type: int = 0
    channel_data_type: int = 0
    channel_names: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class CameraDef:
    """Data set type 5: a camera's pose."""

    TYPE: ClassVar[int] = 5
    name: str
    position: Vec3 = (0.0, 0.0, 0.0)
    orientation: Quat = (0.0, 0.0, 0.0, 1.0)  # x, y, z, w


@dataclass(frozen=True, slots=True)
class MarkerDef:
    """A marker of an asset description."""

    name: str
    id: int
    position: Vec3 = (0.0, 0.0, 0.0)
    size: float = 0.0
    params: int = 0


@dataclass(frozen=True, slots=True)
class AssetDef:
    """Data set type 6 (4.1+): an asset (trained markerset…)."""

    TYPE: ClassVar[int] = 6
    name: str
    asset_type: int
    id: int
    rigid_bodies: tuple[RigidBodyDef, ...] = ()
    markers: tuple[MarkerDef, ...] = ()


DataSetDef = MarkerSetDef | RigidBodyDef | SkeletonDef | ForcePlateDef | DeviceDef | CameraDef | AssetDef


@dataclass(frozen=True, slots=True)
class ModelDefs:
    """MODELDEF: the server's data sets in the order it sent them.

    ``skipped`` counts data sets of unknown types stepped over (possible from 4.1, which carries sizes).
    """

    datasets: tuple[DataSetDef, ...] = ()
    skipped: int = 0

    @property
    def marker_sets(self) -> tuple[MarkerSetDef, ...]:
        return tuple(d for d in self.datasets if isinstance(d, MarkerSetDef))

    @property
    def rigid_bodies(self) -> tuple[RigidBodyDef, ...]:
        return tuple(d for d in self.datasets if isinstance(d, RigidBodyDef))

    @property
    def skeletons(self) -> tuple[SkeletonDef, ...]:
        return tuple(d for d in self.datasets if isinstance(d, SkeletonDef))

    @property
    def force_plates(self) -> tuple[ForcePlateDef, ...]:
        return tuple(d for d in self.datasets if isinstance(d, ForcePlateDef))

    @property
    def devices(self) -> tuple[DeviceDef, ...]:
        return tuple(d for d in self.datasets if isinstance(d, DeviceDef))

    @property
    def cameras(self) -> tuple[CameraDef, ...]:
        return tuple(d for d in self.datasets if isinstance(d, CameraDef))

    @property
    def assets(self) -> tuple[AssetDef, ...]:
        return tuple(d for d in self.datasets if isinstance(d, AssetDef))

    def rigid_body_names(self) -> dict[int, str]:
        """Map rigid body id → name (frames carry only the ids)."""
        return {d.id: d.name for d in self.datasets if isinstance(d, RigidBodyDef)}


def _read_rigid_body_def(data: bytes, off: int, end: int, lay: _Layout) -> tuple[RigidBodyDef, int]:
    name, off = _cstring(data, off, end)
    rid, parent = _I32X2.unpack_from(data, off)
    offset = _VEC3.unpack_from(data, off + 8)
    off += 20
    if not lay.def_markers:
        return RigidBodyDef(name, rid, parent, offset), off
    (count,) = _I32.unpack_from(data, off)
    off += 4
    per_marker = 17 if lay.def_marker_names else 16
    _check_count(count, per_marker, off, end, "rigid body marker")
    offsets = tuple(_VEC3.iter_unpack(data[off : off + 12 * count]))
    off += 12 * count
    labels = struct.unpack_from(f"<{count}i", data, off)
    off += 4 * count
    names: tuple[str, ...] = ()
    if lay.def_marker_names:
        collected = []
        for _ in range(count):
            marker_name, off = _cstring(data, off, end)
            collected.append(marker_name)
        names = tuple(collected)
    return RigidBodyDef(name, rid, parent, offset, offsets, labels, names), off


def _read_strings(data: bytes, off: int, end: int, what: str) -> tuple[tuple[str, ...], int]:
    (count,) = _I32.unpack_from(data, off)
    off += 4
    _check_count(count, 1, off, end, what)
    names = []
    for _ in range(count):
        text, off = _cstring(data, off, end)
        names.append(text)
    return tuple(names), off


def _read_dataset(data: bytes, off: int, end: int, kind: int, lay: _Layout) -> tuple[DataSetDef, int]:
    if kind == 0:
        name, off = _cstring(data, off, end)
        names, off = _read_strings(data, off, end, "marker name")
        return MarkerSetDef(name, names), off
    if kind == 1:
        return _read_rigid_body_def(data, off, end, lay)
    if kind == 2:
        name, off = _cstring(data, off, end)
        sid, count = _I32X2.unpack_from(data, off)
        off += 8
        _check_count(count, 21, off, end, "skeleton bone")
        bones = []
        for _ in range(count):
            bone, off = _read_rigid_body_def(data, off, end, lay)
            bones.append(bone)
        return SkeletonDef(name, sid, tuple(bones)), off
    if kind == 3 and lay.def_extended:
        (fid,) = _I32.unpack_from(data, off)
        serial, off = _cstring(data, off + 4, end)
        width, length = struct.unpack_from("<2f", data, off)
        origin = _VEC3.unpack_from(data, off + 8)
        off += 20
        cal = _FP_CAL_MATRIX.unpack_from(data, off)
        off += _FP_CAL_MATRIX.size
        corners = _FP_CORNERS.unpack_from(data, off)
        off += _FP_CORNERS.size
        plate_type, channel_type = _I32X2.unpack_from(data, off)
        names, off = _read_strings(data, off + 8, end, "force plate channel")
        fp = ForcePlateDef(fid, serial, width, length, origin, cal, corners, plate_type, channel_type, names)
        return fp, off
    if kind == 4 and lay.def_extended:
        (did,) = _I32.unpack_from(data, off)
        name, off = _cstring(data, off + 4, end)
        serial, off = _cstring(data, off, end)
        device_type, channel_type = _I32X2.unpack_from(data, off)
        names, off = _read_strings(data, off + 8, end, "device channel")
        return DeviceDef(did, name, serial, device_type, channel_type, names), off
    if kind == 5:
        name, off = _cstring(data, off, end)
        position = _VEC3.unpack_from(data, off)
        orientation = _QUAT.unpack_from(data, off + 12)
        return CameraDef(name, position, orientation), off + 28
    if kind == 6:
        name, off = _cstring(data, off, end)
        asset_type, aid, count = struct.unpack_from("<3i", data, off)
        off += 12
        _check_count(count, 21, off, end, "asset rigid body")
        bodies = []
        for _ in range(count):
            body, off = _read_rigid_body_def(data, off, end, lay)
            bodies.append(body)
        (count,) = _I32.unpack_from(data, off)
        off += 4
        _check_count(count, 1 + _MARKER_DEF.size, off, end, "asset marker")
        markers = []
        for _ in range(count):
            marker_name, off = _cstring(data, off, end)
            mid, x, y, z, size, params = _MARKER_DEF.unpack_from(data, off)
            off += _MARKER_DEF.size
            markers.append(MarkerDef(marker_name, mid, (x, y, z), size, params))
        return AssetDef(name, asset_type, aid, tuple(bodies), tuple(markers)), off
    raise _Bad(f"unknown data set type {kind} for {lay.label}", off - 4)


_DATASET_NAMES = ("marker set", "rigid body", "skeleton", "force plate", "device", "camera", "asset")


def decode_model_defs(payload: bytes | bytearray | memoryview, version: Version) -> ModelDefs:
    """Decode a MODELDEF payload sent by a server speaking NatNet ``version``.

    All data set types (0 marker set … 6 asset) are decoded; from 4.1 each carries its byte size, which is
    checked and used to step over types this decoder does not know.
    """
    data = _as_bytes(payload)
    lay = _layout(version)
    end = len(data)
    section, off = "data set count", 0
    datasets: list[DataSetDef] = []
    skipped = 0
    try:
        (count,) = _I32.unpack_from(data, 0)
        off = 4
        _check_count(count, 8 if lay.sizes else 5, off, end, "data set")
        for index in range(count):
            section = f"data set {index}"
            (kind,) = _I32.unpack_from(data, off)
            off += 4
            if 0 <= kind < len(_DATASET_NAMES):
                section = f"data set {index} ({_DATASET_NAMES[kind]})"
            if lay.sizes:
                (size,) = _I32.unpack_from(data, off)
                off += 4
                if size < 0 or size > end - off:
                    raise _Bad(f"byte count {size} does not fit in the {end - off} bytes left", off - 4)
                stop = off + size
                if not 0 <= kind < len(_DATASET_NAMES):
                    skipped += 1
                    off = stop
                    continue
                dataset, after = _read_dataset(data, off, stop, kind, lay)
                if after > stop:
                    raise _Bad(f"description runs {after - stop} bytes past its byte count {size}", off)
                off = stop
            else:
                dataset, off = _read_dataset(data, off, end, kind, lay)
            datasets.append(dataset)
        if off != end:
            section = "end of payload"
            raise _Bad(f"{end - off} unexpected trailing bytes", off)
    except NatNetError:
        raise
    except _Bad as bad:
        raise NatNetError(f"MODELDEF ({lay.label}): {section}: {bad.detail} at byte {bad.offset}") from None
    except (struct.error, ValueError, IndexError, OverflowError, MemoryError) as exc:
        raise NatNetError(
            f"MODELDEF ({lay.label}): {section}: truncated or malformed at byte {off}: {exc}"
        ) from None
    return ModelDefs(tuple(datasets), skipped)


def _put_rigid_body_def(out: bytearray, rb: RigidBodyDef, lay: _Layout) -> None:
    _put_cstring(out, rb.name)
    out += _I32X2.pack(rb.id, rb.parent_id)
    out += _VEC3.pack(*rb.offset)
    if not lay.def_markers:
        return
    count = len(rb.marker_offsets)
    labels = rb.marker_labels or (0,) * count
    names = rb.marker_names or tuple(f"Marker{i + 1}" for i in range(count))
    if len(labels) != count or (lay.def_marker_names and len(names) != count):
        raise NatNetError(f"rigid body {rb.name!r}: marker offsets, labels and names differ in number")
    out += _I32.pack(count)
    for marker in rb.marker_offsets:
        out += _VEC3.pack(*marker)
    out += struct.pack(f"<{count}i", *labels)
    if lay.def_marker_names:
        for marker_name in names:
            _put_cstring(out, marker_name)


def _put_strings(out: bytearray, names: tuple[str, ...]) -> None:
    out += _I32.pack(len(names))
    for name in names:
        _put_cstring(out, name)


def _put_dataset(out: bytearray, ds: DataSetDef, lay: _Layout) -> None:
    if isinstance(ds, MarkerSetDef):
        _put_cstring(out, ds.name)
        _put_strings(out, ds.marker_names)
    elif isinstance(ds, RigidBodyDef):
        _put_rigid_body_def(out, ds, lay)
    elif isinstance(ds, SkeletonDef):
        _put_cstring(out, ds.name)
        out += _I32X2.pack(ds.id, len(ds.rigid_bodies))
        for bone in ds.rigid_bodies:
            _put_rigid_body_def(out, bone, lay)
    elif isinstance(ds, ForcePlateDef):
        if not lay.def_extended:
            raise NatNetError(f"force plate descriptions need NatNet 3.0+, not {lay.label}")
        out += _I32.pack(ds.id)
        _put_cstring(out, ds.serial)
        out += struct.pack("<2f", ds.width, ds.length)
        out += _VEC3.pack(*ds.origin)
        out += _FP_CAL_MATRIX.pack(*ds.cal_matrix)
        out += _FP_CORNERS.pack(*ds.corners)
        out += _I32X2.pack(ds.plate_type, ds.channel_data_type)
        _put_strings(out, ds.channel_names)
    elif isinstance(ds, DeviceDef):
        if not lay.def_extended:
            raise NatNetError(f"device descriptions need NatNet 3.0+, not {lay.label}")
        out += _I32.pack(ds.id)
        _put_cstring(out, ds.name)
        _put_cstring(out, ds.serial)
        out += _I32X2.pack(ds.device_type, ds.channel_data_type)
        _put_strings(out, ds.channel_names)
    elif isinstance(ds, CameraDef):
        _put_cstring(out, ds.name)
        out += _VEC3.pack(*ds.position)
        out += _QUAT.pack(*ds.orientation)
    elif isinstance(ds, AssetDef):
        _put_cstring(out, ds.name)
        out += struct.pack("<3i", ds.asset_type, ds.id, len(ds.rigid_bodies))
        for body in ds.rigid_bodies:
            _put_rigid_body_def(out, body, lay)
        out += _I32.pack(len(ds.markers))
        for marker in ds.markers:
            _put_cstring(out, marker.name)
            out += _MARKER_DEF.pack(marker.id, *marker.position, marker.size, marker.params)
    else:
        raise NatNetError(f"not a data set description: {ds!r}")


def encode_model_defs(defs: ModelDefs, version: Version) -> bytes:
    """Encode a MODELDEF datagram for NatNet ``version`` (data sets in the order of ``defs.datasets``)."""
    lay = _layout(version)
    out = bytearray(_I32.pack(len(defs.datasets)))
    try:
        for ds in defs.datasets:
            out += _I32.pack(ds.TYPE)
            if lay.sizes:
                body = bytearray()
                _put_dataset(body, ds, lay)
                out += _I32.pack(len(body))
                out += body
            else:
                _put_dataset(out, ds, lay)
    except (struct.error, TypeError) as exc:
        raise NatNetError(f"MODELDEF ({lay.label}): cannot encode: {exc}") from None
    return encode_packet(MessageId.MODELDEF, out)


# ------------------------------------------------------------------------------------------------------------
# Frames
# ------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RigidBodyMarker:
    """A marker of a rigid body's pre-3.0 per-body marker block."""

    id: int
    pos: Vec3
    size: float


@dataclass(frozen=True, slots=True)
class RigidBody:
    """A rigid body's pose in one frame, in Motive's frame (metres; quaternion x, y, z, w).

    ``tracking_valid`` is bit 0 of ``params`` (2.6+); before 2.6 there is no flag and it is ``True``.
    An untracked body is still streamed, with ``tracking_valid`` false: never use its pose.
    """

    id: int
    pos: Vec3
    quat_xyzw: Quat
    mean_error: float | None = None
    tracking_valid: bool = True
    params: int | None = None
    markers: tuple[RigidBodyMarker, ...] = ()  # pre-3.0 frames decoded with full=True


@dataclass(frozen=True, slots=True)
class MarkerSet:
    """A named marker set of a frame and its marker positions."""

    name: str
    markers: tuple[Vec3, ...] = ()


@dataclass(frozen=True, slots=True)
class Skeleton:
    """A skeleton of a frame and its bones' poses."""

    id: int
    rigid_bodies: tuple[RigidBody, ...] = ()


@dataclass(frozen=True, slots=True)
class LabeledMarker:
    """A labeled marker (2.3+). ``params`` exists from 2.6, ``residual`` from 3.0."""

    id: int
    pos: Vec3
    size: float = 0.0
    params: int | None = None
    residual: float | None = None

    @property
    def model_id(self) -> int:
        """The asset id (high 16 bits of ``id``)."""
        return (self.id >> 16) & 0xFFFF

    @property
    def marker_id(self) -> int:
        """The marker's index in its asset (low 16 bits of ``id``)."""
        return self.id & 0xFFFF

    @property
    def occluded(self) -> bool:
        """Bit 0 of ``params``: the marker was not seen in this frame."""
        return bool((self.params or 0) & 0x01)


@dataclass(frozen=True, slots=True)
class Asset:
    """An asset of a 4.1+ frame: its rigid bodies and markers."""

    id: int
    rigid_bodies: tuple[RigidBody, ...] = ()
    markers: tuple[LabeledMarker, ...] = ()


@dataclass(frozen=True, slots=True)
class Analog:
    """Force plate (2.9+) or device (2.11+) samples: per channel, the samples of this frame."""

    id: int
    channels: tuple[tuple[float, ...], ...] = ()


_DETAIL_FIELDS = (
    ("n_marker_sets", "marker_sets"),
    ("n_unlabeled_markers", "unlabeled_markers"),
    ("n_skeletons", "skeletons"),
    ("n_assets", "assets"),
    ("n_labeled_markers", "labeled_markers"),
    ("n_force_plates", "force_plates"),
    ("n_devices", "devices"),
)


@dataclass(frozen=True, slots=True)
class Frame:
    """FRAMEOFDATA: one motion-capture frame.

    ``timestamp`` is Motive's session clock in seconds (``None`` before 2.6). The three tick stamps (3.0+)
    count the SERVERINFO clock: camera mid-exposure, camera data received by Motive, transmit. The precision
    stamp (4.1) is seconds plus a fraction. ``n_*`` count each section; the sections' contents
    (``marker_sets`` … ``devices``) are kept only by ``decode_frame(..., full=True)`` or set by a sender.
    """

    frame_number: int
    rigid_bodies: tuple[RigidBody, ...] = ()
    timecode: int = 0
    subframe: int = 0
    timestamp: float | None = None
    cam_mid_exposure: int | None = None
    data_received: int | None = None
    transmit: int | None = None
    precision_secs: int | None = None
    precision_fraction: int | None = None
    params: int = 0
    latency: float | None = None  # the meaningless pre-3.0 "latency" float
    n_marker_sets: int = 0
    n_unlabeled_markers: int = 0
    n_skeletons: int = 0
    n_assets: int = 0
    n_labeled_markers: int = 0
    n_force_plates: int = 0
    n_devices: int = 0
    marker_sets: tuple[MarkerSet, ...] = ()
    unlabeled_markers: tuple[Vec3, ...] = ()
    skeletons: tuple[Skeleton, ...] = ()
    assets: tuple[Asset, ...] = ()
    labeled_markers: tuple[LabeledMarker, ...] = ()
    force_plates: tuple[Analog, ...] = ()
    devices: tuple[Analog, ...] = ()

    def __post_init__(self) -> None:
        if (
            self.marker_sets
            or self.unlabeled_markers
            or self.skeletons
            or self.assets
            or self.labeled_markers
            or self.force_plates
            or self.devices
        ):
            self._fill_counts()

    def _fill_counts(self) -> None:
        for count_name, items_name in _DETAIL_FIELDS:
            items = getattr(self, items_name)
            if items:
                count = getattr(self, count_name)
                if count == 0:
                    object.__setattr__(self, count_name, len(items))
                elif count != len(items):
                    raise NatNetError(
                        f"frame {self.frame_number}: {count_name}={count} but {len(items)} {items_name}"
                    )

    @property
    def models_changed(self) -> bool:
        """Frame params bit 0x02: the tracked model list changed; request the model definitions again."""
        return bool(self.params & 0x02)

    @property
    def is_recording(self) -> bool:
        """Frame params bit 0x01: Motive is recording."""
        return bool(self.params & 0x01)

    def system_latency(self, clock_frequency: int) -> float | None:
        """Seconds from camera mid-exposure to transmit (3.0+), given SERVERINFO's clock frequency."""
        if self.transmit is None or self.cam_mid_exposure is None or clock_frequency <= 0:
            return None
        return (self.transmit - self.cam_mid_exposure) / clock_frequency


def _read_rigid_body(data: bytes, off: int, end: int, lay: _Layout, full: bool) -> tuple[RigidBody, int]:
    """Read one rigid body in any version's layout (the 3.0+ main section has its own fast path)."""
    rid, x, y, z, qx, qy, qz, qw = _RB_HEAD.unpack_from(data, off)
    off += 32
    markers: tuple[RigidBodyMarker, ...] = ()
    if lay.rb_markers:
        (count,) = _I32.unpack_from(data, off)
        off += 4
        _check_count(count, 20, off, end, "rigid body marker")
        if full:
            positions = tuple(_VEC3.iter_unpack(data[off : off + 12 * count]))
            ids = struct.unpack_from(f"<{count}i", data, off + 12 * count)
            sizes = struct.unpack_from(f"<{count}f", data, off + 16 * count)
            markers = tuple(RigidBodyMarker(i, p, s) for i, p, s in zip(ids, positions, sizes, strict=True))
        off += 20 * count
    if lay.rb_params:
        mean_error, params = _RB_TAIL_26.unpack_from(data, off)
        off += 6
        return RigidBody(rid, (x, y, z), (qx, qy, qz, qw), mean_error, bool(params & 1), params, markers), off
    (mean_error,) = _F32.unpack_from(data, off)
    return RigidBody(rid, (x, y, z), (qx, qy, qz, qw), mean_error, True, None, markers), off + 4


def _read_labeled(data: bytes, off: int, count: int, lay: _Layout) -> tuple[LabeledMarker, ...]:
    size = lay.lm.size
    records = lay.lm.iter_unpack(data[off : off + size * count])
    if size == 26:
        return tuple(LabeledMarker(r[0], (r[1], r[2], r[3]), r[4], r[5], r[6]) for r in records)
    if size == 22:
        return tuple(LabeledMarker(r[0], (r[1], r[2], r[3]), r[4], r[5]) for r in records)
    return tuple(LabeledMarker(r[0], (r[1], r[2], r[3]), r[4]) for r in records)


def _read_analog(
    data: bytes, off: int, end: int, count: int, full: bool, what: str
) -> tuple[tuple[Analog, ...], int]:
    items = []
    for _ in range(count):
        aid, channels = _I32X2.unpack_from(data, off)
        off += 8
        _check_count(channels, 4, off, end, f"{what} channel")
        samples = []
        for _ in range(channels):
            (frames,) = _I32.unpack_from(data, off)
            off += 4
            _check_count(frames, 4, off, end, f"{what} sample")
            if full:
                samples.append(struct.unpack_from(f"<{frames}f", data, off))
            off += 4 * frames
        if full:
            items.append(Analog(aid, tuple(samples)))
    return tuple(items), off


def decode_frame(payload: bytes | bytearray | memoryview, version: Version, *, full: bool = False) -> Frame:
    """Decode a FRAMEOFDATA payload sent by a server speaking NatNet ``version`` (2.0 through 4.x).

    Every section is checked against its layout. With ``full=False`` (the fast path) only rigid bodies and
    timing are kept, other sections are counted; ``full=True`` keeps every section's contents.
    For 4.x, whether the 4.1 precision stamp is present is decided by the bytes left after the tick stamps
    (6: absent, 14: present), so a server that reports 4.0 but sends 4.1 suffixes still decodes.
    """
    data = payload if type(payload) is bytes else bytes(payload)
    lay = _layout(version)
    end = len(data)
    sizes = lay.sizes
    section, off = "frame number", 0
    marker_sets: tuple[MarkerSet, ...] = ()
    unlabeled: tuple[Vec3, ...] = ()
    skeletons: tuple[Skeleton, ...] = ()
    assets: tuple[Asset, ...] = ()
    labeled: tuple[LabeledMarker, ...] = ()
    force_plates: tuple[Analog, ...] = ()
    devices: tuple[Analog, ...] = ()
    n_skeletons = n_assets = n_labeled = n_plates = n_devices = 0
    timestamp: float | None = None
    latency: float | None = None
    mid = received = transmit = secs = fraction = None
    params = 0
    try:
        frame_number, n_sets = _I32X2.unpack_from(data, 0)
        off = 8

        section = "marker sets"
        stop = end
        if sizes:
            stop = _section_end(data, off, end)
            off += 4
        _check_count(n_sets, 5, off, stop, "marker set")
        if sizes and not full:
            off = stop
        else:
            sets = []
            find, read_i32 = data.find, _I32.unpack_from
            for _ in range(n_sets):
                nul = find(b"\0", off, stop)
                if nul < 0:
                    raise _Bad("marker set name without its terminating NUL", off)
                (count,) = read_i32(data, nul + 1)
                start = nul + 5
                if count < 0 or 12 * count > stop - start:
                    raise _Bad(f"marker count {count} does not fit in the {stop - start} bytes left", start)
                if full:
                    name = data[off:nul].decode("utf-8", "replace")
                    sets.append(MarkerSet(name, tuple(_VEC3.iter_unpack(data[start : start + 12 * count]))))
                off = start + 12 * count
            marker_sets = tuple(sets)
            if sizes:
                off = _close_section(off, stop)

        section = "unlabeled markers"
        (n_unlabeled,) = _I32.unpack_from(data, off)
        off += 4
        stop = end
        if sizes:
            stop = _section_end(data, off, end)
            off += 4
        _check_count(n_unlabeled, 12, off, stop, "unlabeled marker")
        if full:
            unlabeled = tuple(_VEC3.iter_unpack(data[off : off + 12 * n_unlabeled]))
        off = _close_section(off + 12 * n_unlabeled, stop) if sizes else off + 12 * n_unlabeled

        section = "rigid bodies"
        (count,) = _I32.unpack_from(data, off)
        off += 4
        stop = end
        if sizes:
            stop = _section_end(data, off, end)
            off += 4
        if not lay.rb_markers:
            _check_count(count, 38, off, stop, "rigid body")
            bodies = tuple(
                [
                    RigidBody(rid, (x, y, z), (qx, qy, qz, qw), err, bool(p & 1), p)
                    for rid, x, y, z, qx, qy, qz, qw, err, p in _RB30.iter_unpack(
                        data[off : off + 38 * count]
                    )
                ]
            )
            off += 38 * count
        else:
            _check_count(count, 36, off, stop, "rigid body")
            items = []
            for _ in range(count):
                body, off = _read_rigid_body(data, off, stop, lay, full)
                items.append(body)
            bodies = tuple(items)
        if sizes:
            off = _close_section(off, stop)

        if lay.skeletons:
            section = "skeletons"
            (n_skeletons,) = _I32.unpack_from(data, off)
            off += 4
            stop = end
            if sizes:
                stop = _section_end(data, off, end)
                off += 4
            _check_count(n_skeletons, 8, off, stop, "skeleton")
            if sizes and not full:
                off = stop
            else:
                skels = []
                for _ in range(n_skeletons):
                    sid, count = _I32X2.unpack_from(data, off)
                    off += 8
                    _check_count(count, 36, off, stop, "skeleton bone")
                    bones = []
                    for _ in range(count):
                        bone, off = _read_rigid_body(data, off, stop, lay, full)
                        bones.append(bone)
                    if full:
                        skels.append(Skeleton(sid, tuple(bones)))
                skeletons = tuple(skels)
                if sizes:
                    off = _close_section(off, stop)

        if lay.assets:
            section = "assets"
            (n_assets,) = _I32.unpack_from(data, off)
            off += 4
            stop = _section_end(data, off, end)
            off += 4
            _check_count(n_assets, 12, off, stop, "asset")
            if not full:
                off = stop
            else:
                found = []
                for _ in range(n_assets):
                    aid, count = _I32X2.unpack_from(data, off)
                    off += 8
                    _check_count(count, 38, off, stop, "asset rigid body")
                    asset_bodies = []
                    for _ in range(count):
                        body, off = _read_rigid_body(data, off, stop, lay, full)
                        asset_bodies.append(body)
                    (count,) = _I32.unpack_from(data, off)
                    off += 4
                    _check_count(count, 26, off, stop, "asset marker")
                    asset_markers = _read_labeled(data, off, count, lay)
                    off += 26 * count
                    found.append(Asset(aid, tuple(asset_bodies), asset_markers))
                assets = tuple(found)
                off = _close_section(off, stop)

        if lay.labeled:
            section = "labeled markers"
            (n_labeled,) = _I32.unpack_from(data, off)
            off += 4
            stop = end
            if sizes:
                stop = _section_end(data, off, end)
                off += 4
            size = lay.lm.size
            _check_count(n_labeled, size, off, stop, "labeled marker")
            if full:
                labeled = _read_labeled(data, off, n_labeled, lay)
            off = _close_section(off + size * n_labeled, stop) if sizes else off + size * n_labeled

        if lay.force_plates:
            section = "force plates"
            (n_plates,) = _I32.unpack_from(data, off)
            off += 4
            stop = end
            if sizes:
                stop = _section_end(data, off, end)
                off += 4
            _check_count(n_plates, 8, off, stop, "force plate")
            if n_plates:
                force_plates, off = _read_analog(data, off, stop, n_plates, full, "force plate")
            if sizes:
                off = _close_section(off, stop)

        if lay.devices:
            section = "devices"
            (n_devices,) = _I32.unpack_from(data, off)
            off += 4
            stop = end
            if sizes:
                stop = _section_end(data, off, end)
                off += 4
            _check_count(n_devices, 8, off, stop, "device")
            if n_devices:
                devices, off = _read_analog(data, off, stop, n_devices, full, "device")
            if sizes:
                off = _close_section(off, stop)

        section = "frame suffix"
        if lay.latency:
            (latency,) = _F32.unpack_from(data, off)
            off += 4
        timecode, subframe = _U32X2.unpack_from(data, off)
        off += 8
        if lay.timestamp is not None:
            (timestamp,) = lay.timestamp.unpack_from(data, off)
            off += lay.timestamp.size
        if lay.ticks:
            mid, received, transmit = _U64X3.unpack_from(data, off)
            off += 24
        if lay.precision_by_length:
            left = end - off
            if left == 14:
                secs, fraction = _U32X2.unpack_from(data, off)
                off += 8
            elif left != 6:
                raise _Bad(f"{left} bytes after the tick stamps, expected 6 (4.0) or 14 (4.1)", off)
        if lay.frame_params:
            (params,) = _I16.unpack_from(data, off)
            off += 2
        section = "end-of-data tag"
        _I32.unpack_from(data, off)
        off += 4
        if off != end:
            raise _Bad(f"{end - off} unexpected trailing bytes", off)
    except _Bad as bad:
        raise NatNetError(
            f"FRAMEOFDATA ({lay.label}): {section}: {bad.detail} at byte {bad.offset}"
        ) from None
    except (struct.error, ValueError, IndexError, OverflowError, MemoryError) as exc:
        raise NatNetError(
            f"FRAMEOFDATA ({lay.label}): {section}: truncated or malformed at byte {off}: {exc}"
        ) from None
    return Frame(
        frame_number,
        bodies,
        timecode,
        subframe,
        timestamp,
        mid,
        received,
        transmit,
        secs,
        fraction,
        params,
        latency,
        n_sets,
        n_unlabeled,
        n_skeletons,
        n_assets,
        n_labeled,
        n_plates,
        n_devices,
        marker_sets,
        unlabeled,
        skeletons,
        assets,
        labeled,
        force_plates,
        devices,
    )


def _section_end(data: bytes, off: int, end: int) -> int:
    """Read a 4.1 section byte count at ``off``; return where the section ends."""
    (size,) = _I32.unpack_from(data, off)
    if size < 0 or size > end - off - 4:
        raise _Bad(f"section byte count {size} does not fit in the {end - off - 4} bytes left", off)
    return off + 4 + size


def _close_section(off: int, stop: int) -> int:
    """Check a 4.1 section did not overrun its byte count; step over any bytes this decoder does not know."""
    if off > stop:
        raise _Bad(f"section runs {off - stop} bytes past its byte count", stop)
    return stop


def _put_rigid_body(out: bytearray, rb: RigidBody, lay: _Layout) -> None:
    out += _RB_HEAD.pack(rb.id, *rb.pos, *rb.quat_xyzw)
    if lay.rb_markers:
        out += _I32.pack(len(rb.markers))
        for marker in rb.markers:
            out += _VEC3.pack(*marker.pos)
        for marker in rb.markers:
            out += _I32.pack(marker.id)
        for marker in rb.markers:
            out += _F32.pack(marker.size)
    out += _F32.pack(0.0 if rb.mean_error is None else rb.mean_error)
    if lay.rb_params:
        out += _I16.pack(((rb.params or 0) & ~1) | (1 if rb.tracking_valid else 0))


def _put_labeled(out: bytearray, marker: LabeledMarker, lay: _Layout) -> None:
    out += _LM23.pack(marker.id, *marker.pos, marker.size)
    if lay.rb_params:
        out += _I16.pack(marker.params or 0)
    if lay.ticks:
        out += _F32.pack(marker.residual or 0.0)


def _put_analog(out: bytearray, items: tuple[Analog, ...]) -> None:
    for item in items:
        out += _I32X2.pack(item.id, len(item.channels))
        for channel in item.channels:
            out += _I32.pack(len(channel))
            out += struct.pack(f"<{len(channel)}f", *channel)


def _put_section(out: bytearray, count: int, body: bytearray, lay: _Layout) -> None:
    out += _I32X2.pack(count, len(body)) if lay.sizes else _I32.pack(count)
    out += body


def encode_frame(frame: Frame, version: Version) -> bytes:
    """Encode a FRAMEOFDATA datagram exactly as Motive lays it out for NatNet ``version`` (2.0 through 4.x).

    Sections are written from the frame's contents; a frame decoded without ``full=True`` whose counts say a
    section had items cannot be re-encoded faithfully and raises :class:`NatNetError`. Fields a version does
    not have are left out; fields it has but the frame lacks (``None``) are written as zeros.
    """
    lay = _layout(version)
    for count_name, items_name in _DETAIL_FIELDS:
        if getattr(frame, count_name) and not getattr(frame, items_name):
            raise NatNetError(
                f"frame {frame.frame_number}: {count_name}={getattr(frame, count_name)} but no {items_name} "
                "to encode (decode with full=True to re-encode)"
            )
    if frame.skeletons and not lay.skeletons:
        raise NatNetError(f"{lay.label} frames have no skeletons")
    if frame.assets and not lay.assets:
        raise NatNetError(f"{lay.label} frames have no assets")
    if frame.labeled_markers and not lay.labeled:
        raise NatNetError(f"{lay.label} frames have no labeled markers")
    if frame.force_plates and not lay.force_plates:
        raise NatNetError(f"{lay.label} frames have no force plates")
    if frame.devices and not lay.devices:
        raise NatNetError(f"{lay.label} frames have no devices")
    try:
        out = bytearray(_I32.pack(frame.frame_number))
        body = bytearray()
        for marker_set in frame.marker_sets:
            _put_cstring(body, marker_set.name)
            body += _I32.pack(len(marker_set.markers))
            for marker in marker_set.markers:
                body += _VEC3.pack(*marker)
        _put_section(out, len(frame.marker_sets), body, lay)

        body = bytearray()
        for marker in frame.unlabeled_markers:
            body += _VEC3.pack(*marker)
        _put_section(out, len(frame.unlabeled_markers), body, lay)

        body = bytearray()
        for rb in frame.rigid_bodies:
            _put_rigid_body(body, rb, lay)
        _put_section(out, len(frame.rigid_bodies), body, lay)

        if lay.skeletons:
            body = bytearray()
            for skeleton in frame.skeletons:
                body += _I32X2.pack(skeleton.id, len(skeleton.rigid_bodies))
                for rb in skeleton.rigid_bodies:
                    _put_rigid_body(body, rb, lay)
            _put_section(out, len(frame.skeletons), body, lay)

        if lay.assets:
            body = bytearray()
            for asset in frame.assets:
                body += _I32X2.pack(asset.id, len(asset.rigid_bodies))
                for rb in asset.rigid_bodies:
                    _put_rigid_body(body, rb, lay)
                body += _I32.pack(len(asset.markers))
                for lm in asset.markers:
                    _put_labeled(body, lm, lay)
            _put_section(out, len(frame.assets), body, lay)

        if lay.labeled:
            body = bytearray()
            for lm in frame.labeled_markers:
                _put_labeled(body, lm, lay)
            _put_section(out, len(frame.labeled_markers), body, lay)

        if lay.force_plates:
            body = bytearray()
            _put_analog(body, frame.force_plates)
            _put_section(out, len(frame.force_plates), body, lay)

        if lay.devices:
            body = bytearray()
            _put_analog(body, frame.devices)
            _put_section(out, len(frame.devices), body, lay)

        if lay.latency:
            out += _F32.pack(frame.latency or 0.0)
        out += _U32X2.pack(frame.timecode, frame.subframe)
        if lay.timestamp is not None:
            out += lay.timestamp.pack(frame.timestamp or 0.0)
        if lay.ticks:
            out += _U64X3.pack(frame.cam_mid_exposure or 0, frame.data_received or 0, frame.transmit or 0)
        if lay.precision:
            out += _U32X2.pack(frame.precision_secs or 0, frame.precision_fraction or 0)
        if lay.frame_params:
            out += _I16.pack(frame.params)
        out += _I32.pack(0)
    except (struct.error, TypeError) as exc:
        raise NatNetError(
            f"FRAMEOFDATA ({lay.label}): cannot encode frame {frame.frame_number}: {exc}"
        ) from None
    return encode_packet(MessageId.FRAMEOFDATA, out)


# ------------------------------------------------------------------------------------------------------------
# Benchmark
# ------------------------------------------------------------------------------------------------------------


def _bench_frame(n_bodies: int) -> Frame:
    """A realistic NatNet 3.0 frame: per body a 4-marker set and 4 labeled markers, plus the "all" set."""
    bodies: list[RigidBody] = []
    sets: list[MarkerSet] = []
    labeled: list[LabeledMarker] = []
    all_markers: list[Vec3] = []
    for i in range(n_bodies):
        markers = tuple((0.1 * i + 0.01 * k, 1.0, -0.5 + 0.02 * k) for k in range(4))
        all_markers.extend(markers)
        sets.append(MarkerSet(f"Body{i + 1}", markers))
        labeled.extend(
            LabeledMarker(((i + 1) << 16) | (k + 1), m, 0.014, 0, 0.0001) for k, m in enumerate(markers)
        )
        bodies.append(RigidBody(i + 1, (0.1 * i, 1.0, -0.5), (0.0, 0.0, 0.0, 1.0), 0.0005, True, 1))
    sets.append(MarkerSet("all", tuple(all_markers)))
    return Frame(
        frame_number=1,
        rigid_bodies=tuple(bodies),
        timestamp=12.5,
        cam_mid_exposure=1_000_000,
        data_received=1_015_000,
        transmit=1_018_000,
        marker_sets=tuple(sets),
        labeled_markers=tuple(labeled),
    )


def bench_decode(n_bodies: int, iterations: int = 2000, version: Version | None = None) -> float:
    """Micro-benchmark: microseconds per :func:`decode_frame` (fast path) of a frame with ``n_bodies``
    tracked bodies (best of three runs of ``iterations`` decodes)."""
    version = version if version is not None else Version(3)
    _, payload = split_packet(encode_frame(_bench_frame(n_bodies), version))
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter_ns()
        for _ in range(iterations):
            decode_frame(payload, version)
        best = min(best, (time.perf_counter_ns() - start) / iterations / 1000.0)
    return best
