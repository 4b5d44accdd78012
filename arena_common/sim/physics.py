"""A small quadrotor simulated in the arena NED frame (FRD body), with PX4-like on-board control.

Parts, all advanced by :meth:`QuadSim.step` at a fixed tick (250 Hz by default):

- :class:`RigidBody` — the truth: 6-DoF rigid body with first-order motor lag, linear drag and a floor
  at ``down = 0`` (positive down, so the vehicle rests at ``down ≈ 0`` and cannot go below it).
- :class:`Battery` — a LiPo pack whose charge drains with the motors' power and whose voltage sags
  with load; low voltage reduces the available thrust.
- :class:`~arena_common.sim.estimator.Estimator` (module :mod:`~arena_common.sim.estimator`) — a
  complementary filter standing for EKF2: IMU prediction (with a small accelerometer bias), external-vision
  fusion on a delayed horizon (``EKF2_EV_DELAY``) controlled by
  ``EKF2_EV_CTRL`` bits, barometer height as fallback, magnetometer or gyro yaw when vision yaw is off,
  inertial dead reckoning for ``EKF2_NOAID_TOUT`` after vision stops, and an optional first-order lag of
  the estimate it hands on (PX4's output lags the truth a little).
- :class:`Controller` — PX4's multicopter cascade: position P → velocity PID → acceleration →
  thrust vector and attitude (tilt limited) → attitude P (reduced attitude, yaw weighted) → rate PID.
- :class:`~arena_common.sim.land_detector.LandDetector` (its own module) — ground contact, low thrust and no
  motion for a while → landed.

Plain float arithmetic on tuples is used on purpose: for 3-vectors it is several times cheaper than
numpy, which matters when one process flies several vehicles in real time.
"""

from __future__ import annotations

import enum
import math
import random
from dataclasses import dataclass, field

from arena_common.geometry.quat import (
    Quat,
    Vec3,
    quat_canonical,
    quat_conjugate,
    quat_from_axes,
    quat_from_euler,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_rotate_inverse,
    quat_yaw,
    wrap_angle,
)
from arena_common.sim.base import clamp as _clamp
from arena_common.sim.estimator import EV_CTRL_HPOS, EV_CTRL_VEL, EV_CTRL_VPOS, EV_CTRL_YAW, Estimator
from arena_common.sim.land_detector import LandDetector

__all__ = [
    "EV_CTRL_HPOS",
    "EV_CTRL_VEL",
    "EV_CTRL_VPOS",
    "EV_CTRL_YAW",
    "GRAVITY",
    "Battery",
    "BatteryParams",
    "ControlGains",
    "Controller",
    "Estimator",
    "LandDetector",
    "MotorMode",
    "QuadParams",
    "QuadSim",
    "RigidBody",
    "Setpoint",
    "SimPhysicsError",
]

GRAVITY = 9.80665
NAN = math.nan


def _unit(q: Quat) -> Quat:
    """``q`` normalised, the representative with ``w >= 0``."""
    return quat_canonical(quat_normalize(q))


class SimPhysicsError(ValueError):
    """Invalid physical parameter or state given to the simulator."""


# --- parameters -------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class QuadParams:
    """Physical parameters of a ~1 kg, 250 mm class quadrotor."""

    mass: float = 1.0  # kg
    inertia: Vec3 = (0.0085, 0.0085, 0.015)  # kg m², body FRD principal axes
    max_thrust: float = 2.0 * GRAVITY  # N, all motors at full battery voltage (thrust/weight 2)
    max_torque: Vec3 = (0.6, 0.6, 0.12)  # N m
    motor_time_constant: float = 0.025  # s
    # 1/s, linear drag acceleration per m/s (NED axes): PX4 SIH's SIH_KDV / SIH_MASS (1.0 N/(m/s), 1 kg).
    # With it, an offboard velocity of 0.5 m/s settles near 0.33 m/s at first (P 1.8 against drag 1.0), as
    # PX4 SITL flew it (docs/px4.md, parity).
    drag: Vec3 = (1.0, 1.0, 1.0)
    idle_throttle: float = 0.04  # normalised thrust of spinning motors when armed and landed

    def __post_init__(self) -> None:
        if not self.mass > 0 or min(self.inertia) <= 0:
            raise SimPhysicsError(f"mass and inertia must be positive: {self.mass}, {self.inertia}")
        if not self.max_thrust > self.mass * GRAVITY:
            raise SimPhysicsError(
                f"max_thrust {self.max_thrust} N cannot lift {self.mass} kg "
                f"(needs > {self.mass * GRAVITY:.2f} N)"
            )
        if not self.motor_time_constant > 0:
            raise SimPhysicsError("motor_time_constant must be positive")

    @property
    def hover_throttle(self) -> float:
        """Normalised thrust that holds the vehicle at full battery voltage."""
        return self.mass * GRAVITY / self.max_thrust


