"""When a vehicle has arrived: the one definition that ``takeoff``, ``goto``, ``arena takeoff``/``goto``, the
gateway's ``goto wait`` and the demo's formation all wait for.

PX4 does not hold a point still.  Its hover, as ``arena px4 setup`` ships it, wanders 17–24 cm (max) about
the held point on a ~7.5 s swing, and up to 36–40 cm before that setup; the simulated vehicle
(``fidelity = "px4"``) wanders as PX4 SITL does, 9–40 cm max per window (docs/px4.md).  "Within 10 cm at one
instant" is then a matter of luck, and a goal merely flown through is not a goal reached.  So:

- a vehicle has **arrived** when its position *averaged over the last* :data:`ARRIVAL_WINDOW` seconds lies
  within the tolerance of the goal (a vehicle still moving averages behind its position, so passing
  through never counts);
- the default tolerances are sized from that measured wander, with margin: :data:`ARRIVAL_TOLERANCE` for a
  position, :data:`HEIGHT_TOLERANCE` for a take-off height (PX4's vertical wander is ±8 cm);
- a wait that runs out names how far the vehicle is (:meth:`Arrival.describe`): a real miss (a vehicle
  blocked, a goal it cannot reach) still fails, saying so.

An exact (``fidelity = "ideal"``) or tightly tuned vehicle may ask for less with an explicit tolerance.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence

__all__ = ["ARRIVAL_TOLERANCE", "ARRIVAL_WINDOW", "HEIGHT_TOLERANCE", "Arrival"]

ARRIVAL_WINDOW = 1.0  # s (arena time) over which the position is averaged
ARRIVAL_TOLERANCE = 0.3  # m, of the averaged position from a goal: PX4's hover swings up to 24-40 cm
HEIGHT_TOLERANCE = 0.15  # m, of the averaged height from a take-off height: PX4's vertical wander ±8 cm

Vec3 = tuple[float, float, float]


class Arrival:
    """Judges arrival at ``goal`` from positions fed in time order (:meth:`add`).

    ``axes`` picks the components compared (``(2,)``: the height alone); ``window`` is in the same unit as
    the times given to :meth:`add` (seconds of the caller's clock).
    """

    def __init__(
        self,
        goal: Sequence[float],
        tolerance: float = ARRIVAL_TOLERANCE,
        window: float = ARRIVAL_WINDOW,
        axes: tuple[int, ...] = (0, 1, 2),
    ) -> None:
        if not (math.isfinite(tolerance) and tolerance > 0.0):
            raise ValueError(f"an arrival tolerance must be a positive distance in metres, got {tolerance!r}")
        if not (math.isfinite(window) and window >= 0.0):
            raise ValueError(f"an arrival window must be a duration of at least 0 s, got {window!r}")
        self.goal = (float(goal[0]), float(goal[1]), float(goal[2]))
        self.tolerance = tolerance
        self.window = window
        self.axes = axes
        self._samples: collections.deque[tuple[float, Vec3]] = collections.deque()
        self._sums = [0.0, 0.0, 0.0]
        self._since: float | None = None  # first time of the current unbroken run of positions

    def add(self, t: float, p: Sequence[float] | None) -> None:
        """One position at time ``t``; None (no valid position) starts the window again."""
        if p is None:
            self._samples.clear()
            self._sums = [0.0, 0.0, 0.0]
            self._since = None
            return
        if self._since is None:
            self._since = t
        q = (float(p[0]), float(p[1]), float(p[2]))
        self._samples.append((t, q))
        for i in range(3):
            self._sums[i] += q[i]
        while len(self._samples) > 1 and self._samples[0][0] < t - self.window:
            _, old = self._samples.popleft()
            for i in range(3):
                self._sums[i] -= old[i]

    def mean(self) -> Vec3 | None:
        """The position averaged over the window (None before any)."""
        n = len(self._samples)
        if n == 0:
            return None
        return (self._sums[0] / n, self._sums[1] / n, self._sums[2] / n)

    def error(self) -> float | None:
        """Distance (on the compared axes) of the averaged position from the goal, m; None before any."""
        m = self.mean()
        if m is None:
            return None
        return math.sqrt(sum((m[i] - self.goal[i]) ** 2 for i in self.axes))

    def covered(self) -> bool:
        """Whether positions have come unbroken for a whole window."""
        return (
            bool(self._samples)
            and self._since is not None
            and self._samples[-1][0] - self._since >= self.window
        )

    def arrived(self) -> bool:
        """The averaged position lies within the tolerance, over a whole window."""
        err = self.error()
        return self.covered() and err is not None and err <= self.tolerance

    def describe(self) -> str:
        """How far the vehicle is, in words, for an error message."""
        err = self.error()
        if err is None:
            return "no valid position"
        return (
            f"{err:.2f} m from it (position averaged over the last {self.window:.1f} s; tolerance "
            f"{self.tolerance:.2f} m)"
        )
