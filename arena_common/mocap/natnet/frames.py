"""NatNet frames of data (FRAMEOFDATA), the hot path: decode (rigid bodies first) and byte-exact encode."""

from __future__ import annotations

import struct
from dataclasses import dataclass

from arena_common.mocap.natnet._common import (
    _F32,
    _I16,
    _I32,
    _I32X2,
    _LM23,
    _RB30,
    _RB_HEAD,
    _RB_TAIL_26,
    _U32X2,
    _U64X3,
    _VEC3,
    MessageId,
    NatNetError,
    Quat,
    Vec3,
    Version,
    _Bad,
    _check_count,
    _Layout,
    _layout,
    _put_cstring,
)
from arena_common.mocap.natnet.packets import encode_packet

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
        off, stop = _open_section(data, off, end, sizes, n_sets, 5, "marker set")
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
        n_unlabeled, off, stop = _count_section(data, off, end, sizes, 12, "unlabeled marker")
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
            n_skeletons, off, stop = _count_section(data, off, end, sizes, 8, "skeleton")
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
            n_assets, off, stop = _count_section(data, off, end, True, 12, "asset")
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
            size = lay.lm.size
            n_labeled, off, stop = _count_section(data, off, end, sizes, size, "labeled marker")
            if full:
                labeled = _read_labeled(data, off, n_labeled, lay)
            off = _close_section(off + size * n_labeled, stop) if sizes else off + size * n_labeled

        if lay.force_plates:
            section = "force plates"
            n_plates, off, stop = _count_section(data, off, end, sizes, 8, "force plate")
            if n_plates:
                force_plates, off = _read_analog(data, off, stop, n_plates, full, "force plate")
            if sizes:
                off = _close_section(off, stop)

        if lay.devices:
            section = "devices"
            n_devices, off, stop = _count_section(data, off, end, sizes, 8, "device")
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


def _count_section(
    data: bytes, off: int, end: int, sizes: bool, least: int, what: str
) -> tuple[int, int, int]:
    """Open a section that starts with its item count: ``(count, where its items start, where it ends)``."""
    (count,) = _I32.unpack_from(data, off)
    off, stop = _open_section(data, off + 4, end, sizes, count, least, what)
    return count, off, stop


def _open_section(
    data: bytes, off: int, end: int, sizes: bool, count: int, least: int, what: str
) -> tuple[int, int]:
    """Past a section's byte count (4.1: ``sizes``), check that ``count`` items of at least ``least``
    bytes fit before its end: ``(where its items start, where it ends)``."""
    stop = end
    if sizes:
        stop = _section_end(data, off, end)
        off += 4
    _check_count(count, least, off, stop, what)
    return off, stop


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
