"""A simulated PX4 v1.16 multicopter speaking MAVLink 2 over a real link.

:class:`SimAutopilot` is one vehicle: it owns a pymavlink connection (``udpout:HOST:PORT`` sends to a
gateway listening with ``udpin:``, as PX4 does; ``tcpin:HOST:PORT`` waits for a gateway's ``tcp:``),
its system id, its parameters and a :class:`~arena_common.sim.physics.QuadSim`. It behaves toward the
gateway as PX4 v1.16 does — measured against PX4 v1.16.0 SITL, compared row by row in docs/px4.md: heartbeats
and telemetry streams (:mod:`~arena_common.sim.telemetry`), commands and setpoints
(:mod:`~arena_common.sim.mavlink_commands`), modes, arming checks and failsafes
(:mod:`~arena_common.sim.flight`), the mission protocol (:mod:`~arena_common.sim.mission`), the parameter
protocol with bytewise INT32 encoding and reboot-required parameters (:mod:`~arena_common.sim.params`),
external vision fusion and TIMESYNC (here).

Vision: ODOMETRY (estimator type VISION, VIO, NAIVE or UNKNOWN; MOCAP is not fused) in MAV_FRAME_LOCAL_NED
aligns the heading; in MAV_FRAME_LOCAL_FRD it is fused but the heading never aligns to north, so there is
no global position and arming is refused, as PX4 v1.16 does. VISION_POSITION_ESTIMATE is north-referenced.
ATT_POS_MOCAP is not fused (counted in :attr:`SimAutopilot.ignored_mocap`).

Several vehicles share one thread: :func:`run_autopilots` (or :class:`AutopilotLoop` in the background)
calls :meth:`SimAutopilot.step` on each and ``select()``\\ s on their sockets. Time is a :class:`SimClock`
whose ``speed`` can exceed 1 for tests. No input stops the vehicle: a handler that fails on a message
counts it in :attr:`SimAutopilot.input_errors` and the vehicle carries on.

Simulation choices where PX4 was not copied (documented here once):

- MAV_CMD_NAV_TAKEOFF param7 is the AMSL altitude once home has one (EKF origin); without an origin it is
  taken as the height above home. NaN or not above home means MIS_TAKEOFF_ALT.
- A command retried with a higher ``confirmation`` within 5 s of an identical executed one is acked
  with the first result and not executed again; this history survives a simulated reboot.
- MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (param1 1) reboots like PX4 on hardware (SITL refuses): acked, silent
  for :attr:`SimAutopilot.REBOOT_SECONDS`, back with its boot clock at 0 and the reboot-required
  parameters in effect.
- With a ``signing_key`` the vehicle behaves as PX4 with ``MAV_SIGN_CFG`` = 2 (signing always required):
  everything it sends is signed (link id 0), and every message it receives must be signed with the same
  key and carry a timestamp above the last one of its stream (link, system, component), except
  RADIO_STATUS, ADSB_VEHICLE and COLLISION; refused messages are counted in :attr:`SimAutopilot.refused`
  and reported by a STATUSTEXT at most every 5 s.  The streams seen are forgotten on a reboot.
- SET_GPS_GLOBAL_ORIGIN addressed to the vehicle sets its EKF origin (:attr:`SimAutopilot.gps_origin`,
  lost on reboot); every SET_GPS_GLOBAL_ORIGIN is answered with GPS_GLOBAL_ORIGIN once an origin is set.
- The estimate the controllers and telemetry see trails the truth and wanders about it as PX4's did on
  SIH (``ideal`` makes it exact; ``estimate_lag`` sets the lag's time constant).
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
from typing import Any, ClassVar

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

from arena_common.geometry.quat import quat_from_euler, quat_rotate, quat_yaw
from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2
from arena_common.mavlink.px4 import ParamValue
from arena_common.mavlink.signing import PX4_UNSIGNED, LinkSigning, SigningKey
from arena_common.sim.base import MapProjection, SimAutopilotError, TruePose, Vec3
from arena_common.sim.connection import open_connection
from arena_common.sim.estimator import PX4_SIH_ESTIMATE_LAG_S, PX4_SIH_WANDER
from arena_common.sim.flight import FlightMixin
from arena_common.sim.mavlink_commands import CommandsMixin
from arena_common.sim.mission import MissionMixin
from arena_common.sim.params import SIM_EXTRA_DEFAULTS, ParamStore, reboot_required_names
from arena_common.sim.physics import (
    BatteryParams,
    ControlGains,
    QuadParams,
    QuadSim,
    Setpoint,
)
from arena_common.sim.telemetry import TelemetryMixin
from arena_common.sim.time import SimClock, TimesyncFilter

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
Quat = tuple[float, float, float, float]


class SimAutopilot(FlightMixin, CommandsMixin, MissionMixin, TelemetryMixin):
    """One simulated PX4 quadrotor on a MAVLink 2 link.

    ``connection`` is a pymavlink connection string; the vehicle sends first like PX4, so use
    ``udpout:127.0.0.1:PORT`` (gateway on ``udpin:127.0.0.1:PORT``) or ``tcpin:127.0.0.1:PORT``
    (gateway on ``tcp:``). ``params`` overrides PX4's defaults as if stored on the vehicle (in effect from
    boot). The vehicle starts disarmed on the floor at ``position`` (arena NED, down = 0) heading ``yaw``
    rad. By default it flies as PX4 v1.16 SITL (SIH) was measured to (docs/px4.md): spool-up and thrust
    ramp on the ground, Hold reported NAV_MC_ALT_RAD short of the altitude and a slow approach after it,
    Hold entered while moving stops at PX4's braking point, and its estimate trails the truth
    (:data:`~arena_common.sim.estimator.PX4_SIH_ESTIMATE_LAG_S`) and wanders about it
    (:data:`~arena_common.sim.estimator.PX4_SIH_WANDER`), so the vehicle wanders around its hover point
    as PX4's did.  ``ideal`` climbs at once, holds where the mode began and estimates exactly.
    ``estimate_lag`` (s, 0..5), when given, replaces the time constant of the estimate's lag.
    """

    COMPONENT_ID = px4.MAV_COMP_ID_AUTOPILOT1
    CONTROL_PERIOD = 0.02  # s, state machine / failsafe evaluation
    REBOOT_SECONDS = 1.0  # silent time of a simulated reboot
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
        estimate_lag: float | None = None,
        ideal: bool = False,
        link_delay: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        if not 1 <= int(system_id) <= 250:
            raise SimAutopilotError(f"system id must be within 1..250, got {system_id}")
        if len(position) != 3 or position[2] < 0:
            raise SimAutopilotError(f"start position must be (north, east, down>=0), got {tuple(position)}")
        if estimate_lag is None:
            estimate_lag = 0.0 if ideal else PX4_SIH_ESTIMATE_LAG_S
        if not (math.isfinite(estimate_lag) and 0.0 <= estimate_lag <= 5.0):
            raise SimAutopilotError(f"estimate lag must be within 0..5 s, got {estimate_lag}")
        self.clock = clock or SimClock()
        self.name = name or f"sim{system_id}"
        defaults = {**px4.PX4_DEFAULTS, **SIM_EXTRA_DEFAULTS}
        defaults["MAV_SYS_ID"] = (int(system_id), px4.MAV_PARAM_TYPE_INT32)
        reboot_names, self.reboot_required_source = reboot_required_names()
        self.params = ParamStore(defaults, reboot_names)
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
            quad,
            self._base_gains,
            battery=battery,
            position=self._start,
            yaw=yaw,
            soc=soc,
            seed=seed,
            land_stages=not ideal,  # PX4's three land-detector stages; the ideal vehicle lands in 0.5 s
        )
        self.sim.estimator.output_lag_s = float(estimate_lag)
        self.sim.estimator.wander = None if ideal else PX4_SIH_WANDER
        self.ideal = bool(ideal)
        self.timesync = TimesyncFilter()
        self.statustexts: deque[tuple[int, str]] = deque(maxlen=200)
        self._command_history = {}
        self._true_pose = TruePose(
            self.clock.now_ns(), self._start, quat_from_euler(0, 0, yaw), (0.0, 0.0, 0.0)
        )
        self.conn, self.relay = open_connection(connection, self.system_id, self.COMPONENT_ID, link_delay)
        self.connection = connection
        self.signing: LinkSigning | None = None
        if signing_key is not None:
            self.signing = LinkSigning(signing_key, link_id=0, allow_unsigned=PX4_UNSIGNED)
            self.signing.attach(self.conn.mav)
        #: Refused input by "reason MESSAGE" (``"unsigned COMMAND_LONG"``, ``"replayed ODOMETRY"``…).
        self.refused: collections.Counter[str] = collections.Counter()
        #: Input a handler failed on, by "MESSAGE ExceptionType" (the vehicle carries on).
        self.input_errors: collections.Counter[str] = collections.Counter()
        #: Telemetry that could not be packed, by "MESSAGE ExceptionType" (absurd values: skipped).
        self.output_errors: collections.Counter[str] = collections.Counter()
        #: Arithmetic failures in the physics or the flight logic (a tick skipped; none are expected).
        self.internal_errors: collections.Counter[str] = collections.Counter()
        self._refusal_text_at = -math.inf
        self.origin_sets = 0  # SET_GPS_GLOBAL_ORIGIN taken, over reboots
        self.boots = 0
        #: Called with the true pose after every physics tick (in the thread that steps), if set.
        self.on_tick: Callable[[TruePose], None] | None = None
        self._closed = False
        self._boot()

    # ------------------------------------------------------------------ lifecycle

    def _boot(self) -> None:
        """(Re)start the flight stack: state, estimator and streams; parameters persist (in effect now)."""
        self._boot_ns = self.clock.now_ns()
        self.boots += 1
        self.params.boot()
        sysid = int(self.params.applied("MAV_SYS_ID"))
        if 1 <= sysid <= 250:  # PX4's metadata range; anything else keeps the system id it had
            self.system_id = sysid
        self.conn.mav.srcSystem = self.system_id
        sim = self.sim
        sim.time = 0.0
        sim.reset(self._start, self._start_yaw)
        self._apply_params(boot=True)
        self.timesync.reset()
        self.armed = False
        self.terminated = False
        self._user_mode = (px4.MAIN_AUTO, px4.AUTO_LOITER)
        self._failsafe = None
        self._failsafe_since = 0.0
        self._dll_action = None
        self._dll_action_at = math.inf
        self._nav = {}
        self._home = (0.0, 0.0, 0.0)
        self._home_yaw = 0.0
        self._home_set = False
        self._enter_nav()
        self._armed_at = 0.0
        self._flew_since_arming = False
        self._landed_since = 0.0
        self._was_landed = True
        self._sp_times = deque(maxlen=64)
        self._offboard_sp = Setpoint()
        self._frame_warned_at = -math.inf
        self._battery_level = 0  # 0 ok, 1 low, 2 critical, 3 emergency
        self._battery_action_level = 0
        self._xy_valid_prev = False
        self._vision_prev = False
        self._cruise_speed = -1.0
        self._gcs_heard_at = -math.inf
        self._gcs_lost = False
        self._cmd_frame = None
        self._next_control = 0.0
        self._rebooting_until_ns = 0
        self._telemetry_boot()
        self._mission_boot(keep=self.boots > 1)
        self.skipped_time_s = 0.0
        self.ignored_mocap = 0
        self.last_vision_sample_us = -1
        self.messages_in = 0
        self.gps_origin = None  # (lat deg, lon deg, alt m), the EKF origin
        self._projection: MapProjection | None = None
        if self.signing is not None:
            self.signing.forget_streams()

    def close(self) -> None:
        """Close the MAVLink connection (and its link-delay relay)."""
        if not self._closed:
            self._closed = True
            self.conn.close()
            if self.relay is not None:
                self.relay.close()

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
    def rebooting(self) -> bool:
        """Rebooting as a command asked: silent, and what arrives meanwhile is not read (as PX4)."""
        return bool(self._rebooting_until_ns)

    @property
    def landed(self) -> bool:
        """Land detector state."""
        return self.sim.landed

    @property
    def global_position_valid(self) -> bool:
        """Whether the vehicle has a global position (EKF origin, north-aligned heading, position)."""
        return self._global_ok()

    def param(self, name: str) -> ParamValue:
        """Current (stored) value of a parameter."""
        if name not in self.params:
            raise SimAutopilotError(f"unknown parameter {name!r}")
        return self.params.get(name)

    def param_in_effect(self, name: str) -> ParamValue:
        """Value of a parameter the vehicle uses now (a reboot-required one: its value at boot)."""
        if name not in self.params:
            raise SimAutopilotError(f"unknown parameter {name!r}")
        return self.params.applied(name)

    def projection(self) -> MapProjection | None:
        """The projection around the EKF origin (None without an origin)."""
        return self._projection

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
        skipping = t - sim.time > self.MAX_CATCH_UP_S
        if skipping:
            skipped = (int((t - sim.time) / dt) - 1) * dt  # whole ticks: the physics keeps its time grid
            self.skipped_time_s += skipped
            sim.time += skipped
            # What reached the vehicle while its simulation could not run is read before anything judges
            # it: a real vehicle would have read it as it came, and must not take the stall for lost vision.
            self._read_input(sim.time)
        on_tick = self.on_tick
        while sim.time + dt <= t + 1e-9:
            try:
                if sim.time >= self._next_control:
                    self._next_control = sim.time + self.CONTROL_PERIOD
                    self._control(sim.time)
                sim.step()
            except (ArithmeticError, ValueError) as exc:  # never seen; one vehicle must not stop the others
                self.internal_errors[type(exc).__name__] += 1
                sim.time += dt
            if on_tick is not None:
                on_tick(self._update_true_pose())
        if on_tick is None:
            self._update_true_pose()
        if not skipping and (self.clock.now_ns() - now_ns) * 1e-9 > self.MAX_CATCH_UP_S:
            return 0.0  # held up during this step: the next one skips that time, then reads
        self._read_input(sim.time)
        self._mission_tick(sim.time)
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
        except Exception as exc:  # a datagram pymavlink could not decode: dropped, as PX4 drops it
            self.input_errors[f"decode {type(exc).__name__}"] += 1
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

    # ------------------------------------------------------------------ parameters

    def _apply_params(self, boot: bool = False) -> None:
        """Put the parameters in effect (reboot-required ones keep their boot values)."""
        p = self.params
        est = self.sim.estimator
        est.ev_ctrl = int(p.applied("EKF2_EV_CTRL"))
        est.ev_delay_s = min(max(0.0, float(p.applied("EKF2_EV_DELAY"))), 300.0) * 1e-3
        est.baro_enabled = int(p.applied("EKF2_BARO_CTRL")) != 0
        est.hgt_ref_vision = int(p.applied("EKF2_HGT_REF")) == px4.EKF2_HGT_REF_VISION
        est.mag_enabled = int(p.applied("EKF2_MAG_TYPE")) != px4.EKF2_MAG_TYPE_NONE
        est.noaid_timeout_s = min(max(0.5, int(p.applied("EKF2_NOAID_TOUT")) * 1e-6), 10.0)

        def limited(name: str, lo: float, hi: float) -> float:  # within PX4's metadata min..max
            return min(max(float(p.applied(name)), lo), hi)

        gains = replace(
            self._base_gains,
            xy_p=limited("MPC_XY_P", 0.0, 2.0),
            z_p=limited("MPC_Z_P", 0.1, 1.5),
            hover_throttle=limited("MPC_THR_HOVER", 0.1, 0.8),
            vel_max_xy=limited("MPC_XY_VEL_MAX", 0.0, 20.0),
            vel_max_up=limited("MPC_Z_VEL_MAX_UP", 0.5, 8.0),
            vel_max_dn=limited("MPC_Z_VEL_MAX_DN", 0.5, 4.0),
            tilt_max_deg=limited("MPC_TILTMAX_AIR", 20.0, 89.0),
            yaw_rate_auto_max=math.radians(limited("MPC_YAWRAUTO_MAX", 5.0, 360.0)),
        )
        self.sim.gains = gains
        self.sim.controller.gains = gains

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
        if self.params.type_of(name) == px4.MAV_PARAM_TYPE_REAL32 and not math.isfinite(msg.param_value):
            self._statustext(px4.MAV_SEVERITY_WARNING, f"[pm] {name}: not a finite value, unchanged")
        else:
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
            if handler is None:
                continue
            self.messages_in += 1
            try:
                handler(self, msg, t)
            except Exception as exc:  # no input may stop the vehicle (PX4 would not crash either)
                self.input_errors[f"{msg.get_type()} {type(exc).__name__}"] += 1

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

    def _on_heartbeat(self, msg: Any, t: float) -> None:
        """A ground station's heartbeat (MAV_TYPE_GCS, any system) opens the link to STATUSTEXT."""
        if msg.type == px4.MAV_TYPE_GCS:
            self._gcs_heard_at = t

    def _on_odometry(self, msg: Any, t: float) -> None:
        if msg.estimator_type not in px4.EV_FUSED_ESTIMATOR_TYPES:
            if msg.estimator_type == px4.MAV_ESTIMATOR_TYPE_MOCAP:
                self.ignored_mocap += 1  # PX4 routes MOCAP to a topic EKF2 does not fuse
            return
        if msg.frame_id not in (px4.MAV_FRAME_LOCAL_NED, px4.MAV_FRAME_LOCAL_FRD):
            return
        if msg.quality < 0 or msg.quality < int(self.params.applied("EKF2_EV_QMIN")):
            return  # failed, or below the quality EKF2 wants
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
        north_ref = msg.frame_id == px4.MAV_FRAME_LOCAL_NED
        self._fuse_vision(t, msg.time_usec, pos, yaw, vel, msg.reset_counter, north_ref)

    def _on_vision_position_estimate(self, msg: Any, t: float) -> None:
        xyz: Vec3 = (msg.x, msg.y, msg.z)
        pos = xyz if all(math.isfinite(c) for c in xyz) else None
        yaw = msg.yaw if math.isfinite(msg.yaw) else None
        self._fuse_vision(t, msg.usec, pos, yaw, None, msg.reset_counter, True)

    def _on_att_pos_mocap(self, msg: Any, t: float) -> None:
        self.ignored_mocap += 1  # PX4 publishes it as mocap odometry, which EKF2 does not fuse

    def _fuse_vision(
        self,
        t: float,
        time_usec: int,
        pos: Vec3 | None,
        yaw: float | None,
        vel: Vec3 | None,
        reset_counter: int,
        north_ref: bool,
    ) -> None:
        arrival_us = int(t * 1e6)
        sample_us = self.timesync.sync_stamp(int(time_usec), arrival_us)
        self.last_vision_sample_us = sample_us
        self.sim.estimator.fuse_vision(t, sample_us * 1e-6, pos, yaw, vel, reset_counter, north_ref)

    def _on_timesync(self, msg: Any, t: float) -> None:
        now_ns = int(t * 1e9)
        if msg.tc1 == 0:
            self.conn.mav.timesync_send(now_ns, msg.ts1)
        elif msg.tc1 > 0:
            self.timesync.update(now_ns // 1000, msg.tc1 // 1000, msg.ts1 // 1000)

    def _on_set_gps_global_origin(self, msg: Any, t: float) -> None:
        if msg.target_system == self.system_id:
            lat, lon, alt = msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3
            if abs(lat) <= 90 and abs(lon) <= 180:
                self.gps_origin = (lat, lon, alt)
                self._projection = MapProjection(lat, lon, alt)
                self.origin_sets += 1
        self._request_message(
            mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN
        )  # PX4 answers every request with its origin, when it has one

    _handlers: ClassVar[dict[int, Callable[[SimAutopilot, Any, float], None]]] = {}


SimAutopilot._handlers = {
    mavlink2.MAVLINK_MSG_ID_HEARTBEAT: SimAutopilot._on_heartbeat,
    mavlink2.MAVLINK_MSG_ID_COMMAND_LONG: SimAutopilot._on_command_long,
    mavlink2.MAVLINK_MSG_ID_COMMAND_INT: SimAutopilot._on_command_int,
    mavlink2.MAVLINK_MSG_ID_PARAM_REQUEST_LIST: SimAutopilot._on_param_request_list,
    mavlink2.MAVLINK_MSG_ID_PARAM_REQUEST_READ: SimAutopilot._on_param_request_read,
    mavlink2.MAVLINK_MSG_ID_PARAM_SET: SimAutopilot._on_param_set,
    mavlink2.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET: SimAutopilot._on_set_attitude_target,
    mavlink2.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED: SimAutopilot._on_set_position_target,
    mavlink2.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT: SimAutopilot._on_set_position_target_global,
    mavlink2.MAVLINK_MSG_ID_ODOMETRY: SimAutopilot._on_odometry,
    mavlink2.MAVLINK_MSG_ID_VISION_POSITION_ESTIMATE: SimAutopilot._on_vision_position_estimate,
    mavlink2.MAVLINK_MSG_ID_ATT_POS_MOCAP: SimAutopilot._on_att_pos_mocap,
    mavlink2.MAVLINK_MSG_ID_TIMESYNC: SimAutopilot._on_timesync,
    mavlink2.MAVLINK_MSG_ID_SET_GPS_GLOBAL_ORIGIN: SimAutopilot._on_set_gps_global_origin,
    mavlink2.MAVLINK_MSG_ID_MISSION_COUNT: SimAutopilot._on_mission_count,
    mavlink2.MAVLINK_MSG_ID_MISSION_ITEM_INT: SimAutopilot._on_mission_item,
    mavlink2.MAVLINK_MSG_ID_MISSION_ITEM: SimAutopilot._on_mission_item,
    mavlink2.MAVLINK_MSG_ID_MISSION_REQUEST_LIST: SimAutopilot._on_mission_request_list,
    mavlink2.MAVLINK_MSG_ID_MISSION_REQUEST_INT: SimAutopilot._on_mission_request,
    mavlink2.MAVLINK_MSG_ID_MISSION_REQUEST: SimAutopilot._on_mission_request,
    mavlink2.MAVLINK_MSG_ID_MISSION_CLEAR_ALL: SimAutopilot._on_mission_clear_all,
    mavlink2.MAVLINK_MSG_ID_MISSION_SET_CURRENT: SimAutopilot._on_mission_set_current,
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

    @property
    def thread(self) -> threading.Thread:
        """The thread that drives the autopilots (for :meth:`SimClock.paces`)."""
        return self._thread

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
