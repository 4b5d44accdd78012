"""The user's API against a real gateway and the simulated PX4 (speed 2): readings, sensors, raw
telemetry, parameters (INT32 bytewise), goto with a duration, a trajectory with acceleration
feed-forward, body-frame velocity, refusals before anything flies, and the asyncio facade."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Iterator

import pytest

from arena_common import (
    Arena,
    AsyncArena,
    CommandError,
    FlightMode,
    SafetyRefused,
    Trajectory,
)
from arena_common.core import keys, wire
from arena_common.geometry.quat import quat_from_euler
from tests.unit.gateway.test_gateway import Rig, rig_factory  # noqa: F401  (the make_rig fixture)


@pytest.fixture
def flying(make_rig: Callable[..., Rig]) -> Iterator[tuple[Rig, Arena]]:
    rig = make_rig()
    arena = Arena(rig.cfg, bus=rig.bus, name="client-flight")
    try:
        d1 = arena.vehicle("d1")
        d1.wait_until(
            lambda v: v.status is not None and v.status.vision_fused and v.status.setup_ok, 15.0, "ready"
        )
        yield rig, arena
    finally:
        arena.close()


def test_readings_sensors_telemetry_and_parameters(flying: tuple[Rig, Arena]) -> None:
    _, arena = flying
    d1 = arena.vehicle("d1")
    e = d1.estimate
    assert e is not None and e.valid and e.problem == ""
    assert d1.mocap_pose is None and d1.position_source == "estimate"  # this rig feeds vision only
    d1.wait_until(lambda v: v.imu is not None and v.estimator is not None, 10.0, "IMU and estimator")
    imu, est = d1.imu, d1.estimator
    assert imu is not None and -10.5 < imu.accel[2] < -9.0  # at rest: the accelerometer reads −g (FRD)
    assert est is not None and est.position_ok and est.attitude
    raw = d1.telemetry("HIGHRES_IMU", timeout=5.0)
    assert raw is not None and raw.msg == "HIGHRES_IMU" and "zacc" in raw.f
    hb = d1.telemetry("HEARTBEAT", timeout=5.0)  # any message, subscribed on first use
    assert hb is not None and hb.f["autopilot"] == 12  # MAV_AUTOPILOT_PX4
    # Parameters: INT32 travel bytewise; the client reads ints as ints and floats as floats.
    ev = d1.params.get("EKF2_EV_CTRL")
    assert ev == 15 and isinstance(ev, int)
    assert d1.params.set("COM_DL_LOSS_T", 12) == 12 and d1.params["COM_DL_LOSS_T"] == 12
    rad = d1.params.set("NAV_ACC_RAD", 2.5)
    assert rad == 2.5 and isinstance(rad, float)
    with pytest.raises(ValueError, match=r"COM_DL_LOSS_T is an integer parameter: 1\.5"):
        d1.params.set("COM_DL_LOSS_T", 1.5)
    assert d1.params.get("COM_DL_LOSS_T") == 12  # nothing was written
    with pytest.raises(CommandError, match="NO_SUCH_PARAM"):
        d1.params.get("NO_SUCH_PARAM", timeout=1.0)


def test_goto_with_duration_trajectory_and_body_velocity(flying: tuple[Rig, Arena]) -> None:
    rig, arena = flying
    d1 = arena.vehicle("d1")
    modes: list[str] = []
    d1.on_state(lambda s: modes.append(s.mode) if not modes or modes[-1] != s.mode else None)
    events = d1.event_stream(timeout=10.0)
    d1.arm()
    d1.takeoff(1.0)
    p0 = d1.position
    assert p0 is not None
    # A trajectory out of the room or too far from the vehicle is refused before offboard is engaged.
    with pytest.raises(SafetyRefused, match=r"trajectory refused: .*north 3\.2"):
        d1.follow(Trajectory.min_jerk(p0, (5.0, p0[1], -1.0), 6.0))
    with pytest.raises(SafetyRefused, match=r"starts 1\.\d\d m from the vehicle"):
        d1.follow(Trajectory.min_jerk((p0[0] + 1.5, p0[1], -1.0), (0.0, 0.0, -1.0), 4.0))
    assert d1.mode != FlightMode.OFFBOARD
    # goto with a duration: a smooth path streamed by the program, then the gateway holds the goal.
    goal = (p0[0] + 0.8, p0[1], -1.0)
    d1.goto(*goal, yaw=0.0, duration=3.0, tolerance=0.15)
    assert d1.mode == FlightMode.OFFBOARD and rig.state("d1") is not None
    # Waypoints with times: position, velocity and acceleration feed-forward at 30 Hz.
    here = d1.position
    assert here is not None
    traj = Trajectory.waypoints(
        [(0.0, here), (2.5, (here[0] - 0.5, here[1] + 0.5, -1.2)), (5.0, (here[0] - 0.8, here[1], -1.0))],
        yaw=0.0,
    )
    d1.follow(traj)
    d1.wait_until(lambda v: math.dist(v.position or (9, 9, 9), traj.end) < 0.2, 10.0, "trajectory end")
    assert d1.mode == FlightMode.OFFBOARD  # the gateway holds its end
    # Body-frame velocity: heading north (yaw 0), forward is north.
    start = d1.position
    assert start is not None
    with d1.offboard() as ctl:
        ctl.velocity_body(0.4, 0.0, 0.0, yaw=0.0)
        d1.wait_until(lambda v: (v.position or start)[0] - start[0] > 0.3, 10.0, "forward")
        moved = d1.position
    assert moved is not None and abs(moved[1] - start[1]) < 0.15
    assert d1.mode == FlightMode.AUTO_LOITER  # leaving the block holds
    d1.land()
    assert d1.landed == "on_ground" and not d1.armed
    kinds = [ev.kind for ev in events.drain()]
    assert kinds.index("armed") < len(kinds) - 1
    seq = [m for m in modes if m in ("AUTO.TAKEOFF", "OFFBOARD", "AUTO.LOITER", "AUTO.LAND")]
    assert seq.index("AUTO.TAKEOFF") < seq.index("OFFBOARD") < seq.index("AUTO.LAND"), seq


def test_async_flight(flying: tuple[Rig, Arena]) -> None:
    rig, _ = flying

    async def main() -> tuple[list[wire.Event], float]:
        async with AsyncArena(rig.cfg, bus=rig.bus, name="client-async") as arena:
            d2 = arena.vehicle("d1")
            async with d2.event_stream(timeout=10.0) as events:
                await d2.arm()
                await d2.takeoff(0.8)
                height = -(d2.position or (0, 0, 0))[2]
                async with d2.offboard() as ctl:
                    ctl.velocity(0.0, 0.0, 0.0, yaw=0.0)
                    await arena.sleep(0.5)
                await d2.land()
                seen = []
                async for ev in events:
                    seen.append(ev)
                    if ev.kind == "armed" and not ev.data.get("armed", True):
                        break
            return seen, height

    seen, height = asyncio.run(main())
    assert 0.6 < height < 1.0
    armed = [e.data.get("armed") for e in seen if e.kind == "armed"]
    assert armed == [True, False]


def test_attitude_and_thrust_fly_and_a_steep_tilt_is_refused(flying: tuple[Rig, Arena]) -> None:
    _, arena = flying
    d1 = arena.vehicle("d1")
    events = d1.event_stream(timeout=10.0)
    d1.arm()
    d1.takeoff(1.0)
    p0 = d1.position
    assert p0 is not None
    # A steep attitude never reaches the vehicle (sent straight on the bus, as any program could).
    steep = wire.Setpoint(t=wire.now_ns(), q=quat_from_euler(math.radians(50.0), 0.0, 0.0), thrust=0.5)
    arena.bus.stream_publisher(keys.setpoint("d1"), wire.Setpoint).put(steep)
    refused = next(e for e in events if e.kind == "safety" and "tilted 50.0° from level, above 35°" in e.text)
    assert refused.text.startswith("setpoint refused") and d1.mode != FlightMode.OFFBOARD
    with d1.offboard() as ctl:
        # Level, a little more thrust than hover (0.5): it climbs. Then less than hover until the climb
        # has stopped, so how late this program sees the climb does not decide how high it goes.
        ctl.attitude(0.0, 0.0, 0.0, 0.56)
        d1.wait_until(lambda v: v.position is not None and v.position[2] < p0[2] - 0.3, 10.0, "a climb")
        ctl.attitude(0.0, 0.0, 0.0, 0.44)
        d1.wait_until(lambda v: v.velocity is not None and v.velocity[2] > -0.05, 10.0, "the climb stopped")
        # Nose down 10° (negative pitch, FRD), thrust whose vertical part balances gravity: it moves north.
        north0 = d1.position[0] if d1.position else p0[0]
        ctl.attitude(0.0, math.radians(-10.0), 0.0, 0.5 / math.cos(math.radians(10.0)))
        d1.wait_until(lambda v: v.position is not None and v.position[0] > north0 + 0.2, 10.0, "moving north")
        with pytest.raises(ValueError, match=r"thrust must be within 0\.\.1"):
            ctl.attitude(0.0, 0.0, 0.0, 1.5)
        ctl.attitude(0.0, 0.0, 0.0, 0.5)
    d1.wait_until(lambda v: v.mode == FlightMode.HOLD, 10.0, "Hold after the block")
    d1.land()
