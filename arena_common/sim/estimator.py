"""The simulated vehicle's stand-in for EKF2: IMU prediction corrected by vision, barometer, magnetometer.

See :class:`Estimator`. Re-exported by :mod:`arena_common.sim.physics`.
"""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

from arena_common.geometry.quat import (
    Quat,
    Vec3,
    quat_from_euler,
    quat_rotate,
    quat_to_euler,
    quat_yaw,
    wrap_angle,
)
from arena_common.sim.base import clamp

if TYPE_CHECKING:
    from arena_common.sim.physics import RigidBody

__all__ = [
    "EV_CTRL_HPOS",
    "EV_CTRL_VEL",
    "EV_CTRL_VPOS",
    "EV_CTRL_YAW",
    "PX4_SIH_ESTIMATE_LAG_S",
    "PX4_SIH_WANDER",
    "Estimator",
    "Wander",
]

NAN = math.nan
_clamp = clamp


EV_CTRL_HPOS = 1
EV_CTRL_VPOS = 2
EV_CTRL_VEL = 4
EV_CTRL_YAW = 8


@dataclass(frozen=True, slots=True)
class Wander:
    """How an estimate strays from the truth in flight, and so how a vehicle wanders around its setpoint.

    The velocity error along each axis of the heading (forward, right, down) is a first-order random
    process (Ornstein-Uhlenbeck) of rms ``velocity_rms`` and correlation time ``velocity_tau_s``; the
    position error integrates it and is pulled back to the fused measurements with time constant
    ``position_tau_s``.  The roll and pitch estimates stray likewise (``tilt_rms``, ``tilt_tau_s``).  The
    controllers act on the estimate: a wrong tilt held is a real sideways force, a wrong velocity followed
    a real drift, and the position loop pulls the vehicle back.
    """

    velocity_rms: Vec3 = (0.0, 0.0, 0.0)  # m/s: forward, right, down
    velocity_tau_s: float = 0.7
    position_tau_s: float = 0.5
    tilt_rms: tuple[float, float] = (0.0, 0.0)  # rad: roll, pitch
    tilt_tau_s: float = 3.0


#: PX4 v1.16 SITL (SIH) set up by `arena px4 setup`, as its ULog measured it in hover with the arena's vision
#: (docs/px4.md, "Issue 25"): its velocity estimate off the truth by 0.026 / 0.083 / 0.054 m/s rms (north /
#: east / down, heading north), correlated over ~0.5 s; its position estimate 0.8 / 2.1 cm rms off; the
#: estimate trailing the truth by 70-95 ms in flight; true roll 1.2-1.6° and pitch 0.4-0.7° std, its roll
#: estimate 0.5-0.8° std off the truth; and the vehicle wandering 8-11 cm (p50) and 17-24 cm (max) around its
#: hover point, along the roll axis far more than the pitch axis.  These constants reproduce that with the
#: simulation's controllers (tests/unit/sim/test_sim_px4_parity.py): the size of PX4/SIH's wander, not its
#: cause inside PX4.
PX4_SIH_ESTIMATE_LAG_S = 0.05
PX4_SIH_WANDER = Wander(
    velocity_rms=(0.026, 0.085, 0.054),
    velocity_tau_s=0.5,
    position_tau_s=0.3,
    tilt_rms=(math.radians(1.5), math.radians(0.5)),
    tilt_tau_s=2.0,
)


def _ou_factors(dt: float, tau: float) -> tuple[float, float]:
    """One step of ``dt`` of a first-order random process of correlation time ``tau``: the factor on its
    value and the one on a unit normal draw scaled by its rms (``x = decay·x + spread·rms·N(0, 1)``)."""
    decay = math.exp(-dt / tau)
    return decay, math.sqrt(1.0 - decay * decay)


