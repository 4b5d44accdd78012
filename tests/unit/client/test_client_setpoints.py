"""Acceleration feed-forward and full-state setpoints through a real gateway, checked on the MAVLink
bytes it sends (a plain pymavlink peer plays the vehicle); over-limit ones never leave the gateway."""

from __future__ import annotations

import time
from collections.abc import Callable

from arena_common.core import keys, wire
from arena_common.gateway.setpoints import MAX_ACCEL, type_mask
from arena_common.mavlink import px4
from tests.helpers import wait_for
from tests.unit.gateway.test_gateway import MavPeer, Rig, rig_factory  # noqa: F401  (the make_rig fixture)


def test_type_masks_of_the_new_fields() -> None:
    full = wire.Setpoint(t=1, p=(0.0, 0.0, -1.0), v=(0.1, 0.0, 0.0), a=(0.2, 0.0, 0.0), yaw=0.0)
    assert type_mask(full) == px4.TYPEMASK_YAW_RATE_IGNORE  # everything used but the yaw rate
    vel_acc = wire.Setpoint(t=1, v=(0.1, 0.0, 0.0), a=(0.2, 0.0, 0.0), yr=0.1)
    assert type_mask(vel_acc) == px4.TYPEMASK_POSITION | px4.TYPEMASK_YAW_IGNORE
    # Without acceleration the masks are PX4's usual ones.
    assert type_mask(wire.Setpoint(t=1, p=(0.0, 0.0, -1.0), yaw=0.0)) == px4.TYPEMASK_POS_YAW
    assert type_mask(wire.Setpoint(t=1, v=(0.0, 0.0, 0.0), yr=0.0)) == px4.TYPEMASK_VEL_YAWRATE


def test_acceleration_feed_forward_reaches_the_vehicle_and_over_limit_never(
    make_rig: Callable[..., Rig],
) -> None:
    rig = make_rig(simulate=False, start=False)
    port = int(rig.cfg.vehicle("d1").mavlink.rsplit(":", 1)[1])
    rig.start_gateway("d1")
    wait_for(lambda: rig.cmd("d1", "ping", timeout=1.0).ok, 10.0, what="gateway answers")
    vehicle = MavPeer(f"udpout:127.0.0.1:{port}", 1, airborne=True)
    try:
        rig.wait_ready("d1")
        wait_for(lambda: rig.gateways["d1"].state.flight_problem() is None, 5.0, what="armed, in the air")
        pub = rig.bus.stream_publisher(keys.setpoint("d1"), wire.Setpoint)
        # The gateway engages the stream as a mode OFFBOARD command naming it would (the peer answers no
        # command): what reaches the vehicle is what this test judges.
        assert rig.gateways["d1"].forwarder.engage("s1", "test") is None
        too_hard = wire.Setpoint(t=wire.now_ns(), p=(0.0, 0.0, -1.0), a=(0.0, 6.0, 0.0), stream="s1", seq=1)
        pub.put(too_hard)
        rig.wait_event(
            "d1",
            lambda e: e.kind == "safety" and "acceleration feed-forward 6.00 m/s² above 5.0" in e.text,
            3.0,
            "acceleration refused",
        )
        time.sleep(0.3)
        assert vehicle.of("SET_POSITION_TARGET_LOCAL_NED") == []
        sp = wire.Setpoint(
            t=wire.now_ns(),
            p=(1.0, 0.5, -1.0),
            v=(0.2, 0.0, 0.0),
            a=(0.5, -0.25, 0.1),
            yaw=0.3,
            lease=0.3,
            stream="s1",
            seq=2,
        )
        pub.put(sp)
        wait_for(lambda: vehicle.of("SET_POSITION_TARGET_LOCAL_NED"), 3.0, what="setpoint sent")
        m = vehicle.of("SET_POSITION_TARGET_LOCAL_NED")[0]
        assert (m.x, m.y, m.z) == (1.0, 0.5, -1.0)
        assert (round(m.vx, 6), m.vy, m.vz) == (0.2, 0.0, 0.0)
        assert (m.afx, m.afy, round(m.afz, 6)) == (0.5, -0.25, 0.1)
        assert m.type_mask == px4.TYPEMASK_YAW_RATE_IGNORE and abs(m.yaw - 0.3) < 1e-6
        assert MAX_ACCEL == 5.0
    finally:
        vehicle.close()
