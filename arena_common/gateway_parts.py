"""Parts of the MAVLink gateway: events, vehicle state, time sync, vision and telemetry.

Each class does one job and is driven by the gateway's threads (see :mod:`arena_common.gateway`):
the link reader feeds the ``on_*`` methods with decoded messages, other threads call the rest.  All of
them are thread-safe where they are shared.  Times: ``now`` arguments are :func:`time.monotonic`
seconds; wire times are wall-clock ns (:func:`arena_common.wire.now_ns`), the clock the gateway also
answers TIMESYNC with, so that vision ``time_usec`` stamps and PX4's time sync agree.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from arena_common import keys, px4, wire
from arena_common.bus import Bus, Channel, Publisher
from arena_common.errors import ArenaError
from arena_common.mavlink_link import MavlinkLink
from arena_common.service import Stats

__all__ = [
    "EventSink",
    "GatewayError",
    "GlobalOrigin",
    "TelemetryPublisher",
    "TimeSync",
    "VehicleState",
    "VisionSender",
    "parse_origin",
    "yaw_of",
]

MAV_AUTOPILOT_INVALID = 8
_MSG_GPS_GLOBAL_ORIGIN = 49


class GatewayError(ArenaError, ValueError):
    """A gateway part configured with a value it cannot use."""


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
_BATTERY_FLAGS = {2: "battery_low", 3: "battery_critical", 4: "battery_emergency", 5: "battery_failed"}


def yaw_of(q: Sequence[float]) -> float:
    """Yaw (rad, about Down) of a (w, x, y, z) FRD→NED quaternion."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _euler(q: Sequence[float]) -> tuple[float, float, float]:
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    return roll, pitch, yaw_of(q)


# --------------------------------------------------------------------------------------------- events
class EventSink:
    """Events of one vehicle: logged at once, published in order by :meth:`run` (its own thread).

    Publishing is reliable (it may block when the bus is congested), so nothing time-critical ever
    waits on it; the last 500 events stay in :attr:`recent`.
    """

    def __init__(self, publish: Callable[[wire.Event], None] | None, log: logging.Logger) -> None:
        self._publish = publish
        self._log = log
        self._channel: Channel[wire.Event] = Channel(4096, ring=False)
        self.recent: collections.deque[wire.Event] = collections.deque(maxlen=500)
        self._limits: dict[str, float] = {}

    def emit(
        self, kind: str, text: str, sev: int = 6, *, every: float = 0.0, **data: Any
    ) -> wire.Event | None:
        """Record one event; with ``every`` > 0, at most one per ``every`` s for the same kind and text."""
        if every > 0:
            now = time.monotonic()
            key = f"{kind}:{text}"
            if now < self._limits.get(key, -math.inf):
                return None
            self._limits[key] = now + every
        event = wire.Event(t=wire.now_ns(), kind=kind, text=text[:4096], sev=max(0, min(7, sev)), data=data)
        level = logging.ERROR if sev <= 3 else logging.WARNING if sev == 4 else logging.INFO
        self._log.log(level, "%s: %s", kind, text)
        self.recent.append(event)
        self._channel.put(event)
        return event

    def run(self, stop: threading.Event) -> None:
        """Publish queued events until ``stop`` (then flush what is left)."""
        while not stop.is_set() or len(self._channel):
            event = self._channel.get(0.2)
            if event is not None and self._publish is not None:
                try:
                    self._publish(event)
                except Exception as exc:  # the bus is closing; events are also in the log
                    self._log.debug("event not published: %s", exc)

    def close(self) -> None:
        self._channel.close()


