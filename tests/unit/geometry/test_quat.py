"""The one quaternion module: the fast paths agree with the checked ones."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from arena_common.geometry.quat import (
    FrameError,
    quat_angle,
    quat_canonical,
    quat_from_axes,
    quat_from_euler,
    quat_from_matrix,
    quat_rotate,
    quat_rotate_inverse,
    quat_to_matrix,
)

angle = st.floats(-math.pi, math.pi)
half = st.floats(-1.5, 1.5)


@given(angle, half, angle)
def test_from_axes_equals_the_checked_matrix_path(roll: float, pitch: float, yaw: float) -> None:
    q = quat_from_euler(roll, pitch, yaw)
    m = quat_to_matrix(q)
    cols = [tuple(float(m[i][j]) for i in range(3)) for j in range(3)]
    fast = quat_from_axes(*cols)
    checked = quat_from_matrix(m)
    assert fast == pytest.approx(checked, abs=1e-9)
    assert fast[0] >= 0.0 and quat_angle(fast, quat_canonical(q)) < 1e-6


@given(angle, half, angle, st.tuples(*[st.floats(-10, 10)] * 3))
def test_rotate_inverse_undoes_rotate(roll: float, pitch: float, yaw: float, v: tuple[float, ...]) -> None:
    q = quat_from_euler(roll, pitch, yaw)
    assert quat_rotate_inverse(q, quat_rotate(q, v)) == pytest.approx(v, abs=1e-9)


def test_known_vectors() -> None:
    q = quat_from_euler(0.0, 0.0, math.pi / 2)  # yaw 90°: body forward points east (NED)
    assert quat_rotate(q, (1.0, 0.0, 0.0)) == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)
    assert quat_rotate_inverse(q, (0.0, 1.0, 0.0)) == pytest.approx((1.0, 0.0, 0.0), abs=1e-12)
    with pytest.raises(FrameError, match="reflection"):
        quat_from_matrix([[1, 0, 0], [0, 1, 0], [0, 0, -1]])
