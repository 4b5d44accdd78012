"""The asyncio facade: the same machinery, awaitable.

::

    import asyncio
    from arena_common import AsyncArena

    async def main() -> None:
        async with AsyncArena("deploy/sim.toml") as arena:
            d1 = arena.vehicle("d1")
            await d1.arm()
            await d1.takeoff(1.0)
            async for pose in d1.poses():
                ...
            await d1.land()

    asyncio.run(main())

:class:`AsyncArena` wraps an :class:`~arena_common.client.arena.Arena` and :class:`AsyncVehicle` a
:class:`~arena_common.client.vehicle.Vehicle`: attributes are the same objects, read without waiting;
blocking calls (commands, waits) run in a worker thread (``asyncio.to_thread``) so the event loop goes on;
streams are fed into an ``asyncio.Queue`` from the arena's client thread.
"""

from __future__ import annotations

import asyncio
import collections
from collections.abc import AsyncIterator, Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, Generic, TypeVar

from arena_common.client.arena import Arena
from arena_common.client.offboard import OffboardStream
from arena_common.client.streams import Callback, StreamTimeout, Topic
from arena_common.client.trajectory import Trajectory
from arena_common.client.vehicle import Vehicle
from arena_common.core import wire
from arena_common.core.config import ArenaConfig

__all__ = ["AsyncArena", "AsyncOffboard", "AsyncStream", "AsyncVehicle"]

T = TypeVar("T")


class AsyncStream(Generic[T]):
    """An async iterator over the new items of one topic (``async for pose in d1.poses()``).

    Bounded: a slow reader loses the oldest items (counted in :attr:`dropped`).  ``timeout`` bounds each
    wait (:class:`~arena_common.client.streams.StreamTimeout`).  Iteration ends on :meth:`close` or when
    the arena closes.
    """

    def __init__(self, topic: Topic[T], capacity: int = 1024, timeout: float | None = None) -> None:
        self.topic = topic
        self.timeout = timeout
        self.capacity = capacity
        self.dropped = 0
        self._loop = asyncio.get_running_loop()
        self._items: collections.deque[T] = collections.deque()
        self._event = asyncio.Event()
        self._closed = False
        self._cb: Callback = topic.on(self._from_thread)
        topic.on_close(self._closed_from_thread)

    def _closed_from_thread(self) -> None:
        try:
            self._loop.call_soon_threadsafe(self._finish)
        except RuntimeError:  # the event loop is gone already
            pass

    def _from_thread(self, item: T) -> None:
        if not self._closed:
            try:
                self._loop.call_soon_threadsafe(self._put, item)
            except RuntimeError:  # the event loop closed without closing this stream
                self._cb.cancel()

    def _put(self, item: T) -> None:
        if self._closed:
            return
        if len(self._items) >= self.capacity:
            self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self._event.set()

    def _finish(self) -> None:
        self._closed = True
        self._event.set()

    def __aiter__(self) -> AsyncIterator[T]:
        return self

    async def __anext__(self) -> T:
        while not self._items:
            if self._closed:
                raise StopAsyncIteration
            self._event.clear()
            try:
                await asyncio.wait_for(self._event.wait(), self.timeout)
            except TimeoutError:
                raise StreamTimeout(f"{self.topic.name}: nothing new within {self.timeout:.1f} s") from None
        return self._items.popleft()

    def close(self) -> None:
        """Stop receiving."""
        self._cb.cancel()
        self._finish()

    async def __aenter__(self) -> AsyncStream[T]:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


class AsyncOffboard:
    """An :class:`~arena_common.client.offboard.OffboardStream` as an async context manager; setpoint
    methods are the same (they do not block), :meth:`follow` and :meth:`handover` are awaited."""

    def __init__(self, stream: OffboardStream) -> None:
        self.stream = stream

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stream, name)

    async def follow(self, trajectory: Trajectory, yaw: float | None = None) -> None:
        """Fly ``trajectory`` and return when it has ended."""
        await asyncio.to_thread(self.stream.follow, trajectory, True, yaw)

    async def handover(self, goal: Sequence[float], yaw: float | None = None) -> None:
        """Let the gateway hold ``goal`` (see :meth:`OffboardStream.handover`)."""
        await asyncio.to_thread(self.stream.handover, goal, yaw)

    async def __aenter__(self) -> AsyncOffboard:
        await asyncio.to_thread(self.stream.__enter__)
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await asyncio.to_thread(self.stream.__exit__, *exc)


