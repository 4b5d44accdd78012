"""NatNet model definitions (MODELDEF): what Motive streams (rigid bodies, markers, skeletons, devices...)."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import ClassVar

from arena_common.mocap.natnet._common import (
    _FP_CAL_MATRIX,
    _FP_CORNERS,
    _I32,
    _I32X2,
    _MARKER_DEF,
    _QUAT,
    _VEC3,
    MessageId,
    NatNetError,
    Quat,
    Vec3,
    Version,
    _as_bytes,
    _Bad,
    _check_count,
    _cstring,
    _Layout,
    _layout,
    _put_cstring,
)
from arena_common.mocap.natnet.packets import encode_packet

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
