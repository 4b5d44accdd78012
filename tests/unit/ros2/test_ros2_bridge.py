"""The ``ros2`` service on a real Zenoh router, seen by a ROS 2 subscriber built from rmw_zenoh's design
(:mod:`tests.ros2_probe`: liveliness discovery, the derived key expression, zenoh-ext attachment, pycdr2
CDR), and commanded by ROS 2 messages: a goto and a velocity stream reach a simulated vehicle through its
real gateway; an unsafe goto and an unsafe Twist are refused with the reason on /rosout."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from arena_common import Arena
from arena_common.bus.session import Bus
from arena_common.core import keys, wire
from arena_common.ros2 import names, types
from services import ros2 as ros2_service
from tests import ros2_probe
from tests.helpers import Proc, service_argv, write_config
from tests.ros2_probe import Probe, open_session
from tests.unit.gateway.test_gateway import Rig, rig_factory  # noqa: F401  (the make_rig fixture)


@pytest.fixture
def probe(router_endpoint: str) -> Iterator[Probe]:
    session = open_session(router_endpoint)
    p = Probe(session)
    try:
        yield p
    finally:
        p.close()
        session.close()


POSE = wire.Pose(
    t=1_700_000_000_123_456_789,
    p=(1.25, -0.5, -1.0),
    q=(0.9659258262890683, 0.0, 0.0, 0.25881904510252074),
    ok=True,
    v=(0.1, 0.0, 0.0),
    w=(0.0, 0.0, 0.05),
    vok=True,
)


def test_ros2_discovers_and_reads_the_arena(
    tmp_path: Path,
    router_endpoint: str,
    bus_factory: Callable[[], Bus],
    processes: Callable[..., Proc],
    probe: Probe,
) -> None:
    cfg_path = write_config(tmp_path, router_endpoint, services=())
    proc = processes("ros2", service_argv("ros2", cfg_path, "--no-commands"))
    # Discovery: the node and its publishers, as `ros2 node list` / `ros2 topic list` find them.
    pose_ep = probe.find("/arena/d1/pose")
    assert pose_ep.type_name == "geometry_msgs::msg::dds_::PoseStamped_"
    assert pose_ep.type_hash == types.msg_type(types.POSE_STAMPED).hash
    assert pose_ep.qos == "2::,5:,:,:,," and pose_ep.node == "arena_bridge"
    assert any(t.endswith("/NN/%/%/arena_bridge") for t in probe.nodes())
    for topic, type_name in (  # each token as it arrives (find waits for it)
        ("/arena/d1/odom", "nav_msgs::msg::dds_::Odometry_"),
        ("/tf", "tf2_msgs::msg::dds_::TFMessage_"),
        ("/tf_static", "tf2_msgs::msg::dds_::TFMessage_"),
        ("/arena/d1/battery", "sensor_msgs::msg::dds_::BatteryState_"),
        ("/diagnostics", "diagnostic_msgs::msg::dds_::DiagnosticArray_"),
        ("/rosout", "rcl_interfaces::msg::dds_::Log_"),
    ):
        assert probe.find(topic).type_name == type_name, topic
    static = probe.find("/tf_static")
    assert static.qos == ":1:,1:,:,:,,"
    # /tf_static is transient local: a late subscriber gets the arena's frames from the publisher's cache.
    probe.subscribe(static, transient_local=True)
    for topic in ("/arena/d1/pose", "/arena/d1/odom", "/tf", "/arena/d1/battery", "/rosout"):
        probe.subscribe(probe.find(topic))
    (frames_msg, _), *_ = probe.wait("/tf_static")
    t = frames_msg.transforms[0]
    assert (t.header.frame_id, t.child_frame_id) == ("map", "arena_ned")
    assert (t.transform.rotation.x, t.transform.rotation.y) == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)))

    bus = bus_factory()
    pose_pub = bus.stream_publisher(keys.pose("d1"), wire.Pose)
    vision_pub = bus.stream_publisher(keys.vision("d1"), wire.Pose)
    state_pub = bus.stream_publisher(keys.state("d1"), wire.State)
    state = wire.State(t=POSE.t, link=True, volt=11.7, bat=0.82, mode="OFFBOARD")
    event = wire.Event(t=POSE.t, kind="statustext", text="Takeoff detected", sev=6)
    stop = threading.Event()

    def feed() -> None:  # until the bridge's subscriptions are routed: samples before that are lost
        while not stop.wait(0.05):
            pose_pub.put(POSE)
            vision_pub.put(POSE)
            state_pub.put(state)
            bus.put(keys.events("d1"), event)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        (pose, (_seq, ts, gid)), *_ = probe.wait("/arena/d1/pose", 2)
        (odom, _), *_ = probe.wait("/arena/d1/odom")
        (tf_msg, _), *_ = probe.wait("/tf")
        (battery, _), *_ = probe.wait("/arena/d1/battery")
        log = probe.wait_for("/rosout", lambda m: m.msg == "Takeoff detected")
    finally:
        stop.set()
        feeder.join(2.0)
    # The attachment: a sequence that counts from 1, a fresh source time, the GID of the token.
    samples = probe.wait("/arena/d1/pose", 2)
    seqs = [a[0] for _, a in samples]
    assert seqs[0] >= 1 and seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert abs(ts - time.time_ns()) < 60e9 and gid == names.gid(pose_ep.token)
    # The values, against arena/d1/pose (NED/FRD) converted by REP 103/105.
    assert (pose.header.stamp.sec, pose.header.stamp.nanosec, pose.header.frame_id) == (
        1700000000,
        123456789,
        "map",
    )
    assert (pose.pose.position.x, pose.pose.position.y, pose.pose.position.z) == (-0.5, 1.25, 1.0)
    o = pose.pose.orientation
    assert (o.w, o.z) == pytest.approx((math.cos(math.radians(30)), math.sin(math.radians(30))))
    assert tf_msg.transforms[0].child_frame_id == "d1" and tf_msg.transforms[0].header.frame_id == "map"
    assert tf_msg.transforms[0].transform.translation.y == 1.25
    assert odom.child_frame_id == "d1"
    assert odom.twist.twist.linear.x == pytest.approx(0.1 * math.cos(math.radians(30)))
    assert odom.twist.twist.linear.y == pytest.approx(0.1 * math.sin(math.radians(30)))
    assert odom.twist.twist.angular.z == pytest.approx(-0.05)
    assert battery.voltage == pytest.approx(11.7) and battery.percentage == pytest.approx(0.82)
    assert battery.present and math.isnan(battery.current)
    assert log.level == 20 and log.name == "arena_bridge.d1" and log.function == "statustext"
    assert proc.running, proc.tail()


def _wait(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def test_ros2_commands_fly_a_simulated_vehicle_and_unsafe_ones_are_refused(
    make_rig: Callable[..., Rig], router_endpoint: str, probe: Probe
) -> None:
    rig = make_rig()
    stop = threading.Event()
    service = threading.Thread(
        target=ros2_service.main, args=(rig.cfg,), kwargs={"host": "rostest", "stop": stop}, daemon=True
    )
    service.start()
    arena = Arena(rig.cfg, bus=rig.bus, name="ros2-test")
    try:
        d1 = arena.vehicle("d1")
        d1.wait_until(
            lambda v: v.status is not None and v.status.vision_fused and v.status.setup_ok, 15.0, "ready"
        )
        goto_ep = probe.find("/arena/d1/goto", kind="MS")
        twist_ep = probe.find("/arena/d1/cmd_vel", kind="MS")
        assert goto_ep.type_name == "geometry_msgs::msg::dds_::PoseStamped_"
        assert twist_ep.type_name == "geometry_msgs::msg::dds_::Twist_"
        probe.subscribe(probe.find("/rosout"))
        d1.arm()
        d1.takeoff(1.0)
        gid = bytes(range(16))
        seq = iter(range(1, 1000))

        def send(ep: ros2_probe.Endpoint, msg: object) -> None:
            ros2_probe.publish(probe.session, ep.keyexpr(), msg.serialize(), next(seq), gid)  # type: ignore[attr-defined]

        def goto(x: float, y: float, z: float, yaw_deg: float | None) -> object:
            q = (
                ros2_probe.Quaternion(0.0, 0.0, 0.0, 0.0)
                if yaw_deg is None
                else ros2_probe.Quaternion(
                    0.0, 0.0, math.sin(math.radians(yaw_deg) / 2), math.cos(math.radians(yaw_deg) / 2)
                )
            )
            return ros2_probe.PoseStamped(
                ros2_probe.Header(ros2_probe.Time(0, 0), "map"), ros2_probe.Pose(ros2_probe.Point(x, y, z), q)
            )

        # A goto in map (ENU): 0.5 m east, 0.3 m north, 1.2 m up; ROS yaw 90° (facing north) = heading 0.
        start = d1.position
        assert start is not None
        target_ned = (0.3, 0.5, -1.2)
        send(goto_ep, goto(0.5, 0.3, 1.2, 90.0))
        _wait(
            lambda: (p := d1.position) is not None and math.dist(p, target_ned) < 0.15,
            30.0,
            f"d1 at {target_ned} (now {d1.position})",
        )
        probe.wait_for("/rosout", lambda m: "d1: goto 0.30 0.50 -1.20 (NED): ACCEPTED" in m.msg)
        assert d1.mode == "OFFBOARD"  # the gateway holds the goal
        # An unsafe goto: 100 m east is outside the safe volume; refused with the reason, nothing moves.
        send(goto_ep, goto(100.0, 0.0, 1.0, None))
        refusal = probe.wait_for("/rosout", lambda m: "goto refused" in m.msg)
        assert refusal.level == 30 and "outside the safe volume" in refusal.msg
        # A velocity stream: forward (north, heading 0) at 0.3 m/s for a while, then silence: Hold.
        here = d1.position
        assert here is not None
        twist = ros2_probe.Twist(ros2_probe.Vector3(0.3, 0.0, 0.0), ros2_probe.Vector3(0.0, 0.0, 0.0))
        deadline = time.monotonic() + 20.0
        burst = 0
        while (p := d1.position) is not None and p[0] < here[0] + 0.3:
            assert time.monotonic() < deadline, f"no progress north: {p}"
            send(twist_ep, twist)
            burst += 1
            time.sleep(0.01 if burst < 100 else 0.05)  # a burst first: 100 Twists during the engage
        probe.wait_for("/rosout", lambda m: "velocity stream started" in m.msg)
        _wait(lambda: d1.mode == "AUTO.LOITER", 10.0, "Hold after the Twists stopped")
        # A short burst, then silence (issue 32): the engage outlasts the burst, yet the stream is engaged
        # once, ended once, and no Twist that arrived during the engage starts another.
        held_at = wire.now_ns()
        slow = ros2_probe.Twist(ros2_probe.Vector3(0.1, 0.0, 0.0), ros2_probe.Vector3(0.0, 0.0, 0.0))
        for _ in range(20):
            send(twist_ep, slow)
            time.sleep(0.02)
        _wait(lambda: d1.mode == "OFFBOARD", 10.0, "the burst engaged")
        _wait(lambda: d1.mode == "AUTO.LOITER", 10.0, "Hold after the burst")
        time.sleep(3.0)  # the seconds after: the Hold stays
        modes = [e.data.get("mode") for e in d1.events() if e.t >= held_at and e.kind == "mode"]
        assert modes == ["OFFBOARD", "AUTO.LOITER"] and d1.mode == "AUTO.LOITER", modes
        assert not [e for e in d1.events() if e.t >= held_at and e.kind == "failsafe"]
        started = [m for m, _ in probe.samples.get("/rosout", []) if "velocity stream started" in m.msg]
        assert len(started) == 2, [m.msg for m in started]  # the first flight's, and the burst's
        # An unsafe Twist: 5 m/s is beyond max_speed.
        send(twist_ep, ros2_probe.Twist(ros2_probe.Vector3(5.0, 0.0, 0.0), ros2_probe.Vector3(0.0, 0.0, 0.0)))
        refusal = probe.wait_for("/rosout", lambda m: "cmd_vel refused" in m.msg and "max_speed" in m.msg)
        assert refusal.level == 30
        assert d1.mode == "AUTO.LOITER"
        d1.land()
    finally:
        stop.set()
        service.join(10.0)
        arena.close()
    assert not service.is_alive()
