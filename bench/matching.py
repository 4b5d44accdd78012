"""What ``make bench`` measures an arena run by: wire sizes, MAVLink framing, matching ODOMETRY to frames.

Matching an ODOMETRY to its frame: ODOMETRY carries no frame number, but its ``time_usec`` is the pose's
measurement time, the frame's camera mid-exposure mapped onto the local clock by the ingest, so
``time_usec·1000 − mid_exposure`` is one constant (the clock offset) for the right frame and differs by
whole frame periods for the others.  The constant is the mode of that difference over every frame whose
position equals the ODOMETRY's (float32, bit for bit); each ODOMETRY is then assigned the frame with that
position whose difference is nearest the constant.  A position no frame had is a *mismatch* (wrong data),
a frame with no ODOMETRY is *lost*.
"""

from __future__ import annotations

import collections
import itertools
import math
import struct
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import msgpack

from arena_common.bus.session import Bus
from arena_common.core import keys, wire
from arena_common.geometry.frames import FrameTransform
from arena_common.mavlink import px4
from arena_common.mocap import natnet
from bench.harness import (
    latency_stats,
)

__all__ = [
    "ODOMETRY_ID",
    "HopWatcher",
    "analyze_arena",
    "analyze_floor",
    "decode_frames",
    "hop_breakdown",
    "mavlink_frame",
    "odometry_of",
    "payload_sizes",
]

ODOMETRY_ID = px4.MAVLINK_MSG_ID_ODOMETRY
VISION_RATE = 400.0  # Hz: above the mocap rate, so the decimator passes every pose
NATNET_VERSION = "3.1"
_ODO_HEAD = struct.Struct("<Qfff")
_F32 = struct.Struct("<fff")


# -- wire sizes ----------------------------------------------------------------------------------------------


def _example_frame(n_bodies: int) -> natnet.Frame:
    bodies = tuple(
        natnet.RigidBody(i + 1, (0.1 * i, 1.0, -0.2 * i), (0.0, 0.38268343, 0.0, 0.92387953), 0.0002, True, 1)
        for i in range(n_bodies)
    )
    return natnet.Frame(
        frame_number=123456,
        rigid_bodies=bodies,
        timestamp=1234.5,
        cam_mid_exposure=10**12,
        data_received=10**12 + 45700,
        transmit=10**12 + 53800,
    )


def payload_sizes(n_bodies: int) -> dict[str, int]:
    """Bytes of what each hop of the arena carries for ``n_bodies`` (the floors send the same sizes)."""
    from arena_common.pipeline.ingest import encode_pose

    frame = natnet.encode_frame(_example_frame(n_bodies), natnet.Version.parse(NATNET_VERSION))
    body = _example_frame(1).rigid_bodies[0]
    mocap = encode_pose(time.time_ns(), 123456, body, True, "d1", 5_380_000, 1234.5, "echo", time.time_ns())
    now = time.time_ns()
    pose = wire.Pose(
        t=now,
        p=(1.234567, -0.7654321, -1.1234567),
        q=(0.92387953, 0.0, 0.0, 0.38268343),
        ok=True,
        fn=123456,
        v=(0.1234567, 0.2345678, -0.0123456),
        w=(0.01, -0.02, 0.3),
        vok=True,
        tp=now,
    ).encode()
    frames = wire.MocapFrame(
        t=now,
        fn=123456,
        b=tuple(
            wire.MocapBody(f"d{i + 1}", i + 1, body.pos, (1.0, 0.0, 0.0, 0.0), True) for i in range(n_bodies)
        ),
        lat=5_380_000,
        mts=1234.5,
        tsrc="echo",
        tp=now,
    ).encode()
    return {
        "natnet": len(frame),
        "mocap": len(mocap),
        "frames": len(frames),
        "pose": len(pose),
        "odometry": _odometry_size(),
    }


def _odometry_size() -> int:
    from arena_common.mavlink.link import mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=245, srcComponent=mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER)
    args = px4.odometry_args(
        time.time_ns() // 1000, (1.2, -0.7, -1.1), (0.92, 0.0, 0.0, 0.39), (0.1, 0.2, 0.0)
    )
    return len(mav.odometry_encode(**args).pack(mav))


# -- MAVLink parsing (only what matching needs) --------------------------------------------------------------


