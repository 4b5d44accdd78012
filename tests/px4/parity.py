"""One program of every manoeuvre the client offers, and the figures it reads from the true pose.

The parity tier (tests/px4/test_px4_parity.py) flies :func:`fly` on PX4 v1.16 SITL and on the arena's
simulated autopilot (``fidelity = "px4"``), each through the whole arena, and compares the figures of
:data:`FIGURES`.  Every figure is read from the vehicle's true pose (``arena/<d>/truth``: SIH's on PX4,
the simulated world's otherwise) and the autopilot's state, the same way for both; times are the
program's own (arena seconds, real time here).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from arena_common import Arena, Trajectory
from arena_common.client import Vehicle
from arena_common.core import wire
from tests.px4.harness import FlightRecord

HEIGHT = 1.0  # m, the take-off height
VELOCITY = 0.5  # m/s, the offboard velocity block's command, held for VELOCITY_S
VELOCITY_S = 2.0
STOPPED = 0.1  # m/s: below this (horizontal, true) the vehicle has stopped after a block
STEP = 1.2  # m, the position stream's step west (larger than the hover's wander)
CLIMB_THRUST = 0.05  # above hover thrust, level, for CLIMB_S: the attitude stream's block
CLIMB_S = 1.0


@dataclass(frozen=True)
class Figure:
    """One figure of the program: its words, unit, and the tolerance of the parity tier."""

    name: str
    words: str
    unit: str
    absolute: float = 0.0  # the tolerance is the larger of this (in ``unit``) and 25 % of PX4's figure

    def tolerance(self, px4: float) -> float:
        """How far the simulation's figure may lie from PX4's ``px4``."""
        return max(0.25 * abs(px4), self.absolute)


#: The figures :func:`fly` returns, in the order of the program (and of docs/px4.md's table).
FIGURES: tuple[Figure, ...] = (
    Figure("takeoff_s", f"`takeoff({HEIGHT})` returns after", "s"),
    Figure("hover_p50_cm", "hover (Hold) 8 s: distance from its median, p50", "cm", 5.0),
    Figure("hover_max_cm", "hover (Hold) 8 s: distance from its median, max", "cm", 5.0),
    Figure("goto_s", "`goto` 1 m north (the gateway's own): returns after", "s"),
    Figure("goto_end_cm", "`goto`: mean position 1–3 s after, from the goal", "cm", 5.0),
    Figure("traj_max_cm", "3-waypoint trajectory over 9 s: max deviation from the setpoint", "cm", 5.0),
    Figure("traj_rms_cm", "3-waypoint trajectory: tracking rms", "cm", 5.0),
    Figure("velocity_ms", f"offboard velocity {VELOCITY} m/s for {VELOCITY_S:.0f} s: speed reached", "m/s"),
    Figure("exit_coast_cm", "leaving that block (Hold): coast", "cm", 5.0),
    Figure("exit_stop_s", f"leaving that block: stopped (< {STOPPED} m/s) after", "s"),
    Figure("step_half_s", f"position stream, a {STEP} m step: half-way after", "s"),
    Figure("step_peak_ms", "position stream step: peak speed", "m/s"),
    Figure(
        "climb_cm",
        f"attitude stream, level at hover + {CLIMB_THRUST} for {CLIMB_S:.0f} s: height gained",
        "cm",
        5.0,
    ),
    Figure("estimate_p50_cm", "estimate − truth in flight, horizontal p50", "cm", 5.0),
    Figure("estimate_max_cm", "estimate − truth in flight, horizontal max", "cm", 5.0),
    Figure("estimate_lag_ms", "estimate behind the truth (best-fitting shift)", "ms"),
    Figure("touchdown_s", "`land()`: on the floor (true height < 5 cm) after", "s"),
    Figure("land_s", "`land()` returns (landed, disarmed) after", "s"),
)


def _speed(p: wire.Pose) -> float:
    return math.hypot(p.v[0], p.v[1]) if p.v is not None else math.nan


def _track_p(record: FlightRecord, t0: int, t1: int | None = None) -> np.ndarray:
    return np.array([p.p for p in record.track(t0, t1)])


def _stop_after(record: FlightRecord, t0: int, within: float = 5.0) -> tuple[float, float]:
    """(coast [m], seconds) from ``t0`` until the true horizontal speed stays below :data:`STOPPED`
    for 0.3 s; waits up to ``within`` seconds for it (seconds NaN when it never did)."""
    deadline = time.monotonic() + within
    while True:
        track = record.track(t0)
        still = None  # the first sample of the current run below STOPPED
        for p in track:
            if not _speed(p) < STOPPED:
                still = None
            elif still is None:
                still = p
            elif p.t - still.t >= 290_000_000:
                break
        else:
            still = None  # the run (if any) has not lasted yet
        if still is not None or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    end = still or track[-1]
    coast = math.dist(track[0].p[:2], end.p[:2])
    return coast, (end.t - t0) / 1e9 if still else math.nan


def _takeoff(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    v.arm()
    out["takeoff_s"] = v.takeoff(HEIGHT, timeout=60)
    time.sleep(3.0)  # settle


def _hover(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    t0 = wire.now_ns()
    time.sleep(8.0)
    hover = _track_p(record, t0)
    dist = np.linalg.norm(hover - np.median(hover, axis=0), axis=1)
    out["hover_p50_cm"], out["hover_max_cm"] = 100 * float(np.median(dist)), 100 * float(dist.max())


def _goto(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    here = v.position
    assert here is not None
    goal = (here[0] + 1.0, here[1], -HEIGHT)
    t = time.monotonic()
    v.goto(*goal, timeout=30)
    out["goto_s"] = time.monotonic() - t
    time.sleep(1.0)
    t0 = wire.now_ns()
    time.sleep(2.0)
    mean = _track_p(record, t0).mean(axis=0)
    out["goto_end_cm"] = 100 * math.dist(mean, goal)


def _trajectory(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    here = v.position
    assert here is not None
    n, e = here[0], here[1]
    trajectory = Trajectory.waypoints(
        [
            (0.0, (n, e, -HEIGHT)),
            (3.0, (n - 0.8, e, -1.2)),
            (6.0, (n - 0.8, e + 0.6, -1.2)),
            (9.0, (n, e + 0.6, -HEIGHT)),
        ],
        yaw=0.0,
    )
    with v.offboard(rate=30) as ctl:
        t0 = wire.now_ns()
        ctl.follow(trajectory)
        t1 = wire.now_ns()
        time.sleep(2.0)
    errors = [math.dist(p.p, trajectory.sample((p.t - t0) / 1e9).p) for p in record.track(t0, t1)]
    out["traj_max_cm"] = 100 * max(errors)
    out["traj_rms_cm"] = 100 * math.sqrt(float(np.mean(np.square(errors))))


def _velocity(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    with v.offboard() as ctl:
        ctl.velocity(-VELOCITY, 0.0, 0.0, yaw=0.0)
        t0 = wire.now_ns()
        time.sleep(VELOCITY_S)
        late = [_speed(p) for p in record.track(t0 + int((VELOCITY_S - 0.5) * 1e9))]
    t_exit = wire.now_ns()
    out["velocity_ms"] = float(np.median(late))
    coast, out["exit_stop_s"] = _stop_after(record, t_exit)
    out["exit_coast_cm"] = 100 * coast
    time.sleep(2.0)


def _step(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    here = v.position
    start = record.latest_truth()
    assert here is not None and start is not None
    with v.offboard() as ctl:
        ctl.position(here[0], here[1] - STEP, -HEIGHT, yaw=0.0)
        t0 = wire.now_ns()
        time.sleep(5.0)
    step = record.track(t0)
    half = next((p.t for p in step if start.p[1] - p.p[1] >= STEP / 2), None)
    out["step_half_s"] = (half - t0) / 1e9 if half is not None else math.nan
    out["step_peak_ms"] = max(_speed(p) for p in step)
    time.sleep(2.0)


def _attitude(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    hover_thrust = float(v.params.get("MPC_THR_HOVER"))
    before = record.latest_truth()
    assert before is not None
    with v.offboard() as ctl:
        ctl.attitude(0.0, 0.0, 0.0, hover_thrust + CLIMB_THRUST)
        t0 = wire.now_ns()
        time.sleep(CLIMB_S)
        at_end = record.latest_truth()
    assert at_end is not None
    climb = [p for p in record.track(t0) if p.t <= t0 + int(CLIMB_S * 1e9)]
    out["climb_cm"] = 100 * (-(climb[-1] if climb else at_end).p[2] + before.p[2])
    time.sleep(3.0)


def _land(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    t, t0 = time.monotonic(), wire.now_ns()
    v.land(timeout=90)
    out["land_s"] = time.monotonic() - t
    down = next((p.t for p in record.track(t0) if -p.p[2] < 0.05), None)
    out["touchdown_s"] = (down - t0) / 1e9 if down is not None else math.nan


def _back(v: Vehicle, record: FlightRecord, out: dict[str, float]) -> None:
    """Fly back over where the flight took off (its first true pose), so that a program flown again in a
    row starts from the same place: not a figure."""
    first = record.track(0)[0]
    v.goto(first.p[0], first.p[1], -HEIGHT, timeout=30)


Manoeuvre = Callable[[Vehicle, FlightRecord, dict[str, float]], None]

#: The program, in order: each manoeuvre is a phase of the flight record and adds its figures.
MANOEUVRES: dict[str, Manoeuvre] = {
    "takeoff": _takeoff,
    "hover": _hover,
    "goto": _goto,
    "trajectory": _trajectory,
    "velocity": _velocity,
    "step": _step,
    "attitude": _attitude,
    "land": _land,
    "back": _back,
}
#: The parity program: every manoeuvre the client offers, in order.
PROGRAM = ("takeoff", "hover", "goto", "trajectory", "velocity", "step", "attitude", "land")
IN_FLIGHT = ("hover", "goto", "trajectory", "velocity", "step")  # the estimate is judged over these


def fly(
    arena: Arena, name: str, record: FlightRecord, manoeuvres: Sequence[str] = PROGRAM
) -> dict[str, float]:
    """Fly ``manoeuvres`` (of :data:`MANOEUVRES`; takeoff first, land last) on ``name`` (on the ground,
    vision fused) and return their figures by name, with the estimate's error over the flight."""
    v = arena.vehicle(name)
    out: dict[str, float] = {}
    try:
        for manoeuvre in manoeuvres:
            record.phase(manoeuvre)
            MANOEUVRES[manoeuvre](v, record, out)
        record.phase("ground")
    finally:
        record.close()
    estimate = [record.figure(phase) for phase in IN_FLIGHT if phase in manoeuvres]
    out["estimate_p50_cm"] = 100 * float(np.median([f.horizontal_p50 for f in estimate]))
    out["estimate_max_cm"] = 100 * max(f.horizontal_max for f in estimate)
    out["estimate_lag_ms"] = 1000 * record.lag()[0]
    return out


