"""Quaternion and angle helpers of the simulation (w, x, y, z; body → world), plain floats on tuples.

Plain float arithmetic on tuples on purpose: for 3-vectors it is several times cheaper than numpy, which
matters when one process flies several vehicles in real time.
"""

from __future__ import annotations

import math

__all__ = [
    "Quat",
    "QuatError",
    "Vec3",
    "clamp",
    "quat_conj",
    "quat_from_dcm_columns",
    "quat_from_euler",
    "quat_mul",
    "quat_normalize",
    "quat_rotate",
    "quat_rotate_inverse",
    "quat_to_euler",
    "quat_yaw",
    "wrap_pi",
]

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class QuatError(ValueError):
    """A quaternion that is not one (zero norm)."""


def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product ``a ⊗ b``."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_conj(q: Quat) -> Quat:
    """Conjugate (inverse of a unit quaternion)."""
    return (q[0], -q[1], -q[2], -q[3])


def quat_normalize(q: Quat) -> Quat:
    """Unit quaternion with non-negative w (one representative of the rotation)."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n < 1e-12:
        raise QuatError("zero quaternion")
    if w < 0:
        n = -n
    return (w / n, x / n, y / n, z / n)


def quat_rotate(q: Quat, v: Vec3) -> Vec3:
    """Rotate body vector ``v`` into the world frame."""
    w, x, y, z = q
    vx, vy, vz = v
    # t = 2 * cross(q.xyz, v); v' = v + w * t + cross(q.xyz, t)
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


def quat_rotate_inverse(q: Quat, v: Vec3) -> Vec3:
    """Rotate world vector ``v`` into the body frame."""
    return quat_rotate(quat_conj(q), v)


def quat_from_euler(roll: float, pitch: float, yaw: float) -> Quat:
    """Quaternion of ZYX (yaw, pitch, roll) Euler angles in radians."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def quat_to_euler(q: Quat) -> Vec3:
    """ZYX Euler angles (roll, pitch, yaw) in radians of a unit quaternion."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def quat_yaw(q: Quat) -> float:
    """Yaw (heading) of a unit quaternion, radians in (-π, π]."""
    w, x, y, z = q
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def wrap_pi(a: float) -> float:
    """Angle wrapped to [-π, π)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def quat_from_dcm_columns(b1: Vec3, b2: Vec3, b3: Vec3) -> Quat:
    """Quaternion from a rotation matrix given by its columns (body axes expressed in the world)."""
    r00, r10, r20 = b1
    r01, r11, r21 = b2
    r02, r12, r22 = b3
    tr = r00 + r11 + r22
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = (0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s)
    elif r00 > r11 and r00 > r22:
        s = math.sqrt(1.0 + r00 - r11 - r22) * 2
        q = ((r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s)
    elif r11 > r22:
        s = math.sqrt(1.0 + r11 - r00 - r22) * 2
        q = ((r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s)
    else:
        s = math.sqrt(1.0 + r22 - r00 - r11) * 2
        q = ((r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s)
    return quat_normalize(q)


def clamp(v: float, lo: float, hi: float) -> float:
    """``v`` limited to ``lo..hi``."""
    return lo if v < lo else hi if v > hi else v
