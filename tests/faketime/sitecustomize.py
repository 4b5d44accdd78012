"""Loaded (through PYTHONPATH) by the processes the clock-skew tests run under libfaketime.

libfaketime 0.9.10 (Debian 12) with ``FAKETIME_DONT_FAKE_MONOTONIC=1`` breaks
``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)``, which ``time.sleep`` uses from Python 3.11: it
fails with EINVAL (libfaketime issue #426).  Only ``time.sleep`` is concerned (events, locks, queues
and ``select`` keep working), so it becomes a ``select`` timeout, which waits just as long.  The wall
clock the processes read stays the faked one: that is what the tests are about.
"""

from __future__ import annotations

import os
import select
import time

if os.environ.get("FAKETIME") and "faketime" in os.environ.get("LD_PRELOAD", ""):

    def _sleep(seconds: float) -> None:
        if seconds < 0:
            raise ValueError("sleep length must be non-negative")
        select.select([], [], [], seconds)

    time.sleep = _sleep  # type: ignore[assignment]  # same behaviour for the floats the arena passes