@dataclass(frozen=True, slots=True)
class ControlGains:
    """Gains and limits of the control cascade (PX4 v1.14 multicopter defaults where they exist)."""

    xy_p: float = 0.95  # MPC_XY_P
    z_p: float = 1.0  # MPC_Z_P
    xy_vel_p: float = 1.8  # MPC_XY_VEL_P_ACC
    xy_vel_i: float = 0.4  # MPC_XY_VEL_I_ACC
    xy_vel_d: float = 0.2  # MPC_XY_VEL_D_ACC
    z_vel_p: float = 4.0  # MPC_Z_VEL_P_ACC
    z_vel_i: float = 2.0  # MPC_Z_VEL_I_ACC
    z_vel_d: float = 0.0  # MPC_Z_VEL_D_ACC
    att_p: Vec3 = (6.5, 6.5, 2.8)  # MC_ROLL_P, MC_PITCH_P, MC_YAW_P
    rate_p: Vec3 = (18.0, 18.0, 8.0)  # angular acceleration per rate error, 1/s
    rate_i: Vec3 = (4.0, 4.0, 0.0)  # no yaw disturbance torque is simulated: no yaw integrator
    rate_max: Vec3 = (math.radians(220), math.radians(220), math.radians(200))
    tilt_max_deg: float = 45.0  # MPC_TILTMAX_AIR
    thr_min: float = 0.12  # MPC_THR_MIN
    thr_max: float = 1.0  # MPC_THR_MAX
    hover_throttle: float = 0.5  # MPC_THR_HOVER
    vel_max_xy: float = 12.0  # MPC_XY_VEL_MAX
    vel_max_up: float = 3.0  # MPC_Z_VEL_MAX_UP
    vel_max_dn: float = 1.5  # MPC_Z_VEL_MAX_DN
    takeoff_ramp_s: float = 3.0  # MPC_TKO_RAMP_T
    yaw_rate_auto_max: float = math.radians(45)  # MPC_YAWRAUTO_MAX


@dataclass(frozen=True, slots=True)
class BatteryParams:
    """A LiPo pack."""

    cells: int = 4
    capacity_mah: float = 1500.0
    internal_resistance: float = 0.025  # ohm, whole pack
    avionics_current: float = 0.5  # A drawn by electronics
    figure_of_merit: float = 0.55  # rotor efficiency against ideal momentum-theory power
    rotor_area: float = 0.05  # m², all rotor discs together

    def __post_init__(self) -> None:
        if self.cells < 1 or not self.capacity_mah > 0:
            raise SimPhysicsError(f"battery needs >= 1 cell and positive capacity, got {self}")


@dataclass(slots=True)
class Setpoint:
    """A trajectory setpoint, as PX4's ``trajectory_setpoint``: NaN components are not controlled.

    A finite position drives the position loop (finite velocity/acceleration add as feed-forward);
    a finite velocity without position drives the velocity loop; acceleration alone is passed on.
    ``yaw`` NaN keeps the current heading unless ``yaw_rate`` is finite.  An ``attitude`` (with
    ``thrust``, normalised 0..1) bypasses the position and velocity loops, as PX4's
    ``vehicle_attitude_setpoint`` from SET_ATTITUDE_TARGET does.
    """

    position: Vec3 = (NAN, NAN, NAN)
    velocity: Vec3 = (NAN, NAN, NAN)
    acceleration: Vec3 = (NAN, NAN, NAN)
    yaw: float = NAN
    yaw_rate: float = NAN
    attitude: Quat | None = None
    thrust: float = NAN

    @classmethod
    def hold(cls, position: Vec3, yaw: float) -> Setpoint:
        """Hold a position and heading."""
        return cls(position=position, yaw=yaw)


