"""Choose EKF2_EV_DELAY and the vision noise by measurement: fly PX4 SITL through the arena per setting.

    .venv/bin/python -m tests.px4.tune_vision                      # the default matrix, a table at the end
    .venv/bin/python -m tests.px4.tune_vision --delay 0 --delay 5 --noise 0.02 --repeat 2

Each point boots a fresh PX4 v1.16 SITL with the arena's parameters and the point's ``EKF2_EV_DELAY``
[ms] and ``EKF2_EVP_NOISE`` [m] (``EKF2_EVA_NOISE`` follows as noise × 2.5 rad/m, at least 0.05 rad),
flies the same pattern through the arena's unchanged pipeline (take off 1 m, hover, two gotos of 1 m,
hold) once PX4's TIMESYNC has converged (about 50 s after boot; ``--no-timesync``: at once), and measures
PX4's estimate against SIH's truth (:class:`~tests.px4.harness.FlightRecord`): the lag that best
explains the estimate, the estimate error while moving and holding, and how far the vehicle truly strays
from a point it holds.  ``docs/px4.md`` has the table this printed and why the arena sets
what it sets.
"""

from __future__ import annotations

import argparse
import itertools
import math
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from arena_common import Arena, ArenaError, CommandError
from arena_common.bus.session import BusOptions, open_bus
from arena_common.core.config import ZenohSpec
from arena_common.runtime.px4_sitl import is_true
from tests.conftest import free_port, wait_for
from tests.px4.harness import FlightRecord, InstancePool, px4_stack, wait_timesync_settled, write_px4_config

TARGETS = ((0.0, 0.0, -1.0), (0.0, 1.0, -1.0))  # arena NED, from a start at (-1, 0)


@dataclass
class Point:
    """The figures of one flight."""

    delay_ms: float
    noise_m: float
    lag_ms: float
    moving_p50_cm: float
    moving_max_cm: float
    hold_p50_cm: float
    hold_true_p50_cm: float
    hold_true_max_cm: float

    def row(self) -> str:
        return (
            f"| {self.delay_ms:g} | {self.noise_m:g} | {self.lag_ms:.0f} | {self.moving_p50_cm:.1f} / "
            f"{self.moving_max_cm:.1f} | {self.hold_p50_cm:.1f} | {self.hold_true_p50_cm:.1f} / "
            f"{self.hold_true_max_cm:.1f} |"
        )


HEADER = (
    "| EKF2_EV_DELAY ms | EKF2_EVP_NOISE m | estimate lag ms | estimate error moving p50 / max cm "
    "| estimate error holding p50 cm | true distance from the held point p50 / max cm |\n"
    "|---|---|---|---|---|---|"
)


def fly(
    delay_ms: float, noise_m: float, instance: int, workdir: Path, endpoint: str, timesync: bool = True
) -> Point:
    """One flight at one setting; with ``timesync``, once PX4 takes the gateway's vision stamps."""
    params = {
        "EKF2_EV_DELAY": float(delay_ms),
        "EKF2_EVP_NOISE": float(noise_m),
        "EKF2_EVA_NOISE": max(0.05, 2.5 * noise_m),
    }
    cfg = write_px4_config(
        workdir / "arena.toml", endpoint, {"d1": instance}, px4_params={"d1": params}, require_setup=False
    )
    with px4_stack(cfg, workdir) as stack, Arena(cfg, name="tune") as arena:
        d1 = arena.vehicle("d1")
        wait_for(
            lambda: bool(d1.state and d1.state.vis_fused),  # setup differs on purpose: the point's values
            timeout=90,
            interval=0.2,
            what="vision fused",
        )
        px4 = stack.px4["d1"]
        wait_for(
            lambda: is_true(px4.listener("vehicle_status"), "pre_flight_checks_pass"),
            timeout=60,
            interval=0.5,
            what="PX4's pre-flight checks to pass",
        )
        if timesync:
            wait_timesync_settled(px4)
        record = FlightRecord(arena, "d1")
        record.phase("ground")
        for attempt in range(3):  # PX4 may still say "horizontal position unstable" for a moment
            try:
                d1.arm()
                break
            except CommandError:
                if attempt == 2:
                    raise
                time.sleep(2.0)
        d1.takeoff(1.0, timeout=60)
        time.sleep(2.0)
        for i, target in enumerate(TARGETS):
            record.phase(f"move{i}")
            d1.goto(*target, yaw=0.0, tolerance=0.15, timeout=60)
        record.phase("hold")
        time.sleep(4.0)
        record.phase("land")
        hold = record.figure("hold")
        moving = [record.figure(f"move{i}") for i in range(len(TARGETS))]
        true_p50, true_max = record.excursion("hold", TARGETS[-1])
        lag, _ = record.lag()
        d1.land(timeout=90)
        if stack.dead():
            raise RuntimeError(f"processes died: {stack.dead()}")
    return Point(
        delay_ms,
        noise_m,
        lag * 1000,
        100 * max(m.horizontal_p50 for m in moving),
        100 * max(m.horizontal_max for m in moving),
        100 * math.hypot(hold.horizontal_p50, hold.vertical_p50),
        100 * true_p50,
        100 * true_max,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--delay", type=float, action="append", help="EKF2_EV_DELAY [ms] (repeatable)")
    ap.add_argument("--noise", type=float, action="append", help="EKF2_EVP_NOISE [m] (repeatable)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument(
        "--no-timesync",
        action="store_true",
        help="fly at once, before PX4's TIMESYNC converged (PX4 then stamps vision with its arrival time)",
    )
    ap.add_argument("--instances", type=int, nargs="+", default=[7, 8, 9], help="PX4 SITL instance numbers")
    args = ap.parse_args()
    delays = args.delay or [0.0, 20.0]
    noises = args.noise or [0.1, 0.02]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_bus(
        ZenohSpec(mode="router", connect=(), router_listen=(endpoint,)),
        BusOptions(settings={"connect/endpoints": []}),
    )
    pool = InstancePool(args.instances)
    rows: list[Point] = []
    try:
        for (delay, noise), _ in itertools.product(itertools.product(delays, noises), range(args.repeat)):
            n = pool.take()
            try:
                tmp = Path(tempfile.mkdtemp(prefix="tune-vision-"))
                try:
                    point = fly(delay, noise, n, tmp, endpoint, timesync=not args.no_timesync)
                except (ArenaError, AssertionError, RuntimeError) as exc:
                    print(f"| {delay:g} | {noise:g} | failed: {exc} (logs in {tmp}) |", flush=True)
                    continue
                shutil.rmtree(tmp, ignore_errors=True)  # kept, with every log, when the flight failed
            finally:
                pool.give_back(n)
            rows.append(point)
            print(point.row(), flush=True)
    finally:
        router.close()
    print("\n" + HEADER)
    for point in rows:
        print(point.row())


if __name__ == "__main__":
    main()
