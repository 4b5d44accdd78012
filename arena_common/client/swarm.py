"""Several vehicles acting together: :class:`Swarm`, from :meth:`Arena.swarm
<arena_common.client.arena.Arena.swarm>`.

::

    swarm = arena.swarm(["d1", "d2", "d3"])
    swarm.arm()
    swarm.takeoff(1.0)
    swarm.run(lambda v, p: v.goto(*p), [(1, 0, -1), (0, 1, -1), (-1, 0, -1)])   # one argument each
    swarm.run(lambda v, p: v.goto(*p), {"d1": (1, 0, -1), "d2": (0, 1, -1), "d3": (-1, 0, -1)})
    swarm.goto(swarm.assign([(1, 0, -1), (0, 1, -1), (-1, 0, -1)]))   # who goes where: clear ways
    swarm.land()
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from arena_common.core.errors import CommandError
from arena_common.geometry.segments import segment_distance

if TYPE_CHECKING:
    from arena_common.client.vehicle import Vehicle

__all__ = ["WANDER_MARGIN", "Swarm", "clear_assignment"]

WANDER_MARGIN = 0.2  # m kept beyond min_separation when planning ways: the hover's wander on the way
MAX_PERMUTED = 7  # vehicles up to which every assignment is tried (7! = 5040); beyond, nearest first
Point = Sequence[float]


def clear_assignment(
    here: Mapping[str, Point], targets: Sequence[Point], keep: float
) -> dict[str, Point] | None:
    """Which vehicle flies to which target (north, east[, down]; compared on north and east) such that
    each one's straight way from ``here`` keeps ``keep`` from every other vehicle, where it is and where
    it goes; of those, the shortest ways in all.  None when no assignment is clear.

    The gateways refuse a goto whose goal or path comes within ``arena.min_separation`` of another
    vehicle: an assignment found here with ``keep`` = ``min_separation`` + :data:`WANDER_MARGIN` is not.
    """
    names = list(here)
    if len(targets) != len(names):
        raise ValueError(f"{len(targets)} targets for {len(names)} vehicles")
    best: tuple[float, dict[str, Point]] | None = None
    orders: Iterable[tuple[int, ...]]
    if len(names) <= MAX_PERMUTED:
        orders = itertools.permutations(range(len(names)))
    else:  # greedy: each vehicle, in turn, the nearest free target
        free, nearest = list(range(len(targets))), []
        for n in names:
            k = min(free, key=lambda i: math.dist(here[n][:2], targets[i][:2]))
            free.remove(k)
            nearest.append(k)
        orders = [tuple(nearest)]
    for order in orders:
        goal = {n: targets[k] for n, k in zip(names, order, strict=True)}
        if all(
            _keeps(here[a][:2], goal[a][:2], q[:2], keep)
            for a in names
            for b in names
            if b != a
            for q in (here[b], goal[b])
        ):
            length = sum(math.dist(here[n][:2], goal[n][:2]) for n in names)
            if best is None or length < best[0]:
                best = (length, goal)
    return None if best is None else best[1]


def _keeps(a: Point, b: Point, q: Point, keep: float) -> bool:
    """The segment ``a``–``b`` keeps ``keep`` from ``q`` (or starts within it: flying away is allowed)."""
    return math.dist(a, q) < keep or segment_distance(a, b, q) >= keep


class Swarm:
    """Several vehicles: run an action on all at once and wait for every one."""

    def __init__(self, vehicles: Iterable[Vehicle]) -> None:
        self.vehicles = list(vehicles)

    def run(
        self,
        action: Callable[..., Any],
        args: Sequence[Any] | Mapping[str, Any] | None = None,
    ) -> list[Any]:
        """Run ``action(vehicle)`` — or ``action(vehicle, arg)`` with per-vehicle ``args`` (a sequence in
        the swarm's order, or a mapping by vehicle name) — on every vehicle at once; return the results
        in the swarm's order, or raise the first error after all finished (naming every failure)."""
        if not self.vehicles:
            return []
        per: list[tuple[Any, ...]]
        if args is None:
            per = [() for _ in self.vehicles]
        elif isinstance(args, Mapping):
            missing = [v.name for v in self.vehicles if v.name not in args]
            extra = sorted(set(args) - {v.name for v in self.vehicles})
            if missing or extra:
                raise ValueError(
                    f"swarm arguments: missing for {missing or 'none'}, unknown vehicles {extra or 'none'}"
                )
            per = [(args[v.name],) for v in self.vehicles]
        else:
            if len(args) != len(self.vehicles):
                raise ValueError(f"swarm arguments: {len(args)} given for {len(self.vehicles)} vehicles")
            per = [(a,) for a in args]
        # Daemon threads, not an executor: a program stopped (Ctrl-C) while they wait on a vehicle exits
        # at once instead of joining them at interpreter exit.
        outcome: list[tuple[bool, Any]] = [(False, None)] * len(self.vehicles)

        def one(i: int, v: Vehicle, a: tuple[Any, ...]) -> None:
            try:
                outcome[i] = (True, action(v, *a))
            except Exception as exc:
                outcome[i] = (False, exc)

        threads = [
            threading.Thread(target=one, args=(i, v, a), name=f"swarm:{v.name}", daemon=True)
            for i, (v, a) in enumerate(zip(self.vehicles, per, strict=True))
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        results, errors = [], []
        for v, (ok, value) in zip(self.vehicles, outcome, strict=True):
            if ok:
                results.append(value)
            else:
                errors.append((v.name, value))
        if errors:
            first = errors[0][1]
            names = ", ".join(f"{n}: {e}" for n, e in errors)
            if isinstance(first, CommandError):
                raise type(first)(f"swarm action failed for {names}", result=first.result) from first
            raise first
        return results

    def broadcast(self, op: str, timeout: float = 5.0, **args: Any) -> list[Any]:
        """Send the same raw gateway command to every vehicle at once (see :meth:`Vehicle.command`)."""
        return self.run(lambda v: v.command(op, timeout, **args))

    def assign(self, targets: Sequence[Point]) -> dict[str, Point]:
        """Which vehicle goes to which of ``targets`` (one each), by name, so that no vehicle's straight
        way passes within ``arena.min_separation`` (+ :data:`WANDER_MARGIN`) of another, where it is or
        where it goes — what the gateways would refuse; of those, the shortest.  :class:`ValueError` when
        no assignment is clear (fly them in two steps, or choose other targets)."""
        cfg = self.vehicles[0].arena.config if self.vehicles else None
        keep = (cfg.arena.min_separation if cfg is not None else 0.0) + WANDER_MARGIN
        here: dict[str, Point] = {}
        for v in self.vehicles:
            p = v.position
            if p is None:
                raise ValueError(f"{v.name}: no position known: cannot plan its way")
            here[v.name] = p
        got = clear_assignment(here, targets, keep)
        if got is None:
            raise ValueError(
                f"no assignment of {len(targets)} targets keeps the ways {keep:.2f} m from the other vehicles"
            )
        return got

    def arm(self) -> None:
        """Arm every vehicle."""
        self.run(lambda v: v.arm())

    def disarm(self) -> None:
        """Disarm every vehicle."""
        self.run(lambda v: v.disarm())

    def takeoff(self, height: float = 1.0) -> None:
        """Take every vehicle off to ``height`` m."""
        self.run(lambda v: v.takeoff(height))

    def goto(self, targets: Sequence[Sequence[float]] | Mapping[str, Sequence[float]], **kwargs: Any) -> None:
        """Fly each vehicle to its own target (NED), at once; ``kwargs`` as :meth:`Vehicle.goto`."""
        self.run(lambda v, p: v.goto(*p, **kwargs), targets)

    def land(self) -> None:
        """Land every vehicle."""
        self.run(lambda v: v.land())

    def hold(self) -> None:
        """Every vehicle holds where it is."""
        self.run(lambda v: v.hold())

    def __getitem__(self, name: str) -> Vehicle:
        for v in self.vehicles:
            if v.name == name:
                return v
        raise KeyError(f"{name!r} is not in this swarm ({', '.join(v.name for v in self.vehicles)})")

    def __iter__(self) -> Iterator[Vehicle]:
        return iter(self.vehicles)

    def __len__(self) -> int:
        return len(self.vehicles)