class MotorMode(enum.Enum):
    """What the motors are asked to do."""

    OFF = "off"  # disarmed or killed: no thrust at all
    IDLE = "idle"  # armed on the ground: spinning at idle
    FLY = "fly"  # closed-loop control toward the setpoint
    DESCEND = "descend"  # level attitude, vertical velocity only (no position estimate)


# --- the truth ----------------------------------------------------------------------------------


@dataclass(slots=True)
class RigidBody:
    """True state of the vehicle and its integration (semi-implicit Euler)."""

    params: QuadParams = field(default_factory=QuadParams)
    position: Vec3 = (0.0, 0.0, 0.0)
    velocity: Vec3 = (0.0, 0.0, 0.0)
    attitude: Quat = (1.0, 0.0, 0.0, 0.0)
    rates: Vec3 = (0.0, 0.0, 0.0)  # body FRD rad/s
    thrust: float = 0.0  # N, actual (after motor lag)
    torque: Vec3 = (0.0, 0.0, 0.0)  # N m, actual
    acceleration: Vec3 = (0.0, 0.0, 0.0)  # NED kinematic acceleration of the last step
    on_ground: bool = True
    last_impact_speed: float = 0.0

    def step(self, dt: float, thrust_cmd: float, torque_cmd: Vec3) -> None:
        """Advance ``dt`` seconds with commanded collective thrust (N) and body torques (N m)."""
        p = self.params
        k = dt / p.motor_time_constant
        k = 1.0 if k > 1.0 else k
        thrust = self.thrust + (thrust_cmd - self.thrust) * k
        thrust = _clamp(thrust, 0.0, p.max_thrust)
        tx = self.torque[0] + (torque_cmd[0] - self.torque[0]) * k
        ty = self.torque[1] + (torque_cmd[1] - self.torque[1]) * k
        tz = self.torque[2] + (torque_cmd[2] - self.torque[2]) * k
        self.thrust = thrust
        self.torque = (tx, ty, tz)

        q = self.attitude
        fx, fy, fz = quat_rotate(q, (0.0, 0.0, -thrust))
        vx, vy, vz = self.velocity
        m = p.mass
        dx, dy, dz = p.drag
        ax = fx / m - dx * vx
        ay = fy / m - dy * vy
        az = fz / m + GRAVITY - dz * vz

        px, py, pz = self.position
        if self.on_ground and az >= 0.0:
            # Resting on the floor: the ground carries the weight, friction stops sliding.
            self.velocity = (0.0, 0.0, 0.0)
            self.position = (px, py, 0.0)
            self.acceleration = (0.0, 0.0, 0.0)
            yaw = quat_yaw(q)
            self.attitude = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
            # Only yaw can turn while the feet touch the floor, and slowly.
            iz = p.inertia[2]
            wz = self.rates[2] + (tz / iz) * dt if thrust > 0.5 * m * GRAVITY else 0.0
            self.rates = (0.0, 0.0, wz)
            self._integrate_attitude(dt)
            return

        self.on_ground = False
        vx += ax * dt
        vy += ay * dt
        vz += az * dt
        px += vx * dt
        py += vy * dt
        pz += vz * dt
        if pz >= 0.0:
            self.last_impact_speed = vz
            pz = 0.0
            vx = vy = vz = 0.0
            self.on_ground = True
        self.acceleration = (ax, ay, az)
        self.position = (px, py, pz)
        self.velocity = (vx, vy, vz)

        ix, iy, iz = p.inertia
        wx, wy, wz = self.rates
        # Euler's equations: I w' = tau - w x (I w)
        ax_ = (tx - (wy * iz * wz - wz * iy * wy)) / ix
        ay_ = (ty - (wz * ix * wx - wx * iz * wz)) / iy
        az_ = (tz - (wx * iy * wy - wy * ix * wx)) / iz
        self.rates = (wx + ax_ * dt, wy + ay_ * dt, wz + az_ * dt)
        if self.on_ground:
            yaw = quat_yaw(self.attitude)
            self.attitude = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
            self.rates = (0.0, 0.0, 0.0)
        else:
            self._integrate_attitude(dt)

    def _integrate_attitude(self, dt: float) -> None:
        wx, wy, wz = self.rates
        q = self.attitude
        dq = quat_multiply(q, (0.0, wx, wy, wz))
        h = 0.5 * dt
        self.attitude = _unit((q[0] + dq[0] * h, q[1] + dq[1] * h, q[2] + dq[2] * h, q[3] + dq[3] * h))

    def specific_force_body(self) -> Vec3:
        """What an accelerometer measures (FRD, m/s²): −g·z at rest."""
        ax, ay, az = self.acceleration
        return quat_rotate_inverse(self.attitude, (ax, ay, az - GRAVITY))


