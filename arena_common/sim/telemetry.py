"""What the simulated PX4 sends: telemetry streams at PX4's rates, requested messages, STATUSTEXT.

Streams are those PX4 v1.16 sends on its onboard (API) link, at its rates (measured on SITL: ATTITUDE
100 Hz, ATTITUDE_QUATERNION 50 Hz, GLOBAL_POSITION_INT 50 Hz, LOCAL_POSITION_NED and ODOMETRY 30 Hz,
HIGHRES_IMU 50 Hz, EXTENDED_SYS_STATE 5 Hz, ESTIMATOR_STATUS and HEARTBEAT 1 Hz, HOME_POSITION 0.5 Hz);
MAV_CMD_SET_MESSAGE_INTERVAL changes them. GLOBAL_POSITION_INT exists only while the global position is
valid (an EKF origin and a north-aligned heading), HOME_POSITION once home is set — as in PX4, whose
LOCAL_POSITION_NED on the other hand keeps streaming while the position is invalid (the validity is in
ESTIMATOR_STATUS.flags).

STATUSTEXT as PX4 v1.16 sends it: only while a HEARTBEAT of type MAV_TYPE_GCS was heard on the link in
the last 2.5 s (a GCS, not an onboard controller); texts wait in a queue of 8 (PX4's ``mavlink_log``
topic) and go out when a ground station appears, unless older than 5 s; texts longer than 50 characters
travel in chunks (same ``id``, ``chunk_seq`` 0, 1…); every text gets the next ``id``; texts PX4 derives
from its events end with a tab.
"""

from __future__ import annotations

import collections
import math
import struct
from collections import deque
from typing import Final

from arena_common.geometry.quat import quat_rotate_inverse, quat_to_euler
from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2
from arena_common.sim.base import AutopilotState, MapProjection

__all__ = ["CAPABILITIES", "FLIGHT_SW_VERSION", "REQUESTABLE", "STREAMS", "TelemetryMixin"]

NAN = math.nan

#: Telemetry streams (message id → (name, default rate Hz)), as PX4 v1.16's onboard MAVLink mode.
STREAMS: Final[dict[int, tuple[str, float]]] = {
    getattr(mavlink2, f"MAVLINK_MSG_ID_{name}"): (name, rate)
    for name, rate in (
        ("HEARTBEAT", 1.0),
        ("SYS_STATUS", 2.0),
        ("EXTENDED_SYS_STATE", 5.0),
        ("ATTITUDE", 100.0),
        ("ATTITUDE_QUATERNION", 50.0),
        ("LOCAL_POSITION_NED", 30.0),
        ("GLOBAL_POSITION_INT", 50.0),
        ("ODOMETRY", 30.0),
        ("HIGHRES_IMU", 50.0),
        ("BATTERY_STATUS", 1.0),
        ("ESTIMATOR_STATUS", 1.0),
        ("HOME_POSITION", 0.5),
        ("MISSION_CURRENT", 1.0),
    )
}
#: Messages MAV_CMD_REQUEST_MESSAGE can ask for: the streams, AUTOPILOT_VERSION, GPS_GLOBAL_ORIGIN.
REQUESTABLE: Final = frozenset(
    {*STREAMS, mavlink2.MAVLINK_MSG_ID_AUTOPILOT_VERSION, mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN}
)

FLIGHT_SW_VERSION: Final = (1 << 24) | (16 << 16) | (0 << 8) | 255  # 1.16.0 official, as the SITL build
#: What the simulated vehicle implements (PX4 v1.16 SITL advertises 59647: also MISSION_FLOAT, PARAM_FLOAT,
#: FTP, MISSION_FENCE, MISSION_RALLY, which the simulation does not do).
CAPABILITIES: Final = (
    mavlink2.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink2.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink2.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    # attitude and thrust; body rates not simulated
    | mavlink2.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink2.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    # PX4 implements it without advertising it
    | mavlink2.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | mavlink2.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
    | mavlink2.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)

_SENSORS: Final = (
    mavlink2.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink2.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink2.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink2.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink2.MAV_SYS_STATUS_SENSOR_VISION_POSITION
    | mavlink2.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink2.MAV_SYS_STATUS_AHRS
    | mavlink2.MAV_SYS_STATUS_SENSOR_BATTERY
    | mavlink2.MAV_SYS_STATUS_PREARM_CHECK
)
#: HIGHRES_IMU.fields_updated: every field, XACC … TEMPERATURE.
_IMU_UPDATED: Final = 2 * mavlink2.HIGHRES_IMU_UPDATED_TEMPERATURE - 1
#: BATTERY_STATUS.charge_state of each battery level (ok, low, critical, emergency).
_CHARGE_STATES: Final = (
    px4.MAV_BATTERY_CHARGE_STATE_OK,
    px4.MAV_BATTERY_CHARGE_STATE_LOW,
    px4.MAV_BATTERY_CHARGE_STATE_CRITICAL,
    px4.MAV_BATTERY_CHARGE_STATE_EMERGENCY,
)

