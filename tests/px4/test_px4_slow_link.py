"""PX4 SITL over a slow radio link: 30 ± 10 ms each way between PX4 and its gateway, with and without
the arena's compensation, against the same flights on a direct link.

A relay (:mod:`tests.px4.radio`, the radio, in a process of its own) holds every datagram of the MAVLink
link each way.  PX4 then drops every TIMESYNC round trip (10 ms or more) and stamps vision on arrival, so
the link's delay is in every vision sample.  The gateway measures the link and its check wants
``EKF2_EV_DELAY`` from it, as ``setup`` writes it (docs/px4.md, "The link's delay, as the arena shows it");
PX4 takes the parameter after a reboot, which SITL denies, so PX4 boots with it for the compensated flights.
PX4 varies from one flight to the next by more than 20 % (docs/px4.md), so each link flies
``ARENA_RADIO_FLIGHTS`` flights of :func:`tests.px4.parity.fly` (takeoff, Hold, trajectory, back, land)
in one boot of PX4, and their medians are compared:

- direct, PX4's TIMESYNC converged (it takes the gateway's stamps), as `arena px4 setup` leaves it;
- slow link, ``EKF2_EV_DELAY`` left at 0: the estimate trails the truth by the link's delay more.  A
  failsafe of PX4's own ends this link's flights and counts as its outcome (seen only while the relay
  ran inside the test's process: docs/px4.md);
- slow link, ``EKF2_EV_DELAY`` at what the check wants from the measured link.

The table of medians and ranges is printed (docs/px4.md gives it), with whether the compensated hover and
trajectory medians are within 20 % of the direct link's (the aim; met for the trajectory, for the hover in one of
two runs of ten flights: docs/px4.md).
Asserted: the gateway sees the link's delay and PX4 stamping on arrival, and the check wants a delay of
the link's size; compensated, the estimate's lag stays near the direct flights' (the state comes back
over the slow link too); uncompensated, the lag is measurably longer than compensated, or PX4 lost its
estimate and landed.  The bounds and the runs they come from are at the constants.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import pytest

from arena_common import Arena
from arena_common.cli._px4 import request
from arena_common.core.errors import ArenaError
from tests.conftest import wait_for
from tests.px4.conftest import PX4ArenaFactory
from tests.px4.harness import FlightRecord, Px4Stack, wait_timesync_settled
from tests.px4.parity import fly

LINK = (0.030, 0.010)  # s each way: delay, jitter (a telemetry radio, a busy Wi-Fi)
FLIGHTS = int(os.environ.get("ARENA_RADIO_FLIGHTS", "1"))  # per link, in one boot of PX4
PROGRAM = ("takeoff", "hover", "trajectory", "back", "land")  # "back": each flight starts where the first did
FIGURES = [
    "hover_p50_cm",
    "traj_max_cm",
    "traj_rms_cm",
    "estimate_p50_cm",
    "estimate_max_cm",
    "estimate_lag_ms",
]
DIRECT, UNCOMPENSATED, COMPENSATED = "direct", "slow, EKF2_EV_DELAY 0", "slow, compensated"
# The estimate's lag behind the truth (arena state against SIH's truth, medians of each run's flights;
# direct / slow, EKF2_EV_DELAY 0 / slow, compensated): 110/180/130, 100/170/130, 140/190/140 ms (one flight
# each, 2026-11-28, before the arena's own lag was cut); 60/130/100 ms (five flights each, 2026-12-04);
# 60/130/95 ms (ten flights each, 2026-12-04).
# Compensated, the lag is the direct one plus the state's own way back over the link (30 ± 10 ms);
# uncompensated, plus what EKF2_EV_DELAY misses (~40 ms) on top.
NEAR_LAG_MS = 50.0  # compensated: at most this much longer than on the direct link (measured 0-40)
WORSE_LAG_MS = 15.0  # uncompensated: at least this much longer than compensated (measured 30-50)
AIMED = ("hover_p50_cm", "traj_max_cm", "traj_rms_cm")
AIM = 0.20  # compensated: each of AIMED's medians at most 20 % above the direct link's


def judged(arena: Arena) -> dict[str, Any]:
    """The check's EKF2_EV_DELAY row once the gateway has judged the link (8 of its own 1 Hz round trips):
    until then the check wants the default 0 ms and takes any value."""

    def row() -> dict[str, Any] | None:
        got: dict[str, Any] = request(arena.bus, "d1", "check", 10.0).value["params"]["EKF2_EV_DELAY"]
        return got if float(got["want"]) > 0.0 else None

    return wait_for(row, 40.0, 1.0, "the check to want EKF2_EV_DELAY from the measured link")


def median(flights: list[dict[str, float]], figure: str) -> float:
    """The figure's median over the flights that flew the whole program."""
    return float(np.median([f[figure] for f in flights]))


