"""Commands and setpoints the simulated PX4 accepts, answered as PX4 v1.16 answers them.

COMMAND_LONG and COMMAND_INT (whose ``x``/``y`` are 1e7 degrees in the global frames) are executed once
and acknowledged to their sender; a retry (higher ``confirmation``) of one executed within 5 s is acked
with the first result without running it again. Every parameter may be NaN, ±inf or huge: nothing here
raises on it (what PX4 does with such values is followed where it was measured: ARM_DISARM param1 NaN
reads as 0, i.e. disarm; SET_MESSAGE_INTERVAL with NaN is accepted and changes nothing).

Answers measured on PX4 v1.16 SITL and reproduced: DO_SET_MODE is ACCEPTED for every PX4 mode — disarmed
the mode is taken (arming then says what is missing), armed a mode that cannot run is not entered
(``Switching to … is currently not available``); REQUEST_MESSAGE of an unknown message DENIED;
SET_MESSAGE_INTERVAL of a message the vehicle cannot stream FAILED; ARM_DISARM param1 other than 0/1 gets
a STATUSTEXT and no acknowledgement; FLIGHTTERMINATION param1 0 DENIED; PREFLIGHT_REBOOT_SHUTDOWN param1
0 ACCEPTED (nothing), 1 reboots (PX4 SITL answers DENIED: it cannot reboot; hardware does), others DENIED
(SITL's shutdown, param1 2, ends the px4 process: the simulation refuses it); DO_REPOSITION and
DO_CHANGE_SPEED ACCEPTED (the reposition flies in Hold, in the air, with a global position);
MISSION_START without a valid mission DENIED. Unknown commands: UNSUPPORTED.

SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED, or MAV_FRAME_BODY_NED (velocity and acceleration
turned by the heading; position ignored), as PX4; other frames are refused with PX4's STATUSTEXT.
SET_POSITION_TARGET_GLOBAL_INT in GLOBAL_INT / GLOBAL_RELATIVE_ALT_INT, projected around the EKF origin
(dropped without one). Any accepted setpoint is the offboard signal, in any mode.
"""

from __future__ import annotations

import math
from typing import Any, Final

from arena_common.mavlink import px4
from arena_common.mavlink.link import mavlink2
from arena_common.sim.base import AutopilotState, as_int, finite
from arena_common.sim.flight import MODE_LABELS
from arena_common.sim.physics import Setpoint

__all__ = ["CommandsMixin"]

NAN = math.nan