# --- battery ------------------------------------------------------------------------------------


class Battery:
    """LiPo pack: open-circuit voltage from the state of charge, sag with current, charge counting."""

    def __init__(self, params: BatteryParams | None = None, soc: float = 1.0) -> None:
        self.params = params or BatteryParams()
        if not 0.0 <= soc <= 1.0:
            raise SimPhysicsError(f"state of charge must be within 0..1, got {soc}")
        self.soc = soc
        self.current = 0.0  # A
        self.consumed_mah = 0.0
        self.energy_j = 0.0

    @staticmethod
    def cell_ocv(soc: float) -> float:
        """Open-circuit voltage of one cell at a state of charge (4.2 V full, ~3.3 V empty)."""
        return 3.45 + 0.75 * soc - 0.15 * math.exp(-12.0 * soc)

    @property
    def voltage(self) -> float:
        """Terminal voltage under the present load."""
        p = self.params
        return max(0.0, p.cells * self.cell_ocv(self.soc) - self.current * p.internal_resistance)

    @property
    def full_voltage(self) -> float:
        """Open-circuit voltage of a full pack."""
        return self.params.cells * self.cell_ocv(1.0)

    def cell_voltage(self) -> float:
        """Terminal voltage of one cell."""
        return self.voltage / self.params.cells

    def step(self, dt: float, thrust_n: float, armed: bool) -> None:
        """Drain the pack for ``dt`` seconds while the motors produce ``thrust_n`` newtons."""
        p = self.params
        power = 0.0
        if thrust_n > 0.0:
            # Momentum theory: P = T^1.5 / sqrt(2 rho A), over the figure of merit.
            power = thrust_n**1.5 / math.sqrt(2 * 1.225 * p.rotor_area) / p.figure_of_merit
        ocv = p.cells * self.cell_ocv(self.soc)
        current = p.avionics_current + (power / ocv if armed else 0.0)
        self.current = current
        charge_mah = current * dt / 3.6
        self.consumed_mah += charge_mah
        self.energy_j += current * self.voltage * dt
        self.soc = max(0.0, self.soc - charge_mah / p.capacity_mah)


# --- controller ---------------------------------------------------------------------------------


