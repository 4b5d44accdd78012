"""A formation goal another vehicle stands on waits for it to move on (``arena_common.cli._demo.wait_clear``):
the gateway would refuse the goto, and the demo fail, for a vehicle only held or pushed off its place."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace
from typing import Any

import pytest

from arena_common.cli import _demo
from arena_common.core.config import ArenaConfig


def _vehicle(other: list[tuple[float, float, float]]) -> Any:
    """What wait_clear reads of a vehicle: its name, its arena's config and the fleet's positions (itself
    at the origin, ``other[0]`` where the other vehicle is now)."""
    arena = SimpleNamespace(
        config=ArenaConfig(),  # min_separation 0.6 m
        positions=lambda: {"me": (0.0, 0.0, -1.0), "other": other[0]},
    )
    return SimpleNamespace(name="me", arena=arena)


GOAL = (1.0, 0.0, -1.0)


def test_a_goal_clear_of_the_others_goes_at_once() -> None:
    me = _vehicle([(1.0, 1.0, -1.0)])
    t = time.monotonic()
    _demo.wait_clear(me, GOAL, threading.Event())
    assert time.monotonic() - t < 1.0


def test_a_goal_another_stands_on_waits_until_it_moves_on() -> None:
    other = [(1.1, 0.0, -1.0)]
    me = _vehicle(other)
    timer = threading.Timer(0.5, lambda: other.__setitem__(0, (1.0, 1.0, -1.0)))
    timer.start()
    t = time.monotonic()
    _demo.wait_clear(me, GOAL, threading.Event())
    assert 0.5 <= time.monotonic() - t < _demo.CLEAR_WAIT


def test_a_goal_still_blocked_is_sent_after_the_wait(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_demo, "CLEAR_WAIT", 0.5)
    me = _vehicle([GOAL])
    t = time.monotonic()
    _demo.wait_clear(me, GOAL, threading.Event())
    assert 0.5 <= time.monotonic() - t < 5.0


def test_a_stop_ends_the_wait_and_no_goto_follows() -> None:
    """A stop lands the vehicles: the goto a step was waiting to send must not come after the land order."""
    me = _vehicle([GOAL])
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    t = time.monotonic()
    with pytest.raises(_demo.Stopped):
        _demo.wait_clear(me, GOAL, stop)
    assert time.monotonic() - t < 2.0
