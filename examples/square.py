"""Fly a square: take off, visit four corners with goto, come back, land.

python examples/square.py --config deploy/sim.toml --vehicle d1 --side 1.0
"""

from __future__ import annotations

import argparse

from arena_common import Arena


def main(arena: Arena, name: str = "d1", side: float = 1.0, height: float = 1.0) -> None:
    """Fly a square of ``side`` metres around the take-off point, at ``height``, then land there."""
    drone = arena.vehicle(name)
    drone.wait_until(lambda v: v.position is not None, timeout=10, what="first position")
    n0, e0, _ = drone.position or (0.0, 0.0, 0.0)
    drone.arm()
    drone.takeoff(height)
    down = -height
    for dn, de in ((side, 0.0), (side, side), (0.0, side), (0.0, 0.0)):
        drone.goto(n0 + dn, e0 + de, down, yaw=0.0, tolerance=0.15)
        print(f"{name} at corner {drone.position}")
    drone.land()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", "-c", default="deploy/sim.toml")
    parser.add_argument("--connect", "-e", action="append", default=[])
    parser.add_argument("--vehicle", "-v", default="d1")
    parser.add_argument("--side", type=float, default=1.0)
    args = parser.parse_args()
    with Arena(args.config, connect=args.connect) as a:
        main(a, args.vehicle, args.side)
