"""Simulated PX4 vehicles: the configured vehicles as simulated autopilots, their true poses on Zenoh.

Each ``autopilot = "sim"`` vehicle of the config (or each one named with ``--vehicle``) becomes a
:class:`~arena_common.sim.autopilot.SimAutopilot` on the mirror of its gateway's MAVLink connection
(:meth:`~arena_common.core.config.VehicleSpec.sim_mavlink`), starting on the floor at ``sim.start`` heading
``sim.yaw_deg``, with system id ``system_id``. All of them run in one thread. Every physics tick (or at
``--truth-rate``) each true pose is published as a :class:`~arena_common.core.wire.Pose` on
``arena/<name>/truth`` for the Motive emulator; its time ``t`` is the simulated clock, which reads like
the wall clock at ``--speed 1``.  A vehicle whose config names a ``signing_key_file`` signs its MAVLink
and refuses unsigned or replayed input, as PX4 with signing required does.  ``--estimate-lag`` passes
each estimate through a first-order lag (PX4 v1.16's trailed the truth by ~0.16 s with its default vision
noise, see docs/px4.md; 0, the default, hands on the filter's estimate as it is).  Simulated time a
vehicle skips because its loop fell behind the clock (a busy machine) is counted (``skipped_ms.<name>``
in the service's stats) and logged as a warning.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from typing import Annotated

import typer

from arena_common.bus.session import BusOptions, Publisher
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.core.services import by_module
from arena_common.mavlink import px4
from arena_common.mavlink.signing import vehicle_key
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.service import running
from arena_common.sim.autopilot import SimAutopilot, SimAutopilotError, SimClock, TruePose, run_autopilots

SERVICE = by_module("services.sim_vehicle").name  # its one name: arena_common/core/services.py
PHYSICS_RATE = 250.0  # Hz, the simulated autopilots' physics tick


def select_vehicles(cfg: ArenaConfig, names: Sequence[str] = ()) -> list[str]:
    """The vehicles to simulate: those named, else every ``autopilot = "sim"`` vehicle of the config.

    :class:`ConfigError` for an unknown name, a vehicle another autopilot flies, or nothing to simulate.
    """
    chosen = [cfg.vehicle(n) for n in names] if names else [v for v in cfg.vehicles.values() if v.simulated]
    for v in chosen:
        if not v.simulated:
            raise ConfigError(
                f"{cfg.path}: vehicles.{v.name}.autopilot is {v.autopilot!r}: not simulated here"
            )
    if not chosen:
        raise ConfigError(f'{cfg.path}: no vehicle has autopilot = "sim": nothing to simulate')
    return [v.name for v in chosen]


def build_autopilots(
    cfg: ArenaConfig, clock: SimClock, names: Sequence[str] = (), *, estimate_lag: float | None = None
) -> list[SimAutopilot]:
    """One simulated autopilot per selected vehicle, sharing ``clock``; closes them all on failure.

    They fly as ``sim.fidelity`` says; ``estimate_lag`` (s), when given, is the time constant of the
    first-order lag of each vehicle's estimate (0: none) instead of that fidelity's.
    """
    built: list[SimAutopilot] = []
    # "arena": as a lab's vehicle after `arena px4 setup`; "px4": a fresh PX4 with its defaults.
    preset = (
        {k: v for k, (v, _) in px4.ARENA_REQUIRED_PARAMS.items()} if cfg.sim.px4_params == "arena" else {}
    )
    try:
        for index, name in enumerate(select_vehicles(cfg, names)):
            v = cfg.vehicle(name)
            north, east = v.sim.start
            built.append(
                SimAutopilot(
                    v.sim_mavlink(),
                    v.system_id,
                    clock=clock,
                    name=v.name,
                    position=(north, east, 0.0),
                    yaw=math.radians(v.sim.yaw_deg),
                    seed=cfg.sim.seed + index,
                    params=preset,
                    signing_key=vehicle_key(cfg, name),
                    estimate_lag=estimate_lag,
                    ideal=cfg.sim.fidelity == "ideal",
                    link_delay=v.sim.link_delay_s,
                )
            )
    except BaseException:
        for ap in built:
            ap.close()
        raise
    return built


def truth_pose(pose: TruePose) -> wire.Pose:
    """A simulated vehicle's true pose as a :class:`~arena_common.core.wire.Pose`."""
    return wire.Pose(
        t=pose.time_ns,
        p=pose.position,
        q=pose.q,
        ok=True,
        v=pose.velocity,
        w=pose.rates,
        vok=True,
        tp=wire.now_ns(),
    )


