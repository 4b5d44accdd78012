"""Arena payloads as ROS 2 messages, and ROS 2 commands as the arena's: one pure function each.

Which topic each one serves, with what QoS and from which key, is the table of
:mod:`arena_common.ros2.topics`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from arena_common.core import wire
from arena_common.geometry.quat import Vec3, quat_yaw
from arena_common.ros2 import frames, types
from arena_common.ros2.names import ros_name

__all__ = [
    "MAP",
    "NED_FRAME",
    "Goto",
    "RosInputError",
    "Velocity",
    "battery",
    "diagnostics",
    "goto",
    "log",
    "odometry",
    "pose_stamped",
    "static_frames",
    "tf",
    "velocity",
]

MAP = "map"
NED_FRAME = "arena_ned"  # the arena's own NED frame, for whoever wants to see it in RViz


def _point(v: Any) -> Any:
    return types.cls("geometry_msgs/msg/Point")(x=v[0], y=v[1], z=v[2])


def _vector(v: Any) -> Any:
    return types.cls("geometry_msgs/msg/Vector3")(x=v[0], y=v[1], z=v[2])


def _quat(q: Any) -> Any:
    return types.cls("geometry_msgs/msg/Quaternion")(x=q[1], y=q[2], z=q[3], w=q[0])


def _pose(p: wire.Pose) -> Any:
    return types.cls("geometry_msgs/msg/Pose")(
        position=_point(frames.ned_to_enu(p.p)), orientation=_quat(frames.quat_ned_frd_to_enu_flu(p.q))
    )


def pose_stamped(p: wire.Pose) -> Any:
    """geometry_msgs/msg/PoseStamped in ``map`` (ENU, FLU body), stamped with the measurement time."""
    return types.cls(types.POSE_STAMPED)(header=types.header(p.t, MAP), pose=_pose(p))


_COV = 36


def odometry(vehicle: str, p: wire.Pose) -> Any:
    """nav_msgs/msg/Odometry: the pose in ``map``, the twist in the body (``child_frame_id``, FLU), as
    nav_msgs says; covariances unknown (zeros), velocities zero when the pose has none (``vok``)."""
    import numpy as np

    v = frames.velocity_enu_in_flu(p.v, p.q) if p.vok else (0.0, 0.0, 0.0)
    w = frames.body_rates_to_flu(p.w) if p.vok else (0.0, 0.0, 0.0)
    zeros = np.zeros(_COV, dtype=np.float64)
    pose = types.cls("geometry_msgs/msg/PoseWithCovariance")(pose=_pose(p), covariance=zeros)
    twist = types.cls("geometry_msgs/msg/TwistWithCovariance")(
        twist=types.cls(types.TWIST)(linear=_vector(v), angular=_vector(w)), covariance=zeros.copy()
    )
    return types.cls(types.ODOMETRY)(
        header=types.header(p.t, MAP), child_frame_id=vehicle, pose=pose, twist=twist
    )


def _transform(t_ns: int, parent: str, child: str, translation: Any, rotation: Any) -> Any:
    tf_ = types.cls("geometry_msgs/msg/Transform")(translation=_vector(translation), rotation=_quat(rotation))
    return types.cls("geometry_msgs/msg/TransformStamped")(
        header=types.header(t_ns, parent), child_frame_id=child, transform=tf_
    )


def tf(vehicle: str, p: wire.Pose) -> Any:
    """tf2_msgs/msg/TFMessage with the one transform ``map`` → ``<vehicle>`` (REP 105)."""
    t = _transform(p.t, MAP, vehicle, frames.ned_to_enu(p.p), frames.quat_ned_frd_to_enu_flu(p.q))
    return types.cls(types.TF_MESSAGE)(transforms=[t])


def static_frames(t_ns: int) -> Any:
    """The arena's static frames: ``map`` → ``arena_ned`` (same origin, x north, y east, z down)."""
    t = _transform(t_ns, MAP, NED_FRAME, (0.0, 0.0, 0.0), frames.ENU_FROM_NED)
    return types.cls(types.TF_MESSAGE)(transforms=[t])


def battery(vehicle: str, s: wire.State) -> Any:
    """sensor_msgs/msg/BatteryState; NaN where the autopilot says nothing, ``present`` while it reports."""
    cls = types.cls(types.BATTERY_STATE)
    import numpy as np

    return cls(
        header=types.header(s.t, vehicle),
        voltage=types.nan_or(s.volt),
        temperature=math.nan,
        current=math.nan,
        charge=math.nan,
        capacity=math.nan,
        design_capacity=math.nan,
        percentage=types.nan_or(s.bat),
        power_supply_status=cls.POWER_SUPPLY_STATUS_UNKNOWN,
        power_supply_health=cls.POWER_SUPPLY_HEALTH_UNKNOWN,
        power_supply_technology=cls.POWER_SUPPLY_TECHNOLOGY_UNKNOWN,
        present=s.bat is not None or s.volt is not None,
        cell_voltage=np.zeros(0, dtype=np.float32),
        cell_temperature=np.zeros(0, dtype=np.float32),
        location="",
        serial_number="",
    )


OK, WARN, ERROR, STALE = 0, 1, 2, 3  # diagnostic_msgs/msg/DiagnosticStatus levels


