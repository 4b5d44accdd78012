"""Hover and land: the smallest arena program.

python examples/hover_land.py --config deploy/sim.toml --vehicle d1
"""

from __future__ import annotations

import argparse
import time

from arena_common import Arena


def main(arena: Arena, name: str = "d1", height: float = 1.0, hover_s: float = 3.0) -> None:
    """Arm, take off to ``height``, hover for ``hover_s`` seconds, land."""
    drone = arena.vehicle(name)
    drone.wait_until(lambda v: v.state is not None, timeout=10, what="first state")
    drone.arm()
    drone.takeoff(height)
    time.sleep(hover_s)
    print(f"{name} hovering at {drone.position}")
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
