"""Quaternions, Euler angles and angles: the one place the arena's rotation math lives.

Conventions (everywhere in the arena): quaternions are ``(w, x, y, z)`` and rotate **body → world**,
``v_world = q ⊗ v_body ⊗ q*``; Euler angles are ``(roll, pitch, yaw)`` in radians, aerospace ZYX order.

Plain float arithmetic on tuples on purpose: for one pose it is several times cheaper than numpy, which
matters on the per-pose path and when one process flies several simulated vehicles in real time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported where a matrix is asked for: a gateway never loads it
    import numpy as np
    import numpy.typing as npt

__all__ = [
    "IDENTITY_QUAT",
    "FrameError",
    "Quat",
    "Vec3",
    "quat_angle",
    "quat_canonical",
    "quat_conjugate",
    "quat_from_axes",
    "quat_from_axis_angle",
    "quat_from_euler",
    "quat_from_matrix",
    "quat_from_yaw",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_rotate_inverse",
    "quat_to_euler",
    "quat_to_matrix",
    "quat_yaw",
    "wrap_angle",
]

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
if TYPE_CHECKING:
    FloatArray = npt.NDArray[np.float64]

IDENTITY_QUAT: Quat = (1.0, 0.0, 0.0, 0.0)


class FrameError(ValueError):
    """Invalid input to a frame computation (wrong shape, non-finite value, non-unit quaternion...)."""


def _vec3(v: Sequence[float], what: str = "vector") -> Vec3:
    if len(v) != 3:
        raise FrameError(f"{what} must have 3 components, got {len(v)}")
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise FrameError(f"{what} has a non-finite component: {(x, y, z)}")
    return (x, y, z)


def _quat(q: Sequence[float], what: str = "quaternion") -> Quat:
    if len(q) != 4:
        raise FrameError(f"{what} must have 4 components (w, x, y, z), got {len(q)}")
    w, x, y, z = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    if not math.isfinite(w + x + y + z):
        raise FrameError(f"{what} has a non-finite component: {(w, x, y, z)}")
    return (w, x, y, z)


def quat_multiply(a: Sequence[float], b: Sequence[float]) -> Quat:
    """Hamilton product ``a ⊗ b`` (apply ``b`` first, then ``a``)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_conjugate(q: Sequence[float]) -> Quat:
    """Conjugate ``(w, -x, -y, -z)``: the inverse rotation for a unit quaternion."""
    return (float(q[0]), -float(q[1]), -float(q[2]), -float(q[3]))


