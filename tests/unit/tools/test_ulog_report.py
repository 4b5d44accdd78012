"""tools/ulog_report.py on synthetic PX4 topics: a known lag, offset, hover wobble and offboard error."""

from __future__ import annotations

import numpy as np
import pytest

from tools.ulog_report import (
    ARMED,
    NAV_AUTO_LOITER,
    NAV_OFFBOARD,
    analyse,
    best_lag,
    main,
    render,
    spread,
    timesync_error,
    timesync_start,
)

NAV_TAKEOFF = 17


def _flight(lag_s: float = 0.2, vision_lag_s: float = 0.0) -> dict[str, dict[str, np.ndarray]]:
    """60 s at 250 Hz: 10 s on the ground, 4 s climb to 1 m, Hold wobbling ±0.1 m east (period 7 s) until 35 s,
    then offboard 1 m north over 40-50 s (truth 0.05 m short), Hold; the estimate trails the truth
    by ``lag_s`` in a frame 1 m south of SIH's, the vision PX4 gets trails it by ``vision_lag_s``."""
    t = np.arange(0.0, 60.0, 0.004)

    def truth(ts: np.ndarray) -> np.ndarray:
        up = np.clip((ts - 10.0) / 4.0, 0.0, 1.0)
        east = np.where((ts > 14.0) & (ts < 35.0), 0.1 * np.sin(2 * np.pi * (ts - 14.0) / 7.0), 0.0)
        north = np.clip((ts - 40.0) / 5.0, 0.0, 1.0) * 0.95
        return np.stack([north, east, -up], axis=1)

    us = (t * 1e6).astype(np.int64)
    gt = truth(t)
    est = truth(t - lag_s) + np.array([-1.0, 0.0, 0.0])
    vis = truth(t - vision_lag_s) + np.array([-1.0, 0.0, 0.0])
    sp_north = np.clip((t - 40.0) / 5.0, 0.0, 1.0) * 1.0 - 1.0
    status_t = np.array([0.0, 9.0, 10.0, 15.0, 40.0, 50.0]) * 1e6
    return {
        "vehicle_local_position": {"timestamp": us, "x": est[:, 0], "y": est[:, 1], "z": est[:, 2]},
        "vehicle_local_position_groundtruth": {"timestamp": us, "x": gt[:, 0], "y": gt[:, 1], "z": gt[:, 2]},
        "vehicle_status": {
            "timestamp": status_t,
            "nav_state": np.array(
                [NAV_AUTO_LOITER, NAV_AUTO_LOITER, NAV_TAKEOFF, NAV_AUTO_LOITER, NAV_OFFBOARD, 4]
            ),
            "arming_state": np.array([1, ARMED, ARMED, ARMED, ARMED, ARMED]),
        },
        "vehicle_visual_odometry": {
            "timestamp": us + np.where(t > 30.0, 10_000, 0),  # TIMESYNC converged at 30 s
            "timestamp_sample": us,
            "position[0]": vis[:, 0],
            "position[1]": vis[:, 1],
            "position[2]": vis[:, 2],
        },
        "estimator_aid_src_ev_pos": {
            "timestamp": us,
            "fused": np.ones(len(t), bool),
            "innovation[0]": np.full(len(t), 0.01),
            "innovation[1]": np.full(len(t), -0.01),
            "test_ratio[0]": np.linspace(0, 0.1, len(t)),
            "test_ratio[1]": np.zeros(len(t)),
        },
        "trajectory_setpoint": {
            "timestamp": us,
            "position[0]": sp_north,
            "position[1]": np.zeros(len(t)),
            "position[2]": np.full(len(t), -1.0),
        },
    }


def test_best_lag_spread_and_timesync_start() -> None:
    t = np.arange(0.0, 10.0, 0.01) * 1e6
    ref = np.stack([np.sin(t * 1e-6), np.cos(t * 1e-6)], axis=1)
    late = np.stack([np.sin(t * 1e-6 - 0.15), np.cos(t * 1e-6 - 0.15)], axis=1)
    lag = best_lag(t, late, t, ref)
    assert lag is not None and lag.ms == 150 and lag.rms_m < 1e-3 < lag.rms0_m
    assert best_lag(t[:5], late[:5], t, ref) is None
    assert spread(np.array([[0.0, 0, 0], [0.1, 0, 0], [0.3, 0, 0]])) == pytest.approx((0.1, 0.2))
    arrival = np.array([1e6, 2e6, 3e6, 4e6])
    assert timesync_start(arrival, arrival) is None
    assert timesync_start(arrival, arrival - np.array([0, 0, 5000, 5000])) == 3.0


