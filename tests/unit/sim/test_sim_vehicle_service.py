"""The sim_vehicle service with a real Zenoh session: true poses on arena/<name>/truth, MAVLink links.

A test router per test (conftest); the service runs in a thread; a pymavlink peer plays the gateway of
d1 and feeds it ODOMETRY made from the truth it receives over Zenoh, closing the loop.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from typer.testing import CliRunner

from arena_common.bus.session import Bus, Subscription
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig, SimSpec
from arena_common.core.errors import ConfigError
from arena_common.mavlink import px4
from arena_common.sim.autopilot import SimAutopilot, SimAutopilotError, SimClock
from services import sim_vehicle
from tests.unit.sim.test_sim_autopilot import ARENA, Gcs, free_port

SPEED = 4.0


class ZenohMocapGcs(Gcs):
    """The gateway stand-in, with its motion capture taken from the truth on Zenoh."""

    def __init__(self, url: str, clock: SimClock, target: int, truth: Subscription) -> None:
        super().__init__(url, clock, target)
        self.truth = truth
        self.latest: wire.Pose | None = None

    def pump(self, wait_real: float = 0.002) -> None:
        for item in self.truth.channel.drain():
            if item.payload is not None:
                self.latest = item.payload
        super().pump(wait_real)

    def send_mocap(self) -> None:
        pose = self.latest
        if pose is None:
            return
        args = px4.odometry_args(time.monotonic_ns() // 1000, pose.p, pose.q, pose.v)
        self.conn.mav.odometry_send(**args)


@pytest.fixture
def service(arena_config: Callable[..., ArenaConfig]) -> Iterator[Callable[..., tuple[ArenaConfig, Any]]]:
    running: list[tuple[threading.Event, threading.Thread]] = []
    errors: list[BaseException] = []

    def start(n_vehicles: int = 2, **kwargs: Any) -> tuple[ArenaConfig, threading.Thread]:
        cfg = arena_config(n_vehicles=n_vehicles, speed=SPEED)
        stop = threading.Event()

        def run() -> None:
            try:
                sim_vehicle.main(cfg, None, stop=stop, host="simhost", **kwargs)
            except BaseException as exc:
                errors.append(exc)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        running.append((stop, thread))
        return cfg, thread

    yield start
    for stop, thread in running:
        stop.set()
        thread.join(10.0)
        assert not thread.is_alive(), "the service did not stop"
    assert errors == []


def collect(sub: Subscription, until: Callable[[list[Any]], bool], timeout: float) -> list[Any]:
    items: list[Any] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        item = sub.get(0.05)
        if item is not None:
            assert item.error is None, item.error
            items.append(item)
            if until(items):
                return items
    raise AssertionError(f"timed out; got {len(items)} samples")


def test_truth_published_for_every_vehicle(
    service: Callable[..., tuple[ArenaConfig, threading.Thread]], bus_factory: Callable[[], Bus]
) -> None:
    bus = bus_factory()
    sub = bus.subscribe("arena/*/truth", capacity=100_000, ring=False)
    cfg, _ = service(n_vehicles=2)
    items = collect(sub, lambda xs: sum(1 for x in xs if x.key == keys.truth("d2")) >= 300, 10.0)
    by_key: dict[str, list[wire.Pose]] = {}
    for item in items:
        assert isinstance(item.payload, wire.Pose)
        by_key.setdefault(item.key, []).append(item.payload)
    assert set(by_key) == {keys.truth("d1"), keys.truth("d2")}
    for name, poses in (("d1", by_key[keys.truth("d1")]), ("d2", by_key[keys.truth("d2")])):
        north, east = cfg.vehicle(name).sim.start
        last = poses[-1]
        assert last.ok and last.vok
        assert last.p == pytest.approx((north, east, 0.0), abs=1e-9)  # resting on the floor at its start
        assert last.q == pytest.approx((1.0, 0.0, 0.0, 0.0), abs=1e-9)
        # One pose per physics tick, in order: every interval a whole number of ticks (more than one only
        # where a busy machine made the simulation skip time or a sample was dropped), and one tick apart
        # wherever two consecutive ticks arrived.  How many were skipped depends on the load, not asserted.
        intervals = [b.t - a.t for a, b in itertools.pairwise(poses)]
        tick_ns = 1e9 / sim_vehicle.PHYSICS_RATE
        assert all(i > 0 and abs(i / tick_ns - round(i / tick_ns)) < 1e-3 for i in intervals)
        assert min(intervals) == pytest.approx(tick_ns, abs=1e3)
    # Presence: the service's liveliness token (bounded retries while it propagates through the router).
    token = keys.alive("simhost", "sim-vehicle")
    assert any(token in bus.alive("arena/sys/alive/**") for _ in range(5))


def test_truth_rate_option(
    service: Callable[..., tuple[ArenaConfig, threading.Thread]], bus_factory: Callable[[], Bus]
) -> None:
    bus = bus_factory()
    sub = bus.subscribe(keys.truth("d1"), capacity=100_000, ring=False)
    service(n_vehicles=1, truth_rate=50.0)
    items = collect(sub, lambda xs: len(xs) >= 60, 10.0)
    intervals = sorted(b.payload.t - a.payload.t for a, b in itertools.pairwise(items))
    assert intervals[0] > 0
    assert intervals[len(intervals) // 2] == pytest.approx(1e9 / 50.0, abs=1e3)  # 50 Hz of simulated time


def test_flies_from_truth_over_zenoh(
    service: Callable[..., tuple[ArenaConfig, threading.Thread]], bus_factory: Callable[[], Bus]
) -> None:
    """The pymavlink gateway of d1 feeds back the truth it gets over Zenoh as vision, and flies d1."""
    bus = bus_factory()
    truth = bus.subscribe(keys.truth("d1"), capacity=1)
    cfg, _ = service(n_vehicles=2)
    v = cfg.vehicle("d1")
    gcs = ZenohMocapGcs(v.mavlink, SimClock(speed=SPEED), v.system_id, truth)
    try:
        gcs.wait_for(lambda: gcs.heartbeat is not None and gcs.latest is not None, 3.0, "heartbeat and truth")
        assert gcs.heartbeat.get_srcSystem() == v.system_id
        assert gcs.sources == {v.system_id}  # d2 talks on its own link
        start = gcs.latest.p  # type: ignore[union-attr]
        gcs.set_params(ARENA)
        gcs.mocap = True
        gcs.wait_for(lambda: gcs.texts_with("vision fusion started") != [], 2.0, "vision fusion")
        gcs.setpoint = {"x": start[0], "y": start[1], "z": -1.0}
        gcs.run_for(0.5)
        assert gcs.command(px4.MAV_CMD_DO_SET_MODE, 1, px4.MAIN_OFFBOARD) == px4.MAV_RESULT_ACCEPTED
        assert gcs.command(px4.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.MAV_RESULT_ACCEPTED
        gcs.wait_for(lambda: abs(gcs.latest.p[2] + 1.0) < 0.05, 15.0, "truth at 1 m")  # type: ignore[union-attr]
        p = gcs.latest.p  # type: ignore[union-attr]
        assert math.hypot(p[0] - start[0], p[1] - start[1]) < 0.5  # over its start, give or take PX4's wander
    finally:
        gcs.close()


def test_unknown_vehicle_and_bad_options(arena_config: Callable[..., ArenaConfig]) -> None:
    cfg = arena_config(n_vehicles=1)
    with pytest.raises(ConfigError, match="no vehicle 'nope'"):
        sim_vehicle.main(cfg, vehicles=["nope"])
    with pytest.raises(ConfigError, match="truth rate"):
        sim_vehicle.main(cfg, truth_rate=0.0)
    with pytest.raises(SimAutopilotError, match="speed"):
        sim_vehicle.main(cfg, speed=0.0)
    with pytest.raises(ConfigError, match="estimate lag"):
        sim_vehicle.main(cfg, estimate_lag=-0.1)
    clock = SimClock(speed=SPEED)
    aps = sim_vehicle.build_autopilots(cfg, clock, estimate_lag=0.15)
    try:
        assert [ap.sim.estimator.output_lag_s for ap in aps] == [0.15]
    finally:
        for ap in aps:
            ap.close()
    assert sim_vehicle.select_vehicles(cfg) == ["d1"]


def test_fidelity_chooses_px4s_flight_or_the_ideal_one(arena_config: Callable[..., ArenaConfig]) -> None:
    for fidelity, ideal in (("px4", False), ("ideal", True)):
        cfg = arena_config(n_vehicles=2, fidelity=fidelity)
        aps = sim_vehicle.build_autopilots(cfg, SimClock(speed=SPEED))
        try:
            assert [ap.ideal for ap in aps] == [ideal, ideal]
            assert [ap.sim.estimator.wander is None for ap in aps] == [ideal, ideal]
        finally:
            for ap in aps:
                ap.close()
    assert SimSpec().fidelity == "px4"  # the default


def test_cli_reports_bad_input(arena_config: Callable[..., ArenaConfig], tmp_path: Any) -> None:
    arena_config(n_vehicles=1)  # writes tmp_path/arena.toml
    app = __import__("typer").Typer()
    app.command()(sim_vehicle.cli)
    runner = CliRunner()
    result = runner.invoke(app, ["--config", str(tmp_path / "arena.toml"), "--vehicle", "nope"])
    assert result.exit_code == 2 and "no vehicle 'nope'" in result.output
    result = runner.invoke(app, ["--config", str(tmp_path / "arena.toml"), "--speed", "0"])
    assert result.exit_code == 2 and "speed" in result.output
    assert "--speed" in runner.invoke(app, ["--help"]).output


def test_a_vehicle_that_skips_simulated_time_is_counted_and_logged() -> None:
    # A loop held back longer than MAX_CATCH_UP_S (a busy machine) skips that time: the service says so.
    ap = SimAutopilot(f"udpout:127.0.0.1:{free_port()}", 1, clock=SimClock(1.0), name="d1")
    counts: dict[str, int] = {}
    warnings: list[str] = []
    report = sim_vehicle._skip_reporter(
        [ap],
        lambda name, n: counts.__setitem__(name, counts.get(name, 0) + n),
        lambda fmt, *args: warnings.append(fmt % args),
    )
    try:
        ap.step()
        report()
        assert counts == {} and warnings == []  # nothing skipped yet: nothing said
        time.sleep(SimAutopilot.MAX_CATCH_UP_S + 0.25)
        ap.step()
        report()
        report()  # a skip is reported once
        assert ap.skipped_time_s >= 0.2
        assert counts == {"skipped_ms.d1": round(ap.skipped_time_s * 1000)}
        assert len(warnings) == 1 and warnings[0].startswith("d1: the simulation could not keep up"), warnings
    finally:
        ap.close()
