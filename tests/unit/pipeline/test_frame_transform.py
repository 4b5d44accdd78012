"""Frame transform service: Motive poses in, arena-frame poses out, through a real bus."""

from __future__ import annotations

import itertools
import math
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from arena_common.bus.session import Bus, Subscription
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig, CalibrationSpec
from arena_common.geometry.frames import quat_angle, quat_from_axis_angle, quat_from_euler
from services import frame_transform
from tests.helpers import Proc, service_argv, wait_for, write_config

T0 = 1_700_000_000_000_000_000
DT = 5_555_556  # 180 Hz


@contextmanager
def service_thread(target: Callable[..., None], *args: Any, **kwargs: Any) -> Iterator[threading.Event]:
    """Run a service's ``main`` in a thread with a stop event; stop it and re-raise its error at the end."""
    stop = threading.Event()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            target(*args, stop=stop, **kwargs)
        except BaseException as exc:
            errors.append(exc)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    try:
        yield stop
    finally:
        stop.set()
        th.join(15)
    assert not th.is_alive(), "service did not stop"
    if errors:
        raise errors[0]


def latest_stats(sub: Subscription, service: str) -> wire.Stats | None:
    """The newest Stats of ``service`` waiting on ``sub``, if any."""
    found = None
    for item in sub.channel.drain():
        if isinstance(item.payload, wire.Stats) and item.payload.service == service:
            found = item.payload
    return found


def mocap(fn: int, p: tuple[float, float, float], q: tuple[float, ...], ok: bool = True) -> wire.MocapPose:
    return wire.MocapPose(t=T0 + fn * DT, fn=fn, id=1, p=p, q=q, ok=ok, name="d1")  # type: ignore[arg-type]


def frame(*bodies: tuple[str, wire.MocapPose]) -> wire.MocapFrame:
    """The mocap frame of the ingest carrying ``(drone, sample)`` bodies (frame fields from the first)."""
    m = bodies[0][1]
    b = tuple(wire.MocapBody(d, s.id, s.p, s.q, s.ok, s.name, s.err) for d, s in bodies)
    return wire.MocapFrame(t=m.t, fn=m.fn, b=b, lat=m.lat, mts=m.mts, tsrc=m.tsrc, tp=m.tp)


class Link:
    """A publisher of one drone's mocap frames and a FIFO of its arena poses, once the service is reachable."""

    def __init__(self, bus: Bus, drone: str = "d1") -> None:
        self.drone = drone
        self.pub = bus.stream_publisher(keys.FRAMES, wire.MocapFrame)
        self.sub = bus.subscribe(keys.pose(drone), capacity=10_000, ring=False)
        self.got: list[wire.Pose] = []

    def put(self, sample: wire.MocapPose) -> None:
        """Publish ``sample`` as the one body of a frame."""
        self.pub.put(frame((self.drone, sample)))

    def poll(self) -> list[wire.Pose]:
        self.got.extend(i.payload for i in self.sub.channel.drain() if i.payload is not None)
        return self.got

    def warm_up(self) -> None:
        """Publish untracked samples (they reset the velocity estimate) until the service answers."""
        warm = mocap(0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), ok=False)

        def answered() -> list[wire.Pose]:
            self.put(warm)
            return self.poll()

        wait_for(answered, timeout=20, interval=0.05, what="first pose")
        self.got.clear()

    def exchange(self, samples: list[wire.MocapPose]) -> list[wire.Pose]:
        """Publish ``samples`` and return the poses answering them (by frame number)."""
        for s in samples:
            self.put(s)
        want = {s.fn for s in samples}
        wait_for(lambda: want <= {p.fn for p in self.poll()}, timeout=10, what="every pose")
        return [p for p in self.got if p.fn in want]


def configure(
    cfg: ArenaConfig, up_axis: str, yaw_deg: float, offset: tuple[float, float, float]
) -> ArenaConfig:
    return cfg.replace(
        mocap=cfg.mocap.replace(up_axis=up_axis),
        calibration=CalibrationSpec(yaw_deg=yaw_deg, offset=offset),
    )


