"""The asyncio facade: fly one vehicle while other coroutines watch its state, events and IMU.

python examples/async_monitor.py --config deploy/sim.toml --vehicle d1
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
from pathlib import Path
from typing import Any

from arena_common import AsyncArena, AsyncVehicle, Status


async def watch_states(drone: AsyncVehicle, modes: list[str]) -> None:
    """Record every flight-mode change, in order."""
    async with drone.states() as states:  # closed (unsubscribed) when the task is cancelled
        async for status in states:
            assert isinstance(status, Status)
            if not modes or modes[-1] != status.mode:
                modes.append(status.mode)


async def fly(drone: AsyncVehicle, height: float, hover_wall_s: float) -> None:
    """Arm, take off, hover in offboard (zero velocity) for ``hover_wall_s`` wall seconds, land."""
    await drone.arm()
    await drone.takeoff(height)
    async with drone.offboard() as ctl:
        ctl.velocity(0.0, 0.0, 0.0, yaw=0.0)
        await asyncio.sleep(hover_wall_s)
    await drone.land()


async def main(
    config: str | Path, vehicle: str = "d1", height: float = 0.8, hover_s: float = 2.0, **kw: Any
) -> list[str]:
    """Fly ``vehicle`` and return the flight modes it went through (``kw``: :class:`AsyncArena`'s)."""
    async with AsyncArena(config, **kw) as arena:
        name = vehicle
        drone = arena.vehicle(name)
        await drone.wait_until(lambda v: v.position is not None, timeout=10, what="first position")
        imu = await drone.telemetry("HIGHRES_IMU")
        print(f"{name}: accelerometer z {imu.f['zacc'] if imu else '?'} m/s² on the ground")
        modes: list[str] = []
        watcher = asyncio.create_task(watch_states(drone, modes))
        await fly(drone, height, arena.clock.wall(hover_s))
        watcher.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await watcher
        print(f"{name} flew through {' → '.join(modes)}")
        return modes


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", "-c", default="deploy/sim.toml")
    parser.add_argument("--connect", "-e", action="append", default=[])
    parser.add_argument("--vehicle", "-v", default="d1")
    args = parser.parse_args()
    asyncio.run(main(args.config, args.vehicle, connect=args.connect))