def test_analyse_finds_hover_lags_and_offboard_errors() -> None:
    report = analyse(_flight(lag_s=0.2, vision_lag_s=0.01))
    assert report.hover_s == pytest.approx((19.0, 29.0), abs=0.01)  # Hold from 15 s, at height: + 4 s
    assert report.hover_height_m == pytest.approx(1.0)
    assert 0.1 <= report.hover_xy_max_m < 0.2  # ±0.1 m east, from the median of 10 s of a 7 s period
    assert report.estimate_vs_truth is not None and report.estimate_vs_truth.ms == 200
    assert report.estimate_vs_vision is not None and report.estimate_vs_vision.ms == pytest.approx(190, abs=5)
    assert report.vision_vs_truth is not None and report.vision_vs_truth.ms == 10
    assert report.innovation_source == "ev" and report.innovation_rms_m == pytest.approx(0.01)
    assert report.test_ratio_p95 == pytest.approx(0.095, abs=0.001)
    assert report.timesync_from_s == pytest.approx(30.014, abs=0.001)  # its arrival
    assert report.offboard_s == pytest.approx((40.0, 50.0))
    assert report.offboard_end_p50_m == pytest.approx(0.05, abs=0.002)  # 0.95 m of the 1 m
    assert 0.049 < (report.offboard_max_m or 0) < 0.13
    # 5 % short along the 5 s ramp, then 5 cm for 5 s: sqrt((0.05² · 5/3 + 0.05² · 5) / 10)
    assert report.offboard_rms_m == pytest.approx(0.05 * (2 / 3) ** 0.5, abs=0.002)
    assert "200 ms behind" in render(report)
    # A given hover window is used as it is.
    assert analyse(_flight(), hover=(30.0, 31.0)).hover_s == pytest.approx((30.0, 31.0))


def test_no_hover_found_and_a_bad_file_are_errors(
    tmp_path: object, capsys: pytest.CaptureFixture[str]
) -> None:
    flight = _flight()
    flight["vehicle_status"]["arming_state"][:] = 1  # never armed
    with pytest.raises(ValueError, match="no hover"):
        analyse(flight)
    assert main(["/nonexistent/flight.ulg"]) == 1
    assert "ulog_report:" in capsys.readouterr().err


def _px4_timesync_drifts(flight: dict[str, dict[str, np.ndarray]]) -> None:
    """PX4's TIMESYNC estimate leaves the answers from 30 s on (converged there): its stamps drift to 40 ms
    early at 60 s, as after a change of SITL's clock rate; ``timesync_status`` logged at 1 Hz, two answers
    of a round trip over 10 ms (not taken by PX4) far off."""
    vo = flight["vehicle_visual_odometry"]
    true_stamp = vo["timestamp_sample"].astype(float)
    error_us = np.where(true_stamp > 30e6, -40_000.0 * (true_stamp - 30e6) / 30e6, 0.0)
    vo["timestamp_sample"] = np.where(true_stamp > 30e6, true_stamp + error_us, true_stamp).astype(np.int64)
    vo["timestamp"] = np.where(true_stamp > 30e6, true_stamp + 10_000, true_stamp).astype(np.int64)
    t = np.arange(0.0, 60.0, 1.0)
    observed = 5e6 - 8_000.0 * t + np.tile([-1500.0, 0.0, 1500.0], 20)  # SITL 0.8 % slow, jitter
    error = np.where(t > 30.0, -40_000.0 * (t - 30.0) / 30.0, 0.0)
    rtt = np.zeros(len(t))
    rtt[[40, 50]] = 20_000.0
    observed[[40, 50]] += 300_000.0
    flight["timesync_status"] = {
        "timestamp": (t * 1e6).astype(np.int64),
        "remote_timestamp": (t * 1e6 + 1e9).astype(np.int64),
        "observed_offset": observed.astype(np.int64),
        "estimated_offset": (observed + error).astype(np.int64),
        "round_trip_time": rtt.astype(np.int64),
    }


def test_vision_lag_with_pxs_timesync_error_taken_out() -> None:
    flight = _flight(lag_s=0.2, vision_lag_s=0.01)
    _px4_timesync_drifts(flight)
    report = analyse(flight)
    # As PX4 stamped it: the vision looks earlier than it is, PX4's mapping error mixed in.
    assert report.vision_vs_truth is not None and report.vision_vs_truth.ms <= 5
    # With PX4's own error (its estimate minus its answers) taken out: the vision's true 10 ms.
    assert report.vision_vs_truth_synced is not None and report.vision_vs_truth_synced.ms == pytest.approx(
        10, abs=1
    )
    assert report.timesync_error_ms is not None
    p50, largest = report.timesync_error_ms
    assert -30 < p50 < -10 and 35 < largest <= 40
    assert "TIMESYNC error taken out: 10 ms behind" in render(report)
    found = timesync_error(flight["timesync_status"])
    assert found is not None and len(found[0]) == 58  # the two slow answers left out
    # Without timesync_status (an older log), no synced figure.
    del flight["timesync_status"]
    assert analyse(flight).vision_vs_truth_synced is None