GCS_TIMEOUT_S: Final = 2.5  # PX4's telemetry_status HEARTBEAT_TIMEOUT_US
STATUSTEXT_QUEUE: Final = 8  # PX4's mavlink_log ORB_QUEUE_LENGTH
STATUSTEXT_STALE_S: Final = 5.0
STATUSTEXT_MAX: Final = 126  # mavlink_log text[127], NUL-terminated


def _i32(value: float) -> int:
    """``value`` rounded into int32 (what a diverged estimate or an absurd home must not break)."""
    if not math.isfinite(value):
        return 0x7FFFFFFF
    return max(-0x80000000, min(0x7FFFFFFF, round(value)))


class TelemetryMixin(AutopilotState):
    """Streams, requested messages and STATUSTEXT of :class:`~arena_common.sim.autopilot.SimAutopilot`."""

    _text_queue: deque[tuple[float, int, str]]
    _text_id: int
    _next_timesync: float
    output_errors: collections.Counter[str]

    def _telemetry_boot(self) -> None:
        """Default rates, empty queues (boot)."""
        self._next_due = {mid: 0.0 for mid in STREAMS}
        self._intervals = {mid: 1.0 / rate for mid, (_, rate) in STREAMS.items()}
        self._pending_requests = []
        self._param_queue = deque()
        self._text_queue = deque(maxlen=STATUSTEXT_QUEUE)
        self._text_id = 0
        self._next_timesync = 0.1

    # ------------------------------------------------------------------ the ground station

    def gcs_connected(self, t: float | None = None) -> bool:
        """Whether a MAV_TYPE_GCS heartbeat was heard on the link in the last 2.5 s (vehicle time)."""
        now = self.sim.time if t is None else t
        return now - self._gcs_heard_at < GCS_TIMEOUT_S

    # ------------------------------------------------------------------ STATUSTEXT

    def _statustext(self, severity: int, text: str, *, tab: bool = False) -> None:
        """Queue a text for the ground station (recorded in :attr:`statustexts` whether sent or not)."""
        text = text[: STATUSTEXT_MAX - (1 if tab else 0)]
        self.statustexts.append((severity, text))
        self._text_queue.append((self.sim.time, severity, text + ("\t" if tab else "")))

    def _flush_texts(self, t: float) -> None:
        if not self._text_queue or not self.gcs_connected(t) or self._rebooting_until_ns or self._closed:
            return
        mav = self.conn.mav
        while self._text_queue:
            when, severity, text = self._text_queue.popleft()
            if t - when >= STATUSTEXT_STALE_S:
                continue
            raw = text.encode("ascii", errors="replace")
            msg_id = self._text_id
            self._text_id = (self._text_id + 1) & 0xFFFF
            for seq, start in enumerate(range(0, max(len(raw), 1), 50)):
                mav.statustext_send(severity, raw[start : start + 50], msg_id, seq)

    # ------------------------------------------------------------------ streams

    def _request_message(self, msgid: int) -> bool:
        """Queue one message asked for with REQUEST_MESSAGE; False when it is not one the vehicle has."""
        if msgid not in REQUESTABLE:
            return False
        self._pending_requests.append(msgid)
        return True

    def _set_interval(self, msgid: int, interval_us: float, t: float) -> bool:
        """SET_MESSAGE_INTERVAL: -1 stops, 0 or NaN restores the default, else the interval (≥ 2 ms)."""
        if msgid not in STREAMS:
            return False
        if interval_us < 0:
            self._intervals[msgid] = math.inf
        elif interval_us == 0 or not math.isfinite(interval_us):
            self._intervals[msgid] = 1.0 / STREAMS[msgid][1]
        else:
            self._intervals[msgid] = min(max(interval_us * 1e-6, 0.002), 3600.0)
        self._next_due[msgid] = t
        return True

    def _send_due(self, t: float) -> None:
        mav = self.conn.mav
        if self._param_queue:
            for _ in range(min(10, len(self._param_queue))):
                self._send_param(self.params.names[self._param_queue.popleft()])
        if t >= self._next_timesync:
            self._next_timesync = t + 0.1
            mav.timesync_send(0, max(1, int(t * 1e9)))
        due = self._next_due
        for mid, next_t in due.items():
            if t >= next_t:
                interval = self._intervals[mid]
                due[mid] = next_t + interval if t - next_t < interval else t + interval
                if interval != math.inf:
                    self._send_safely(mid, t)
        while self._pending_requests:
            self._send_safely(self._pending_requests.pop(0), t)
        self._flush_texts(t)

    def _send_safely(self, mid: int, t: float) -> None:
        """One message; a value MAVLink cannot carry (an estimate driven to 1e39 by absurd input) skips it."""
        try:
            self._send_stream(mid, t)
        except (ArithmeticError, ValueError, struct.error) as exc:
            self.output_errors[f"{STREAMS.get(mid, (str(mid),))[0]} {type(exc).__name__}"] += 1

    def _estimator_flags(self) -> int:
        """ESTIMATOR_STATUS.flags as PX4 v1.16 SITL set them (measured: on the ground 511 (495 without an
        origin), flying 383, dead reckoning 127, position lost 101 in the air and 37 landed)."""
        est = self.sim.estimator
        landed = self.sim.landed
        flags = px4.ESTIMATOR_ATTITUDE
        if est.z_valid:
            flags |= px4.ESTIMATOR_VELOCITY_VERT | px4.ESTIMATOR_POS_VERT_ABS
            if est.xy_valid or not landed:
                flags |= px4.ESTIMATOR_POS_VERT_AGL
        if est.xy_valid:
            flags |= px4.ESTIMATOR_VELOCITY_HORIZ | px4.ESTIMATOR_POS_HORIZ_REL
            if self.gps_origin is not None:
                flags |= px4.ESTIMATOR_POS_HORIZ_ABS
            if landed:
                flags |= px4.ESTIMATOR_CONST_POS_MODE
            if not est.dead_reckoning:
                flags |= px4.ESTIMATOR_PRED_POS_HORIZ_REL
        return flags

    def _home_global(self, proj: MapProjection) -> tuple[float, float, float]:
        lat, lon = proj.reproject(self._home[0], self._home[1])
        return lat, lon, proj.alt - self._home[2]

    def _send_stream(self, mid: int, t: float) -> None:
        # Motion first: it holds the fast streams (ATTITUDE 100 Hz, the rest 30–50 Hz), sent in one call.
        for send in (self._send_motion, self._send_health, self._send_places):
            if send(mid, t):
                return

    def _send_health(self, mid: int, t: float) -> bool:
        """Send one message of the heartbeat, system status, landed state streams; False: ``mid`` is not one of them."""
        mav = self.conn.mav
        sim = self.sim
        est = sim.estimator
        if mid == mavlink2.MAVLINK_MSG_ID_HEARTBEAT:
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
        elif mid == mavlink2.MAVLINK_MSG_ID_SYS_STATUS:
            bat = sim.battery
            health = _SENSORS
            if not est.vision_fusing:
                health &= ~mavlink2.MAV_SYS_STATUS_SENSOR_VISION_POSITION
            if not self.armed and self._arm_denial(t):
                health &= ~mavlink2.MAV_SYS_STATUS_PREARM_CHECK
            mav.sys_status_send(
                _SENSORS, _SENSORS, health, 250, int(bat.voltage * 1000), int(bat.current * 100),
                round(bat.soc * 100), 0, 0, 0, 0, 0, 0,
            )  # fmt: skip
        elif mid == mavlink2.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            mav.extended_sys_state_send(mavlink2.MAV_VTOL_STATE_UNDEFINED, self.landed_state)
        else:
            return False
        return True

    def _send_motion(self, mid: int, t: float) -> bool:
        """Send one message of the attitude, position, odometry, the IMU streams; False: ``mid`` is not one of them."""
        mav = self.conn.mav
        sim = self.sim
        est = sim.estimator
        boot_ms = int(t * 1000) & 0xFFFFFFFF
        if mid == mavlink2.MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch, yaw = quat_to_euler(est.attitude())
            r = sim.body.rates
            mav.attitude_send(boot_ms, roll, pitch, yaw, r[0], r[1], r[2])
        elif mid == mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            q = est.attitude()
            r = sim.body.rates
            mav.attitude_quaternion_send(boot_ms, q[0], q[1], q[2], q[3], r[0], r[1], r[2])
        elif mid == mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            p, v = est.out_position, est.out_velocity
            mav.local_position_ned_send(boot_ms, p[0], p[1], p[2], v[0], v[1], v[2])
        elif mid == mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            proj = self.projection()
            if proj is None or not self._global_ok():
                return True
            p, v = est.out_position, est.out_velocity
            lat, lon = proj.reproject(p[0], p[1])
            hdg = round(math.degrees(est.yaw) * 100) % 36000 if math.isfinite(est.yaw) else 0xFFFF
            mav.global_position_int_send(
                boot_ms, _i32(lat * 1e7), _i32(lon * 1e7), _i32((proj.alt - p[2]) * 1000),
                _i32((self._home[2] - p[2]) * 1000), max(-32768, min(32767, round(v[0] * 100))),
                max(-32768, min(32767, round(v[1] * 100))), max(-32768, min(32767, round(v[2] * 100))), hdg,
            )  # fmt: skip
        elif mid == mavlink2.MAVLINK_MSG_ID_ODOMETRY:
            q = est.attitude()
            p = est.out_position
            vb = quat_rotate_inverse(q, est.out_velocity)
            r = sim.body.rates
            nan21 = [NAN] * 21
            mav.odometry_send(
                int(t * 1e6), px4.MAV_FRAME_LOCAL_NED, px4.MAV_FRAME_BODY_FRD, p[0], p[1], p[2], list(q),
                vb[0], vb[1], vb[2], r[0], r[1], r[2], nan21, nan21, 0, px4.MAV_ESTIMATOR_TYPE_AUTOPILOT, 0,
            )  # fmt: skip
        elif mid == mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU:
            body = sim.body
            acc = body.specific_force_body()
            r = body.rates
            mag = quat_rotate_inverse(body.attitude, (0.21, 0.0, 0.42))
            alt = -body.position[2]
            mav.highres_imu_send(
                int(t * 1e6), acc[0], acc[1], acc[2], r[0], r[1], r[2], mag[0], mag[1], mag[2],
                1013.25 - alt * 0.12, 0.0, alt, 25.0, _IMU_UPDATED,
            )  # fmt: skip
        else:
            return False
        return True

    def _send_places(self, mid: int, t: float) -> bool:
        """Send one message of the battery, estimator, home, mission, origin and version streams; False:
        ``mid`` is not one of them."""
        mav = self.conn.mav
        sim = self.sim
        if mid == mavlink2.MAVLINK_MSG_ID_BATTERY_STATUS:
            bat = sim.battery
            cells = min(bat.params.cells, 10)
            voltages = [int(bat.cell_voltage() * 1000)] * cells + [0xFFFF] * (10 - cells)
            mav.battery_status_send(
                0, mavlink2.MAV_BATTERY_FUNCTION_ALL, mavlink2.MAV_BATTERY_TYPE_LIPO, 0x7FFF, voltages,
                int(bat.current * 100), int(bat.consumed_mah), int(bat.energy_j / 100), round(bat.soc * 100), 0,
                _CHARGE_STATES[self._battery_level],
            )  # fmt: skip
        elif mid == mavlink2.MAVLINK_MSG_ID_ESTIMATOR_STATUS:
            mav.estimator_status_send(
                int(t * 1e6), self._estimator_flags(), NAN, 0.01, 0.01, 0.0, 0.0, NAN, 0.03, 0.02
            )
        elif mid == mavlink2.MAVLINK_MSG_ID_HOME_POSITION:
            proj = self.projection()
            if proj is None or not self._home_set:
                return True
            lat, lon, alt = self._home_global(proj)
            h = self._home
            q = (math.cos(self._home_yaw / 2), 0.0, 0.0, math.sin(self._home_yaw / 2))
            lat_e7, lon_e7, alt_mm = _i32(lat * 1e7), _i32(lon * 1e7), _i32(alt * 1000)
            usec = int(t * 1e6)
            mav.home_position_send(lat_e7, lon_e7, alt_mm, h[0], h[1], h[2], list(q), 0.0, 0.0, 0.0, usec)
        elif mid == mavlink2.MAVLINK_MSG_ID_MISSION_CURRENT:
            total = len(self._mission)
            if total == 0:
                state = mavlink2.MISSION_STATE_NO_MISSION
            elif self._mission_done:
                state = mavlink2.MISSION_STATE_COMPLETE
            elif self.mode == (px4.MAIN_AUTO, px4.AUTO_MISSION):
                state = mavlink2.MISSION_STATE_ACTIVE
            elif self._mission_current == 0:
                state = mavlink2.MISSION_STATE_NOT_STARTED
            else:
                state = mavlink2.MISSION_STATE_PAUSED
            in_mission = 1 if self.mode == (px4.MAIN_AUTO, px4.AUTO_MISSION) else 2
            mav.mission_current_send(self._mission_current, total, state, in_mission)
        elif mid == mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            origin = self.gps_origin
            if origin is not None:
                mav.gps_global_origin_send(
                    _i32(origin[0] * 1e7), _i32(origin[1] * 1e7), _i32(origin[2] * 1000), int(t * 1e6)
                )
        elif mid == mavlink2.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            uid = (self.system_id << 32) | 0x5E4A
            mav.autopilot_version_send(
                CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, uid
            )
        else:
            return False
        return True
