"""What every NatNet message shares: ports, message ids, the error, versions and their layouts, byte helpers."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from struct import Struct

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