def _status(level: int, name: str, message: str, hw: str, values: dict[str, str]) -> Any:
    kv = types.cls("diagnostic_msgs/msg/KeyValue")
    return types.cls("diagnostic_msgs/msg/DiagnosticStatus")(
        level=level,
        name=name,
        message=message,
        hardware_id=hw,
        values=[kv(key=k, value=v) for k, v in values.items()],
    )


def diagnostics(vehicle: str, s: wire.State) -> Any:
    """diagnostic_msgs/msg/DiagnosticArray: the vehicle's link, estimator (vision fusion), failsafes and
    offboard stream, one DiagnosticStatus each, named ``arena/<vehicle>/<what>``."""
    name = f"arena/{vehicle}"
    link = _status(
        OK if s.link else ERROR,
        f"{name}/link",
        "heartbeats arriving" if s.link else "link lost",
        vehicle,
        {
            "sysid": str(s.sysid),
            "rtt": "" if s.rtt is None else f"{s.rtt:.4f}",
            "hb_age": "" if s.hb_age is None else f"{s.hb_age:.2f}",
            "armed": str(s.armed).lower(),
            "mode": s.mode,
            "landed": s.landed,
        },
    )
    est = _status(
        OK if s.vis_fused else WARN,
        f"{name}/estimator",
        "follows vision" if s.vis_fused else "vision not fused",
        vehicle,
        {
            "vis_rate": f"{s.vis_rate:.1f}",
            "vis_age": "" if s.vis_age is None else f"{s.vis_age:.3f}",
            "setup_ok": str(s.setup_ok).lower(),
        },
    )
    fs = _status(
        WARN if s.fs else OK,
        f"{name}/failsafe",
        ", ".join(s.fs) if s.fs else "none",
        vehicle,
        {f"fs{i}": f for i, f in enumerate(s.fs)},
    )
    ofb = _status(
        OK, f"{name}/offboard", "streaming" if s.ofb else "idle", vehicle, {"ofb": str(s.ofb).lower()}
    )
    return types.cls(types.DIAGNOSTIC_ARRAY)(header=types.header(s.t, vehicle), status=[link, est, fs, ofb])


def log_level(sev: int) -> int:
    """MAV_SEVERITY (0 emergency … 7 debug) as an rcl_interfaces/msg/Log level."""
    if sev <= 2:
        return 50  # FATAL
    return {3: 40, 4: 30, 5: 20, 6: 20}.get(sev, 10)


def log(vehicle: str, e: wire.Event, node: str = "arena") -> Any:
    """rcl_interfaces/msg/Log of an event: logger ``<node>.<vehicle>``, function the event's kind."""
    return types.cls(types.LOG)(
        stamp=types.stamp(e.t),
        level=log_level(e.sev),
        name=f"{node}.{ros_name(vehicle)}",
        msg=e.text,
        file="",
        function=e.kind,
        line=0,
    )


def text_log(t_ns: int, level: int, name: str, text: str, function: str = "") -> Any:
    """A plain rcl_interfaces/msg/Log (the bridge's own messages: refusals)."""
    return types.cls(types.LOG)(
        stamp=types.stamp(t_ns), level=level, name=name, msg=text, file="", function=function, line=0
    )


# -- ROS 2 → arena ---------------------------------------------------------------------------------------


class RosInputError(ValueError):
    """A ROS 2 message the arena cannot take; its text says why."""


@dataclass(frozen=True, slots=True)
class Goto:
    """A goto as the gateway's ``goto`` command takes it: position (NED, m), heading (rad, clockwise from
    north; ``None``: keep the heading)."""

    p: Vec3
    yaw: float | None


@dataclass(frozen=True, slots=True)
class Velocity:
    """A body velocity as the offboard stream takes it: FRD (m/s) and yaw rate (rad/s, clockwise)."""

    body: Vec3
    yaw_rate: float


def goto(msg: Any) -> Goto:
    """geometry_msgs/msg/PoseStamped in ``map`` (ENU; the default when ``frame_id`` is empty) or
    ``arena_ned`` as a :class:`Goto`; an all-zero orientation keeps the heading."""
    frame = msg.header.frame_id or MAP
    pos = (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z)
    o = msg.pose.orientation
    q = (o.w, o.x, o.y, o.z)
    if frame not in (MAP, NED_FRAME):
        raise RosInputError(f"frame {frame!r} unknown: use {MAP!r} or {NED_FRAME!r}")
    if not all(math.isfinite(x) for x in (*pos, *q)):
        raise RosInputError("position or orientation not finite")
    if frame == MAP:
        p = frames.enu_to_ned(pos)
        yaw = None if not any(q) else frames.ros_yaw_to_heading(quat_yaw(q))
    else:
        p = (float(pos[0]), float(pos[1]), float(pos[2]))
        yaw = None if not any(q) else quat_yaw(q)
    return Goto(p, yaw)


def velocity(msg: Any) -> Velocity:
    """geometry_msgs/msg/Twist in the body, REP 103 FLU (``linear.x`` forward, ``linear.y`` left,
    ``linear.z`` up, ``angular.z`` counter-clockwise), as the arena's FRD :class:`Velocity`."""
    body = (float(msg.linear.x), -float(msg.linear.y), -float(msg.linear.z))
    yaw_rate = -float(msg.angular.z)
    if not all(math.isfinite(x) for x in (*body, yaw_rate)):
        raise RosInputError("velocity not finite")
    return Velocity(body, yaw_rate)
