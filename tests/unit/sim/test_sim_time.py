"""The simulated clock: speed times real time; with ``max_gap_s``, a pause of the process is not simulated."""

from __future__ import annotations

import threading
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


def test_a_pacer_away_holds_the_clock_however_busily_another_thread_reads_it() -> None:
    """The ground station's thread not scheduled while the vehicle's loop runs: no simulated time passes
    without its mocap, and the clock runs on as soon as it is back."""
    clock = SimClock(speed=4.0, max_gap_s=0.05)
    clock.paces()
    stop, seen = threading.Event(), []

    def vehicle_loop() -> None:
        while not stop.is_set():
            seen.append(clock.now())
            time.sleep(0.005)

    thread = threading.Thread(target=vehicle_loop)
    t0 = clock.now()
    thread.start()
    time.sleep(0.5)  # the pacer away, 2 s of simulated time were it not
    held = seen[-1] - t0
    t1 = clock.now()  # back, and waiting on the clock
    clock.sleep(0.4)
    stop.set()
    thread.join()
    assert held <= 4.0 * (0.05 + 0.05), held  # its allowance, and at most as much again for a read
    assert seen[-1] - t1 >= 0.3, (seen[-1], t1)  # back: the other thread's reads run the clock again
    assert clock.pauses >= 1 and clock.skipped_ns >= 0.35e9, (clock.pauses, clock.skipped_ns)


def test_a_pacer_asleep_on_the_clock_is_not_away() -> None:
    clock = SimClock(speed=4.0, max_gap_s=0.05)
    clock.paces()
    result: list[float] = []

    def read_later() -> None:
        time.sleep(0.25)
        result.append(clock.now())

    thread = threading.Thread(target=read_later)
    t0 = clock.now()
    thread.start()
    clock.sleep(2.0)  # 0.5 s real, asked of the clock
    thread.join()
    assert result[0] - t0 >= 4.0 * 0.2, result[0] - t0  # the other thread saw the time run meanwhile
    assert clock.now() - t0 >= 2.0


def test_a_paced_thread_away_holds_the_clock_read_by_the_one_that_named_it() -> None:
    """The vehicle's loop named as a pacer by the test: while it is held up, the test's reads do not
    run the clock."""
    clock = SimClock(speed=4.0, max_gap_s=0.05)
    release = threading.Event()
    loop = threading.Thread(target=release.wait)  # away from the clock until released
    loop.start()
    clock.paces(loop)
    t0 = clock.now()
    end = time.monotonic() + 0.3
    while time.monotonic() < end:
        clock.now()
        time.sleep(0.005)
    held = clock.now() - t0
    release.set()
    loop.join()
    t1 = clock.now()  # an ended pacer no longer counts
    time.sleep(0.02)
    assert held <= 4.0 * (0.05 + 0.05), held
    assert clock.now() - t1 >= 4.0 * 0.015, clock.now() - t1
