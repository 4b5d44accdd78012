"""Waiting for a condition with a bound: the one polling loop of the library, its tools and its tests.

::

    wait_until(lambda: sub.count() >= 10, 5.0, "ten poses")        # returns the predicate's value
    wait_until(ready, 30.0, "the router", check=procs.check_alive)  # ``check`` may raise to stop early

A wait that runs out raises :class:`~arena_common.core.errors.WaitTimeout` naming what was awaited.
Code that is woken by an event (a condition variable, a queue) waits on that instead; this loop is for
conditions nothing signals (a file appearing, a port accepting, a counter another process advances).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

from arena_common.core.errors import WaitTimeout

T = TypeVar("T")


def wait_until(
    predicate: Callable[[], T],
    timeout: float,
    what: str = "condition",
    *,
    interval: float = 0.01,
    check: Callable[[], object] | None = None,
) -> T:
    """Poll ``predicate`` every ``interval`` seconds until it returns a truthy value, and return that value.

    ``check`` (optional) is called before each poll and may raise to end the wait early (a child process
    that died, say).  After ``timeout`` seconds without a truthy value, raises
    :class:`~arena_common.core.errors.WaitTimeout` ("timed out after 5 s waiting for <what>").  The
    predicate is always evaluated at least once, and once more at the deadline, so a slow poll on a busy
    machine never fails a condition that holds.
    """
    deadline = time.monotonic() + timeout
    while True:
        if check is not None:
            check()
        expired = time.monotonic() >= deadline
        value = predicate()
        if value:
            return value
        if expired:
            raise WaitTimeout(f"timed out after {timeout:g} s waiting for {what}", what=what, timeout=timeout)
        time.sleep(max(0.0, min(interval, deadline - time.monotonic())))
