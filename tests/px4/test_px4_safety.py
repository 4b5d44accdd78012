"""Safety on a real PX4 v1.16 (SITL, SIH), through the arena's unchanged pipeline.

- a user program killed in OFFBOARD: its setpoint leases lapse and PX4's own offboard-loss failsafe
  (COM_OBL_RC_ACT 4) lands the vehicle;
- mocap stopped while hovering: the arena declares the position not valid (state, client, event) and PX4
  takes its position-loss action after EKF2_NOAID_TOUT (1 s, set by ``arena px4 setup``); the vehicle's
  true drift until touchdown is measured;
- ``arena estop`` lands the vehicle, an estop with ``kill`` disarms it in the air;
- PX4's STATUSTEXT reaches ``arena/<d>/events`` and the user's error: an arming PX4 itself refuses.

Each checks PX4's own view (vehicle_status, failsafe_flags, vehicle_land_detected) and SIH's true pose;
figures are printed, only bounds asserted.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from arena_common.cli import app
from arena_common.core import keys, wire
from arena_common.core.errors import CommandError, CommandRejected
from tests.conftest import REPO, wait_for
from tests.px4.conftest import PX4ArenaFactory
from tests.px4.harness import FlightRecord, Px4View, Px4Watch

LAND_DETECT_WAIT_S = 5.0  # how long the mocap-loss test lets PX4 detect its landing before the kill
# On SIH's ground, in the arena frame.  SIH stops a vehicle at the ground by zeroing its velocity, not its
# position: one pressing down with some thrust (armed, before PX4 detects the landing) sinks ~4 cm/s
# (0.18-0.28 m below the floor measured after 2-5 s armed on it).
FLOOR_Z = (-0.05, 0.5)

# A user program that takes over the hovering vehicle with an offboard stream holding where it is.
VICTIM = """
import sys, time
from arena_common import Arena

arena = Arena(sys.argv[1], name="victim")
d1 = arena.vehicle("d1")
d1.wait_until(lambda v: v.position is not None and v.armed, 10.0, "a position")
with d1.offboard() as ctl:
    print("OFFBOARD", flush=True)
    time.sleep(600)
