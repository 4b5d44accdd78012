"""Hover and land: the smallest arena program.

python examples/hover_land.py --config deploy/sim.toml --vehicle d1
"""

from __future__ import annotations

import argparse

from arena_common import Arena


def main(arena: Arena, name: str = "d1", height: float = 1.0, hover_s: float = 3.0) -> None:
    """Arm, take off to ``height``, hover for ``hover_s`` seconds (arena time), land."""
    drone = arena.vehicle(name)
    drone.wait_until(lambda v: v.status is not None, timeout=10, what="first state")
    drone.arm()
    drone.takeoff(height)
    arena.clock.sleep(hover_s)  # arena time: shorter in a simulation that runs faster than real time
    battery = drone.battery
    print(
        f"{name} hovering at {drone.position} (from {drone.position_source}), mode {drone.mode}, "
        f"battery {battery.remaining if battery else '?'}"
    )
    drone.land()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", "-c", default="deploy/sim.toml")
    parser.add_argument("--connect", "-e", action="append", default=[])
    parser.add_argument("--vehicle", "-v", default="d1")
    parser.add_argument("--height", type=float, default=1.0)
    args = parser.parse_args()
    with Arena(args.config, connect=args.connect) as a:
        main(a, args.vehicle, args.height)