def mavlink_frame(data: bytes) -> tuple[int, bytes] | None:
    """``(message id, payload)`` of the first MAVLink frame of a datagram (v2 payload zero-padded)."""
    if len(data) >= 12 and data[0] == 0xFD:
        n = data[1]
        msgid = data[7] | (data[8] << 8) | (data[9] << 16)
        return msgid, data[10 : 10 + n] + bytes(max(0, 255 - n))
    if len(data) >= 8 and data[0] == 0xFE:
        n = data[1]
        return data[5], data[6 : 6 + n]
    return None


def odometry_of(data: bytes) -> tuple[int, tuple[float, float, float]] | None:
    """``(time_usec, (x, y, z))`` of an ODOMETRY datagram, ``None`` for any other message."""
    parsed = mavlink_frame(data)
    if parsed is None or parsed[0] != ODOMETRY_ID:
        return None
    usec, x, y, z = _ODO_HEAD.unpack_from(parsed[1])
    return usec, (x, y, z)


def _f32(p: Sequence[float]) -> tuple[float, float, float]:
    x, y, z = _F32.unpack(_F32.pack(*p))
    return x, y, z


# -- analysis ------------------------------------------------------------------------------------------------


@dataclass
class _FrameInfo:
    fn: int
    stamp: int
    mid_ns: int
    positions: dict[int, tuple[float, float, float] | None]  # vehicle index → NED float32 (None: untracked)


def decode_frames(
    records: Sequence[tuple[int, bytes]],
    body_to_vehicle: Mapping[int, int],
    transform: FrameTransform,
    version: natnet.Version,
    tick_frequency: int,
) -> list[_FrameInfo]:
    """The harness's copy of every NatNet frame: number, stamp, mid-exposure and each vehicle's position."""
    out: list[_FrameInfo] = []
    for stamp, data in records:
        try:
            msg_id, payload = natnet.split_packet(data)
            if msg_id != natnet.MessageId.FRAMEOFDATA:
                continue
            frame = natnet.decode_frame(payload, version)
        except natnet.NatNetError:
            continue
        mid = frame.cam_mid_exposure
        mid_ns = mid * 1_000_000_000 // tick_frequency if mid is not None else 0
        positions: dict[int, tuple[float, float, float] | None] = {}
        for body in frame.rigid_bodies:
            v = body_to_vehicle.get(body.id)
            if v is None:
                continue
            positions[v] = _f32(transform.position(body.pos)) if body.tracking_valid else None
        out.append(_FrameInfo(frame.frame_number, stamp, mid_ns, positions))
    return out


def designed_outputs(frames: Sequence[_FrameInfo], vehicle: int, first: int, vision_rate: float) -> set[int]:
    """Indices of the frames the downsampler's decimator passes for ``vehicle`` when it starts at ``first``.

    The downsampler's own :class:`~arena_common.geometry.filters.TimeDecimator` fed with the frames' mid-exposure
    times (its input times up to a constant clock offset), so what it skips is a drop by design.
    """
    from arena_common.geometry.filters import TimeDecimator

    dec = TimeDecimator(vision_rate)
    out: set[int] = set()
    for k in range(first, len(frames)):
        if frames[k].positions.get(vehicle) is not None and dec.offer(frames[k].mid_ns):
            out.add(k)
    return out


