"""End-to-end runs of ``make bench``: the real vision pipeline, and its floors, as processes on loopback.

**Arena.** A private Zenoh router, the Motive emulator (``services.sim_mocap``), the ingest, the frame
transform, one downsampler and one gateway per vehicle, each a process with the config this module writes
(multicast NatNet on 127.0.0.1, no noise, vision rate 400 Hz so that the downsampler drops nothing by
design at 180 or 360 Hz, every gateway sending MAVLink to a UDP port of the harness).  The harness
publishes each vehicle's true pose (a circle, 60 Hz), joins the NatNet multicast group itself and reads
every vehicle's MAVLink socket, all with kernel receive stamps (:mod:`bench.harness`).

Matching an ODOMETRY to its frame: ODOMETRY carries no frame number, but its ``time_usec`` is the pose's
measurement time, the frame's camera mid-exposure mapped onto the local clock by the ingest, so
``time_usec·1000 − mid_exposure`` is one constant (the clock offset) for the right frame and differs by
whole frame periods for the others.  The constant is the mode of that difference over every frame whose
position equals the ODOMETRY's (float32, bit for bit); each ODOMETRY is then assigned the frame with that
position whose difference is nearest the constant.  A position no frame had is a *mismatch* (wrong data),
a frame with no ODOMETRY is *lost*.

**Floors.** The same topology with :mod:`bench.floor` processes that only move bytes (of the
arena payloads' sizes), over Zenoh with the arena's settings, or over UDP; messages carry their frame
number, so matching is exact.
"""

from __future__ import annotations

import collections
import itertools
import math
import os
import random
import struct
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from arena_common.bus.session import Bus, open_bus
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.config import load as load_config
from arena_common.geometry.frames import FrameTransform, quat_from_yaw
from arena_common.mocap import natnet
from bench.harness import (
    BenchError,
    Collector,
    ProcessSet,
    free_port,
    latency_stats,
    python_module,
    stamped_socket,
    wait_port,
    wait_until,
)

__all__ = [
    "CHAINS",
    "ODOMETRY_ID",
    "PointResult",
    "RunSettings",
    "analyze_arena",
    "analyze_floor",
    "mavlink_frame",
    "payload_sizes",
    "run_arena",
    "run_floor",
    "write_config",
]

ODOMETRY_ID = 331
VISION_RATE = 400.0  # Hz: above the mocap rate, so the decimator passes every pose
# The arena's chains, by where the vision is decimated ([pipeline] decimate).
CHAINS = {"downsampler": "arena", "transform": "arena-td"}
TRUTH_RATE = 60.0  # Hz per vehicle
NATNET_VERSION = "3.1"
HOST = "bench"
_ODO_HEAD = struct.Struct("<Qfff")
_F32 = struct.Struct("<fff")
FLOOR_PREFIX = "bench/floor"


@dataclass(frozen=True)
class RunSettings:
    """How long each load point runs, and where logs go."""

    duration: float = 3.0  # s measured
    warmup: float = 1.0  # s of flow before the measurement starts
    drain: float = 0.3  # s after the window for late messages to arrive
    start_timeout: float = 90.0  # s for the processes to come up and data to flow
    idle: float = 1.0  # s of idle CPU measured before the stream starts (0: skip)
    logs: Path = Path("bench-results/logs")
    repo: Path = Path(".")
    profile: Callable[[ProcessSet, float], dict[str, Any]] | None = None  # run during the window
    hops: bool = False  # also subscribe to the first vehicle's mocap/pose/vision for a per-stage breakdown


