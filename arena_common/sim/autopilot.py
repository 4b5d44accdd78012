"""A simulated PX4 (v1.14–v1.16) multicopter speaking MAVLink 2 over a real link.

:class:`SimAutopilot` is one vehicle: it owns a pymavlink connection (``udpout:HOST:PORT`` sends to a
gateway listening with ``udpin:``, as PX4 does; ``tcpin:HOST:PORT`` waits for a gateway's ``tcp:``),
its system id, its parameters and a :class:`~arena_common.sim.physics.QuadSim`. It behaves toward the
gateway as PX4 does: heartbeats and telemetry streams, commands with acknowledgements, the parameter
protocol with bytewise INT32 encoding, external vision fusion (ODOMETRY / VISION_POSITION_ESTIMATE),
TIMESYNC, offboard setpoints and the failsafes (offboard loss, position loss, low battery).

Several vehicles share one thread: :func:`run_autopilots` (or :class:`AutopilotLoop` in the
background) calls :meth:`SimAutopilot.step` on each and ``select()``\\ s on their sockets. Time is a
:class:`SimClock` whose ``speed`` can exceed 1 for tests.

Behaviour chosen where PX4 versions differ (documented here once):

- DO_SET_MODE to OFFBOARD is refused (TEMPORARILY_REJECTED + STATUSTEXT) unless a setpoint stream of
  at least 2 Hz is running, armed or not; manual modes (MANUAL, ALTCTL, POSCTL, STABILIZED, ACRO) are
  refused because the arena never feeds manual control input.
- MAV_CMD_NAV_TAKEOFF param7 is the height above home in metres (no global frame indoors); NaN or
  ≤ 0 means MIS_TAKEOFF_ALT.
- A command retried with a higher ``confirmation`` within 5 s of an identical executed one is acked
  with the first result and not executed again; this history survives a simulated reboot.
- With a ``signing_key`` the vehicle behaves as PX4 with ``MAV_SIGN_CFG`` = 2 (signing always required):
  everything it sends is signed (link id 0), and every message it receives must be signed with the same
  key and carry a timestamp above the last one of its stream (link, system, component), except
  RADIO_STATUS, ADSB_VEHICLE and COLLISION; refused messages are counted in :attr:`SimAutopilot.refused`
  and reported by a STATUSTEXT at most every 5 s.  The streams seen are forgotten on a reboot (PX4 keeps
  them in RAM).
- SET_GPS_GLOBAL_ORIGIN addressed to the vehicle sets its EKF origin (:attr:`SimAutopilot.gps_origin`,
  lost on reboot); every SET_GPS_GLOBAL_ORIGIN is answered with GPS_GLOBAL_ORIGIN once an origin is set.
"""

from __future__ import annotations

import collections
import math
import os
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from typing import Any, ClassVar, NamedTuple

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

from arena_common.mavlink import px4
from arena_common.mavlink.px4 import ParamValue
from arena_common.mavlink.signing import PX4_UNSIGNED, LinkSigning, SigningKey
from arena_common.sim.physics import (
    BatteryParams,
    ControlGains,
    MotorMode,
    QuadParams,
    QuadSim,
    Setpoint,
    quat_from_euler,
    quat_rotate,
    quat_rotate_inverse,
    quat_yaw,
)

__all__ = [
    "AutopilotLoop",
    "SimAutopilot",
    "SimAutopilotError",
    "SimClock",
    "TimesyncFilter",
    "TruePose",
    "run_autopilots",
]

NAN = math.nan
Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class SimAutopilotError(ValueError):
    """Bad configuration of a simulated autopilot (system id, connection string, parameter)."""


class TruePose(NamedTuple):
    """The simulated vehicle's true pose, as a motion-capture system would measure it."""

    time_ns: int  # SimClock time of the pose
    position: Vec3  # arena NED, m
    q: Quat  # body FRD → arena NED, (w, x, y, z)
    velocity: Vec3  # arena NED, m/s
    rates: Vec3 = (0.0, 0.0, 0.0)  # body FRD angular velocity, rad/s


class SimClock:
    """Simulated time: wall-clock driven, ``speed`` times faster than real time.

    ``now_ns()`` starts at ``start_ns`` (default: the wall clock at creation, so that at speed 1 the
    simulated time reads like ``time.time_ns()``) and advances ``speed`` ns per real ns.
    """

    def __init__(self, speed: float = 1.0, start_ns: int | None = None) -> None:
        if not (math.isfinite(speed) and 0.01 <= speed <= 100.0):
            raise SimAutopilotError(f"clock speed must be within 0.01..100, got {speed}")
        self.speed = float(speed)
        self._t0 = time.monotonic_ns()
        self.start_ns = time.time_ns() if start_ns is None else int(start_ns)

    def now_ns(self) -> int:
        """Current simulated time in ns."""
        return self.start_ns + int((time.monotonic_ns() - self._t0) * self.speed)

    def now(self) -> float:
        """Current simulated time in seconds."""
        return self.now_ns() * 1e-9

    def real_seconds(self, sim_seconds: float) -> float:
        """Real (wall) seconds that ``sim_seconds`` of simulated time take."""
        return sim_seconds / self.speed

    def sleep(self, sim_seconds: float) -> None:
        """Sleep for ``sim_seconds`` of simulated time."""
        if sim_seconds > 0:
            time.sleep(sim_seconds / self.speed)


