"""Frame math: Motive → arena NED/FRD conversion and arena calibration (quaternions: :mod:`.quat`).

Conventions used everywhere in the arena:

* Quaternions are ``(w, x, y, z)`` and rotate **body → world**: ``v_world = q ⊗ v_body ⊗ q*``.
* Rotation matrices act the same way: ``v_world = R @ v_body`` (columns are the body axes in the world).
* Euler angles are ``(roll, pitch, yaw)`` in radians, aerospace ZYX order: ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
* The arena world frame is NED, vehicle bodies are FRD.

Motive's frame is chosen by :class:`UpAxis` (nothing in the NatNet stream says which one the operator
picked). Each up axis is a *proper* rotation ``C`` of the world axes (Motive → NED) and ``B`` of the body axes
(Motive body → FRD), so positions map as ``p_ned = C p`` and orientations as ``q_ned = c ⊗ q ⊗ b*``.

:class:`Calibration` then rotates about Down and shifts the origin, and :class:`FrameTransform` bundles both
into one precomputed affine map with a fast per-pose path, a vectorised path and the inverse (used by the
Motive emulator).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from arena_common.geometry.quat import (
    IDENTITY_QUAT,
    FrameError,
    Quat,
    Vec3,
    _vec3,
    quat_angle,
    quat_canonical,
    quat_conjugate,
    quat_from_axis_angle,
    quat_from_euler,
    quat_from_matrix,
    quat_from_yaw,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_to_euler,
    quat_to_matrix,
    quat_yaw,
    wrap_angle,
)

if TYPE_CHECKING:  # numpy is imported where a batch or a fit needs it: a gateway never loads it
    import numpy as np
    import numpy.typing as npt

__all__ = [
    "IDENTITY_QUAT",
    "Calibration",
    "CalibrationError",
    "FrameError",
    "FrameTransform",
    "Quat",
    "UpAxis",
    "Vec3",
    "calibration_residuals",
    "frd_to_motive",
    "motive_to_frd",
    "motive_to_ned",
    "ned_to_motive",
    "quat_angle",
    "quat_canonical",
    "quat_conjugate",
    "quat_from_axis_angle",
    "quat_from_euler",
    "quat_from_matrix",
    "quat_from_yaw",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_to_euler",
    "quat_to_matrix",
    "quat_yaw",
    "solve_calibration",
    "wrap_angle",
]

if TYPE_CHECKING:
    FloatArray = npt.NDArray[np.float64]
_SQRT_HALF = math.sqrt(0.5)
# FrameTransform accepts quaternions whose norm is within this of 1 (float32 Motive data is ~1e-7 off).
_UNIT_TOLERANCE = 0.01


class CalibrationError(FrameError):
    """The calibration cannot be solved from the given points (too few, degenerate, inconsistent)."""


# --------------------------------------------------------------------------------------------------
# Motive up axis → arena NED/FRD
# --------------------------------------------------------------------------------------------------


class UpAxis(StrEnum):
    """How Motive's streamed frame is oriented (configuration: the NatNet stream does not say).

    * ``Y_UP`` — Motive's default: x forward, y up, z right; rigid bodies x forward, y up, z right.
    * ``Z_UP`` — x forward, y left, z up; rigid bodies FLU.
    * ``ENU`` — what the original arena assumed: x East, y North, z up; rigid bodies FLU (mavros' rule).

    "Forward" is the direction that becomes the arena's North before calibration. A rigid body created in
    Motive takes the world axes as its own, so it must be created with the vehicle facing Motive's +x.
    """

    Y_UP = "y_up"
    Z_UP = "z_up"
    ENU = "enu"

    @classmethod
    def parse(cls, value: str | UpAxis) -> UpAxis:
        """Parse ``"y_up"``, ``"Y-up"``, ``"y"``, ``"z_up"``, ``"Z"``, ``"enu"`` ... (case-insensitive)."""
        if isinstance(value, UpAxis):
            return value
        key = str(value).strip().lower().replace("-", "_").replace(" ", "_")
        aliases = {"y": "y_up", "yup": "y_up", "z": "z_up", "zup": "z_up"}
        key = aliases.get(key, key)
        try:
            return cls(key)
        except ValueError:
            choices = ", ".join(m.value for m in cls)
            raise FrameError(f"unknown up axis {value!r}; expected one of: {choices}") from None


# World (C) and body (B) axis changes, Motive → NED / Motive body → FRD, as proper rotation matrices.
# These are the definitions; the explicit formulas below are checked against them in the tests.
_WORLD_MATRIX: dict[UpAxis, tuple[tuple[float, ...], ...]] = {
    UpAxis.Y_UP: ((1, 0, 0), (0, 0, 1), (0, -1, 0)),  # N = x, E = z, D = -y
    UpAxis.Z_UP: ((1, 0, 0), (0, -1, 0), (0, 0, -1)),  # N = x, E = -y, D = -z
    UpAxis.ENU: ((0, 1, 0), (1, 0, 0), (0, 0, -1)),  # N = y, E = x, D = -z
}
_BODY_MATRIX: dict[UpAxis, tuple[tuple[float, ...], ...]] = {
    UpAxis.Y_UP: ((1, 0, 0), (0, 0, 1), (0, -1, 0)),  # F = x, R = z, D = -y
    UpAxis.Z_UP: ((1, 0, 0), (0, -1, 0), (0, 0, -1)),  # F = x, R = -y, D = -z (FLU → FRD)
    UpAxis.ENU: ((1, 0, 0), (0, -1, 0), (0, 0, -1)),  # FLU → FRD
}


def motive_to_ned(p: Sequence[float], up_axis: UpAxis) -> Vec3:
    """Position in Motive's frame → NED (before calibration)."""
    x, y, z = p
    if up_axis is UpAxis.Y_UP:
        return (float(x), float(z), -float(y))
    if up_axis is UpAxis.Z_UP:
        return (float(x), -float(y), -float(z))
    if up_axis is UpAxis.ENU:
        return (float(y), float(x), -float(z))
    raise FrameError(f"unknown up axis {up_axis!r}")


def ned_to_motive(p: Sequence[float], up_axis: UpAxis) -> Vec3:
    """Inverse of :func:`motive_to_ned`: NED position → Motive's frame."""
    n, e, d = p
    if up_axis is UpAxis.Y_UP:
        return (float(n), -float(d), float(e))
    if up_axis is UpAxis.Z_UP:
        return (float(n), -float(e), -float(d))
    if up_axis is UpAxis.ENU:
        return (float(e), float(n), -float(d))
    raise FrameError(f"unknown up axis {up_axis!r}")


def motive_to_frd(q: Sequence[float], up_axis: UpAxis) -> Quat:
    """Rigid-body quaternion in Motive's frame → FRD body in NED (before calibration). Not normalised."""
    w, x, y, z = (float(c) for c in q)
    if up_axis is UpAxis.Y_UP:
        return (w, x, z, -y)
    if up_axis is UpAxis.Z_UP:
        return (w, x, -y, -z)
    if up_axis is UpAxis.ENU:
        s = _SQRT_HALF
        return (s * (w + z), s * (x + y), s * (x - y), s * (w - z))
    raise FrameError(f"unknown up axis {up_axis!r}")


def frd_to_motive(q: Sequence[float], up_axis: UpAxis) -> Quat:
    """Inverse of :func:`motive_to_frd`: FRD-in-NED quaternion → Motive rigid-body quaternion."""
    w, x, y, z = (float(c) for c in q)
    if up_axis is UpAxis.Y_UP:
        return (w, x, -z, y)
    if up_axis is UpAxis.Z_UP:
        return (w, x, -y, -z)
    if up_axis is UpAxis.ENU:  # the ENU map is its own inverse
        s = _SQRT_HALF
        return (s * (w + z), s * (x + y), s * (x - y), s * (w - z))
    raise FrameError(f"unknown up axis {up_axis!r}")


# --------------------------------------------------------------------------------------------------
# Calibration: Motive-NED → arena NED
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Calibration:
    """Rigid map from Motive's frame (already converted to NED) to the arena frame.

    ``arena = Rz(yaw_rad) @ motive_ned + offset_ned`` — rotate about Down first, then add the offset
    (expressed in the arena frame, metres). Orientations: ``q_arena = qz(yaw_rad) ⊗ q_motive_ned``.
    ``yaw_rad`` is in radians, positive from North towards East; use :meth:`from_degrees` for degrees.
    """

    yaw_rad: float = 0.0
    offset_ned: Vec3 = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        yaw = float(self.yaw_rad)
        if not math.isfinite(yaw):
            raise FrameError(f"calibration yaw must be finite, got {self.yaw_rad!r}")
        object.__setattr__(self, "yaw_rad", yaw)
        object.__setattr__(self, "offset_ned", _vec3(self.offset_ned, "calibration offset_ned"))

    @classmethod
    def from_degrees(cls, yaw_deg: float, offset_ned: Sequence[float] = (0.0, 0.0, 0.0)) -> Calibration:
        """Build from a yaw in degrees."""
        return cls(math.radians(yaw_deg), _vec3(offset_ned, "calibration offset_ned"))

    @property
    def yaw_deg(self) -> float:
        """The yaw in degrees."""
        return math.degrees(self.yaw_rad)

    def apply_position(self, p: Sequence[float]) -> Vec3:
        """Motive-NED position → arena NED."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        n, e, d = p
        on, oe, od = self.offset_ned
        return (c * n - s * e + on, s * n + c * e + oe, d + od)

    def inverse_position(self, p: Sequence[float]) -> Vec3:
        """Arena NED position → Motive-NED."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        on, oe, od = self.offset_ned
        n, e, d = p[0] - on, p[1] - oe, p[2] - od
        return (c * n + s * e, -s * n + c * e, d)

    def apply_quaternion(self, q: Sequence[float]) -> Quat:
        """Motive-NED body quaternion → arena (world rotation applied on the left)."""
        return quat_multiply(quat_from_yaw(self.yaw_rad), q)

    def inverse_quaternion(self, q: Sequence[float]) -> Quat:
        """Arena body quaternion → Motive-NED."""
        return quat_multiply(quat_from_yaw(-self.yaw_rad), q)

    def to_dict(self) -> dict[str, Any]:
        """Plain form for configuration files: ``{"yaw_deg": float, "offset_ned": [n, e, d]}``."""
        return {"yaw_deg": self.yaw_deg, "offset_ned": list(self.offset_ned)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Calibration:
        """Inverse of :meth:`to_dict` (missing keys default to no rotation / no offset)."""
        unknown = set(data) - {"yaw_deg", "offset_ned"}
        if unknown:
            raise FrameError(f"unknown calibration keys: {sorted(unknown)}")
        try:
            yaw_deg = float(data.get("yaw_deg", 0.0))
        except (TypeError, ValueError):
            raise FrameError(f"calibration yaw_deg must be a number, got {data.get('yaw_deg')!r}") from None
        return cls.from_degrees(yaw_deg, data.get("offset_ned", (0.0, 0.0, 0.0)))


def _points(points: Sequence[Sequence[float]] | npt.ArrayLike, what: str) -> FloatArray:
    import numpy as np

    try:
        a = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{what} must be a list of (n, e, d) points: {exc}") from None
    if a.ndim != 2 or a.shape[1] != 3:
        raise CalibrationError(f"{what} must be a list of (n, e, d) points, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise CalibrationError(f"{what} contains non-finite values")
    return a


def solve_calibration(
    measured_ned: Sequence[Sequence[float]] | npt.ArrayLike,
    known_arena: Sequence[Sequence[float]] | npt.ArrayLike,
    *,
    min_spread_m: float = 0.05,
) -> Calibration:
    """Least-squares :class:`Calibration` mapping ``measured_ned[i]`` onto ``known_arena[i]``.

    ``measured_ned`` are points as Motive reports them, converted to NED with the up axis (no calibration);
    ``known_arena`` the same points' surveyed arena coordinates. The fit is a 2-D rigid transform in the
    horizontal plane (yaw about Down and a North/East shift, no scale) plus the mean vertical offset.

    Raises :class:`CalibrationError` if there are fewer than 2 points, the lists differ in length, values
    are not finite, or the points do not spread at least ``min_spread_m`` horizontally (yaw undetermined).
    """
    import numpy as np

    m = _points(measured_ned, "measured points")
    k = _points(known_arena, "known arena points")
    if len(m) != len(k):
        raise CalibrationError(f"got {len(m)} measured points but {len(k)} known points")
    if len(m) < 2:
        raise CalibrationError(f"need at least 2 point pairs to solve yaw and offset, got {len(m)}")
    m_c = m[:, :2].mean(axis=0)
    k_c = k[:, :2].mean(axis=0)
    mh = m[:, :2] - m_c
    kh = k[:, :2] - k_c
    m_spread = float(np.sqrt((mh**2).sum(axis=1).max()))
    k_spread = float(np.sqrt((kh**2).sum(axis=1).max()))
    if m_spread < min_spread_m:
        raise CalibrationError(
            f"measured points are horizontally coincident (spread {m_spread:.4f} m < {min_spread_m} m): "
            "yaw is undetermined; place the points apart"
        )
    if k_spread < min_spread_m:
        raise CalibrationError(
            f"known arena points are horizontally coincident (spread {k_spread:.4f} m < {min_spread_m} m)"
        )
    # Minimise Σ|R m_i + t - k_i|²: the optimal yaw is atan2(Σ m × k, Σ m · k) on the centred points.
    cross = float((mh[:, 0] * kh[:, 1] - mh[:, 1] * kh[:, 0]).sum())
    dot = float((mh[:, 0] * kh[:, 0] + mh[:, 1] * kh[:, 1]).sum())
    yaw = math.atan2(cross, dot)
    c, s = math.cos(yaw), math.sin(yaw)
    t_n = k_c[0] - (c * m_c[0] - s * m_c[1])
    t_e = k_c[1] - (s * m_c[0] + c * m_c[1])
    t_d = float((k[:, 2] - m[:, 2]).mean())
    return Calibration(yaw, (float(t_n), float(t_e), t_d))


def calibration_residuals(
    calibration: Calibration,
    measured_ned: Sequence[Sequence[float]] | npt.ArrayLike,
    known_arena: Sequence[Sequence[float]] | npt.ArrayLike,
) -> FloatArray:
    """Per-point distance (m) between the calibrated measured points and the known arena points."""
    import numpy as np

    m = _points(measured_ned, "measured points")
    k = _points(known_arena, "known arena points")
    if len(m) != len(k):
        raise CalibrationError(f"got {len(m)} measured points but {len(k)} known points")
    mapped = np.array([calibration.apply_position(p) for p in m]).reshape(-1, 3)
    return np.asarray(np.linalg.norm(mapped - k, axis=1), dtype=np.float64)


# --------------------------------------------------------------------------------------------------
# Combined transform
# --------------------------------------------------------------------------------------------------


def _quat_linear_map(left: Quat, right: Quat) -> tuple[tuple[float, ...], ...]:
    """4×4 matrix ``M`` with ``M @ q == left ⊗ q ⊗ right`` (the product is linear in ``q``)."""
    cols = []
    for i in range(4):
        e = [0.0, 0.0, 0.0, 0.0]
        e[i] = 1.0
        cols.append(quat_multiply(quat_multiply(left, e), right))
    return tuple(tuple(cols[j][i] for j in range(4)) for i in range(4))


@dataclass(frozen=True)
class FrameTransform:
    """Motive pose → arena NED/FRD pose: the up-axis conversion followed by the :class:`Calibration`.

    The whole chain is precomputed as ``p_arena = A @ p_motive + t`` and ``q_arena = M @ q_motive`` (``M``
    orthogonal 4×4), so :meth:`pose` costs a handful of float operations. Output quaternions are normalised
    and canonical (``w >= 0``). Input quaternions must be unit to within 1 % (else :class:`FrameError`).
    """

    up_axis: UpAxis = UpAxis.Y_UP
    calibration: Calibration = field(default_factory=Calibration)
    _a: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)
    _t: Vec3 = field(init=False, repr=False, compare=False)
    _m: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)
    _m_inv: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        up = UpAxis.parse(self.up_axis)
        object.__setattr__(self, "up_axis", up)
        if not isinstance(self.calibration, Calibration):
            raise FrameError(f"calibration must be a Calibration, got {type(self.calibration).__name__}")
        world = _WORLD_MATRIX[up]
        yaw = self.calibration.yaw_rad
        c, s_ = math.cos(yaw), math.sin(yaw)
        rz = ((c, -s_, 0.0), (s_, c, 0.0), (0.0, 0.0, 1.0))
        a = tuple(tuple(sum(rz[i][k] * world[k][j] for k in range(3)) for j in range(3)) for i in range(3))
        left = quat_multiply(quat_from_yaw(yaw), quat_from_matrix(world))
        right = quat_conjugate(quat_from_matrix(_BODY_MATRIX[up]))
        m = _quat_linear_map(left, right)
        object.__setattr__(self, "_a", tuple(tuple(float(v) for v in row) for row in a))
        object.__setattr__(self, "_t", self.calibration.offset_ned)
        object.__setattr__(self, "_m", m)
        object.__setattr__(self, "_m_inv", tuple(tuple(m[j][i] for j in range(4)) for i in range(4)))

    def _arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``A``, ``t`` and ``M`` as numpy arrays, for the batch methods (built on first use)."""
        cached: tuple[FloatArray, FloatArray, FloatArray] | None = self.__dict__.get("_np")
        if cached is None:
            import numpy as np

            cached = (np.array(self._a), np.array(self._t), np.array(self._m))
            object.__setattr__(self, "_np", cached)
        return cached

    def position(self, p: Sequence[float]) -> Vec3:
        """Motive position → arena NED (m)."""
        x, y, z = p
        if not math.isfinite(x + y + z):
            raise FrameError(f"position has a non-finite component: {tuple(p)}")
        (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = self._a
        tn, te, td = self._t
        return (
            a00 * x + a01 * y + a02 * z + tn,
            a10 * x + a11 * y + a12 * z + te,
            a20 * x + a21 * y + a22 * z + td,
        )

    def quaternion(self, q: Sequence[float]) -> Quat:
        """Motive rigid-body quaternion → arena FRD quaternion (normalised, ``w >= 0``)."""
        return _apply_quat_map(self._m, q)

    def pose(self, p: Sequence[float], q: Sequence[float]) -> tuple[Vec3, Quat]:
        """One Motive pose → ``(p_ned, q_frd)`` in the arena frame. Fast path for a single body."""
        return self.position(p), _apply_quat_map(self._m, q)

    def poses(self, p: npt.ArrayLike, q: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Vectorised :meth:`pose`: ``P[N, 3]``, ``Q[N, 4]`` → arena ``(P[N, 3], Q[N, 4])``."""
        pa, qa = _check_batch(p, q)
        a, t, m = self._arrays()
        p_out = pa @ a.T + t
        q_out = _normalise_batch(qa @ m.T)
        return p_out, q_out

    def inverse_position(self, p: Sequence[float]) -> Vec3:
        """Arena NED position → Motive position (``A.T @ (p - t)``)."""
        if not math.isfinite(p[0] + p[1] + p[2]):
            raise FrameError(f"position has a non-finite component: {tuple(p)}")
        tn, te, td = self._t
        n, e, d = p[0] - tn, p[1] - te, p[2] - td
        (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = self._a
        return (
            a00 * n + a10 * e + a20 * d,
            a01 * n + a11 * e + a21 * d,
            a02 * n + a12 * e + a22 * d,
        )

    def inverse_pose(self, p: Sequence[float], q: Sequence[float]) -> tuple[Vec3, Quat]:
        """Arena ``(p_ned, q_frd)`` → Motive ``(p, q)`` (what the Motive emulator streams)."""
        return self.inverse_position(p), _apply_quat_map(self._m_inv, q)

    def inverse_poses(self, p: npt.ArrayLike, q: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Vectorised :meth:`inverse_pose`."""
        pa, qa = _check_batch(p, q)
        a, t, m = self._arrays()
        p_out = (pa - t) @ a
        q_out = _normalise_batch(qa @ m)
        return p_out, q_out


def _apply_quat_map(m: tuple[tuple[float, ...], ...], q: Sequence[float]) -> Quat:
    w, x, y, z = q
    n2 = w * w + x * x + y * y + z * z
    if not (abs(n2 - 1.0) <= 2.0 * _UNIT_TOLERANCE):  # also catches NaN
        raise FrameError(f"quaternion is not unit (norm² {n2}): {tuple(q)}")
    r0, r1, r2, r3 = m
    ow = r0[0] * w + r0[1] * x + r0[2] * y + r0[3] * z
    ox = r1[0] * w + r1[1] * x + r1[2] * y + r1[3] * z
    oy = r2[0] * w + r2[1] * x + r2[2] * y + r2[3] * z
    oz = r3[0] * w + r3[1] * x + r3[2] * y + r3[3] * z
    inv = 1.0 / math.sqrt(n2)
    if ow < 0.0:
        inv = -inv
    return (ow * inv, ox * inv, oy * inv, oz * inv)


def _check_batch(p: npt.ArrayLike, q: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    import numpy as np

    pa = np.asarray(p, dtype=np.float64)
    qa = np.asarray(q, dtype=np.float64)
    if pa.ndim != 2 or pa.shape[1] != 3:
        raise FrameError(f"positions must have shape (N, 3), got {pa.shape}")
    if qa.ndim != 2 or qa.shape[1] != 4:
        raise FrameError(f"quaternions must have shape (N, 4), got {qa.shape}")
    if len(pa) != len(qa):
        raise FrameError(f"got {len(pa)} positions but {len(qa)} quaternions")
    bad_p = ~np.isfinite(pa).all(axis=1)
    if bad_p.any():
        raise FrameError(f"position {int(np.argmax(bad_p))} has a non-finite component")
    n2 = (qa * qa).sum(axis=1)
    bad_q = ~(np.abs(n2 - 1.0) <= 2.0 * _UNIT_TOLERANCE)
    if bad_q.any():
        i = int(np.argmax(bad_q))
        raise FrameError(f"quaternion {i} is not unit (norm² {n2[i]}): {tuple(qa[i])}")
    return pa, qa


def _normalise_batch(q: FloatArray) -> FloatArray:
    import numpy as np

    scale = 1.0 / np.sqrt((q * q).sum(axis=1))
    scale = np.where(q[:, 0] < 0.0, -scale, scale)
    return np.asarray(q * scale[:, None], dtype=np.float64)