def analyze_arena(
    frames: Sequence[_FrameInfo],
    outputs: Mapping[int, Sequence[tuple[int, bytes]]],
    t0: int,
    t1: int,
    rate: float,
    vision_rate: float = VISION_RATE,
) -> dict[str, Any]:
    """Latencies (ns) and losses of the frames stamped within ``[t0, t1]``.

    ``expected`` counts the frames the decimator passes by design (every tracked frame when the vision
    rate is above the mocap rate); ``lost`` is how many fewer poses arrived (a pose the decimator took in
    place of a lost neighbour counts as delivered), ``designed_drops`` the frames it skips by design.
    """
    latencies: list[int] = []
    residuals: list[int] = []
    per_vehicle: dict[int, dict[str, int]] = {}
    first_vehicle: list[tuple[int, int, int]] = []  # (frame number, frame stamp, ODOMETRY stamp) of vehicle 0
    in_window_idx = [k for k, f in enumerate(frames) if t0 <= f.stamp <= t1]
    for v, records in outputs.items():
        m = _match_vehicle(frames, v, records, t0, t1, 1e9 / rate)
        tracked = {k for k in in_window_idx if frames[k].positions.get(v) is not None}
        # The decimator starts on the first pose it gets (the first one sent); when nothing came out
        # before the window (a starved pipeline), assume it started with the window.
        anchor = min(tracked, default=None)
        if m.first_out is not None and (anchor is None or m.first_out < anchor):
            anchor = m.first_out
        wanted = designed_outputs(frames, v, anchor, vision_rate) & tracked if anchor is not None else set()
        per_vehicle[v] = {
            "expected": len(wanted),
            "delivered": len(m.matched),
            "designed_drops": len(tracked) - len(wanted),
            "substituted": len(m.matched - wanted),
            "mismatched": m.mismatched,
            "unmatched_time": m.unmatched_time,
            "duplicates": m.duplicates,
        }
        latencies += m.latencies
        residuals += m.residuals
        if v == 0:
            first_vehicle += m.stamps
    total = {k: sum(c[k] for c in per_vehicle.values()) for k in _COUNTS}
    in_window = [frames[k] for k in in_window_idx]
    gaps = 0
    for a, b in itertools.pairwise(in_window):
        if b.fn > a.fn + 1:
            gaps += b.fn - a.fn - 1
    res_abs = sorted(abs(r) for r in residuals)
    return {
        "latencies": latencies,
        "expected": total["expected"],
        "delivered": total["delivered"],
        "lost": max(0, total["expected"] - total["delivered"]),
        "designed_drops": total["designed_drops"],
        "substituted": total["substituted"],
        "mismatched": total["mismatched"],
        "duplicates": total["duplicates"],
        "unmatched_time": total["unmatched_time"],
        "frames": len(in_window),
        "frame_gaps": gaps,
        "clock_residual_us_p99": (res_abs[int(0.99 * (len(res_abs) - 1))] / 1e3) if res_abs else math.nan,
        "per_vehicle": per_vehicle,
        "first_vehicle": first_vehicle,
    }


_COUNTS = (
    "expected",
    "delivered",
    "designed_drops",
    "substituted",
    "mismatched",
    "duplicates",
    "unmatched_time",
)


@dataclass
class _VehicleMatch:
    """One vehicle's ODOMETRY matched to the frames: what was delivered in the window, and what was not."""

    matched: set[int] = field(default_factory=set)  # indices of the window's frames delivered
    first_out: int | None = None  # index of the earliest frame delivered, in the window or not
    latencies: list[int] = field(default_factory=list)  # ns, frame arrival → ODOMETRY arrival
    residuals: list[int] = field(default_factory=list)  # ns, time_usec off the clock offset
    stamps: list[tuple[int, int, int]] = field(default_factory=list)  # (frame number, frame stamp, its stamp)
    mismatched: int = 0  # a position no frame had
    duplicates: int = 0  # a frame delivered twice
    unmatched_time: int = 0  # the position of a frame, but not its time


def _match_vehicle(
    frames: Sequence[_FrameInfo],
    v: int,
    records: Sequence[tuple[int, bytes]],
    t0: int,
    t1: int,
    period: float,
) -> _VehicleMatch:
    """Each ODOMETRY of vehicle ``v`` assigned the frame with its position nearest in time (module doc)."""
    index: dict[tuple[float, float, float], list[int]] = collections.defaultdict(list)
    for k, f in enumerate(frames):
        p = f.positions.get(v)
        if p is not None:
            index[p].append(k)
    odos = [(stamp, od) for stamp, data in records if (od := odometry_of(data)) is not None]
    offset = _clock_offset(frames, index, odos)
    m = _VehicleMatch()
    for stamp, (usec, p) in odos:
        cands = index.get(p)
        if not cands:
            m.mismatched += 1
            continue
        best = min(cands, key=lambda k: abs(usec * 1000 - frames[k].mid_ns - offset))
        resid = usec * 1000 - frames[best].mid_ns - offset
        if abs(resid) > period / 3:
            m.unmatched_time += 1
            continue
        if m.first_out is None or best < m.first_out:
            m.first_out = best
        f = frames[best]
        if not t0 <= f.stamp <= t1:
            continue
        if best in m.matched:
            m.duplicates += 1
            continue
        m.matched.add(best)
        m.residuals.append(resid)
        m.latencies.append(stamp - f.stamp)
        m.stamps.append((f.fn, f.stamp, stamp))
    return m