class Estimator:
    """Stand-in for EKF2: IMU prediction corrected by external vision, barometer and magnetometer.

    Vision samples are fused against the estimate stored at their measurement time (``sample time −
    EKF2_EV_DELAY``), so a wrong delay shows up as lag or overshoot like on a real vehicle. Vision is
    used only when ``ev_ctrl`` enables it, stops 400 ms after the last sample and needs two samples
    less than 200 ms apart to (re)start, when the estimate is reset onto the measurement.

    After vision stops the horizontal estimate dead-reckons on the IMU (:attr:`dead_reckoning`) and is
    declared invalid ``noaid_timeout_s`` − 0.4 s after the last fused sample (at least 0.6 s), which is
    when PX4 v1.16 SITL declared it (measured with EKF2_NOAID_TOUT 1, 3 and 5 s: 0.6, 2.6, 4.6 s).

    Heading: vision yaw in a north-referenced frame (ODOMETRY LOCAL_NED, VISION_POSITION_ESTIMATE) or
    the magnetometer aligns it (:attr:`north_aligned`); vision yaw in LOCAL_FRD (``north_ref=False``)
    steers the heading but never aligns it, as in PX4 v1.16, so there is no global position.

    ``output_lag_s`` > 0 passes position and velocity through a first-order lag before anyone uses
    them (:attr:`out_position`, :attr:`out_velocity`: the controllers and the telemetry); ``wander`` (a
    :class:`Wander`) adds a random error to them in flight.  Both are off by default (an exact estimate).
    """

    HISTORY_S = 0.6
    EV_TIMEOUT_S = 0.4
    EV_START_GAP_S = 0.2
    NOAID_MARGIN_S = 0.4  # PX4 v1.16 SITL declared position invalid this much before EKF2_NOAID_TOUT
    NOAID_MIN_S = 0.6

    def __init__(self, rng: random.Random, position: Vec3 = (0.0, 0.0, 0.0), yaw: float = 0.0) -> None:
        self.rng = rng
        self.ev_ctrl = 0
        self.ev_delay_s = 0.0
        self.baro_enabled = True
        self.mag_enabled = True
        self.hgt_ref_vision = False
        self.noaid_timeout_s = 5.0  # EKF2_NOAID_TOUT
        self.output_lag_s = 0.0
        self.wander: Wander | None = None
        # Small constant sensor errors, different for each vehicle (seeded).
        self.accel_bias = (rng.uniform(-0.04, 0.04), rng.uniform(-0.04, 0.04), rng.uniform(-0.06, 0.06))
        self.gyro_z_bias = rng.uniform(-0.004, 0.004)
        self.mag_yaw_error = rng.uniform(-0.12, 0.12)  # indoor magnetic disturbance
        self.baro_offset = rng.uniform(-0.3, 0.3)
        self.reset(position, yaw, 0.0)

    def reset(self, position: Vec3, yaw: float, t: float) -> None:
        """Start again from a known pose (boot)."""
        self.position = position
        self.velocity = (0.0, 0.0, 0.0)
        self.bias_est = [0.0, 0.0, 0.0]  # learned accelerometer bias (NED), as EKF2's delta-velocity bias
        # Before any heading aiding the yaw starts at zero, as EKF2 aligns it with no magnetometer.
        self.yaw = 0.0
        self.roll = 0.0
        self.pitch = 0.0
        self.time = t
        self.history: deque[tuple[float, Vec3, Vec3, float]] = deque()
        self.ev_active = False
        self.ev_last_arrival = -math.inf
        self.ev_last_fused = -math.inf
        self.ev_reset_counter: int | None = None
        self.ev_hpos_fused_at = -math.inf
        self.ev_vpos_fused_at = -math.inf
        self.ev_yaw_fused_at = -math.inf
        self.baro_bias = 0.0
        self.baro_bias_valid = False
        self.yaw_aligned = False
        self.north_aligned = False
        self.last_sample_time = NAN
        self.out_position = position
        self.out_velocity = (0.0, 0.0, 0.0)
        self._lagged = (position, (0.0, 0.0, 0.0))
        self._wander_v = [0.0, 0.0, 0.0]
        self._wander_p = [0.0, 0.0, 0.0]
        self._wander_tilt = [0.0, 0.0]

    # --- validity flags (PX4 vehicle_local_position.*_valid) ---
    @property
    def xy_valid(self) -> bool:
        """Horizontal position (and velocity) estimate usable for control, dead reckoning included."""
        limit = max(self.noaid_timeout_s - self.NOAID_MARGIN_S, self.NOAID_MIN_S)
        return self.time - self.ev_hpos_fused_at < limit

    @property
    def dead_reckoning(self) -> bool:
        """Horizontal position still valid but no longer aided (vision stopped): IMU only."""
        return self.xy_valid and self.time - self.ev_hpos_fused_at >= self.EV_TIMEOUT_S

    @property
    def z_valid(self) -> bool:
        """Height estimate usable for control (vision or barometer)."""
        return self.time - self.ev_vpos_fused_at < self.EV_TIMEOUT_S or (
            self.baro_enabled and self.baro_bias_valid
        )

    @property
    def yaw_valid(self) -> bool:
        """Heading estimate aligned with the arena (vision or magnetometer yaw)."""
        return self.time - self.ev_yaw_fused_at < self.EV_TIMEOUT_S or (self.mag_enabled and self.yaw_aligned)

    @property
    def vision_fusing(self) -> bool:
        """Whether external vision is being fused right now."""
        return self.ev_active and self.time - self.ev_last_fused < self.EV_TIMEOUT_S

    def predict(self, t: float, dt: float, body: RigidBody) -> None:
        """IMU prediction for one tick, from the true motion plus sensor errors."""
        self.time = t
        ax, ay, az = body.acceleration
        bx, by, bz = self.accel_bias
        if body.on_ground:
            # The EKF knows a vehicle at rest does not accelerate (zero-velocity update on ground).
            vx, vy, vz = self.velocity
            decay = 1.0 - min(1.0, 5.0 * dt)
            self.velocity = (vx * decay, vy * decay, vz * decay)
        else:
            vx, vy, vz = self.velocity
            ex, ey, ez = self.bias_est
            self.velocity = (vx + (ax + bx - ex) * dt, vy + (ay + by - ey) * dt, vz + (az + bz - ez) * dt)
        px, py, pz = self.position
        vx, vy, vz = self.velocity
        self.position = (px + vx * dt, py + vy * dt, pz + vz * dt)
        roll, pitch, _ = quat_to_euler(body.attitude)
        self.roll, self.pitch = roll, pitch  # IMU tilt is well observed: take it as measured
        wander = self.wander
        if wander is not None and wander.tilt_rms != (0.0, 0.0):
            # ... but not exactly: the attitude controller holds the estimated tilt, so an error in it is a
            # real sideways force, which the position loop then fights (vision sees the vehicle move).
            et = self._wander_tilt
            decay, spread = _ou_factors(dt, wander.tilt_tau_s)
            for i in (0, 1):
                et[i] = decay * et[i] + spread * wander.tilt_rms[i] * self.rng.gauss(0.0, 1.0)
            self.roll, self.pitch = roll + et[0], pitch + et[1]
        # Yaw from the body-rate about the vertical (gyro), with a bias.
        wz_world = quat_rotate(body.attitude, body.rates)[2]
        self.yaw = wrap_angle(self.yaw + (wz_world + self.gyro_z_bias) * dt)
        if self.mag_enabled and not (self.ev_ctrl & EV_CTRL_YAW and self.vision_fusing):
            true_yaw = quat_yaw(body.attitude)
            mag_yaw = wrap_angle(true_yaw + self.mag_yaw_error)
            if not self.yaw_aligned:
                self.yaw = mag_yaw
                self.yaw_aligned = True
                self.north_aligned = True
            else:
                self.yaw = wrap_angle(self.yaw + min(1.0, 1.0 * dt) * wrap_angle(mag_yaw - self.yaw))
        self.history.append((t, self.position, self.velocity, self.yaw))
        while self.history and self.history[0][0] < t - self.HISTORY_S:
            self.history.popleft()
        self._update_output(dt, body.on_ground)

    def _update_output(self, dt: float, on_ground: bool = False) -> None:
        """What is handed on: the state through a first-order lag (:attr:`output_lag_s`), plus the wander."""
        tau = self.output_lag_s
        if not tau > 0.0:
            op, ov = self.position, self.velocity
        else:
            k = dt / (tau + dt)
            (lp, lv), p, v = self._lagged, self.position, self.velocity
            op = (lp[0] + k * (p[0] - lp[0]), lp[1] + k * (p[1] - lp[1]), lp[2] + k * (p[2] - lp[2]))
            ov = (lv[0] + k * (v[0] - lv[0]), lv[1] + k * (v[1] - lv[1]), lv[2] + k * (v[2] - lv[2]))
            self._lagged = (op, ov)
        wander = self.wander
        if wander is not None:
            ev, ep = self._wander_v, self._wander_p
            decay, spread = _ou_factors(dt, wander.velocity_tau_s)
            pull = min(dt / wander.position_tau_s, 1.0)
            if on_ground:  # at rest the EKF knows the velocity is zero: the error dies away
                ev[0], ev[1], ev[2] = ev[0] * decay, ev[1] * decay, ev[2] * decay
            else:  # the error is drawn along the heading's axes (forward, right, down), kept in NED
                gauss, rms = self.rng.gauss, wander.velocity_rms
                fwd, right = spread * rms[0] * gauss(0.0, 1.0), spread * rms[1] * gauss(0.0, 1.0)
                c, s = math.cos(self.yaw), math.sin(self.yaw)
                ev[0] = decay * ev[0] + c * fwd - s * right
                ev[1] = decay * ev[1] + s * fwd + c * right
                ev[2] = decay * ev[2] + spread * rms[2] * gauss(0.0, 1.0)
            for i in range(3):  # the position error integrates the velocity's, pulled back to the fusion
                ep[i] += ev[i] * dt - pull * ep[i]
            op = (op[0] + ep[0], op[1] + ep[1], op[2] + ep[2])
            ov = (ov[0] + ev[0], ov[1] + ev[1], ov[2] + ev[2])
        self.out_position = op
        self.out_velocity = ov

    def fuse_baro(self, dt: float, true_down: float) -> None:
        """Barometric height: learns its offset while vision height is fused, replaces it otherwise."""
        if not self.baro_enabled:
            return
        baro_down = true_down + self.baro_offset + self.rng.gauss(0.0, 0.02)
        px, py, pz = self.position
        if self.time - self.ev_vpos_fused_at < self.EV_TIMEOUT_S:
            k = min(1.0, 0.5 * dt)
            if not self.baro_bias_valid:
                self.baro_bias = baro_down - pz
                self.baro_bias_valid = True
            else:
                self.baro_bias += k * ((baro_down - pz) - self.baro_bias)
        else:
            if not self.baro_bias_valid:
                self.baro_bias = baro_down - pz
                self.baro_bias_valid = True
            innov = (baro_down - self.baro_bias) - pz
            vx, vy, vz = self.velocity
            self.position = (px, py, pz + min(1.0, 3.0 * dt) * innov)
            self.velocity = (vx, vy, vz + min(1.0, 2.0 * dt) * innov)

    def _state_at(self, t: float) -> tuple[Vec3, Vec3, float] | None:
        hist = self.history
        if not hist or t < hist[0][0] - 1e-9:
            return None
        # Scan from the newest entry (delays are short, so few steps).
        for i in range(len(hist) - 1, -1, -1):
            entry = hist[i]
            if entry[0] <= t + 1e-9:
                return entry[1], entry[2], entry[3]
        return None

    def fuse_vision(
        self,
        arrival: float,
        sample_time: float,
        position: Vec3 | None,
        yaw: float | None,
        velocity: Vec3 | None,
        reset_counter: int | None,
        north_ref: bool = True,
    ) -> bool:
        """Fuse one external-vision sample; ``sample_time`` in the vehicle clock (s). Returns fused.

        ``north_ref``: the pose frame is north-referenced (LOCAL_NED); False for LOCAL_FRD, whose yaw
        steers the heading without aligning it to north.
        """
        self.time = max(self.time, arrival)
        self.last_sample_time = sample_time
        if not self.ev_ctrl:
            return False
        prev_arrival = self.ev_last_arrival
        self.ev_last_arrival = arrival
        if not self.vision_fusing:
            self.ev_active = False
            if arrival - prev_arrival >= self.EV_START_GAP_S:
                return False  # needs a second sample soon after the first one
        t_meas = sample_time - self.ev_delay_s
        if t_meas > self.time + 1e-3:
            t_meas = self.time  # a stamp from the future is treated as now
        starting = not self.ev_active
        reset = starting or (reset_counter is not None and reset_counter != self.ev_reset_counter)
        self.ev_reset_counter = reset_counter
        past = self._state_at(t_meas)
        if past is None:
            return False
        p_past, v_past, yaw_past = past
        dt_s = _clamp(arrival - self.ev_last_fused, 0.005, 0.1)
        px, py, pz = self.position
        vx, vy, vz = self.velocity
        ctrl = self.ev_ctrl
        use_yaw = ctrl & EV_CTRL_YAW and yaw is not None and math.isfinite(yaw)
        if use_yaw:
            innov_yaw = wrap_angle(yaw - yaw_past)  # type: ignore[operator]
            if reset:
                self.yaw = wrap_angle(self.yaw + innov_yaw)
            else:
                self.yaw = wrap_angle(self.yaw + min(1.0, 6.0 * dt_s) * innov_yaw)
            self.yaw_aligned = True
            if north_ref:
                self.north_aligned = True
            self.ev_yaw_fused_at = arrival
        if position is not None:
            ix = position[0] - p_past[0]
            iy = position[1] - p_past[1]
            iz = position[2] - p_past[2]
            if reset:
                # Jump the estimate onto the measurement (and its motion since the sample).
                if ctrl & EV_CTRL_HPOS:
                    px += ix
                    py += iy
                if ctrl & EV_CTRL_VPOS:
                    pz += iz
            else:
                # Third-order complementary filter, poles at -2, -2, -4 rad/s.
                kp = min(1.0, 8.0 * dt_s)
                kv = 20.0 * dt_s
                kb = 16.0 * dt_s
                be = self.bias_est
                if ctrl & EV_CTRL_HPOS:
                    px += kp * ix
                    py += kp * iy
                    vx += kv * ix
                    vy += kv * iy
                    be[0] = _clamp(be[0] - kb * ix, -0.5, 0.5)
                    be[1] = _clamp(be[1] - kb * iy, -0.5, 0.5)
                if ctrl & EV_CTRL_VPOS:
                    pz += kp * iz
                    vz += kv * iz
                    be[2] = _clamp(be[2] - kb * iz, -0.5, 0.5)
            if ctrl & EV_CTRL_HPOS:
                self.ev_hpos_fused_at = arrival
            if ctrl & EV_CTRL_VPOS:
                self.ev_vpos_fused_at = arrival
        if velocity is not None and ctrl & EV_CTRL_VEL and all(math.isfinite(c) for c in velocity):
            kv2 = min(1.0, 10.0 * dt_s)
            vx += kv2 * (velocity[0] - v_past[0])
            vy += kv2 * (velocity[1] - v_past[1])
            vz += kv2 * (velocity[2] - v_past[2])
        if reset:
            # A reset moves what is handed on at once too (PX4 resets its output predictor).
            old = self.position
            shift = (px - old[0], py - old[1], pz - old[2])
            op, (lp, lv) = self.out_position, self._lagged
            self.out_position = (op[0] + shift[0], op[1] + shift[1], op[2] + shift[2])
            self._lagged = ((lp[0] + shift[0], lp[1] + shift[1], lp[2] + shift[2]), lv)
        self.position = (px, py, pz)
        self.velocity = (vx, vy, vz)
        fused = bool(use_yaw or (position is not None and ctrl & (EV_CTRL_HPOS | EV_CTRL_VPOS)))
        if fused:
            self.ev_active = True
            self.ev_last_fused = arrival
            if reset:
                self.history.clear()
                self.history.append((self.time, self.position, self.velocity, self.yaw))
        return fused

    def attitude(self) -> Quat:
        """Estimated attitude (IMU roll/pitch, estimated yaw)."""
        return quat_from_euler(self.roll, self.pitch, self.yaw)
