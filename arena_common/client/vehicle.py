"""The user's side: an :class:`Arena` on the bus, one :class:`Vehicle` object per drone.

::

    from arena_common import Arena

    with Arena("deploy/sim.toml") as arena:
        d1 = arena.vehicle("d1")
        d1.arm()
        d1.takeoff(1.0)
        d1.goto(1.0, 0.5, -1.0, yaw=0.0)
        with d1.offboard() as ctl:          # a setpoint stream that owns its lease
            ctl.velocity(0.3, 0.0, 0.0)
            time.sleep(2.0)
        d1.land()

A vehicle's attributes (position, velocity, attitude, armed, mode, battery, mocap pose…) are kept fresh
by one background thread per :class:`Arena`; each has an age.  Methods block until the autopilot confirms
or raise a typed :class:`~arena_common.core.errors.CommandError` saying why.  If the program dies, its
setpoint leases lapse and the autopilot's offboard-loss failsafe lands the vehicle.
"""

from __future__ import annotations

import math
import os
import socket
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import TracebackType
from typing import Any

from arena_common.bus.hosts import host_bus_options, host_name
from arena_common.bus.session import Bus, BusOptions, Channel, Received, open_bus
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig, ZenohSpec
from arena_common.core.errors import (
    CommandError,
    CommandRejected,
    CommandTimeout,
    SafetyRefused,
    VehicleNotPresent,
)
from arena_common.geometry.frames import quat_to_euler


def _src() -> str:
    return f"{socket.gethostname()}/{os.getpid()}"


