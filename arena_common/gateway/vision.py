"""**Where a pose is sent**: each fresh, valid pose once as ODOMETRY (or VISION_POSITION_ESTIMATE)."""

from __future__ import annotations

import collections
import math
import statistics
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

    Every pose offered is counted, and every one refused since the last one sent is counted by reason (the
    ages of those refused as too old, the lead of those from the future kept), so that :meth:`problem` can
    say why no pose reached the autopilot: none arrived (for how long), or they arrived and were refused.

    A pose's ``t`` is on the mocap host's clock.  ``offset_ns`` (when given) returns that clock minus
    ours (:class:`~arena_common.runtime.clock.ClockSync`, None while unknown): ages are judged, and
    ODOMETRY's ``time_usec`` stamped, on our clock whatever our wall clock says; their error is the
    offset's uncertainty.  Without it (or while unknown) both clocks are taken to agree.  ``stamp_us``
    (when given: :meth:`~arena_common.gateway.timesync.TimeSync.autopilot_us`) puts that time on the
    autopilot's clock, the one our TIMESYNC answers give it; while it returns None, ``time_usec`` is on
    ours (the autopilot has had no answer then, and stamps on arrival).
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
        stamp_us: Callable[[int], int | None] | None = None,
        source: str = "the vision key",
        published_on_mocap_clock: bool = False,
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
        self.stamp_us = stamp_us
        self.last_usec = -1
        self._on_autopilot_clock = False
        self.reset_counter = 0
        self.sent = 0
        self.last_t = -1
        self.last_p: tuple[float, float, float] | None = None
        self.last_sent_mono = -math.inf
        self._last_rc: int | None = None
        self._times: collections.deque[float] = collections.deque(maxlen=1024)
        self._ages: collections.deque[int] = collections.deque(maxlen=256)  # ns, of the last poses sent
        self.source = source  # where the poses come from, named when none arrives
        # Whose clock stamps a pose's publication (tp): the downsampler's, beside this gateway (ours), or the
        # frame transform's on the mocap host when it decimates (pipeline.decimate = "transform").
        self.published_on_mocap_clock = published_on_mocap_clock
        self.arrived = 0  # poses offered (and samples refused as no pose), ever
        self.last_arrival_mono = -math.inf
        # Since the last pose sent (what explains a stale vision): refusals by reason, the least and the
        # most age of the poses refused as too old, the most lead of those from the future (ns).
        self._refused: dict[str, int] = {}
        self._late_ns = (0, 0)
        # Of the oldest pose refused as too old: ns from its measurement to its publication on the vision
        # key, and from there to its arrival here (the bus and this gateway); None if unstamped.
        self._late_split: tuple[int, int] | None = None
        self._ahead_ns = 0

    def bump_reset(self) -> None:
        """Tell the autopilot the next pose jumps (new calibration, re-acquired body)."""
        self.reset_counter = (self.reset_counter + 1) & 0xFF

    def offer(self, pose: wire.Pose, now_ns: int | None = None) -> str | None:
        """Send ``pose`` if it may be sent; the reason it was not, else None."""
        self.arrived += 1
        # One clock read for both: a pose sent is sent as it arrives, so "last pose sent" is never nearer
        # than "last pose arrived" (a stale refusal names both).
        self.last_arrival_mono = mono = time.monotonic()
        reason = self._send(pose, now_ns, mono)
        if reason is not None:
            self._note(reason, pose, now_ns)
        return reason

    def refused(self, reason: str) -> None:
        """Count a sample that arrived on the vision key and was refused before it became a pose."""
        self.arrived += 1
        self.last_arrival_mono = time.monotonic()
        self._refused[reason] = self._refused.get(reason, 0) + 1

    def _note(self, reason: str, pose: wire.Pose, now_ns: int | None) -> None:
        self._refused[reason] = self._refused.get(reason, 0) + 1
        if reason in ("stale", "from the future"):
            now = wire.now_ns() if now_ns is None else now_ns
            t_local = pose.t - self.correction()
            age = now - t_local
            if reason == "from the future":
                self._ahead_ns = max(self._ahead_ns, -age)
                return
            first = self._refused[reason] == 1
            if first or age > self._late_ns[1]:
                self._late_split = None
                if pose.tp:  # 0: a publisher that does not stamp
                    tp = pose.tp - self.correction() if self.published_on_mocap_clock else pose.tp
                    self._late_split = (tp - t_local, now - tp)
            if first:
                self._late_ns = (age, age)
            else:
                self._late_ns = (min(self._late_ns[0], age), max(self._late_ns[1], age))

    def _send(self, pose: wire.Pose, now_ns: int | None, mono: float) -> str | None:
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
        stamped = self.stamp_us(t_local) if self.stamp_us is not None else None
        if (stamped is not None) != self._on_autopilot_clock:  # another clock: no order with the last stamp
            self._on_autopilot_clock = stamped is not None
            self.last_usec = -1
        # A new offset estimate may move a stamp back by its correction: keep time_usec increasing.
        usec = max(t_local // 1000 if stamped is None else stamped, self.last_usec + 1)
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
        if self._refused:
            self._refused, self._ahead_ns = {}, 0
        self.last_sent_mono = mono
        self._times.append(mono)
        self._ages.append(now_ns - t_local)  # the pose's age when it was judged fresh and sent
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

    def sent_age_median(self) -> float | None:
        """The median age (s, from the mocap's exposure to the frame leaving) of the last 256 poses sent;
        None before any."""
        return statistics.median(self._ages) * 1e-9 if self._ages else None

    def age(self, now: float) -> float | None:
        """Seconds since the last pose was sent (None before the first)."""
        return None if self.sent == 0 else now - self.last_sent_mono

    def problem(self, now: float, limit: float) -> str | None:
        """Why no pose has reached the autopilot for more than ``limit`` s (at monotonic time ``now``), naming
        its cause; None while one has."""
        age = self.age(now)
        if age is not None and age <= limit:
            return None
        head = (
            "no vision pose sent to the autopilot yet"
            if age is None
            else f"vision stale: last pose sent {age:.2f} s ago"
        )
        return f"{head}: {self.why(now, limit)}"

    def why(self, now: float, limit: float) -> str:
        """What became of the poses since the last one sent: none arrived (for how long), or each arrived
        and was refused, by reason with its figures."""
        refused = dict(self._refused)  # one copy: the Zenoh thread may count meanwhile
        silent = now - self.last_arrival_mono
        if self.arrived == 0:
            return (
                f"no pose has arrived on {self.source} (the mocap not streaming, the body not tracked, or a "
                "stage before the gateway down: `arena top` shows where the poses stop)"
            )
        hint = "the mocap stopped, the body is not tracked, or a stage before the gateway stalls"
        hint += ": `arena top` shows where the poses stop"
        if not refused:
            return f"no pose has arrived on {self.source} for {silent:.2f} s ({hint})"
        n = sum(refused.values())
        texts = [self._refusal_text(r, k) for r, k in sorted(refused.items(), key=lambda rk: -rk[1])]
        since = " since" if self.sent else ""
        said = [f"{n} pose{'s' if n > 1 else ''} arrived{since}, none sent: {'; '.join(texts)}"]
        if silent > limit:
            said.append(f"the last one {silent:.2f} s ago ({hint})")
        return "; ".join(said)

    def _late_where(self) -> str:
        """Where the oldest pose refused as too old spent its time: before it was published on the vision key
        (the mocap, the transform, the downsampler) or after (the bus, this gateway)."""
        if self._late_split is None:
            return "the pipeline runs late, a busy computer?"
        stages, bus = (round(x * 1e-6) for x in self._late_split)
        late = "the stages before the bus run late" if stages > bus else "the bus or this gateway runs late"
        return (
            f"{late}: the oldest was published {stages} ms after its measurement and arrived here {bus} ms "
            "after that; a busy computer?"
        )

    def _refusal_text(self, reason: str, n: int) -> str:
        if reason == "stale":
            lo, hi = (round(x * 1e-6) for x in self._late_ns)
            ages = f"{hi} ms" if lo == hi else f"{lo}–{hi} ms"
            allowed = f"more than the {self.max_age_ns * 1e-6:.0f} ms allowed"
            return f"{n} too old ({ages} after their measurement, {allowed}: {self._late_where()})"
        if reason == "from the future":
            return f"{n} stamped up to {self._ahead_ns * 1e-6:.0f} ms ahead of this host's clock (the clocks disagree)"
        if reason == "not tracked":
            return f"{n} not tracked (the mocap lost the body)"
        if reason == "link down":
            return f"{n} not sent: the link to the autopilot is down"
        return f"{n} {reason}"
