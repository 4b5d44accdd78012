"""Vehicles never meet: ``arena.min_separation`` between this gateway's vehicle and every other one.

The frame transform publishes every tracked vehicle's position and velocity in one message at 10 Hz
(``arena/sys/fleet``, :class:`~arena_common.core.wire.Fleet`); each gateway subscribes to that one key,
so the cost per vehicle stays fixed whatever the fleet's size.  With it:

- a ``goto`` whose goal — or whose straight path from the vehicle — comes within ``min_separation`` of
  another vehicle is refused, naming the other (:meth:`Separation.path_problem`);
- a setpoint whose position lies within it of another vehicle is refused the same way
  (:meth:`Separation.point_problem`);
- two vehicles closing in anyway (a velocity stream, the wander) are caught before they meet
  (:meth:`Separation.closing`): when this vehicle moves toward another and, on their present courses,
  the two would come within ``min_separation`` before a Hold could stop them (the time PX4's Hold takes
  to brake, ``v/(2·MPC_ACC_HOR) + delay`` at their relative speed, :data:`BRAKE_DELAY` as measured, plus
  the fleet message's age), the gateway takes the vehicle and commands Hold, with an event naming the
  other.  Two vehicles passing each other wide, or turning in formation, are not closing in.  Each
  gateway judges its own vehicle's motion toward the other: a vehicle hovering
  (its wander, below :data:`WANDER_SPEED`) is held only once inside ``min_separation``, and two flying
  side by side (no closing speed) are left alone.

A fleet older than :data:`FLEET_MAX_AGE` says nothing (no position of the others is then trusted, and
nothing is refused for it: a vehicle whose mocap stopped is landing by itself).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from arena_common.core import wire
from arena_common.geometry.segments import segment_distance

__all__ = ["BRAKE_ACCEL", "FLEET_MAX_AGE", "Closing", "Separation"]

Vec3 = tuple[float, float, float]
FLEET_MAX_AGE = 1.0  # s since the last fleet message arrived: older, the others' positions are unknown
BRAKE_ACCEL = 3.0  # m/s²: PX4's MPC_ACC_HOR default, the deceleration of its Hold
BRAKE_DELAY = 1.2  # s: PX4 Hold brakes as late as 1.0 s in effect (38-47 cm from 0.45 m/s), + 0.2 s of load
MIN_CLOSING = 0.05  # m/s toward the other: slower is hovering still, never held for
#: m/s of own speed toward the other below which only entering min_separation is held for: PX4's hover
#: wanders at 0.1-0.2 m/s (docs/px4.md), and holding a wandering vehicle in Hold changes nothing (Hold
#: wanders alike); spacing keeps wandering vehicles apart (arena demo: min_separation + two swings).
WANDER_SPEED = 0.25
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
            f"{self.other} {self.distance:.2f} m away, closing at {self.speed:.2f} m/s (would come "
            f"{self.stop_at:.2f} m near before a Hold stops them; min_separation {min_separation:.2f} m)"
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
            d = segment_distance(start, goal, q)
            if d < self.min_separation:
                return f"its path passes {d:.2f} m from {other} (min_separation {self.min_separation:.2f} m)"
        return None

    def closing(
        self, now: float | None = None, commanded: Vec3 | None = None, travel_left: float | None = None
    ) -> Closing | None:
        """The nearest other vehicle this one (as the same fleet message has it) would come within
        ``min_separation`` of before a Hold could stop it, or None.

        ``commanded``: the velocity a stream commands this vehicle, used when faster than the measured
        one (a vehicle still accelerating toward it); ``travel_left``: how far the gateway's goto still
        flies it (it stops at its goal: no further course is predicted).  Cheap when this vehicle hovers
        (the common case at any fleet size): nothing is judged below ``MIN_CLOSING``."""
        fleet = self._current(now)
        if self.min_separation <= 0.0 or fleet is None:
            return None
        own = next((e for e in fleet.b if e.n == self.name), None)
        if own is None:
            return None
        p, v = own.p, own.v
        speed2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        if commanded is not None and sum(c * c for c in commanded) > speed2:
            v, speed2 = commanded, sum(c * c for c in commanded)
        if speed2 < MIN_CLOSING * MIN_CLOSING:
            return None
        cap = math.inf if travel_left is None else travel_left / math.sqrt(speed2)
        worst: Closing | None = None
        for e in fleet.b:
            if e is own:
                continue
            q, w = e.p, e.v
            d = math.dist(p, q)
            if d == 0.0:
                continue
            toward = ((q[0] - p[0]) * v[0] + (q[1] - p[1]) * v[1] + (q[2] - p[2]) * v[2]) / d
            if toward < MIN_CLOSING or (toward < WANDER_SPEED and d >= self.min_separation):
                continue
            r = (q[0] - p[0], q[1] - p[1], q[2] - p[2])  # the other, seen from here
            u = (w[0] - v[0], w[1] - v[1], w[2] - v[2])  # its velocity relative to ours
            ru, uu = r[0] * u[0] + r[1] * u[1] + r[2] * u[2], u[0] * u[0] + u[1] * u[1] + u[2] * u[2]
            if ru >= 0.0:
                continue  # the gap does not shrink: side by side, or parting
            # The closest the two come on their present courses within the time a Hold takes to stop.
            t = min(-ru / uu, _stopping_time(math.sqrt(uu)), cap)
            stop_at = math.dist(r, (-u[0] * t, -u[1] * t, -u[2] * t))
            if stop_at < self.min_separation and (worst is None or stop_at < worst.stop_at):
                worst = Closing(e.n, d, -ru / d, stop_at)
        return worst


def _stopping_time(speed: float) -> float:
    """How long, flown at ``speed``, covers what a vehicle goes before PX4's Hold has stopped it (and the
    fleet message is this old): ``speed · t`` is the braking path ``v·(v/(2·a) + delay)``."""
    return speed / (2.0 * BRAKE_ACCEL) + BRAKE_DELAY + FLEET_PERIOD