class Vehicle:
    """One drone on the bus.  Get it from :meth:`Arena.vehicle`."""

    def __init__(self, arena: Arena, name: str) -> None:
        self.name = keys.validate_name(name)
        self._arena = arena
        self._cond = threading.Condition()
        self._state: wire.State | None = None
        self._state_mono = 0.0
        self._pose: wire.Pose | None = None
        self._pose_mono = 0.0
        self._events: list[wire.Event] = []

    # -- fresh data -----------------------------------------------------------------------------------
    def _update(self, item: Received[Any]) -> None:
        kind = item.key.rsplit("/", 1)[-1]
        with self._cond:
            if kind == "state" and isinstance(item.payload, wire.State):
                self._state, self._state_mono = item.payload, time.monotonic()
            elif kind == "pose" and isinstance(item.payload, wire.Pose):
                self._pose, self._pose_mono = item.payload, time.monotonic()
            elif kind == "events" and isinstance(item.payload, wire.Event):
                self._events.append(item.payload)
                del self._events[:-100]
            self._cond.notify_all()

    @property
    def state(self) -> wire.State | None:
        """The latest :class:`~arena_common.core.wire.State` from the vehicle's gateway (None before any)."""
        return self._state

    @property
    def state_age(self) -> float:
        """Seconds since the last state arrived (inf before any)."""
        return time.monotonic() - self._state_mono if self._state else math.inf

    @property
    def mocap(self) -> wire.Pose | None:
        """The latest mocap pose in the arena frame, full rate (``arena/<drone>/pose``)."""
        return self._pose

    @property
    def mocap_age(self) -> float:
        """Seconds since the last mocap pose arrived (inf before any)."""
        return time.monotonic() - self._pose_mono if self._pose else math.inf

    @property
    def position(self) -> tuple[float, float, float] | None:
        """North, east, down [m]: the mocap pose when fresh, else the autopilot's estimate."""
        if self._pose is not None and self._pose.ok and self.mocap_age < 0.5:
            return self._pose.p
        return self._state.p if self._state else None

    @property
    def velocity(self) -> tuple[float, float, float] | None:
        """NED velocity [m/s]: the autopilot's estimate, else the mocap finite difference."""
        if self._state is not None and self._state.v is not None:
            return self._state.v
        return self._pose.v if self._pose is not None and self._pose.vok else None

    @property
    def attitude(self) -> tuple[float, float, float, float] | None:
        """Quaternion (w, x, y, z), body FRD to arena NED."""
        if self._pose is not None and self._pose.ok and self.mocap_age < 0.5:
            return self._pose.q
        return self._state.q if self._state else None

    @property
    def euler(self) -> tuple[float, float, float] | None:
        """(roll, pitch, yaw) in radians."""
        q = self.attitude
        return quat_to_euler(q) if q is not None else None

    @property
    def armed(self) -> bool:
        return bool(self._state and self._state.armed)

    @property
    def mode(self) -> str:
        return self._state.mode if self._state else "UNKNOWN"

    @property
    def landed(self) -> str:
        return self._state.landed if self._state else "undefined"

    @property
    def battery(self) -> float | None:
        return self._state.bat if self._state else None

    @property
    def link(self) -> bool:
        """True while the gateway reports heartbeats and its state is fresh."""
        return bool(self._state and self._state.link and self.state_age < 1.0)

    def events(self) -> list[wire.Event]:
        """The last (up to 100) events of this vehicle."""
        with self._cond:
            return list(self._events)

    def wait_until(self, predicate: Callable[[Vehicle], bool], timeout: float = 10.0, what: str = "") -> None:
        """Block until ``predicate(self)`` holds; :class:`CommandTimeout` after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate(self):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise CommandTimeout(
                        f"{self.name}: {what or 'condition'} not reached within {timeout:.1f} s",
                        result="TIMEOUT",
                        drone=self.name,
                    )
                self._cond.wait(min(left, 0.1))

    def _catch_up(self, t_ns: int, timeout: float = 1.0) -> None:
        """Wait (briefly) for a state the gateway stamped at or after ``t_ns`` (its clock): the attributes
        then show what a confirmed command did (``mode`` after :meth:`set_mode`…)."""
        if t_ns <= 0:
            return  # an answer without the gateway's time
        with self._cond:
            self._cond.wait_for(lambda: self._state is not None and self._state.t >= t_ns, timeout)

    # -- commands -----------------------------------------------------------------------------------
    def command(self, op: str, timeout: float = 5.0, **args: Any) -> wire.CommandResult:
        """Send a raw command to the gateway; raise a typed error unless it succeeded.

        It returns once the vehicle's attributes show the command's effect (a state the gateway stamped
        after its answer arrived, within a second), so ``mode`` reads the mode just confirmed.
        """
        cmd = wire.Command(op=op, args=args, src=self._arena.src, timeout=timeout, t=wire.now_ns())
        res = self._arena.bus.request(keys.cmd(self.name), cmd, timeout)
        if res.ok:
            self._catch_up(res.t)
            return res
        text = f"{self.name}: {op} {res.result}: {res.reason}".rstrip(": ")
        if res.result == "TIMEOUT" and not self._arena.is_alive(self.name):
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
        if self.mode == "OFFBOARD":
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

    def takeoff(self, height: float = 1.0, timeout: float = 20.0, tolerance: float = 0.15) -> None:
        """Take off to ``height`` metres above the floor and wait until there."""
        self.command("takeoff", min(timeout, 10.0), height=float(height))
        self.wait_until(
            lambda v: (p := v.position) is not None and -p[2] >= height - tolerance,
            timeout,
            f"height {height} m",
        )

    def land(self, timeout: float = 30.0, wait: bool = True) -> None:
        """Land where it is; with ``wait`` block until it is on the ground and disarmed."""
        self.command("land", min(timeout, 10.0))
        if wait:
            self.wait_until(lambda v: v.landed == "on_ground" and not v.armed, timeout, "landed and disarmed")

    def hold(self, timeout: float = 5.0) -> None:
        """Hold position (the autopilot's loiter)."""
        self.command("hold", timeout)

    def set_mode(self, mode: str, timeout: float = 5.0) -> None:
        """Switch flight mode by name (POSCTL, AUTO.LOITER, OFFBOARD…), confirmed from the heartbeat."""
        self.command("mode", timeout, mode=mode)

    def goto(
        self,
        north: float,
        east: float,
        down: float,
        yaw: float | None = None,
        tolerance: float = 0.1,
        timeout: float = 30.0,
    ) -> None:
        """Fly to a point of the arena (NED, metres) and wait until within ``tolerance``."""
        args: dict[str, Any] = {"p": [float(north), float(east), float(down)]}
        if yaw is not None:
            args["yaw"] = float(yaw)
        self.command("goto", min(timeout, 10.0), **args)
        target = (north, east, down)
        self.wait_until(
            lambda v: (p := v.position) is not None and math.dist(p, target) <= tolerance,
            timeout,
            f"position {target}",
        )

    def offboard(self, rate: float = 20.0, lease: float = 0.5, engage: bool = True) -> OffboardStream:
        """A setpoint stream as a context manager (see :class:`OffboardStream`)."""
        return OffboardStream(self, rate, lease, engage)

    def __repr__(self) -> str:
        p = self.position
        where = "?" if p is None else f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})"
        return f"<Vehicle {self.name} {self.mode} {'armed' if self.armed else 'disarmed'} at {where}>"