def median(runs: Sequence[Mapping[str, float]], figure: Figure) -> float:
    """The figure's median over ``runs``."""
    return float(np.median([r[figure.name] for r in runs]))


def within(px4: float, sim: float, figure: Figure) -> bool:
    """True when the simulation's figure is within the figure's :meth:`Figure.tolerance` of PX4's (False
    when either is NaN: a manoeuvre that never reached its mark)."""
    return abs(sim - px4) <= figure.tolerance(px4)


def bounds(px4: float, flights: Sequence[float], figure: Figure) -> tuple[float, float]:
    """Where the simulation's figure may lie when PX4 varies from flight to flight: from the least to the
    most of PX4's figures (this run's ``px4`` and its earlier ``flights``), each end widened by its
    tolerance; never below zero for a figure PX4 never gave negative (a distance, a time)."""
    lo, hi = min(px4, *flights), max(px4, *flights)
    least = lo - figure.tolerance(lo)
    return (max(0.0, least) if lo >= 0 else least), hi + figure.tolerance(hi)


def verdict(px4: float, sim: float, figure: Figure, flights: Sequence[float] | None) -> tuple[bool, str]:
    """Whether ``sim`` passes, and the table's words for it: within the tolerance of PX4's figure or, for a
    figure PX4 varies (its earlier ``flights`` given), within :func:`bounds`."""
    if flights is None:
        return within(px4, sim, figure), f"±{figure.tolerance(px4):.2g}"
    lo, hi = bounds(px4, flights, figure)
    d = _digits(figure)
    return lo <= sim <= hi, f"{lo:.{d}f}–{hi:.{d}f}: PX4's {len(flights) + 1} flights, ± tolerance"


