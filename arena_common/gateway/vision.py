"""**Where a pose is sent**: each fresh, valid pose once as ODOMETRY (or VISION_POSITION_ESTIMATE)."""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable

from arena_common.core import wire
from arena_common.core.errors import GatewayError
from arena_common.geometry.frames import quat_to_euler
from arena_common.mavlink import fastframe, px4
from arena_common.mavlink.link import MavlinkLink
from arena_common.runtime.service import Stats


class VisionSender:
    """Sends each fresh, valid pose once as ODOMETRY (or VISION_POSITION_ESTIMATE); never resends.

    A pose is dropped when it is not tracked (``ok`` false), older than ``max_pose_age`` s by its own
    ``t`` (checked again just before the frame is written), stamped more than ``max_pose_age`` s in the
    future, not newer than the last one sent, or out of range (a coordinate beyond ±``max_position`` m, a
    speed beyond ``max_speed`` m/s or rad/s, anything not finite).  The reset counter is bumped when the
    pose's ``rc`` changes, when the position jumps (more than ``jump_m`` and faster than ``jump_speed``),
    or on :meth:`bump_reset` (a calibration change).

    A pose's ``t`` is on the mocap host's clock.  ``offset_ns`` (when given) returns that clock minus
    ours (:class:`~arena_common.runtime.clock.ClockSync`, None while unknown): ages are judged, and
    ODOMETRY's ``time_usec`` stamped, on our clock — the one TIMESYNC shares with the autopilot — whatever
    our wall clock says; their error is the offset's uncertainty.  Without it (or while unknown) both
    clocks are taken to agree.
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
        offset_ns: Callable[[], int | None] | None = None,
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
        self.offset_ns = offset_ns
        self.last_usec = -1
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
        t_local = pose.t - self.correction()  # the measurement time on our clock
        if now_ns - t_local > self.max_age_ns:
            return "stale"
        if t_local - now_ns > self.max_age_ns:
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
        # A new offset estimate may move t_local back by its (µs) correction: keep time_usec increasing.
        usec = max(t_local // 1000, self.last_usec + 1)
        mav = self.link.mav
        deadline_ns = t_local + self.max_age_ns

        def fresh() -> bool:
            # The thread may have been stopped (a frozen process, a long pause) since the age check.
            return clock_given or wire.now_ns() <= deadline_ns

        if self.message == "odometry":
            args = px4.odometry_args(
                usec,
                p,
                pose.q,
                pose.v if with_velocity else None,
                reset_counter=self.reset_counter,
                angular_velocity_frd=pose.w if with_velocity else None,
            )
            sent = self.link.send_packed(
                fastframe.ODOMETRY,
                lambda: fastframe.odometry_payload(args),
                lambda: mav.odometry_encode(**args),
                fresh,
            )
        else:
            roll, pitch, yaw = quat_to_euler(pose.q)
            cov = [math.nan] + [0.0] * 20
            msg = mav.vision_position_estimate_encode(
                usec, p[0], p[1], p[2], roll, pitch, yaw, cov, self.reset_counter
            )
            sent = self.link.send(msg, fresh=fresh)
        if not sent:
            if not fresh():
                return "stale"
            return "cannot be packed" if self.link.pack_errors > packs else "link down"
        self.last_t = pose.t
        self.last_usec = usec
        self.last_p = p
        self.sent += 1
        mono = time.monotonic()
        self.last_sent_mono = mono
        self._times.append(mono)
        self.stats.count("vision")
        self.stats.count("out")
        return None

    def correction(self) -> int:
        """The mocap host's clock minus ours, ns (0 while unknown or not measured)."""
        if self.offset_ns is None:
            return 0
        off = self.offset_ns()
        return 0 if off is None else off

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
