"""The parity tier's rule (tests/px4/parity.py), checked without PX4: a figure within its tolerance of
PX4's passes, one PX4 varies passes within the spread of PX4's flights widened by the tolerance, and the
table says which rule judged it."""

from __future__ import annotations

from tests.px4.parity import FIGURES, apart, bounds, table, verdict

BY_NAME = {f.name: f for f in FIGURES}


def test_a_figure_is_judged_against_this_runs_px4_within_its_tolerance() -> None:
    takeoff = BY_NAME["takeoff_s"]  # 25 %, no absolute tolerance
    assert verdict(10.0, 12.5, takeoff, None) == (True, "±2.5")
    assert verdict(10.0, 12.6, takeoff, None)[0] is False
    assert verdict(10.0, float("nan"), takeoff, None)[0] is False


def test_a_figure_px4_varies_is_judged_against_the_spread_of_its_flights() -> None:
    coast = BY_NAME["exit_coast_cm"]  # 25 % or 5 cm
    assert bounds(16.9, (21.3, 13.6, 26.3, 21.3), coast) == (13.6 - 5.0, 26.3 + 0.25 * 26.3)
    ok, words = verdict(16.9, 27.4, coast, (21.3, 13.6, 26.3, 21.3))
    assert ok and words == "8.6–32.9: PX4's 5 flights, ± tolerance", words
    assert verdict(16.9, 33.0, coast, (21.3, 13.6, 26.3, 21.3))[0] is False
    assert verdict(16.9, 8.5, coast, (21.3, 13.6, 26.3, 21.3))[0] is False
    # A spread whose least figure is within its tolerance of zero starts at zero, not below it.
    assert bounds(4.1, (13.7, 8.2), coast) == (0.0, 13.7 + 5.0)
    # This run's PX4 figure widens the spread as an earlier flight does.
    assert verdict(40.0, 45.0, coast, (21.3, 13.6))[0] is True


def test_the_table_and_the_verdicts_agree() -> None:
    px4 = {f.name: 10.0 for f in FIGURES}
    sim = {**px4, "takeoff_s": 13.0, "exit_coast_cm": 30.0}
    varies = {"exit_coast_cm": (20.0, 25.0)}
    far = apart([px4], [sim], varies)
    assert len(far) == 1 and far[0].startswith(BY_NAME["takeoff_s"].words), far
    rows = {line.split(" | ")[0][2:]: line for line in table([px4], [sim], varies).splitlines()[2:]}
    assert len(rows) == len(FIGURES)
    assert rows[BY_NAME["takeoff_s"].words].endswith("| **no** (±2.5) |")
    coast = rows[BY_NAME["exit_coast_cm"].words]
    assert "| 10.0; earlier: 20.0, 25.0 |" in coast and coast.endswith(
        "| yes (5.0–31.2: PX4's 3 flights, ± tolerance) |"
    )
