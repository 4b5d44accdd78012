"""Hand-overs on a real PX4 v1.16 (SITL, SIH): the simulated hand-over tier's flows, fewer, each judged for
the 3 s after the call returns, with the program's setpoints delayed and reordered 50–300 ms against its
commands (tests/handoverlib.py).

follow → the gateway's hold, an offboard block's exit (Hold), a goto inside a block, another program's goto
taking the vehicle from a block, a stream after a goto: PX4 must show no failsafe and no mode change nobody
asked for in the seconds after each, and PX4's own view (vehicle_status) must agree at the end.
"""

from __future__ import annotations

import pytest

from arena_common import Arena
from tests.handoverlib import Judge, delay_setpoints, kinds
from tests.px4.conftest import PX4ArenaFactory

pytestmark = pytest.mark.timeout(600)

ROUNDS = 2  # each flow twice (once each way)


def test_hand_overs_on_px4_with_setpoints_delayed_and_reordered(px4_arena: PX4ArenaFactory) -> None:
    stack, arena = px4_arena(("d1",))
    delayed = delay_setpoints(arena.bus, seed=34)
    d1 = arena.vehicle("d1")
    judge = Judge()
    with Arena(stack.cfg, name="px4-handover-other") as other:
        flows = kinds(other)
        d1.arm()
        d1.takeoff(1.0, timeout=60)
        for k in range(ROUNDS * len(flows)):
            kind, mode, act = flows[k % len(flows)]
            act(d1, 1.0 if k < len(flows) else -1.0)
            judge.after(d1, kind, mode)
        assert judge.problems == [], judge.problems
        assert judge.total == ROUNDS * len(flows)
        status = stack.px4["d1"].listener("vehicle_status")
        assert status["arming_state"] == 2 and status["nav_state"] in (4, 14), status  # LOITER or OFFBOARD
        assert not [e.text for e in d1.events() if e.kind == "failsafe"]
        d1.land(timeout=90)
    assert sum(p.delayed for p in delayed) > 0
    print(f"\nPX4 hand-overs: {judge.count}; setpoints delayed: {sum(p.delayed for p in delayed)}")