# ---------------------------------------------------------------------------------------- vehicle
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
        if msg.autopilot == MAV_AUTOPILOT_INVALID:
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
        self._boot_time(int(msg.time_boot_ms))

    def on_attitude(self, msg: Any, now: float) -> None:
        q = (float(msg.q1), float(msg.q2), float(msg.q3), float(msg.q4))
        n = math.sqrt(sum(c * c for c in q))
        if n > 0.5 and math.isfinite(n):
            self.q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
        self._boot_time(int(msg.time_boot_ms))

    def on_estimator_status(self, msg: Any, now: float) -> None:
        self.est_flags, self.est_time = int(msg.flags), now

    def _boot_time(self, boot_ms: int) -> None:
        if self.boot_ms >= 0 and boot_ms + 1000 < self.boot_ms:
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
        flag = _BATTERY_FLAGS.get(int(getattr(msg, "charge_state", 0)), "")
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
        return yaw_of(self.q) if self.q is not None else None

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
        """Failsafe and warning flags for :class:`~arena_common.wire.State`."""
        out = []
        if not self.link:
            out.append("link_lost")
        flag = _STATUS_FLAGS.get(self.system_status)
        if flag:
            out.append(flag)
        if self.battery_flag:
            out.append(self.battery_flag)
        return out