"""


def _horizontal(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _down(view: Px4View | None) -> bool:
    return view is not None and view.landed and not view.armed


def _events(arena_events: list[wire.Event], since_ns: int, kinds: tuple[str, ...]) -> list[str]:
    return [f"{e.kind}: {e.text}" for e in arena_events if e.t >= since_ns and e.kind in kinds]


def test_user_program_killed_in_offboard_px4_lands(px4_arena: PX4ArenaFactory, tmp_path: Path) -> None:
    stack, arena = px4_arena(("d1",))
    px4 = stack.px4["d1"]
    d1 = arena.vehicle("d1")
    record = FlightRecord(arena, "d1")
    script = tmp_path / "victim.py"
    script.write_text(VICTIM)

    with Px4Watch(px4) as watch:
        d1.arm()
        d1.takeoff(1.0, timeout=60)
        victim = subprocess.Popen(
            [sys.executable, str(script), str(stack.cfg.path)],
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            assert victim.stdout is not None
            line = victim.stdout.readline()  # blocks until the program is in OFFBOARD (or dies)
            assert line.strip() == "OFFBOARD", line + victim.stdout.read()
            wait_for(lambda: d1.mode == "OFFBOARD", 5, 0.05, "the arena's state in OFFBOARD")
            wait_for(lambda: watch.latest and watch.latest.nav == "OFFBOARD", 5, 0.05, "PX4 in OFFBOARD")
            time.sleep(1.0)
            killed_truth = record.latest_truth()
            killed_ns, killed = wire.now_ns(), time.monotonic()
            victim.send_signal(signal.SIGKILL)
            victim.wait(5)
        finally:
            if victim.poll() is None:
                victim.kill()
                victim.wait(5)
        assert killed_truth is not None

        lost = wait_for(
            lambda: watch.first(lambda v: "offboard_control_signal_lost" in v.flags, since=killed),
            timeout=10,
            interval=0.05,
            what="PX4 noticing the offboard signal lost",
        )
        landing = wait_for(
            lambda: watch.first(lambda v: v.nav == "AUTO_LAND", since=killed),
            timeout=15,
            interval=0.05,
            what="PX4's offboard-loss failsafe: AUTO_LAND",
        )
        down = wait_for(lambda: watch.first(_down, since=killed), 60, 0.1, "PX4 landed and disarmed")
        timeline = watch.timeline(killed)

    track = record.track(killed_ns)
    drift = max(_horizontal(p.p, killed_truth.p) for p in track)
    final = track[-1].p
    texts = _events(d1.events(), killed_ns, ("failsafe", "statustext", "mode"))
    print(
        f"\nprogram killed in OFFBOARD at {tuple(round(x, 2) for x in killed_truth.p)}: PX4 flags the "
        f"offboard signal lost after {lost.t - killed:.2f} s, lands (AUTO_LAND) after "
        f"{landing.t - killed:.2f} s, is down and disarmed after {down.t - killed:.2f} s; true drift "
        f"{drift:.2f} m, landed at {tuple(round(x, 3) for x in final)}\n  PX4: {timeline}\n  events: {texts}"
    )
    assert any(v.failsafe for v in watch.changes if v.t >= killed), watch.timeline(killed)
    assert FLOOR_Z[0] < final[2] < FLOOR_Z[1], final
    assert drift < 1.0, drift  # it lands where it was abandoned, give or take PX4's wander (0.3-0.7 m)
    assert any("failsafe" in t.lower() for t in texts), texts  # PX4's own words reached the events
    wait_for(lambda: not d1.armed and d1.landed == "on_ground", 10, 0.1, "the arena's state: on the ground")
    assert not stack.dead(), stack.dead()


def test_mocap_lost_position_declared_invalid_px4_lands(px4_arena: PX4ArenaFactory) -> None:
    stack, arena = px4_arena(("d1",))
    px4 = stack.px4["d1"]
    d1 = arena.vehicle("d1")
    record = FlightRecord(arena, "d1")

    raw_events = arena.bus.subscribe(keys.events("d1"), capacity=10_000, ring=False)
    with Px4Watch(px4) as watch:
        d1.arm()
        d1.takeoff(1.0, timeout=60)
        d1.hold()
        time.sleep(1.0)
        assert d1.position is not None and d1.state is not None and d1.state.p is not None
        lost_truth = record.latest_truth()
        assert lost_truth is not None
        lost_ns, lost = wire.now_ns(), time.monotonic()
        stack.stop("sim_mocap")  # the room goes dark: no pose reaches the gateway any more

        # The client never hands out a stale position: from some moment on, position is None.
        positions: list[tuple[float, tuple[float, float, float] | None]] = []
        flagged: tuple[float, tuple[str, ...]] | None = None
        deadline, down_at = time.monotonic() + 60, math.inf
        while time.monotonic() < min(deadline, down_at + LAND_DETECT_WAIT_S):
            now = time.monotonic()
            positions.append((now - lost, d1.position))
            state = d1.state
            invalid_now = state is not None and state.p is None
            if flagged is None and invalid_now and {"position_invalid", "dead_reckoning"} & set(state.fs):
                flagged = (now - lost, state.fs)
            truth = record.latest_truth()
            if down_at == math.inf and truth is not None and truth.p[2] > FLOOR_Z[0]:
                down_at = now  # touchdown
            if watch.latest is not None and watch.latest.landed:
                break
            time.sleep(0.02)
        assert down_at < math.inf, watch.timeline(lost)
        landed = watch.first(lambda v: v.landed, since=lost)
        # PX4 keeps the motors running on the floor until its land detector, on a drifting baro height,
        # calls it landed (5-34 s after touchdown, measured; once it saw a "takeoff" there and went on
        # descending) and disarms 2 s later: the operator cuts the motors.
        d1.kill()
        wait_for(lambda: watch.latest and not watch.latest.armed, 5, 0.05, "PX4 disarmed by the kill")
        timeline = watch.timeline(lost)

    track = record.track(lost_ns)
    touchdown = next((p for p in track if p.p[2] > FLOOR_Z[0]), track[-1])
    drift = max(_horizontal(p.p, lost_truth.p) for p in track if p.t <= touchdown.t)
    last_given = max((t for t, p in positions if p is not None), default=math.nan)
    invalid = watch.first(lambda v: "local_position_invalid" in v.flags, since=lost)
    actions = [v.nav for v in watch.changes if v.t >= lost]
    events = _events(d1.events(), lost_ns, ("estimator", "failsafe", "statustext", "mode"))
    print(
        f"\nmocap stopped at {tuple(round(x, 2) for x in lost_truth.p)}: the arena flags it after "
        f"{flagged[0] if flagged else math.nan:.2f} s ({flagged[1] if flagged else '-'}), the client's last "
        f"position {last_given:.2f} s after; PX4 local_position_invalid after "
        f"{invalid.t - lost if invalid else math.nan:.2f} s; true drift until touchdown "
        f"{drift:.2f} m (touchdown {(touchdown.t - lost_ns) / 1e9:.1f} s after; PX4's land detector: "
        f"{f'{landed.t - lost:.1f} s after' if landed else f'nothing {LAND_DETECT_WAIT_S:.0f} s later'})"
        f"\n  PX4: {timeline}\n"
        f"  events: {events}"
    )
    assert flagged is not None, positions[-5:]
    assert last_given < 1.0, last_given  # the client's position went None within a second, and stayed so
    assert all(p is None for t, p in positions if t > last_given)
    assert invalid is not None, timeline  # PX4's own view: the position is gone
    assert any(a in ("AUTO_LAND", "DESCEND") for a in actions), timeline  # its position-loss action
    assert FLOOR_Z[0] < track[-1].p[2] < FLOOR_Z[1], track[-1].p
    assert drift < 1.5, drift
    assert d1.state is not None and d1.state.p is None
    assert not stack.dead(), stack.dead()
    # The gateway's "estimator" event on arena/d1/events, as every subscriber receives it.
    items = raw_events.channel.drain()
    decoded = [
        i.payload.text for i in items if isinstance(i.payload, wire.Event) and i.payload.kind == "estimator"
    ]
    rejected = [str(i.error) for i in items if i.payload is None]
    assert not rejected, rejected
    assert any(t.startswith("position not valid") for t in decoded), decoded


def test_estop_lands_and_kill_disarms_in_the_air(px4_arena: PX4ArenaFactory) -> None:
    stack, arena = px4_arena(("d1",))
    px4 = stack.px4["d1"]
    d1 = arena.vehicle("d1")
    record = FlightRecord(arena, "d1")
    runner = CliRunner()

    with Px4Watch(px4) as watch:
        d1.arm()
        d1.takeoff(1.5, timeout=60)
        hover = record.latest_truth()
        assert hover is not None
        t_ns, t0 = wire.now_ns(), time.monotonic()
        res = runner.invoke(app, ["estop", "-c", str(stack.cfg.path), "--reason", "px4 tier"])
        assert res.exit_code == 0, res.output
        landing = wait_for(
            lambda: watch.first(lambda v: v.nav == "AUTO_LAND", since=t0), 10, 0.05, "PX4 landing (estop)"
        )
        wait_for(
            lambda: (p := record.latest_truth()) and p.p[2] > hover.p[2] + 0.3,
            timeout=10,
            interval=0.02,
            what="the vehicle descending",
        )
        # In the air, descending: cut the motors (the Arena's estop with kill, as `arena estop --kill`).
        cut = record.latest_truth()
        assert cut is not None
        assert cut.p[2] < -0.5, cut.p
        k_ns, k0 = wire.now_ns(), time.monotonic()
        arena.estop(kill=True, reason="px4 tier kill")
        disarmed = wait_for(
            lambda: watch.first(lambda v: not v.armed, since=k0), 5, 0.02, "PX4 disarmed by the kill"
        )
        # PX4 calls itself landed once disarmed; the truth says when it is down.
        wait_for(
            lambda: (p := record.latest_truth()) and p.p[2] > FLOOR_Z[0] and abs(p.v[2]) < 0.05,
            timeout=20,
            interval=0.1,
            what="the vehicle truly on the floor",
        )
        timeline = watch.timeline(t0)

    at_disarm = [p for p in record.track(k_ns) if p.t <= k_ns + int((disarmed.t - k0) * 1e9)]
    height_at_kill = -(at_disarm[-1].p[2] if at_disarm else cut.p[2])
    final = record.track(k_ns)[-1].p
    events = _events(d1.events(), t_ns, ("safety",))
    print(
        f"\nestop: PX4 AUTO_LAND {landing.t - t0:.2f} s after the CLI was called; kill at "
        f"{-cut.p[2]:.2f} m: PX4 disarmed {disarmed.t - k0:.2f} s later, the vehicle still "
        f"{height_at_kill:.2f} m up; it came down at {tuple(round(x, 3) for x in final)}\n  PX4: {timeline}\n"
        f"  events: {events}"
    )
    assert height_at_kill > 0.2, height_at_kill  # disarmed in the air: a kill, not a landing
    assert any("estop (px4 tier)" in e and "land → ACCEPTED" in e for e in events), events
    assert any("estop (px4 tier kill)" in e and "kill → ACCEPTED" in e for e in events), events
    assert FLOOR_Z[0] < final[2] < FLOOR_Z[1], final
    wait_for(lambda: not d1.armed, 5, 0.1, "the arena's state: disarmed")
    assert not stack.dead(), stack.dead()


def test_px4_refuses_arming_in_its_own_words(px4_arena: PX4ArenaFactory) -> None:
    # Vision not fused (EKF2_EV_CTRL 0, no GNSS, no magnetometer): PX4 has neither position nor heading and
    # refuses to arm; the gateway lets the arm through (require_setup false) so PX4 itself says no.
    stack, arena = px4_arena(
        ("d1",), px4_params={"d1": {"EKF2_EV_CTRL": 0}}, require_setup=False, fused=False
    )
    px4 = stack.px4["d1"]
    d1 = arena.vehicle("d1")
    wait_for(lambda: d1.state is not None and d1.state.vis_age is not None, 20, 0.1, "vision sent to PX4")
    # PX4 sends STATUSTEXT once it heard a ground station's heartbeat (the gateway's, 1 Hz): an arm in the
    # first second of the link can be refused before PX4 speaks to it (then its words come ~0.25 s late).
    time.sleep(2.0)
    t_ns = wire.now_ns()
    with pytest.raises(CommandRejected) as refused:
        d1.arm()
    error: CommandError = refused.value
    status = px4.listener("vehicle_status")
    said = [line.split("] ", 1)[1] for line in px4.lines if "Arming denied" in line]
    wait_for(
        lambda: any("Arming denied" in e for e in _events(d1.events(), t_ns, ("statustext",))),
        timeout=5,
        interval=0.05,
        what="PX4's STATUSTEXT on arena/d1/events",
    )
    texts = _events(d1.events(), t_ns, ("statustext", "failsafe", "command"))
    print(f"\narm → {error.result}: {error}\n  PX4's console: {said}\n  events: {texts}")
    assert error.result in ("DENIED", "TEMPORARILY_REJECTED"), error
    assert "autopilot says: Arming denied" in str(error), error  # PX4's own words, in the user's error
    assert status["arming_state"] == 1 and status["pre_flight_checks_pass"] is False, status
    assert said, list(px4.lines)[-20:]
    assert not d1.armed
    # PX4's whole text, as its console printed it: its 51 characters came in two STATUSTEXT chunks.
    whole = said[0].strip()
    assert f"statustext: {whole}" in texts, (whole, texts)
    assert f"autopilot says: {whole}" in str(error), error