class OffboardStream:
    """Streams the latest setpoint at a steady rate from its own thread, whatever the user's loop does.

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
        self._target: wire.Setpoint | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pub = vehicle._arena.bus.stream_publisher(keys.setpoint(vehicle.name), wire.Setpoint)
        self.sent = 0

    def _set(self, **fields: Any) -> None:
        self._target = wire.Setpoint(t=wire.now_ns(), lease=self.lease, src=self.vehicle._arena.src, **fields)

    def position(
        self,
        north: float,
        east: float,
        down: float,
        yaw: float | None = None,
        velocity: Sequence[float] | None = None,
    ) -> None:
        """Hold a position (NED, m), optionally with yaw [rad] and a velocity feed-forward [m/s]."""
        v = tuple(float(x) for x in velocity) if velocity is not None else None
        self._set(p=(float(north), float(east), float(down)), v=v, yaw=yaw)

    def velocity(
        self, north: float, east: float, down: float, yaw: float | None = None, yaw_rate: float | None = None
    ) -> None:
        """Fly a velocity (NED, m/s) with a yaw [rad] or a yaw rate [rad/s]."""
        self._set(v=(float(north), float(east), float(down)), yaw=yaw, yr=yaw_rate)

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            target = self._target
            if target is not None:
                self._pub.put(target.replace(t=wire.now_ns()))
                self.sent += 1
            next_t += self.period
            delay = next_t - time.monotonic()
            if delay < -self.period:  # fell behind (suspended?): re-anchor rather than burst
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(max(delay, 0.0))

    def __enter__(self) -> OffboardStream:
        v = self.vehicle
        if self._target is None:
            p = v.position
            if p is None:
                raise VehicleNotPresent(
                    f"{v.name}: no position known; cannot start an offboard stream", drone=v.name
                )
            e = v.euler
            self.position(*p, yaw=e[2] if e else None)
        self._thread = threading.Thread(target=self._run, name=f"offboard:{v.name}", daemon=True)
        self._thread.start()
        if self.engage:
            try:
                time.sleep(max(3 * self.period, 0.3))  # the autopilot needs a stream before OFFBOARD
                v.set_mode("OFFBOARD")
            except BaseException:
                self.close()
                raise
        return self

    def close(self) -> None:
        """Stop streaming; the leases lapse."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self._pub.close()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            if self.vehicle.mode == "OFFBOARD":
                self.vehicle.hold()  # while our stream still runs: no gap for the failsafe to see
        except CommandError:
            if exc_type is None:
                raise
        finally:
            self.close()


class Swarm:
    """Several vehicles acting together: run the same action on all and wait for every one."""

    def __init__(self, vehicles: Iterable[Vehicle]) -> None:
        self.vehicles = list(vehicles)

    def run(self, action: Callable[[Vehicle], Any]) -> list[Any]:
        """Run ``action(vehicle)`` on every vehicle at once; raise the first error after all finished."""
        if not self.vehicles:
            return []
        with ThreadPoolExecutor(max_workers=len(self.vehicles)) as pool:
            futures = [pool.submit(action, v) for v in self.vehicles]
            results, errors = [], []
            for v, f in zip(self.vehicles, futures, strict=True):
                try:
                    results.append(f.result())
                except Exception as exc:
                    errors.append((v.name, exc))
        if errors:
            first = errors[0][1]
            names = ", ".join(f"{n}: {e}" for n, e in errors)
            if isinstance(first, CommandError):
                raise type(first)(f"swarm action failed for {names}", result=first.result) from first
            raise first
        return results

    def arm(self) -> None:
        self.run(lambda v: v.arm())

    def takeoff(self, height: float = 1.0) -> None:
        self.run(lambda v: v.takeoff(height))

    def land(self) -> None:
        self.run(lambda v: v.land())

    def hold(self) -> None:
        self.run(lambda v: v.hold())

    def __iter__(self) -> Any:
        return iter(self.vehicles)

    def __len__(self) -> int:
        return len(self.vehicles)


