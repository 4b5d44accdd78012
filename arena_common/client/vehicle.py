"""One drone as a program sees it: :class:`Vehicle`, from :meth:`Arena.vehicle
<arena_common.client.arena.Arena.vehicle>`.

::

    from arena_common import Arena

    with Arena("deploy/sim.toml") as arena:
        d1 = arena.vehicle("d1")
        d1.arm()
        d1.takeoff(1.0)
        d1.goto(1.0, -1.0, -1.0, yaw=0.0)
        for pose in d1.poses(timeout=1.0):   # every new mocap pose, in order, with its measurement time
            ...
        d1.land()

Attributes are kept fresh by the arena's client thread, each with its source, age and validity:
:attr:`Vehicle.mocap_pose` (the motion-capture pose), :attr:`Vehicle.estimate` (the autopilot's, not
valid when the autopilot says so), :attr:`Vehicle.status` (typed state), :attr:`Vehicle.imu`,
:attr:`Vehicle.battery`, :attr:`Vehicle.estimator`.  Streams (``poses()``, ``vision()``, ``states()``,
``event_stream()``, ``imu_stream()``…) yield every new item in order; ``on_*`` methods register
callbacks.  Commands block until the autopilot confirms or raise a typed
:class:`~arena_common.core.errors.CommandError` saying why.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from arena_common.client.offboard import OffboardStream, trajectory_problem
from arena_common.client.params import Params
from arena_common.client.streams import Callback, Stream, Topic
from arena_common.client.telemetry import SENSOR_MESSAGES, Telemetry
from arena_common.client.trajectory import Trajectory
from arena_common.client.types import (
    Battery,
    EstimatorStatus,
    FlightMode,
    Imu,
    LandedState,
    PoseReading,
    Status,
)
from arena_common.core import keys, ops, wire
from arena_common.core.arrival import ARRIVAL_TOLERANCE, ARRIVAL_WINDOW, HEIGHT_TOLERANCE, Arrival
from arena_common.core.errors import (
    CommandRejected,
    CommandTimeout,
    NotPermitted,
    SafetyRefused,
    VehicleNotPresent,
)
from arena_common.geometry.frames import quat_to_euler

if TYPE_CHECKING:
    from arena_common.client.arena import Arena

__all__ = ["MOCAP_MAX_AGE", "STATE_MAX_AGE", "Vehicle"]

log = logging.getLogger("arena_common.client")

Vec3 = tuple[float, float, float]
MOCAP_MAX_AGE = 0.5  # s: an older mocap pose is not valid
STATE_MAX_AGE = 1.0  # s: an older state (estimate) is not valid
ESTIMATOR_MAX_AGE = 3.0  # s: an older ESTIMATOR_STATUS says nothing (as the gateway judges it)


class Vehicle:
    """One drone on the bus.  Get it from :meth:`Arena.vehicle`."""

    def __init__(self, arena: Arena, name: str) -> None:
        self.name = keys.validate_name(name)
        self.arena = arena
        self._cond = threading.Condition()
        self._state: wire.State | None = None
        self._history: collections.deque[wire.Event] = collections.deque(maxlen=100)
        self.pose_topic: Topic[wire.Pose] = Topic(f"{name}/pose")
        self.vision_topic: Topic[wire.Pose] = Topic(f"{name}/vision")
        self.state_topic: Topic[Status] = Topic(f"{name}/state")
        self.event_topic: Topic[wire.Event] = Topic(f"{name}/events")
        self.imu_topic: Topic[Imu] = Topic(f"{name}/imu")
        self.battery_topic: Topic[Battery] = Topic(f"{name}/battery")
        self.estimator_topic: Topic[EstimatorStatus] = Topic(f"{name}/estimator")
        self.telemetry = Telemetry(self)
        """Raw autopilot messages: ``d1.telemetry("HIGHRES_IMU")``, ``.stream(name)``, ``.on(name, fn)``."""
        self.params = Params(self)
        """The autopilot's parameters: ``d1.params.get("MPC_XY_VEL_MAX")``, ``.set(name, value)``."""
        self._open_streams: list[str] = []  # this program's offboard blocks open on this vehicle

    # -- input from the arena's client thread ---------------------------------------------------------
    def _update(self, item: Any) -> None:
        parts = item.key.split("/")
        leaf, payload, now = parts[2], item.payload, time.monotonic()
        if leaf == "state" and isinstance(payload, wire.State):
            with self._cond:
                self._state = payload
                self._cond.notify_all()
            self.state_topic.publish(Status.from_wire(payload, now))
        elif leaf == "pose" and isinstance(payload, wire.Pose):
            self.pose_topic.publish(payload)
            with self._cond:
                self._cond.notify_all()
        elif leaf == "vision" and isinstance(payload, wire.Pose):
            self.vision_topic.publish(payload)
        elif leaf == "events" and isinstance(payload, wire.Event):
            with self._cond:
                self._history.append(payload)
            self.event_topic.publish(payload)
        elif leaf == "telemetry" and len(parts) > 3 and isinstance(payload, wire.Telemetry):
            self.telemetry._publish(parts[3], payload)
            if payload.msg in ("HIGHRES_IMU", "SCALED_IMU"):
                self.imu_topic.publish(Imu.from_telemetry(payload, now))
            elif payload.msg == "BATTERY_STATUS":
                self.battery_topic.publish(Battery.from_telemetry(payload, now))
            elif payload.msg == "ESTIMATOR_STATUS":
                self.estimator_topic.publish(EstimatorStatus.from_telemetry(payload, now))
        else:
            self.arena._reject(item.key, f"unexpected {type(payload).__name__}")

    def _subscriptions(self) -> list[str]:
        base = f"arena/{self.name}"
        return [f"{base}/{leaf}" for leaf in ("state", "pose", "vision", "events")] + [
            keys.telemetry(self.name, m) for m in SENSOR_MESSAGES
        ]

    def _close(self) -> None:
        for topic in (
            self.pose_topic,
            self.vision_topic,
            self.state_topic,
            self.event_topic,
            self.imu_topic,
            self.battery_topic,
            self.estimator_topic,
        ):
            topic.close()
        self.telemetry._close()

    # -- readings -------------------------------------------------------------------------------------
    @property
    def state(self) -> wire.State | None:
        """The latest raw :class:`~arena_common.core.wire.State` (None before any); see :attr:`status`."""
        return self._state

    @property
    def status(self) -> Status | None:
        """The latest state, typed (:class:`~arena_common.client.types.Status`; None before any)."""
        return self.state_topic.latest

    @property
    def state_age(self) -> float:
        """Seconds since the last state arrived (inf before any)."""
        return self.state_topic.age

    @property
    def mocap(self) -> wire.Pose | None:
        """The latest raw mocap pose in the arena frame, full rate (``arena/<drone>/pose``)."""
        return self.pose_topic.latest

    @property
    def mocap_age(self) -> float:
        """Seconds since the last mocap pose arrived (inf before any)."""
        return self.pose_topic.age

    @property
    def mocap_pose(self) -> PoseReading | None:
        """The motion-capture pose with its age; valid while tracked and younger than ``MOCAP_MAX_AGE``."""
        pose = self.pose_topic.latest
        if pose is None:
            return None
        age = time.monotonic() - self.pose_topic.received
        problem = "" if pose.ok else "not tracked by the motion capture"
        if not problem and age > MOCAP_MAX_AGE:
            problem = f"stale: {age:.2f} s old"
        return PoseReading(
            "mocap", pose.t, self.pose_topic.received, pose.p, pose.q, pose.v if pose.vok else None,
            not problem, problem,
        )  # fmt: skip

    @property
    def estimate(self) -> PoseReading | None:
        """The autopilot's own position estimate with its age; not valid when the autopilot marks it so
        (ESTIMATOR_STATUS), when the link is down or when the state is older than ``STATE_MAX_AGE``."""
        s, status = self._state, self.state_topic.latest
        if s is None or s.p is None or status is None:
            return None
        problem = ""
        age = time.monotonic() - status.received
        est = self.estimator_topic.latest
        if not s.link:
            problem = "no link to the autopilot"
        elif age > STATE_MAX_AGE:
            problem = f"stale: {age:.2f} s old"
        elif est is not None and est.age <= ESTIMATOR_MAX_AGE and est.problem:
            problem = est.problem
        return PoseReading("estimate", s.t, status.received, s.p, s.q, s.v, not problem, problem)

    def _source(self) -> PoseReading | None:
        m = self.mocap_pose
        if m is not None and m.valid:
            return m
        e = self.estimate
        return e if e is not None and e.valid else None

    @property
    def position_source(self) -> str | None:
        """Where :attr:`position` and :attr:`attitude` come from now: ``"mocap"``, ``"estimate"`` or None."""
        src = self._source()
        return src.source if src is not None else None

    @property
    def position(self) -> Vec3 | None:
        """North, east, down [m]: the mocap pose while valid, else the autopilot's estimate while valid,
        else None (see :attr:`position_source`, :attr:`mocap_pose`, :attr:`estimate`)."""
        src = self._source()
        return src.p if src is not None else None

    @property
    def attitude(self) -> tuple[float, float, float, float] | None:
        """Quaternion (w, x, y, z), body FRD to arena NED, from the same source as :attr:`position`."""
        src = self._source()
        return src.q if src is not None else None

    @property
    def velocity(self) -> Vec3 | None:
        """NED velocity [m/s]: the autopilot's estimate while valid (mocap poses carry no velocity unless
        the pipeline measured one), else the mocap pose's, else None."""
        e = self.estimate
        if e is not None and e.valid and e.v is not None:
            return e.v
        m = self.mocap_pose
        return m.v if m is not None and m.valid else None

    @property
    def euler(self) -> tuple[float, float, float] | None:
        """(roll, pitch, yaw) in radians."""
        q = self.attitude
        return quat_to_euler(q) if q is not None else None

    @property
    def armed(self) -> bool:
        """Motors armed."""
        return bool(self._state and self._state.armed)

    @property
    def mode(self) -> FlightMode:
        """The flight mode (:class:`FlightMode`; compares equal to PX4's names, ``"OFFBOARD"``…)."""
        return FlightMode.parse(self._state.mode) if self._state else FlightMode.UNKNOWN

    @property
    def landed(self) -> LandedState:
        """The landed state (:class:`LandedState`; compares equal to ``"on_ground"``…)."""
        return LandedState.parse(self._state.landed) if self._state else LandedState.UNDEFINED

    @property
    def battery(self) -> Battery | None:
        """The latest battery reading (BATTERY_STATUS, else the state's remaining and voltage)."""
        b = self.battery_topic.latest
        if b is not None:
            return b
        status = self.state_topic.latest
        return Battery.from_status(status) if status is not None and status.battery is not None else None

    @property
    def imu(self) -> Imu | None:
        """The latest IMU reading (body FRD; HIGHRES_IMU or SCALED_IMU) at the telemetry rate."""
        return self.imu_topic.latest

    @property
    def estimator(self) -> EstimatorStatus | None:
        """The latest estimator status (ESTIMATOR_STATUS)."""
        return self.estimator_topic.latest

    @property
    def link(self) -> bool:
        """True while the gateway reports heartbeats and its state is fresh."""
        return bool(self._state and self._state.link and self.state_age < STATE_MAX_AGE)

    def events(self) -> list[wire.Event]:
        """The last (up to 100) events of this vehicle (see :meth:`event_stream` for new ones)."""
        with self._cond:
            return list(self._history)

    # -- streams and callbacks ------------------------------------------------------------------------
    def poses(self, timeout: float | None = None, capacity: int = 1024) -> Stream[wire.Pose]:
        """Every new mocap pose (arena frame, full rate), in order; ``pose.t`` is its measurement time."""
        return self.pose_topic.stream(capacity, timeout)

    def vision(self, timeout: float | None = None, capacity: int = 1024) -> Stream[wire.Pose]:
        """Every pose sent to the autopilot as vision (decimated), in order."""
        return self.vision_topic.stream(capacity, timeout)

    def states(self, timeout: float | None = None, capacity: int = 1024) -> Stream[Status]:
        """Every new typed state, in order."""
        return self.state_topic.stream(capacity, timeout)

    def event_stream(self, timeout: float | None = None, capacity: int = 1024) -> Stream[wire.Event]:
        """Every new event (mode and arming changes, failsafes, status texts…), in order."""
        return self.event_topic.stream(capacity, timeout)

    def imu_stream(self, timeout: float | None = None, capacity: int = 1024) -> Stream[Imu]:
        """Every new IMU reading, in order."""
        return self.imu_topic.stream(capacity, timeout)

    def battery_stream(self, timeout: float | None = None, capacity: int = 1024) -> Stream[Battery]:
        """Every new battery reading, in order."""
        return self.battery_topic.stream(capacity, timeout)

    def estimator_stream(self, timeout: float | None = None, capacity: int = 1024) -> Stream[EstimatorStatus]:
        """Every new estimator status, in order."""
        return self.estimator_topic.stream(capacity, timeout)

    def on_pose(self, fn: Callable[[wire.Pose], object]) -> Callback:
        """Call ``fn(pose)`` for every new mocap pose (on the arena's client thread: keep it short)."""
        return self.pose_topic.on(fn)

    def on_vision(self, fn: Callable[[wire.Pose], object]) -> Callback:
        """Call ``fn(pose)`` for every pose sent as vision."""
        return self.vision_topic.on(fn)

    def on_state(self, fn: Callable[[Status], object]) -> Callback:
        """Call ``fn(status)`` for every new state."""
        return self.state_topic.on(fn)

    def on_event(self, fn: Callable[[wire.Event], object]) -> Callback:
        """Call ``fn(event)`` for every new event."""
        return self.event_topic.on(fn)

    def on_imu(self, fn: Callable[[Imu], object]) -> Callback:
        """Call ``fn(imu)`` for every new IMU reading."""
        return self.imu_topic.on(fn)

    def on_battery(self, fn: Callable[[Battery], object]) -> Callback:
        """Call ``fn(battery)`` for every new battery reading."""
        return self.battery_topic.on(fn)

    def on_estimator(self, fn: Callable[[EstimatorStatus], object]) -> Callback:
        """Call ``fn(status)`` for every new estimator status."""
        return self.estimator_topic.on(fn)

    # -- waiting --------------------------------------------------------------------------------------
    def wait_until(
        self,
        predicate: Callable[[Vehicle], bool],
        timeout: float = 10.0,
        what: str = "",
        detail: Callable[[], str] | None = None,
    ) -> None:
        """Block until ``predicate(self)`` holds; :class:`CommandTimeout` after ``timeout`` seconds (its
        text ends with ``detail()`` when given: how far from it the vehicle is)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate(self):
                left = deadline - time.monotonic()
                if left <= 0:
                    more = f": {detail()}" if detail is not None else ""
                    raise CommandTimeout(
                        f"{self.name}: {what or 'condition'} not reached within {timeout:.1f} s{more}",
                        result="TIMEOUT",
                        drone=self.name,
                    )
                self._cond.wait(min(left, 0.1))

    def wait_arrival(self, arrival: Arrival, timeout: float, what: str, holding: str = "") -> None:
        """Block until ``arrival`` judges the vehicle arrived (its position averaged over the arrival
        window, :mod:`arena_common.core.arrival`); :class:`CommandTimeout` after ``timeout`` seconds,
        naming how far the vehicle is.  With ``holding`` (a mode, ``"OFFBOARD"`` for a goto), leaving that
        mode ends the wait at once with :class:`CommandRejected` and the last events: nothing flies the
        vehicle there any more (a separation hold, a failsafe, another program)."""
        left_mode: list[str] = []
        seen = [False]  # the vehicle was seen in ``holding`` (a state may lag the command's answer)
        started = time.monotonic()

        def arrived(v: Vehicle) -> bool:
            now = time.monotonic()
            arrival.add(now, v.position)
            if holding:
                if v.mode == holding:
                    seen[0] = True
                elif seen[0] or now - started > 3.0:
                    left_mode.append(str(v.mode))
                    return True
            return arrival.arrived()

        self.wait_until(arrived, timeout, what, arrival.describe)
        if left_mode:
            recent = "; ".join(e.text for e in self.events()[-3:])
            raise CommandRejected(
                f"{self.name}: {what} not reached: the vehicle left {holding} ({left_mode[0]}), "
                f"{arrival.describe()} (last events: {recent})",
                result="REJECTED",
                drone=self.name,
            )

    def _catch_up(self, t_ns: int, timeout: float = 1.0) -> None:
        """Wait (briefly) for a state the gateway stamped at or after ``t_ns`` (its clock): the attributes
        then show what a confirmed command did (``mode`` after :meth:`set_mode`…)."""
        if t_ns <= 0:
            return  # an answer without the gateway's time
        with self._cond:
            self._cond.wait_for(lambda: self._state is not None and self._state.t >= t_ns, timeout)

    # -- commands -------------------------------------------------------------------------------------
    def command(self, op: str, timeout: float = 5.0, **args: Any) -> wire.CommandResult:
        """Send a raw command to the gateway; raise a typed error unless it succeeded.

        It returns once the vehicle's attributes show the command's effect (a state the gateway stamped
        after its answer arrived, within a second), so ``mode`` reads the mode just confirmed.
        """
        sec = self.arena.config.security if self.arena.config is not None else None
        if sec is not None and sec.enabled and sec.command_hosts and self.arena.host not in sec.command_hosts:
            raise NotPermitted(
                f"{self.name}: {op}: host {self.arena.host!r} may not command vehicles "
                f"(security.command_hosts = {list(sec.command_hosts)}): the router drops its "
                "commands, setpoints and estops",
                result="NOT_PERMITTED",
                drone=self.name,
            )
        ops.check(op, args)  # the gateway takes what the table says, no more: an OpError names what is wrong
        cmd = wire.Command(op=op, args=args, src=self.arena.src, timeout=timeout, t=wire.now_ns())
        res = self.arena.bus.request(keys.cmd(self.name), cmd, timeout)
        if res.ok:
            self._catch_up(res.t)
            return res
        text = f"{self.name}: {op} {res.result}: {res.reason}".rstrip(": ")
        if res.result == "TIMEOUT" and not self.arena.is_alive(self.name):
            raise VehicleNotPresent(
                f"{self.name}: no gateway for this vehicle is alive on the bus",
                result=res.result,
                drone=self.name,
            )
        if res.result == "TIMEOUT":
            raise CommandTimeout(text, result=res.result, drone=self.name)
        if res.result == "REFUSED":
            raise SafetyRefused(text, result=res.result, drone=self.name)
        raise CommandRejected(text, result=res.result, drone=self.name)

    def arm(self, timeout: float = 5.0) -> None:
        """Arm the motors.

        A vehicle whose chosen mode is still OFFBOARD (after an offboard-loss failsafe landed it) would
        refuse to arm without a setpoint stream, so it is switched to hold first.
        """
        with self._cond:  # a fresh program may not have heard the vehicle's state yet
            self._cond.wait_for(lambda: self._state is not None, timeout=min(timeout, 2.0))
        if self.mode == FlightMode.OFFBOARD:
            self.command("hold", timeout)
        self.command("arm", timeout)
        self.wait_until(lambda v: v.armed, timeout, "armed")

    def disarm(self, timeout: float = 5.0) -> None:
        """Disarm (refused by the autopilot in the air; use :meth:`kill` for an emergency)."""
        self.command("disarm", timeout)
        self.wait_until(lambda v: not v.armed, timeout, "disarmed")

    def kill(self, timeout: float = 5.0) -> None:
        """Cut the motors now, in the air too (forced disarm)."""
        self.command("kill", timeout)

    def takeoff(
        self, height: float = 1.0, timeout: float = 30.0, tolerance: float = HEIGHT_TOLERANCE
    ) -> float:
        """Take off to ``height`` metres above the floor; return once arrived there (the height averaged
        over the last second within ``tolerance``: :mod:`arena_common.core.arrival`), with the seconds
        (arena time) it took from the command.

        PX4 v1.16 takes its time (docs/px4.md): ~4 s on the ground (motor spool-up, thrust ramp), then it
        reports Hold ``NAV_MC_ALT_RAD`` (0.8 m) short of the height and closes the rest slowly — about
        9.5 s for 1 m in SITL.  The simulated autopilot does the same (``ideal`` climbs at once).
        """
        clock = self.arena.clock
        started = clock.now()
        judge = Arrival((0.0, 0.0, -float(height)), tolerance, clock.wall(ARRIVAL_WINDOW), axes=(2,))
        self.command("takeoff", min(timeout, 10.0), height=float(height))
        self.wait_arrival(judge, clock.wall(timeout), f"height {height} m")
        took = clock.now() - started
        log.info("%s: took off to %.2f m in %.1f s", self.name, height, took)
        return took

    def land(self, timeout: float = 30.0, wait: bool = True) -> None:
        """Land where it is; with ``wait`` block until it is on the ground and disarmed."""
        self.command("land", min(timeout, 10.0))
        if wait:
            self.wait_until(
                lambda v: v.landed == LandedState.ON_GROUND and not v.armed,
                self.arena.clock.wall(timeout),
                "landed and disarmed",
            )

    def hold(self, timeout: float = 5.0) -> None:
        """Hold position (the autopilot's loiter)."""
        self.command("hold", timeout)

    def set_mode(self, mode: str, timeout: float = 5.0) -> None:
        """Switch flight mode by name or :class:`FlightMode` (POSCTL, AUTO.LOITER, OFFBOARD…), confirmed
        from the heartbeat.  OFFBOARD engages this program's newest open offboard block on the vehicle
        (one opened with ``engage=False``); any other mode ends every setpoint stream (docs/safety.md)."""
        if str(mode) == "OFFBOARD" and self._open_streams:
            self.command("mode", timeout, mode="OFFBOARD", stream=self._open_streams[-1])
        else:
            self.command("mode", timeout, mode=str(mode))

    def goto(
        self,
        north: float,
        east: float,
        down: float,
        yaw: float | None = None,
        tolerance: float = ARRIVAL_TOLERANCE,
        timeout: float = 30.0,
        duration: float | None = None,
    ) -> None:
        """Fly to a point of the arena (NED, metres) and wait until arrived: the position averaged over the
        last second within ``tolerance`` (:mod:`arena_common.core.arrival`); the gateway then holds it.

        Without ``duration`` the gateway flies there at its own speed (``goto_speed``).  With ``duration``
        (seconds of arena time) the vehicle follows a smooth minimum-jerk path that arrives then, streamed
        by this program under the gateway's safety checks, before the gateway takes over the hold.
        """
        target = (float(north), float(east), float(down))
        if duration is not None:
            start = self.position
            if start is None:
                raise VehicleNotPresent(
                    f"{self.name}: no position known; cannot plan a goto", drone=self.name
                )
            self.follow(Trajectory.min_jerk(start, target, duration, yaw=yaw))
        else:
            args: dict[str, Any] = {"p": list(target)}
            if yaw is not None:
                args["yaw"] = float(yaw)
            self.command("goto", min(timeout, 10.0), **args)
        clock = self.arena.clock
        judge = Arrival(target, tolerance, clock.wall(ARRIVAL_WINDOW))
        self.wait_arrival(judge, clock.wall(timeout), f"position {target}", holding="OFFBOARD")

    def follow(self, trajectory: Trajectory, rate: float = 30.0) -> None:
        """Fly ``trajectory`` (from its start, which should be near the vehicle) in an offboard block and
        hold its end point (the gateway's hold) afterwards."""
        problem = trajectory_problem(self, trajectory)
        if problem is not None:  # before offboard is engaged
            raise SafetyRefused(
                f"{self.name}: trajectory refused: {problem}", result="REFUSED", drone=self.name
            )
        end = trajectory.sample(trajectory.duration)
        with self.offboard(rate=rate) as ctl:
            ctl.follow(trajectory)
            ctl.handover(end.p, end.yaw)

    def offboard(self, rate: float = 20.0, lease: float = 0.5, engage: bool = True) -> OffboardStream:
        """A setpoint stream as a context manager (see :class:`OffboardStream`)."""
        return OffboardStream(self, rate, lease, engage)

    def __repr__(self) -> str:
        p = self.position
        where = "?" if p is None else f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})"
        return f"<Vehicle {self.name} {self.mode} {'armed' if self.armed else 'disarmed'} at {where}>"


def __getattr__(name: str) -> Any:
    # Arena and Swarm were defined in this module before the client was split by facet; programs that
    # import them from here keep working.
    if name == "Arena":
        from arena_common.client.arena import Arena

        return Arena
    if name == "Swarm":
        from arena_common.client.swarm import Swarm

        return Swarm
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