_KNOWN_MAINS: Final = frozenset(
    {
        px4.MAIN_MANUAL,
        px4.MAIN_ALTCTL,
        px4.MAIN_POSCTL,
        px4.MAIN_AUTO,
        px4.MAIN_ACRO,
        px4.MAIN_OFFBOARD,
        px4.MAIN_STABILIZED,
    }
)
_KNOWN_AUTO: Final = frozenset(
    {px4.AUTO_TAKEOFF, px4.AUTO_LOITER, px4.AUTO_MISSION, px4.AUTO_RTL, px4.AUTO_LAND}
)
_RELATIVE_CMD_FRAMES: Final = frozenset(
    {mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
)
_GLOBAL_CMD_FRAMES: Final = _RELATIVE_CMD_FRAMES | {mavlink2.MAV_FRAME_GLOBAL, mavlink2.MAV_FRAME_GLOBAL_INT}
RETRY_WINDOW_S: Final = 5.0
MAX_ALT_M: Final = 100_000.0  # beyond this an altitude is nonsense (taken as not given)


def _latlon_ok(lat: float, lon: float) -> bool:
    return finite(lat) and finite(lon) and abs(lat) <= 90.0 and abs(lon) <= 180.0


class CommandsMixin(AutopilotState):
    """COMMAND_LONG/COMMAND_INT and setpoints of :class:`~arena_common.sim.autopilot.SimAutopilot`."""

    _command_history: dict[tuple[Any, ...], tuple[float, int | None, int]]
    _cmd_frame: int | None

    # ------------------------------------------------------------------ reception

    def _on_command_long(self, msg: Any, t: float) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._cmd_frame = None
        self._on_command(msg, msg.command, params, msg.confirmation, t)

    def _on_command_int(self, msg: Any, t: float) -> None:
        frame = int(msg.frame)
        x, y = float(msg.x), float(msg.y)
        if frame in _GLOBAL_CMD_FRAMES:
            x, y = x * 1e-7, y * 1e-7
        self._cmd_frame = frame
        self._on_command(
            msg, msg.command, (msg.param1, msg.param2, msg.param3, msg.param4, x, y, msg.z), 0, t
        )

    def _on_command(
        self, msg: Any, command: int, params: tuple[float, ...], confirmation: int, t: float
    ) -> None:
        broadcast_ok = command in (
            px4.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
            px4.MAV_CMD_REQUEST_PROTOCOL_VERSION,
        )
        if not self._addressed(msg.target_system, msg.target_component, broadcast_ok):
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        key = (src, command, tuple(p if p == p else "nan" for p in params))
        now = self.clock.now()  # the shared clock, so that the history survives a reboot
        previous = self._command_history.get(key)
        if previous is not None and confirmation > 0:
            when, result, prev_conf = previous
            if now - when <= RETRY_WINDOW_S and confirmation > prev_conf:
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

    def _ack(self, command: int, result: int | None, src: tuple[int, int]) -> None:
        if result is not None:  # None: PX4 sends no acknowledgement
            self.conn.mav.command_ack_send(command, result, 0, 0, src[0], src[1])

    # ------------------------------------------------------------------ execution

    def _execute(self, command: int, p: tuple[float, ...], t: float) -> int | None:
        R = px4
        if command == 0:
            return None  # PX4 does not answer command 0
        if command == R.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_request(p, t)
        if command == R.MAV_CMD_DO_SET_MODE:
            return self._cmd_set_mode(p, t)
        if command == R.MAV_CMD_NAV_TAKEOFF:
            return self._cmd_takeoff(p, t)
        if command == R.MAV_CMD_NAV_LAND:
            result = self._change_mode((R.MAIN_AUTO, R.AUTO_LAND), t)
            if self.mode == (R.MAIN_AUTO, R.AUTO_LAND):
                self._statustext(R.MAV_SEVERITY_INFO, "Landing at current position", tab=True)
            return result
        if command == px4.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._change_mode((R.MAIN_AUTO, R.AUTO_RTL), t)
        if command == R.MAV_CMD_DO_FLIGHTTERMINATION:
            if finite(p[0]) and p[0] > 0.5:
                if not self.terminated:
                    self._terminate()
                return R.MAV_RESULT_ACCEPTED
            return R.MAV_RESULT_DENIED
        if command == R.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            return self._cmd_reboot(p)
        if command == px4.MAV_CMD_PREFLIGHT_STORAGE:
            # PX4 saves on param1 1 (its parameters persist already; so do the simulated vehicle's).
            return R.MAV_RESULT_ACCEPTED if finite(p[0]) and int(p[0]) in (0, 1) else R.MAV_RESULT_DENIED
        if command == R.MAV_CMD_SET_MESSAGE_INTERVAL:
            msgid = as_int(p[0], 0, 0xFFFFFF)
            if msgid is None:
                return R.MAV_RESULT_ACCEPTED  # PX4 accepts (and ignores) a NaN message id
            ok = self._set_interval(msgid, p[1], t)
            return R.MAV_RESULT_ACCEPTED if ok else R.MAV_RESULT_FAILED
        if command == R.MAV_CMD_REQUEST_MESSAGE:
            msgid = as_int(p[0], 0, 0xFFFFFF)
            return (
                R.MAV_RESULT_ACCEPTED
                if msgid is not None and self._request_message(msgid)
                else R.MAV_RESULT_DENIED
            )
        if command == R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._request_message(mavlink2.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
            return R.MAV_RESULT_ACCEPTED
        if command == px4.MAV_CMD_REQUEST_PROTOCOL_VERSION:
            return R.MAV_RESULT_ACCEPTED  # PX4 acknowledges; no PROTOCOL_VERSION was seen from SITL
        if command == px4.MAV_CMD_DO_CHANGE_SPEED:
            if finite(p[1]) and p[1] > 0:
                self._cruise_speed = min(p[1], 100.0)
            return R.MAV_RESULT_ACCEPTED
        if command == px4.MAV_CMD_DO_REPOSITION:
            return self._cmd_reposition(p, t)
        if command == px4.MAV_CMD_DO_SET_HOME:
            return self._cmd_set_home(p)
        if command == px4.MAV_CMD_MISSION_START:
            return self._cmd_mission_start(p, t)
        if command == px4.MAV_CMD_DO_SET_MISSION_CURRENT:
            seq = as_int(p[0], 0, 0xFFFF)
            ok = seq is not None and self._mission_set_current(seq)
            return R.MAV_RESULT_ACCEPTED if ok else R.MAV_RESULT_DENIED
        return R.MAV_RESULT_UNSUPPORTED

    def _cmd_reboot(self, p: tuple[float, ...]) -> int:
        R = px4
        what = as_int(p[0], 0, 255)
        if what == 0:
            return R.MAV_RESULT_ACCEPTED  # "do nothing" for the autopilot
        if what != 1:
            return R.MAV_RESULT_DENIED
        if self.armed:
            self._statustext(R.MAV_SEVERITY_CRITICAL, "Reboot denied: vehicle armed")
            return R.MAV_RESULT_DENIED
        self._statustext(R.MAV_SEVERITY_INFO, "Rebooting")
        self._rebooting_until_ns = self.clock.now_ns() + int(self.REBOOT_SECONDS * 1e9)
        return R.MAV_RESULT_ACCEPTED

    def _cmd_takeoff(self, p: tuple[float, ...], t: float) -> int:
        """NAV_TAKEOFF: param7 is PX4's AMSL altitude when home has one, else (no EKF origin) the height
        above home; NaN or not above home means MIS_TAKEOFF_ALT."""
        R = px4
        height = NAN
        if finite(p[6]):
            proj = self.projection()
            height = p[6] - (proj.alt - self._home[2]) if proj is not None and self._home_set else p[6]
        default = not (finite(height) and 0 < height < MAX_ALT_M)
        if default:
            height = float(self.params.get("MIS_TAKEOFF_ALT"))
        result = self._change_mode((R.MAIN_AUTO, R.AUTO_TAKEOFF), t)
        if self._user_mode == (R.MAIN_AUTO, R.AUTO_TAKEOFF):
            self._nav["alt"] = height
            self._nav.pop("target", None)
            if default:
                self._statustext(
                    R.MAV_SEVERITY_INFO, f"Using default takeoff altitude: {height:.1f} m", tab=True
                )
        return result

    def _cmd_set_mode(self, p: tuple[float, ...], t: float) -> int:
        R = px4
        base = as_int(p[0], 0, 255)
        main = as_int(p[1], 0, 255)
        sub = as_int(p[2], 0, 255) or 0
        if base is None or not base & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED or main is None:
            return R.MAV_RESULT_ACCEPTED  # PX4 acknowledges these and changes nothing
        if main == R.MAIN_AUTO and sub == 0:
            sub = R.AUTO_LOITER
        if main != R.MAIN_AUTO:
            sub = 0
        return self._change_mode((main, sub), t)

    def _change_mode(self, mode: tuple[int, int], t: float) -> int:
        """Switch the user's mode as PX4 v1.16 does (ACCEPTED even when an armed vehicle cannot switch)."""
        R = px4
        main, sub = mode
        if main not in _KNOWN_MAINS or (main == R.MAIN_AUTO and sub not in _KNOWN_AUTO):
            self._statustext(R.MAV_SEVERITY_CRITICAL, f"{R.mode_name(main, sub)}: mode not supported")
            return R.MAV_RESULT_DENIED
        if self.terminated:
            self._statustext(R.MAV_SEVERITY_CRITICAL, f"{R.mode_name(main, sub)} rejected: flight terminated")
            return R.MAV_RESULT_TEMPORARILY_REJECTED
        if self.armed:
            reason = self._mode_unavailable(mode, t)
            if reason is not None:
                label = MODE_LABELS.get(mode, R.mode_name(main, sub))
                self._statustext(
                    R.MAV_SEVERITY_CRITICAL, f"Switching to {label} is currently not available", tab=True
                )
                self._statustext(R.MAV_SEVERITY_CRITICAL, f"{R.mode_name(main, sub)} rejected: {reason}")
                return R.MAV_RESULT_ACCEPTED
        self._user_mode = mode
        self._failsafe = None
        if mode == (R.MAIN_AUTO, R.AUTO_MISSION):
            self._mission_start(t)
        self._enter_nav()
        return R.MAV_RESULT_ACCEPTED

    def _cmd_reposition(self, p: tuple[float, ...], t: float) -> int:
        """DO_REPOSITION: fly to lat/lon/alt (param5..7; NaN keeps that coordinate) in Hold, at param1 m/s."""
        R = px4
        proj = self.projection()
        if not self.armed or self.sim.landed or proj is None or not self._global_ok():
            return R.MAV_RESULT_ACCEPTED  # PX4 acknowledges, and nothing moves
        here = self.sim.estimator.out_position
        north, east = here[0], here[1]
        if _latlon_ok(p[4], p[5]):
            north, east = proj.project(p[4], p[5])
        down = here[2]
        if finite(p[6]) and abs(p[6]) < MAX_ALT_M:
            relative = self._cmd_frame in _RELATIVE_CMD_FRAMES
            down = self._home[2] - p[6] if relative else proj.alt - p[6]
        if self.mode != (R.MAIN_AUTO, R.AUTO_LOITER):
            self._change_mode((R.MAIN_AUTO, R.AUTO_LOITER), t)
            if self.mode != (R.MAIN_AUTO, R.AUTO_LOITER):
                return R.MAV_RESULT_ACCEPTED  # Hold cannot run: nothing moves
        if finite(p[0]) and p[0] > 0:
            self._cruise_speed = min(p[0], 100.0)
        self._nav["goto"] = (north, east, down)
        self._nav["hold"] = (north, east, down)
        if finite(p[3]):
            self._nav["goto_yaw"] = p[3]
            self._nav["yaw"] = p[3]
        return R.MAV_RESULT_ACCEPTED

    def _cmd_set_home(self, p: tuple[float, ...]) -> int:
        R = px4
        if finite(p[0]) and round(p[0]) == 1:
            self._set_home(self.sim.estimator.out_position)
            return R.MAV_RESULT_ACCEPTED
        proj = self.projection()
        if proj is None or not (_latlon_ok(p[4], p[5]) and finite(p[6]) and abs(p[6]) < MAX_ALT_M):
            return R.MAV_RESULT_DENIED
        north, east = proj.project(p[4], p[5])
        self._set_home((north, east, proj.alt - p[6]))
        return R.MAV_RESULT_ACCEPTED

    # ------------------------------------------------------------------ setpoints

    def _take_setpoint(self, sp: Setpoint, t: float) -> None:
        self._offboard_sp = sp
        self._sp_times.append(t)
        if self.mode[0] == px4.MAIN_OFFBOARD and self.armed:
            self.sim.setpoint = sp

    def _frame_text(self, t: float, text: str) -> None:
        if t - self._frame_warned_at > 5.0:  # PX4 says it for every message; once per 5 s is enough here
            self._frame_warned_at = t
            self._statustext(px4.MAV_SEVERITY_CRITICAL, text, tab=True)

    def _on_set_position_target(self, msg: Any, t: float) -> None:
        R = px4
        if not self._addressed(msg.target_system, msg.target_component, True):
            return
        m = int(msg.type_mask)
        frame = int(msg.coordinate_frame)
        vel = (
            NAN if m & R.TYPEMASK_VX_IGNORE else msg.vx,
            NAN if m & R.TYPEMASK_VY_IGNORE else msg.vy,
            NAN if m & R.TYPEMASK_VZ_IGNORE else msg.vz,
        )
        acc = (
            NAN if m & R.TYPEMASK_AX_IGNORE else msg.afx,
            NAN if m & R.TYPEMASK_AY_IGNORE else msg.afy,
            NAN if m & R.TYPEMASK_AZ_IGNORE else msg.afz,
        )
        if frame == R.MAV_FRAME_LOCAL_NED:
            pos = (
                NAN if m & R.TYPEMASK_X_IGNORE else msg.x,
                NAN if m & R.TYPEMASK_Y_IGNORE else msg.y,
                NAN if m & R.TYPEMASK_Z_IGNORE else msg.z,
            )
        elif frame == R.MAV_FRAME_BODY_NED:
            yaw = self.sim.estimator.yaw
            c, s = math.cos(yaw), math.sin(yaw)
            pos = (NAN, NAN, NAN)
            if not all(v != v for v in vel):
                bx, by, bz = (0.0 if v != v else v for v in vel)
                vel = (c * bx - s * by, s * bx + c * by, bz)
            if not all(a != a for a in acc):
                ax, ay, az = (0.0 if a != a else a for a in acc)
                acc = (c * ax - s * ay, s * ax + c * ay, az)
        else:
            self._frame_text(t, f"SET_POSITION_TARGET_LOCAL_NED coordinate frame {frame} unsupported")
            return
        self._setpoint_from(pos, vel, acc, m, msg.yaw, msg.yaw_rate, "SET_POSITION_TARGET_LOCAL_NED", t)

    def _on_set_position_target_global(self, msg: Any, t: float) -> None:
        R = px4
        if not self._addressed(msg.target_system, msg.target_component, True):
            return
        m = int(msg.type_mask)
        frame = int(msg.coordinate_frame)
        pos = (NAN, NAN, NAN)
        if not m & R.TYPEMASK_POSITION:
            proj = self.projection()
            if proj is None:
                return  # PX4 drops it without a global reference
            if not _latlon_ok(msg.lat_int * 1e-7, msg.lon_int * 1e-7) or not abs(msg.alt) < MAX_ALT_M:
                return
            north, east = proj.project(msg.lat_int * 1e-7, msg.lon_int * 1e-7)
            if frame == mavlink2.MAV_FRAME_GLOBAL_INT:
                down = proj.alt - msg.alt
            elif frame == mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT:
                if not self._home_set:
                    return
                down = self._home[2] - msg.alt
            elif frame == mavlink2.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT:  # no terrain estimate
                return
            else:
                self._frame_text(t, f"SET_POSITION_TARGET_GLOBAL_INT invalid coordinate frame {frame}")
                return
            pos = (north, east, down)
        vel = (
            NAN if m & R.TYPEMASK_VX_IGNORE else msg.vx,
            NAN if m & R.TYPEMASK_VY_IGNORE else msg.vy,
            NAN if m & R.TYPEMASK_VZ_IGNORE else msg.vz,
        )
        acc = (
            NAN if m & R.TYPEMASK_AX_IGNORE else msg.afx,
            NAN if m & R.TYPEMASK_AY_IGNORE else msg.afy,
            NAN if m & R.TYPEMASK_AZ_IGNORE else msg.afz,
        )
        self._setpoint_from(pos, vel, acc, m, msg.yaw, msg.yaw_rate, "SET_POSITION_TARGET_GLOBAL_INT", t)

    def _on_set_attitude_target(self, msg: Any, t: float) -> None:
        """SET_ATTITUDE_TARGET: an attitude and a normalised thrust (body rates are not simulated)."""
        R = px4
        if not self._addressed(msg.target_system, msg.target_component, True):
            return
        m = int(msg.type_mask)
        if m & R.ATTITUDE_TARGET_ATTITUDE_IGNORE or m & R.ATTITUDE_TARGET_THROTTLE_IGNORE:
            self._frame_text(t, "SET_ATTITUDE_TARGET without attitude or thrust not simulated")
            return
        q = tuple(float(c) for c in msg.q)
        n = math.sqrt(sum(c * c for c in q))
        if not all(finite(c) for c in q) or not finite(msg.thrust) or abs(n - 1.0) > 0.01:
            self._frame_text(t, "SET_ATTITUDE_TARGET invalid")
            return
        w, x, y, z = q
        self._take_setpoint(Setpoint(attitude=(w, x, y, z), thrust=float(msg.thrust)), t)

    def _setpoint_from(
        self,
        pos: tuple[float, float, float],
        vel: tuple[float, float, float],
        acc: tuple[float, float, float],
        mask: int,
        yaw: float,
        yaw_rate: float,
        what: str,
        t: float,
    ) -> None:
        R = px4
        # Infinite components are as unusable as ignored ones.
        pos = (
            pos[0] if finite(pos[0]) else NAN,
            pos[1] if finite(pos[1]) else NAN,
            pos[2] if finite(pos[2]) else NAN,
        )
        vel = (
            vel[0] if finite(vel[0]) else NAN,
            vel[1] if finite(vel[1]) else NAN,
            vel[2] if finite(vel[2]) else NAN,
        )
        acc = (
            acc[0] if finite(acc[0]) else NAN,
            acc[1] if finite(acc[1]) else NAN,
            acc[2] if finite(acc[2]) else NAN,
        )
        has_acc = not all(a != a for a in acc)
        if has_acc and mask & R.TYPEMASK_FORCE_SET:
            self._frame_text(t, f"{what} force not supported")
            return
        if all(c != c for c in (*pos, *vel, *acc)):
            self._frame_text(t, f"{what} invalid")
            return
        yaw = NAN if mask & R.TYPEMASK_YAW_IGNORE or not finite(yaw) else yaw
        yaw_rate = NAN if mask & R.TYPEMASK_YAW_RATE_IGNORE or not finite(yaw_rate) else yaw_rate
        self._take_setpoint(
            Setpoint(position=pos, velocity=vel, acceleration=acc, yaw=yaw, yaw_rate=yaw_rate), t
        )