def _truth_publisher(
    pub: Publisher[wire.Pose], period_ns: int, count: Callable[[str], None]
) -> Callable[[TruePose], None]:
    """A per-tick callback publishing at most one pose per ``period_ns`` of simulated time."""
    next_due = 0

    def on_tick(pose: TruePose) -> None:
        nonlocal next_due
        if pose.time_ns >= next_due:
            # Half a period of tolerance: a period equal to the physics tick publishes every tick.
            next_due = max(next_due + period_ns, pose.time_ns + period_ns // 2)
            pub.put(truth_pose(pose))
            count("truth")

    return on_tick


def _skip_reporter(
    autopilots: Sequence[SimAutopilot], count: Callable[[str, int], None], warn: Callable[..., None]
) -> Callable[[], None]:
    """A per-round callback that counts (``skipped_ms.<name>``) and logs the simulated time each vehicle
    skipped because its loop could not keep up with the wall clock (a busy machine): a skip is a gap in
    its flight that processes on the wall clock see, never a silent one."""
    seen = {ap.name: 0.0 for ap in autopilots}

    def after_step() -> None:
        for ap in autopilots:
            skipped = ap.skipped_time_s - seen[ap.name]
            if skipped > 0.0:
                seen[ap.name] = ap.skipped_time_s
                count(f"skipped_ms.{ap.name}", round(skipped * 1000))
                warn(
                    "%s: the simulation could not keep up with the clock (a busy machine): skipped %.0f ms "
                    "of its flight (%.0f ms in all)",
                    ap.name,
                    skipped * 1000,
                    ap.skipped_time_s * 1000,
                )

    return after_step


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    vehicles: Sequence[str] = (),
    speed: float | None = None,
    truth_rate: float = PHYSICS_RATE,
    estimate_lag: float | None = None,
    host: str | None = None,
    stop: threading.Event | None = None,
) -> None:
    """Run the simulated vehicles until ``stop`` is set (or SIGINT/SIGTERM in the main thread).

    ``speed`` overrides ``sim.speed``; ``truth_rate`` (Hz of simulated time) limits how often each
    true pose is published (at most once per physics tick); ``estimate_lag`` (s, 0..5), when given,
    replaces the time constant of the lag of each vehicle's estimate behind its filter (``sim.fidelity``
    "px4": PX4's, docs/px4.md; "ideal": none).
    """
    if not truth_rate > 0:
        raise ConfigError(f"truth rate must be positive, got {truth_rate}")
    if estimate_lag is not None and not (math.isfinite(estimate_lag) and 0.0 <= estimate_lag <= 5.0):
        raise ConfigError(f"estimate lag must be within 0..5 s, got {estimate_lag}")
    names = select_vehicles(cfg, vehicles)  # fail on an unknown name before opening anything
    clock = SimClock(cfg.sim.speed if speed is None else speed)
    period_ns = int(1e9 / truth_rate)
    with running(SERVICE, cfg, options, host=host, stop=stop) as svc:
        autopilots = build_autopilots(cfg, clock, names, estimate_lag=estimate_lag)
        try:
            for ap in autopilots:
                ap.on_tick = _truth_publisher(
                    svc.bus.stream_publisher(keys.truth(ap.name), wire.Pose), period_ns, svc.stats.count
                )

            svc.log.info(
                "simulating %s at speed %.2f",
                ", ".join(
                    f"{ap.name} (sysid {ap.system_id}, {ap.connection}"
                    + (f", signed with key {ap.signing.key.fingerprint})" if ap.signing else ")")
                    for ap in autopilots
                ),
                clock.speed,
            )
            run_autopilots(
                autopilots,
                stop=svc.stop,
                after_step=_skip_reporter(autopilots, svc.stats.count, svc.log.warning),
            )
        finally:
            for ap in autopilots:
                ap.close()


@service_command
def cli(
    shared: Shared,
    vehicle: Annotated[
        list[str] | None, typer.Option("--vehicle", "-v", help="Simulate only this vehicle (repeatable).")
    ] = None,
    speed: Annotated[
        float | None, typer.Option("--speed", help="Simulated time per real time (default: sim.speed).")
    ] = None,
    truth_rate: Annotated[
        float, typer.Option("--truth-rate", help="True poses published per simulated second, per vehicle.")
    ] = PHYSICS_RATE,
    estimate_lag: Annotated[
        float | None,
        typer.Option(
            "--estimate-lag",
            help="Time constant (s) of a first-order lag of each estimate (0: none; default: sim.fidelity's).",
        ),
    ] = None,
) -> None:
    """Simulated PX4 vehicles speaking MAVLink 2, with their true poses on arena/<name>/truth."""
    try:
        main(
            shared.config,
            shared.bus,
            vehicles=vehicle or (),
            speed=speed,
            truth_rate=truth_rate,
            estimate_lag=estimate_lag,
            host=shared.host,
        )
    except SimAutopilotError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


if __name__ == "__main__":
    typer.run(cli)
