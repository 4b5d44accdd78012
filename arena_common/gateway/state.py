"""The vehicle as its autopilot reports it, kept up to date from its messages (:class:`VehicleState`), and the
:class:`~arena_common.core.wire.State` the gateway publishes of it (:class:`StateReport`)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

from arena_common.core import wire
from arena_common.gateway.clockwatch import ClockWatch
from arena_common.gateway.events import EventSink
from arena_common.gateway.setpoints import SetpointForwarder
from arena_common.gateway.timesync import TimeSync
from arena_common.gateway.vision import VisionSender
from arena_common.geometry.frames import quat_yaw
from arena_common.mavlink import px4
from arena_common.mavlink.protocols import SetupChecker

__all__ = ["StateReport", "VehicleState"]

_LANDED = ("undefined", "on_ground", "in_air", "takeoff", "landing")
_STATUS_FLAGS = {
    px4.MAV_STATE_CRITICAL: "failsafe",
    px4.MAV_STATE_EMERGENCY: "emergency",
    px4.MAV_STATE_FLIGHT_TERMINATION: "terminated",
}
_EST_REQUIRED = (
    (px4.ESTIMATOR_ATTITUDE, "attitude"),
    (px4.ESTIMATOR_VELOCITY_HORIZ, "horizontal velocity"),
    (px4.ESTIMATOR_POS_HORIZ_REL, "horizontal position"),
)
_BATTERY_FLAGS = {
    px4.MAV_BATTERY_CHARGE_STATE_LOW: "battery_low",
    px4.MAV_BATTERY_CHARGE_STATE_CRITICAL: "battery_critical",
    px4.MAV_BATTERY_CHARGE_STATE_EMERGENCY: "battery_emergency",
    px4.MAV_BATTERY_CHARGE_STATE_FAILED: "battery_failed",
}


class VehicleState:
    """What the autopilot reports, kept up to date from its messages (reader thread) and read by others."""

    def __init__(self, system_id: int, events: EventSink, link_timeout: float = 3.0) -> None:
        self.system_id = system_id
        self.events = events
        self.link_timeout = link_timeout
        self.cond = threading.Condition()
        self.hb_time: float | None = None
        self.hb_count = 0
        self.link = False
        self.armed = False
        self.mode = "UNKNOWN"
        self.system_status = 0
        self.landed = "undefined"
        self.p: tuple[float, float, float] | None = None
        self.v: tuple[float, float, float] | None = None
        self.p_time = -math.inf
        self.q: tuple[float, float, float, float] | None = None
        self.bat: float | None = None
        self.volt: float | None = None
        self.battery_flag = ""
        self.boot_ms = -1
        self._boot_seen = -math.inf  # when the last time_boot_ms arrived
        self._reboot_expected_until = -math.inf  # a reboot we asked for and the autopilot accepted
        self.reboots = 0
        self.est_flags: int | None = None  # ESTIMATOR_STATUS.flags, None before the first
        self.est_time = -math.inf
        self.on_mode_change: list[Callable[[str, str], None]] = []
        self.on_reboot: list[Callable[[], None]] = []
        self.on_link_change: list[Callable[[bool], None]] = []
        self._text_parts: dict[int, tuple[float, int, list[str]]] = {}
        self._text_lock = threading.Lock()  # the reader adds chunks, the supervisor flushes late ones

    # -- input from the reader thread -----------------------------------------------------------------
    def on_heartbeat(self, msg: Any, now: float) -> None:
        if msg.autopilot == px4.MAV_AUTOPILOT_INVALID:
            return  # a ground station or companion using the vehicle's system id, not the autopilot
        armed = bool(msg.base_mode & px4.MAV_MODE_FLAG_SAFETY_ARMED)
        if msg.base_mode & px4.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            mode = px4.mode_name(*px4.decode_custom_mode(msg.custom_mode))
        else:
            mode = "UNKNOWN"
        status = int(msg.system_status)
        with self.cond:
            old_mode, old_armed, old_status, had_link = self.mode, self.armed, self.system_status, self.link
            self.hb_time = now
            self.hb_count += 1
            self.link = True
            self.armed, self.mode, self.system_status = armed, mode, status
            self.cond.notify_all()
        if not had_link:
            self.events.emit("link", f"heartbeat from system {self.system_id}: link up ({mode})", 5)
            for cb in self.on_link_change:
                cb(True)
        # Arming state first: after a disarm PX4 may report another mode, and that comes after.
        if armed != old_armed:
            self.events.emit("armed", "armed" if armed else "disarmed", 5, armed=armed)
        if mode != old_mode:
            self.events.emit("mode", f"mode {old_mode} → {mode}", 5, old=old_mode, mode=mode)
            for cb2 in self.on_mode_change:
                cb2(old_mode, mode)
        flag, old_flag = _STATUS_FLAGS.get(status), _STATUS_FLAGS.get(old_status)
        if flag != old_flag:
            if flag:
                self.events.emit(
                    "failsafe", f"autopilot reports {flag} (MAV_STATE {status})", 2, state=status
                )
            elif old_flag:
                self.events.emit("failsafe", f"autopilot {old_flag} cleared", 5, state=status)

    def on_ext_sys_state(self, msg: Any, now: float) -> None:
        ls = int(msg.landed_state)
        self.landed = _LANDED[ls] if 0 <= ls < len(_LANDED) else "undefined"

    def on_local_position(self, msg: Any, now: float) -> None:
        with self.cond:
            self.p = (float(msg.x), float(msg.y), float(msg.z))
            self.v = (float(msg.vx), float(msg.vy), float(msg.vz))
            self.p_time = now
            self.cond.notify_all()
        self._boot_time(int(msg.time_boot_ms), now)

    def on_attitude(self, msg: Any, now: float) -> None:
        q = (float(msg.q1), float(msg.q2), float(msg.q3), float(msg.q4))
        n = math.sqrt(sum(c * c for c in q))
        if n > 0.5 and math.isfinite(n):
            self.q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
        self._boot_time(int(msg.time_boot_ms), now)

    def on_estimator_status(self, msg: Any, now: float) -> None:
        self.est_flags, self.est_time = int(msg.flags), now

    def expect_reboot(self, until: float) -> None:
        """The autopilot accepted a reboot: its next silence (until the monotonic ``until``) is that reboot."""
        self._reboot_expected_until = until

    def _boot_time(self, boot_ms: int, now: float) -> None:
        # Message types are sampled at different times, so a clock a few ms back is not a reboot; a clock
        # back by more than a second is, and so is one back at all after the autopilot fell silent, or one
        # back by more than the sampling spread to under a second (a reboot soon after the last one: its
        # clock has not gone far; a busy host may read the silence's two ends back to back).  After a
        # reboot we asked for, a silence alone is enough: an autopilot that rebooted seconds after its last
        # boot may stream again only once its new clock has passed where the old one stopped.
        back = self.boot_ms - boot_ms
        silent = now - self._boot_seen > 0.3
        self._boot_seen = now
        expected = now <= self._reboot_expected_until
        restarted = (
            back > 1000 or (back > 0 and silent) or (back > 50 and boot_ms < 1000) or (expected and silent)
        )
        if self.boot_ms >= 0 and restarted:
            self._reboot_expected_until = -math.inf
            self.reboots += 1
            self.events.emit("info", "the autopilot rebooted (its clock went back)", 5, boot_ms=boot_ms)
            for cb in self.on_reboot:
                cb()
        self.boot_ms = boot_ms

    def on_sys_status(self, msg: Any, now: float) -> None:
        if msg.voltage_battery not in (0xFFFF, 0):
            self.volt = msg.voltage_battery / 1000.0
        if 0 <= msg.battery_remaining <= 100:
            self.bat = msg.battery_remaining / 100.0

    def on_battery(self, msg: Any, now: float) -> None:
        if 0 <= msg.battery_remaining <= 100:
            self.bat = msg.battery_remaining / 100.0
        flag = _BATTERY_FLAGS.get(
            int(getattr(msg, "charge_state", px4.MAV_BATTERY_CHARGE_STATE_UNDEFINED)), ""
        )
        if flag != self.battery_flag:
            self.battery_flag = flag
            if flag:
                self.events.emit(
                    "failsafe", f"battery: {flag.replace('_', ' ')}", 4 if flag == "battery_low" else 2
                )

    def on_statustext(self, msg: Any, now: float) -> None:
        text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("ascii", "replace")
        text = text.split("\0", 1)[0]
        chunk_id = int(getattr(msg, "id", 0))
        sev = int(msg.severity)
        # Long texts arrive in chunks of 50 characters, the last one shorter: with the same id, or (PX4
        # v1.16) with id 0, one after the other at the same severity.
        self.flush_texts(now)
        key = chunk_id if chunk_id else -1 - sev
        with self._text_lock:
            if key not in self._text_parts and len(text) < 50:
                parts = [text]
            else:
                _, _, parts = self._text_parts.setdefault(key, (now, sev, []))
                parts.append(text)
                if len(text) >= 50:
                    return
                del self._text_parts[key]
        self._emit_text(sev, parts)

    def flush_texts(self, now: float, after: float = 1.0) -> None:
        """Emit the texts whose last chunk has not come within ``after`` s."""
        with self._text_lock:
            late = [
                self._text_parts.pop(k)
                for k, (t0, _, _) in list(self._text_parts.items())
                if now - t0 > after
            ]
        for _, sev, parts in late:
            self._emit_text(sev, parts)

    def _emit_text(self, sev: int, parts: list[str]) -> None:
        text = "".join(parts).strip()  # PX4 ends texts it also sent as events with a tab
        kind = "failsafe" if "failsafe" in text.lower() else "statustext"
        self.events.emit(kind, text, sev)

    # -- queries ---------------------------------------------------------------------------------------
    def hb_age(self, now: float) -> float | None:
        return None if self.hb_time is None else now - self.hb_time

    def supervise(self, now: float) -> None:
        """Declare the link lost after ``link_timeout`` s without a heartbeat (the supervisor calls it)."""
        self.flush_texts(now)
        age = self.hb_age(now)
        if self.link and age is not None and age > self.link_timeout:
            with self.cond:
                self.link = False
                self.cond.notify_all()
            self.events.emit("link", f"no heartbeat for {age:.1f} s: link lost", 2, age=age)
            for cb in self.on_link_change:
                cb(False)

    def position(self, now: float, max_age: float = 0.5) -> tuple[float, float, float] | None:
        """The autopilot's position estimate if it is fresh (valid or not: see :meth:`estimate_problem`)."""
        return self.p if now - self.p_time <= max_age else None

    def estimate_problem(self, now: float, max_age: float = 3.0) -> str | None:
        """Why the autopilot itself says its position estimate is not valid (ESTIMATOR_STATUS), or None.

        None also when no ESTIMATOR_STATUS arrived within ``max_age`` s: the autopilot said nothing.
        """
        flags = self.est_flags
        if flags is None or now - self.est_time > max_age:
            return None
        missing = [name for bit, name in _EST_REQUIRED if not flags & bit]
        if not flags & (px4.ESTIMATOR_POS_VERT_ABS | px4.ESTIMATOR_POS_VERT_AGL):
            missing.append("vertical position")
        return "estimator: no " + ", ".join(missing) if missing else None

    def yaw(self) -> float | None:
        return quat_yaw(self.q) if self.q is not None else None

    def flight_problem(self) -> str | None:
        """Why the vehicle cannot be flown by setpoints or OFFBOARD now (disarmed, on the ground,
        landing), or None: ``takeoff`` is the way up."""
        if not self.armed:
            return "disarmed"
        if self.landed in ("on_ground", "undefined"):
            return "on the ground"
        if self.landed == "landing" or self.mode == "AUTO.LAND":
            return "landing"
        return None

    def wait(self, predicate: Callable[[], bool], deadline: float) -> bool:
        """Wait until ``predicate()`` (checked on every heartbeat or position) or the monotonic deadline."""
        with self.cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.cond.wait(min(left, 0.1))
            return True

    def flags(self, now: float) -> list[str]:
        """Failsafe and warning flags for :class:`~arena_common.core.wire.State`."""
        out = []
        if not self.link:
            out.append("link_lost")
        flag = _STATUS_FLAGS.get(self.system_status)
        if flag:
            out.append(flag)
        if self.battery_flag:
            out.append(self.battery_flag)
        return out