# Calibration used by the known vectors: 90° about Down ((n, e) → (−e, n)), then an offset.
# Expected values are worked by hand from the axis conventions, not with the library.
YAW, OFFSET = 90.0, (0.5, -0.25, 0.1)
# (up axis, Motive position (1, 2, 3) → arena position)
POSITIONS = {
    "y": (-2.5, 0.75, -1.9),  # NED (1, 3, -2) → rotated (-3, 1, -2) → + offset
    "z": (2.5, 0.75, -2.9),  # NED (1, -2, -3) → (2, 1, -3)
    "enu": (-0.5, 1.75, -2.9),  # NED (2, 1, -3) → (-1, 2, -3)
}
# (up axis, rotation of the body about a Motive axis, degrees) → arena (roll, pitch, yaw) in degrees
ATTITUDES = {
    "y": [
        ((0, 1, 0), 30, (0, 0, 60)),  # about up: turns left, NED yaw −30, +90 calibration
        ((1, 0, 0), 20, (20, 0, 90)),  # about forward: right side goes down (+roll)
        ((0, 0, 1), 20, (0, 20, 90)),  # about right (z): nose up (+pitch)
    ],
    "z": [
        ((0, 0, 1), 30, (0, 0, 60)),  # about up: turns left
        ((1, 0, 0), 20, (20, 0, 90)),  # about forward: left side up (+roll)
        ((0, 1, 0), 20, (0, -20, 90)),  # about left (y): nose down (−pitch)
    ],
    "enu": [
        ((0, 0, 1), 0, (0, 0, 180)),  # identity faces East: NED yaw 90, +90 calibration
        ((0, 0, 1), 30, (0, 0, 150)),  # ENU yaw 30 → NED yaw 60
        ((1, 0, 0), 20, (20, 0, 180)),  # about the FLU body's forward axis: +roll
    ],
}


