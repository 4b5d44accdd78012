"""Three vehicles in formation: take off together, fly a triangle around the arena centre, turn it, land.

python examples/formation.py --config deploy/sim.toml --vehicles d1 d2 d3
"""

from __future__ import annotations

import argparse
import math

from arena_common import Arena


def slots(center: tuple[float, float], radius: float, angle: float, n: int) -> list[tuple[float, float]]:
    """North/east positions of ``n`` vehicles evenly spaced on a circle, rotated by ``angle``."""
    return [
        (
            center[0] + radius * math.cos(angle + 2 * math.pi * i / n),
            center[1] + radius * math.sin(angle + 2 * math.pi * i / n),
        )
        for i in range(n)
    ]


def main(arena: Arena, names: list[str], radius: float = 1.0, height: float = 1.0, turns: int = 3) -> None:
    """Take off all, hold a formation, rotate it in ``turns`` steps of 120° / turns, land all."""
    swarm = arena.swarm(names)
    swarm.run(lambda v: v.wait_until(lambda x: x.position is not None, timeout=10, what="first position"))
    swarm.arm()
    swarm.takeoff(height)
    # Who takes which slot: the assignment whose ways keep min_separation from the other vehicles (the
    # gateways refuse a goto that would not); the formation then turns with each vehicle in its slot.
    first = slots((0.0, 0.0), radius, 0.0, len(names))
    place = swarm.assign(first)
    index = {name: first.index(place[name]) for name in place}  # type: ignore[arg-type]
    for step in range(turns + 1):
        targets = slots((0.0, 0.0), radius, step * (2 * math.pi / 3) / turns, len(names))
        # One argument per vehicle, by name: every vehicle flies to its own slot at once.
        swarm.run(lambda v, t: v.goto(t[0], t[1], -height, yaw=0.0), {n: targets[index[n]] for n in names})
        print(f"formation step {step}: " + ", ".join(f"{v.name} {v.position}" for v in swarm))
    swarm.land()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", "-c", default="deploy/sim.toml")
    parser.add_argument("--connect", "-e", action="append", default=[])
    parser.add_argument("--vehicles", nargs="+", default=["d1", "d2", "d3"])
    args = parser.parse_args()
    with Arena(args.config, connect=args.connect) as a:
        main(a, args.vehicles)
