"""Offboard setpoints: the arena's safety rules, leases, the stream to PX4 and the gateway's own goto.

The rules, in the order they apply:

- A setpoint (:class:`~arena_common.core.wire.Setpoint`, arena NED) is refused — an Event of kind
  ``safety`` says why, and it never reaches the vehicle — when it does not decode (NaN, infinity…), when
  its position lies outside ``arena.safe_box()``, when its horizontal speed exceeds ``arena.max_speed``
  or its vertical speed ``arena.max_climb``, when its acceleration feed-forward exceeds ``MAX_ACCEL``,
  when its yaw lies beyond ±``MAX_YAW`` rad (a yaw within is wrapped to ±π) or its yaw rate beyond
  ``MAX_YAW_RATE``, or when it is a velocity that leads further out of the safe volume while the vehicle
  already is outside it.  An attitude setpoint (``q`` and ``thrust``) steers no position the gateway
  could check, so it is refused when it tilts more than ``MAX_TILT`` or while the vehicle's position is
  unknown or outside the safe volume; the moment the vehicle leaves the safe volume under an attitude
  stream, or its velocity would take it out within ``ATTITUDE_LOOKAHEAD`` s, the stream stops, the
  forwarder latches and PX4 is commanded to Hold (AUTO.LOITER) at once.
- An accepted setpoint is sent at once as SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED, type mask
  from the fields given: position, velocity, acceleration feed-forward, yaw or yaw rate; an attitude one
  as SET_ATTITUDE_TARGET: quaternion and thrust, body rates ignored) and repeated at
  ``rate`` Hz while its lease runs (``lease`` s from its arrival, renewed by every accepted setpoint).
  When the lease expires, streaming stops (an Event says so): the silence is what lets PX4 detect
  offboard loss and take its COM_OBL_RC_ACT action.  The gateway never streams on its own to keep a
  vehicle in offboard.
- Who holds the vehicle, and the order of hand-overs, follow :mod:`~arena_common.gateway.authority`:
  every setpoint names its stream and its number; only commands move the vehicle from one source to
  another (``mode OFFBOARD`` with a stream's identity engages that stream, ``goto`` the gateway's own
  hold, ``takeoff``/``land``/``hold``/another mode/``kill``/estop the autopilot), and a command that takes
  the vehicle ends every stream seen before it: their later setpoints are dropped and counted, never
  taking over.  A setpoint of a stream that does not hold the vehicle is held back until its engage.
- Nothing flies from the floor: a setpoint while the vehicle is disarmed, on the ground or landing is
  refused with that reason (``takeoff`` is the way up).
- Whenever the vehicle leaves OFFBOARD (a failsafe, a land, hold or mode command, a ground station, an
  estop), the forwarder *latches*: it stops sending and nobody holds the vehicle, so that neither PX4 nor
  a late stream can re-engage offboard by itself.  A program opening an offboard block streams first and
  engages a moment later (PX4 needs the stream before the switch): setpoints held back for less than
  ``HELD_BACK_GRACE`` s are that, and only a stream held back longer is warned about.
- ``goto`` is the gateway's own stream: a position carrot that moves from the vehicle toward the goal
  at ``goto_speed`` (horizontal) and ``goto_climb`` (vertical), then holds the goal indefinitely, until
  a command engages a stream, another command changes the mode, or the vehicle leaves OFFBOARD.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

from arena_common.bus.session import Subscription, typed
from arena_common.core import wire
from arena_common.core.config import ArenaSpec
from arena_common.gateway.authority import Holder, Ledger
from arena_common.gateway.events import EventSink
from arena_common.gateway.separation import Closing, Separation
from arena_common.mavlink import px4
from arena_common.mavlink.link import MavlinkLink
from arena_common.runtime.service import Stats

__all__ = [
    "ATTITUDE_LOOKAHEAD",
    "HELD_BACK_GRACE",
    "MAX_ACCEL",
    "MAX_TILT",
    "MAX_YAW",
    "MAX_YAW_RATE",
    "SetpointForwarder",
    "type_mask",
    "wrap_yaw",
    "yaw_problem",
]

Vec3 = tuple[float, float, float]

MAX_YAW = 1000.0  # rad: a larger yaw is a mistake, not a heading (it would not even fit MAVLink's float32)
MAX_YAW_RATE = 2.0 * math.pi  # rad/s
MAX_ACCEL = 5.0  # m/s², norm of an acceleration feed-forward: a trajectory's, not an aerobatic one
ATTITUDE_LOOKAHEAD = 0.75  # s: an attitude stream stops where the vehicle's velocity takes it out this soon
MAX_TILT = math.radians(35.0)  # rad, of an attitude setpoint from level: PX4's default MPC_TILTMAX_AIR
HELD_BACK_GRACE = 1.5  # s: a stream held back this long without a mode OFFBOARD command is warned about
MAX_PENDING = 16  # streams waiting for their engage, remembered with their latest setpoint


def yaw_problem(yaw: float | None, yr: float | None = None) -> str | None:
    """Why a yaw (rad) or yaw rate (rad/s) must not reach the vehicle, or None."""
    if yaw is not None and not (math.isfinite(yaw) and abs(yaw) <= MAX_YAW):
        return f"yaw {yaw!r} rad is not a finite angle within ±{MAX_YAW:g} rad"
    if yr is not None and not (math.isfinite(yr) and abs(yr) <= MAX_YAW_RATE):
        return f"yaw rate {yr!r} rad/s beyond ±{MAX_YAW_RATE:.2f} rad/s"
    return None


def wrap_yaw(yaw: float | None) -> float | None:
    """``yaw`` wrapped to [-π, π] (None stays None); check it with :func:`yaw_problem` first."""
    return None if yaw is None else math.remainder(yaw, 2.0 * math.pi)


def type_mask(sp: wire.Setpoint) -> int:
    """SET_POSITION_TARGET_LOCAL_NED type_mask for the fields a setpoint gives."""
    mask = 0
    if sp.a is None:
        mask |= px4.TYPEMASK_ACCELERATION
    if sp.p is None:
        mask |= px4.TYPEMASK_POSITION
    if sp.v is None:
        mask |= px4.TYPEMASK_VELOCITY
    if sp.yaw is None:
        mask |= px4.TYPEMASK_YAW_IGNORE
    if sp.yr is None:
        mask |= px4.TYPEMASK_YAW_RATE_IGNORE
    return mask


@dataclass(slots=True)
class _Stream:
    source: str  # "user" or "goto"
    p: Vec3 | None
    v: Vec3 | None
    yaw: float | None
    yr: float | None
    mask: int
    expires: float
    goal: Vec3 | None = None
    a: Vec3 | None = None
    q: tuple[float, float, float, float] | None = None  # an attitude stream (with thrust)
    thrust: float = 0.0
    sid: str = ""  # the user stream's identity


def outside(p: Vec3, box: tuple[tuple[float, float], tuple[float, float], tuple[float, float]]) -> str | None:
    """Which limit of the safe box ``p`` breaks, in words, or None."""
    for i, axis in enumerate(("north", "east", "down")):
        lo, hi = box[i]
        if not lo <= p[i] <= hi:
            return f"{axis} {p[i]:.2f} m outside [{lo:.2f}, {hi:.2f}]"
    return None


#: s between the forwarder thread's looks while no stream runs (a setpoint, or :meth:`start_goto`, wakes
#: it at once): an idle gateway's thread wakes twice a second instead of at the stream rate.
IDLE_WAIT = 0.5
_WAKE = object()  # put in the thread's channel by start_goto: "a stream started, tick now"


class SetpointForwarder:
    """Checks, leases and streams offboard setpoints to one vehicle (see the module's rules)."""

    def __init__(
        self,
        link: MavlinkLink,
        target_system: int,
        arena: ArenaSpec,
        events: EventSink,
        *,
        rate: float = 20.0,
        max_rate: float = 50.0,
        prestream: float = 0.5,
        goto_speed: float = 1.0,
        goto_climb: float = 0.5,
        position: Callable[[], Vec3 | None] = lambda: None,
        velocity: Callable[[], Vec3 | None] = lambda: None,
        grounded: Callable[[], str | None] = lambda: None,
        separation: Separation | None = None,
        stats: Stats | None = None,
    ) -> None:
        self.link = link
        self.target_system = target_system
        self.arena = arena
        self.box = arena.safe_box()
        self.events = events
        self.period = 1.0 / rate
        self.min_gap = 0.7 / max_rate  # tolerate jitter: a user streaming at max_rate is forwarded whole
        self.prestream = prestream
        self.goto_speed = min(goto_speed, arena.max_speed)
        self.goto_climb = min(goto_climb, arena.max_climb)
        self.position = position
        self.velocity = velocity
        self.grounded = grounded  # why setpoints cannot fly now (disarmed, on the ground, landing)
        self.separation = separation
        self.stats = stats or Stats()
        self._lock = threading.RLock()
        self._stream: _Stream | None = None  # what is sent: the holder's latest setpoint, or the goto carrot
        self._holder: Holder | None = None
        self._pending: dict[
            str, tuple[_Stream, str, float]
        ] = {}  # stream -> latest setpoint, source, arrival
        self.ledger = Ledger()
        self._latched: str | None = None
        self._since = math.inf
        self._held: tuple[float, float] | None = None  # first and latest user setpoint held back
        self._last_send = -math.inf
        self._last_tick = time.monotonic()
        self._t0 = time.monotonic()
        self.sent = 0
        self.refused = 0
        self.dropped = 0  # setpoints of ended streams, or out of order
        self.held = 0  # setpoints of streams not (yet) engaged
        self._sub: Subscription | None = None  # the thread's subscription (start_goto wakes it there)
        self._idle = False  # the thread waits IDLE_WAIT: no stream

    # -- rules ---------------------------------------------------------------------------------------
    def check(self, sp: wire.Setpoint) -> str | None:
        """Why the setpoint must not reach the vehicle, or None."""
        values = [*(sp.p or ()), *(sp.v or ()), *(sp.a or ()), *(sp.q or ()), sp.yaw or 0.0, sp.yr or 0.0]
        if not all(math.isfinite(x) for x in values) or not math.isfinite(sp.thrust or 0.0):
            return "not a finite number"
        if sp.q is not None:
            return self._attitude_problem(sp.q, sp.thrust)
        problem = yaw_problem(sp.yaw, sp.yr)
        if problem:
            return problem
        if sp.p is not None:
            where = outside(sp.p, self.box)
            if where:
                return f"position outside the safe volume: {where}"
            near = self.separation.point_problem(sp.p) if self.separation is not None else None
            if near:
                return f"position {near}"
        if sp.a is not None and math.sqrt(sum(x * x for x in sp.a)) > MAX_ACCEL + 1e-9:
            norm = math.sqrt(sum(x * x for x in sp.a))
            return f"acceleration feed-forward {norm:.2f} m/s² above {MAX_ACCEL:.1f} m/s²"
        if sp.v is not None:
            vn, ve, vd = sp.v
            speed = math.hypot(vn, ve)
            if speed > self.arena.max_speed + 1e-9:
                return f"horizontal speed {speed:.2f} m/s above max_speed {self.arena.max_speed:.2f}"
            if abs(vd) > self.arena.max_climb + 1e-9:
                return f"vertical speed {abs(vd):.2f} m/s above max_climb {self.arena.max_climb:.2f}"
            pos = self.position() if sp.p is None else None
            if pos is not None:
                for i, axis in enumerate(("north", "east", "down")):
                    lo, hi = self.box[i]
                    if (pos[i] < lo and sp.v[i] < 0) or (pos[i] > hi and sp.v[i] > 0):
                        return f"velocity leads further out of the safe volume ({axis})"
        return None

    def _attitude_problem(self, q: tuple[float, float, float, float], thrust: float | None) -> str | None:
        w, x, y, z = q
        n = math.sqrt(w * w + x * x + y * y + z * z)
        if abs(n - 1.0) > 1e-3 or thrust is None or not 0.0 <= thrust <= 1.0:
            return "an attitude setpoint needs a unit quaternion and a thrust in 0..1"
        # Tilt: the angle between the body's down axis and the world's (R[2][2] = cos tilt).
        cos_tilt = (1.0 - 2.0 * (x * x + y * y)) / (n * n)
        tilt = math.acos(max(-1.0, min(1.0, cos_tilt)))
        if tilt > MAX_TILT + 1e-9:
            return (
                f"attitude tilted {math.degrees(tilt):.1f}° from level, above {math.degrees(MAX_TILT):.0f}°"
            )
        where = self._attitude_outside()
        if where:
            return f"attitude setpoints only inside the safe volume: {where}"
        return None

    def _attitude_outside(self) -> str | None:
        """Why the vehicle is (or, at its velocity, within ``ATTITUDE_LOOKAHEAD`` s will be) out of the safe
        volume, or its position is unknown; None while an attitude stream may go on."""
        pos = self.position()
        if pos is None:
            return "the vehicle's position is unknown"
        where = outside(pos, self.box)
        if where:
            return f"the vehicle is at {where}"
        vel = self.velocity()
        if vel is not None and all(math.isfinite(x) for x in vel):
            ahead = tuple(p + ATTITUDE_LOOKAHEAD * v for p, v in zip(pos, vel, strict=True))
            where = outside((ahead[0], ahead[1], ahead[2]), self.box)
            if where:
                return f"the vehicle heads out of it within {ATTITUDE_LOOKAHEAD:.1f} s ({where})"
        return None

    def refuse(self, reason: str) -> None:
        """Count and announce a refused setpoint (one Event per reason per second)."""
        self.refused += 1
        self.stats.reject("setpoint")
        self.events.emit("safety", f"setpoint refused: {reason}", 4, every=1.0, reason=reason)

    # -- input ---------------------------------------------------------------------------------------
    def offer(self, sp: wire.Setpoint, now: float | None = None) -> str | None:
        """Take a user setpoint: sent at once (then streamed while its lease runs) when its stream holds
        the vehicle, held back when it waits for its engage; refused or dropped (counted) otherwise.
        Returns why it does not fly, or None."""
        now = time.monotonic() if now is None else now
        reason = self.check(sp)
        if reason is None and (not sp.stream or sp.seq < 1):
            reason = "no stream identity (stream, seq): a setpoint must say which stream it belongs to"
        if reason is not None:
            self.refuse(reason)
            return reason
        with self._lock:
            why = self.ledger.admit(sp.stream, sp.seq)
            if why is not None:
                self._drop(why)
                return why
            grounded = self.grounded()
            if grounded is not None:
                reason = f"{grounded}: take off first"
                self.refuse(reason)
                return reason
            st = _Stream(
                "user",
                sp.p,
                sp.v,
                wrap_yaw(sp.yaw),
                sp.yr,
                type_mask(sp),
                now + sp.lease,
                a=sp.a,
                q=sp.q,
                thrust=sp.thrust or 0.0,
                sid=sp.stream,
            )
            h = self._holder
            if h is not None and h.kind == "stream" and h.sid == sp.stream and self._latched is None:
                if self._stream is not None and self._stream.source == "goto":
                    self.events.emit("authority", f"{h.describe()} takes over from goto", 6, stream=h.sid)
                self._stream = st
                if now - self._last_send >= self.min_gap:
                    self._send(now)
                return None
            self._pending[sp.stream] = (st, sp.src, now)
            if len(self._pending) > MAX_PENDING:
                del self._pending[min(self._pending, key=lambda k: self._pending[k][2])]
            self.held += 1
            self.stats.count("setpoints_held")
            self._held_back(now)
        return None

    def _drop(self, why: str) -> None:
        """Count and announce a setpoint dropped for its order (one Event per second)."""
        self.dropped += 1
        self.stats.reject("setpoint_ended")
        self.events.emit("authority", f"setpoint dropped: {why}", 5, every=1.0, reason=why)

    def _held_back(self, now: float) -> None:
        """Note a user setpoint held back by the latch; warn once the stream has been held back for
        ``HELD_BACK_GRACE`` s (a block that commands OFFBOARD itself does so well before)."""
        first = now if self._held is None or now - self._held[1] > HELD_BACK_GRACE else self._held[0]
        self._held = (first, now)
        if now - first >= HELD_BACK_GRACE:
            why = f"offboard was left ({self._latched})" if self._latched else "its stream is not engaged"
            self.events.emit(
                "safety", f"setpoints held back: {why}; command mode OFFBOARD with the stream", 4, every=5.0
            )

    def start_goto(self, goal: Vec3, yaw: float | None, now: float | None = None, src: str = "") -> None:
        """Stream toward ``goal`` (checked by the caller) and hold it: the gateway's goto takes the vehicle
        (every stream seen so far ends) and the latch is released.

        The caller checks the goal and the yaw (:func:`yaw_problem`); a yaw out of range is a ValueError.
        """
        problem = yaw_problem(yaw)
        if problem:
            raise ValueError(problem)
        yaw = wrap_yaw(yaw)
        now = time.monotonic() if now is None else now
        start = self.position() or goal
        mask = px4.TYPEMASK_VELOCITY | px4.TYPEMASK_ACCELERATION | px4.TYPEMASK_YAW_RATE_IGNORE
        if yaw is None:
            mask |= px4.TYPEMASK_YAW_IGNORE
        with self._lock:
            self.supersede(f"goto from {src or '?'}", keep_sending=False, src=src)
            self._holder = Holder("goto", "", src)
            self._latched, self._held = None, None
            self._stream = _Stream("goto", start, None, yaw, None, mask, math.inf, goal)
            self._last_tick = now
            self._send(now)
        sub = self._sub
        if self._idle and sub is not None:
            sub.channel.put(cast(Any, _WAKE))

    def cancel_goto(self, reason: str) -> None:
        """Stop the gateway's own stream (a user stream is left alone)."""
        with self._lock:
            if self._stream is not None and self._stream.source == "goto":
                self._stream = None
                self._since = math.inf
                self.events.emit("info", f"goto stream stopped: {reason}", 6)
            if self._holder is not None and self._holder.kind == "goto":
                self._holder = None

    def supersede(self, by: str, keep_sending: bool = True, src: str = "") -> None:
        """A command (``by``: what and from whom) takes the vehicle: every stream seen so far ends, the one
        holding it included (an Event names both).  With ``keep_sending`` the last setpoint goes on under
        its lease until the command changes the mode (no gap for PX4's offboard-loss check); no new
        setpoint of an ended stream is taken.  ``src`` is the command's source (in the Event's data)."""
        with self._lock:
            h = self._holder
            why = f"superseded by {by}"
            for sid in [*self._pending, *self.ledger.seen()]:
                self.ledger.end(sid, why)
            self._pending.clear()
            if h is not None:
                if h.kind == "stream":
                    self.ledger.end(h.sid, why)
                self.events.emit(
                    "authority", f"{by} takes the vehicle from {h.describe()}", 6, ended=h.sid, by=src
                )
            self._holder = None
            s = self._stream
            if s is not None and (not keep_sending or s.source == "goto"):
                self._stream = None
                self._since = math.inf

    def engage(self, sid: str | None, src: str, now: float | None = None) -> str | None:
        """Give the vehicle to stream ``sid`` (None: the newest stream waiting with a live lease) for a
        ``mode OFFBOARD`` command from ``src``; why not, or None.  The stream holding it before ends; the
        goto carrot is sent on until the engaged stream's first setpoint arrives."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if sid is None:
                live = [(arr, k) for k, (st, _, arr) in self._pending.items() if now <= st.expires]
                if not live:
                    return (
                        "no live setpoint stream: stream setpoints (within their lease) for "
                        f"{self.prestream:.1f} s first, or use goto"
                    )
                sid = max(live)[1]
            why = self.ledger.ended(sid)
            if why is not None:
                return f"stream {sid} has ended ({why}): start a new one"
            new, prev = Holder("stream", sid, src), self._holder
            if prev is not None and prev != new:
                if prev.kind == "stream":
                    self.ledger.end(prev.sid, f"taken over by {new.describe()}")
                self.events.emit(
                    "authority", f"{new.describe()} takes the vehicle from {prev.describe()}", 6,
                    ended=prev.sid, stream=sid, by=src,
                )  # fmt: skip
            self._holder = new
            self._latched, self._held = None, None
            pending = self._pending.pop(sid, None)
            if pending is not None:
                self._stream = pending[0]
                self._send(now)
            elif self._stream is not None and self._stream.source == "user" and self._stream.sid != sid:
                self._stream = None
                self._since = math.inf
        return None

    def snapshot(self) -> tuple[Holder | None, str | None, _Stream | None]:
        """Who holds the vehicle, the latch and the stream sent: to :meth:`restore` after a failed engage."""
        with self._lock:
            return self._holder, self._latched, self._stream

    def restore(self, snap: tuple[Holder | None, str | None, _Stream | None]) -> None:
        """Put back what :meth:`snapshot` saw (the engaged stream stays ended only if it had ended)."""
        with self._lock:
            self._holder, self._latched, self._stream = snap
            if self._latched is not None or self._stream is None:
                self._since = math.inf

    @property
    def holder(self) -> str:
        """Who holds the vehicle, in words ("" : nobody: the autopilot's own mode)."""
        h = self._holder
        return "" if h is None else h.describe()

    def latch(self, reason: str) -> None:
        """Stop sending until a command engages a stream or a goto (the vehicle left OFFBOARD, or an estop)."""
        with self._lock:
            if self._latched is None:
                self._latched = reason
                self._since = math.inf
                self._holder = None
                if self._stream is not None:
                    if self._stream.source == "goto":
                        self._stream = None
                    self.events.emit("info", f"offboard stream stopped: {reason}", 5)

    @property
    def latched(self) -> str | None:
        """Why streaming is held back, or None."""
        return self._latched

    def streaming(self, now: float | None = None) -> bool:
        """Whether setpoints are being sent to the vehicle now."""
        now = time.monotonic() if now is None else now
        s = self._stream
        return s is not None and self._latched is None and now <= s.expires and now - self._last_send < 0.5

    def live(self, now: float | None = None) -> bool:
        """Streaming for at least ``prestream`` s: PX4 will accept a switch to OFFBOARD."""
        now = time.monotonic() if now is None else now
        return self.streaming(now) and now - self._since >= self.prestream

    # -- output --------------------------------------------------------------------------------------
    def tick(self, now: float | None = None) -> float:
        """Expire leases, move the goto carrot, send when due; seconds until the next tick is needed."""
        now = time.monotonic() if now is None else now
        with self._lock:
            s = self._stream
            dt, self._last_tick = now - self._last_tick, now
            for sid in [k for k, (st, _, _) in self._pending.items() if now > st.expires]:
                del self._pending[sid]
            if s is None:
                return self.period
            if now > s.expires:
                self._stream = None
                self._since = math.inf
                h = self._holder
                if h is not None and h.kind == "stream" and h.sid == s.sid:
                    self.ledger.end(s.sid, "its lease lapsed")
                    self._holder = None
                if self._latched is None:
                    self.events.emit(
                        "safety",
                        "setpoint lease expired: offboard stream stopped: PX4 takes its offboard-loss action",
                        4,
                    )
                return self.period
            if self._latched is not None:
                return self.period
            if s.goal is not None and s.p is not None:
                s.p = _toward(s.p, s.goal, self.goto_speed * dt, self.goto_climb * dt)
            if s.q is not None:
                where = self._attitude_outside()
                if where:
                    self._stream = None
                    self._since = math.inf
                    self._latched = f"attitude stream leaving the safe volume ({where})"
                    self._hold_now()
                    self.events.emit(
                        "safety",
                        f"attitude stream stopped: leaving the safe volume ({where}); "
                        "commanded Hold (AUTO.LOITER)",
                        3,
                        reason=where,
                    )
                    return self.period
            left = self._last_send + self.period - now
            if left > 0:
                return min(left, s.expires - now + 1e-3)
            self._send(now)
            return self.period

    def _send(self, now: float) -> None:
        s = self._stream
        if s is None:
            return
        if s.q is not None:
            msg = self.link.mav.set_attitude_target_encode(
                int((now - self._t0) * 1000) & 0xFFFFFFFF,
                self.target_system,
                px4.MAV_COMP_ID_AUTOPILOT1,
                px4.ATTITUDE_TARGET_BODY_RATES_IGNORE,
                list(s.q), 0.0, 0.0, 0.0, s.thrust,
            )  # fmt: skip
        else:
            msg = self._position_target(now, s)
        if self.link.send(msg):
            if self._since == math.inf or now - self._last_send > 3 * self.period:
                self._since = now  # a new continuous stream begins
            self._last_send = now
            self.sent += 1
            self.stats.count("setpoints")

    def course(self) -> tuple[Vec3 | None, float | None]:
        """What the arena flies the vehicle to now: the velocity a user stream commands (None for a
        position stream) and how far the gateway's goto still has to go (None when no goto flies it)."""
        s, pos = self._stream, self.position()
        if s is None or self._latched is not None:
            return None, None
        if s.source == "goto" and s.goal is not None:
            return None, math.dist(pos, s.goal) if pos is not None else None
        return (s.v if s.p is None else None), None

    def guard(self, closing: Closing, offboard: bool) -> None:
        """The vehicle heads for another (``closing``): when the arena flies it (OFFBOARD), take it from
        whoever holds it and command Hold at once; in the autopilot's own modes, warn."""
        text = closing.describe(self.separation.min_separation if self.separation else 0.0)
        if not offboard:
            self.events.emit("safety", f"separation: {text}", 4, every=2.0, other=closing.other)
            return
        with self._lock:
            self.supersede(f"the separation guard ({closing.other})", keep_sending=False)
            self._latched = self._latched or f"held apart from {closing.other}"
        self._hold_now()
        self.events.emit(
            "safety", f"held before meeting {text}: commanded Hold (AUTO.LOITER)", 3, every=0.5,
            other=closing.other,
        )  # fmt: skip

    def _hold_now(self) -> None:
        """Ask PX4 for Hold at once (DO_SET_MODE AUTO.LOITER, twice against a lost packet), without
        waiting for its answer: an attitude stream that left the room must not coast until PX4's
        offboard-loss timeout."""
        msg = self.link.mav.command_long_encode(
            self.target_system,
            px4.MAV_COMP_ID_AUTOPILOT1,
            px4.MAV_CMD_DO_SET_MODE,
            0,
            px4.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            px4.MAIN_AUTO,
            px4.AUTO_LOITER,
            0, 0, 0, 0,
        )  # fmt: skip
        for _ in range(2):
            self.link.send(msg)

    def _position_target(self, now: float, s: _Stream) -> Any:
        p = s.p or (0.0, 0.0, 0.0)
        v = s.v or (0.0, 0.0, 0.0)
        a = s.a or (0.0, 0.0, 0.0)
        return self.link.mav.set_position_target_local_ned_encode(
            int((now - self._t0) * 1000) & 0xFFFFFFFF,
            self.target_system,
            px4.MAV_COMP_ID_AUTOPILOT1,
            px4.MAV_FRAME_LOCAL_NED,
            s.mask,
            p[0], p[1], p[2], v[0], v[1], v[2], a[0], a[1], a[2],
            s.yaw if s.yaw is not None else 0.0,
            s.yr if s.yr is not None else 0.0,
        )  # fmt: skip

    def _reject_sample(self, kind: str, detail: str) -> None:
        if kind == "bad_payload":
            self.refuse(f"undecodable: {detail}")
        else:
            self.refuse(f"not a Setpoint: {detail}")

    def run(
        self, sub: Subscription, stop: threading.Event, on_error: Callable[[str, BaseException], None]
    ) -> None:
        """The forwarder's thread: take setpoints from ``sub`` and stream until ``stop``.

        A failure of one sample (or send) goes to ``on_error("setpoint", exc)`` and the stream goes on.
        """
        self._sub = sub
        while not stop.is_set():
            try:
                wait = self.tick()
                self._idle = True  # before looking at the stream: start_goto then sees it and wakes us
                if self._stream is None:  # nothing to stream: wait for a setpoint or start_goto's wake-up
                    item = sub.get(IDLE_WAIT)
                else:
                    item = sub.get(max(0.001, min(wait, 0.05)))
                self._idle = False
                if item is None or item is _WAKE:
                    continue
                sp = typed(item, wire.Setpoint, self._reject_sample)
                if sp is not None:
                    self.offer(sp)
            except Exception as exc:  # one bad sample (or send) must never end the stream for good
                on_error("setpoint", exc)
                stop.wait(0.01)


def _toward(p: Vec3, goal: Vec3, step_xy: float, step_z: float) -> Vec3:
    dn, de, dd = goal[0] - p[0], goal[1] - p[1], goal[2] - p[2]
    dist = math.hypot(dn, de)
    k = 1.0 if dist <= step_xy or dist == 0.0 else step_xy / dist
    dz = max(-step_z, min(step_z, dd))
    return (p[0] + dn * k, p[1] + de * k, p[2] + dz)
