"""Attitude and thrust setpoints on a real PX4 v1.16 (SITL, SIH), and the rule that keeps them in the room.

An attitude setpoint steers no position the gateway could check, so the gateway streams one only while
the vehicle is inside the safe volume and its velocity does not take it out within 0.75 s.  Here PX4
takes the arena's SET_ATTITUDE_TARGET in OFFBOARD and the vehicle truly climbs on more than hover thrust;
heading for the safe volume's ceiling, the gateway stops the stream, latches and commands Hold at once
(an Event says so).  Measured (SIH, hover + 0.15 thrust): stopped at 1.31-1.32 m, peak 2.03-2.13 m, under
the 2.2 m safe-volume ceiling (a 0.5 s look-ahead stopped at 1.44-1.69 m and peaked at 2.33-2.73 m, above
the 2.5 m room in 3 of 4 runs; without the look-ahead, stopping on the ceiling itself: 3.6 m; without the
Hold, waiting for PX4's offboard-loss failsafe: 7.1 m).
Bounds asserted, figures printed.
"""

from __future__ import annotations

import time

import pytest

from arena_common.core.errors import SafetyRefused
from tests.conftest import wait_for
from tests.px4.conftest import PX4ArenaFactory
from tests.px4.harness import FlightRecord, Px4Watch

PEAK_ABOVE_M = 0.5  # how far above the ceiling the vehicle may coast before Hold has braked it


def test_attitude_thrust_climbs_and_the_ceiling_stops_the_stream(px4_arena: PX4ArenaFactory) -> None:
    stack, arena = px4_arena(("d1",))
    d1 = arena.vehicle("d1")
    record = FlightRecord(arena, "d1")
    ceiling = -stack.cfg.arena.safe_box()[2][0]  # height of the safe volume's top [m]
    events = d1.event_stream(timeout=30.0)
    hover = float(d1.params.get("MPC_THR_HOVER"))
    with Px4Watch(stack.px4["d1"]) as watch:
        d1.arm()
        d1.takeoff(1.0, timeout=60)
        start = record.latest_truth()
        assert start is not None
        # The program learns that its stream was refused: SafetyRefused, at the latest when the block ends.
        refused = pytest.raises(SafetyRefused, match="attitude setpoints only inside the safe volume")
        with refused, d1.offboard() as ctl:
            ctl.attitude(0.0, 0.0, 0.0, min(1.0, hover + 0.15))  # level, more than hover thrust
            wait_for(lambda: watch.latest and watch.latest.nav == "OFFBOARD", 5, 0.05, "PX4 in OFFBOARD")
            stopped = next(
                e for e in events if e.kind == "safety" and e.text.startswith("attitude stream stopped")
            )
            top = record.latest_truth()
            # The gateway commanded Hold; the program's setpoints are held back from now on.
            wait_for(lambda: watch.latest and watch.latest.nav == "AUTO_LOITER", 5, 0.05, "PX4 in Hold")
            d1.wait_until(lambda v: v.mode == "AUTO.LOITER", 5.0, "the arena's state to show Hold")
        assert "leaving the safe volume" in stopped.text and top is not None
        assert -top.p[2] > -start.p[2] + 0.3, top.p  # it truly climbed on thrust alone
        hold = time.monotonic()
        time.sleep(3.0)
        record.collect()
        peak = max(-t.p[2] for t in record.truth)
        print(
            f"\nattitude offboard on PX4 (hover thrust {hover:.2f}): climbed from {-start.p[2]:.2f} m; "
            f"stream stopped and Hold commanded at {-top.p[2]:.2f} m (ceiling {ceiling:.2f} m); "
            f"peak {peak:.2f} m; {time.monotonic() - hold:.1f} s later at {-record.truth[-1].p[2]:.2f} m"
        )
        assert peak < ceiling + PEAK_ABOVE_M, peak  # braked near the ceiling, not far above it
        d1.land(timeout=90)
    assert not stack.dead(), stack.dead()