class StateReport:
    """Builds the vehicle's :class:`~arena_common.core.wire.State` from what the gateway's parts know.

    The state carries no position the autopilot marks invalid (ESTIMATOR_STATUS), nor one dead-reckoned
    without vision (``fs``: ``position_invalid``, ``dead_reckoning``); an ``estimator`` event says when the
    position stops or starts being valid.
    """

    def __init__(
        self,
        state: VehicleState,
        vision: VisionSender,
        forwarder: SetpointForwarder,
        setup: SetupChecker,
        timesync: TimeSync,
        clock: ClockWatch,
        *,
        fused_tolerance: float,
    ) -> None:
        self.state = state
        self.vision = vision
        self.forwarder = forwarder
        self.setup = setup
        self.timesync = timesync
        self.clock = clock
        self.fused_tolerance = fused_tolerance  # m between the EKF position and the vision pose: fused
        self._position_problem: str | None = None
        self._vision_stale = False

    def build(self, now: float) -> wire.State:
        """The state at the monotonic ``now`` (and the ``estimator`` event when the position's validity
        changed since the last call)."""
        s, vis = self.state, self.vision
        t = wire.now_ns()
        p = s.position(now, max_age=1.0)
        vis_age = vis.age(now)
        mp = vis.last_p if vis.sent else None
        fused = (
            p is not None
            and mp is not None
            and vis_age is not None
            and vis_age < 0.3
            and now - s.p_time < 0.3
            and math.dist(p, mp) <= self.fused_tolerance
        )
        flags = s.flags(now)
        problem = s.estimate_problem(now)
        if vis_age is None or vis_age > px4.EV_TIMEOUT_S:
            flags.append("vision_stale")
            if p is not None and problem is None:
                problem = "no vision reaching the autopilot: its position is dead-reckoned"
                flags.append("dead_reckoning")
        stale = vis_age is not None and vis_age > px4.EV_TIMEOUT_S  # once a pose was sent, then none
        if stale != self._vision_stale:  # once per loss: what became of the poses since the last one sent
            self._vision_stale = stale
            if stale:
                s.events.emit("estimator", f"vision stale: {vis.why(now, px4.EV_TIMEOUT_S)}", 4)
            else:
                s.events.emit("estimator", "vision reaching the autopilot again", 6)
        if problem is not None and "dead_reckoning" not in flags:
            flags.append("position_invalid")
        if problem != self._position_problem:
            self._position_problem = problem
            if problem is not None:
                s.events.emit("estimator", f"position not valid: {problem}", 3, reason=problem)
            else:
                s.events.emit("estimator", "position valid again", 6)
        if self.forwarder.latched is not None and s.mode != "OFFBOARD":
            flags.append("offboard_latched")
        flags += self.clock.flags()
        valid = p is not None and problem is None
        bat = s.bat
        return wire.State(
            t=t,
            sysid=s.system_id,
            link=s.link,
            armed=s.armed,
            mode=s.mode,
            landed=s.landed,
            p=p if p is not None and valid and all(math.isfinite(c) for c in p) else None,
            v=s.v if valid and s.v is not None and all(math.isfinite(c) for c in s.v) else None,
            q=s.q,
            mp=mp,
            bat=None if bat is None else min(1.0, max(0.0, bat)),
            volt=s.volt,
            rtt=self.timesync.rtt_s,
            rtt_jit=self.timesync.jitter_s,
            stamps=self.timesync.stamps,
            hb_age=s.hb_age(now),
            vis_rate=vis.rate(now),
            vis_age=vis_age,
            vis_fused=fused,
            ofb=self.forwarder.streaming(now),
            setup_ok=bool(self.setup.ok) and not self.setup.reboot_pending,
            fs=tuple(flags),
            tp=t,
            auth=self.forwarder.holder,
        )
