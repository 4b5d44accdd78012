"""What the Motive emulator's parts share: its error, the NatNet versions it serves and the Motive release
that streams each, and its high-resolution tick clock with drift-free, clock-driven schedules."""

from __future__ import annotations

import math
import threading
import time
from fractions import Fraction

from arena_common.core.errors import ArenaError
from arena_common.mocap import natnet
from arena_common.mocap.natnet import Version

__all__ = [
    "TICK_FREQUENCY",
    "NatNetServerError",
    "TickClock",
    "motive_app_version",
    "served_version",
    "sleep_until",
]

#: Ticks per second of :class:`TickClock` (what SERVERINFO announces as the clock frequency).
TICK_FREQUENCY = 10_000_000

_SUPPORTED = (Version(2, 0), Version(5, 0))  # what the codec can encode, [lo, hi)


class NatNetServerError(ArenaError, ValueError):
    """Bad input to the NatNet server or its frame sources (version, socket, body, recording)."""


def motive_app_version(version: Version) -> Version:
    """The Motive release that streams NatNet ``version`` (what SERVERINFO announces as the app version)."""
    table = {(3, 0): Version(2, 1), (3, 1): Version(2, 2), (4, 0): Version(3, 0), (4, 1): Version(3, 1)}
    return table.get((version.major, version.minor), Version(version.major - 1, version.minor))


def served_version(value: str | Version) -> Version:
    """``value`` as a NatNet version the emulator serves (2.0 to 4.x); else :class:`NatNetServerError`."""
    try:
        v = value if isinstance(value, Version) else Version.parse(str(value))
    except natnet.NatNetError as exc:
        raise NatNetServerError(str(exc)) from None
    if not _SUPPORTED[0] <= v < _SUPPORTED[1]:
        raise NatNetServerError(f"NatNet version {v} cannot be served (2.0 through 4.x can)")
    return v


# ------------------------------------------------------------------------------------------------------------
# Clock and schedule
# ------------------------------------------------------------------------------------------------------------


class TickClock:
    """The high-resolution clock of the tick stamps: ``perf_counter_ns`` counted at ``frequency`` Hz.

    :meth:`align` re-bases it so that it reads ``tick`` at ``perf_ns`` and runs ``rate`` times as fast as
    real time: replay uses it to keep the echo replies in the recorded clock's domain. Integer arithmetic:
    two instants a whole number of ticks apart are stamped exactly that many ticks apart.
    """

    def __init__(self, frequency: int = TICK_FREQUENCY) -> None:
        if not isinstance(frequency, int) or frequency <= 0:
            raise NatNetServerError(f"clock frequency must be a positive integer, got {frequency!r}")
        self.frequency = frequency
        self._origin_tick = 0
        self._origin_ns = 0
        self._num, self._den = frequency, 1_000_000_000

    def align(self, tick: int, perf_ns: int, rate: float = 1.0) -> None:
        """Read ``tick`` at ``perf_ns`` (a ``time.perf_counter_ns`` value) and run at ``rate`` × real time."""
        if not rate > 0 or not math.isfinite(rate):
            raise NatNetServerError(f"clock rate must be positive, got {rate}")
        ratio = Fraction(rate).limit_denominator(1_000_000)
        self._origin_tick, self._origin_ns = int(tick), int(perf_ns)
        self._num, self._den = self.frequency * ratio.numerator, 1_000_000_000 * ratio.denominator

    def at(self, perf_ns: int) -> int:
        """The tick count at ``perf_ns`` (never negative)."""
        return max(0, self._origin_tick + (perf_ns - self._origin_ns) * self._num // self._den)

    def now(self) -> int:
        """The tick count now."""
        return self.at(time.perf_counter_ns())


def sleep_until(deadline_ns: int, stop: threading.Event | None = None) -> bool:
    """Sleep until ``time.perf_counter_ns()`` reaches ``deadline_ns``; ``False`` if ``stop`` was set first.

    A schedule built as ``start + k * period`` and this function does not drift: lateness of one wake-up
    does not delay the next deadline.
    """
    while True:
        left = deadline_ns - time.perf_counter_ns()
        if stop is not None and stop.is_set():
            return False
        if left <= 0:
            return True
        if stop is None:
            time.sleep(left / 1e9)
        elif stop.wait(left / 1e9):
            return False