# -------------------------------------------------------------------------------------------- time
class TimeSync:
    """Answers the autopilot's TIMESYNC requests at once, and measures round trip and offset with our own.

    Our clock is ``clock_ns`` (wall-clock ns by default): the same clock stamps vision ``time_usec``.
    The offset is the autopilot's clock minus ours, from the fastest of the last 16 round trips.
    """

    def __init__(self, link: MavlinkLink, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.link = link
        self.clock_ns = clock_ns
        self._pending: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._samples: collections.deque[tuple[int, int]] = collections.deque(maxlen=16)
        self.answered = 0
        self.rtt_s: float | None = None
        self.offset_s: float | None = None
        self.rtt_min_s: float | None = None

    def on_timesync(self, msg: Any, now: float) -> None:
        if msg.tc1 == 0:
            self.link.send(self.link.mav.timesync_encode(self.clock_ns(), msg.ts1))
            self.answered += 1
            return
        if msg.ts1 not in self._pending:
            return  # an answer to someone else (a GCS through the forwarder)
        del self._pending[msg.ts1]
        t_now = self.clock_ns()
        rtt = t_now - msg.ts1
        if rtt < 0:
            return
        self._samples.append((rtt, msg.tc1 - (msg.ts1 + t_now) // 2))
        best = min(self._samples)
        self.rtt_s = rtt * 1e-9
        self.rtt_min_s = best[0] * 1e-9
        self.offset_s = best[1] * 1e-9

    def request(self) -> None:
        """Send one TIMESYNC request (tc1 = 0, ts1 = our clock)."""
        ts = self.clock_ns()
        self._pending[ts] = None
        while len(self._pending) > 8:
            self._pending.popitem(last=False)
        self.link.send(self.link.mav.timesync_encode(0, ts))

    def reset(self) -> None:
        """Forget the measurements (the autopilot rebooted: its clock restarted)."""
        self._samples.clear()
        self.offset_s = None


# ------------------------------------------------------------------------------------------ origin
def parse_origin(text: str) -> tuple[float, float, float] | None:
    """``"LAT,LON,ALT"`` (degrees, degrees, metres above mean sea level) or ``"off"`` (None)."""
    if text.strip().lower() in ("off", "none", "no"):
        return None
    parts = text.split(",")
    try:
        lat, lon, alt = (float(p) for p in parts)
    except ValueError:
        raise GatewayError(
            f"origin must be LAT,LON,ALT (degrees, degrees, metres) or off, got {text!r}"
        ) from None
    return check_origin((lat, lon, alt))


def check_origin(origin: Sequence[float]) -> tuple[float, float, float]:
    """A valid (lat, lon, alt) or :class:`GatewayError` naming the bad value."""
    if len(origin) != 3:
        raise GatewayError(f"origin must be (lat, lon, alt), got {tuple(origin)!r}")
    lat, lon, alt = (float(c) for c in origin)
    if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise GatewayError(f"origin latitude must be within -90..90 degrees, got {lat}")
    if not (math.isfinite(lon) and -180.0 <= lon <= 180.0):
        raise GatewayError(f"origin longitude must be within -180..180 degrees, got {lon}")
    if not (math.isfinite(alt) and -1000.0 <= alt <= 10000.0):
        raise GatewayError(f"origin altitude must be within -1000..10000 m, got {alt}")
    return (lat, lon, alt)


class GlobalOrigin:
    """Gives an autopilot that has no EKF origin one with SET_GPS_GLOBAL_ORIGIN, as mavros's set_gp_origin.

    Without GPS, PX4 has no global reference, and its AUTO modes (takeoff, land, hold) need one.  An EKF
    that already has an origin (GNSS, or set before) must keep it: a new one re-bases its local frame.
    So :meth:`request` (link up, autopilot rebooted) first asks for GPS_GLOBAL_ORIGIN (REQUEST_MESSAGE;
    PX4 sends it only when its origin is valid) for ``ask_s`` s; only when none comes does it send ours
    to the vehicle's system id (never 0), every ``period`` s, until the autopilot reports it back, at
    most ``attempts`` times.
    """

    def __init__(
        self,
        link: MavlinkLink,
        target_system: int,
        origin: Sequence[float],
        events: EventSink,
        *,
        period: float = 1.0,
        attempts: int = 5,
        ask_s: float = 1.0,
    ) -> None:
        if not 1 <= int(target_system) <= 250:
            raise GatewayError(f"the origin's target system must be within 1..250, got {target_system}")
        self.link = link
        self.target = int(target_system)
        self.origin = check_origin(origin)
        lat, lon, alt = self.origin
        self._wire = (round(lat * 1e7), round(lon * 1e7), round(alt * 1000.0))
        self.events = events
        self.period = period
        self.attempts = attempts
        self.ask_s = ask_s
        self.sent = 0
        self.confirmed = False
        self.kept = False  # the autopilot had an origin of its own: left alone
        self.reported: tuple[float, float, float] | None = None
        self._asking_until = -math.inf
        self._left = 0
        self._next = math.inf
        self._settled = threading.Event()  # kept, confirmed, or given up: arming need not wait for it

    def wait_settled(self, deadline: float) -> bool:
        """Wait (until the monotonic ``deadline``) for the origin to be kept, confirmed or given up."""
        return self._settled.wait(max(0.0, deadline - time.monotonic()))

    def request(self, now: float) -> None:
        """Ask whether the autopilot has an origin; give it ours if it has none."""
        self._settled.clear()
        self.confirmed = self.kept = False
        self.reported = None
        self._asking_until = now + self.ask_s
        self._left = self.attempts
        self._next = now
        self.supervise(now)

    def supervise(self, now: float) -> None:
        """Ask or resend when due (the supervisor calls it)."""
        if self.confirmed or self.kept or now < self._next:
            return
        self._next = now + self.period / 2
        if now < self._asking_until:
            self.link.send(
                self.link.mav.command_long_encode(
                    self.target, 1, px4.MAV_CMD_REQUEST_MESSAGE, 0, _MSG_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0
                )
            )
            return
        if self._left <= 0:
            self._next = math.inf
            self._settled.set()
            lat, lon, alt = self.origin
            self.events.emit(
                "setup",
                f"the autopilot did not confirm the EKF origin {lat:.7f}, {lon:.7f}, {alt:.2f} m "
                f"after {self.attempts} SET_GPS_GLOBAL_ORIGIN",
                4,
            )
            return
        self._left -= 1
        self._next = now + self.period
        lat_e7, lon_e7, alt_mm = self._wire
        msg = self.link.mav.set_gps_global_origin_encode(
            self.target, lat_e7, lon_e7, alt_mm, wire.now_ns() // 1000
        )
        if self.link.send(msg):
            self.sent += 1

    def on_gps_global_origin(self, msg: Any, now: float) -> None:
        """The autopilot's origin (GPS_GLOBAL_ORIGIN): kept when it had one, else confirms ours."""
        self.reported = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        if self.sent == 0 and not self.kept and not self.confirmed:
            if now >= self._asking_until + self.period:
                return  # not asked for (a stream); our request decides
            self.kept = True
            self._next = math.inf
            self._settled.set()
            lat, lon, alt = self.reported
            self.events.emit(
                "setup",
                f"the autopilot has an EKF origin ({lat:.7f}, {lon:.7f}, {alt:.2f} m): left as it is",
                6,
                origin=list(self.reported),
            )
            return
        lat_e7, lon_e7, alt_mm = self._wire
        match = msg.latitude == lat_e7 and msg.longitude == lon_e7 and abs(msg.altitude - alt_mm) <= 10
        if match and not self.confirmed:
            self.confirmed = True
            self._next = math.inf
            self._settled.set()
            lat, lon, alt = self.origin
            self.events.emit(
                "setup", f"EKF origin set: {lat:.7f}, {lon:.7f}, {alt:.2f} m", 6, origin=list(self.origin)
            )


# ------------------------------------------------------------------------------------------ vision
class VisionSender:
    """Sends each fresh, valid pose once as ODOMETRY (or VISION_POSITION_ESTIMATE); never resends.

    A pose is dropped when it is not tracked (``ok`` false), older than ``max_pose_age`` s by its own
    ``t`` (checked again just before the frame is written), stamped more than ``max_pose_age`` s in the
    future, not newer than the last one sent, or out of range (a coordinate beyond ±``max_position`` m, a
    speed beyond ``max_speed`` m/s or rad/s, anything not finite).  The reset counter is bumped when the
    pose's ``rc`` changes, when the position jumps (more than ``jump_m`` and faster than ``jump_speed``),
    or on :meth:`bump_reset` (a calibration change).
    """

    def __init__(
        self,
        link: MavlinkLink,
        *,
        max_pose_age: float = 0.1,
        message: str = "odometry",
        send_velocity: bool = True,
        jump_m: float = 0.5,
        jump_speed: float = 5.0,
        max_position: float = 1e4,
        max_speed: float = 1e3,
        stats: Stats | None = None,
    ) -> None:
        if message not in ("odometry", "vision_position_estimate"):
            raise GatewayError(
                f"vision message must be odometry or vision_position_estimate, not {message!r}"
            )
        self.link = link
        self.max_age_ns = int(max_pose_age * 1e9)
        self.message = message
        self.send_velocity = send_velocity
        self.jump_m = jump_m
        self.jump_speed = jump_speed
        self.max_position = max_position
        self.max_speed = max_speed
        self.stats = stats or Stats()
        self.reset_counter = 0
        self.sent = 0
        self.last_t = -1
        self.last_p: tuple[float, float, float] | None = None
        self.last_sent_mono = -math.inf
        self._last_rc: int | None = None
        self._times: collections.deque[float] = collections.deque(maxlen=1024)

    def bump_reset(self) -> None:
        """Tell the autopilot the next pose jumps (new calibration, re-acquired body)."""
        self.reset_counter = (self.reset_counter + 1) & 0xFF

    def offer(self, pose: wire.Pose, now_ns: int | None = None) -> str | None:
        """Send ``pose`` if it may be sent; the reason it was not, else None."""
        if not pose.ok:
            return "not tracked"
        clock_given = now_ns is not None
        now_ns = wire.now_ns() if now_ns is None else now_ns
        if now_ns - pose.t > self.max_age_ns:
            return "stale"
        if pose.t - now_ns > self.max_age_ns:
            return "from the future"  # once sent, every later pose would be refused as not newer
        if pose.t <= self.last_t:
            return "not newer than the last pose sent"
        with_velocity = pose.vok and self.send_velocity
        if not self._in_range(pose, with_velocity):
            return "out of range"
        p = pose.p
        if self._last_rc is not None and pose.rc != self._last_rc:
            self.bump_reset()
        elif self.last_p is not None:
            dt = (pose.t - self.last_t) * 1e-9
            dist = math.dist(p, self.last_p)
            if dist > self.jump_m and dist > self.jump_speed * dt:
                self.bump_reset()
        self._last_rc = pose.rc
        packs = self.link.pack_errors
        usec = pose.t // 1000
        mav = self.link.mav
        if self.message == "odometry":
            args = px4.odometry_args(
                usec,
                p,
                pose.q,
                pose.v if with_velocity else None,
                reset_counter=self.reset_counter,
                angular_velocity_frd=pose.w if with_velocity else None,
            )
            msg = mav.odometry_encode(**args)
        else:
            roll, pitch, yaw = _euler(pose.q)
            cov = [math.nan] + [0.0] * 20
            msg = mav.vision_position_estimate_encode(
                usec, p[0], p[1], p[2], roll, pitch, yaw, cov, self.reset_counter
            )
        deadline_ns = pose.t + self.max_age_ns

        def fresh() -> bool:
            # The thread may have been stopped (a frozen process, a long pause) since the age check.
            return clock_given or wire.now_ns() <= deadline_ns

        if not self.link.send(msg, fresh=fresh):
            if not fresh():
                return "stale"
            return "cannot be packed" if self.link.pack_errors > packs else "link down"
        self.last_t = pose.t
        self.last_p = p
        self.sent += 1
        mono = time.monotonic()
        self.last_sent_mono = mono
        self._times.append(mono)
        self.stats.count("vision")
        self.stats.count("out")
        return None

    def _in_range(self, pose: wire.Pose, with_velocity: bool) -> bool:
        lim, vlim = self.max_position, self.max_speed
        if not all(math.isfinite(c) and abs(c) <= lim for c in pose.p):
            return False
        if not all(math.isfinite(c) and abs(c) <= 2.0 for c in pose.q):
            return False
        if with_velocity:
            return all(math.isfinite(c) and abs(c) <= vlim for c in (*pose.v, *pose.w))
        return True

    def rate(self, now: float) -> float:
        """Poses sent over the last second."""
        times = self._times
        while times and now - times[0] > 1.0:
            times.popleft()
        return float(len(times))

    def age(self, now: float) -> float | None:
        """Seconds since the last pose was sent (None before the first)."""
        return None if self.sent == 0 else now - self.last_sent_mono


# --------------------------------------------------------------------------------------- telemetry
def _plain(value: Any) -> Any:
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


class TelemetryPublisher:
    """Publishes raw messages on ``arena/<drone>/telemetry/<MSG>``, at most ``rate`` Hz per message type.

    :meth:`due` is asked before decoding, so a message type that is not due costs nothing.
    """

    def __init__(self, bus: Bus | None, drone: str, rate: float = 10.0, exclude: Iterable[int] = ()) -> None:
        self.bus = bus
        self.drone = drone
        self.period = 1.0 / rate if rate > 0 else math.inf
        self.exclude = frozenset(exclude)
        self._next: dict[int, float] = {}
        self._pubs: dict[str, Publisher[wire.Telemetry]] = {}
        self.published = 0

    def due(self, msgid: int, now: float) -> bool:
        return self.bus is not None and now >= self._next.get(msgid, 0.0) and msgid not in self.exclude

    def publish(self, msg: Any, now: float, t_ns: int) -> None:
        """Publish one decoded message (the caller checked :meth:`due`)."""
        self._next[msg.get_msgId()] = now + self.period
        self.put(
            msg.get_type(), {k: _plain(v) for k, v in msg.to_dict().items() if k != "mavpackettype"}, t_ns
        )

    def put(self, name: str, fields: Mapping[str, Any], t_ns: int) -> None:
        """Publish fields under a message name (also used for the gateway's own measurements)."""
        if self.bus is None:
            return
        pub = self._pubs.get(name)
        if pub is None:
            pub = self._pubs[name] = self.bus.stream_publisher(
                keys.telemetry(self.drone, name), wire.Telemetry
            )
        pub.put(wire.Telemetry(t=t_ns, msg=name, f=dict(fields)))
        self.published += 1