def _clock_offset(
    frames: Sequence[_FrameInfo],
    index: Mapping[tuple[float, float, float], list[int]],
    odos: Sequence[tuple[int, tuple[int, tuple[float, float, float]]]],
) -> int:
    """The clock offset (ns): the mode of time_usec·1000 − mid over every candidate frame of every output."""
    diffs: list[int] = []
    for _, (usec, p) in odos[:3000]:
        for k in index.get(p, ()):
            diffs.append(usec * 1000 - frames[k].mid_ns)
    if not diffs:
        return 0
    bins = collections.Counter(d // 20_000 for d in diffs)
    mode = bins.most_common(1)[0][0] * 20_000 + 10_000
    near = sorted(d for d in diffs if abs(d - mode) <= 100_000)
    return near[len(near) // 2]


def hop_breakdown(
    matches: Sequence[tuple[int, int, int]], hops: Mapping[str, Mapping[int, int]]
) -> dict[str, dict[str, float]]:
    """Per-stage latency of vehicle 0 (ms percentiles) from the publish stamps its payloads carry.

    Stages: ``ingest`` frame arrival → MocapPose stamped; ``transform`` → Pose stamped; ``downsampler`` →
    vision stamped; ``gateway`` → ODOMETRY arrival.  Each includes the hop into it and the previous
    stage's encoding and publication.  When the transform decimates, it stamps the vision pose before
    the full-rate one: ``transform`` then ends at the vision stamp and there is no ``downsampler`` stage.
    """
    stages: dict[str, list[int]] = {"ingest": [], "transform": [], "downsampler": [], "gateway": []}
    mocap, pose, vision = hops.get("mocap", {}), hops.get("pose", {}), hops.get("vision", {})
    for fn, t_frame, t_odo in matches:
        a, b, c = mocap.get(fn), pose.get(fn), vision.get(fn)
        if a is None or b is None or c is None:
            continue
        stages["ingest"].append(a - t_frame)
        if c <= b:  # the transform decimated: vision was stamped first
            stages["transform"].append(c - a)
        else:
            stages["transform"].append(b - a)
            stages["downsampler"].append(c - b)
        stages["gateway"].append(t_odo - c)
    return {name: latency_stats(v).as_dict() for name, v in stages.items() if v}


class HopWatcher:
    """Subscribes to the first vehicle's mocap, pose and vision keys and keeps each frame's publish stamp."""

    def __init__(self, bus: Bus, vehicle: str) -> None:
        self.stamps: dict[str, dict[int, int]] = {"mocap": {}, "pose": {}, "vision": {}}
        self._subs = []
        for kind, key in (
            ("mocap", keys.mocap(vehicle)),
            ("pose", keys.pose(vehicle)),
            ("vision", keys.vision(vehicle)),
        ):
            table = self.stamps[kind]

            def on_sample(sample: Any, table: dict[int, int] = table) -> None:
                try:
                    m = msgpack.unpackb(sample.payload.to_bytes())
                    table[int(m["fn"])] = int(m["tp"])
                except Exception:
                    pass

            self._subs.append(bus.session.declare_subscriber(key, on_sample))

    def clear(self) -> None:
        for table in self.stamps.values():
            table.clear()

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:
                pass


def analyze_floor(
    frames: Sequence[tuple[int, bytes]],
    outputs: Mapping[int, Sequence[tuple[int, bytes]]],
    t0: int,
    t1: int,
    *,
    keep: float | None = None,
) -> dict[str, Any]:
    """Latencies (ns) and losses of a floor chain: messages carry their frame number.

    ``keep``: the share of frames a decimating relay passed (:func:`bench.floor.kept`); only those are
    expected."""
    from bench.floor import HEADER, kept

    stamps: dict[int, int] = {}
    for stamp, data in frames:
        if len(data) >= 8:
            stamps.setdefault(struct.unpack_from("<Q", data)[0], stamp)
    window = {fn for fn, s in stamps.items() if t0 <= s <= t1}
    if keep is not None:
        window = {fn for fn in window if kept(fn, keep)}
    latencies: list[int] = []
    delivered = duplicates = 0
    per_vehicle: dict[int, dict[str, int]] = {}
    for v, records in outputs.items():
        seen: set[int] = set()
        for stamp, data in records:
            if len(data) < HEADER.size:
                continue
            fn = HEADER.unpack_from(data)[0]
            if fn not in window:
                continue
            if fn in seen:
                duplicates += 1
                continue
            seen.add(fn)
            latencies.append(stamp - stamps[fn])
        delivered += len(seen)
        per_vehicle[v] = {"expected": len(window), "delivered": len(seen)}
    expected = len(window) * len(outputs)
    return {
        "latencies": latencies,
        "expected": expected,
        "delivered": delivered,
        "lost": expected - delivered,
        "duplicates": duplicates,
        "frames": len(window),
        "per_vehicle": per_vehicle,
    }