class Controller:
    """PX4's multicopter cascade, run on the estimate: position/velocity at 50 Hz, attitude/rate each tick."""

    POSITION_PERIOD = 0.02

    HOVER_TIME_CONSTANT = 1.5  # s, hover-thrust estimator

    def __init__(self, params: QuadParams, gains: ControlGains) -> None:
        self.params = params
        self.gains = gains
        self.hover_est = gains.hover_throttle
        self.reset()

    def update_hover_estimate(self, dt: float, specific_force_body: Vec3) -> None:
        """PX4's hover-thrust estimator (MPC_USE_HTE): the throttle that would just balance gravity.

        The accelerometer's thrust-axis reading divided into the applied throttle gives the throttle
        per m/s²; it drifts with battery voltage and payload, which the z integrator alone follows slowly.
        """
        spec = -specific_force_body[2]
        if spec < 2.0 or self.throttle_sp <= 0.0:
            return
        implied = self.throttle_sp * GRAVITY / spec
        k = min(1.0, dt / self.HOVER_TIME_CONSTANT)
        self.hover_est = _clamp(self.hover_est + k * (implied - self.hover_est), 0.1, 0.9)

    def reset(self) -> None:
        """Clear integrators and held setpoints (on arming, landing or mode change to idle)."""
        self.vel_int = [0.0, 0.0, 0.0]
        self.rate_int = [0.0, 0.0, 0.0]
        self.att_sp: Quat = (1.0, 0.0, 0.0, 0.0)
        self.throttle_sp = 0.0
        self.yaw_rate_ff = 0.0
        self.pos_timer = 0.0
        self.last_acc_sp: Vec3 = (0.0, 0.0, 0.0)
        self.vel_sp: Vec3 = (0.0, 0.0, 0.0)
        self.takeoff_time = math.inf
        self.saturated_z = False

    def position_control(
        self, sp: Setpoint, est: Estimator, accel: Vec3, yaw_now: float, t: float, dt: float
    ) -> None:
        """Position/velocity loops → attitude and thrust setpoints (``self.att_sp``, ``self.throttle_sp``)."""
        g = self.gains
        if sp.attitude is not None:  # attitude and thrust given: nothing for the outer loops to do
            self.att_sp = _unit(sp.attitude)
            self.throttle_sp = _clamp(sp.thrust, 0.0, g.thr_max) if sp.thrust == sp.thrust else 0.0
            self.vel_sp = (NAN, NAN, NAN)
            self.yaw_rate_ff = 0.0
            self.saturated_z = False
            return
        pos, vel = est.out_position, est.out_velocity
        vsp = [NAN, NAN, NAN]
        kp = (g.xy_p, g.xy_p, g.z_p)
        for i in range(3):
            ps, vs = sp.position[i], sp.velocity[i]
            if ps == ps:  # finite position (NaN != NaN)
                vsp[i] = kp[i] * (ps - pos[i]) + (vs if vs == vs else 0.0)
            elif vs == vs:
                vsp[i] = vs
        # Velocity limits, horizontal norm and vertical up/down (up is negative down).
        if vsp[0] == vsp[0] and vsp[1] == vsp[1]:
            n = math.hypot(vsp[0], vsp[1])
            if n > g.vel_max_xy:
                vsp[0] *= g.vel_max_xy / n
                vsp[1] *= g.vel_max_xy / n
        if vsp[2] == vsp[2]:
            up_limit = g.vel_max_up
            since_takeoff = t - self.takeoff_time
            if 0.0 <= since_takeoff < g.takeoff_ramp_s:
                up_limit = max(0.3, g.vel_max_up * since_takeoff / g.takeoff_ramp_s)
            vsp[2] = _clamp(vsp[2], -up_limit, g.vel_max_dn)
        acc = [0.0, 0.0, 0.0]
        kv = (g.xy_vel_p, g.xy_vel_p, g.z_vel_p)
        ki = (g.xy_vel_i, g.xy_vel_i, g.z_vel_i)
        kd = (g.xy_vel_d, g.xy_vel_d, g.z_vel_d)
        for i in range(3):
            af = sp.acceleration[i]
            if vsp[i] == vsp[i]:
                err = vsp[i] - vel[i]
                acc[i] = kv[i] * err + self.vel_int[i] - kd[i] * accel[i] + (af if af == af else 0.0)
                if not (i == 2 and self.saturated_z and err * self.vel_int[2] > 0):
                    self.vel_int[i] += ki[i] * err * dt
                lim = 3.0 if i < 2 else 6.0
                self.vel_int[i] = _clamp(self.vel_int[i], -lim, lim)
            elif af == af:
                acc[i] = af
        self.vel_sp = (vsp[0], vsp[1], vsp[2])
        self.last_acc_sp = (acc[0], acc[1], acc[2])
        # Yaw setpoint: absolute, rate-integrated, or hold.
        if sp.yaw == sp.yaw:
            yaw_sp = sp.yaw
            self.yaw_rate_ff = 0.0
        elif sp.yaw_rate == sp.yaw_rate:
            yaw_sp = wrap_angle(yaw_now + sp.yaw_rate * self.POSITION_PERIOD)
            self.yaw_rate_ff = sp.yaw_rate
        else:
            yaw_sp = quat_yaw(self.att_sp) if self.throttle_sp > 0 else yaw_now
            self.yaw_rate_ff = 0.0
        self.thrust_from_acceleration(acc[0], acc[1], acc[2], yaw_sp)

    def thrust_from_acceleration(self, ax: float, ay: float, az: float, yaw_sp: float) -> None:
        """Acceleration setpoint (NED) → tilt-limited thrust direction, normalised thrust, attitude."""
        g = self.gains
        # Thrust direction: opposite gravity plus the horizontal demand (PX4 keeps altitude priority).
        tx, ty, tz = ax, ay, -GRAVITY
        n = math.sqrt(tx * tx + ty * ty + tz * tz)
        tx, ty, tz = tx / n, ty / n, tz / n
        tilt_max = math.radians(g.tilt_max_deg)
        if -tz < math.cos(tilt_max):
            h = math.hypot(tx, ty)
            s = math.sin(tilt_max) / h
            tx, ty, tz = tx * s, ty * s, -math.cos(tilt_max)
        # Collective specific thrust so that the vertical acceleration is met.
        spec = (az - GRAVITY) / tz
        throttle = spec * self.hover_est / GRAVITY
        self.saturated_z = throttle >= g.thr_max or throttle <= g.thr_min
        self.throttle_sp = _clamp(throttle, g.thr_min, g.thr_max)
        # Attitude: body z (down) opposite the thrust direction, heading yaw_sp.
        b3 = (-tx, -ty, -tz)
        xc = (math.cos(yaw_sp), math.sin(yaw_sp), 0.0)
        b2 = (b3[1] * xc[2] - b3[2] * xc[1], b3[2] * xc[0] - b3[0] * xc[2], b3[0] * xc[1] - b3[1] * xc[0])
        n2 = math.sqrt(b2[0] ** 2 + b2[1] ** 2 + b2[2] ** 2)
        b2 = (b2[0] / n2, b2[1] / n2, b2[2] / n2)
        b1 = (b2[1] * b3[2] - b2[2] * b3[1], b2[2] * b3[0] - b2[0] * b3[2], b2[0] * b3[1] - b2[1] * b3[0])
        self.att_sp = quat_from_axes(b1, b2, b3)

    def attitude_rate_control(self, q: Quat, rates: Vec3, dt: float) -> Vec3:
        """Attitude P (reduced attitude, yaw weighted) and rate PI → body torques (N m)."""
        g = self.gains
        p = self.params
        qd = self.att_sp
        # Reduced attitude: first the shortest rotation aligning the thrust axes.
        ez = quat_rotate(q, (0.0, 0.0, 1.0))
        ezd = quat_rotate(qd, (0.0, 0.0, 1.0))
        c = ez[0] * ezd[0] + ez[1] * ezd[1] + ez[2] * ezd[2]
        cx = ez[1] * ezd[2] - ez[2] * ezd[1]
        cy = ez[2] * ezd[0] - ez[0] * ezd[2]
        cz = ez[0] * ezd[1] - ez[1] * ezd[0]
        if c > -0.999:
            qr = _unit((1.0 + c, cx, cy, cz))
            qd_red = quat_multiply(qr, q)
            # Mix in the yaw part with a weight (roll/pitch have priority).
            q_mix = quat_multiply(quat_conjugate(qd_red), qd)
            w_mix = _clamp(q_mix[0], -1.0, 1.0)
            z_mix = _clamp(q_mix[3], -1.0, 1.0)
            yaw_w = _clamp(g.att_p[2] / g.att_p[0], 0.0, 1.0)
            qd = quat_multiply(
                qd_red, (math.cos(yaw_w * math.acos(w_mix)), 0.0, 0.0, math.sin(yaw_w * math.asin(z_mix)))
            )
        qe = quat_multiply(quat_conjugate(q), qd)
        sgn = 2.0 if qe[0] >= 0 else -2.0
        ex, ey, ez_ = sgn * qe[1], sgn * qe[2], sgn * qe[3]
        kp = g.att_p
        rx = _clamp(kp[0] * ex, -g.rate_max[0], g.rate_max[0])
        ry = _clamp(kp[1] * ey, -g.rate_max[1], g.rate_max[1])
        # Yaw-rate feed-forward expressed in the body frame.
        ff = quat_rotate_inverse(q, (0.0, 0.0, self.yaw_rate_ff))
        rx += ff[0]
        ry += ff[1]
        # The yaw weight already scaled the yaw error; PX4 compensates by dividing the gain by it.
        yaw_gain = kp[2] / max(_clamp(kp[2] / kp[0], 0.0, 1.0), 1e-3)
        rz = _clamp(yaw_gain * ez_ + ff[2], -g.rate_max[2], g.rate_max[2])
        torques = []
        for i, (rsp, r) in enumerate(((rx, rates[0]), (ry, rates[1]), (rz, rates[2]))):
            err = rsp - r
            self.rate_int[i] = _clamp(self.rate_int[i] + g.rate_i[i] * err * dt, -3.0, 3.0)
            alpha = g.rate_p[i] * err + self.rate_int[i]
            tau = p.inertia[i] * alpha
            torques.append(_clamp(tau, -p.max_torque[i], p.max_torque[i]))
        return torques[0], torques[1], torques[2]


