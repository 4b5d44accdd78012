"""Fly a square as one smooth trajectory: timed corners, streamed with position, velocity and
acceleration feed-forward; then land where it started.

python examples/square.py --config deploy/sim.toml --vehicle d1 --side 1.0
"""

from __future__ import annotations

import argparse

from arena_common import Arena, Trajectory


def main(arena: Arena, name: str = "d1", side: float = 1.0, height: float = 1.0, leg_s: float = 3.0) -> None:
    """Fly a square of ``side`` metres from the take-off point, ``leg_s`` seconds a side, then land."""
    drone = arena.vehicle(name)
    drone.wait_until(lambda v: v.position is not None, timeout=10, what="first position")
    drone.arm()
    drone.takeoff(height)
    n0, e0, _ = drone.position or (0.0, 0.0, 0.0)
    down = -height
    corners = [(n0, e0), (n0 + side, e0), (n0 + side, e0 + side), (n0, e0 + side), (n0, e0)]
    square = Trajectory.waypoints([(i * leg_s, (n, e, down)) for i, (n, e) in enumerate(corners)], yaw=0.0)
    drone.follow(square)  # refused before anything flies if some point broke the arena's limits
    drone.wait_until(lambda v: v.position is not None and abs(v.position[0] - n0) < 0.15, 10, what="back")
    print(f"{name} back at {drone.position} after {square.duration:.0f} s")
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