class Arena:
    """A connection to the arena's bus.  Use as a context manager (or call :meth:`close`).

    ``config`` is a config file path or :class:`~arena_common.core.config.ArenaConfig` (its Zenoh section
    says how to reach the bus); ``connect`` endpoints override it (``["tcp/192.168.1.20:7447"]``).
    ``host`` names this computer in the config (default: the hostname).  The session is a client of the
    router unless ``mode`` says otherwise.
    """

    def __init__(
        self,
        config: ArenaConfig | str | Path | None = None,
        *,
        connect: Sequence[str] = (),
        mode: str | None = None,
        bus: Bus | None = None,
        name: str = "",
        host: str | None = None,
    ) -> None:
        if isinstance(config, (str, Path)):
            config = config_mod.load(config)
        self.config = config
        self.src = name or _src()
        self._own_bus = bus is None
        # A client of the router by default: the router knows every service's presence at once, while a
        # peer learns it link by link; user programs gain nothing from direct links.
        options = host_bus_options(
            config, host_name(host), BusOptions(mode=mode or "client", connect=tuple(connect))
        )
        self.bus = bus or open_bus(config.zenoh if config else ZenohSpec(), options)
        self._vehicles: dict[str, Vehicle] = {}
        self._channel: Channel[Received[Any]] = Channel(4096, ring=True)
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._pump, name="arena-client", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        while not self._closed.is_set():
            item = self._channel.get(0.2)
            if item is None or item.payload is None:
                continue
            parts = item.key.split("/")
            v = self._vehicles.get(parts[1]) if len(parts) > 2 else None
            if v is not None:
                v._update(item)

    def vehicle(self, name: str) -> Vehicle:
        """The :class:`Vehicle` object of ``name`` (one per name; created on first use)."""
        with self._lock:
            v = self._vehicles.get(name)
            if v is None:
                v = Vehicle(self, name)
                self._vehicles[name] = v
                for leaf in ("state", "pose", "events"):
                    self.bus.subscribe(f"arena/{v.name}/{leaf}", channel=self._channel)
            return v

    def vehicles(self, timeout: float = 1.0) -> list[str]:
        """Names of the vehicles whose gateway is alive on the bus right now."""
        names = set()
        for key in self.bus.alive(keys.ALIVE_ALL, timeout):
            service = key.rsplit("/", 1)[-1]
            if service.startswith("gateway."):
                names.add(service[len("gateway.") :])
        return sorted(names)

    def is_alive(self, name: str) -> bool:
        """True when a gateway for ``name`` holds its presence token."""
        return bool(self.bus.alive(f"arena/sys/alive/*/gateway.{name}", 0.5))

    def swarm(self, names: Iterable[str] | None = None) -> Swarm:
        """A :class:`Swarm` of the named vehicles (default: every vehicle alive now)."""
        return Swarm(self.vehicle(n) for n in (names if names is not None else self.vehicles()))

    def estop(self, kill: bool = False, reason: str = "") -> None:
        """Stop everything: every gateway lands its vehicle at once (or cuts the motors with ``kill``)."""
        self.bus.put(keys.ESTOP, wire.Estop(t=wire.now_ns(), kill=kill, reason=reason, src=self.src))

    def close(self) -> None:
        """Stop the background thread and close the bus (if this object opened it)."""
        self._closed.set()
        self._thread.join(2.0)
        if self._own_bus:
            self.bus.close()

    def __enter__(self) -> Arena:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