class TimesyncFilter:
    """PX4's TIMESYNC offset estimator: double exponential smoothing with gain scheduling.

    Offsets are in µs with ``local = remote + offset``. Samples with a round trip of 10 ms or more are
    skipped; once converged (500 accepted samples), samples deviating by more than 100 ms are rejected
    and more than 5 in a row reset the filter (a time jump on the other side).
    """

    ALPHA_INITIAL = 0.05
    BETA_INITIAL = 0.05
    ALPHA_FINAL = 0.003
    BETA_FINAL = 0.003

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget everything (reboot, time jump)."""
        self.sequence = 0
        self.offset_us = 0.0
        self.skew_us = 0.0
        self.alpha = self.ALPHA_INITIAL
        self.beta = self.BETA_INITIAL
        self.high_deviation_count = 0
        self.high_rtt_count = 0
        self.resets = 0
        self.last_rtt_us = -1

    @property
    def converged(self) -> bool:
        """Whether enough good samples were seen to trust the offset."""
        return self.sequence >= px4.TIMESYNC_CONVERGENCE_WINDOW

    def update(self, now_us: int, remote_us: int, originate_us: int) -> bool:
        """Feed one reply (our receive time, the remote's ``tc1``, our echoed ``ts1``, all µs).

        Returns whether the sample was accepted.
        """
        rtt = now_us - originate_us
        self.last_rtt_us = rtt
        if rtt < 0 or rtt >= px4.TIMESYNC_MAX_RTT_US:
            self.high_rtt_count += 1
            return False
        offset = (originate_us + now_us - 2 * remote_us) / 2.0
        deviation = abs(self.offset_us - offset)
        if self.converged and deviation > px4.TIMESYNC_MAX_DEVIATION_US:
            self.high_deviation_count += 1
            if self.high_deviation_count > px4.TIMESYNC_MAX_CONSECUTIVE_HIGH_DEVIATION:
                resets = self.resets + 1
                self.reset()
                self.resets = resets
            return False
        if not self.converged:
            progress = self.sequence / px4.TIMESYNC_CONVERGENCE_WINDOW
            p = 1.0 - math.exp(0.5 * (1.0 - 1.0 / (1.0 - progress)))
            self.alpha = p * self.ALPHA_FINAL + (1.0 - p) * self.ALPHA_INITIAL
            self.beta = p * self.BETA_FINAL + (1.0 - p) * self.BETA_INITIAL
        else:
            self.alpha, self.beta = self.ALPHA_FINAL, self.BETA_FINAL
        if self.sequence == 0:
            self.offset_us = offset
        else:
            previous = self.offset_us
            self.offset_us = self.alpha * offset + (1.0 - self.alpha) * (self.offset_us + self.skew_us)
            self.skew_us = self.beta * (self.offset_us - previous) + (1.0 - self.beta) * self.skew_us
        self.sequence += 1
        self.high_deviation_count = 0
        self.high_rtt_count = 0
        return True

    def sync_stamp(self, remote_us: int, arrival_us: int) -> int:
        """Local time of a remote timestamp once converged, else the arrival time (as PX4)."""
        if self.converged:
            return int(remote_us + self.offset_us)
        return arrival_us


class _ParamStore:
    """Parameters by name with PX4's sorted indices; values kept typed, sent bytewise."""

    def __init__(self, values: Mapping[str, tuple[ParamValue, int]]) -> None:
        self._values: dict[str, list[Any]] = {name: [value, ptype] for name, (value, ptype) in values.items()}
        self.names = sorted(self._values)
        self._index = {name: i for i, name in enumerate(self.names)}

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def __len__(self) -> int:
        return len(self.names)

    def get(self, name: str) -> ParamValue:
        return self._values[name][0]  # type: ignore[no-any-return,unused-ignore]

    def type_of(self, name: str) -> int:
        return int(self._values[name][1])

    def index_of(self, name: str) -> int:
        return self._index[name]

    def set_value(self, name: str, value: ParamValue) -> None:
        entry = self._values[name]
        if entry[1] == px4.MAV_PARAM_TYPE_REAL32:
            entry[0] = float(value)
        else:
            # Round-trip through the wire encoding to validate the range.
            entry[0] = px4.decode_param_value(px4.encode_param_value(value, entry[1]), entry[1])

    def set_wire(self, name: str, wire_value: float) -> None:
        """Store the float of a PARAM_SET bytewise in the parameter's own type (what PX4 does)."""
        entry = self._values[name]
        entry[0] = px4.decode_param_value(wire_value, entry[1])

    def wire(self, name: str) -> float:
        entry = self._values[name]
        return px4.encode_param_value(entry[0], entry[1])


_MANUAL_MAINS = (px4.MAIN_MANUAL, px4.MAIN_ALTCTL, px4.MAIN_POSCTL, px4.MAIN_STABILIZED, px4.MAIN_ACRO)
_SUPPORTED_AUTO = (px4.AUTO_TAKEOFF, px4.AUTO_LOITER, px4.AUTO_RTL, px4.AUTO_LAND)

# Telemetry streams (message id → (name, default rate Hz)), as PX4's onboard MAVLink mode.
_STREAMS: dict[int, tuple[str, float]] = {
    0: ("HEARTBEAT", 1.0),
    1: ("SYS_STATUS", 2.0),
    245: ("EXTENDED_SYS_STATE", 5.0),
    31: ("ATTITUDE_QUATERNION", 50.0),
    32: ("LOCAL_POSITION_NED", 30.0),
    331: ("ODOMETRY", 30.0),
    105: ("HIGHRES_IMU", 50.0),
    147: ("BATTERY_STATUS", 1.0),
}
_REQUESTABLE = {*_STREAMS, 148}  # AUTOPILOT_VERSION on request

_FLIGHT_SW_VERSION = (1 << 24) | (14 << 16) | (3 << 8) | 255  # 1.14.3 official
_CAPABILITIES = (
    1  # MISSION_FLOAT
    | 4  # MISSION_INT
    | 8  # COMMAND_INT
    | 16  # PARAM_ENCODE_BYTEWISE
    | 64  # SET_ATTITUDE_TARGET
    | 128  # SET_POSITION_TARGET_LOCAL_NED
    | 256  # SET_POSITION_TARGET_GLOBAL_INT
    | 8192  # MAVLINK2
)

_SENSORS = (
    0x01  # 3D gyro
    | 0x02  # 3D accel
    | 0x04  # 3D mag
    | 0x08  # absolute pressure
    | 0x80  # vision position
    | 0x8000  # motor outputs
    | 0x200000  # AHRS
    | 0x2000000  # battery
    | 0x10000000  # pre-arm check
)


class SimAutopilot:
    """One simulated PX4 quadrotor on a MAVLink 2 link.

    ``connection`` is a pymavlink connection string; the vehicle sends first like PX4, so use
    ``udpout:127.0.0.1:PORT`` (gateway on ``udpin:127.0.0.1:PORT``) or ``tcpin:127.0.0.1:PORT``
    (gateway on ``tcp:``). ``params`` overrides PX4's defaults as if stored on the vehicle. The
    vehicle starts disarmed on the floor at ``position`` (arena NED, down = 0) heading ``yaw`` rad.
    """

    COMPONENT_ID = px4.MAV_COMP_ID_AUTOPILOT1
    CONTROL_PERIOD = 0.02  # s, state machine / failsafe evaluation
    REBOOT_SECONDS = 1.0  # silent time of a simulated reboot
    RETRY_WINDOW_S = 5.0
    MAX_CATCH_UP_S = 0.25  # beyond this lag the simulation skips time instead of catching up

    def __init__(
        self,
        connection: str,
        system_id: int = 1,
        *,
        clock: SimClock | None = None,
        name: str = "",
        position: Sequence[float] = (0.0, 0.0, 0.0),
        yaw: float = 0.0,
        params: Mapping[str, ParamValue] | None = None,
        quad: QuadParams | None = None,
        gains: ControlGains | None = None,
        battery: BatteryParams | None = None,
        soc: float = 1.0,
        seed: int = 0,
        signing_key: SigningKey | None = None,
    ) -> None:
        if not 1 <= int(system_id) <= 250:
            raise SimAutopilotError(f"system id must be within 1..250, got {system_id}")
        if len(position) != 3 or position[2] < 0:
            raise SimAutopilotError(f"start position must be (north, east, down>=0), got {tuple(position)}")
        self.clock = clock or SimClock()
        self.name = name or f"sim{system_id}"
        defaults = dict(px4.PX4_DEFAULTS)
        defaults["MAV_SYS_ID"] = (int(system_id), px4.MAV_PARAM_TYPE_INT32)
        self.params = _ParamStore(defaults)
        for pname, value in (params or {}).items():
            if pname not in self.params:
                raise SimAutopilotError(f"unknown parameter {pname!r} for the simulated PX4")
            try:
                self.params.set_value(pname, value)
            except px4.Px4Error as exc:
                raise SimAutopilotError(f"parameter {pname}: {exc}") from None
        self.params.set_value("MAV_SYS_ID", int(system_id))
        self.system_id = int(system_id)
        self._start = (float(position[0]), float(position[1]), 0.0)
        self._start_yaw = float(yaw)
        self._base_gains = gains or ControlGains()
        self.sim = QuadSim(
            quad, self._base_gains, battery=battery, position=self._start, yaw=yaw, soc=soc, seed=seed
        )
        self.timesync = TimesyncFilter()
        self.statustexts: deque[tuple[int, str]] = deque(maxlen=200)
        self._command_history: dict[tuple[Any, ...], tuple[float, int, int]] = {}
        self._lock = threading.Lock()
        self._true_pose = TruePose(
            self.clock.now_ns(), self._start, quat_from_euler(0, 0, yaw), (0.0, 0.0, 0.0)
        )
        try:
            self.conn = mavutil.mavlink_connection(
                connection, source_system=self.system_id, source_component=self.COMPONENT_ID, dialect="common"
            )
        except (OSError, ValueError) as exc:
            raise SimAutopilotError(f"cannot open MAVLink connection {connection!r}: {exc}") from exc
        if not type(self.conn.mav).__module__.startswith("pymavlink.dialects.v20."):
            self.conn.close()
            raise SimAutopilotError("pymavlink was loaded for MAVLink 1; import this module before pymavlink")
        self.connection = connection
        self.signing: LinkSigning | None = None
        if signing_key is not None:
            self.signing = LinkSigning(signing_key, link_id=0, allow_unsigned=PX4_UNSIGNED)
            self.signing.attach(self.conn.mav)
        #: Refused input by "reason MESSAGE" (``"unsigned COMMAND_LONG"``, ``"replayed ODOMETRY"``…).
        self.refused: collections.Counter[str] = collections.Counter()
        self._refusal_text_at = -math.inf
        self.origin_sets = 0  # SET_GPS_GLOBAL_ORIGIN taken, over reboots
        #: Called with the true pose after every physics tick (in the thread that steps), if set.
        self.on_tick: Callable[[TruePose], None] | None = None
        self._closed = False
        self._boot()

    # ------------------------------------------------------------------ lifecycle

    def _boot(self) -> None:
        """(Re)start the flight stack: state, estimator and streams; parameters persist."""
        self._boot_ns = self.clock.now_ns()
        self.system_id = int(self.params.get("MAV_SYS_ID"))
        self.conn.mav.srcSystem = self.system_id
        sim = self.sim
        sim.time = 0.0
        sim.reset(self._start, self._start_yaw)
        self._apply_params(boot=True)
        self.timesync.reset()
        self.armed = False
        self.terminated = False
        self._user_mode = (px4.MAIN_AUTO, px4.AUTO_LOITER)
        self._failsafe: tuple[str, str] | None = None  # (action, cause)
        self._nav: dict[str, Any] = {}
        self._enter_nav()
        self._home: Vec3 = (0.0, 0.0, 0.0)
        self._armed_at = 0.0
        self._flew_since_arming = False
        self._landed_since = 0.0
        self._sp_times: deque[float] = deque(maxlen=64)
        self._offboard_sp = Setpoint()
        self._frame_warned_at = -math.inf
        self._battery_level = 0  # 0 ok, 1 low, 2 critical, 3 emergency
        self._battery_action_level = 0
        self._xy_valid_prev = False
        self._vision_prev = False
        self._next_control = 0.0
        self._rebooting_until_ns = 0
        self._param_queue: deque[int] = deque()
        self._pending_requests: list[int] = []
        self._next_due = {mid: 0.0 for mid in _STREAMS}
        self._intervals = {mid: 1.0 / rate for mid, (_, rate) in _STREAMS.items()}
        self._next_timesync = 0.1
        self.skipped_time_s = 0.0
        self.ignored_mocap = 0
        self.last_vision_sample_us = -1
        self.messages_in = 0
        self.gps_origin: tuple[float, float, float] | None = None  # (lat deg, lon deg, alt m), EKF origin
        if self.signing is not None:
            self.signing.forget_streams()

    def close(self) -> None:
        """Close the MAVLink connection."""
        if not self._closed:
            self._closed = True
            self.conn.close()

    def __enter__(self) -> SimAutopilot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def fileno(self) -> int | None:
        """File descriptor to wait on for input (changes when a TCP client connects)."""
        if self._closed:
            return None
        conn = self.conn
        port = getattr(conn, "port", None)
        if isinstance(conn, mavutil.mavtcpin) and port is None:
            return conn.listen.fileno()
        return port.fileno() if port is not None else None

    # ------------------------------------------------------------------ public state

    @property
    def time_s(self) -> float:
        """Vehicle time since (re)boot, s (its physics time)."""
        return self.sim.time

    @property
    def mode(self) -> tuple[int, int]:
        """Reported PX4 (main, sub) mode: a failsafe action overrides the user's choice."""
        if self.terminated:
            return (px4.MAIN_TERMINATION, 0)
        if self._failsafe is not None:
            return _ACTION_MODES[self._failsafe[0]]
        return self._user_mode

    @property
    def mode_name(self) -> str:
        """Name of :attr:`mode`, e.g. ``"OFFBOARD"``."""
        return px4.mode_name(*self.mode)

    @property
    def landed(self) -> bool:
        """Land detector state."""
        return self.sim.landed

    @property
    def landed_state(self) -> int:
        """MAV_LANDED_STATE as reported in EXTENDED_SYS_STATE."""
        if self.sim.landed:
            return px4.MAV_LANDED_STATE_ON_GROUND
        main, sub = self.mode
        if main == px4.MAIN_AUTO and sub == px4.AUTO_TAKEOFF:
            return px4.MAV_LANDED_STATE_TAKEOFF
        if main == px4.MAIN_AUTO and sub == px4.AUTO_LAND:
            return px4.MAV_LANDED_STATE_LANDING
        return px4.MAV_LANDED_STATE_IN_AIR

    def param(self, name: str) -> ParamValue:
        """Current value of a parameter."""
        if name not in self.params:
            raise SimAutopilotError(f"unknown parameter {name!r}")
        return self.params.get(name)

    def true_pose(self) -> TruePose:
        """The true pose (thread-safe snapshot, updated every physics tick)."""
        return self._true_pose

    def set_battery(self, soc: float) -> None:
        """Set the battery state of charge (0..1), e.g. to rehearse a low-battery landing."""
        if not 0.0 <= soc <= 1.0:
            raise SimAutopilotError(f"state of charge must be within 0..1, got {soc}")
        self.sim.battery.soc = soc

    # ------------------------------------------------------------------ main step

    def step(self) -> float:
        """Advance to the clock's present: physics, input, control, telemetry.

        Returns the simulated seconds until this vehicle next needs a step.
        """
        if self._closed:
            return 1.0
        if self.signing is not None:
            self.signing.refresh()
        now_ns = self.clock.now_ns()
        if self._rebooting_until_ns:
            self._drain_input()
            if now_ns < self._rebooting_until_ns:
                return (self._rebooting_until_ns - now_ns) * 1e-9
            self._boot()
            now_ns = self.clock.now_ns()
        t = (now_ns - self._boot_ns) * 1e-9
        sim = self.sim
        dt = sim.dt
        if t - sim.time > self.MAX_CATCH_UP_S:
            skipped = t - sim.time - dt
            self.skipped_time_s += skipped
            sim.time += skipped
        on_tick = self.on_tick
        while sim.time + dt <= t + 1e-9:
            if sim.time >= self._next_control:
                self._next_control = sim.time + self.CONTROL_PERIOD
                self._control(sim.time)
            sim.step()
            if on_tick is not None:
                on_tick(self._update_true_pose())
        if on_tick is None:
            self._update_true_pose()
        self._read_input(sim.time)
        self._send_due(sim.time)
        return max(0.0, sim.time + dt - t)

    def _update_true_pose(self) -> TruePose:
        pos, q, vel, rates = self.sim.true_state()
        pose = TruePose(self._boot_ns + int(self.sim.time * 1e9), pos, q, vel, rates)
        self._true_pose = pose
        return pose

    def _drain_input(self) -> None:
        for _ in range(1000):
            if self._recv() is None:
                break

    def _recv(self) -> Any:
        conn = self.conn
        try:
            msg = conn.recv_msg()
        except OSError:
            return None
        if msg is None and isinstance(conn, mavutil.mavtcpin) and conn.port is not None:
            self._check_tcp_peer(conn)
        return msg

    @staticmethod
    def _check_tcp_peer(conn: Any) -> None:
        """pymavlink does not notice a TCP peer closing: detect EOF and go back to listening."""
        try:
            data = conn.port.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if data == b"":
            conn.port.close()
            conn.port = None
            conn.fd = conn.listen.fileno()

    # ------------------------------------------------------------------ parameters applied

    def _apply_params(self, boot: bool = False) -> None:
        p = self.params
        est = self.sim.estimator
        est.ev_ctrl = int(p.get("EKF2_EV_CTRL"))
        est.ev_delay_s = max(0.0, float(p.get("EKF2_EV_DELAY"))) * 1e-3
        est.baro_enabled = int(p.get("EKF2_BARO_CTRL")) != 0
        est.hgt_ref_vision = int(p.get("EKF2_HGT_REF")) == px4.EKF2_HGT_REF_VISION
        if boot:  # EKF2_MAG_TYPE needs a reboot in PX4
            est.mag_enabled = int(p.get("EKF2_MAG_TYPE")) != px4.EKF2_MAG_TYPE_NONE
        g = self._base_gains
        gains = replace(
            g,
            xy_p=float(p.get("MPC_XY_P")),
            z_p=float(p.get("MPC_Z_P")),
            hover_throttle=float(p.get("MPC_THR_HOVER")),
            vel_max_xy=float(p.get("MPC_XY_VEL_MAX")),
            vel_max_up=float(p.get("MPC_Z_VEL_MAX_UP")),
            vel_max_dn=float(p.get("MPC_Z_VEL_MAX_DN")),
            tilt_max_deg=float(p.get("MPC_TILTMAX_AIR")),
            yaw_rate_auto_max=math.radians(float(p.get("MPC_YAWRAUTO_MAX"))),
        )
        self.sim.gains = gains
        self.sim.controller.gains = gains

    # ------------------------------------------------------------------ state machine (50 Hz)

    def _pos_ok(self) -> bool:
        est = self.sim.estimator
        return est.xy_valid and est.z_valid

    def _offboard_stream_ok(self, t: float) -> bool:
        """A setpoint stream is running: last within COM_OF_LOSS_T and at least 2 in the last second."""
        times = self._sp_times
        if not times or t - times[-1] > float(self.params.get("COM_OF_LOSS_T")):
            return False
        return sum(1 for ts in times if t - ts <= 1.0) >= 2

    def _control(self, t: float) -> None:
        sim = self.sim
        est = sim.estimator
        # Vision / position state changes.
        fusing = est.vision_fusing
        if fusing != self._vision_prev:
            self._vision_prev = fusing
            self._statustext(
                px4.MAV_SEVERITY_INFO, "EKF: vision fusion " + ("started" if fusing else "stopped")
            )
        xy_valid = est.xy_valid
        if self._xy_valid_prev and not xy_valid and self.armed:
            self._statustext(px4.MAV_SEVERITY_CRITICAL, "Position estimate lost")
        self._xy_valid_prev = xy_valid

        self._battery_checks(t)
        if self.armed and not self.terminated:
            self._failsafe_checks(t)
        self._auto_disarm(t)
        self._navigate(t)

    def _battery_checks(self, t: float) -> None:
        soc = self.sim.battery.soc
        p = self.params
        low, crit, emer = (
            float(p.get("BAT_LOW_THR")),
            float(p.get("BAT_CRIT_THR")),
            float(p.get("BAT_EMERGEN_THR")),
        )
        level = 3 if soc <= emer else 2 if soc <= crit else 1 if soc <= low else 0
        if level > self._battery_level:
            texts = {
                1: (px4.MAV_SEVERITY_WARNING, "Low battery level"),
                2: (px4.MAV_SEVERITY_CRITICAL, "Critical battery level"),
                3: (px4.MAV_SEVERITY_EMERGENCY, "Emergency battery level"),
            }
            sev, text = texts[level]
            self._statustext(sev, f"{text}: {soc * 100:.0f}% remaining")
        self._battery_level = level

    def _battery_action(self) -> str | None:
        act = int(self.params.get("COM_LOW_BAT_ACT"))
        level = self._battery_level
        if act == 2 and level >= 2:
            return "land"
        if act == 3 and level >= 3:
            return "land"
        if act == 3 and level == 2:
            return "rtl"
        return None

    def _failsafe_checks(self, t: float) -> None:
        sim = self.sim
        in_air = not sim.landed
        user_main = self._user_mode[0]
        needs_position = user_main == px4.MAIN_OFFBOARD or user_main == px4.MAIN_AUTO
        current = self._failsafe
        # Position loss while flying a mode that needs it: descend (reported as AUTO.LAND).
        if in_air and needs_position and not self._pos_ok():
            if current is None or current[1] != "position":
                self._set_failsafe("descend", "position", "Failsafe: no position estimate, descending")
            return
        # Battery.
        bat = self._battery_action()
        if bat is not None and self._battery_level > self._battery_action_level:
            self._battery_action_level = self._battery_level
            if in_air:
                self._set_failsafe(bat, "battery", f"Failsafe: low battery, {_VERBS[bat]}")
                return
        # Offboard loss.
        if user_main == px4.MAIN_OFFBOARD:
            last = self._sp_times[-1] if self._sp_times else -math.inf
            lost = t - last > float(self.params.get("COM_OF_LOSS_T"))
            if lost and current is None:
                action = _OBL_ACTIONS.get(int(self.params.get("COM_OBL_RC_ACT")), "hold")
                self._set_failsafe(action, "offboard", f"Failsafe: no offboard signal, {_VERBS[action]}")
            elif not lost and current is not None and current[1] == "offboard":
                # PX4 clears the offboard-loss failsafe when the stream comes back.
                self._failsafe = None
                self._statustext(px4.MAV_SEVERITY_INFO, "Offboard signal regained")
                self._enter_nav()

    def _set_failsafe(self, action: str, cause: str, text: str) -> None:
        self._statustext(px4.MAV_SEVERITY_CRITICAL, text)
        if action == "terminate":
            self._terminate()
            return
        if action == "disarm":
            self._disarm("failsafe", forced=True)
            return
        self._failsafe = (action, cause)
        self._enter_nav()

    def _terminate(self) -> None:
        self.terminated = True
        self._failsafe = None
        self.sim.motor_mode = MotorMode.OFF
        self._statustext(px4.MAV_SEVERITY_EMERGENCY, "Flight termination active")

    def _auto_disarm(self, t: float) -> None:
        if not self.armed:
            return
        sim = self.sim
        if not sim.landed:
            self._flew_since_arming = True
            self._landed_since = t
            return
        if self.terminated:
            self._disarm("terminated", forced=True)
            return
        disarm_land = float(self.params.get("COM_DISARM_LAND"))
        prflt = float(self.params.get("COM_DISARM_PRFLT"))
        if self._flew_since_arming:
            if disarm_land > 0 and t - self._landed_since >= disarm_land:
                self._statustext(px4.MAV_SEVERITY_INFO, "Landing detected")
                self._disarm("landing", forced=True)
        elif prflt > 0 and t - self._armed_at >= prflt:
            self._statustext(px4.MAV_SEVERITY_INFO, "Disarmed by auto preflight disarming")
            self._disarm("preflight", forced=True)

    # ------------------------------------------------------------------ navigation

    def _enter_nav(self) -> None:
        """Initialise the behaviour of the current (reported) mode from the present estimate."""
        est = self.sim.estimator
        self._nav = {
            "mode": self.mode,
            "hold": est.position,
            "yaw": est.yaw,
            "phase": "return",
        }
        if self.mode == (px4.MAIN_AUTO, px4.AUTO_RTL):
            home = self._home
            dist = math.hypot(est.position[0] - home[0], est.position[1] - home[1])
            alt = est.position[2]
            if dist > float(self.params.get("RTL_MIN_DIST")):
                alt = min(alt, home[2] - float(self.params.get("RTL_RETURN_ALT")))
            self._nav["alt"] = alt

    def _navigate(self, t: float) -> None:
        sim = self.sim
        if not self.armed or self.terminated:
            sim.motor_mode = MotorMode.OFF
            return
        main, sub = self.mode
        if self._nav.get("mode") != (main, sub):
            self._enter_nav()
        nav = self._nav
        est = sim.estimator
        if self._failsafe is not None and self._failsafe[0] == "descend" and not self._pos_ok():
            sim.motor_mode = MotorMode.DESCEND
            sim.descend_rate = float(self.params.get("MPC_LAND_SPEED"))
            return
        sim.motor_mode = MotorMode.FLY
        if main == px4.MAIN_OFFBOARD:
            sim.setpoint = self._offboard_sp
        elif (main, sub) == (px4.MAIN_AUTO, px4.AUTO_TAKEOFF):
            target = nav.get("target")
            if target is None:
                alt = nav.get("alt", float(self.params.get("MIS_TAKEOFF_ALT")))
                hold = nav["hold"]
                target = (hold[0], hold[1], self._home[2] - alt)
                nav["target"] = target
                self._statustext(px4.MAV_SEVERITY_INFO, f"Takeoff to {alt:.1f} m above home")
            sim.setpoint = Setpoint.hold(target, nav["yaw"])
            if abs(est.position[2] - target[2]) < 0.1 and not sim.landed:
                self._user_mode = (px4.MAIN_AUTO, px4.AUTO_LOITER)
                self._enter_nav()
                self._nav["hold"] = target
        elif (main, sub) == (px4.MAIN_AUTO, px4.AUTO_LAND):
            hold = nav["hold"]
            sim.setpoint = Setpoint(
                position=(hold[0], hold[1], NAN),
                velocity=(NAN, NAN, float(self.params.get("MPC_LAND_SPEED"))),
                yaw=nav["yaw"],
            )
        elif (main, sub) == (px4.MAIN_AUTO, px4.AUTO_RTL):
            home = self._home
            if nav["phase"] == "return":
                p = est.position
                dx, dy = home[0] - p[0], home[1] - p[1]
                dist = math.hypot(dx, dy)
                if dist < 0.3:
                    nav["phase"] = "land"
                    nav["hold"] = (home[0], home[1], p[2])
                else:
                    # Carrot toward home: limits the speed to about MPC_XY_CRUISE.
                    step = min(dist, float(self.params.get("MPC_XY_CRUISE")))
                    carrot = (p[0] + dx / dist * step, p[1] + dy / dist * step, nav["alt"])
                    sim.setpoint = Setpoint.hold(carrot, nav["yaw"])
            if nav["phase"] == "land":
                hold = nav["hold"]
                sim.setpoint = Setpoint(
                    position=(hold[0], hold[1], NAN),
                    velocity=(NAN, NAN, float(self.params.get("MPC_LAND_SPEED"))),
                    yaw=nav["yaw"],
                )
        else:  # AUTO.LOITER and anything else: hold where the mode started
            sim.setpoint = Setpoint.hold(nav["hold"], nav["yaw"])

    # ------------------------------------------------------------------ arming

    def _arm_denial(self, t: float) -> list[str]:
        """Reasons (STATUSTEXT lines) arming is refused, empty when it may arm."""
        p = self.params
        est = self.sim.estimator
        if self.terminated:
            return ["Arming denied: flight terminated", "Reboot the vehicle to fly again"]
        reasons: list[str] = []
        if int(p.get("COM_RC_IN_MODE")) != px4.COM_RC_IN_MODE_DISABLED:
            reasons.append("Preflight Fail: No manual control input")
        if not self._pos_ok():
            reasons.append("Preflight Fail: No valid position estimate")
            ev_ctrl = int(p.get("EKF2_EV_CTRL"))
            if not ev_ctrl & px4.EV_CTRL_HPOS:
                reasons.append(f"Vision position not fused: EKF2_EV_CTRL={ev_ctrl}")
            elif self.last_vision_sample_us < 0 and not est.vision_fusing:
                reasons.append("No external vision (ODOMETRY) received")
            else:
                reasons.append("External vision stopped or too slow")
        if self._battery_level >= 2:
            reasons.append("Preflight Fail: battery too low")
        main, _ = self._user_mode
        if main == px4.MAIN_OFFBOARD and not self._offboard_stream_ok(t):
            reasons.append("Arming denied: no offboard signal")
        return reasons

    def _arm(self, t: float) -> None:
        takeoff_alt = self._nav.get("alt")
        self.armed = True
        self._armed_at = t
        self._flew_since_arming = False
        self._landed_since = t
        self._failsafe = None
        self._battery_action_level = self._battery_level
        self._home = self.sim.estimator.position
        self.sim.controller.reset()
        self._enter_nav()
        if takeoff_alt is not None and self._user_mode == (px4.MAIN_AUTO, px4.AUTO_TAKEOFF):
            self._nav["alt"] = takeoff_alt  # a takeoff commanded before arming keeps its altitude
        self._statustext(px4.MAV_SEVERITY_INFO, "Armed")

    def _disarm(self, why: str, forced: bool) -> None:
        was_in_air = not self.sim.landed
        self.armed = False
        self.sim.motor_mode = MotorMode.OFF
        self._failsafe = None
        if forced and was_in_air:
            self._statustext(px4.MAV_SEVERITY_CRITICAL, "Motors killed in the air")
        self._statustext(px4.MAV_SEVERITY_INFO, f"Disarmed by {why}")

    # ------------------------------------------------------------------ input

    def _read_input(self, t: float) -> None:
        handlers = self._handlers
        for _ in range(500):
            msg = self._recv()
            if msg is None:
                return
            if self._rebooting_until_ns:
                continue
            if self.signing is not None and not self._authentic(msg, t):
                continue
            handler = handlers.get(msg.get_msgId())
            if handler is not None:
                self.messages_in += 1
                handler(self, msg, t)

    def _authentic(self, msg: Any, t: float) -> bool:
        """Whether a received message passes the signing rules (PX4 drops those that do not)."""
        assert self.signing is not None
        msgid = msg.get_msgId()
        if msgid < 0:
            return False  # bad data
        reason = self.signing.check(msg.get_msgbuf(), msgid, msg.get_srcSystem(), msg.get_srcComponent())
        if reason is None:
            return True
        name = msg.get_type()
        self.refused[f"{reason} {name}"] += 1
        if t - self._refusal_text_at >= 5.0:
            self._refusal_text_at = t
            self._statustext(px4.MAV_SEVERITY_WARNING, f"Signing: refused {reason} {name}")
        return False

    def _addressed(self, target_system: int, target_component: int, allow_broadcast: bool) -> bool:
        if target_system == self.system_id:
            return target_component in (0, self.COMPONENT_ID)
        return allow_broadcast and target_system == 0 and target_component in (0, self.COMPONENT_ID)

    def _on_command_long(self, msg: Any, t: float) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._on_command(msg, msg.command, params, msg.confirmation, t)

    def _on_command_int(self, msg: Any, t: float) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._on_command(msg, msg.command, params, 0, t)

    def _on_command(
        self, msg: Any, command: int, params: tuple[float, ...], confirmation: int, t: float
    ) -> None:
        broadcast_ok = command in (px4.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 519)
        if not self._addressed(msg.target_system, msg.target_component, broadcast_ok):
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        key = (src, command, tuple(p if p == p else "nan" for p in params))
        now = self.clock.now()  # the shared clock, so that the history survives a reboot
        previous = self._command_history.get(key)
        if previous is not None and confirmation > 0:
            when, result, prev_conf = previous
            if now - when <= self.RETRY_WINDOW_S and confirmation > prev_conf:
                # A retry of a command already executed: acknowledge again, do not run it twice.
                self._command_history[key] = (when, result, confirmation)
                self._ack(command, result, src)
                return
        result = self._execute(command, params, t)
        self._command_history[key] = (now, result, confirmation)
        if len(self._command_history) > 64:
            oldest = min(self._command_history, key=lambda k: self._command_history[k][0])
            del self._command_history[oldest]
        self._ack(command, result, src)

    def _ack(self, command: int, result: int, src: tuple[int, int]) -> None:
        self.conn.mav.command_ack_send(command, result, 0, 0, src[0], src[1])

    def _execute(self, command: int, p: tuple[float, ...], t: float) -> int:
        R = px4
        if command == R.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._cmd_arm(p, t)
        if command == R.MAV_CMD_DO_SET_MODE:
            return self._cmd_set_mode(p, t)
        if command == R.MAV_CMD_NAV_TAKEOFF:
            alt = p[6] if math.isfinite(p[6]) and p[6] > 0 else float(self.params.get("MIS_TAKEOFF_ALT"))
            result = self._change_mode((R.MAIN_AUTO, R.AUTO_TAKEOFF), t)
            if result == R.MAV_RESULT_ACCEPTED:
                self._nav["alt"] = alt
            return result
        if command == R.MAV_CMD_NAV_LAND:
            return self._change_mode((R.MAIN_AUTO, R.AUTO_LAND), t)
        if command == R.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._change_mode((R.MAIN_AUTO, R.AUTO_RTL), t)
        if command == R.MAV_CMD_DO_FLIGHTTERMINATION:
            if p[0] > 0.5:
                if not self.terminated:
                    self._terminate()
                return R.MAV_RESULT_ACCEPTED
            return R.MAV_RESULT_ACCEPTED
        if command == R.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            if int(p[0]) != 1:
                return R.MAV_RESULT_UNSUPPORTED
            if self.armed:
                self._statustext(R.MAV_SEVERITY_CRITICAL, "Reboot denied: vehicle armed")
                return R.MAV_RESULT_DENIED
            self._statustext(R.MAV_SEVERITY_INFO, "Rebooting")
            self._rebooting_until_ns = self.clock.now_ns() + int(self.REBOOT_SECONDS * 1e9)
            return R.MAV_RESULT_ACCEPTED
        if command == R.MAV_CMD_SET_MESSAGE_INTERVAL:
            mid, interval_us = int(p[0]), p[1]
            if mid not in _STREAMS:
                return R.MAV_RESULT_FAILED
            if interval_us < 0:
                self._intervals[mid] = math.inf
            elif interval_us == 0:
                self._intervals[mid] = 1.0 / _STREAMS[mid][1]
            else:
                self._intervals[mid] = max(interval_us * 1e-6, 0.002)
            self._next_due[mid] = t
            return R.MAV_RESULT_ACCEPTED
        if command == R.MAV_CMD_REQUEST_MESSAGE:
            mid = int(p[0])
            if mid not in _REQUESTABLE:
                return R.MAV_RESULT_FAILED
            self._pending_requests.append(mid)
            return R.MAV_RESULT_ACCEPTED
        if command == R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._pending_requests.append(148)
            return R.MAV_RESULT_ACCEPTED
        return R.MAV_RESULT_UNSUPPORTED

    def _cmd_arm(self, p: tuple[float, ...], t: float) -> int:
        R = px4
        want, force = p[0], round(p[1]) == R.ARM_DISARM_FORCE_MAGIC
        if want not in (0.0, 1.0):
            return R.MAV_RESULT_DENIED
        if want == 1.0:
            if self.armed:
                return R.MAV_RESULT_ACCEPTED
            reasons = [] if force and not self.terminated else self._arm_denial(t)
            if reasons:
                for line in reasons:
                    self._statustext(R.MAV_SEVERITY_CRITICAL, line)
                return R.MAV_RESULT_TEMPORARILY_REJECTED
            self._arm(t)
            return R.MAV_RESULT_ACCEPTED
        if not self.armed:
            return R.MAV_RESULT_ACCEPTED
        if not self.sim.landed and not force:
            self._statustext(R.MAV_SEVERITY_CRITICAL, "Disarming denied: not landed")
            return R.MAV_RESULT_TEMPORARILY_REJECTED
        self._disarm("external command", forced=force)
        return R.MAV_RESULT_ACCEPTED

    def _cmd_set_mode(self, p: tuple[float, ...], t: float) -> int:
        R = px4
        base, main, sub = int(p[0]), int(p[1]), int(p[2])
        if not base & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            self._statustext(R.MAV_SEVERITY_CRITICAL, "Mode change rejected: custom mode only")
            return R.MAV_RESULT_DENIED
        if main == R.MAIN_AUTO and sub == 0:
            sub = R.AUTO_LOITER
        if main != R.MAIN_AUTO:
            sub = 0
        return self._change_mode((main, sub), t)

    def _change_mode(self, mode: tuple[int, int], t: float) -> int:
        """Switch the user's mode if its requirements are met; STATUSTEXT says why not."""
        R = px4
        main, sub = mode
        name = R.mode_name(main, sub)
        reason: str | None = None
        if self.terminated:
            reason = "flight terminated"
        elif main in _MANUAL_MAINS:
            reason = "no manual control input"
        elif main == R.MAIN_OFFBOARD:
            if not self._offboard_stream_ok(t):
                reason = "no setpoint stream"
            elif not self._pos_ok():
                reason = "no position estimate"
        elif main == R.MAIN_AUTO and sub in _SUPPORTED_AUTO:
            if not self._pos_ok():
                reason = "no position estimate"
        else:
            reason = "mode not supported"
        if reason is not None:
            self._statustext(R.MAV_SEVERITY_CRITICAL, f"{name} rejected: {reason}")
            return R.MAV_RESULT_TEMPORARILY_REJECTED
        self._user_mode = (main, sub)
        self._failsafe = None
        self._enter_nav()
        return R.MAV_RESULT_ACCEPTED

    def _on_param_request_list(self, msg: Any, t: float) -> None:
        if self._addressed(msg.target_system, msg.target_component, False):
            self._param_queue.extend(range(len(self.params)))

    def _on_param_request_read(self, msg: Any, t: float) -> None:
        if not self._addressed(msg.target_system, msg.target_component, False):
            return
        if msg.param_index >= 0:
            if msg.param_index < len(self.params):
                self._send_param(self.params.names[msg.param_index])
            return
        name = px4.param_name_from_field(msg.param_id)
        if name in self.params:
            self._send_param(name)
        else:
            self._statustext(px4.MAV_SEVERITY_WARNING, f"[pm] unknown param: {name}")

    def _on_param_set(self, msg: Any, t: float) -> None:
        if not self._addressed(msg.target_system, msg.target_component, False):
            return
        name = px4.param_name_from_field(msg.param_id)
        if name not in self.params:
            self._statustext(px4.MAV_SEVERITY_WARNING, f"[pm] unknown param: {name}")
            return
        self.params.set_wire(name, msg.param_value)
        self._apply_params()
        self._send_param(name)

    def _send_param(self, name: str) -> None:
        self.conn.mav.param_value_send(
            px4.param_name_bytes(name),
            self.params.wire(name),
            self.params.type_of(name),
            len(self.params),
            self.params.index_of(name),
        )

    def _on_set_position_target(self, msg: Any, t: float) -> None:
        if not self._addressed(msg.target_system, msg.target_component, True):
            return
        if msg.coordinate_frame != px4.MAV_FRAME_LOCAL_NED:
            if t - self._frame_warned_at > 5.0:
                self._frame_warned_at = t
                self._statustext(
                    px4.MAV_SEVERITY_WARNING, f"Setpoint frame {msg.coordinate_frame} unsupported"
                )
            return
        m = msg.type_mask
        pos = (
            NAN if m & px4.TYPEMASK_X_IGNORE else msg.x,
            NAN if m & px4.TYPEMASK_Y_IGNORE else msg.y,
            NAN if m & px4.TYPEMASK_Z_IGNORE else msg.z,
        )
        vel = (
            NAN if m & px4.TYPEMASK_VX_IGNORE else msg.vx,
            NAN if m & px4.TYPEMASK_VY_IGNORE else msg.vy,
            NAN if m & px4.TYPEMASK_VZ_IGNORE else msg.vz,
        )
        force = bool(m & px4.TYPEMASK_FORCE_SET)
        acc = (
            NAN if m & px4.TYPEMASK_AX_IGNORE or force else msg.afx,
            NAN if m & px4.TYPEMASK_AY_IGNORE or force else msg.afy,
            NAN if m & px4.TYPEMASK_AZ_IGNORE or force else msg.afz,
        )
        if all(c != c for c in (*pos, *vel, *acc)):
            return  # nothing to control: not a setpoint
        yaw = NAN if m & px4.TYPEMASK_YAW_IGNORE else msg.yaw
        yaw_rate = NAN if m & px4.TYPEMASK_YAW_RATE_IGNORE else msg.yaw_rate
        self._offboard_sp = Setpoint(position=pos, velocity=vel, acceleration=acc, yaw=yaw, yaw_rate=yaw_rate)
        self._sp_times.append(t)
        if self.mode[0] == px4.MAIN_OFFBOARD and self.armed:
            self.sim.setpoint = self._offboard_sp

    def _on_odometry(self, msg: Any, t: float) -> None:
        if msg.estimator_type not in px4.EV_FUSED_ESTIMATOR_TYPES:
            if msg.estimator_type == px4.MAV_ESTIMATOR_TYPE_MOCAP:
                self.ignored_mocap += 1  # PX4 routes MOCAP to a topic EKF2 does not fuse
            return
        if msg.frame_id not in (px4.MAV_FRAME_LOCAL_NED, px4.MAV_FRAME_LOCAL_FRD):
            return
        if msg.quality < int(self.params.get("EKF2_EV_QMIN")) and msg.quality >= 0:
            return
        if msg.quality < 0:
            return  # odometry failed
        q: Quat = (float(msg.q[0]), float(msg.q[1]), float(msg.q[2]), float(msg.q[3]))
        q_ok = all(math.isfinite(c) for c in q) and abs(sum(c * c for c in q) - 1.0) < 0.1
        xyz: Vec3 = (msg.x, msg.y, msg.z)
        pos = xyz if all(math.isfinite(c) for c in xyz) else None
        yaw = quat_yaw(q) if q_ok else None
        vel: Vec3 | None = None
        v = (msg.vx, msg.vy, msg.vz)
        if all(math.isfinite(c) for c in v):
            if msg.child_frame_id in (
                px4.MAV_FRAME_BODY_FRD,
                px4.MAV_FRAME_BODY_NED,
                px4.MAV_FRAME_BODY_OFFSET_NED,
            ):
                vel = quat_rotate(q, v) if q_ok else None
            elif msg.child_frame_id in (px4.MAV_FRAME_LOCAL_NED, px4.MAV_FRAME_LOCAL_FRD):
                vel = v
        self._fuse_vision(t, msg.time_usec, pos, yaw, vel, msg.reset_counter)

    def _on_vision_position_estimate(self, msg: Any, t: float) -> None:
        xyz: Vec3 = (msg.x, msg.y, msg.z)
        pos = xyz if all(math.isfinite(c) for c in xyz) else None
        yaw = msg.yaw if math.isfinite(msg.yaw) else None
        self._fuse_vision(t, msg.usec, pos, yaw, None, msg.reset_counter)

    def _fuse_vision(
        self,
        t: float,
        time_usec: int,
        pos: Vec3 | None,
        yaw: float | None,
        vel: Vec3 | None,
        reset_counter: int,
    ) -> None:
        arrival_us = int(t * 1e6)
        sample_us = self.timesync.sync_stamp(int(time_usec), arrival_us)
        self.last_vision_sample_us = sample_us
        self.sim.estimator.fuse_vision(t, sample_us * 1e-6, pos, yaw, vel, reset_counter)

    def _on_timesync(self, msg: Any, t: float) -> None:
        now_ns = int(t * 1e9)
        if msg.tc1 == 0:
            self.conn.mav.timesync_send(now_ns, msg.ts1)
        elif msg.tc1 > 0:
            self.timesync.update(now_ns // 1000, msg.tc1 // 1000, msg.ts1 // 1000)

    def _on_set_gps_global_origin(self, msg: Any, t: float) -> None:
        if msg.target_system == self.system_id:
            self.gps_origin = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            self.origin_sets += 1
        origin = self.gps_origin
        if origin is not None:  # PX4 answers every request with its origin, when it has one
            self.conn.mav.gps_global_origin_send(
                round(origin[0] * 1e7), round(origin[1] * 1e7), round(origin[2] * 1000), int(t * 1e6)
            )

    _handlers: ClassVar[dict[int, Callable[[SimAutopilot, Any, float], None]]] = {}

    # ------------------------------------------------------------------ output

    def _statustext(self, severity: int, text: str) -> None:
        text = text[:50]
        self.statustexts.append((severity, text))
        if not self._rebooting_until_ns and not self._closed:
            self.conn.mav.statustext_send(severity, text.encode("ascii", errors="replace"))

    def _send_due(self, t: float) -> None:
        mav = self.conn.mav
        while self._param_queue:
            for _ in range(min(10, len(self._param_queue))):
                self._send_param(self.params.names[self._param_queue.popleft()])
            break
        if t >= self._next_timesync:
            self._next_timesync = t + 0.1
            mav.timesync_send(0, max(1, int(t * 1e9)))
        due = self._next_due
        for mid, next_t in due.items():
            if t >= next_t:
                interval = self._intervals[mid]
                due[mid] = next_t + interval if t - next_t < interval else t + interval
                if interval != math.inf:
                    self._send_stream(mid, t)
        while self._pending_requests:
            self._send_stream(self._pending_requests.pop(0), t)

    def _send_stream(self, mid: int, t: float) -> None:
        mav = self.conn.mav
        sim = self.sim
        est = sim.estimator
        boot_ms = int(t * 1000) & 0xFFFFFFFF
        if mid == 0:
            main, sub = self.mode
            status = px4.MAV_STATE_STANDBY
            if self.terminated:
                status = px4.MAV_STATE_FLIGHT_TERMINATION
            elif self.armed:
                status = px4.MAV_STATE_CRITICAL if self._failsafe is not None else px4.MAV_STATE_ACTIVE
                if self._battery_level >= 3:
                    status = px4.MAV_STATE_EMERGENCY
            mav.heartbeat_send(
                px4.MAV_TYPE_QUADROTOR,
                px4.MAV_AUTOPILOT_PX4,
                px4.base_mode_flags(main, sub, self.armed),
                px4.encode_custom_mode(main, sub),
                status,
            )
        elif mid == 1:
            bat = sim.battery
            health = _SENSORS
            if not est.vision_fusing:
                health &= ~0x80
            if self._arm_denial(t) and not self.armed:
                health &= ~0x10000000
            mav.sys_status_send(
                _SENSORS,
                _SENSORS,
                health,
                250,
                int(bat.voltage * 1000),
                int(bat.current * 100),
                round(bat.soc * 100),
                0,
                0,
                0,
                0,
                0,
                0,
            )
        elif mid == 245:
            mav.extended_sys_state_send(0, self.landed_state)
        elif mid == 31:
            q = est.attitude()
            rates = sim.body.rates
            mav.attitude_quaternion_send(boot_ms, q[0], q[1], q[2], q[3], rates[0], rates[1], rates[2])
        elif mid == 32:
            p, v = est.position, est.velocity
            mav.local_position_ned_send(boot_ms, p[0], p[1], p[2], v[0], v[1], v[2])
        elif mid == 331:
            q = est.attitude()
            p = est.position
            vb = quat_rotate_inverse(q, est.velocity)
            rates = sim.body.rates
            nan21 = [NAN] * 21
            mav.odometry_send(
                int(t * 1e6),
                px4.MAV_FRAME_LOCAL_NED,
                px4.MAV_FRAME_BODY_FRD,
                p[0],
                p[1],
                p[2],
                list(q),
                vb[0],
                vb[1],
                vb[2],
                rates[0],
                rates[1],
                rates[2],
                nan21,
                nan21,
                0,
                px4.MAV_ESTIMATOR_TYPE_AUTOPILOT,
                0,
            )
        elif mid == 105:
            body = sim.body
            acc = body.specific_force_body()
            rates = body.rates
            mag = quat_rotate_inverse(body.attitude, (0.21, 0.0, 0.42))
            alt = -body.position[2]
            mav.highres_imu_send(
                int(t * 1e6),
                acc[0],
                acc[1],
                acc[2],
                rates[0],
                rates[1],
                rates[2],
                mag[0],
                mag[1],
                mag[2],
                1013.25 - alt * 0.12,
                0.0,
                alt,
                25.0,
                0x1FFF,
            )
        elif mid == 147:
            bat = sim.battery
            cells = bat.params.cells
            cell_mv = int(bat.cell_voltage() * 1000)
            voltages = [cell_mv] * min(cells, 10) + [0xFFFF] * (10 - min(cells, 10))
            charge_state = (1, 2, 3, 4)[self._battery_level]
            mav.battery_status_send(
                0,
                1,
                1,
                0x7FFF,
                voltages,
                int(bat.current * 100),
                int(bat.consumed_mah),
                int(bat.energy_j / 100),
                round(bat.soc * 100),
                0,
                charge_state,
            )
        elif mid == 148:
            uid = (self.system_id << 32) | 0x5E4A
            mav.autopilot_version_send(
                _CAPABILITIES,
                _FLIGHT_SW_VERSION,
                0,
                0,
                0,
                [0] * 8,
                [0] * 8,
                [0] * 8,
                0,
                0,
                uid,
            )


SimAutopilot._handlers = {
    76: SimAutopilot._on_command_long,
    75: SimAutopilot._on_command_int,
    21: SimAutopilot._on_param_request_list,
    20: SimAutopilot._on_param_request_read,
    23: SimAutopilot._on_param_set,
    84: SimAutopilot._on_set_position_target,
    331: SimAutopilot._on_odometry,
    102: SimAutopilot._on_vision_position_estimate,
    111: SimAutopilot._on_timesync,
    48: SimAutopilot._on_set_gps_global_origin,
}

_ACTION_MODES: dict[str, tuple[int, int]] = {
    "hold": (px4.MAIN_AUTO, px4.AUTO_LOITER),
    "rtl": (px4.MAIN_AUTO, px4.AUTO_RTL),
    "land": (px4.MAIN_AUTO, px4.AUTO_LAND),
    "descend": (px4.MAIN_AUTO, px4.AUTO_LAND),  # PX4 reports Descend as AUTO.LAND
}

_VERBS = {
    "hold": "holding",
    "rtl": "returning",
    "land": "landing",
    "terminate": "terminating",
    "disarm": "disarming",
}

# COM_OBL_RC_ACT → failsafe action. Position/Altitude/Stabilized need manual control, which the arena
# never provides, so PX4's failsafe falls through to Hold.
_OBL_ACTIONS: dict[int, str] = {
    px4.OBL_POSITION: "hold",
    px4.OBL_ALTITUDE: "hold",
    px4.OBL_STABILIZED: "hold",
    px4.OBL_RETURN: "rtl",
    px4.OBL_LAND: "land",
    px4.OBL_HOLD: "hold",
    px4.OBL_TERMINATE: "terminate",
    px4.OBL_DISARM: "disarm",
}


def run_autopilots(
    autopilots: Sequence[SimAutopilot],
    *,
    stop: threading.Event | None = None,
    duration: float | None = None,
    after_step: Callable[[], None] | None = None,
) -> None:
    """Drive several autopilots (sharing one :class:`SimClock`) from this thread.

    Runs until ``stop`` is set or ``duration`` simulated seconds have passed (at least one of them is
    required). Waits in ``select()`` on all sockets between steps; ``after_step`` runs after each round
    of steps (e.g. to publish the true poses).
    """
    if not autopilots:
        raise SimAutopilotError("no autopilots to run")
    if stop is None and duration is None:
        raise SimAutopilotError("give a stop event or a duration, or the loop never ends")
    clock = autopilots[0].clock
    if any(ap.clock is not clock for ap in autopilots):
        raise SimAutopilotError("all autopilots driven by one loop must share one SimClock")
    end = clock.now() + duration if duration is not None else math.inf
    while not (stop is not None and stop.is_set()) and clock.now() < end:
        wait = min(ap.step() for ap in autopilots)
        if after_step is not None:
            after_step()
        fds = [fd for fd in (ap.fileno() for ap in autopilots) if fd is not None]
        timeout = min(clock.real_seconds(wait), 0.05)
        if timeout > 0.0002:
            try:
                select.select(fds, [], [], timeout)
            except (OSError, ValueError):
                time.sleep(timeout)  # a socket was closed under us; the next step notices


class AutopilotLoop:
    """:func:`run_autopilots` in a background thread: ``with AutopilotLoop(aps): ...``.

    :meth:`stop` joins the thread and re-raises an exception the loop died of.
    """

    def __init__(self, autopilots: Iterable[SimAutopilot]) -> None:
        self.autopilots = list(autopilots)
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="sim-autopilots", daemon=True)

    def _run(self) -> None:
        try:
            run_autopilots(self.autopilots, stop=self._stop)
        except BaseException as exc:  # handed to the owner in stop()
            self._error = exc

    def start(self) -> AutopilotLoop:
        """Start the thread."""
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop and join the thread; re-raise its error if it died of one."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)
        if self._error is not None:
            raise self._error

    @property
    def alive(self) -> bool:
        """Whether the loop thread is still running."""
        return self._thread.is_alive()

    def __enter__(self) -> AutopilotLoop:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