def apart(
    px4: Sequence[Mapping[str, float]],
    sim: Sequence[Mapping[str, float]],
    varies: Mapping[str, Sequence[float]],
) -> list[str]:
    """The figures whose simulated median fails its :func:`verdict` (``varies``: PX4's earlier flights of
    the figures it varies), in words."""
    out = []
    for f in FIGURES:
        real, simulated = median(px4, f), median(sim, f)
        ok, words = verdict(real, simulated, f, varies.get(f.name))
        if not ok:
            out.append(f"{f.words}: PX4 {real:.3g} {f.unit}, simulated {simulated:.3g} {f.unit} ({words})")
    return out


def table(
    px4: Sequence[Mapping[str, float]],
    sim: Sequence[Mapping[str, float]],
    varies: Mapping[str, Sequence[float]],
) -> str:
    """The side-by-side table (Markdown): each figure's median over the runs, and their range; for the
    figures of ``varies``, PX4's earlier flights too."""

    def cell(runs: Sequence[Mapping[str, float]], f: Figure) -> str:
        values, d = [r[f.name] for r in runs], _digits(f)
        mid = f"{median(runs, f):.{d}f}"
        if len(values) > 1:
            mid += f" ({min(values):.{d}f}–{max(values):.{d}f})"
        return mid

    rows = [
        f"| manoeuvre, figure | unit | PX4 SITL ({len(px4)} run{'s' * (len(px4) > 1)}) | simulated "
        f"({len(sim)} run{'s' * (len(sim) > 1)}) | within |",
        "|---|---|---|---|---|",
    ]
    for f in FIGURES:
        real, flights = median(px4, f), varies.get(f.name)
        ok, words = verdict(real, median(sim, f), f, flights)
        px4_cell = cell(px4, f)
        if flights is not None:
            px4_cell += "; earlier: " + ", ".join(f"{x:.{_digits(f)}f}" for x in flights)
        rows.append(
            f"| {f.words} | {f.unit} | {px4_cell} | {cell(sim, f)} | {'yes' if ok else '**no**'} ({words}) |"
        )
    return "\n".join(rows)


def _digits(f: Figure) -> int:
    return 2 if f.unit in ("s", "m/s") else 0 if f.unit == "ms" else 1