@dataclass
class PointResult:
    """One load point of one chain (arena, floor-zenoh, floor-udp)."""

    chain: str
    vehicles: int
    rate: float
    latency: dict[str, float]
    expected: int
    delivered: int
    lost: int
    designed_drops: int = 0
    mismatched: int = 0
    duplicates: int = 0
    per_service: dict[str, dict[str, Any]] = field(default_factory=dict)
    idle: dict[str, dict[str, Any]] = field(default_factory=dict)
    counters: dict[str, dict[str, int]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    profile: dict[str, Any] = field(default_factory=dict)
    hops: dict[str, dict[str, float]] = field(default_factory=dict)
    load: float = math.nan  # the machine's 1-minute load average at the end of the measurement

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


# -- configuration -------------------------------------------------------------------------------------------


def _group() -> str:
    return f"239.255.{random.randint(1, 254)}.{random.randint(1, 254)}"


def write_config(
    directory: Path,
    n_vehicles: int,
    rate: float,
    harness_ports: Sequence[int],
    *,
    decimate: str = "downsampler",
) -> Path:
    """An arena config with private ports: multicast NatNet, no noise, gateways sending to the harness.

    ``decimate`` is the config's ``[pipeline] decimate``.
    """
    directory.mkdir(parents=True, exist_ok=True)
    router = free_port(socket_kind_tcp())
    lines = [
        "[arena]",
        'name = "bench"',
        "[mocap]",
        'server = "127.0.0.1"',
        'interface = "127.0.0.1"',
        "multicast = true",
        f'group = "{_group()}"',
        f"command_port = {free_port()}",
        f"data_port = {free_port()}",
        'up_axis = "y"',
        "[zenoh]",
        'mode = "peer"',
        f'connect = ["tcp/127.0.0.1:{router}"]',
        f'router_listen = ["tcp/127.0.0.1:{router}"]',
        f"[hosts.{HOST}]",
        'services = ["router", "sim", "mocap", "transform"]',
        "vehicles = [" + ", ".join(f'"d{i + 1}"' for i in range(n_vehicles)) + "]",
        "[sim]",
        f"mocap_rate = {float(rate)}",
        f'natnet_version = "{NATNET_VERSION}"',
        "noise_m = 0.0",
        "dropout = 0.0",
        "[pipeline]",
        f'decimate = "{decimate}"',
    ]
    for i in range(n_vehicles):
        lines += [
            f"[vehicles.d{i + 1}]",
            f'rigid_body = "d{i + 1}"',
            f'mavlink = "udpout:127.0.0.1:{harness_ports[i]}"',
            f"system_id = {i + 1}",
            f"vision_rate = {VISION_RATE}",
        ]
    path = directory / f"bench-{n_vehicles}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def socket_kind_tcp() -> int:
    import socket

    return socket.SOCK_STREAM


def router_port(cfg: ArenaConfig) -> int:
    return int(cfg.zenoh.router_listen[0].rsplit(":", 1)[1])


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
    from services.mocap_ingest import encode_pose

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
    return {"natnet": len(frame), "mocap": len(mocap), "pose": len(pose), "odometry": _odometry_size()}


def _odometry_size() -> int:
    from arena_common.mavlink import px4
    from arena_common.mavlink.link import mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=245, srcComponent=191)
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
    period = 1e9 / rate
    latencies: list[int] = []
    expected = delivered = mismatched = duplicates = unmatched_time = designed = substituted = 0
    residuals: list[int] = []
    per_vehicle: dict[int, dict[str, int]] = {}
    first_vehicle: list[tuple[int, int, int]] = []  # (frame number, frame stamp, ODOMETRY stamp) of vehicle 0
    in_window_idx = [k for k, f in enumerate(frames) if t0 <= f.stamp <= t1]
    for v, records in outputs.items():
        index: dict[tuple[float, float, float], list[int]] = collections.defaultdict(list)
        for k, f in enumerate(frames):
            p = f.positions.get(v)
            if p is not None:
                index[p].append(k)
        odos = [(stamp, od) for stamp, data in records if (od := odometry_of(data)) is not None]
        # The clock offset: the mode of time_usec·1000 − mid over every candidate frame of every output.
        diffs: list[int] = []
        for _, (usec, p) in odos[:3000]:
            for k in index.get(p, ()):
                diffs.append(usec * 1000 - frames[k].mid_ns)
        if not diffs:
            offset = 0
        else:
            bins = collections.Counter(d // 20_000 for d in diffs)
            mode = bins.most_common(1)[0][0] * 20_000 + 10_000
            near = sorted(d for d in diffs if abs(d - mode) <= 100_000)
            offset = near[len(near) // 2]
        matched: set[int] = set()
        first_out: int | None = None
        v_lat: list[int] = []
        v_mis = v_dup = v_time = 0
        for stamp, (usec, p) in odos:
            cands = index.get(p)
            if not cands:
                v_mis += 1
                continue
            best = min(cands, key=lambda k: abs(usec * 1000 - frames[k].mid_ns - offset))
            resid = usec * 1000 - frames[best].mid_ns - offset
            if abs(resid) > period / 3:
                v_time += 1
                continue
            if first_out is None or best < first_out:
                first_out = best
            f = frames[best]
            if not t0 <= f.stamp <= t1:
                continue
            if best in matched:
                v_dup += 1
                continue
            matched.add(best)
            residuals.append(resid)
            v_lat.append(stamp - f.stamp)
            if v == 0:
                first_vehicle.append((f.fn, f.stamp, stamp))
        tracked = {k for k in in_window_idx if frames[k].positions.get(v) is not None}
        # The decimator starts on the first pose it gets (the first one sent); when nothing came out
        # before the window (a starved pipeline), assume it started with the window.
        anchor = min(tracked, default=None)
        if first_out is not None and (anchor is None or first_out < anchor):
            anchor = first_out
        wanted = designed_outputs(frames, v, anchor, vision_rate) & tracked if anchor is not None else set()
        v_expected = len(wanted)
        per_vehicle[v] = {
            "expected": v_expected,
            "delivered": len(matched),
            "designed_drops": len(tracked) - v_expected,
            "substituted": len(matched - wanted),
            "mismatched": v_mis,
            "unmatched_time": v_time,
            "duplicates": v_dup,
        }
        latencies += v_lat
        expected += v_expected
        delivered += len(matched)
        designed += len(tracked) - v_expected
        substituted += len(matched - wanted)
        mismatched += v_mis
        duplicates += v_dup
        unmatched_time += v_time
    in_window = [frames[k] for k in in_window_idx]
    gaps = 0
    for a, b in itertools.pairwise(in_window):
        if b.fn > a.fn + 1:
            gaps += b.fn - a.fn - 1
    res_abs = sorted(abs(r) for r in residuals)
    return {
        "latencies": latencies,
        "expected": expected,
        "delivered": delivered,
        "lost": max(0, expected - delivered),
        "designed_drops": designed,
        "substituted": substituted,
        "mismatched": mismatched,
        "duplicates": duplicates,
        "unmatched_time": unmatched_time,
        "frames": len(in_window),
        "frame_gaps": gaps,
        "clock_residual_us_p99": (res_abs[int(0.99 * (len(res_abs) - 1))] / 1e3) if res_abs else math.nan,
        "per_vehicle": per_vehicle,
        "first_vehicle": first_vehicle,
    }


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
) -> dict[str, Any]:
    """Latencies (ns) and losses of a floor chain: messages carry their frame number."""
    from bench.floor import HEADER

    stamps: dict[int, int] = {}
    for stamp, data in frames:
        if len(data) >= 8:
            stamps.setdefault(struct.unpack_from("<Q", data)[0], stamp)
    window = {fn for fn, s in stamps.items() if t0 <= s <= t1}
    latencies: list[int] = []
    delivered = duplicates = 0
    for records in outputs.values():
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
    expected = len(window) * len(outputs)
    return {
        "latencies": latencies,
        "expected": expected,
        "delivered": delivered,
        "lost": expected - delivered,
        "duplicates": duplicates,
        "frames": len(window),
    }


# -- the harness's Zenoh side --------------------------------------------------------------------------------


class TruthFeeder:
    """Publishes every vehicle's true pose (a small circle each, all different) at ``rate`` Hz."""

    def __init__(self, bus: Bus, vehicles: Sequence[str], rate: float = TRUTH_RATE) -> None:
        self.pubs = [bus.stream_publisher(keys.truth(v), wire.Pose) for v in vehicles]
        self.rate = rate
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-truth", daemon=True)
        self.sent = 0

    @staticmethod
    def position(i: int, t: float) -> tuple[float, float, float]:
        """Vehicle ``i``'s true NED position at ``t`` s: a 0.2 m circle at 0.5 Hz around its grid cell."""
        col, row = i % 5, i // 5
        cn, ce = -2.4 + 1.2 * col, -1.2 + 0.8 * (row % 4)
        a = 2 * math.pi * 0.5 * t + 0.3 * i
        return cn + 0.2 * math.cos(a), ce + 0.2 * math.sin(a), -1.0 - 0.05 * math.sin(a)

    def _run(self) -> None:
        period = 1.0 / self.rate
        t_start = time.monotonic()
        k = 0
        while not self._stop.is_set():
            due = t_start + k * period
            left = due - time.monotonic()
            if left > 0 and self._stop.wait(left):
                break
            k += 1
            now = time.time_ns()
            t = now * 1e-9
            for i, pub in enumerate(self.pubs):
                q = quat_from_yaw(0.5 * math.sin(0.2 * t + i))
                pub.put(wire.Pose(t=now, p=self.position(i, t), q=q, ok=True, tp=now))
            self.sent += 1

    def start(self) -> TruthFeeder:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


class StatsWatcher:
    """Keeps the latest :class:`~arena_common.core.wire.Stats` of every service."""

    def __init__(self, bus: Bus) -> None:
        self.latest: dict[str, wire.Stats] = {}
        self._lock = threading.Lock()
        self._sub = bus.subscribe("arena/sys/stats/**", capacity=4096, ring=False)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-stats", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            item = self._sub.get(0.2)
            if item is not None and isinstance(item.payload, wire.Stats):
                with self._lock:
                    self.latest[item.payload.service] = item.payload

    def counters(self) -> dict[str, dict[str, int]]:
        """Every service's counters and rejections (cumulative), flattened per service."""
        with self._lock:
            return {
                name: {
                    "pid": s.pid,
                    **{k: int(v) for k, v in s.counts.items()},
                    **{f"rejected:{k}": int(v) for k, v in s.rejected.items()},
                }
                for name, s in self.latest.items()
            }

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


def _result(
    chain: str, n: int, rate: float, found: Mapping[str, Any], usage: dict[str, Any], **extra: Any
) -> PointResult:
    """A load point from an analysis (``analyze_arena`` or ``analyze_floor``) and the processes' usage."""
    return PointResult(
        chain=chain,
        vehicles=n,
        rate=rate,
        latency=latency_stats(found["latencies"]).as_dict(),
        expected=found["expected"],
        delivered=found["delivered"],
        lost=found["lost"],
        duplicates=found["duplicates"],
        per_service=usage,
        load=os.getloadavg()[0],
        **extra,
    )


def _delta(
    before: Mapping[str, Mapping[str, int]], after: Mapping[str, Mapping[str, int]]
) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    for name, counts in after.items():
        prev = before.get(name, {})
        if prev.get("pid") != counts.get("pid"):
            prev = {}  # a new process of the same name: its counters start from zero
        d = {k: v - prev.get(k, 0) for k, v in counts.items() if k != "pid" and v != prev.get(k, 0)}
        if d:
            out[name] = d
    return out


# -- the arena run -------------------------------------------------------------------------------------------


def _vehicle_sockets(n: int) -> tuple[dict[Any, Any], list[int]]:
    socks: dict[Any, Any] = {}
    ports: list[int] = []
    for i in range(n):
        s = stamped_socket(0)
        socks[i] = s
        ports.append(int(s.getsockname()[1]))
    return socks, ports


def _wait_outputs(
    collector: Collector,
    n: int,
    timeout: float,
    what: str,
    procs: ProcessSet,
    accept: Callable[[bytes], bool] = lambda data: True,
) -> None:
    """Wait until every vehicle's socket received a datagram ``accept`` takes (ODOMETRY, not HEARTBEAT)."""
    checked = dict.fromkeys(range(n), 0)
    done: set[int] = set()

    def flowing() -> bool:
        for i in range(n):
            if i in done:
                continue
            records = collector.records[i]
            end = len(records)
            if any(accept(data) for _, data in records[checked[i] : end]):
                done.add(i)
            checked[i] = end
        return len(done) == n

    wait_until(flowing, timeout, what, procs)


def _wait_quiet(collector: Collector, tags: Sequence[Any], quiet: float = 0.3, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    last = sum(collector.count(t) for t in tags)
    calm_since = time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.05)
        now_count = sum(collector.count(t) for t in tags)
        if now_count != last:
            last, calm_since = now_count, time.monotonic()
        elif time.monotonic() - calm_since >= quiet:
            return


def run_arena(
    n: int,
    rates: Sequence[float],
    settings: RunSettings,
    *,
    realistic_vision: float | None = None,
    on_point: Callable[[PointResult], None] | None = None,
    decimate: str = "downsampler",
) -> list[PointResult]:
    """The real pipeline for ``n`` vehicles at each rate (processes started once, the emulator per rate).

    Every pose goes to the autopilot (vision rate :data:`VISION_RATE`).  With ``realistic_vision``, the
    decimators are then restarted at that vision rate and one more point runs at the first rate (chain
    ``arena-v<rate>``): the pipeline's CPU as deployed, its latencies and losses against what the
    decimator passes by design.  ``decimate`` is the config's ``[pipeline] decimate``: ``downsampler``
    (one process per vehicle; chain ``arena``) or ``transform`` (chain ``arena-td``).
    """
    from arena_common.sim.natnet_server import TICK_FREQUENCY
    from services.frame_transform import frame_transform
    from services.sim_mocap import rigid_bodies

    chain_name = CHAINS[decimate]
    workdir = settings.logs / f"{chain_name}-{n}"
    socks, ports = _vehicle_sockets(n)
    path = write_config(workdir, n, rates[0], ports, decimate=decimate)
    cfg = load_config(path)
    socks["frames"] = stamped_socket(cfg.mocap.data_port, group=cfg.mocap.group)
    names = list(cfg.vehicles)
    body_to_vehicle = {body_id: names.index(vehicle) for vehicle, _, body_id in rigid_bodies(cfg)}
    transform = frame_transform(cfg)
    version = natnet.Version.parse(NATNET_VERSION)
    common = ["-c", str(path), "--host", HOST, "--log-level", "WARNING"]
    results: list[PointResult] = []
    procs = ProcessSet(workdir, env=_env(settings.repo))
    collector = Collector(socks)
    bus: Bus | None = None
    feeder: TruthFeeder | None = None
    watcher: StatsWatcher | None = None
    hop_watcher: HopWatcher | None = None

    def decimators(vision_rate: float) -> None:
        if decimate == "transform":
            conf = path
            if vision_rate != VISION_RATE:  # the same arena (ports and all), another vision rate
                conf = path.with_name(f"{path.stem}-v{vision_rate:g}.toml")
                conf.write_text(
                    path.read_text().replace(f"vision_rate = {VISION_RATE}", f"vision_rate = {vision_rate}")
                )
            args = ["-c", str(conf), *common[2:]]
            procs.spawn(
                "transform", "transform", python_module("services.frame_transform", *args), settings.repo
            )
            return
        for v in names:
            procs.spawn(
                f"downsampler.{v}",
                "downsampler",
                python_module("services.downsampler", *common, "--vehicle", v, "--rate", str(vision_rate)),
                settings.repo,
            )

    def all_up() -> None:
        # router, transform, gateways, downsamplers
        expected_alive = 2 + (2 * n if decimate == "downsampler" else n)
        assert bus is not None
        the_bus = bus
        wait_until(
            lambda: len(the_bus.alive(f"arena/sys/alive/{HOST}/**", timeout=0.5)) >= expected_alive,
            settings.start_timeout,
            f"{expected_alive} services to come up",
            procs,
        )

    def measure(rate: float, chain: str, vision_rate: float, idle: dict[str, dict[str, Any]]) -> PointResult:
        assert watcher is not None
        before = watcher.counters()
        collector.clear()
        if hop_watcher is not None:
            hop_watcher.clear()
        # The emulator first, then the ingest (its handshake then succeeds at once): both per rate.
        emulator = procs.spawn(
            f"emulator.{int(rate)}",
            "emulator",
            python_module("services.sim_mocap", *common, "--rate", str(rate)),
            settings.repo,
        )
        wait_until(lambda: collector.count("frames") > 0, settings.start_timeout, "NatNet frames", procs)
        ingest = procs.spawn(
            "ingest", "ingest", python_module("services.mocap_ingest", *common), settings.repo
        )
        what = f"ODOMETRY from all {n} gateways at {rate:g} Hz"
        _wait_outputs(collector, n, settings.start_timeout, what, procs, lambda d: odometry_of(d) is not None)
        time.sleep(settings.warmup)
        procs.check_alive()
        t0 = time.time_ns()
        procs.mark()
        profile = settings.profile(procs, settings.duration) if settings.profile else {}
        remaining = settings.duration - (time.time_ns() - t0) / 1e9
        if remaining > 0:
            time.sleep(remaining)
        usage = procs.usage()
        t1 = time.time_ns()
        time.sleep(settings.drain)
        procs.check_alive()
        procs.stop(emulator)
        _wait_quiet(collector, list(range(n)))
        time.sleep(1.2)  # one more stats period, so the counters cover the whole run
        after = watcher.counters()
        procs.stop(ingest)
        records = collector.take()
        frames = decode_frames(records["frames"], body_to_vehicle, transform, version, TICK_FREQUENCY)
        found = analyze_arena(frames, {i: records[i] for i in range(n)}, t0, t1, rate, vision_rate)
        point = _result(
            chain,
            n,
            rate,
            found,
            usage,
            designed_drops=found["designed_drops"],
            mismatched=found["mismatched"],
            idle=idle,
            counters=_delta(before, after),
            profile=profile,
            hops=hop_breakdown(found["first_vehicle"], hop_watcher.stamps) if hop_watcher else {},
        )
        keys_ = ("frames", "frame_gaps", "substituted", "unmatched_time", "clock_residual_us_p99")
        point.notes.append(
            f"vision {vision_rate:g} Hz, "
            + ", ".join(
                f"{k}={found[k]:.3g}" if isinstance(found[k], float) else f"{k}={found[k]}" for k in keys_
            )
        )
        results.append(point)
        if on_point is not None:
            on_point(point)
        return point

    try:
        collector.start()
        procs.spawn(
            "router",
            "router",
            python_module("arena_common.cli", "router", "-c", str(path), "--host", HOST),
            settings.repo,
        )
        wait_port(router_port(cfg), 30, "the Zenoh router", procs)
        bus = open_bus(cfg.zenoh)
        feeder = TruthFeeder(bus, names).start()
        watcher = StatsWatcher(bus)
        if settings.hops:
            hop_watcher = HopWatcher(bus, names[0])
        decimators(VISION_RATE)
        if decimate == "downsampler":
            procs.spawn(
                "transform", "transform", python_module("services.frame_transform", *common), settings.repo
            )
        for v in names:
            procs.spawn(
                f"gateway.{v}",
                "gateway",
                python_module("services.mavlink_gateway", *common, "--vehicle", v),
                settings.repo,
            )
        all_up()
        idle: dict[str, dict[str, Any]] = {}
        if settings.idle > 0:
            time.sleep(0.5)
            procs.mark()
            time.sleep(settings.idle)
            idle = procs.usage()
        for rate in rates:
            measure(rate, chain_name, VISION_RATE, idle)
            idle = {}
        if realistic_vision is not None:
            role = "downsampler" if decimate == "downsampler" else "transform"
            for c in [c for c in procs.children if c.role == role]:
                procs.stop(c)
            decimators(realistic_vision)
            all_up()
            measure(rates[0], f"{chain_name}-v{realistic_vision:g}", realistic_vision, {})
    finally:
        if hop_watcher is not None:
            hop_watcher.close()
        if feeder is not None:
            feeder.close()
        if watcher is not None:
            watcher.close()
        procs.stop()
        if bus is not None:
            bus.close()
        collector.close()
    return results


def _env(repo: Path) -> dict[str, str]:
    import os

    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo.resolve()) + (
        os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else ""
    )
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


