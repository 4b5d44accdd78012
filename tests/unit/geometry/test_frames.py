"""Frame math: known vectors derived by hand for each Motive up axis, properties over random rotations,
calibration solving and the per-pose cost."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena_common.geometry.frames import (
    Calibration,
    CalibrationError,
    FrameError,
    FrameTransform,
    UpAxis,
    calibration_residuals,
    frd_to_motive,
    motive_to_frd,
    motive_to_ned,
    ned_to_motive,
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
    solve_calibration,
    wrap_angle,
)

C10, S10 = math.cos(math.radians(10)), math.sin(math.radians(10))
EX, EY, EZ = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


def close(a, b, tol=1e-9) -> bool:
    return bool(np.allclose(np.asarray(a, float), np.asarray(b, float), atol=tol, rtol=0))


def same_rotation(a, b, tol=1e-9) -> bool:
    return close(a, b, tol) or close(a, neg(b), tol)


def neg(v):
    return tuple(-c for c in v)


# --------------------------------------------------------------------------------------------------
# Quaternion helpers against hand-computed values
# --------------------------------------------------------------------------------------------------


def test_rotate_known_vectors() -> None:
    q = quat_from_axis_angle(EZ, math.pi / 2)  # +90° about z: x → y, y → −x
    assert close(quat_rotate(q, EX), EY)
    assert close(quat_rotate(q, EY), neg(EX))
    q = quat_from_axis_angle(EX, math.pi / 2)  # +90° about x: y → z
    assert close(quat_rotate(q, EY), EZ)
    q = quat_from_axis_angle(EY, math.pi / 2)  # +90° about y: z → x
    assert close(quat_rotate(q, EZ), EX)
    assert close(quat_to_matrix(quat_from_axis_angle(EZ, math.pi / 2)), [[0, -1, 0], [1, 0, 0], [0, 0, 1]])


def test_multiply_composes_right_to_left() -> None:
    yaw90 = quat_from_axis_angle(EZ, math.pi / 2)
    roll90 = quat_from_axis_angle(EX, math.pi / 2)
    # yaw ⊗ roll: roll first (y → z), then yaw leaves z alone.
    assert close(quat_rotate(quat_multiply(yaw90, roll90), EY), EZ)
    # roll ⊗ yaw: yaw first (x → y), then roll (y → z).
    assert close(quat_rotate(quat_multiply(roll90, yaw90), EX), EZ)
    assert close(quat_multiply(yaw90, quat_conjugate(yaw90)), (1, 0, 0, 0))


def test_euler_known_values() -> None:
    assert close(quat_from_euler(0, 0, math.pi / 2), (math.sqrt(0.5), 0, 0, math.sqrt(0.5)))
    # pitch 10° nose up in NED/FRD: forward gets a negative Down component
    assert close(quat_rotate(quat_from_euler(0, math.radians(10), 0), EX), (C10, 0, -S10))
    # roll 10° right wing down: right gets a positive Down component
    assert close(quat_rotate(quat_from_euler(math.radians(10), 0, 0), EY), (0, C10, S10))
    r, p, y = quat_to_euler(quat_from_euler(0.1, -0.2, 2.5))
    assert close((r, p, y), (0.1, -0.2, 2.5))
    assert quat_yaw(quat_from_yaw(-1.2)) == pytest.approx(-1.2)
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)


def test_from_matrix_rejects_non_rotations() -> None:
    with pytest.raises(FrameError, match="reflection"):
        quat_from_matrix(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(FrameError, match="orthonormal"):
        quat_from_matrix(np.eye(3) * 2)
    with pytest.raises(FrameError, match="3×3"):
        quat_from_matrix(np.eye(4))
    with pytest.raises(FrameError, match="zero quaternion"):
        quat_normalize((0, 0, 0, 0))
    with pytest.raises(FrameError, match="non-zero"):
        quat_from_axis_angle((0, 0, 0), 1.0)


# --------------------------------------------------------------------------------------------------
# Known vectors per up axis
# --------------------------------------------------------------------------------------------------

# For each case: the arena attitude as NED forward/right/down vectors, written by hand, and for each up
# axis the same three directions written by hand in Motive's coordinates
#   Y-up: x = N, y = Up, z = E;   Z-up: x = N, y = W, z = Up;   ENU: x = E, y = N, z = Up.
ARENA_CASES = {
    "identity": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "yaw90": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),
    "roll10": ((1, 0, 0), (0, C10, S10), (0, -S10, C10)),
    "pitch10": ((C10, 0, -S10), (0, 1, 0), (S10, 0, C10)),
}
EULER_CASES = {
    "identity": (0.0, 0.0, 0.0),
    "yaw90": (0.0, 0.0, math.pi / 2),
    "roll10": (math.radians(10), 0.0, 0.0),
    "pitch10": (0.0, math.radians(10), 0.0),
}
Axes = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
MOTIVE_CASES: dict[UpAxis, dict[str, Axes]] = {
    UpAxis.Y_UP: {
        "identity": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
        "yaw90": ((0, 0, 1), (-1, 0, 0), (0, -1, 0)),
        "roll10": ((1, 0, 0), (0, -S10, C10), (0, -C10, -S10)),
        "pitch10": ((C10, S10, 0), (0, 0, 1), (S10, -C10, 0)),
    },
    UpAxis.Z_UP: {
        "identity": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
        "yaw90": ((0, -1, 0), (-1, 0, 0), (0, 0, -1)),
        "roll10": ((1, 0, 0), (0, -C10, -S10), (0, S10, -C10)),
        "pitch10": ((C10, 0, S10), (0, -1, 0), (S10, 0, -C10)),
    },
    UpAxis.ENU: {
        "identity": ((0, 1, 0), (1, 0, 0), (0, 0, -1)),
        "yaw90": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
        "roll10": ((0, 1, 0), (C10, 0, -S10), (-S10, 0, -C10)),
        "pitch10": ((0, C10, S10), (1, 0, 0), (0, S10, -C10)),
    },
}


def motive_body_matrix(up: UpAxis, fwd, right, down) -> np.ndarray:
    """Rotation matrix of a Motive rigid body whose F/R/D directions (Motive coordinates) are given.

    Motive rigid bodies take the world axes as theirs: Y-up bodies are (x fwd, y up, z right), Z-up and
    ENU bodies are FLU (x fwd, y left, z up). Columns are the body axes in world coordinates.
    """
    f, r, d = (np.asarray(v, float) for v in (fwd, right, down))
    cols = (f, -d, r) if up is UpAxis.Y_UP else (f, -r, -d)
    return np.column_stack(cols)


@pytest.mark.parametrize("up", list(UpAxis))
@pytest.mark.parametrize("case", list(ARENA_CASES))
def test_known_attitudes(up: UpAxis, case: str) -> None:
    f_ned, r_ned, d_ned = ARENA_CASES[case]
    f_m, r_m, d_m = MOTIVE_CASES[up][case]
    assert close(np.cross(f_m, r_m), d_m, 1e-12), "hand-written Motive axes must be right-handed FRD"
    q_motive = quat_from_matrix(motive_body_matrix(up, f_m, r_m, d_m))
    ft = FrameTransform(up)
    _, q = ft.pose((0.0, 0.0, 0.0), q_motive)
    assert close(quat_rotate(q, EX), f_ned), "forward"
    assert close(quat_rotate(q, EY), r_ned), "right"
    assert close(quat_rotate(q, EZ), d_ned), "down"
    assert same_rotation(q, quat_from_euler(*EULER_CASES[case]))
    # the same directions taken as positions land on the same NED vectors
    assert (
        close(ft.position(f_m), f_ned) and close(ft.position(r_m), r_ned) and close(ft.position(d_m), d_ned)
    )
    # explicit per-axis formulas of the brief agree
    assert same_rotation(quat_normalize(motive_to_frd(q_motive, up)), q)
    assert close(motive_to_ned(f_m, up), f_ned)


def test_body_created_facing_north_reads_identity() -> None:
    # Y-up and Z-up: a body created in Motive has the identity orientation and faces Motive +x = North.
    for up in (UpAxis.Y_UP, UpAxis.Z_UP):
        assert close(FrameTransform(up).quaternion((1, 0, 0, 0)), (1, 0, 0, 0))
    # ENU: created facing +x = East it reads yaw 90°; facing North it is yawed +90° about Up in ENU
    enu = FrameTransform(UpAxis.ENU)
    assert same_rotation(enu.quaternion((1, 0, 0, 0)), quat_from_yaw(math.pi / 2))
    assert close(enu.quaternion(quat_from_axis_angle(EZ, math.pi / 2)), (1, 0, 0, 0))


# Mixed attitude: the Motive side is built from elementary rotations about Motive's own axes, with the
# sign each up axis needs (heading clockwise from above; nose up; right wing down).
def _rx(a):
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def _ry(a):
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _rz(a):
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


@pytest.mark.parametrize("up", list(UpAxis))
def test_mixed_attitude(up: UpAxis) -> None:
    roll, pitch, yaw = math.radians(-15), math.radians(20), math.radians(130)
    if up is UpAxis.Y_UP:  # up = +y, right = +z, forward = +x
        r_m = _ry(-yaw) @ _rz(pitch) @ _rx(roll)
    elif up is UpAxis.Z_UP:  # up = +z, left = +y
        r_m = _rz(-yaw) @ _ry(-pitch) @ _rx(roll)
    else:  # ENU: heading measured from +y (North) clockwise, body FLU
        r_m = _rz(math.pi / 2 - yaw) @ _ry(-pitch) @ _rx(roll)
    expected_ned = _rz(yaw) @ _ry(pitch) @ _rx(roll)
    _, q = FrameTransform(up).pose((0, 0, 0), quat_from_matrix(r_m))
    assert close(quat_to_matrix(q), expected_ned)
    assert close(quat_to_euler(q), (roll, pitch, yaw))


def test_up_axes_agree_on_one_physical_pose() -> None:
    # One physical pose seen in Y-up; Z-up coordinates are (x, −z, y); ENU = Z-up yawed by +90°.
    q_y = quat_from_axis_angle((0.2, 0.9, -0.3), 1.3)
    p_y = (1.5, 0.8, -2.0)
    r_yz = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # Y-up → Z-up coordinates
    q_yz = quat_from_matrix(r_yz)
    p_z = tuple(r_yz @ p_y)
    q_z = quat_multiply(quat_multiply(q_yz, q_y), quat_conjugate(q_yz))  # same body convention change
    a = FrameTransform(UpAxis.Y_UP).pose(p_y, q_y)
    b = FrameTransform(UpAxis.Z_UP).pose(p_z, q_z)
    # Y-up bodies are (fwd, up, right) and Z-up bodies (fwd, left, up): the x axis is forward in both.
    assert close(a[0], b[0])
    assert close(quat_rotate(a[1], EX), quat_rotate(b[1], EX))
    enu_as_z = FrameTransform(UpAxis.Z_UP, Calibration(math.pi / 2))
    p, q = (0.3, -1.0, 2.0), quat_from_axis_angle((1, 2, 3), 0.7)
    e = FrameTransform(UpAxis.ENU).pose(p, q)
    z = enu_as_z.pose(p, q)
    assert close(e[0], z[0]) and same_rotation(e[1], z[1])


def test_enu_formula_is_exact_not_only_up_to_sign() -> None:
    # The brief's ENU quaternion formula √½·(w+z, x+y, x−y, w−z) equals c ⊗ q ⊗ b* for the world change
    # c (π about (1,1,0)/√2) and body change b (π about x) — checked against that composition directly.
    s = math.sqrt(0.5)
    c, b = (0.0, s, s, 0.0), (0.0, 1.0, 0.0, 0.0)
    q = quat_from_axis_angle((0.4, -0.1, 0.9), 2.2)
    direct = quat_multiply(quat_multiply(c, q), quat_conjugate(b))
    assert close(motive_to_frd(q, UpAxis.ENU), direct)


# --------------------------------------------------------------------------------------------------
# Properties over random rotations
# --------------------------------------------------------------------------------------------------

unit = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(unit, unit, unit, unit).filter(lambda q: sum(c * c for c in q) > 0.01).map(quat_normalize)
coords = st.floats(-20.0, 20.0, allow_nan=False)
points = st.tuples(coords, coords, coords)
calibrations = st.builds(Calibration, st.floats(-math.pi, math.pi), points)
ups = st.sampled_from(list(UpAxis))

BODY_FRD_IN_MOTIVE_BODY = {  # which Motive body axis is F, R, D
    UpAxis.Y_UP: (EX, EZ, neg(EY)),
    UpAxis.Z_UP: (EX, neg(EY), neg(EZ)),
    UpAxis.ENU: (EX, neg(EY), neg(EZ)),
}


@settings(max_examples=150, deadline=None)
@given(q=quats)
def test_matrix_properties(q) -> None:
    r = quat_to_matrix(q)
    assert close(r.T @ r, np.eye(3), 1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    assert same_rotation(quat_from_matrix(r), q, 1e-9)
    v = (0.3, -1.2, 2.0)
    assert close(r @ v, quat_rotate(q, v), 1e-12)


@settings(max_examples=150, deadline=None)
@given(q=quats)
def test_euler_round_trip(q) -> None:
    roll, pitch, yaw = quat_to_euler(q)
    if abs(abs(pitch) - math.pi / 2) > 1e-3:  # away from gimbal lock
        assert same_rotation(quat_from_euler(roll, pitch, yaw), q, 1e-9)


@settings(max_examples=200, deadline=None)
@given(up=ups, cal=calibrations, p=points, q=quats)
def test_transform_round_trip_and_axes(up, cal, p, q) -> None:
    ft = FrameTransform(up, cal)
    pa, qa = ft.pose(p, q)
    assert math.sqrt(sum(c * c for c in qa)) == pytest.approx(1.0, abs=1e-12)
    assert qa[0] >= 0.0
    pm, qm = ft.inverse_pose(pa, qa)
    assert close(pm, p, 1e-9) and same_rotation(qm, q, 1e-12)
    # every body axis ends where the point map sends the same Motive direction
    origin = ft.position((0, 0, 0))
    for axis_frd, axis_motive_body in zip((EX, EY, EZ), BODY_FRD_IN_MOTIVE_BODY[up], strict=True):
        tip = ft.position(quat_rotate(q, axis_motive_body))
        assert close(np.subtract(tip, origin), quat_rotate(qa, axis_frd), 1e-9)
    # yaw only rotates about Down: the Down component of positions is the Motive up axis plus offset
    assert pa[2] == pytest.approx(motive_to_ned(p, up)[2] + cal.offset_ned[2], abs=1e-9)


@settings(max_examples=100, deadline=None)
@given(up=ups, p=points, q=quats)
def test_explicit_formulas_match_transform(up, p, q) -> None:
    ft = FrameTransform(up)
    pa, qa = ft.pose(p, q)
    assert close(motive_to_ned(p, up), pa, 1e-12)
    assert same_rotation(motive_to_frd(q, up), qa, 1e-12)
    assert close(ned_to_motive(pa, up), p, 1e-12)
    assert same_rotation(frd_to_motive(qa, up), q, 1e-12)


@settings(max_examples=50, deadline=None)
@given(up=ups, cal=calibrations, data=st.lists(st.tuples(points, quats), min_size=1, max_size=8))
def test_vectorised_matches_scalar(up, cal, data) -> None:
    ft = FrameTransform(up, cal)
    p = np.array([d[0] for d in data])
    q = np.array([d[1] for d in data])
    pa, qa = ft.poses(p, q)
    for i, (pi, qi) in enumerate(data):
        sp, sq = ft.pose(pi, qi)
        assert close(pa[i], sp, 1e-9) and close(qa[i], sq, 1e-12)
    pm, qm = ft.inverse_poses(pa, qa)
    assert close(pm, p, 1e-9)
    for i in range(len(data)):
        assert same_rotation(qm[i], q[i], 1e-12)


def test_transform_rejects_bad_input() -> None:
    ft = FrameTransform("Y-up")  # type: ignore[arg-type]
    assert ft.up_axis is UpAxis.Y_UP
    with pytest.raises(FrameError, match="not unit"):
        ft.pose((0, 0, 0), (0, 0, 0, 0))
    with pytest.raises(FrameError, match="not unit"):
        ft.pose((0, 0, 0), (math.nan, 0, 0, 1))
    with pytest.raises(FrameError, match="non-finite"):
        ft.pose((0, math.inf, 0), (1, 0, 0, 0))
    with pytest.raises(FrameError, match=r"shape \(N, 4\)"):
        ft.poses(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(FrameError, match="quaternion 1 is not unit"):
        ft.poses(np.zeros((2, 3)), [[1, 0, 0, 0], [2, 0, 0, 0]])
    with pytest.raises(FrameError, match="unknown up axis"):
        UpAxis.parse("x_up")
    assert UpAxis.parse("Z") is UpAxis.Z_UP and UpAxis.parse("ENU") is UpAxis.ENU


# --------------------------------------------------------------------------------------------------
# Calibration
# --------------------------------------------------------------------------------------------------


def test_calibration_order_by_hand() -> None:
    cal = Calibration.from_degrees(90.0, (1.0, 0.0, -0.5))
    # rotate (North → East) first, then add the offset
    assert close(cal.apply_position((1.0, 0.0, 2.0)), (1.0, 1.0, 1.5))
    assert close(cal.inverse_position((1.0, 1.0, 1.5)), (1.0, 0.0, 2.0))
    assert same_rotation(cal.apply_quaternion((1, 0, 0, 0)), quat_from_yaw(math.pi / 2))
    assert same_rotation(cal.inverse_quaternion(quat_from_yaw(math.pi / 2)), (1, 0, 0, 0))
    back = Calibration.from_dict(cal.to_dict())
    assert back.yaw_rad == pytest.approx(cal.yaw_rad) and close(back.offset_ned, cal.offset_ned)
    ft = FrameTransform(UpAxis.Y_UP, cal)
    # Motive Y-up (1, -2, 0) is NED (1, 0, 2) before calibration
    assert close(ft.position((1.0, -2.0, 0.0)), (1.0, 1.0, 1.5))


def test_calibration_rejects_bad_values() -> None:
    with pytest.raises(FrameError, match="yaw"):
        Calibration(math.nan)
    with pytest.raises(FrameError, match="3 components"):
        Calibration(0.0, (1.0, 2.0))  # type: ignore[arg-type]
    with pytest.raises(FrameError, match="unknown calibration keys"):
        Calibration.from_dict({"yaw": 3})


def test_solve_calibration_recovers_random_transforms() -> None:
    rng = np.random.default_rng(7)
    for _ in range(50):
        truth = Calibration(rng.uniform(-math.pi, math.pi), tuple(rng.uniform(-3, 3, 3)))
        n = int(rng.integers(2, 9))
        known = np.column_stack([rng.uniform(-3.5, 3.5, n), rng.uniform(-2, 2, n), rng.uniform(-2, 0, n)])
        known[1, :2] = known[0, :2] + (1.0, 0.5)  # at least two points well apart
        measured = np.array([truth.inverse_position(k) for k in known]) + rng.normal(0, 0.001, (n, 3))
        got = solve_calibration(measured, known)
        assert abs(wrap_angle(got.yaw_rad - truth.yaw_rad)) < math.radians(0.3)
        assert close(got.offset_ned, truth.offset_ned, 0.006)
        assert calibration_residuals(got, measured, known).max() < 0.006


def test_solve_calibration_least_squares_beats_perturbations() -> None:
    rng = np.random.default_rng(3)
    known = rng.uniform(-3, 3, (6, 3))
    measured = known + rng.normal(0, 0.05, (6, 3))
    best = solve_calibration(measured, known)
    cost = float((calibration_residuals(best, measured, known) ** 2).sum())
    for dyaw, dn in ((1e-3, 0), (-1e-3, 0), (0, 1e-3), (0, -1e-3)):
        other = Calibration(best.yaw_rad + dyaw, np.add(best.offset_ned, (dn, 0, 0)))  # type: ignore[arg-type]
        assert float((calibration_residuals(other, measured, known) ** 2).sum()) > cost


@pytest.mark.parametrize(
    ("measured", "known", "match"),
    [
        ([(0, 0, 0)], [(1, 1, 1)], "at least 2"),
        ([(0, 0, 0), (1, 0, 0)], [(0, 0, 0)], "2 measured points but 1"),
        ([(0, 0, 0), (0, 0, 1)], [(0, 0, 0), (1, 0, 0)], "measured points are horizontally coincident"),
        ([(0, 0, 0), (1, 0, 0)], [(0, 0, 0), (0.001, 0, 0)], "known arena points are horizontally"),
        ([(0, 0, math.nan), (1, 0, 0)], [(0, 0, 0), (1, 0, 0)], "non-finite"),
        ([(0, 0), (1, 0)], [(0, 0, 0), (1, 0, 0)], r"\(n, e, d\)"),
    ],
)
def test_solve_calibration_degenerate(measured, known, match) -> None:
    with pytest.raises(CalibrationError, match=match):
        solve_calibration(measured, known)
    assert issubclass(CalibrationError, ValueError)


# --------------------------------------------------------------------------------------------------
# Cost
# --------------------------------------------------------------------------------------------------


def test_single_pose_is_cheap() -> None:
    ft = FrameTransform(UpAxis.Y_UP, Calibration.from_degrees(12.0, (0.1, 0.2, 0.0)))
    p, q = (0.1, 1.0, -0.3), quat_from_axis_angle((0.1, 1.0, 0.2), 0.4)
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(2000):
            ft.pose(p, q)
        best = min(best, (time.perf_counter() - t0) / 2000)
    assert best < 10e-6, f"{best * 1e6:.2f} µs per pose"


def test_quat_angle() -> None:
    a = quat_from_yaw(0.2)
    assert quat_angle(a, quat_from_yaw(0.5)) == pytest.approx(0.3)
    assert quat_angle(a, neg(a)) == pytest.approx(0.0, abs=1e-7)
    assert quat_canonical(neg(a)) == pytest.approx(a)