def quat_normalize(q: Sequence[float]) -> Quat:
    """Return ``q`` scaled to unit norm; raises :class:`FrameError` for a zero or non-finite quaternion."""
    w, x, y, z = _quat(q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n < 1e-12:
        raise FrameError("cannot normalise a zero quaternion")
    return (w / n, x / n, y / n, z / n)


def quat_canonical(q: Sequence[float]) -> Quat:
    """Return the representative of ``±q`` with ``w >= 0`` (both describe the same rotation)."""
    w, x, y, z = (float(c) for c in q)
    if w < 0.0:
        return (-w, -x, -y, -z)
    return (w, x, y, z)


def quat_rotate(q: Sequence[float], v: Sequence[float]) -> Vec3:
    """Rotate vector ``v`` by unit quaternion ``q`` (body → world): ``q ⊗ v ⊗ q*``."""
    w, qx, qy, qz = q
    vx, vy, vz = v
    # v' = v + 2w (u × v) + 2 u × (u × v), u = vector part
    tx = 2.0 * (qy * vz - qz * vy)
    ty = 2.0 * (qz * vx - qx * vz)
    tz = 2.0 * (qx * vy - qy * vx)
    return (
        vx + w * tx + (qy * tz - qz * ty),
        vy + w * ty + (qz * tx - qx * tz),
        vz + w * tz + (qx * ty - qy * tx),
    )


def quat_to_matrix(q: Sequence[float]) -> FloatArray:
    """3×3 rotation matrix of unit quaternion ``q`` (columns = body axes expressed in the world)."""
    import numpy as np

    w, x, y, z = quat_normalize(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=np.float64,
    )


def quat_from_matrix(m: npt.ArrayLike) -> Quat:
    """Unit quaternion (``w >= 0``) of a 3×3 rotation matrix.

    Raises :class:`FrameError` unless ``m`` is orthonormal with determinant +1 (to within 1e-6): a
    reflection (determinant −1) has no quaternion.
    """
    try:
        rows = [[float(v) for v in row] for row in m]  # type: ignore[union-attr, arg-type]
    except (TypeError, ValueError):
        raise FrameError("rotation matrix must be 3×3 numbers") from None
    if len(rows) != 3 or any(len(row) != 3 for row in rows):
        raise FrameError(f"rotation matrix must be 3×3, got rows of {[len(row) for row in rows]}")
    if not all(math.isfinite(v) for row in rows for v in row):
        raise FrameError("rotation matrix has non-finite entries")
    for i in range(3):
        for j in range(3):
            dot = sum(rows[k][i] * rows[k][j] for k in range(3))
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-6:
                raise FrameError("matrix is not orthonormal")
    if _det3(rows) < 0:
        raise FrameError("matrix is a reflection (determinant −1), not a rotation")
    return quat_canonical(quat_normalize(_shepperd(rows)))


def _shepperd(r: list[list[float]]) -> Quat:
    trace = r[0][0] + r[1][1] + r[2][2]
    # Shepperd: pick the largest of w, x, y, z to divide by, for numerical stability.
    if trace > max(r[0][0], r[1][1], r[2][2]):
        s = 2.0 * math.sqrt(1.0 + trace)
        q = (0.25 * s, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s)
    elif r[0][0] >= r[1][1] and r[0][0] >= r[2][2]:
        s = 2.0 * math.sqrt(1.0 + r[0][0] - r[1][1] - r[2][2])
        q = ((r[2][1] - r[1][2]) / s, 0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s)
    elif r[1][1] >= r[2][2]:
        s = 2.0 * math.sqrt(1.0 + r[1][1] - r[0][0] - r[2][2])
        q = ((r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r[2][2] - r[0][0] - r[1][1])
        q = ((r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s)
    return q


def _det3(r: list[list[float]]) -> float:
    return (
        r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
    )


def quat_from_euler(roll: float, pitch: float, yaw: float) -> Quat:
    """Quaternion of aerospace ZYX Euler angles (radians): ``q = qz(yaw) ⊗ qy(pitch) ⊗ qx(roll)``."""
    cr, sr = math.cos(roll * 0.5), math.sin(roll * 0.5)
    cp, sp = math.cos(pitch * 0.5), math.sin(pitch * 0.5)
    cy, sy = math.cos(yaw * 0.5), math.sin(yaw * 0.5)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def quat_to_euler(q: Sequence[float]) -> Vec3:
    """Aerospace ZYX Euler angles ``(roll, pitch, yaw)`` in radians of unit quaternion ``q``.

    ``pitch`` is in [−π/2, π/2]; ``roll`` and ``yaw`` in (−π, π]. At pitch ±90° roll and yaw are not unique.
    """
    w, x, y, z = quat_normalize(q)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return (roll, pitch, yaw)


def quat_yaw(q: Sequence[float]) -> float:
    """Yaw (heading, radians, about Down for NED/FRD) of unit quaternion ``q``."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quat_from_yaw(yaw: float) -> Quat:
    """Yaw-only quaternion: rotation by ``yaw`` radians about the world's third axis (Down in NED)."""
    return (math.cos(yaw * 0.5), 0.0, 0.0, math.sin(yaw * 0.5))


def quat_from_axis_angle(axis: Sequence[float], angle: float) -> Quat:
    """Rotation by ``angle`` radians about ``axis`` (any non-zero length; right-hand rule)."""
    ax, ay, az = _vec3(axis, "axis")
    n = math.sqrt(ax * ax + ay * ay + az * az)
    if n < 1e-12:
        raise FrameError("rotation axis must be non-zero")
    s = math.sin(angle * 0.5) / n
    return (math.cos(angle * 0.5), ax * s, ay * s, az * s)


def quat_angle(a: Sequence[float], b: Sequence[float]) -> float:
    """Smallest rotation angle (radians, in [0, π]) taking unit quaternion ``a`` to ``b``."""
    dot = abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3])
    return 2.0 * math.acos(min(1.0, dot))


def wrap_angle(angle: float) -> float:
    """Wrap an angle (radians) into [−π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def quat_rotate_inverse(q: Sequence[float], v: Sequence[float]) -> Vec3:
    """Rotate world vector ``v`` into the body frame of unit quaternion ``q``: ``q* ⊗ v ⊗ q``."""
    return quat_rotate(quat_conjugate(q), v)


def quat_from_axes(b1: Sequence[float], b2: Sequence[float], b3: Sequence[float]) -> Quat:
    """Unit quaternion (``w >= 0``) of the rotation whose columns are the body axes ``b1, b2, b3`` in the world.

    Unchecked and fast (the simulation calls it every control step); :func:`quat_from_matrix` checks its input.
    """
    rows = [[b1[0], b2[0], b3[0]], [b1[1], b2[1], b3[1]], [b1[2], b2[2], b3[2]]]
    return quat_canonical(quat_normalize(_shepperd(rows)))
