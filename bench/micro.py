"""Per-stage micro-benchmarks of ``make bench``: what each step of the pipeline costs in this process.

Each figure is the best of three timed loops (microseconds per call unless said otherwise), so a busy
machine inflates it less than a mean would.  ``scale`` shortens every loop (tests use a tiny one).
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from arena_common.core import keys, wire
from arena_common.mavlink import fastframe, px4
from arena_common.mocap import natnet
from tools.vectors import vectors

__all__ = ["per_call_us", "run_micro", "wire_examples"]


def per_call_us(fn: Callable[[], Any], iterations: int, repeats: int = 3) -> float:
    """Best of ``repeats`` loops of ``iterations`` calls of ``fn``, in µs per call."""
    iterations = max(1, iterations)
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter_ns()
        for _ in range(iterations):
            fn()
        best = min(best, (time.perf_counter_ns() - start) / iterations / 1000.0)
    return best


def wire_examples() -> dict[str, wire.Payload]:
    """One realistic value of every payload type: the first golden vector of each (tools/vectors.py)."""
    out: dict[str, wire.Payload] = {}
    for vec in vectors():
        out.setdefault(vec.type_name, vec.payload)
    return out


#: The key each example travels on.
_KEYS = {vec.type_name: vec.key for vec in reversed(vectors())}


def natnet_bench_frame(n_bodies: int) -> natnet.Frame:
    """A realistic NatNet 3.0 frame: per body a 4-marker set and 4 labeled markers, plus the "all" set."""
    bodies: list[natnet.RigidBody] = []
    sets: list[natnet.MarkerSet] = []
    labeled: list[natnet.LabeledMarker] = []
    all_markers: list[natnet.Vec3] = []
    for i in range(n_bodies):
        markers = tuple((0.1 * i + 0.01 * k, 1.0, -0.5 + 0.02 * k) for k in range(4))
        all_markers.extend(markers)
        sets.append(natnet.MarkerSet(f"Body{i + 1}", markers))
        labeled.extend(
            natnet.LabeledMarker(((i + 1) << 16) | (k + 1), m, 0.014, 0, 0.0001)
            for k, m in enumerate(markers)
        )
        bodies.append(natnet.RigidBody(i + 1, (0.1 * i, 1.0, -0.5), (0.0, 0.0, 0.0, 1.0), 0.0005, True, 1))
    sets.append(natnet.MarkerSet("all", tuple(all_markers)))
    return natnet.Frame(
        frame_number=1,
        rigid_bodies=tuple(bodies),
        timestamp=12.5,
        cam_mid_exposure=1_000_000,
        data_received=1_015_000,
        transmit=1_018_000,
        marker_sets=tuple(sets),
        labeled_markers=tuple(labeled),
    )


def natnet_decode_us(n_bodies: int, iterations: int = 2000, version: natnet.Version | None = None) -> float:
    """Microseconds per NatNet frame decode (fast path) of a frame with ``n_bodies`` tracked bodies (best of
    three runs of ``iterations`` decodes)."""
    version = version if version is not None else natnet.Version(3)
    _, payload = natnet.split_packet(natnet.encode_frame(natnet_bench_frame(n_bodies), version))
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter_ns()
        for _ in range(iterations):
            natnet.decode_frame(payload, version)
        best = min(best, (time.perf_counter_ns() - start) / iterations / 1000.0)
    return best


def _natnet(scale: float) -> dict[str, float]:
    return {f"{n} bodies": natnet_decode_us(n, max(10, int(2000 * scale))) for n in (1, 10, 50)}


def _transform(scale: float) -> dict[str, float]:
    import numpy as np

    from arena_common.geometry.frames import Calibration, FrameTransform, UpAxis

    tf = FrameTransform(UpAxis.Y_UP, Calibration.from_degrees(-25.0, (0.4, -0.3, 0.05)))
    p, q = (1.2, 0.9, -0.5), (0.92387953, 0.0, 0.38268343, 0.0)
    out = {"pose (1 body)": per_call_us(lambda: tf.pose(p, q), int(50_000 * scale))}
    for n in (10, 50):
        ps = np.tile(np.array(p), (n, 1))
        qs = np.tile(np.array(q), (n, 1))
        out[f"poses, batch of {n} (per pose)"] = per_call_us(partial(tf.poses, ps, qs), int(5000 * scale)) / n
    return out


# µs per (encode, decode) of the wire before it moved to msgspec Structs (the hand-written dataclass codec
# of commit ce0ffc3), measured by this same loop on the 2-core development machine just before the change;
# ``make bench`` lists them under today's figures for comparison (same bytes).
WIRE_BEFORE_MSGSPEC_US: dict[str, tuple[float, float]] = {
    "MocapPose": (2.24, 6.87),
    "Pose": (2.06, 6.02),
    "State": (3.37, 10.58),
    "Telemetry": (1.21, 3.86),
    "Event": (1.19, 3.89),
    "Command": (1.34, 3.96),
    "CommandResult": (1.13, 3.59),
    "Setpoint": (1.33, 3.45),
    "Estop": (1.03, 2.46),
    "Stats": (2.25, 9.02),
}


def _wire(scale: float) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    n = int(20_000 * scale)
    for name, value in wire_examples().items():
        raw = value.encode()
        cls = type(value)
        key = _KEYS[name]
        out[name] = {
            "bytes": float(len(raw)),
            "encode": per_call_us(value.encode, n),
            "decode": per_call_us(partial(cls.decode, raw, key), n),
        }
        if name in WIRE_BEFORE_MSGSPEC_US:
            encode, decode = WIRE_BEFORE_MSGSPEC_US[name]
            out[f"{name} before msgspec (recorded)"] = {
                "bytes": float(len(raw)),
                "encode": encode,
                "decode": decode,
            }
    return out


def _mavlink(scale: float) -> dict[str, float]:
    from arena_common.mavlink.link import mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=245, srcComponent=mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER)
    pose = wire_examples()["Pose"]
    assert isinstance(pose, wire.Pose)
    usec = pose.t // 1000

    def encode() -> bytes:
        args = px4.odometry_args(usec, pose.p, pose.q, pose.v, angular_velocity_frd=pose.w)
        return bytes(mav.odometry_encode(**args).pack(mav))

    raw = encode()
    parser = mavlink2.MAVLink(None)
    n = int(20_000 * scale)
    args = px4.odometry_args(usec, pose.p, pose.q, pose.v, angular_velocity_frd=pose.w)
    return {
        "ODOMETRY args + encode + pack": per_call_us(encode, n),
        "ODOMETRY encode + pack (pymavlink only)": per_call_us(
            lambda: mav.odometry_encode(**args).pack(mav), n
        ),
        "ODOMETRY args + frame (the gateway's, fastframe)": per_call_us(
            lambda: fastframe.ODOMETRY.frame(
                fastframe.odometry_payload(
                    px4.odometry_args(usec, pose.p, pose.q, pose.v, angular_velocity_frd=pose.w)
                ),
                0,
                mav.srcSystem,
                mav.srcComponent,
            ),
            n,
        ),
        "ODOMETRY parse (pymavlink)": per_call_us(lambda: parser.parse_buffer(raw), n),
        "bytes": float(len(raw)),
    }


def _stages(scale: float) -> dict[str, float]:
    """The Python work each service does per pose, outside Zenoh (decode, process, encode)."""
    from arena_common.geometry.frames import FrameTransform
    from arena_common.mavlink.link import mavlink2
    from arena_common.pipeline.ingest import body_numbers, encode_pose
    from arena_common.pipeline.transform import PoseConverter
    from arena_common.pipeline.vision import VisionFilter

    n = int(10_000 * scale)
    now = time.time_ns()
    body = natnet.RigidBody(1, (1.2, 0.9, -0.5), (0.0, 0.38268343, 0.0, 0.92387953), 0.0002, True, 1)
    p, q, err = body_numbers(body, True)
    mocap = wire.MocapBody("d1", 1, p, q, True, "d1", err)
    frame_raw = wire.MocapFrame(now, 1, (mocap,), 5_380_000, 12.5, "echo", now).encode()
    enc_f = wire.MocapFrame.encoding()
    conv = PoseConverter(FrameTransform())
    state = {"t": now}

    def transform() -> bytes:
        state["t"] += 5_555_555
        frame = wire.decode_any(keys.FRAMES, frame_raw, enc_f)
        assert isinstance(frame, wire.MocapFrame)
        return conv.convert(frame.replace(t=state["t"]), frame.b[0]).encode()

    def ingest() -> bytes:
        bodies = []
        for i in range(10):
            p, q, err = body_numbers(body, True)
            bodies.append(wire.MocapBody(f"d{i + 1}", i + 1, p, q, True, "d1", err))
        return wire.MocapFrame(now, 1, tuple(bodies), 5_380_000, 12.5, "echo", now).encode()

    pose_raw = transform()
    enc_p = wire.Pose.encoding()
    filt = VisionFilter(400.0)

    def downsample() -> None:
        state["t"] += 5_555_555
        pose = wire.decode_any("arena/d1/pose", pose_raw, enc_p)
        assert isinstance(pose, wire.Pose)
        d = filt.process(pose.replace(t=state["t"]))
        if d.vision is not None:
            d.vision.encode()

    mav = mavlink2.MAVLink(None, srcSystem=245, srcComponent=mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER)

    def gateway() -> bytes:
        pose = wire.decode_any("arena/d1/vision", pose_raw, enc_p)
        assert isinstance(pose, wire.Pose)
        args = px4.odometry_args(pose.t // 1000, pose.p, pose.q, pose.v, angular_velocity_frd=pose.w)
        return fastframe.ODOMETRY.frame(
            fastframe.odometry_payload(args), mav.seq, mav.srcSystem, mav.srcComponent
        )

    return {
        "ingest: a body of a 10-body MocapFrame, built and encoded": per_call_us(ingest, n // 10) / 10,
        "ingest: encode MocapPose (a watched vehicle's mocap key)": per_call_us(
            lambda: encode_pose(now, 1, body, True, "d1", 5_380_000, 12.5, "echo", now), n
        ),
        "transform: decode a 1-body frame + convert + encode": per_call_us(transform, n),
        "downsampler: decode + filter + encode": per_call_us(downsample, n),
        "gateway: decode + ODOMETRY encode": per_call_us(gateway, n),
    }


def _recorder(scale: float) -> dict[str, float]:
    from arena_common.recording.mcap import RecordingWriter, Sample

    pose = wire_examples()["Pose"]
    assert isinstance(pose, wire.Pose)
    raw = pose.encode()
    enc = wire.Pose.encoding()
    n = max(200, int(20_000 * scale))
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="arena-bench-") as tmp:
        for encoding in ("json", "msgpack"):
            path = Path(tmp) / f"bench-{encoding}.mcap"
            samples = [Sample(f"arena/d{i % 10 + 1}/pose", raw, enc, pose.t + i) for i in range(n)]
            start = time.perf_counter_ns()
            writer = RecordingWriter(path, encoding=encoding)
            for s in samples:
                writer.record(s)
            writer.close()
            dt = (time.perf_counter_ns() - start) / 1e9
            out[f"{encoding} (messages/s)"] = n / dt
            out[f"{encoding} (MB/s of file)"] = path.stat().st_size / dt / 1e6
    return out


def _fleet(scale: float) -> dict[str, dict[str, float]]:
    """What keeping vehicles apart costs one gateway: a fleet message of N vehicles decoded, taken and
    judged (:class:`~arena_common.gateway.separation.Separation`), at the transform's 10 Hz."""
    from arena_common.gateway.separation import Separation
    from arena_common.pipeline.transform import FLEET_RATE

    out: dict[str, dict[str, float]] = {}
    for n in (10, 20, 50):
        fleet = wire.Fleet(
            t=1,
            b=tuple(
                wire.FleetVehicle(f"d{i + 1}", (1.4 * (i % 10), 1.4 * (i // 10), -1.0), (0.1, 0.0, 0.0))
                for i in range(n)
            ),
        )
        raw = fleet.encode()
        sep = Separation("d1", 0.6)

        def one(raw: bytes = raw, sep: Separation = sep) -> None:
            sep.update(wire.Fleet.decode(raw, keys.FLEET))
            sep.closing()

        us = per_call_us(one, int(2000 * scale))
        out[f"{n} vehicles"] = {"bytes": len(raw), "us": us, "cpu_pct": us * FLEET_RATE * 1e-4}
    return out


def run_micro(scale: float = 1.0) -> dict[str, Any]:
    """Every micro-benchmark; a dict of sections (µs per call unless the name says otherwise)."""
    return {
        "natnet_decode_us": _natnet(scale),
        "transform_us": _transform(scale),
        "stages_us": _stages(scale),
        "mavlink_us": _mavlink(scale),
        "wire_us": _wire(scale),
        "recorder": _recorder(scale),
        "fleet": _fleet(scale),
    }
