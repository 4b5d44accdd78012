"""Arrival: the position averaged over a window, within a tolerance (arena_common.core.arrival)."""

from __future__ import annotations

import math

import pytest

from arena_common.core.arrival import ARRIVAL_TOLERANCE, ARRIVAL_WINDOW, Arrival


def _swing(t: float, amplitude: float, period: float = 7.5) -> tuple[float, float, float]:
    """A hover swinging east-west about (1, 0, -1), as PX4's does (docs/px4.md: ~7.5 s, ±0.3 m)."""
    return (1.0, amplitude * math.sin(2 * math.pi * t / period), -1.0)


def test_a_hover_swinging_as_px4s_arrives_where_an_instant_within_10_cm_may_not() -> None:
    judge = Arrival((1.0, 0.0, -1.0))
    arrived_at = None
    for k in range(0, 1500):  # 15 s at 100 Hz
        t = k / 100.0
        judge.add(t, _swing(t, 0.3))
        if arrived_at is None and judge.arrived():
            arrived_at = t
    assert arrived_at is not None and arrived_at <= 2 * ARRIVAL_WINDOW + 0.1
    # the same swing, judged at one instant within 10 cm, holds for only a quarter of the time
    within = sum(abs(_swing(k / 100.0, 0.3)[1]) <= 0.1 for k in range(1500))
    assert within < 0.25 * 1500


def test_passing_through_the_goal_never_counts() -> None:
    judge = Arrival((0.0, 0.0, -1.0), tolerance=0.1)
    for k in range(0, 400):  # flying north at 1 m/s through the goal, never stopping
        t = k / 100.0
        judge.add(t, (t - 2.0, 0.0, -1.0))
        assert not judge.arrived() or abs(t - 2.0) < 0.6  # averaged behind the vehicle: 0.5 m at 1 m/s
    assert not judge.arrived()


def test_a_vehicle_held_away_fails_naming_how_far() -> None:
    judge = Arrival((0.0, 0.0, -1.0))
    for k in range(0, 300):
        judge.add(k / 100.0, (0.8, 0.0, -1.0))
    assert judge.covered() and not judge.arrived()
    assert judge.describe().startswith("0.80 m from it")
    assert f"tolerance {ARRIVAL_TOLERANCE:.2f} m" in judge.describe()


def test_a_lost_position_starts_the_window_again() -> None:
    judge = Arrival((0.0, 0.0, -1.0))
    for k in range(0, 90):
        judge.add(k / 100.0, (0.0, 0.0, -1.0))
    judge.add(0.9, None)
    assert judge.describe() == "no valid position"
    for k in range(91, 180):
        judge.add(k / 100.0, (0.0, 0.0, -1.0))
    assert not judge.arrived()  # 0.88 s of positions since the gap: not yet a whole window
    judge.add(1.92, (0.0, 0.0, -1.0))
    assert judge.arrived()


def test_height_alone() -> None:
    judge = Arrival((0.0, 0.0, -1.0), 0.15, axes=(2,))
    for k in range(0, 200):
        judge.add(k / 100.0, (3.0, -2.0, -0.9))  # far away horizontally, 10 cm low
    assert judge.arrived()


@pytest.mark.parametrize("tolerance", [0.0, -1.0, math.nan, math.inf])
def test_a_tolerance_must_be_a_positive_distance(tolerance: float) -> None:
    with pytest.raises(ValueError, match="positive distance"):
        Arrival((0.0, 0.0, 0.0), tolerance)
