"""The flight logic of the simulated PX4: modes, arming checks, failsafes and what each mode flies.

Run at 50 Hz by :class:`~arena_common.sim.autopilot.SimAutopilot` (``_control``). Behaviour measured on
PX4 v1.16 SITL (see docs/px4.md) and reproduced here:

- Modes need what PX4's mode requirements say: Hold, Return and Mission a global position (an EKF origin
  and a north-aligned heading), Mission a valid mission, Takeoff and Land a local position, Offboard a
  setpoint received within COM_OF_LOSS_T and a local position, the manual modes manual control (never, in
  the arena). Disarmed, any mode may be selected (arming then fails); armed, a mode that cannot run is
  not entered (the command is still acknowledged ACCEPTED, as PX4 does).
- Arming: the checks' reasons as ``Preflight Fail: …`` lines, then PX4's ``Arming denied: Resolve system
  health failures first``.
- Position loss (vision gone for EKF2_NOAID_TOUT − 0.4 s): in Offboard the offboard-loss action
  (COM_OBL_RC_ACT) falls back to what can fly without a position — Position → Altitude (COM_POSCTL_NAVL 0)
  or Descend (1), Land/Hold/Return → Descend; in the AUTO modes Descend (reported as AUTO.LAND). Each
  activation says ``Failsafe activated`` (PX4's STATUSTEXT) and then the reason.
- Offboard loss (no setpoint for COM_OF_LOSS_T): COM_OBL_RC_ACT at once (0 Position, 1 Altitude,
  2 Stabilized: without manual control PX4 descends and lands in them; 3 Return, 4 Land, 5 Hold,
  6 Terminate, 7 Disarm); a setpoint stream coming back returns to Offboard.
- Data link loss (no GCS heartbeat for 2.5 s + COM_DL_LOSS_T, after one was heard): NAV_DLL_ACT (0 none,
  1 Hold, 2 Return, 3 Land, 5 Terminate, 6 Disarm), after COM_FAIL_ACT_T of Hold; NAV_DLL_ACT ≠ 0 also
  refuses arming without a ground station.
"""

from __future__ import annotations

import math
from typing import Any, Final

from arena_common.mavlink import px4
from arena_common.sim.base import AutopilotState, Vec3
from arena_common.sim.physics import MotorMode, Setpoint
from arena_common.sim.telemetry import GCS_TIMEOUT_S

__all__ = ["ACTION_MODES", "MODE_LABELS", "FlightMixin"]

NAN = math.nan
#: s: after PX4 v1.16 SITL reports Hold at the end of a takeoff (NAV_MC_ALT_RAD short of the altitude), its
#: altitude setpoint closes the rest by a factor 0.65 a second (vehicle_local_position_setpoint, ULog).
TAKEOFF_APPROACH_TAU = 2.3

