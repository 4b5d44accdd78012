"""NatNet packets and the small messages: CONNECT, DISCOVERY, SERVERINFO, text requests and responses, echo."""

from __future__ import annotations

import struct
from dataclasses import dataclass

from arena_common.mocap.natnet._common import (
    _F32,
    _HEADER,
    _I32,
    _MAX_DATAGRAM,
    _SERVER_INFO_3,
    _U64,
    _U64X2,
    NAME_FIELD_SIZE,
    MessageId,
    NatNetError,
    Version,
    _as_bytes,
    _put_cstring,
)

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
