"""The simulated clock: speed times real time; with ``max_gap_s``, a pause of the process is not simulated."""

from __future__ import annotations

import time

from arena_common.sim.time import SimClock


def test_a_pause_longer_than_the_gap_is_not_simulated_time() -> None:
    clock = SimClock(speed=4.0, max_gap_s=0.05)
    t0 = clock.now()
    time.sleep(0.3)  # nothing read the clock: the process as if not run by a busy machine
    paused = clock.now() - t0
    assert paused <= 4.0 * (0.05 + 0.05), paused  # the gap, and at most as much again for the read itself
    assert clock.pauses == 1 and clock.skipped_ns >= 0.25e9, (clock.pauses, clock.skipped_ns)
    # A sleep asked of the clock is simulated time, however long: not a pause.
    pauses, t1 = clock.pauses, clock.now()
    clock.sleep(0.8)  # 0.2 s real, in one go
    assert clock.now() - t1 >= 0.8 and clock.pauses == pauses, (clock.now() - t1, clock.pauses)


def test_a_services_clock_keeps_real_time_through_any_pause() -> None:
    clock = SimClock(speed=2.0)
    t0 = clock.now()
    time.sleep(0.3)
    assert clock.now() - t0 >= 0.6