# --- the whole vehicle --------------------------------------------------------------------------


class QuadSim:
    """One simulated quadrotor: truth, battery, estimator, controller and land detector.

    Call :meth:`step` every :attr:`dt` seconds of simulated time after setting :attr:`motor_mode` and
    :attr:`setpoint` (or :attr:`descend_rate` for :attr:`MotorMode.DESCEND`).
    """

    def __init__(
        self,
        params: QuadParams | None = None,
        gains: ControlGains | None = None,
        *,
        battery: BatteryParams | None = None,
        position: Vec3 = (0.0, 0.0, 0.0),
        yaw: float = 0.0,
        soc: float = 1.0,
        seed: int = 0,
        dt: float = 0.004,
        land_stages: bool = False,
    ) -> None:
        if not 0.0005 <= dt <= 0.004 + 1e-12:
            raise SimPhysicsError(f"physics tick must be between 0.5 and 4 ms (>= 250 Hz), got {dt}")
        if position[2] < 0.0:
            raise SimPhysicsError("initial position must be on the floor (down >= 0 means on the ground)")
        self.params = params or QuadParams()
        self.gains = gains or ControlGains()
        self.dt = dt
        self.rng = random.Random(seed)
        self.body = RigidBody(self.params)
        self.battery = Battery(battery, soc)
        self.estimator = Estimator(self.rng)
        self.controller = Controller(self.params, self.gains)
        self.land_detector = LandDetector(staged=land_stages)
        self.motor_mode = MotorMode.OFF
        self.setpoint = Setpoint()
        self.descend_rate = 0.7
        self.time = 0.0
        self._initial = (position, yaw)
        self.reset()

    def reset(self, position: Vec3 | None = None, yaw: float | None = None) -> None:
        """Put the vehicle back on the floor at rest (keeps the battery)."""
        pos, yw = self._initial
        if position is not None:
            pos = position
        if yaw is not None:
            yw = yaw
        self.body.position = (pos[0], pos[1], 0.0)
        self.body.velocity = (0.0, 0.0, 0.0)
        self.body.attitude = quat_from_euler(0.0, 0.0, yw)
        self.body.rates = (0.0, 0.0, 0.0)
        self.body.thrust = 0.0
        self.body.torque = (0.0, 0.0, 0.0)
        self.body.on_ground = True
        self.estimator.reset((0.0, 0.0, 0.0), yw, self.time)
        self.controller.reset()
        self.land_detector.reset(True)
        self.motor_mode = MotorMode.OFF
        self.setpoint = Setpoint()

    @property
    def landed(self) -> bool:
        """Land detector output."""
        return self.land_detector.landed

    def step(self) -> None:
        """Advance one physics tick."""
        dt = self.dt
        self.time += dt
        t = self.time
        body = self.body
        est = self.estimator
        ctrl = self.controller
        est.predict(t, dt, body)
        est.fuse_baro(dt, body.position[2])
        mode = self.motor_mode
        volt_factor = self.battery.voltage / self.battery.full_voltage
        max_thrust = self.params.max_thrust * volt_factor
        thrust_cmd = 0.0
        torque_cmd: Vec3 = (0.0, 0.0, 0.0)
        q_est = est.attitude()
        landed = self.land_detector.landed
        if mode is MotorMode.OFF:
            ctrl.reset()
        elif mode is MotorMode.IDLE or (landed and not (mode is MotorMode.FLY and self.want_takeoff())):
            # Armed on the floor with nothing asking to climb: motors at idle, controller cleared.
            ctrl.reset()
            thrust_cmd = self.params.idle_throttle * max_thrust
        else:
            if landed and ctrl.takeoff_time == math.inf:
                ctrl.takeoff_time = t  # takeoff trigger: start the smooth climb ramp
                ctrl.pos_timer = 0.0
            ctrl.pos_timer -= dt
            if ctrl.pos_timer <= 0.0:
                ctrl.pos_timer += Controller.POSITION_PERIOD
                pdt = Controller.POSITION_PERIOD
                if mode is MotorMode.FLY:
                    ctrl.position_control(self.setpoint, est, body.acceleration, est.yaw, t, pdt)
                else:
                    sp = Setpoint(velocity=(NAN, NAN, self.descend_rate), acceleration=(0.0, 0.0, NAN))
                    ctrl.position_control(sp, est, body.acceleration, est.yaw, t, pdt)
            if self.land_detector.ground_contact and not math.isnan(ctrl.vel_sp[2]):
                # PX4's position controller ("flying but ground contact"): no thrust, no integrator wind-up
                ctrl.vel_int = [0.0, 0.0, 0.0]
                ctrl.throttle_sp = self.gains.thr_min
            thrust_cmd = ctrl.throttle_sp * max_thrust  # ESC throttle: thrust scales with the voltage
            torque_cmd = ctrl.attitude_rate_control(q_est, body.rates, dt)
            if not landed and not body.on_ground:
                # On the floor the floor carries the weight: what the thrust would balance is not measured
                # (winding the thrust down after touchdown would have taught it a hover thrust of MPC_THR_MIN).
                ctrl.update_hover_estimate(dt, body.specific_force_body())
        body.step(dt, thrust_cmd, torque_cmd)
        self.battery.step(dt, body.thrust, mode is not MotorMode.OFF)
        self.land_detector.update(
            dt,
            body,
            ctrl.throttle_sp,
            ctrl.hover_est,
            mode in (MotorMode.FLY, MotorMode.DESCEND),
            self.gains,
            climb_rate_sp=ctrl.vel_sp[2],  # NaN without climb-rate control (attitude and thrust given)
        )

    def vision_from_truth(self, latency: float = 0.0, reset_counter: int = 0) -> bool:
        """Fuse the true pose as a perfect motion-capture sample measured ``latency`` seconds ago."""
        b = self.body
        return self.estimator.fuse_vision(
            self.time, self.time - latency, b.position, quat_yaw(b.attitude), None, reset_counter
        )

    def want_takeoff(self) -> bool:
        """Whether the setpoint asks to leave the ground (PX4's takeoff trigger)."""
        sp = self.setpoint
        z_est = self.estimator.out_position[2]
        pz, vz = sp.position[2], sp.velocity[2]
        if sp.attitude is not None:  # thrust above the hover estimate lifts off
            return sp.thrust == sp.thrust and sp.thrust > self.controller.hover_est
        return (pz == pz and pz < z_est - 0.2) or (pz != pz and vz == vz and vz < -0.3)

    def true_state(self) -> tuple[Vec3, Quat, Vec3, Vec3]:
        """(position NED, attitude w,x,y,z FRD→NED, velocity NED, body rates FRD)."""
        b = self.body
        return b.position, b.attitude, b.velocity, b.rates
