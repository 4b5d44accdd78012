"""Pose filters: time-based decimation, velocity estimation, jump rejection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from arena_common.geometry.filters import (
    FilterError,
    JumpGate,
    RejectReason,
    TimeDecimator,
    VelocityEstimator,
)
from arena_common.geometry.frames import quat_from_axis_angle, quat_from_euler, quat_from_yaw, quat_multiply

MS = 1_000_000  # ns


def jittery_times(
    rate_hz: float, seconds: float, jitter_s: float, seed: int, start_ns: int = 10**12
) -> list[int]:
    rng = np.random.default_rng(seed)
    n = int(rate_hz * seconds)
    nominal = np.arange(n) / rate_hz
    t = nominal + rng.uniform(-jitter_s, jitter_s, n)
    return [start_ns + round(x * 1e9) for x in np.sort(t)]


def run(dec: TimeDecimator, times: list[int]) -> list[int]:
    return [t for t in times if dec.offer(t)]


# --------------------------------------------------------------------------------------------------
# TimeDecimator
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("target", [50.0, 30.0])
def test_decimate_180_jittery(target: float) -> None:
    times = jittery_times(180.0, 20.0, 0.0005, seed=1)
    out = run(TimeDecimator(target), times)
    duration = (out[-1] - out[0]) * 1e-9
    rate = (len(out) - 1) / duration
    assert rate == pytest.approx(target, rel=0.02)
    gaps = np.diff(out) * 1e-9
    in_period = 1 / 180
    # spacing can only be quantised to the input samples: within one input interval (+ jitter) of the period
    assert gaps.min() > 1 / target - in_period - 0.0011
    assert gaps.max() < 1 / target + in_period + 0.0011
    assert len(set(out)) == len(out)


def test_decimate_180_to_60_is_steady() -> None:
    # 60 Hz is every third 180 Hz sample: jitter around the slot must not alternate 11 ms / 22 ms gaps.
    times = jittery_times(180.0, 10.0, 0.0008, seed=2)
    dec = TimeDecimator(60.0)
    out = run(dec, times)
    gaps = np.diff(out) * 1e-9
    assert (len(out) - 1) / ((out[-1] - out[0]) * 1e-9) == pytest.approx(60.0, rel=0.02)
    assert np.abs(gaps - 1 / 60).max() < 0.0017  # at most twice the jitter
    assert dec.emitted == len(out) and dec.offered == len(times)


def test_decimator_never_repeats_and_refuses_old_samples() -> None:
    dec = TimeDecimator(50.0)
    assert dec.offer(1_000 * MS)
    assert not dec.offer(1_000 * MS)  # same sample again
    assert not dec.offer(990 * MS)  # older
    assert dec.offer(1_020 * MS)
    assert not dec.offer(1_020 * MS)
    # a stream that repeats every sample twice still emits each at most once
    dec = TimeDecimator(90.0)
    times = [t for t in jittery_times(180.0, 2.0, 0.0, seed=3) for _ in range(2)]
    out = run(dec, times)
    assert len(out) == len(set(out)) and out == sorted(out)


def test_silence_re_anchors_without_burst() -> None:
    dec = TimeDecimator(50.0)
    first = jittery_times(180.0, 1.0, 0.0003, seed=4, start_ns=0)
    second = jittery_times(180.0, 1.0, 0.0003, seed=5, start_ns=3_000 * MS)  # 2 s of silence
    out1 = run(dec, first)
    out2 = run(dec, second)
    assert out1[-1] < 1_000 * MS and out2[0] == second[0]  # resumes with the first sample after silence
    gaps = np.diff(out2) * 1e-9
    assert gaps.min() > 0.02 - 1 / 180 - 0.0007  # no catch-up burst
    assert len(out2) == pytest.approx(50, abs=2)
    # short dropout (a few samples lost, less than a period) keeps the phase
    dec = TimeDecimator(50.0)
    times = [t for t in jittery_times(180.0, 2.0, 0.0, seed=6) if not 500 * MS < t % 10**12 < 512 * MS]
    gaps = np.diff(run(dec, times)) * 1e-9
    assert gaps.min() > 0.02 - 1 / 180 - 1e-6


def test_slow_input_passes_everything() -> None:
    times = jittery_times(30.0, 3.0, 0.002, seed=7)
    assert run(TimeDecimator(50.0), times) == times


def test_rate_change_at_run_time() -> None:
    dec = TimeDecimator(50.0)
    times = jittery_times(240.0, 20.0, 0.0003, seed=8)
    half = len(times) // 2
    out1 = run(dec, times[:half])
    dec.set_rate(20.0)
    assert dec.rate_hz == 20.0 and dec.period_ns == 50 * MS
    out2 = run(dec, times[half:])
    assert (len(out1) - 1) / ((out1[-1] - out1[0]) * 1e-9) == pytest.approx(50.0, rel=0.02)
    assert (len(out2) - 1) / ((out2[-1] - out2[0]) * 1e-9) == pytest.approx(20.0, rel=0.02)
    assert (out2[0] - out1[-1]) * 1e-9 == pytest.approx(0.05, abs=1 / 240 + 0.001)


def test_source_clock_restart_starts_new_schedule() -> None:
    dec = TimeDecimator(50.0)
    assert dec.offer(100_000 * MS)
    assert not dec.offer(99_999 * MS)  # slightly back: refused
    assert dec.offer(5 * MS)  # far back: the source restarted
    assert not dec.offer(10 * MS)
    assert dec.offer(25 * MS)


def test_decimator_rejects_bad_rates() -> None:
    for bad in (0.0, -5.0, math.nan, math.inf):
        with pytest.raises(FilterError, match="rate_hz"):
            TimeDecimator(bad)
    dec = TimeDecimator(10.0)
    with pytest.raises(FilterError, match="rate_hz"):
        dec.set_rate(0.0)


# --------------------------------------------------------------------------------------------------
# VelocityEstimator
# --------------------------------------------------------------------------------------------------


def test_constant_velocity_exact_with_jitter() -> None:
    est = VelocityEstimator(cutoff_hz=15.0)
    v = np.array([1.5, -0.5, 0.25])
    times = jittery_times(180.0, 1.0, 0.001, seed=10, start_ns=0)
    results = [est.update(t, tuple(v * t * 1e-9 + (1, 2, 3)), (1, 0, 0, 0)) for t in times]
    assert not results[0].valid and all(math.isnan(c) for c in results[0].linear_ned)
    assert all(r.valid for r in results[1:])
    for r in results[1:]:
        assert np.allclose(r.linear_ned, v, atol=1e-6)
        assert np.allclose(r.angular_frd, 0.0, atol=1e-9)


def test_sinusoid_matches_first_order_response() -> None:
    fc, f, amp, rate = 15.0, 2.0, 0.5, 180.0
    est = VelocityEstimator(cutoff_hz=fc)
    w, dt = 2 * math.pi * f, 1 / rate
    # Steady state of (finite difference → one-pole low-pass) from its frequency response:
    # D(z) = (1 − z⁻¹)/dt, H(z) = α / (1 − (1 − α) z⁻¹), α = 1 − exp(−2π fc dt).
    alpha = 1 - math.exp(-2 * math.pi * fc * dt)
    zinv = complex(math.cos(w * dt), -math.sin(w * dt))
    resp = (1 - zinv) / dt * alpha / (1 - (1 - alpha) * zinv)
    # ... which must behave like the continuous filter: gain 1/√(1 + (f/fc)²) on the true derivative, lag
    # ≈ τ + dt/2 (low-pass plus half a finite-difference step).
    assert abs(resp) / w == pytest.approx(1 / math.sqrt(1 + (f / fc) ** 2), rel=0.01)
    lag = (math.pi / 2 - math.atan2(resp.imag, resp.real)) / w
    assert lag == pytest.approx(1 / (2 * math.pi * fc) + dt / 2, abs=dt / 2)
    errs = []
    for k in range(int(rate * 2)):
        t = k * dt
        r = est.update(round(t * 1e9), (amp * math.sin(w * t), 0.0, 0.0), (1, 0, 0, 0))
        if t > 0.5:
            expected = amp * abs(resp) * math.sin(w * t + math.atan2(resp.imag, resp.real))
            errs.append(r.linear_ned[0] - expected)
    assert max(abs(e) for e in errs) < 1e-4 * amp * w


def test_lower_cutoff_means_less_noise() -> None:
    rng = np.random.default_rng(11)
    noise = rng.normal(0, 0.0003, (900, 3))
    spread = {}
    for fc in (5.0, 20.0):
        est = VelocityEstimator(cutoff_hz=fc)
        vals = [
            est.update(int(k * 1e9 / 180), tuple(noise[k]), (1, 0, 0, 0)).linear_ned[0] for k in range(900)
        ]
        spread[fc] = float(np.std(vals[50:]))
    assert spread[5.0] < 0.6 * spread[20.0]
    assert spread[20.0] < 0.0003 * 180 * math.sqrt(2)  # below the raw finite-difference noise


def test_angular_velocity_of_tilted_yawing_body() -> None:
    # World yaw rate r with the body rolled by φ: body rates are Rx(φ)ᵀ (0, 0, r) = (0, r sin φ, r cos φ).
    r, phi = 1.2, math.radians(25)
    roll = quat_from_euler(phi, 0, 0)
    est = VelocityEstimator(cutoff_hz=20.0)
    out = None
    for k in range(200):
        t = k / 200
        q = quat_multiply(quat_from_yaw(r * t), roll)
        if k % 2:
            q = (-q[0], -q[1], -q[2], -q[3])  # the sign of a quaternion is arbitrary
        out = est.update(int(t * 1e9), (0, 0, 0), q)
    assert out is not None and out.valid
    assert np.allclose(out.angular_frd, (0.0, r * math.sin(phi), r * math.cos(phi)), atol=1e-6)


def test_fast_body_rotation_rate() -> None:
    axis, rate = np.array([0.3, -0.4, 0.866]), 20.0  # rad/s, ~19° per 60 Hz sample
    axis /= np.linalg.norm(axis)
    est = VelocityEstimator()
    for k in range(30):
        t = k / 60
        res = est.update(int(t * 1e9), (0, 0, 0), quat_from_axis_angle(tuple(axis), rate * t))
    assert np.allclose(res.angular_frd, axis * rate, atol=1e-6)


def test_velocity_validity_rules() -> None:
    est = VelocityEstimator(max_gap_s=0.05)
    q = (1.0, 0.0, 0.0, 0.0)
    assert not est.update(0, (0, 0, 0), q).valid
    assert est.update(10 * MS, (0.01, 0, 0), q).valid
    assert est.update(10 * MS, (5.0, 0, 0), q).linear_ned[0] == pytest.approx(1.0)  # duplicate ignored
    # invalid pose: invalid now and for the next sample
    assert not est.update(20 * MS, (0.02, 0, 0), q, valid=False).valid
    assert not est.update(30 * MS, (0.03, 0, 0), q).valid
    assert est.update(40 * MS, (0.05, 0, 0), q).linear_ned[0] == pytest.approx(2.0)
    # gap longer than max_gap_s restarts (no velocity from the jump across the gap)
    assert not est.update(200 * MS, (1.0, 0, 0), q).valid
    assert est.update(210 * MS, (1.0, 0.01, 0), q).linear_ned == pytest.approx((0.0, 1.0, 0.0))
    # time going backwards restarts, NaN is invalid
    assert not est.update(100 * MS, (0, 0, 0), q).valid
    assert not est.update(110 * MS, (math.nan, 0, 0), q).valid
    assert not est.update(120 * MS, (0, 0, 0), (0, 0, 0, 0)).valid
    est.reset()
    assert not est.last.valid
    with pytest.raises(FilterError, match="3 components"):
        est.update(0, (0, 0), q)
    with pytest.raises(FilterError, match="cutoff_hz"):
        VelocityEstimator(cutoff_hz=0)


# --------------------------------------------------------------------------------------------------
# JumpGate
# --------------------------------------------------------------------------------------------------


def test_gate_passes_real_motion_and_drops_spikes() -> None:
    gate = JumpGate(max_speed_m_s=5.0, margin_m=0.05)
    dt = 1 / 180
    decisions = []
    for k in range(360):
        x = 4.0 * k * dt  # 4 m/s, inside the limit
        p = (x, 0.0, -1.0) if k != 100 else (x + 1.0, 0.0, -1.0)  # one 1 m spike
        decisions.append(gate.check(int(k * dt * 1e9), p))
    assert [i for i, d in enumerate(decisions) if not d.accepted] == [100]
    assert decisions[100].reason is RejectReason.JUMP and not any(d.reset for d in decisions)
    assert gate.rejected[RejectReason.JUMP] == 1 and gate.accepted == 359


def test_gate_reacquires_after_consistent_rejections() -> None:
    gate = JumpGate(max_speed_m_s=3.0, reacquire_after=5)
    t = 0
    for _ in range(10):
        t += 5 * MS
        assert gate.check(t, (0.0, 0.0, -1.0)).accepted
    results = []
    for _ in range(7):  # the body now reads 2 m away, steadily (e.g. a re-identified rigid body)
        t += 5 * MS
        results.append(gate.check(t, (2.0, 0.0, -1.0)))
    assert [r.accepted for r in results] == [False] * 5 + [True, True]
    assert results[5].reset and not results[6].reset
    assert gate.resets == 1 and gate.rejected[RejectReason.JUMP] == 5


def test_gate_scattered_outliers_do_not_reacquire() -> None:
    gate = JumpGate(max_speed_m_s=3.0, reacquire_after=3, max_gap_s=0.5)
    gate.check(0, (0.0, 0.0, 0.0))
    t = 0
    for k in range(40):  # ghosts alternating between two far-apart places, for 0.2 s
        t += 5 * MS
        assert not gate.check(t, (3.0, 0.0, 0.0) if k % 2 else (-3.0, 0.0, 0.0)).accepted
    assert gate.resets == 0
    d = gate.check(t + 600 * MS, (3.0, 0.0, 0.0))  # long gap since the last accepted pose
    assert d.accepted and d.reset


def test_gate_rotation_flip_stale_and_nan() -> None:
    gate = JumpGate(max_rate_rad_s=10.0, margin_rad=0.1)
    p = (0.0, 0.0, -1.0)
    assert gate.check(0, p, (1, 0, 0, 0)).accepted
    assert gate.check(5 * MS, p, quat_from_yaw(0.05)).accepted
    flipped = gate.check(10 * MS, p, quat_from_yaw(math.pi))
    assert not flipped.accepted and flipped.reason is RejectReason.ROTATION
    assert gate.check(15 * MS, p, (-1, 0, 0, 0)).accepted  # sign of a quaternion is no rotation
    assert gate.check(15 * MS, p).reason is RejectReason.STALE
    assert gate.check(20 * MS, (math.nan, 0, 0)).reason is RejectReason.NON_FINITE
    assert gate.check(20 * MS, p, (0, 0, 0, 0)).reason is RejectReason.NON_FINITE
    assert gate.rejected == {
        RejectReason.JUMP: 0,
        RejectReason.ROTATION: 1,
        RejectReason.STALE: 1,
        RejectReason.NON_FINITE: 2,
    }
    gate.reset()
    assert gate.check(0, (100.0, 0, 0)).accepted  # fresh start after reset


def test_gate_rejects_bad_config() -> None:
    with pytest.raises(FilterError, match="max_speed_m_s"):
        JumpGate(max_speed_m_s=0)
    with pytest.raises(FilterError, match="reacquire_after"):
        JumpGate(reacquire_after=0)
    with pytest.raises(FilterError, match="margin_m"):
        JumpGate(margin_m=-1)
