"""Vehicles never meet: ``arena.min_separation`` between this gateway's vehicle and every other one.

The frame transform publishes every tracked vehicle's position and velocity in one message at 10 Hz
(``arena/sys/fleet``, :class:`~arena_common.core.wire.Fleet`); each gateway subscribes to that one key,
so the cost per vehicle stays fixed whatever the fleet's size.  With it:

- a ``goto`` whose goal — or whose straight path from the vehicle — comes within ``min_separation`` of
  another vehicle is refused, naming the other (:meth:`Separation.path_problem`);
- a setpoint whose position lies within it of another vehicle is refused the same way
  (:meth:`Separation.point_problem`);
- two vehicles closing in anyway (a velocity stream, the wander) are caught before they meet
  (:meth:`Separation.closing`): when this vehicle moves toward another and the gap between them shrinks
  fast enough that the braking path at that closing speed (PX4's Hold brakes over
  ``v·(v/(2·MPC_ACC_HOR) + delay)``, :data:`BRAKE_DELAY` as measured, plus the fleet message's age) would
  bring them within ``min_separation``, the gateway takes the vehicle and commands Hold, with an event
  naming the other.  Each gateway judges its own vehicle's motion toward the other: a vehicle hovering
  still is never the one held, and two flying side by side (no closing speed) are left alone.

A fleet older than :data:`FLEET_MAX_AGE` says nothing (no position of the others is then trusted, and
nothing is refused for it: a vehicle whose mocap stopped is landing by itself).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from arena_common.core import wire

__all__ = ["BRAKE_ACCEL", "FLEET_MAX_AGE", "Closing", "Separation"]

Vec3 = tuple[float, float, float]
FLEET_MAX_AGE = 1.0  # s since the last fleet message arrived: older, the others' positions are unknown
BRAKE_ACCEL = 3.0  # m/s²: PX4's MPC_ACC_HOR default, the deceleration of its Hold
BRAKE_DELAY = 1.2  # s: PX4 Hold brakes as late as 1.0 s in effect (38-47 cm from 0.45 m/s), + 0.2 s of load
MIN_CLOSING = 0.05  # m/s toward the other: slower is hovering (the wander), never held for
FLEET_PERIOD = 0.1  # s between fleet messages: how old the others' positions may be


@dataclass(frozen=True, slots=True)
class Closing:
    """This vehicle heading for another: who, how far, how fast toward it."""

    other: str
    distance: float
    speed: float
    stop_at: float  # distance left once braked to a stop

    def describe(self, min_separation: float) -> str:
        return (
            f"{self.other} {self.distance:.2f} m away, closing at {self.speed:.2f} m/s (would stop "
            f"{self.stop_at:.2f} m from it; min_separation {min_separation:.2f} m)"
        )


class Separation:
    """The other vehicles' latest positions and the separation rules for one vehicle (``name``)."""

    def __init__(self, name: str, min_separation: float) -> None:
        self.name = name
        self.min_separation = min_separation
        self._fleet: wire.Fleet | None = None  # the latest, kept as it came (no copy per message)
        self._received = -math.inf
        self.fleets = 0

    def update(self, fleet: wire.Fleet, now: float | None = None) -> None:
        """Take a fleet message (this vehicle's own entry is left out of the others)."""
        self._fleet, self._received = fleet, time.monotonic() if now is None else now
        self.fleets += 1

    def _current(self, now: float | None) -> wire.Fleet | None:
        fleet = self._fleet
        now = time.monotonic() if now is None else now
        return fleet if fleet is not None and now - self._received <= FLEET_MAX_AGE else None

    def others(self, now: float | None = None) -> dict[str, tuple[Vec3, Vec3]]:
        """The other vehicles' (position, velocity), or nothing when the fleet is stale."""
        fleet = self._current(now)
        if fleet is None:
            return {}
        return {e.n: (e.p, e.v) for e in fleet.b if e.n != self.name}

    def point_problem(self, p: Vec3, now: float | None = None) -> str | None:
        """Why a position ``p`` is too close to another vehicle, or None."""
        if self.min_separation <= 0.0:
            return None
        for other, (q, _) in sorted(self.others(now).items()):
            d = math.dist(p, q)
            if d < self.min_separation:
                return f"{d:.2f} m from {other} (min_separation {self.min_separation:.2f} m)"
        return None

    def path_problem(self, start: Vec3 | None, goal: Vec3, now: float | None = None) -> str | None:
        """Why the straight flight from ``start`` to ``goal`` comes too close to another vehicle, or None."""
        if self.min_separation <= 0.0:
            return None
        where = self.point_problem(goal, now)
        if where is not None:
            return f"the goal is {where}"
        if start is None:
            return None
        for other, (q, _) in sorted(self.others(now).items()):
            if math.dist(start, q) < self.min_separation:
                continue  # already close: flying away from it must stay possible
            d = _segment_distance(start, goal, q)
            if d < self.min_separation:
                return f"its path passes {d:.2f} m from {other} (min_separation {self.min_separation:.2f} m)"
        return None

    def closing(self, now: float | None = None) -> Closing | None:
        """The nearest other vehicle this one (as the same fleet message has it) would come within
        ``min_separation`` of before a Hold could stop it, or None.  Cheap when this vehicle hovers (the
        common case at any fleet size): nothing is judged below ``MIN_CLOSING``."""
        fleet = self._current(now)
        if self.min_separation <= 0.0 or fleet is None:
            return None
        own = next((e for e in fleet.b if e.n == self.name), None)
        if own is None:
            return None
        p, v = own.p, own.v
        if v[0] * v[0] + v[1] * v[1] + v[2] * v[2] < MIN_CLOSING * MIN_CLOSING:
            return None
        worst: Closing | None = None
        for e in fleet.b:
            if e is own:
                continue
            q, w = e.p, e.v
            d = math.dist(p, q)
            if d == 0.0:
                continue
            toward = ((q[0] - p[0]) * v[0] + (q[1] - p[1]) * v[1] + (q[2] - p[2]) * v[2]) / d
            if toward < MIN_CLOSING:
                continue
            coming = ((p[0] - q[0]) * w[0] + (p[1] - q[1]) * w[1] + (p[2] - q[2]) * w[2]) / d
            closing = toward + coming  # how fast the gap shrinks: 0 for two flying side by side
            if closing <= 0.0:
                continue
            stop_at = d - _braking(closing)  # both held: the gap shrinks by at most this much
            if stop_at < self.min_separation and (worst is None or stop_at < worst.stop_at):
                worst = Closing(e.n, d, closing, stop_at)
        return worst


def _braking(speed: float) -> float:
    """How far a vehicle at ``speed`` goes before PX4's Hold has stopped it (and the fleet is this old)."""
    return speed * (speed / (2.0 * BRAKE_ACCEL) + BRAKE_DELAY + FLEET_PERIOD)


def _segment_distance(a: Vec3, b: Vec3, q: Vec3) -> float:
    """Distance from point ``q`` to the segment ``a``–``b``."""
    ab = [b[i] - a[i] for i in range(3)]
    aq = [q[i] - a[i] for i in range(3)]
    n2 = sum(x * x for x in ab)
    k = 0.0 if n2 == 0.0 else max(0.0, min(1.0, sum(ab[i] * aq[i] for i in range(3)) / n2))
    return math.dist(q, tuple(a[i] + k * ab[i] for i in range(3)))