@pytest.mark.timeout(300 + 250 * FLIGHTS)
@pytest.mark.skipif(not os.environ.get("ARENA_RADIO"), reason="PX4 flights over a slow link: make test-radio")
def test_px4_over_a_slow_link_with_and_without_compensation(px4_arena: PX4ArenaFactory) -> None:
    runs: dict[str, list[dict[str, float]]] = {}
    failed: dict[str, str] = {}  # a link whose flight ended in PX4's failsafe: what the arena said

    def failsafes(stack: Px4Stack) -> int:
        return (stack.logs / "px4.d1.log").read_text(errors="replace").count("Failsafe activated")

    def flights(stack: Px4Stack, arena: Arena, name: str, may_fail: bool = False) -> None:
        runs[name], before = [], failsafes(stack)
        for _ in range(FLIGHTS):
            try:
                runs[name].append(fly(arena, "d1", FlightRecord(arena, "d1"), PROGRAM))
            except ArenaError as e:
                if not may_fail or failsafes(stack) == before:  # only PX4's own failsafe ends these flights
                    raise
                failed[name] = f"flight {len(runs[name]) + 1} of {FLIGHTS}: {e}"
                print(f"\n{name}: {failed[name]}")
                return
            print(f"\n{name}: " + ", ".join(f"{k} {v:.1f}" for k, v in runs[name][-1].items()))

    stack, arena = px4_arena(("d1",))
    wait_timesync_settled(stack.px4["d1"])
    flights(stack, arena, DIRECT)
    assert not stack.dead(), stack.dead()
    stack.close()

    # Slow link, EKF2_EV_DELAY 0 (as PX4 ships): the gateway measures the link, the check wants the delay.
    stack, arena = px4_arena(("d1",), links={"d1": LINK})
    d1 = arena.vehicle("d1")
    row = judged(arena)
    assert d1.state is not None and d1.state.stamps == "arrival", d1.state
    want = float(row["want"])
    assert not row["ok"] and float(row["have"]) == 0.0, row
    assert 25.0 <= want <= 60.0, want  # half a round trip of 40-80 ms, plus a pose's age
    flights(stack, arena, UNCOMPENSATED, may_fail=True)
    assert not stack.dead(), stack.dead()
    stack.close()

    # Slow link, EKF2_EV_DELAY as `arena px4 setup` writes it.  PX4 applies it after a reboot, which SITL
    # denies (PREFLIGHT_REBOOT_SHUTDOWN), so PX4 boots with it, as a real vehicle comes back from one.
    stack, arena = px4_arena(("d1",), links={"d1": LINK}, px4_params={"d1": {"EKF2_EV_DELAY": want}})
    row = judged(arena)
    assert row["ok"] and float(row["have"]) == want, row
    flights(stack, arena, COMPENSATED)
    print(f"\nEKF2_EV_DELAY {want:g} ms; the radio relay's counts: {stack.relay_counts('d1')}")
    assert not stack.dead(), stack.dead()
    stack.close()

    print("\n| figure: median (range) of the flights | " + " | ".join(runs) + " |")
    print("|---|" + "---|" * len(runs))
    for f in FIGURES:
        cells = [
            f"{median(rs, f):.1f} ({min(r[f] for r in rs):.1f}–{max(r[f] for r in rs):.1f})" if rs else "–"
            for rs in runs.values()
        ]
        print(f"| {f} | " + " | ".join(cells) + " |")
    print("| flights | " + " | ".join(f"{len(rs)} of {FLIGHTS}" for rs in runs.values()) + " |")
    print("\n".join(f"{name}: {why}" for name, why in failed.items()))

    direct, compensated = runs[DIRECT], runs[COMPENSATED]
    lag = {name: median(rs, "estimate_lag_ms") for name, rs in runs.items() if rs}
    assert lag[COMPENSATED] - lag[DIRECT] <= NEAR_LAG_MS, lag
    # The aim (compensated, each of AIMED's medians within 20 % of the direct link's) is measured and printed,
    # not asserted: one flight's hover spreads over 3.7-11.9 cm on the direct link itself, so a median of ten
    # moves by more than 20 % from run to run (+14 % and +31 % in two runs; docs/px4.md, "PX4 SITL over a
    # slow link").
    for f in AIMED:
        ratio = median(compensated, f) / median(direct, f) - 1
        print(
            f"aim {f}: compensated {100 * ratio:+.0f} % of direct: {'within' if ratio <= AIM else 'NOT within'} 20 %"
        )
    # Uncompensated, measurably worse: its estimate lags further, or PX4 lost it and landed.
    assert UNCOMPENSATED in failed or lag[UNCOMPENSATED] >= lag[COMPENSATED] + WORSE_LAG_MS, (lag, failed)