# -- the floors ----------------------------------------------------------------------------------------------


def run_floor(
    kind: str,
    n: int,
    rates: Sequence[float],
    settings: RunSettings,
    *,
    inline: bool = False,
    on_point: Callable[[PointResult], None] | None = None,
) -> list[PointResult]:
    """The floor chain over ``kind`` (``zenoh`` or ``udp``) for ``n`` vehicles at each rate."""
    if kind not in ("zenoh", "udp"):
        raise BenchError(f"floor transport must be zenoh or udp, not {kind!r}")
    chain = f"floor-{kind}" + ("-inline" if inline else "")
    sizes = payload_sizes(n)
    workdir = settings.logs / f"{chain}-{n}"
    socks, ports = _vehicle_sockets(n)
    group, data_port = _group(), free_port()
    socks["frames"] = stamped_socket(data_port, group=group)
    procs = ProcessSet(workdir, env=_env(settings.repo))
    collector = Collector(socks)
    results: list[PointResult] = []
    relay = ["bench.floor", "relay"]
    try:
        collector.start()
        if kind == "zenoh":
            rport = free_port(socket_kind_tcp())
            endpoint = f"tcp/127.0.0.1:{rport}"
            procs.spawn(
                "router",
                "router",
                python_module("arena_common.cli", "router", "--listen", endpoint),
                settings.repo,
            )
            wait_port(rport, 30, "the Zenoh router", procs)
            z = ["--connect", endpoint] + (["--inline"] if inline else [])
            a, b, c = (f"zenoh:{FLOOR_PREFIX}/v{{i}}/{s}" for s in "abc")
            procs.spawn(
                "ingest",
                "ingest",
                python_module(
                    *relay,
                    "--in",
                    f"mcast:{group}:{data_port}",
                    "--out",
                    a,
                    "--fanout",
                    str(n),
                    "--size",
                    str(sizes["mocap"]),
                    *z,
                ),
                settings.repo,
            )
            procs.spawn(
                "transform",
                "transform",
                python_module(
                    *relay, "--in", f"zenoh:{FLOOR_PREFIX}/*/a", "--out", b, "--size", str(sizes["pose"]), *z
                ),
                settings.repo,
            )
            for i in range(n):
                procs.spawn(
                    f"downsampler.d{i + 1}",
                    "downsampler",
                    python_module(
                        *relay,
                        "--in",
                        f"zenoh:{FLOOR_PREFIX}/v{i}/b",
                        "--out",
                        c,
                        "--size",
                        str(sizes["pose"]),
                        *z,
                    ),
                    settings.repo,
                )
            for i in range(n):
                procs.spawn(
                    f"gateway.d{i + 1}",
                    "gateway",
                    python_module(
                        *relay,
                        "--in",
                        f"zenoh:{FLOOR_PREFIX}/v{i}/c",
                        "--out",
                        f"udp:{ports[i]}",
                        "--size",
                        str(sizes["odometry"]),
                        *z,
                    ),
                    settings.repo,
                )
        else:
            p_all = free_port()
            p_b = [free_port() for _ in range(n)]
            p_c = [free_port() for _ in range(n)]
            procs.spawn(
                "ingest",
                "ingest",
                python_module(
                    *relay,
                    "--in",
                    f"mcast:{group}:{data_port}",
                    "--out",
                    f"udp:{p_all}",
                    "--fanout",
                    str(n),
                    "--size",
                    str(sizes["mocap"]),
                ),
                settings.repo,
            )
            procs.spawn(
                "transform",
                "transform",
                python_module(
                    *relay,
                    "--in",
                    f"udp:{p_all}",
                    "--out",
                    "udp:" + ",".join(map(str, p_b)),
                    "--size",
                    str(sizes["pose"]),
                ),
                settings.repo,
            )
            for i in range(n):
                procs.spawn(
                    f"downsampler.d{i + 1}",
                    "downsampler",
                    python_module(
                        *relay,
                        "--in",
                        f"udp:{p_b[i]}",
                        "--out",
                        f"udp:{p_c[i]}",
                        "--size",
                        str(sizes["pose"]),
                    ),
                    settings.repo,
                )
            for i in range(n):
                procs.spawn(
                    f"gateway.d{i + 1}",
                    "gateway",
                    python_module(
                        *relay,
                        "--in",
                        f"udp:{p_c[i]}",
                        "--out",
                        f"udp:{ports[i]}",
                        "--size",
                        str(sizes["odometry"]),
                    ),
                    settings.repo,
                )
        time.sleep(0.5)
        for rate in rates:
            collector.clear()
            source = procs.spawn(
                f"source.{int(rate)}",
                "emulator",
                python_module(
                    "bench.floor",
                    "source",
                    "--group",
                    group,
                    "--port",
                    str(data_port),
                    "--rate",
                    str(rate),
                    "--size",
                    str(sizes["natnet"]),
                ),
                settings.repo,
            )
            _wait_outputs(
                collector,
                n,
                settings.start_timeout,
                f"the {chain} chain to carry data for {n} vehicles",
                procs,
            )
            time.sleep(settings.warmup)
            t0 = time.time_ns()
            procs.mark()
            time.sleep(settings.duration)
            usage = procs.usage()
            t1 = time.time_ns()
            time.sleep(settings.drain)
            procs.check_alive()
            procs.stop(source)
            _wait_quiet(collector, list(range(n)))
            records = collector.take()
            found = analyze_floor(records["frames"], {i: records[i] for i in range(n)}, t0, t1)
            point = _result(chain, n, rate, found, usage)
            results.append(point)
            if on_point is not None:
                on_point(point)
    finally:
        procs.stop()
        collector.close()
    return results
