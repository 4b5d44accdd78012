"""Time of the simulated autopilots: a fast-forwardable clock and PX4's TIMESYNC offset filter.

:class:`SimClock` is the simulated time every vehicle of one loop shares (``speed`` times real time);
:class:`TimesyncFilter` is PX4's estimator of the offset between a peer's clock and the vehicle's
(src/modules/mavlink/mavlink_timesync, lib/timesync), which decides whether a vision ``time_usec`` is used
(once converged) or replaced by its arrival time.
"""

from __future__ import annotations

import math
import threading
import time

from arena_common.mavlink import px4
from arena_common.sim.base import SimAutopilotError

__all__ = ["SimClock", "TimesyncFilter"]


class SimClock:
    """Simulated time: wall-clock driven, ``speed`` times faster than real time.

    ``now_ns()`` starts at ``start_ns`` (default: the wall clock at creation, so that at speed 1 the
    simulated time reads like ``time.time_ns()``) and advances ``speed`` ns per real ns.

    ``max_gap_s`` is for a test whose vehicles and ground station share this clock in one process: a pause
    of the process (a busy machine not running it) longer than that between two reads of the clock, by any
    thread, is not simulated time, so the vehicle does not see its ground station silent for it.  A thread
    that :meth:`paces` the clock (the test's ground station) holds it still while it is away more than
    ``max_gap_s``, however busily other threads read it: the vehicle's loop may run while the ground
    station's thread waits to be scheduled, and that time would otherwise be simulated without its mocap.
    The vehicle's loop may pace it too, so that a busy machine does not make the vehicle skip time.
    A service's clock keeps real time (the default, None): its vehicles face processes on the wall clock.
    """

    def __init__(
        self, speed: float = 1.0, start_ns: int | None = None, max_gap_s: float | None = None
    ) -> None:
        if not (math.isfinite(speed) and 0.01 <= speed <= 100.0):
            raise SimAutopilotError(f"clock speed must be within 0.01..100, got {speed}")
        self.speed = float(speed)
        self._t0 = time.monotonic_ns()
        self.start_ns = time.time_ns() if start_ns is None else int(start_ns)
        self.max_gap_ns = None if max_gap_s is None else int(max_gap_s * 1e9)
        self._lock = threading.Lock()
        self._last_real = self._t0
        self.skipped_ns = 0  # real ns of pauses longer than max_gap_s, not simulated
        self.pauses = 0
        self._pacers: dict[threading.Thread, int] = {}  # thread -> real ns until which it vouches
        self._held = False

    def paces(self, thread: threading.Thread | None = None) -> None:
        """Make ``thread`` (default: the calling one) a pacer: while it is away (no read, no :meth:`sleep`)
        longer than ``max_gap_s``, simulated time stands still.  A pacer that has ended no longer counts."""
        if self.max_gap_ns is None:
            raise SimAutopilotError("only a clock with max_gap_s can be paced")
        with self._lock:
            self._pacers[thread or threading.current_thread()] = time.monotonic_ns()

    def now_ns(self) -> int:
        """Current simulated time in ns."""
        if self.max_gap_ns is None:
            return self.start_ns + int((time.monotonic_ns() - self._t0) * self.speed)
        with self._lock:  # read inside the lock: every thread sees the time move forward
            real = time.monotonic_ns()
            self._account(real, asked=False)
            return self.start_ns + int((real - self.skipped_ns - self._t0) * self.speed)

    def _account(self, real: int, asked: bool) -> None:
        """Simulate the real time since the last read, less what a pause or an absent pacer takes (locked).

        ``asked``: the time was a :meth:`sleep` of the calling thread, simulated however long it was.
        """
        assert self.max_gap_ns is not None
        gap = real - self._last_real  # read under the lock: never negative
        vouched = [seen for t, seen in self._pacers.items() if t.is_alive()]
        if vouched:  # no further than the least recent pacer's last sign of life, and its allowance
            ran = max(0, min(gap, min(vouched) + self.max_gap_ns - self._last_real))
        else:  # any thread's reads: a gap between them longer than max_gap_s is a pause
            ran = gap if asked else min(gap, self.max_gap_ns)
        me = threading.current_thread()
        if me in self._pacers:
            self._pacers[me] = max(self._pacers[me], real)
        if ran < gap and not self._held:
            self.pauses += 1
        self._held = ran < gap
        self.skipped_ns += gap - ran
        self._last_real = real

    def now(self) -> float:
        """Current simulated time in seconds."""
        return self.now_ns() * 1e-9

    def real_seconds(self, sim_seconds: float) -> float:
        """Real (wall) seconds that ``sim_seconds`` of simulated time take."""
        return sim_seconds / self.speed

    def sleep(self, sim_seconds: float) -> None:
        """Sleep for ``sim_seconds`` of simulated time."""
        if sim_seconds > 0:
            real_s = sim_seconds / self.speed
            if self.max_gap_ns is not None:
                with self._lock:  # a pacer asleep is not away
                    me = threading.current_thread()
                    if me in self._pacers:
                        self._pacers[me] = time.monotonic_ns() + int(real_s * 1e9)
            time.sleep(real_s)
            if self.max_gap_ns is not None:  # asked for, so simulated
                with self._lock:
                    self._account(time.monotonic_ns(), asked=True)


