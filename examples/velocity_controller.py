"""A velocity controller written by the user on top of the mocap pose stream.

The program takes every new mocap pose (arena frame, full rate, in order, with its measurement time)
and answers it with a velocity setpoint from its own proportional law toward a target, with a speed
limit — the pattern for your own controllers.

    python examples/velocity_controller.py --config deploy/sim.toml --vehicle d1 --target 1.0 0.5 -1.0
"""

from __future__ import annotations

import argparse
import math

from arena_common import Arena


def main(
    arena: Arena,
    name: str = "d1",
    target: tuple[float, float, float] = (1.0, 0.5, -1.0),
    gain: float = 1.2,
    max_speed: float = 0.6,
    tolerance: float = 0.08,
    timeout: float = 30.0,
) -> float:
    """Fly to ``target`` with a P velocity law; return the final distance to it. Lands at the end."""
    drone = arena.vehicle(name)
    drone.wait_until(lambda v: v.position is not None, timeout=10, what="first position")
    drone.arm()
    drone.takeoff(-target[2])
    with drone.offboard(rate=30) as ctl:
        t_end = None
        for pose in drone.poses(timeout=1.0):  # every pose; StreamTimeout if the mocap goes silent
            t_end = t_end or pose.t + int(timeout * 1e9)  # measurement time: arena time of the pose
            if not pose.ok:
                ctl.velocity(0.0, 0.0, 0.0)  # not tracked: stop rather than guess
                continue
            err = [t - p for t, p in zip(target, pose.p, strict=True)]
            dist = math.sqrt(sum(e * e for e in err))
            if dist < tolerance or pose.t > t_end:
                break
            scale = min(1.0, max_speed / max(gain * dist, 1e-9))
            vn, ve, vd = (gain * e * scale for e in err)
            ctl.velocity(vn, ve, vd, yaw=0.0)
        ctl.handover(target, yaw=0.0)  # the gateway holds the target from here
    drone.wait_until(lambda v: math.dist(v.position or (math.inf,) * 3, target) < 0.2, 10, "at the target")
    final = math.dist(drone.position or (math.inf,) * 3, target)
    print(f"{name} reached {drone.position}, {final:.3f} m from the target")
    drone.land()
    return final


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", "-c", default="deploy/sim.toml")
    parser.add_argument("--connect", "-e", action="append", default=[])
    parser.add_argument("--vehicle", "-v", default="d1")
    parser.add_argument("--target", type=float, nargs=3, default=[1.0, 0.5, -1.0])
    args = parser.parse_args()
    with Arena(args.config, connect=args.connect) as a:
        main(a, args.vehicle, tuple(args.target))