#: Failsafe action → the (main, sub) mode PX4 reports while taking it.
ACTION_MODES: Final[dict[str, tuple[int, int]]] = {
    "hold": (px4.MAIN_AUTO, px4.AUTO_LOITER),
    "rtl": (px4.MAIN_AUTO, px4.AUTO_RTL),
    "land": (px4.MAIN_AUTO, px4.AUTO_LAND),
    "descend": (px4.MAIN_AUTO, px4.AUTO_LAND),  # PX4 reports Descend as AUTO.LAND
    "posctl_land": (px4.MAIN_POSCTL, 0),  # Position mode without sticks: lands where it is
    "altctl_descend": (px4.MAIN_ALTCTL, 0),  # Altitude mode without sticks: descends
    "stab_descend": (px4.MAIN_STABILIZED, 0),
}
_VERBS: Final = {
    "hold": "holding",
    "rtl": "returning",
    "land": "landing",
    "descend": "descending",
    "posctl_land": "Position mode, landing",
    "altctl_descend": "Altitude mode, descending",
    "stab_descend": "Stabilized mode, descending",
    "terminate": "terminating",
    "disarm": "disarming",
}
#: COM_OBL_RC_ACT → action.
_OBL_ACTIONS: Final = {
    px4.OBL_POSITION: "posctl_land",
    px4.OBL_ALTITUDE: "altctl_descend",
    px4.OBL_STABILIZED: "stab_descend",
    px4.OBL_RETURN: "rtl",
    px4.OBL_LAND: "land",
    px4.OBL_HOLD: "hold",
    px4.OBL_TERMINATE: "terminate",
    px4.OBL_DISARM: "disarm",
}
#: NAV_DLL_ACT → action.
_DLL_ACTIONS: Final = {1: "hold", 2: "rtl", 3: "land", 5: "terminate", 6: "disarm"}
#: PX4's names of the modes in its "Switching to … is currently not available".
MODE_LABELS: Final[dict[tuple[int, int], str]] = {
    (px4.MAIN_MANUAL, 0): "Manual",
    (px4.MAIN_ALTCTL, 0): "Altitude",
    (px4.MAIN_POSCTL, 0): "Position",
    (px4.MAIN_ACRO, 0): "Acro",
    (px4.MAIN_STABILIZED, 0): "Stabilized",
    (px4.MAIN_OFFBOARD, 0): "Offboard",
    (px4.MAIN_AUTO, px4.AUTO_TAKEOFF): "Takeoff",
    (px4.MAIN_AUTO, px4.AUTO_LOITER): "Hold",
    (px4.MAIN_AUTO, px4.AUTO_MISSION): "Mission",
    (px4.MAIN_AUTO, px4.AUTO_RTL): "Return",
    (px4.MAIN_AUTO, px4.AUTO_LAND): "Land",
}
_MANUAL_MAINS: Final = (px4.MAIN_MANUAL, px4.MAIN_ALTCTL, px4.MAIN_POSCTL, px4.MAIN_STABILIZED, px4.MAIN_ACRO)
_GLOBAL_MODES: Final = (
    (px4.MAIN_AUTO, px4.AUTO_LOITER),
    (px4.MAIN_AUTO, px4.AUTO_RTL),
    (px4.MAIN_AUTO, px4.AUTO_MISSION),
)
ARMING_DENIED: Final = "Arming denied: Resolve system health failures first"