class TimesyncFilter:
    """PX4's TIMESYNC offset estimator: double exponential smoothing with gain scheduling.

    Offsets are in µs with ``local = remote + offset``. Samples with a round trip of 10 ms or more are
    skipped; once converged (500 accepted samples), samples deviating by more than 100 ms are rejected
    and more than 5 in a row reset the filter (a time jump on the other side).
    """

    ALPHA_INITIAL = 0.05
    BETA_INITIAL = 0.05
    ALPHA_FINAL = 0.003
    BETA_FINAL = 0.003

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget everything (reboot, time jump)."""
        self.sequence = 0
        self.offset_us = 0.0
        self.skew_us = 0.0
        self.alpha = self.ALPHA_INITIAL
        self.beta = self.BETA_INITIAL
        self.high_deviation_count = 0
        self.high_rtt_count = 0
        self.resets = 0
        self.last_rtt_us = -1

    @property
    def converged(self) -> bool:
        """Whether enough good samples were seen to trust the offset."""
        return self.sequence >= px4.TIMESYNC_CONVERGENCE_WINDOW

    def update(self, now_us: int, remote_us: int, originate_us: int) -> bool:
        """Feed one reply (our receive time, the remote's ``tc1``, our echoed ``ts1``, all µs).

        Returns whether the sample was accepted.
        """
        rtt = now_us - originate_us
        self.last_rtt_us = rtt
        if rtt < 0 or rtt >= px4.TIMESYNC_MAX_RTT_US:
            self.high_rtt_count += 1
            return False
        offset = (originate_us + now_us - 2 * remote_us) / 2.0
        deviation = abs(self.offset_us - offset)
        if self.converged and deviation > px4.TIMESYNC_MAX_DEVIATION_US:
            self.high_deviation_count += 1
            if self.high_deviation_count > px4.TIMESYNC_MAX_CONSECUTIVE_HIGH_DEVIATION:
                resets = self.resets + 1
                self.reset()
                self.resets = resets
            return False
        if not self.converged:
            progress = self.sequence / px4.TIMESYNC_CONVERGENCE_WINDOW
            p = 1.0 - math.exp(0.5 * (1.0 - 1.0 / (1.0 - progress)))
            self.alpha = p * self.ALPHA_FINAL + (1.0 - p) * self.ALPHA_INITIAL
            self.beta = p * self.BETA_FINAL + (1.0 - p) * self.BETA_INITIAL
        else:
            self.alpha, self.beta = self.ALPHA_FINAL, self.BETA_FINAL
        if self.sequence == 0:
            self.offset_us = offset
        else:
            previous = self.offset_us
            self.offset_us = self.alpha * offset + (1.0 - self.alpha) * (self.offset_us + self.skew_us)
            self.skew_us = self.beta * (self.offset_us - previous) + (1.0 - self.beta) * self.skew_us
        self.sequence += 1
        self.high_deviation_count = 0
        self.high_rtt_count = 0
        return True

    def sync_stamp(self, remote_us: int, arrival_us: int) -> int:
        """Local time of a remote timestamp once converged, else the arrival time (as PX4)."""
        if self.converged:
            return int(remote_us + self.offset_us)
        return arrival_us