@pytest.mark.parametrize("up_axis", ["y", "z", "enu"])
def test_known_vectors_through_the_service(
    up_axis: str, arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = configure(arena_config(), up_axis, YAW, OFFSET)
    link = Link(bus_factory())
    with service_thread(frame_transform.main, cfg, host="test"):
        link.warm_up()
        samples = [
            mocap(10 + i, (1.0, 2.0, 3.0), quat_from_axis_angle(axis, math.radians(angle)))
            for i, (axis, angle, _) in enumerate(ATTITUDES[up_axis])
        ]
        poses = link.exchange(samples)
    for sample, (_, _, euler), pose in zip(samples, ATTITUDES[up_axis], poses, strict=True):
        assert pose.ok and pose.fn == sample.fn and pose.t == sample.t
        assert pose.tp >= pose.t - 10**9 and pose.rc == 0
        assert pose.p == pytest.approx(POSITIONS[up_axis], abs=1e-9)
        want = quat_from_euler(*(math.radians(a) for a in euler))
        assert quat_angle(pose.q, want) < 1e-6, (pose.q, euler)
        assert pose.q[0] >= 0.0 and math.isclose(sum(c * c for c in pose.q), 1.0, rel_tol=1e-9)


def test_velocity_and_invalid_bodies(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    """Y-up body moving at (1, 0.5, 0) m/s in Motive and turning about up; then it is lost, then found."""
    cfg = configure(arena_config(), "y", YAW, OFFSET)
    link = Link(bus_factory())
    rate = math.radians(90.0)  # rad/s about Motive's up: turning left, so −rate about FRD down
    with service_thread(frame_transform.main, cfg, host="test"):
        link.warm_up()
        moving = [
            mocap(
                100 + i,
                (1.0 * i * DT * 1e-9, 0.5 * i * DT * 1e-9, 0.0),
                quat_from_axis_angle((0, 1, 0), rate * i * DT * 1e-9),
            )
            for i in range(40)
        ]
        poses = link.exchange(moving)
        # Lost: Motive streams the body with the bit clear and garbage numbers.
        lost = [mocap(200 + i, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), ok=False) for i in range(3)]
        lost_poses = link.exchange(lost)
        found = link.exchange([mocap(300, (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))])
    assert not poses[0].vok and poses[0].v == (0.0, 0.0, 0.0)
    assert all(p.vok and p.ok for p in poses[1:])
    # Motive Y-up velocity (1, 0.5, 0) → NED (1, 0, −0.5) → rotated 90° about Down → (0, 1, −0.5)
    assert poses[-1].v == pytest.approx((0.0, 1.0, -0.5), abs=1e-6)
    assert poses[-1].w == pytest.approx((0.0, 0.0, -rate), abs=1e-6)
    for p in lost_poses:
        assert not p.ok and not p.vok and p.v == (0.0, 0.0, 0.0)
        assert p.p == pytest.approx((0.5, -0.25, 0.1))  # the converted (meaningless) position: origin
        assert p.q == (1.0, 0.0, 0.0, 0.0)  # an unusable quaternion becomes identity, still invalid
    assert found[0].ok and not found[0].vok  # tracking back: velocities restart from scratch


def test_bad_payloads_are_counted_and_the_service_lives(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = arena_config()
    bus = bus_factory()
    link = Link(bus)
    stats = bus.subscribe(keys.stats("test", "transform"), capacity=100, ring=False)
    wrong = bus.stream_publisher(keys.FRAMES, wire.Pose)  # a Pose on the frames key
    with service_thread(frame_transform.main, cfg, host="test"):
        link.warm_up()
        link.pub.put_raw(b"\x93\x01\x02\x03")  # msgpack, not a map
        link.pub.put_raw(b"\xc1")  # not msgpack at all
        bad_body = wire.MocapBody(
            "d1", 1, (0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0), True
        )  # not a unit quaternion
        link.pub.put_raw(wire.MocapFrame(t=1, fn=1, b=(bad_body,)).encode())
        wrong.put(wire.Pose(t=1, p=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), ok=True))
        after = link.exchange([mocap(5, (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))])
        assert after[0].ok and after[0].p == pytest.approx((1.0, 3.0, -2.0))

        def counted() -> wire.Stats | None:
            s = latest_stats(stats, "transform")
            # The Pose on the frames key is refused by its decoder (its encoding names another type).
            return s if s and s.rejected.get("bad_payload", 0) == 4 else None

        snap = wait_for(counted, timeout=10, interval=0.1, what="rejections in the stats")
    assert snap.counts["frames"] >= 6 and snap.counts["in"] >= 2 and snap.counts["out"] >= 2
    assert snap.counts["invalid"] >= 1  # the warm-up samples


def test_one_frame_carries_every_vehicle_and_unwatched_full_rate_poses_are_not_sent(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    """One frame in, each vehicle's pose and vision out; decimating, a pose nobody reads is not published."""
    cfg = arena_config(2, DECIMATE_IN_TRANSFORM)
    bus = bus_factory()
    link = Link(bus)  # reads d1's full-rate poses; nobody reads d2's
    vision2 = bus.subscribe(keys.vision("d2"), capacity=10_000, ring=False)
    stats = bus.subscribe(keys.stats("test", "transform"), capacity=100, ring=False)
    sent: list[int] = []
    with service_thread(frame_transform.main, cfg, host="test"):
        link.warm_up()

        def counted() -> wire.Stats | None:
            for _ in range(18):  # a tenth of a second of frames, each with both vehicles
                fn = 1000 + len(sent)
                d1 = mocap(fn, (0.001 * fn, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
                link.pub.put(frame(("d1", d1), ("d2", d1.replace(id=2, p=(1.0, 2.0, 3.0)))))
                sent.append(fn)
            s = latest_stats(stats, "transform")
            return s if s and s.counts.get("unwatched", 0) >= 20 else None

        snap = wait_for(counted, timeout=20, interval=0.1, what="d2's unwatched poses counted")
        wait_for(lambda: set(sent) <= {p.fn for p in link.poll()}, timeout=10, what="every d1 pose")
    vision = [i.payload for i in vision2.channel.drain()]
    assert len(vision) >= 0.2 * len(sent), (len(vision), len(sent))  # 50 of 180 Hz: d2's vision went on
    assert all(isinstance(v, wire.Pose) and v.p == pytest.approx((1.0, 3.0, -2.0)) for v in vision)
    assert snap.counts["frames"] < snap.counts["in"] <= 2 * snap.counts["frames"]  # one or two bodies each
    assert snap.counts["out"] + snap.counts["unwatched"] <= snap.counts["in"]


def test_runs_as_a_process(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus], processes: Callable[..., Proc]
) -> None:
    path = write_config(
        tmp_path, router_endpoint, extra="[calibration]\nyaw_deg = -90.0\noffset = [1.0, 0, 0]"
    )
    link = Link(bus_factory())
    proc = processes("transform", service_argv("frame_transform", path))
    try:
        link.warm_up()
        pose = link.exchange([mocap(7, (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))])[0]
        assert proc.running
    finally:
        code = proc.stop(sig=signal.SIGTERM)
    assert code == 0, proc.tail()
    # Y-up (1, 2, 3) → NED (1, 3, −2) → −90° about Down: (3, −1, −2) → + (1, 0, 0)
    assert pose.p == pytest.approx((4.0, -1.0, -2.0), abs=1e-9)
    assert quat_angle(pose.q, quat_from_euler(0.0, 0.0, math.radians(-90.0))) < 1e-9


DECIMATE_IN_TRANSFORM = '[pipeline]\ndecimate = "transform"\nshed_after = 0  # every pose out, however busy'


def test_decimates_into_vision_when_configured(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    """``decimate = "transform"``: 180 Hz in, the vehicle's 50 Hz vision out, by time; nothing for others."""
    cfg = arena_config(extra=DECIMATE_IN_TRANSFORM)
    assert cfg.vehicles["d1"].vision_rate == 50.0
    bus = bus_factory()
    link = Link(bus)
    vision = bus.subscribe(keys.vision("d1"), capacity=10_000, ring=False)
    stranger = Link(bus, "zz")  # a body no vehicle is configured for: pose yes, vision no
    stranger_vision = bus.subscribe(keys.vision("zz"), capacity=100, ring=False)
    with service_thread(frame_transform.main, cfg, host="test"):
        link.warm_up()
        vision.channel.drain()  # the warm-up samples are untracked: none became vision anyway
        samples = [mocap(1000 + i, (0.001 * i, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)) for i in range(180)]
        poses = link.exchange(samples)
        stranger.warm_up()
        stranger.exchange([mocap(5000, (1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0))])
        wait_for(lambda: len(vision.channel) >= 49, timeout=10, what="a second of vision")
    items = vision.channel.drain()
    out = [i.payload for i in items if isinstance(i.payload, wire.Pose)]
    assert len(out) == len(items) and all(v.ok for v in out)
    assert 49 <= len(out) <= 51, len(out)  # one second of 180 Hz input at 50 Hz
    by_fn = {p.fn: p for p in poses}
    for v in out:
        assert v.p == by_fn[v.fn].p and v.t == by_fn[v.fn].t  # a pose the transform made, not a blend
    gaps = [(b.t - a.t) / 1e6 for a, b in itertools.pairwise(out)]
    assert min(gaps) > 16.0 and max(gaps) < 24.0, gaps  # 20 ms slots, picked by measurement time
    assert len(stranger_vision.channel) == 0


def test_a_transform_behind_sheds_full_rate_poses_never_vision(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    """A sample that waited in the queue longer than ``shed_after`` loses its pose, never its vision."""
    # 1 µs: every sample has waited longer by the time it is taken, so every full-rate pose is shed.
    cfg = arena_config(extra='[pipeline]\ndecimate = "transform"\nshed_after = 0.000001')
    bus = bus_factory()
    link = Link(bus)
    poses = bus.subscribe(keys.pose("d1"), capacity=1000, ring=False)
    vision = bus.subscribe(keys.vision("d1"), capacity=1000, ring=False)
    stats = bus.subscribe(keys.stats("test", "transform"), capacity=100, ring=True)
    with service_thread(frame_transform.main, cfg, host="test"):

        def count(name: str) -> float:
            item = stats.get(0.3)
            payload = item.payload if item is not None else None
            return payload.counts.get(name, 0) if isinstance(payload, wire.Stats) else 0

        warm = mocap(0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), ok=False)

        def reading() -> bool:
            link.put(warm)
            return count("in") > 0

        wait_for(reading, timeout=20, what="the transform reading")
        before = count("shed")
        for i in range(180):
            link.put(mocap(1000 + i, (0.001 * i, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)))
        wait_for(
            lambda: count("shed") >= before + 180, timeout=10, what="every full-rate pose counted as shed"
        )
        wait_for(lambda: len(vision.channel) >= 49, timeout=10, what="a second of vision")
    assert all(not i.payload.ok for i in poses.channel.drain() if isinstance(i.payload, wire.Pose))
    out = [i.payload for i in vision.channel.drain() if isinstance(i.payload, wire.Pose)]
    assert 49 <= len(out) <= 51 and all(v.ok for v in out), len(out)


def test_decimating_transform_replaces_the_downsampler_processes(
    tmp_path: Path, router_endpoint: str
) -> None:
    from arena_common.core.config import load
    from arena_common.core.errors import ConfigError
    from arena_common.runtime.supervisor import plan

    cfg = load(write_config(tmp_path, router_endpoint, 2, DECIMATE_IN_TRANSFORM))
    assert cfg.hosts["test"].vehicle_services == ("gateway",)
    names = [p.name for p in plan(cfg, "test")]
    assert "gateway.d1" in names and not any(n.startswith("downsampler") for n in names)
    bad = write_config(tmp_path, router_endpoint, 1, DECIMATE_IN_TRANSFORM)
    bad.write_text(
        bad.read_text().replace("[hosts.test]", '[hosts.test]\nvehicle_services = ["downsampler", "gateway"]')
    )
    with pytest.raises(ConfigError, match=r"vehicle_services.*the transform decimates"):
        load(bad)


def test_decimating_each_frames_vision_goes_out_as_one_message_and_a_vehicles_own_key_only_when_read(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    """One VisionFrame per frame on arena/sys/vision (what a gateway serving several vehicles reads), the same
    poses as the vehicles' own vision keys; a vehicle's own key nobody reads is counted, not sent."""
    cfg = arena_config(2, DECIMATE_IN_TRANSFORM)
    bus = bus_factory()
    link = Link(bus)
    frames = bus.subscribe(keys.VISIONS, capacity=10_000, ring=False)
    vision1 = bus.subscribe(keys.vision("d1"), capacity=10_000, ring=False)  # nobody reads d2's own key
    stats = bus.subscribe(keys.stats("test", "transform"), capacity=100, ring=False)
    sent: list[int] = []
    with service_thread(frame_transform.main, cfg, host="test"):
        link.warm_up()

        def counted() -> wire.Stats | None:
            for _ in range(18):
                fn = 1000 + len(sent)
                d1 = mocap(fn, (0.001 * fn, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
                link.pub.put(frame(("d1", d1), ("d2", d1.replace(id=2, p=(1.0, 2.0, 3.0)))))
                sent.append(fn)
            s = latest_stats(stats, "transform")
            return (
                s
                if s and s.counts.get("vision_unwatched", 0) >= 10 and s.counts.get("vision_frames")
                else None
            )

        snap = wait_for(counted, timeout=20, interval=0.1, what="d2's unread vision counted, frames sent")
    items = frames.channel.drain()
    got = [i.payload for i in items if isinstance(i.payload, wire.VisionFrame)]
    assert got and len(got) == len(items)
    own = {p.fn: p for p in (i.payload for i in vision1.channel.drain()) if isinstance(p, wire.Pose)}
    both = [f for f in got if {b.n for b in f.b} == {"d1", "d2"}]
    assert len(both) >= 0.8 * len(got), [[b.n for b in f.b] for f in got]  # one filter rate: mostly together
    matched = 0
    for f in got:
        assert len({b.n for b in f.b}) == len(f.b)  # a vehicle once per frame
        for b in f.b:
            assert b.fn == f.fn and b.ok
            if b.n == "d2":
                assert b.p == pytest.approx((1.0, 3.0, -2.0))
            elif b.fn in own:
                assert b.pose() == own[b.fn]  # the very pose d1's own key carried
                matched += 1
    assert matched >= 0.8 * len(own), (matched, len(own))
    assert snap.counts["vision_frames"] <= snap.counts["vision"]
