"""The user's API against real Zenoh sessions: a test bus publishes what a gateway and the pose pipeline
publish (real msgpack payloads on the real keys) and the client's streams, callbacks, typed readings,
validity rules, asyncio facade, swarm and clock are checked; trajectories are checked numerically."""

from __future__ import annotations

import asyncio
import itertools
import math
import re
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from arena_common import (
    Arena,
    ArenaClock,
    AsyncArena,
    FlightMode,
    LandedState,
    SafetyRefused,
    StreamTimeout,
    Trajectory,
    VehicleNotPresent,
)
from arena_common.bus.session import Bus
from arena_common.client.offboard import MAX_ACCEL
from arena_common.client.swarm import Swarm
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.gateway import setpoints as gw_setpoints
from arena_common.mavlink import px4
from tests.helpers import wait_for, write_config

EST_OK = px4.ESTIMATOR_ATTITUDE | px4.ESTIMATOR_VELOCITY_HORIZ | px4.ESTIMATOR_POS_HORIZ_REL | 32


@pytest.fixture
def client(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus]
) -> Iterator[tuple[Arena, Bus, ArenaConfig]]:
    """An Arena (its own session) and a second session standing for the gateway and the pipeline."""
    cfg = config_mod.load(write_config(tmp_path, router_endpoint, n_vehicles=2, speed=4.0))
    arena = Arena(cfg, mode="peer", name="test-client")
    feed = bus_factory()
    try:
        yield arena, feed, cfg
    finally:
        arena.close()


