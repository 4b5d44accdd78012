"""A program's own setpoints: :class:`OffboardStream`, from :meth:`Vehicle.offboard
<arena_common.client.vehicle.Vehicle.offboard>`.

::

    with d1.offboard() as ctl:
        ctl.position(1.0, 0.0, -1.0, yaw=0.0)                 # position (+ velocity/acceleration feed-forward)
        ctl.velocity(0.3, 0.0, 0.0)                           # NED velocity
        ctl.velocity_body(0.3, 0.0, 0.0, yaw_rate=0.2)        # forward/right/down, turned by the heading
        ctl.full_state((1, 0, -1), (0.2, 0, 0), (0, 0, 0), yaw=0.0)
        ctl.follow(Trajectory.waypoints([(0, a), (3, b), (6, c)]))   # a smooth reference, streamed

Every setpoint goes to the gateway, which applies the arena's safety rules to it (safe volume, speed,
climb and acceleration limits) before the autopilot sees it.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import threading
import time
from collections.abc import Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

import msgspec

from arena_common.bus.session import Lane
from arena_common.client.streams import Callback
from arena_common.client.trajectory import Trajectory
from arena_common.core import keys, wire
from arena_common.core.errors import CommandError, CommandRejected, SafetyRefused, VehicleNotPresent
from arena_common.geometry.quat import quat_from_euler

if TYPE_CHECKING:
    from arena_common.client.vehicle import Vehicle

__all__ = [
    "MAX_ACCEL",
    "MAX_START_OFFSET",
    "MAX_TILT",
    "MAX_YAW",
    "MAX_YAW_RATE",
    "OffboardStream",
    "setpoint_problem",
    "trajectory_problem",
]

Vec3 = tuple[float, float, float]
log = logging.getLogger("arena_common.client")
MAX_ACCEL = 5.0  # m/s²: the gateway's limit on an acceleration feed-forward (gateway.setpoints.MAX_ACCEL)
MAX_START_OFFSET = 0.5  # m: a trajectory must start this close to the vehicle (PX4's hover swings 24-40 cm)
MAX_YAW = 1000.0  # rad: the gateway's limit on a yaw (gateway.setpoints.MAX_YAW)
MAX_YAW_RATE = 2.0 * math.pi  # rad/s: the gateway's limit on a yaw rate (gateway.setpoints.MAX_YAW_RATE)
MAX_TILT = math.radians(35.0)  # rad: the gateway's limit on an attitude setpoint's tilt


def _vec(values: Sequence[float], what: str) -> Vec3:
    if len(values) != 3:
        raise ValueError(f"{what} needs three components (north, east, down), got {len(values)}")
    return (float(values[0]), float(values[1]), float(values[2]))


def trajectory_problem(vehicle: Vehicle, trajectory: Trajectory) -> str | None:
    """Why the gateway would refuse some point of ``trajectory`` for ``vehicle`` (the arena's safe volume,
    speed, climb and acceleration limits), or why it cannot start (too far from the vehicle); or None."""
    cfg = vehicle.arena.config
    problem = trajectory.check(
        cfg.arena.safe_box() if cfg else None,
        cfg.arena.max_speed if cfg else math.inf,
        cfg.arena.max_climb if cfg else math.inf,
        MAX_ACCEL,
    )
    p = vehicle.position
    if problem is None and p is not None and math.dist(p, trajectory.start) > MAX_START_OFFSET:
        problem = f"it starts {math.dist(p, trajectory.start):.2f} m from the vehicle"
    if problem is None and cfg is not None:
        problem = _separation_problem(vehicle, trajectory, cfg.arena.min_separation)
    return problem


def _separation_problem(vehicle: Vehicle, trajectory: Trajectory, min_separation: float) -> str | None:
    """Where ``trajectory`` comes within ``min_separation`` of another vehicle's position now (the gateway
    would refuse those setpoints), or None.  A vehicle it already starts near is left out: flying away
    must stay possible."""
    others = {
        n: q
        for n, q in vehicle.arena.positions().items()
        if n != vehicle.name and math.dist(q, trajectory.start) >= min_separation
    }
    if min_separation <= 0.0 or not others:
        return None
    steps = max(1, math.ceil(trajectory.duration / 0.05))
    for k in range(steps + 1):
        pt = trajectory.sample(trajectory.duration * k / steps)
        for n, q in others.items():
            if math.dist(pt.p, q) < min_separation:
                return (
                    f"at {pt.t:.1f} s it passes {math.dist(pt.p, q):.2f} m from {n} "
                    f"(min_separation {min_separation:.2f} m)"
                )
    return None


def setpoint_problem(vehicle: Vehicle, fields: dict[str, Any]) -> str | None:
    """Why the gateway would refuse a setpoint of these fields (``p``, ``v``, ``a``, ``yaw``, ``yr``,
    ``q``/``thrust``) under the arena's limits (safe volume, ``max_speed``, ``max_climb``, ``MAX_ACCEL``,
    yaw, tilt), or None.  A body-frame velocity is checked by its norms, which turning does not change.

    The gateway checks once more, with what only it knows (where the vehicle is): a velocity leading
    further out of the safe volume, an attitude stream outside it; those refusals reach the program as
    events, which :class:`OffboardStream` turns into :class:`SafetyRefused` at the next call.
    """
    cfg = vehicle.arena.config
    yaw, yr = fields.get("yaw"), fields.get("yr")
    if yaw is not None and abs(yaw) > MAX_YAW:
        return f"yaw {yaw!r} rad is not within ±{MAX_YAW:g} rad"
    if yr is not None and abs(yr) > MAX_YAW_RATE:
        return f"yaw rate {yr!r} rad/s beyond ±{MAX_YAW_RATE:.2f} rad/s"
    q = fields.get("q")
    if q is not None:
        x, y = q[1], q[2]
        tilt = math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (x * x + y * y))))
        if tilt > MAX_TILT + 1e-9:
            return (
                f"attitude tilted {math.degrees(tilt):.1f}° from level, above {math.degrees(MAX_TILT):.0f}°"
            )
    a = fields.get("a")
    if a is not None and math.sqrt(sum(x * x for x in a)) > MAX_ACCEL + 1e-9:
        return f"acceleration feed-forward {math.sqrt(sum(x * x for x in a)):.2f} m/s² above {MAX_ACCEL:.1f} m/s²"
    if cfg is None:
        return None
    p = fields.get("p")
    if p is not None:
        for k, axis in enumerate(("north", "east", "down")):
            lo, hi = cfg.arena.safe_box()[k]
            if not lo <= p[k] <= hi:
                return f"position outside the safe volume: {axis} {p[k]:.2f} m outside [{lo:.2f}, {hi:.2f}]"
    v = fields.get("v")
    if v is not None:
        speed = math.hypot(v[0], v[1])
        if speed > cfg.arena.max_speed + 1e-9:
            return f"horizontal speed {speed:.2f} m/s above max_speed {cfg.arena.max_speed:.2f}"
        if abs(v[2]) > cfg.arena.max_climb + 1e-9:
            return f"vertical speed {abs(v[2]):.2f} m/s above max_climb {cfg.arena.max_climb:.2f}"
    return None


def _checked(fields: dict[str, Any]) -> None:
    """Raise :class:`~arena_common.core.errors.PayloadError` (a ValueError) naming the field that the
    gateway would not decode (NaN, infinity, yaw with yaw rate…)."""
    wire.Setpoint.decode(wire.Setpoint(t=0, **fields).encode(), "setpoint")


_STREAMS = itertools.count(1)


def new_stream_id(vehicle: str) -> str:
    """An identity for one stream, unique across hosts and programs (random) and readable (vehicle, pid,
    number within this process)."""
    return f"{vehicle}-{os.getpid()}-{next(_STREAMS)}-{os.urandom(3).hex()}"


class OffboardStream:
    """Streams the latest setpoint at a steady rate from its own thread, whatever the user's loop does.

    Every setpoint names this stream (:attr:`id`) and its number in it: the gateway orders them by that,
    never by arrival (docs/safety.md).  Entering the block engages *this* stream (``mode OFFBOARD`` with
    its identity); leaving it, or :meth:`handover`, ends it by a command — a late setpoint of it is then
    dropped by the gateway, never taking the vehicle back.

    Each setpoint carries a lease.  Leaving the block puts the vehicle in Hold (AUTO.LOITER) where it is,
    as MAVSDK's ``offboard.stop()`` does, before the stream stops: a velocity setpoint does not coast on.
    Only when the program dies do the leases lapse without that, and the autopilot's offboard-loss
    failsafe (``COM_OBL_RC_ACT``: Land) takes over.  If Hold is refused, the block's exit raises
    :class:`~arena_common.core.errors.CommandError` after stopping the stream (the failsafe then acts).
    """

    def __init__(self, vehicle: Vehicle, rate: float, lease: float, engage: bool) -> None:
        if not 2.0 <= rate <= 100.0:
            raise ValueError("offboard rate must be within 2..100 Hz")
        self.vehicle = vehicle
        self.period = 1.0 / rate
        self.lease = lease
        self.engage = engage
        self._lock = threading.Lock()
        self._fields: dict[str, Any] | None = None
        self._body: tuple[Vec3, float | None, float | None] | None = None  # velocity, yaw, yaw rate
        self._traj: tuple[Trajectory, float, float | None] | None = None  # trajectory, start, yaw
        self._traj_done = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._handed_over = False
        self._refused: str | None = None  # a refusal the gateway reported, raised at the next call
        self._taken = threading.Event()  # a command (of any program) took the vehicle from this stream
        self._ending = False  # this block's own hold or hand-over is under way: it takes the vehicle
        self._watch: Callback | None = None
        self._pub = vehicle.arena.bus.stream_publisher(
            keys.setpoint(vehicle.name), wire.Setpoint, Lane.CONTROL
        )
        self.id = new_stream_id(vehicle.name)
        """This stream's identity on the wire (``Setpoint.stream``)."""
        self._seq = 0
        self.sent = 0
        self.errors = 0

    # -- what to stream -------------------------------------------------------------------------------
    def _check(self, fields: dict[str, Any]) -> None:
        """Raise in the caller's thread what the gateway would refuse (or has refused since the last
        call): a refused setpoint never reaches the vehicle, so streaming it would only let the lease
        lapse and the autopilot's offboard-loss failsafe land the vehicle."""
        _checked(fields)  # NaN, infinity, yaw with yaw rate: a PayloadError (ValueError)
        self._raise_refused()
        problem = setpoint_problem(self.vehicle, fields)
        if problem is not None:
            name = self.vehicle.name
            raise SafetyRefused(f"{name}: setpoint refused: {problem}", result="REFUSED", drone=name)

    def _on_event(self, event: wire.Event) -> None:
        if event.kind == "authority" and event.data.get("ended") == self.id:
            if not self._ending and event.data.get("by") != self.vehicle.arena.src:
                with self._lock:  # another program (or ROS 2, the CLI) took the vehicle: say so
                    self._refused = self._refused or event.text
            self._taken.set()  # by this program's own command too: the stream has ended, stop it
            self._stop.set()
        elif event.kind == "safety" and event.text.startswith("setpoint refused"):
            with self._lock:
                self._refused = self._refused or event.text

    def _raise_refused(self) -> None:
        """Raise :class:`SafetyRefused` once for a refusal the gateway reported during this block."""
        with self._lock:
            text, self._refused = self._refused, None
        if text is not None:
            name = self.vehicle.name
            raise SafetyRefused(f"{name}: {text} (by the gateway)", result="REFUSED", drone=name)

    def _set(self, **fields: Any) -> None:
        self._check(fields)  # a wrong setpoint fails here, in the caller's thread
        with self._lock:
            self._fields, self._body, self._traj = fields, None, None

    def position(
        self,
        north: float,
        east: float,
        down: float,
        yaw: float | None = None,
        velocity: Sequence[float] | None = None,
        acceleration: Sequence[float] | None = None,
    ) -> None:
        """Hold a position (NED, m), optionally with yaw [rad] and velocity [m/s] and acceleration [m/s²]
        feed-forwards."""
        v = _vec(velocity, "velocity") if velocity is not None else None
        a = _vec(acceleration, "acceleration") if acceleration is not None else None
        self._set(p=(float(north), float(east), float(down)), v=v, a=a, yaw=yaw)

    def velocity(
        self,
        north: float,
        east: float,
        down: float,
        yaw: float | None = None,
        yaw_rate: float | None = None,
        acceleration: Sequence[float] | None = None,
    ) -> None:
        """Fly a velocity (NED, m/s) with a yaw [rad] or a yaw rate [rad/s], optionally an acceleration
        feed-forward [m/s²]."""
        a = _vec(acceleration, "acceleration") if acceleration is not None else None
        self._set(v=(float(north), float(east), float(down)), a=a, yaw=yaw, yr=yaw_rate)

    def velocity_body(
        self,
        forward: float,
        right: float,
        down: float,
        yaw: float | None = None,
        yaw_rate: float | None = None,
    ) -> None:
        """Fly a velocity in the body's heading frame (forward, right, down; m/s), as MAVSDK's
        ``VelocityBodyYawspeed``: it is turned by the vehicle's current heading at every send."""
        if yaw is not None and yaw_rate is not None:
            raise ValueError("give yaw or yaw rate, not both")
        body = (float(forward), float(right), float(down))
        self._check({"v": body, "yaw": yaw, "yr": yaw_rate})
        with self._lock:
            self._fields, self._body, self._traj = None, (body, yaw, yaw_rate), None

    def full_state(
        self,
        position: Sequence[float],
        velocity: Sequence[float],
        acceleration: Sequence[float],
        yaw: float | None = None,
        yaw_rate: float | None = None,
    ) -> None:
        """Position, velocity and acceleration together (Crazyswarm2's ``cmdFullState``), with a yaw or,
        without one, a yaw rate."""
        p, v = _vec(position, "position"), _vec(velocity, "velocity")
        a = _vec(acceleration, "acceleration")
        self._set(p=p, v=v, a=a, yaw=yaw, yr=yaw_rate if yaw is None else None)

    def attitude(self, roll: float, pitch: float, yaw: float, thrust: float) -> None:
        """Fly an attitude (radians, aerospace ZYX, FRD body in the arena NED frame) with a collective
        thrust from 0 to 1, as MAVSDK's ``Attitude``.  The gateway refuses a tilt beyond 35° and attitude
        setpoints while the vehicle is outside the safe volume (or its position unknown), and stops the
        stream the moment it leaves it."""
        if not 0.0 <= thrust <= 1.0:
            raise ValueError(f"thrust must be within 0..1, got {thrust}")
        self._set(q=quat_from_euler(float(roll), float(pitch), float(yaw)), thrust=float(thrust))

    # -- trajectories ---------------------------------------------------------------------------------
    def follow(self, trajectory: Trajectory, wait: bool = True, yaw: float | None = None) -> None:
        """Stream ``trajectory`` (time 0 = now, on the arena's clock) and, with ``wait``, return when it
        has ended; its end point is then held.

        Refused before anything flies (:class:`SafetyRefused`) when a point breaks the arena's limits or
        the trajectory starts more than ``MAX_START_OFFSET`` m from the vehicle; stopped with
        :class:`CommandRejected` when the vehicle leaves OFFBOARD during it.  A trajectory without yaw
        keeps ``yaw`` (default: the heading at its start).
        """
        v = self.vehicle
        problem = trajectory_problem(v, trajectory)
        if problem is not None:
            raise SafetyRefused(f"{v.name}: trajectory refused: {problem}", result="REFUSED", drone=v.name)
        e = v.euler
        keep = yaw if yaw is not None else (e[2] if e else None)
        self._traj_done.clear()
        with self._lock:
            self._fields, self._body = None, None
            self._traj = (trajectory, v.arena.clock.now(), keep)
        if wait:
            self.wait(trajectory.duration)

    def wait(self, duration: float) -> None:
        """Block until the trajectory being followed ends (``duration`` arena seconds, plus a margin)."""
        v = self.vehicle
        deadline = time.monotonic() + v.arena.clock.wall(duration) + 5.0
        while not self._traj_done.wait(0.05):
            if self.engage and v.mode != "OFFBOARD" and self._thread is not None:
                recent = "; ".join(e.text for e in v.events()[-3:])
                raise CommandRejected(
                    f"{v.name}: left OFFBOARD ({v.mode}) while following a trajectory (last events: {recent})",
                    drone=v.name,
                )
            if self._taken.is_set():
                raise CommandRejected(
                    f"{v.name}: the vehicle was taken from this stream while following a trajectory "
                    f"({self._refused or 'by a command of this program'})",
                    drone=v.name,
                )
            if time.monotonic() > deadline or self._stop.is_set():
                raise CommandRejected(f"{v.name}: trajectory not completed", drone=v.name)

    def handover(self, goal: Sequence[float], yaw: float | None = None) -> None:
        """Stop this stream and let the gateway hold ``goal`` (its own ``goto`` stream, in OFFBOARD):
        leaving the block then keeps that hold instead of switching to Hold."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self._ending = True
        args: dict[str, Any] = {"p": list(_vec(goal, "goal"))}
        if yaw is not None:
            args["yaw"] = float(yaw)
        self.vehicle.command("goto", 5.0, **args)
        self._handed_over = True

    # -- the stream -----------------------------------------------------------------------------------
    def _next(self) -> wire.Setpoint | None:
        with self._lock:
            fields, body, traj = self._fields, self._body, self._traj
        src, now = self.vehicle.arena.src, wire.now_ns()
        if fields is not None:
            return wire.Setpoint(t=now, lease=self.lease, src=src, **fields)
        if body is not None:
            e = self.vehicle.euler
            if e is None:
                return None  # no heading known: nothing to turn the velocity by
            (f, r, d), yaw, yr = body
            c, s = math.cos(e[2]), math.sin(e[2])
            return wire.Setpoint(
                t=now, lease=self.lease, src=src, v=(c * f - s * r, s * f + c * r, d), yaw=yaw, yr=yr
            )
        if traj is not None:
            trajectory, t0, keep = traj
            pt = trajectory.sample(self.vehicle.arena.clock.now() - t0)
            if pt.t >= trajectory.duration:
                self._traj_done.set()
            yaw = pt.yaw if pt.yaw is not None else keep
            yr = pt.yaw_rate if pt.yaw is not None and pt.yaw_rate != 0.0 else None
            return wire.Setpoint(
                t=now,
                lease=self.lease,
                src=src,
                p=pt.p,
                v=pt.v,
                a=pt.a,
                yaw=yaw,
                yr=None if yaw is not None else yr,
            )
        return None

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                sp = self._next()
                if sp is not None:
                    self._seq += 1
                    self._pub.put(msgspec.structs.replace(sp, stream=self.id, seq=self._seq))
                    self.sent += 1
            except Exception:  # counted and logged; nothing is sent, so the lease lapses if it goes on
                self.errors += 1
                if self.errors == 1 or self.errors % 100 == 0:
                    log.exception(
                        "%s: offboard stream: setpoint not sent (%d so far)", self.vehicle.name, self.errors
                    )
            next_t += self.period
            delay = next_t - time.monotonic()
            if delay < -self.period:  # fell behind (suspended?): re-anchor rather than burst
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(max(delay, 0.0))

    def __enter__(self) -> OffboardStream:
        v = self.vehicle
        if self._fields is None and self._body is None and self._traj is None:
            p = v.position
            if p is None:
                raise VehicleNotPresent(
                    f"{v.name}: no position known; cannot start an offboard stream", drone=v.name
                )
            e = v.euler
            self.position(*p, yaw=e[2] if e else None)
        self._watch = v.on_event(self._on_event)
        self._thread = threading.Thread(target=self._run, name=f"offboard:{v.name}", daemon=True)
        self._thread.start()
        v._open_streams.append(self.id)
        if self.engage:
            try:
                time.sleep(max(3 * self.period, 0.3))  # the autopilot needs a stream before OFFBOARD
                v.command("mode", 5.0, mode="OFFBOARD", stream=self.id)
            except BaseException:
                self.close()
                raise
        return self

    def close(self) -> None:
        """Stop streaming; the leases lapse."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        if self.id in self.vehicle._open_streams:
            self.vehicle._open_streams.remove(self.id)
        if self._watch is not None:
            self._watch.cancel()
            self._watch = None
        self._pub.close()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            if not self._handed_over and self.vehicle.mode == "OFFBOARD" and not self._taken.is_set():
                self._ending = True
                self.vehicle.hold()  # while our stream still runs: no gap for the failsafe to see
        except CommandError:
            if exc_type is None:
                raise
        finally:
            self.close()
        if exc_type is None:
            self._raise_refused()