class FlightMixin(AutopilotState):
    """Modes, arming, failsafes and navigation of :class:`~arena_common.sim.autopilot.SimAutopilot`."""

    _dll_action: str | None
    _dll_action_at: float
    _home_yaw: float

    # ------------------------------------------------------------------ public state

    @property
    def mode(self) -> tuple[int, int]:
        """Reported PX4 (main, sub) mode: a failsafe action overrides the user's choice."""
        if self.terminated:
            return (px4.MAIN_TERMINATION, 0)
        if self._failsafe is not None:
            return ACTION_MODES[self._failsafe[0]]
        return self._user_mode

    @property
    def failsafe(self) -> tuple[str, str, float] | None:
        """The failsafe being taken: (action, cause, vehicle time it started), or None."""
        if self._failsafe is None:
            return None
        return (self._failsafe[0], self._failsafe[1], self._failsafe_since)

    @property
    def mode_name(self) -> str:
        """Name of :attr:`mode`, e.g. ``"OFFBOARD"``."""
        return px4.mode_name(*self.mode)

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

    # ------------------------------------------------------------------ what the estimate allows

    def _pos_ok(self) -> bool:
        est = self.sim.estimator
        return est.xy_valid and est.z_valid

    def _global_ok(self) -> bool:
        """A global position: local position, an EKF origin and a north-aligned heading."""
        return self._pos_ok() and self.gps_origin is not None and self.sim.estimator.north_aligned

    def _offboard_stream_ok(self, t: float) -> bool:
        """PX4's offboard signal: a setpoint received within COM_OF_LOSS_T (one is enough)."""
        times = self._sp_times
        return bool(times) and t - times[-1] <= float(self.params.get("COM_OF_LOSS_T"))

    def _mode_unavailable(self, mode: tuple[int, int], t: float) -> str | None:
        """Why ``mode`` cannot run now (None when it can)."""
        main, _ = mode
        if main in _MANUAL_MAINS:
            return "no manual control input"
        if main == px4.MAIN_OFFBOARD:
            if not self._offboard_stream_ok(t):
                return "no offboard setpoint stream"
            return None if self._pos_ok() else "no position estimate"
        if mode in _GLOBAL_MODES and not self._global_ok():
            return "no global position (EKF origin and heading)" if self._pos_ok() else "no position estimate"
        if mode == (px4.MAIN_AUTO, px4.AUTO_MISSION) and not self._mission_valid():
            return "no valid mission"
        if not self._pos_ok():
            return "no position estimate"
        return None

    def _fallback(self, action: str) -> str:
        """The action PX4 takes instead when ``action`` cannot run without a (global) position."""
        if (action == "hold" and not self._global_ok()) or (
            action == "rtl" and not (self._global_ok() and self._home_set)
        ):
            action = "land"
        if action == "land" and not self._pos_ok():
            return "descend"
        if action == "posctl_land" and not self._pos_ok():
            return "altctl_descend" if int(self.params.get("COM_POSCTL_NAVL")) == 0 else "descend"
        return action

    # ------------------------------------------------------------------ the 50 Hz state machine

    def _control(self, t: float) -> None:
        sim = self.sim
        est = sim.estimator
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
        if not self._home_set and self._global_ok():
            self._set_home(est.out_position)  # PX4 sets home once the global position is valid
        landed = sim.landed
        if self.armed and landed != self._was_landed:
            self._statustext(
                px4.MAV_SEVERITY_INFO, "Landing detected" if landed else "Takeoff detected", tab=True
            )
        self._was_landed = landed
        self._datalink_checks(t)
        self._battery_checks(t)
        if self.armed and not self.terminated:
            self._failsafe_checks(t)
        self._auto_disarm(t)
        self._navigate(t)

    def _datalink_checks(self, t: float) -> None:
        heard = self._gcs_heard_at
        if heard == -math.inf:
            return
        if self._gcs_lost:
            if t - heard < GCS_TIMEOUT_S:
                self._gcs_lost = False
                self._statustext(px4.MAV_SEVERITY_INFO, "GCS connection regained", tab=True)
                if self._failsafe is not None and self._failsafe[1] == "datalink" and self._dll_action:
                    self._failsafe = None  # still in the Hold before the action: the user has it back
                    self._dll_action = None
                    self._enter_nav()
            return
        if t - heard < GCS_TIMEOUT_S + float(self.params.get("COM_DL_LOSS_T")):
            return
        self._gcs_lost = True
        action = _DLL_ACTIONS.get(int(self.params.get("NAV_DLL_ACT")))
        if (
            action is None
            or not self.armed
            or self.sim.landed
            or self.terminated
            or self._failsafe is not None
        ):
            return
        delay = max(0.0, float(self.params.get("COM_FAIL_ACT_T")))
        if action in ("hold", "terminate", "disarm") or delay == 0.0:
            self._set_failsafe(action, "datalink", f"Failsafe: no ground station, {_VERBS[action]}")
            return
        self._set_failsafe(
            "hold", "datalink", f"Failsafe: no ground station, {_VERBS[action]} in {delay:g} s"
        )
        self._dll_action, self._dll_action_at = action, t + delay

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
            sev, text = {
                1: (px4.MAV_SEVERITY_WARNING, "Low battery level"),
                2: (px4.MAV_SEVERITY_CRITICAL, "Critical battery level"),
                3: (px4.MAV_SEVERITY_EMERGENCY, "Emergency battery level"),
            }[level]
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

    def _offboard_loss_action(self) -> str:
        return _OBL_ACTIONS.get(int(self.params.get("COM_OBL_RC_ACT")), "posctl_land")

    def _failsafe_checks(self, t: float) -> None:
        in_air = not self.sim.landed
        user_main = self._user_mode[0]
        current = self._failsafe
        if current is not None:
            if current[1] == "datalink" and self._dll_action is not None and t >= self._dll_action_at:
                action, self._dll_action = self._dll_action, None
                if action in ("terminate", "disarm"):
                    self._set_failsafe(action, "datalink", f"Failsafe: no ground station, {_VERBS[action]}")
                    return
                self._failsafe = (action, "datalink")
                self._enter_nav()
            fallback = self._fallback(self._failsafe[0]) if self._failsafe is not None else None
            if self._failsafe is not None and fallback is not None and fallback != self._failsafe[0]:
                self._failsafe = (fallback, self._failsafe[1])  # e.g. Land without a position: Descend
                self._enter_nav()
        # Position loss while flying a mode that needs it.
        needs_position = user_main in (px4.MAIN_OFFBOARD, px4.MAIN_AUTO)
        if in_air and needs_position and not self._pos_ok():
            if self._failsafe is None or self._failsafe[1] not in ("position", "datalink", "battery"):
                action = self._offboard_loss_action() if user_main == px4.MAIN_OFFBOARD else "descend"
                self._set_failsafe(
                    action, "position", f"Failsafe: no position estimate, {_VERBS[self._fallback(action)]}"
                )
            return
        bat = self._battery_action()
        if bat is not None and self._battery_level > self._battery_action_level:
            self._battery_action_level = self._battery_level
            if in_air:
                self._set_failsafe(bat, "battery", f"Failsafe: low battery, {_VERBS[self._fallback(bat)]}")
                return
        if user_main == px4.MAIN_OFFBOARD:
            lost = not self._offboard_stream_ok(t)
            current = self._failsafe
            if lost and current is None:
                action = self._offboard_loss_action()
                self._set_failsafe(
                    action, "offboard", f"Failsafe: no offboard signal, {_VERBS[self._fallback(action)]}"
                )
            elif not lost and current is not None and current[1] == "offboard":
                self._failsafe = None  # the stream is back: PX4 returns to Offboard
                self._enter_nav()

    def _set_failsafe(self, action: str, cause: str, text: str) -> None:
        self._statustext(px4.MAV_SEVERITY_CRITICAL, "Failsafe activated", tab=True)
        self._statustext(px4.MAV_SEVERITY_CRITICAL, text)
        if action == "terminate":
            self._terminate()
            return
        if action == "disarm":
            self._disarm("failsafe", forced=True)
            return
        self._failsafe = (self._fallback(action), cause)
        self._failsafe_since = self.sim.time
        self._enter_nav()

    def _terminate(self) -> None:
        self.terminated = True
        self._failsafe = None
        self.sim.motor_mode = MotorMode.OFF
        self._statustext(px4.MAV_SEVERITY_EMERGENCY, "Flight termination active")

    def _auto_disarm(self, t: float) -> None:
        if not self.armed:
            return
        if not self.sim.landed:
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
                self._disarm("landing", forced=True)
        elif prflt > 0 and t - self._armed_at >= prflt:
            self._disarm("auto preflight disarming", forced=True)

    # ------------------------------------------------------------------ navigation

    def _set_home(self, position: Vec3) -> None:
        self._home = position
        self._home_yaw = self.sim.estimator.yaw
        self._home_set = True

    def _cruise(self) -> float:
        """Horizontal speed of AUTO moves: DO_CHANGE_SPEED, else MPC_XY_CRUISE."""
        speed = self._cruise_speed if self._cruise_speed > 0 else float(self.params.get("MPC_XY_CRUISE"))
        return min(speed, float(self.params.get("MPC_XY_VEL_MAX")))

    def _brake(self, speed: float, tau: float) -> tuple[float, float]:
        """(distance, speed) ``tau`` seconds into PX4's Hold braking from ``speed``: a jerk-limited stop
        (MPC_JERK_AUTO, deceleration at most MPC_ACC_HOR), as PX4 v1.16 SITL was measured to stop (the
        parity tier, four flights: 14–26 cm and 0.65–2.1 s from 0.35–0.38 m/s, the switch to Hold and the
        hover's wander included; this stop is v·√(v/j) = 10–12 cm in 2√(v/j) = 0.6 s before the switch
        and the estimate's lag; the navigator's braking point v·(v/(2·a) + 0.6 s) = 23–25 cm lies within
        PX4's spread too: four flights do not tell the two apart)."""
        j = float(self.params.get("MPC_JERK_AUTO"))
        a = float(self.params.get("MPC_ACC_HOR"))
        t1 = min(math.sqrt(speed / j), a / j)  # deceleration ramps up (and later down) for t1
        peak = j * t1
        t2 = max(0.0, (speed - peak * t1) / peak)  # then holds at its peak, when that peak is MPC_ACC_HOR
        tau = min(max(tau, 0.0), 2 * t1 + t2)
        if tau <= t1:
            return speed * tau - j * tau**3 / 6, speed - j * tau**2 / 2
        s, v = speed * t1 - j * t1**3 / 6, speed - j * t1**2 / 2
        d = min(tau - t1, t2)
        s, v = s + v * d - peak * d * d / 2, v - peak * d
        d = tau - t1 - t2
        if d > 0:
            s, v = s + v * d - peak * d * d / 2 + j * d**3 / 6, v - peak * d + j * d * d / 2
        return s, max(v, 0.0)

    def _braking_point(self) -> Vec3:
        """Where Hold stops a moving multicopter: the estimate moved along its horizontal course by the
        distance of :meth:`_brake`'s whole stop."""
        est = self.sim.estimator
        p, v = est.out_position, est.out_velocity
        speed = math.hypot(v[0], v[1])
        if self.ideal or self.sim.landed or speed < 1e-3:
            return p
        dist, _ = self._brake(speed, math.inf)
        return (p[0] + v[0] / speed * dist, p[1] + v[1] / speed * dist, p[2])

    def _brake_setpoint(self, t: float, nav: dict[str, Any]) -> Setpoint:
        """The way to the braking point along :meth:`_brake`'s profile, with its velocity as feed-forward."""
        t0, p0, (vn, ve) = nav["brake"]
        speed = math.hypot(vn, ve)
        s, v = self._brake(speed, t - t0)
        if v <= 0.0:  # stopped: Hold keeps where it stopped (PX4 flies no way back to its braking point)
            nav["braked"] = True
            here = self.sim.estimator.out_position
            nav["hold"] = (here[0], here[1], nav["hold"][2])
            return Setpoint.hold(nav["hold"], nav["yaw"])
        un, ue = vn / speed, ve / speed
        return Setpoint(
            position=(p0[0] + un * s, p0[1] + ue * s, self._hold_height(t, nav)),
            velocity=(un * v, ue * v, 0.0),
            yaw=nav["yaw"],
        )

    @staticmethod
    def _hold_height(t: float, nav: dict[str, Any]) -> float:
        """Hold's height: after a takeoff approached exponentially, as PX4's (docs/px4.md), else the hold's."""
        hold = nav["hold"]
        if "approach" not in nav:
            return float(hold[2])
        t0, dz = nav["approach"]
        return float(hold[2] + dz * math.exp(-(t - t0) / TAKEOFF_APPROACH_TAU))

    def _enter_nav(self) -> None:
        """Initialise the behaviour of the current (reported) mode from the present estimate."""
        est = self.sim.estimator
        self._nav = {"mode": self.mode, "hold": est.out_position, "yaw": est.yaw, "phase": "return"}
        if self.mode == (px4.MAIN_AUTO, px4.AUTO_LOITER):
            self._nav["hold"] = self._braking_point()
            v = est.out_velocity
            if self._nav["hold"] != est.out_position:  # braking: a smooth path to the point, as PX4's
                self._nav["brake"] = (self.sim.time, est.out_position, (v[0], v[1]))
        if self.mode == (px4.MAIN_AUTO, px4.AUTO_RTL):
            home, p = self._home, est.out_position
            alt = p[2]
            if math.hypot(p[0] - home[0], p[1] - home[1]) > float(self.params.get("RTL_MIN_DIST")):
                alt = min(alt, home[2] - float(self.params.get("RTL_RETURN_ALT")))
            self._nav["alt"] = alt

    def _carrot(self, target: Vec3, yaw: float) -> Setpoint:
        """A position setpoint moving toward ``target`` at the cruise speed (horizontally)."""
        p = self.sim.estimator.out_position
        dx, dy = target[0] - p[0], target[1] - p[1]
        dist = math.hypot(dx, dy)
        step = self._cruise()
        if dist <= step:
            return Setpoint.hold(target, yaw)
        return Setpoint.hold((p[0] + dx / dist * step, p[1] + dy / dist * step, target[2]), yaw)

    def _land_speed(self) -> float:
        """Land's descent speed: MPC_LAND_SPEED above MPC_LAND_ALT2, MPC_LAND_CRWL below MPC_LAND_ALT3,
        graded in between, by the height above home.  PX4 v1.16 SITL crawls so without a distance sensor
        (the parity tier: 2.9–3.6 s from ~1.1 m to the floor, where MPC_LAND_SPEED alone takes ~1.7 s)."""
        fast, crawl = float(self.params.get("MPC_LAND_SPEED")), float(self.params.get("MPC_LAND_CRWL"))
        alt2, alt3 = float(self.params.get("MPC_LAND_ALT2")), float(self.params.get("MPC_LAND_ALT3"))
        height = self._home[2] - self.sim.estimator.out_position[2] if self._home_set else 0.0
        if alt2 <= alt3:
            return fast if height >= alt2 else crawl
        return crawl + (fast - crawl) * min(1.0, max(0.0, (height - alt3) / (alt2 - alt3)))

    def _land_setpoint(self, hold: Vec3, yaw: float) -> Setpoint:
        speed = self._land_speed()
        return Setpoint(position=(hold[0], hold[1], NAN), velocity=(NAN, NAN, speed), yaw=yaw)

    def _navigate(self, t: float) -> None:
        sim = self.sim
        if not self.armed or self.terminated:
            sim.motor_mode = MotorMode.OFF
            return
        mode = self.mode
        if self._nav.get("mode") != mode:
            self._enter_nav()
        nav = self._nav
        est = sim.estimator
        action = self._failsafe[0] if self._failsafe is not None else None
        if action in ("altctl_descend", "stab_descend") or (action == "descend" and not self._pos_ok()):
            sim.motor_mode = MotorMode.DESCEND  # level attitude, vertical speed only
            sim.descend_rate = float(self.params.get("MPC_LAND_SPEED"))
            return
        sim.motor_mode = MotorMode.FLY
        if action in ("posctl_land", "descend"):
            sim.setpoint = self._land_setpoint(nav["hold"], nav["yaw"])
        elif mode[0] == px4.MAIN_OFFBOARD:
            sim.setpoint = self._offboard_sp
        elif mode == (px4.MAIN_AUTO, px4.AUTO_TAKEOFF):
            target = nav.get("target")
            if target is None:
                alt = nav.get("alt", float(self.params.get("MIS_TAKEOFF_ALT")))
                hold = nav["hold"]
                target = (hold[0], hold[1], self._home[2] - alt)
                nav["target"] = target
            if self.ideal:
                sim.setpoint = Setpoint.hold(target, nav["yaw"])
                done = abs(est.out_position[2] - target[2]) < 0.1
            else:  # PX4: on the ground until spool-up and thrust ramp are over; Hold NAV_MC_ALT_RAD short
                start = nav.setdefault("tko_start", t)
                lift = max(start, self._armed_at + float(self.params.get("COM_SPOOLUP_TIME")))
                lift += float(self.params.get("MPC_TKO_RAMP_T"))
                sim.setpoint = Setpoint.hold(target if t >= lift else nav["hold"], nav["yaw"])
                done = t >= lift and abs(est.out_position[2] - target[2]) < float(
                    self.params.get("NAV_MC_ALT_RAD")
                )
            if done and not sim.landed:
                self._user_mode = (px4.MAIN_AUTO, px4.AUTO_LOITER)
                self._enter_nav()
                self._nav["hold"] = target
                if not self.ideal:  # PX4's Hold then approaches the altitude slowly (docs/px4.md)
                    self._nav["approach"] = (t, est.out_position[2] - target[2])
        elif mode == (px4.MAIN_AUTO, px4.AUTO_LAND):
            sim.setpoint = self._land_setpoint(nav["hold"], nav["yaw"])
        elif mode == (px4.MAIN_AUTO, px4.AUTO_RTL):
            home = self._home
            if nav["phase"] == "return":
                p = est.out_position
                if math.hypot(home[0] - p[0], home[1] - p[1]) < 0.3:
                    nav["phase"] = "land"
                    nav["hold"] = (home[0], home[1], p[2])
                else:
                    sim.setpoint = self._carrot((home[0], home[1], nav["alt"]), nav["yaw"])
            if nav["phase"] == "land":
                sim.setpoint = self._land_setpoint(nav["hold"], nav["yaw"])
        elif mode == (px4.MAIN_AUTO, px4.AUTO_MISSION):
            self._mission_navigate(t)
        else:  # AUTO.LOITER: hold where the mode started, or fly to a reposition target
            goal = nav.get("goto")
            if goal is not None:
                sim.setpoint = self._carrot(goal, nav.get("goto_yaw", nav["yaw"]))
            elif "brake" in nav and not nav.get("braked"):
                sim.setpoint = self._brake_setpoint(t, nav)
            else:
                hold = nav["hold"]
                sim.setpoint = Setpoint.hold((hold[0], hold[1], self._hold_height(t, nav)), nav["yaw"])

    # ------------------------------------------------------------------ arming

    def _arm_denial(self, t: float) -> list[str]:
        """Reasons (``Preflight Fail: …`` lines) arming is refused now, empty when it may arm."""
        p = self.params
        est = self.sim.estimator
        if self.terminated:
            return ["Arming denied: flight terminated", "Reboot the vehicle to fly again"]
        reasons: list[str] = []
        mode = self._user_mode
        if mode[0] in _MANUAL_MAINS:  # only a manual mode needs sticks (PX4 SITL arms in Hold without any)
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
        elif not est.north_aligned:
            reasons.append("Preflight Fail: heading not aligned (vision yaw in LOCAL_FRD never aligns)")
        elif mode in _GLOBAL_MODES and not self._global_ok():
            reasons.append(f"Preflight Fail: {MODE_LABELS[mode]} needs a global position (no EKF origin)")
        if mode == (px4.MAIN_AUTO, px4.AUTO_MISSION) and not self._mission_valid():
            reasons.append("Preflight Fail: no valid mission")
        if self._battery_level >= 2:
            reasons.append("Preflight Fail: battery too low")
        if int(p.get("NAV_DLL_ACT")) != 0 and not self.gcs_connected(t):
            reasons.append("Preflight Fail: No connection to the ground control station")
        if mode[0] == px4.MAIN_OFFBOARD and not self._offboard_stream_ok(t):
            reasons.append("Arming denied: no offboard signal")
        return reasons

    def _arm_request(self, p: tuple[float, ...], t: float) -> int | None:
        """MAV_CMD_COMPONENT_ARM_DISARM: param1 1 arms, 0 (or NaN, as PX4 reads it) disarms; param2 21196
        forces. Any other param1 is refused with a STATUSTEXT and no acknowledgement, as PX4 does."""
        R = px4
        want = p[0] if math.isfinite(p[0]) else 0.0
        force = math.isfinite(p[1]) and round(p[1]) == R.ARM_DISARM_FORCE_MAGIC
        if round(want) not in (0, 1) or want != round(want):
            self._statustext(R.MAV_SEVERITY_CRITICAL, f"Unsupported ARM_DISARM param: {want:.3f}", tab=True)
            return None
        if round(want) == 1:
            if self.armed:
                return R.MAV_RESULT_ACCEPTED
            reasons = [] if force and not self.terminated else self._arm_denial(t)
            if reasons:
                for line in reasons:
                    severity = R.MAV_SEVERITY_WARNING if "ground control" in line else R.MAV_SEVERITY_CRITICAL
                    self._statustext(severity, line)
                self._statustext(R.MAV_SEVERITY_CRITICAL, ARMING_DENIED, tab=True)
                return R.MAV_RESULT_TEMPORARILY_REJECTED
            self._arm(t)
            return R.MAV_RESULT_ACCEPTED
        if not self.armed:
            return R.MAV_RESULT_ACCEPTED
        if not self.sim.landed and not force:
            self._statustext(R.MAV_SEVERITY_CRITICAL, "Disarming denied: not landed", tab=True)
            return R.MAV_RESULT_TEMPORARILY_REJECTED
        self._disarm("external command", forced=force)
        return R.MAV_RESULT_ACCEPTED

    def _arm(self, t: float) -> None:
        takeoff_alt = self._nav.get("alt")
        self.armed = True
        self._armed_at = t
        self._flew_since_arming = False
        self._landed_since = t
        self._was_landed = self.sim.landed
        self._failsafe = None
        self._battery_action_level = self._battery_level
        self._set_home(self.sim.estimator.out_position)  # PX4 sets home on arming
        self.sim.controller.reset()
        self._enter_nav()
        if takeoff_alt is not None and self._user_mode == (px4.MAIN_AUTO, px4.AUTO_TAKEOFF):
            self._nav["alt"] = takeoff_alt  # a takeoff commanded before arming keeps its altitude
        self._statustext(px4.MAV_SEVERITY_INFO, "Armed by external command", tab=True)

    def _disarm(self, why: str, forced: bool) -> None:
        was_in_air = not self.sim.landed
        self.armed = False
        self.sim.motor_mode = MotorMode.OFF
        self._failsafe = None
        self._dll_action = None
        if forced and was_in_air:
            self._statustext(px4.MAV_SEVERITY_CRITICAL, "Motors killed in the air")
        self._statustext(px4.MAV_SEVERITY_INFO, f"Disarmed by {why}", tab=True)
