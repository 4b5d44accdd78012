"""Vehicles never meet (arena.min_separation): the rules on their own, then two simulated vehicles flown at
each other through their gateways, judged by their true positions."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

from arena_common import Arena, Trajectory
from arena_common.core import wire
from arena_common.core.errors import SafetyRefused
from arena_common.gateway.separation import Separation
from tests.helpers import wait_for
from tests.unit.gateway.test_gateway import Rig, rig_factory  # noqa: F401  (the make_rig fixture)


def _fleet(**where: tuple[tuple[float, float, float], tuple[float, float, float]]) -> wire.Fleet:
    return wire.Fleet(t=1, b=tuple(wire.FleetVehicle(n, p, v) for n, (p, v) in where.items()))


STILL = (0.0, 0.0, 0.0)


def test_points_and_paths_near_another_vehicle_are_refused_naming_it() -> None:
    sep = Separation("d1", 0.6)
    sep.update(_fleet(d1=((-1.0, 0.0, -1.0), STILL), d2=((0.0, 0.0, -1.0), STILL)), now=10.0)
    assert sep.point_problem((-0.5, 0.0, -1.0), now=10.0) == "0.50 m from d2 (min_separation 0.60 m)"
    assert sep.point_problem((-1.0, 0.5, -1.0), now=10.0) is None
    assert sep.path_problem((-1.0, 0.0, -1.0), (1.0, 0.0, -1.0), now=10.0) == (
        "its path passes 0.00 m from d2 (min_separation 0.60 m)"
    )
    assert sep.path_problem((-1.0, 0.0, -1.0), (-1.0, 1.0, -1.0), now=10.0) is None
    # A stale fleet says nothing: no position of the others is trusted.
    assert sep.point_problem((-0.5, 0.0, -1.0), now=11.5) is None


def test_closing_in_is_caught_before_the_braking_path_reaches_the_other() -> None:
    sep = Separation("d1", 0.6)
    # Hovering (the wander's few cm/s) beside another: never held.
    sep.update(_fleet(d1=((-1.0, 0.0, -1.0), (0.04, 0.0, 0.0)), d2=((0.0, 0.0, -1.0), STILL)), now=0.0)
    assert sep.closing(now=0.0) is None
    # Flying at it at 0.5 m/s from 1.5 m: it would stop 0.91 m short, no need yet; from 1.0 m it would not.
    sep.update(_fleet(d1=((-1.5, 0.0, -1.0), (0.5, 0.0, 0.0)), d2=((0.0, 0.0, -1.0), STILL)), now=0.0)
    assert sep.closing(now=0.0) is None
    sep.update(_fleet(d1=((-1.0, 0.0, -1.0), (0.5, 0.0, 0.0)), d2=((0.0, 0.0, -1.0), STILL)), now=0.0)
    c = sep.closing(now=0.0)
    assert c is not None and c.other == "d2" and c.distance == 1.0 and c.stop_at < 0.6
    # Two flying side by side (the same velocity): the gap does not shrink, never held.
    sep.update(
        _fleet(d1=((-1.0, 0.0, -1.0), (1.0, 0.0, 0.0)), d2=((0.4, 0.0, -1.0), (1.0, 0.0, 0.0))), now=0.0
    )
    assert sep.closing(now=0.0) is None
    # Head on, both at 0.5 m/s from 1.8 m: the gap shrinks at 1 m/s, too fast to stop in time.
    sep.update(
        _fleet(d1=((-1.0, 0.0, -1.0), (0.5, 0.0, 0.0)), d2=((0.8, 0.0, -1.0), (-0.5, 0.0, 0.0))), now=0.0
    )
    c = sep.closing(now=0.0)
    assert c is not None and c.speed == 1.0
    # Flying away from it: never held.
    sep.update(_fleet(d1=((-1.0, 0.0, -1.0), (-0.5, 0.0, 0.0)), d2=((-0.5, 0.0, -1.0), STILL)), now=0.0)
    assert sep.closing(now=0.0) is None


def test_two_vehicles_flown_at_each_other_never_meet(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(n_vehicles=2, speed=1.0)  # d1 at north -1, d2 at north 0; real time, as PX4 brakes
    sep = rig.cfg.arena.min_separation
    closest = [math.inf]
    stop = threading.Event()

    def watch() -> None:  # the true distance, as the mocap sees it, all along
        while not stop.wait(0.01):
            a, b = rig.aps["d1"].true_pose().position, rig.aps["d2"].true_pose().position
            if a[2] < -0.3 and b[2] < -0.3:
                closest[0] = min(closest[0], math.dist(a, b))

    with Arena(rig.cfg, name="separation-test") as arena:
        d1, d2 = arena.vehicle("d1"), arena.vehicle("d2")
        for v in (d1, d2):
            v.wait_until(lambda v: v.status is not None and v.status.vision_fused, 15.0, "vision fused")
            v.arm()
            v.takeoff(1.0)
        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        try:
            # A goto onto the other, or through it, is refused naming it; beside it is flown.
            try:
                d1.goto(-0.2, 0.0, -1.0)
                raise AssertionError("a goal 0.2 m from d2 was flown")
            except SafetyRefused as exc:
                assert "the goal is 0.2" in str(exc) and "m from d2" in str(exc) and "never meet" in str(exc)
            try:
                d1.goto(1.0, 0.0, -1.0)
                raise AssertionError("a path through d2 was flown")
            except SafetyRefused as exc:
                assert "its path passes" in str(exc) and "from d2" in str(exc)
            # A trajectory through d2 is refused before anything flies (the client knows the fleet too).
            here = d1.position
            assert here is not None
            wait_for(lambda: "d2" in arena.positions(), 5.0, what="the fleet's positions")
            try:
                d1.follow(Trajectory.min_jerk(here, (1.0, here[1], -1.0), 4.0))
                raise AssertionError("a trajectory through d2 was flown")
            except SafetyRefused as exc:
                assert "trajectory refused" in str(exc) and "from d2 (min_separation" in str(exc)
            assert d1.mode != "OFFBOARD"
            # A velocity stream straight at d2 (hovering): held before they meet, with an event.
            started = wire.now_ns()
            try:
                with d1.offboard() as ctl:
                    ctl.velocity(0.6, 0.0, 0.0)
                    time.sleep(3.0)
            except (SafetyRefused, Exception) as exc:  # the guard took the vehicle: the block says so
                assert "separation guard" in str(exc), exc
            wait_for(lambda: d1.mode == "AUTO.LOITER", 5.0, what="d1 held")
            held = [e for e in d1.events() if e.t >= started and "held before meeting d2" in e.text]
            assert held, [e.text for e in d1.events()[-5:]]
            time.sleep(2.0)  # the seconds after: still apart, still holding
            assert d1.mode == "AUTO.LOITER" and closest[0] >= sep, (
                closest[0],
                [e.text for e in d1.events()[-12:]],
            )
            # Both flown at each other at once.
            p1, p2 = d1.position, d2.position
            assert p1 is not None and p2 is not None
            d1.goto(p1[0], p1[1], -1.0, tolerance=0.3)
            d2.goto(p2[0] + 0.3, p2[1], -1.0, tolerance=0.3)

            def at_each_other(v: object, dn: float) -> None:
                try:
                    with v.offboard() as ctl:  # type: ignore[attr-defined]
                        ctl.velocity(dn, 0.0, 0.0)
                        time.sleep(3.0)
                except Exception as exc:  # the guard took it: expected
                    assert "separation guard" in str(exc), exc

            flights = [
                threading.Thread(target=at_each_other, args=(d1, 0.5)),
                threading.Thread(target=at_each_other, args=(d2, -0.5)),
            ]
            for t in flights:
                t.start()
            for t in flights:
                t.join(20.0)
            time.sleep(2.0)
            assert closest[0] >= sep, f"closest {closest[0]:.3f} m, min_separation {sep} m"
            assert not [e for e in d1.events() + d2.events() if e.kind == "failsafe"]
        finally:
            stop.set()
            watcher.join(2.0)
        for v in (d1, d2):
            v.land()
    print(f"\nclosest approach {closest[0]:.3f} m (min_separation {sep} m)")
