"""The arena's frames as ROS 2 sees them (REP 103 and REP 105).

The arena is **NED** (x north, y east, z down) with **FRD** bodies (forward, right, down); ROS is **ENU**
(x east, y north, z up) with **FLU** bodies (forward, left, up).  The ROS world frame is ``map`` (REP 105:
a fixed world frame, here the room: its origin is the arena's, at the floor's centre); each vehicle's
body frame is named after the vehicle.

- position: ``(x, y, z)_ENU = (east, north, -down)``
- attitude: ``q_ENU←FLU = q_ENU←NED ⊗ q_NED←FRD ⊗ q_FRD←FLU``, where ENU←NED turns by π about the
  axis (1, 1, 0)/√2 and FRD←FLU by π about x; a yaw ψ (heading, clockwise from north) becomes the
  ROS yaw π/2 − ψ (counter-clockwise from east)
- world velocity: as the position; body rates: ``(p, -q, -r)``.

Worked example (tested): a vehicle 1 m above the floor at 1.25 m north, 0.5 m west, heading 30° (east
of north) is ``p = (1.25, -0.5, -1.0)`` in the arena and ``(-0.5, 1.25, 1.0)`` in ``map``, with ROS yaw
60°.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from arena_common.geometry.quat import Quat, Vec3, quat_multiply, quat_normalize, quat_rotate_inverse

__all__ = [
    "ENU_FROM_NED",
    "FRD_FROM_FLU",
    "body_rates_to_flu",
    "enu_to_ned",
    "ned_to_enu",
    "quat_enu_flu_to_ned_frd",
    "quat_ned_frd_to_enu_flu",
    "ros_yaw_to_heading",
    "velocity_enu_in_flu",
]

_H = math.sqrt(0.5)
#: ``q_ENU←NED`` (w, x, y, z): π about (1, 1, 0)/√2; it is its own inverse.
ENU_FROM_NED: Quat = (0.0, _H, _H, 0.0)
#: ``q_FRD←FLU``: π about x; its own inverse.
FRD_FROM_FLU: Quat = (0.0, 1.0, 0.0, 0.0)


def ned_to_enu(v: Sequence[float]) -> Vec3:
    """A position or world vector from NED to ENU."""
    return (float(v[1]), float(v[0]), -float(v[2]))


def enu_to_ned(v: Sequence[float]) -> Vec3:
    """A position or world vector from ENU to NED (the same swap)."""
    return (float(v[1]), float(v[0]), -float(v[2]))


def quat_ned_frd_to_enu_flu(q: Sequence[float]) -> Quat:
    """An attitude (FRD body → NED world) as ROS's (FLU body → ENU world), ``(w, x, y, z)``, w ≥ 0."""
    r = quat_normalize(quat_multiply(quat_multiply(ENU_FROM_NED, q), FRD_FROM_FLU))
    return r if r[0] >= 0.0 else (-r[0], -r[1], -r[2], -r[3])


def quat_enu_flu_to_ned_frd(q: Sequence[float]) -> Quat:
    """The inverse of :func:`quat_ned_frd_to_enu_flu`."""
    r = quat_normalize(quat_multiply(quat_multiply(ENU_FROM_NED, q), FRD_FROM_FLU))
    return r if r[0] >= 0.0 else (-r[0], -r[1], -r[2], -r[3])


def body_rates_to_flu(w: Sequence[float]) -> Vec3:
    """Angular velocity from the FRD body to the FLU body."""
    return (float(w[0]), -float(w[1]), -float(w[2]))


def velocity_enu_in_flu(v_ned: Sequence[float], q_ned_frd: Sequence[float]) -> Vec3:
    """A world velocity (NED) expressed in the FLU body frame (what ``nav_msgs/Odometry`` wants)."""
    frd = quat_rotate_inverse(q_ned_frd, v_ned)
    return (frd[0], -frd[1], -frd[2])


def ros_yaw_to_heading(yaw_enu: float) -> float:
    """A ROS yaw (counter-clockwise from east) as the arena's heading (clockwise from north), in ±π."""
    return math.atan2(math.cos(yaw_enu), math.sin(yaw_enu))