def _pose(i: int, ok: bool = True) -> wire.Pose:
    return wire.Pose(t=1_000_000 * (i + 1), p=(0.01 * i, 0.0, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=ok, fn=i + 1)


def _put_until(feed: Bus, key: str, payload: wire.Payload, done: Callable[[], object], what: str) -> None:
    """Publish ``payload`` every 20 ms until ``done()`` (the subscriber's discovery takes a moment)."""
    _repeat(lambda: feed.put(key, payload), done, what)


def _repeat(action: Callable[[], None], done: Callable[[], object], what: str) -> None:
    """Do ``action()`` every 20 ms until ``done()``."""

    def step() -> object:
        action()
        return done()

    wait_for(step, timeout=10.0, interval=0.02, what=what)


def test_poses_stream_and_callback_get_every_pose_in_order(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    arena, feed, _ = client
    d1 = arena.vehicle("d1")
    pub = feed.stream_publisher(keys.pose("d1"), wire.Pose)
    _repeat(lambda: pub.put(_pose(0)), lambda: d1.mocap is not None, "first pose")
    seen: list[int] = []
    cb = d1.on_pose(lambda p: seen.append(p.fn))
    with d1.poses(timeout=5.0) as stream:
        for i in range(1, 201):
            pub.put(_pose(i))
            if i % 20 == 0:
                time.sleep(0.005)  # a 180 Hz-like stream, not one burst
        got: list[wire.Pose] = []
        for pose in stream:
            if pose.fn != 1:  # a late copy of the discovery pose may still come first
                got.append(pose)
            if pose.fn == 201:
                break
    assert [p.fn for p in got] == list(range(2, 202))  # every pose, in order
    assert all(b.t > a.t for a, b in itertools.pairwise(got))  # measurement times kept
    wait_for(lambda: 201 in seen, 5.0, what="callbacks")
    assert [fn for fn in seen if fn != 1] == list(range(2, 202))
    cb.cancel()
    pub.put(_pose(300))
    wait_for(lambda: d1.mocap is not None and d1.mocap.fn == 301, 5.0, what="last pose")
    assert 301 not in seen  # cancelled
    with pytest.raises(StreamTimeout, match=r"d1/pose: nothing new within 0\.2 s"):
        next(d1.poses(timeout=0.2))


def test_a_failing_callback_is_counted_and_the_stream_goes_on(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    arena, feed, _ = client
    d1 = arena.vehicle("d1")
    d1.on_pose(lambda p: 1 / 0)
    good: list[int] = []
    d1.on_pose(lambda p: good.append(p.fn))
    pub = feed.stream_publisher(keys.pose("d1"), wire.Pose)
    _repeat(lambda: pub.put(_pose(1)), lambda: len(good) >= 3, "poses after a failing callback")
    assert d1.pose_topic.errors >= 3


def test_undecodable_samples_are_counted_and_never_stop_the_client(
    client: tuple[Arena, Bus, ArenaConfig],
) -> None:
    arena, feed, _ = client
    d1 = arena.vehicle("d1")
    raw = feed.stream_publisher(keys.pose("d1"), wire.Pose)
    _repeat(lambda: raw.put_raw(b"\x93garbage"), lambda: arena.rejected["undecodable"] > 0, "reject")
    _put_until(feed, keys.pose("d1"), _pose(5), lambda: d1.mocap is not None, "a good pose after garbage")
    assert d1.mocap is not None and d1.mocap.fn == 6


def test_typed_state_and_modes(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    arena, feed, _ = client
    d1 = arena.vehicle("d1")
    states = d1.states(timeout=5.0)
    st = wire.State(
        t=wire.now_ns(), link=True, armed=True, mode="OFFBOARD", landed="in_air", bat=0.8, volt=15.9
    )
    _put_until(feed, keys.state("d1"), st, lambda: d1.status is not None, "state")
    assert d1.mode is FlightMode.OFFBOARD and d1.mode == "OFFBOARD"
    assert d1.landed is LandedState.IN_AIR and d1.landed == "in_air"
    s = next(states)
    assert s.armed and s.mode is FlightMode.OFFBOARD and s.battery == 0.8 and s.voltage == 15.9
    b = d1.battery
    assert b is not None and b.remaining == 0.8 and b.voltage == 15.9
    new = st.replace(t=wire.now_ns(), mode="CUSTOM(main=12,sub=0)")
    _put_until(feed, keys.state("d1"), new, lambda: d1.mode is FlightMode.CUSTOM, "custom mode")
    assert d1.status is not None and d1.status.mode_name == "CUSTOM(main=12,sub=0)"
    assert FlightMode.HOLD is FlightMode.AUTO_LOITER


def test_estimate_is_never_good_when_the_autopilot_marks_it_invalid(
    client: tuple[Arena, Bus, ArenaConfig],
) -> None:
    arena, feed, _ = client
    d1 = arena.vehicle("d1")
    est_p = (1.0, 2.0, -1.0)
    state = wire.State(t=wire.now_ns(), link=True, mode="POSCTL", p=est_p, v=(0.1, 0.0, 0.0))
    ok = wire.Telemetry(t=wire.now_ns(), msg="ESTIMATOR_STATUS", f={"flags": EST_OK})
    _put_until(feed, keys.telemetry("d1", "ESTIMATOR_STATUS"), ok, lambda: d1.estimator is not None, "est")
    _put_until(feed, keys.state("d1"), state, lambda: d1.estimate is not None, "state")
    e = d1.estimate
    assert e is not None and e.valid and e.source == "estimate" and e.p == est_p and e.age < 5.0
    assert d1.position == est_p and d1.position_source == "estimate" and d1.velocity == (0.1, 0.0, 0.0)
    # The autopilot says it has no horizontal position: the estimate is not valid, position is None.
    bad = ok.replace(f={"flags": px4.ESTIMATOR_ATTITUDE | 32})
    _put_until(
        feed, keys.telemetry("d1", "ESTIMATOR_STATUS"), bad, lambda: d1.estimator and d1.estimator.flags != EST_OK,
        "bad estimator",
    )  # fmt: skip
    e = d1.estimate
    assert (
        e is not None
        and not e.valid
        and "horizontal position" in e.problem
        and "horizontal velocity" in e.problem
    )
    assert d1.position is None and d1.velocity is None and d1.position_source is None
    # A tracked mocap pose is the position then; an untracked one is not.
    _put_until(feed, keys.pose("d1"), _pose(3), lambda: d1.mocap is not None, "pose")
    m = d1.mocap_pose
    assert m is not None and m.valid and d1.position_source == "mocap" and d1.position == m.p
    _put_until(feed, keys.pose("d1"), _pose(4, ok=False), lambda: d1.mocap and not d1.mocap.ok, "untracked")
    m = d1.mocap_pose
    assert m is not None and not m.valid and "not tracked" in m.problem and d1.position is None


def test_sensor_readings_and_raw_telemetry(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    arena, feed, _ = client
    d1 = arena.vehicle("d1")
    imus = d1.imu_stream(timeout=5.0)
    hr = wire.Telemetry(
        t=wire.now_ns(),
        msg="HIGHRES_IMU",
        f={"xacc": 0.1, "yacc": -0.2, "zacc": -9.8, "xgyro": 0.01, "ygyro": 0.0, "zgyro": -0.01,
           "xmag": 0.2, "ymag": 0.0, "zmag": 0.4, "temperature": 31.5},
    )  # fmt: skip
    _put_until(feed, keys.telemetry("d1", "HIGHRES_IMU"), hr, lambda: d1.imu is not None, "imu")
    imu = next(imus)
    assert imu.accel == (0.1, -0.2, -9.8) and imu.gyro == (0.01, 0.0, -0.01) and imu.temperature == 31.5
    scaled = wire.Telemetry(
        t=wire.now_ns(),
        msg="SCALED_IMU",
        f={"xacc": 0, "yacc": 0, "zacc": -1000, "xgyro": 10, "ygyro": 0, "zgyro": 0},
    )
    _put_until(
        feed,
        keys.telemetry("d1", "SCALED_IMU"),
        scaled,
        lambda: d1.imu and d1.imu.source == "SCALED_IMU",
        "scaled",
    )
    assert (
        d1.imu is not None and math.isclose(d1.imu.accel[2], -9.80665) and math.isclose(d1.imu.gyro[0], 0.01)
    )
    bat = wire.Telemetry(
        t=wire.now_ns(),
        msg="BATTERY_STATUS",
        f={"voltages": [4000, 4000, 4000, 4000] + [0xFFFF] * 6, "battery_remaining": 55, "current_battery": 1250,
           "temperature": 0x7FFF, "charge_state": 2},
    )  # fmt: skip
    _put_until(feed, keys.telemetry("d1", "BATTERY_STATUS"), bat, lambda: d1.battery_topic.count, "battery")
    b = d1.battery
    assert b is not None and b.remaining == 0.55 and b.voltage == 16.0 and b.current == 12.5
    assert b.temperature is None and b.charge_state == "low"
    # Any message by name, subscribed on first use.
    att = wire.Telemetry(t=wire.now_ns(), msg="ATTITUDE", f={"roll": 0.1})
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.05):
            feed.put(keys.telemetry("d1", "ATTITUDE"), att)

    threading.Thread(target=publish, daemon=True).start()
    try:
        got = d1.telemetry("ATTITUDE", timeout=10.0)
        assert got is not None and got.f["roll"] == 0.1
        with d1.telemetry.stream("ATTITUDE", timeout=5.0) as s:
            assert next(s).msg == "ATTITUDE"
        assert "ATTITUDE" in d1.telemetry.names()
    finally:
        stop.set()
    assert d1.telemetry("NO_SUCH_MESSAGE", timeout=0.2) is None


def test_unknown_vehicle_fails_at_once_naming_the_known_ones(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    arena, _, _ = client
    with pytest.raises(VehicleNotPresent, match="unknown vehicle 'd7': the config lists d1, d2"):
        arena.vehicle("d7")
    assert arena.vehicle("d2") is arena.vehicle("d2")


def test_swarm_runs_per_vehicle_arguments(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    arena, _, _ = client
    swarm = arena.swarm(["d1", "d2"])
    assert swarm.run(lambda v, p: (v.name, p), [(1, 0), (0, 1)]) == [("d1", (1, 0)), ("d2", (0, 1))]
    assert swarm.run(lambda v, p: p * 2, {"d2": 5, "d1": 3}) == [6, 10]
    with pytest.raises(ValueError, match="3 given for 2 vehicles"):
        swarm.run(lambda v, p: p, [1, 2, 3])
    with pytest.raises(ValueError, match=r"missing for \['d2'\], unknown vehicles \['d9'\]"):
        swarm.run(lambda v, p: p, {"d1": 1, "d9": 2})
    with pytest.raises(ZeroDivisionError):
        swarm.run(lambda v: 1 / 0 if v.name == "d2" else 1)
    assert swarm["d2"].name == "d2" and Swarm([]).run(lambda v: v) == []


def test_clock_follows_the_simulation_speed(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    arena, _, cfg = client
    assert cfg.sim.speed == 4.0 and arena.clock.speed == 4.0  # every vehicle is simulated
    assert arena.clock.wall(2.0) == 0.5
    t0, w0 = arena.clock.now(), time.monotonic()
    arena.clock.sleep(0.4)
    assert arena.clock.now() - t0 >= 0.4 and time.monotonic() - w0 >= 0.1
    real = cfg.replace(vehicles={n: v.replace(autopilot="px4") for n, v in cfg.vehicles.items()})
    assert ArenaClock.for_config(real).speed == 1.0  # a real vehicle flies in real time
    assert ArenaClock.for_config(None).speed == 1.0


def test_async_facade_streams_every_pose(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    _, feed, cfg = client

    async def main() -> list[int]:
        async with AsyncArena(cfg, mode="peer", name="test-async") as arena:
            d1 = arena.vehicle("d1")
            pub = feed.stream_publisher(keys.pose("d1"), wire.Pose)
            while d1.mocap is None:  # readings are the sync object's, read without waiting
                pub.put(_pose(0))
                await asyncio.sleep(0.02)
            got: list[int] = []
            async with d1.poses(timeout=5.0) as stream:
                for i in range(1, 51):
                    pub.put(_pose(i))
                async for pose in stream:
                    if pose.fn != 1:  # a late copy of the discovery pose
                        got.append(pose.fn)
                    if pose.fn == 51:
                        break
            with pytest.raises(StreamTimeout):
                await d1.poses(timeout=0.1).__anext__()
            await arena.sleep(0.2)
            return got

    assert asyncio.run(main()) == list(range(2, 52))


def test_trajectories_are_smooth_and_checked() -> None:
    tr = Trajectory.min_jerk((0.0, 0.0, -1.0), (2.0, 0.0, -1.0), 4.0, yaw=0.5)
    assert tr.sample(0.0).p == (0.0, 0.0, -1.0) and tr.sample(4.0).p == pytest.approx((2.0, 0.0, -1.0))
    mid = tr.sample(2.0)
    assert mid.v[0] == pytest.approx(1.875 * 2.0 / 4.0) and mid.a[0] == pytest.approx(0.0, abs=1e-9)
    assert tr.sample(9.0).v == (0.0, 0.0, 0.0) and tr.sample(9.0).yaw == 0.5
    wp = Trajectory.waypoints([(0, (0, 0, -1)), (2, (1, 0, -1)), (4, (1, 1, -1.5)), (6, (0, 0, -1))])
    h = 1e-5
    for t in (0.5, 1.999, 2.0, 2.001, 3.3, 4.0, 5.9):
        s0, s1 = wp.sample(t - h), wp.sample(t + h)
        s = wp.sample(t)
        for k in range(3):  # velocity and acceleration are the derivatives, and continuous
            assert (s1.p[k] - s0.p[k]) / (2 * h) == pytest.approx(s.v[k], abs=1e-4)
            assert (s1.v[k] - s0.v[k]) / (2 * h) == pytest.approx(s.a[k], abs=1e-3)
    assert wp.sample(2.0).p == pytest.approx((1, 0, -1)) and wp.sample(4.0).p == pytest.approx((1, 1, -1.5))
    box = ((-3.2, 3.2), (-1.7, 1.7), (-2.2, 0.0))
    assert wp.check(box, 2.0, 1.0, MAX_ACCEL) is None
    fast = Trajectory.min_jerk((0, 0, -1), (3, 0, -1), 1.0)
    assert "acceleration 6.36 m/s² above 5.00" in (fast.check(box, 2.0, 1.0, MAX_ACCEL) or "")
    assert re.search(r"t=0\.\d\d s: horizontal speed 2\.\d\d m/s above 2\.00", fast.check(box, 2.0) or "")
    out = Trajectory.waypoints([(0, (3.0, 0, -1)), (3, (3.5, 0, -1))])
    assert "north 3.2" in (out.check(box) or "")
    poly = Trajectory.polynomial([(2.0, [0.0, 0.5], [0.0], [-1.0], [0.0, 0.1])])
    p = poly.sample(1.0)
    assert (
        p.p == (0.5, 0.0, -1.0)
        and p.v == (0.5, 0.0, 0.0)
        and p.yaw == pytest.approx(0.1)
        and p.yaw_rate == 0.1
    )
    with pytest.raises(ValueError, match=r"waypoint 1: time 0\.0 s does not come after 0\.0 s"):
        Trajectory.waypoints([(0, (0, 0, 0)), (0, (1, 0, 0))])
    with pytest.raises(ValueError, match="piece 0: duration"):
        Trajectory.polynomial([(0.0, [0.0], [0.0], [0.0], None)])


def test_client_and_gateway_agree_on_the_acceleration_limit() -> None:
    assert MAX_ACCEL == gw_setpoints.MAX_ACCEL


def test_setpoint_fields_are_checked_in_the_caller(client: tuple[Arena, Bus, ArenaConfig]) -> None:
    arena, _, _ = client
    d1 = arena.vehicle("d1")
    ctl = d1.offboard(engage=False)
    with pytest.raises(ValueError, match=r"not both .*field=yr"):
        ctl.velocity(0.1, 0.0, 0.0, yaw=0.0, yaw_rate=0.1)
    with pytest.raises(ValueError, match="field=a"):
        ctl.position(0.0, 0.0, -1.0, acceleration=(math.nan, 0.0, 0.0))
    with pytest.raises(ValueError, match="acceleration needs three components"):
        ctl.full_state((0, 0, -1), (0, 0, 0), (0, 0))
    ctl.close()


def test_a_setpoint_the_gateway_would_refuse_raises_in_the_caller(
    client: tuple[Arena, Bus, ArenaConfig],
) -> None:
    """Issue 25: an over-limit setpoint used to be dropped by the gateway in silence (its lease lapsed and
    PX4 landed the vehicle 1.5 s later); it must fail in the program that sent it, before it is streamed."""
    arena, _, cfg = client
    d1 = arena.vehicle("d1")
    ctl = d1.offboard(engage=False)
    too_fast = cfg.arena.max_speed + 0.5
    with pytest.raises(SafetyRefused, match=rf"horizontal speed {too_fast:.2f} m/s above max_speed"):
        ctl.velocity(too_fast, 0.0, 0.0)
    with pytest.raises(SafetyRefused, match=r"vertical speed .* above max_climb"):
        ctl.velocity(0.0, 0.0, -(cfg.arena.max_climb + 0.1))
    with pytest.raises(SafetyRefused, match="horizontal speed"):
        ctl.velocity_body(0.0, too_fast, 0.0)  # turning by the heading keeps the norm
    with pytest.raises(SafetyRefused, match="position outside the safe volume: north"):
        ctl.position(cfg.arena.size[0], 0.0, -1.0)
    with pytest.raises(SafetyRefused, match=r"acceleration feed-forward 6.00"):
        ctl.position(0.0, 0.0, -1.0, acceleration=(0.0, 6.0, 0.0))
    with pytest.raises(SafetyRefused, match=r"tilted 50.0°"):
        ctl.attitude(math.radians(50.0), 0.0, 0.0, 0.5)
    with pytest.raises(SafetyRefused, match="yaw rate"):
        ctl.velocity(0.1, 0.0, 0.0, yaw_rate=10.0)
    assert ctl._fields is None and ctl.sent == 0  # nothing refused was kept to be streamed
    ctl.velocity(cfg.arena.max_speed, 0.0, 0.0)  # at the limit: accepted
    ctl.close()


def test_a_refusal_reported_by_the_gateway_raises_at_the_next_call(
    client: tuple[Arena, Bus, ArenaConfig],
) -> None:
    """What only the gateway can judge (a velocity leading further out of the room) comes back as its
    "setpoint refused" event, which the stream raises at the next call and again never in silence."""
    arena, feed, _ = client
    d1 = arena.vehicle("d1")
    ctl = d1.offboard(engage=False)
    ctl.velocity(0.1, 0.0, 0.0)
    with ctl:
        refusal = wire.Event(
            t=wire.now_ns(),
            kind="safety",
            text="setpoint refused: velocity leads further out of the safe volume",
        )
        _put_until(feed, keys.events("d1"), refusal, lambda: ctl._refused is not None, "the refusal heard")
        time.sleep(0.3)  # the copies published while the subscription came up arrive (one is kept)
        with pytest.raises(SafetyRefused, match=r"velocity leads further out .*by the gateway"):
            ctl.velocity(0.1, 0.0, 0.0)
        ctl.velocity(-0.1, 0.0, 0.0)  # raised once; the next setpoint goes