class AsyncVehicle:
    """A :class:`~arena_common.client.vehicle.Vehicle` for asyncio: attributes as they are, commands
    awaited, streams as async iterators."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.sync = vehicle
        self.name = vehicle.name

    def __getattr__(self, name: str) -> Any:
        # Readings (position, mode, mocap_pose, estimate, imu, params facet…) are the sync object's.
        return getattr(self.sync, name)

    async def _call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        return await asyncio.to_thread(fn, *args, **kwargs)

    async def arm(self, timeout: float = 5.0) -> None:
        """Arm the motors (see :meth:`Vehicle.arm`)."""
        await self._call(self.sync.arm, timeout)

    async def disarm(self, timeout: float = 5.0) -> None:
        """Disarm (see :meth:`Vehicle.disarm`)."""
        await self._call(self.sync.disarm, timeout)

    async def kill(self, timeout: float = 5.0) -> None:
        """Cut the motors now (see :meth:`Vehicle.kill`)."""
        await self._call(self.sync.kill, timeout)

    async def takeoff(self, height: float = 1.0, timeout: float = 20.0) -> None:
        """Take off to ``height`` m and wait until there."""
        await self._call(self.sync.takeoff, height, timeout)

    async def land(self, timeout: float = 30.0, wait: bool = True) -> None:
        """Land where it is (and wait until landed and disarmed)."""
        await self._call(self.sync.land, timeout, wait)

    async def hold(self, timeout: float = 5.0) -> None:
        """Hold position."""
        await self._call(self.sync.hold, timeout)

    async def set_mode(self, mode: str, timeout: float = 5.0) -> None:
        """Switch flight mode (see :meth:`Vehicle.set_mode`)."""
        await self._call(self.sync.set_mode, mode, timeout)

    async def goto(self, north: float, east: float, down: float, **kwargs: Any) -> None:
        """Fly to a point and wait until there (see :meth:`Vehicle.goto`)."""
        await self._call(self.sync.goto, north, east, down, **kwargs)

    async def follow(self, trajectory: Trajectory, rate: float = 30.0) -> None:
        """Fly a trajectory and hold its end (see :meth:`Vehicle.follow`)."""
        await self._call(self.sync.follow, trajectory, rate)

    async def command(self, op: str, timeout: float = 5.0, **args: Any) -> wire.CommandResult:
        """A raw gateway command (see :meth:`Vehicle.command`)."""
        res: wire.CommandResult = await self._call(self.sync.command, op, timeout, **args)
        return res

    async def wait_until(
        self, predicate: Callable[[Vehicle], bool], timeout: float = 10.0, what: str = ""
    ) -> None:
        """Wait until ``predicate(vehicle)`` holds (see :meth:`Vehicle.wait_until`)."""
        await self._call(self.sync.wait_until, predicate, timeout, what)

    async def get_param(self, name: str, timeout: float = 5.0) -> int | float:
        """A parameter's value (see :class:`~arena_common.client.params.Params`)."""
        value: int | float = await self._call(self.sync.params.get, name, timeout)
        return value

    async def set_param(self, name: str, value: float, timeout: float = 5.0) -> int | float:
        """Write a parameter; the confirmed value."""
        back: int | float = await self._call(self.sync.params.set, name, value, timeout)
        return back

    async def telemetry(self, name: str, timeout: float = 2.0) -> wire.Telemetry | None:
        """The latest raw message ``name`` (waiting up to ``timeout`` s for a first)."""
        tm: wire.Telemetry | None = await self._call(self.sync.telemetry, name, timeout)
        return tm

    def offboard(self, rate: float = 20.0, lease: float = 0.5, engage: bool = True) -> AsyncOffboard:
        """``async with d1.offboard() as ctl:`` (see :class:`OffboardStream`)."""
        return AsyncOffboard(self.sync.offboard(rate, lease, engage))

    def poses(self, timeout: float | None = None, capacity: int = 1024) -> AsyncStream[wire.Pose]:
        """Every new mocap pose, in order."""
        return AsyncStream(self.sync.pose_topic, capacity, timeout)

    def vision(self, timeout: float | None = None, capacity: int = 1024) -> AsyncStream[wire.Pose]:
        """Every pose sent as vision, in order."""
        return AsyncStream(self.sync.vision_topic, capacity, timeout)

    def states(self, timeout: float | None = None, capacity: int = 1024) -> AsyncStream[Any]:
        """Every new typed state, in order."""
        return AsyncStream(self.sync.state_topic, capacity, timeout)

    def event_stream(self, timeout: float | None = None, capacity: int = 1024) -> AsyncStream[wire.Event]:
        """Every new event, in order."""
        return AsyncStream(self.sync.event_topic, capacity, timeout)

    def imu_stream(self, timeout: float | None = None, capacity: int = 1024) -> AsyncStream[Any]:
        """Every new IMU reading, in order."""
        return AsyncStream(self.sync.imu_topic, capacity, timeout)

    def battery_stream(self, timeout: float | None = None, capacity: int = 1024) -> AsyncStream[Any]:
        """Every new battery reading, in order."""
        return AsyncStream(self.sync.battery_topic, capacity, timeout)

    def estimator_stream(self, timeout: float | None = None, capacity: int = 1024) -> AsyncStream[Any]:
        """Every new estimator status, in order."""
        return AsyncStream(self.sync.estimator_topic, capacity, timeout)

    def telemetry_stream(
        self, name: str, timeout: float | None = None, capacity: int = 1024
    ) -> AsyncStream[wire.Telemetry]:
        """Every new raw message ``name``, in order."""
        return AsyncStream(self.sync.telemetry.topic(name), capacity, timeout)

    def __repr__(self) -> str:
        return f"<Async{self.sync!r}"[:-1] + ">"


