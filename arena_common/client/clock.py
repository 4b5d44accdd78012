"""The arena's clock: one script runs unchanged in the simulation at ``sim.speed`` and in the room at 1×.

As Crazyswarm2's ``TimeHelper``: ``arena.clock.sleep(2.0)`` waits two seconds of *arena* time —
0.5 s of wall time when the simulation runs at 4×, 2 s in the room.  Command timeouts, trajectories
and ``goto`` durations are counted on it.
"""

from __future__ import annotations

import time

from arena_common.core.config import ArenaConfig

__all__ = ["ArenaClock"]


class ArenaClock:
    """Arena time: wall time scaled by ``speed`` (the simulation's ``sim.speed`` when every configured
    vehicle is simulated, else 1)."""

    def __init__(self, speed: float = 1.0) -> None:
        if not speed > 0.0:
            raise ValueError(f"clock speed must be positive, got {speed!r}")
        self.speed = float(speed)
        self._t0 = time.monotonic()

    @classmethod
    def for_config(cls, config: ArenaConfig | None) -> ArenaClock:
        """The clock of an arena: simulated at ``sim.speed`` when all its vehicles are simulated."""
        if config is None or not config.vehicles:
            return cls(1.0)
        simulated = all(v.autopilot == "sim" for v in config.vehicles.values())
        return cls(config.sim.speed if simulated else 1.0)

    def now(self) -> float:
        """Arena seconds since this clock started."""
        return (time.monotonic() - self._t0) * self.speed

    def time(self) -> float:
        """Same as :meth:`now` (Crazyswarm2's name)."""
        return self.now()

    def wall(self, seconds: float) -> float:
        """The wall-clock seconds that ``seconds`` of arena time take."""
        return seconds / self.speed

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of arena time."""
        if seconds > 0:
            time.sleep(seconds / self.speed)

    def sleep_for_rate(self, rate: float) -> None:
        """Wait one period of ``rate`` Hz in arena time (for loops that pace themselves)."""
        self.sleep(1.0 / rate)

    def rate(self, hz: float) -> Rate:
        """A :class:`Rate` that paces a loop at ``hz`` arena-time hertz without drift."""
        return Rate(self, hz)


class Rate:
    """Paces a loop: ``r = arena.clock.rate(50)``, then ``r.sleep()`` at the end of each turn."""

    def __init__(self, clock: ArenaClock, hz: float) -> None:
        if not hz > 0.0:
            raise ValueError(f"rate must be positive, got {hz!r}")
        self.clock = clock
        self.period = 1.0 / hz
        self._next = clock.now() + self.period

    def sleep(self) -> None:
        """Wait until the next tick (at once when the loop fell behind by more than a period)."""
        left = self._next - self.clock.now()
        if left < -self.period:
            self._next = self.clock.now() + self.period
            return
        self.clock.sleep(left)
        self._next += self.period