class AsyncArena:
    """An :class:`~arena_common.client.arena.Arena` for asyncio: ``async with AsyncArena(…) as arena``.

    Same arguments as :class:`Arena`; opening the session runs in a worker thread.
    """

    def __init__(self, config: ArenaConfig | str | Path | None = None, **kwargs: Any) -> None:
        self._args = (config, kwargs)
        self.sync: Arena | None = None
        self._vehicles: dict[str, AsyncVehicle] = {}

    async def open(self) -> AsyncArena:
        """Open the connection (``async with`` does it)."""
        config, kwargs = self._args
        self.sync = await asyncio.to_thread(lambda: Arena(config, **kwargs))
        return self

    def _arena(self) -> Arena:
        if self.sync is None:
            raise RuntimeError("AsyncArena is not open: use `async with AsyncArena(...) as arena`")
        return self.sync

    def vehicle(self, name: str) -> AsyncVehicle:
        """The :class:`AsyncVehicle` of ``name`` (fails at once on an unknown name, as :meth:`Arena.vehicle`)."""
        v = self._vehicles.get(name)
        if v is None:
            v = self._vehicles[name] = AsyncVehicle(self._arena().vehicle(name))
        return v

    async def vehicles(self, timeout: float = 1.0) -> list[str]:
        """Names of the vehicles whose gateway is alive now."""
        names: list[str] = await asyncio.to_thread(self._arena().vehicles, timeout)
        return names

    async def run(self, names: Iterable[str], action: Callable[[AsyncVehicle], Any]) -> list[Any]:
        """Await ``action(vehicle)`` for every named vehicle at once (asyncio.gather)."""
        return list(await asyncio.gather(*(action(self.vehicle(n)) for n in names)))

    @property
    def clock(self) -> Any:
        """The arena's clock (see :class:`~arena_common.client.clock.ArenaClock`); sleep with
        :meth:`sleep` in coroutines."""
        return self._arena().clock

    async def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of arena time without blocking the event loop."""
        await asyncio.sleep(self._arena().clock.wall(seconds))

    def estop(self, kill: bool = False, reason: str = "") -> None:
        """Stop everything (see :meth:`Arena.estop`)."""
        self._arena().estop(kill, reason)

    async def close(self) -> None:
        """Close the connection."""
        if self.sync is not None:
            await asyncio.to_thread(self.sync.close)
            self.sync = None

    async def __aenter__(self) -> AsyncArena:
        return await self.open()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
