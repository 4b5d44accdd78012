"""MAVLink gateway: one process per vehicle between the arena bus and its PX4.

Vision poses (``arena/<drone>/vision``) go to the autopilot as ODOMETRY; its state, telemetry and events
come back (``arena/<drone>/state``, ``…/telemetry/<MSG>``, ``…/events``); commands are served on
``arena/<drone>/cmd``, offboard setpoints streamed from ``arena/<drone>/setpoint`` under leases and the
arena's safety rules, and ``arena/estop`` lands (or kills) the vehicle.  See
:mod:`arena_common.gateway.gateway`.
"""

from __future__ import annotations

import threading
from typing import Annotated

import typer

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import GatewayError
from arena_common.core.services import by_module
from arena_common.gateway.gateway import Gateway, GatewayOptions
from arena_common.gateway.origin import parse_origin
from arena_common.mavlink.signing import vehicle_key
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.service import running

SERVICE = by_module("services.mavlink_gateway").name  # its one name: arena_common/core/services.py


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    vehicle: str,
    gateway: GatewayOptions | None = None,
    host: str | None = None,
    stop: threading.Event | None = None,
) -> None:
    """Run the gateway of ``vehicle`` until ``stop`` is set (or SIGINT/SIGTERM)."""
    cfg.vehicle(vehicle)  # an unknown vehicle, or a bad signing key file, fails before anything opens
    vehicle_key(cfg, vehicle)
    with (
        running(SERVICE, cfg, options, vehicle=vehicle, host=host, stop=stop) as svc,
        Gateway(cfg, vehicle, svc.bus, options=gateway, stats=svc.stats, log=svc.log, clock=svc.clock) as gw,
    ):
        gw.run(svc.stop)


@service_command
def cli(
    shared: Shared,
    vehicle: Annotated[str, typer.Option("--vehicle", "-v", help="The vehicle to serve (config name).")],
    sysid: Annotated[int, typer.Option("--sysid", help="Our own MAVLink system id (not 255: QGC's).")] = 245,
    gcs: Annotated[
        str | None, typer.Option("--gcs", help="Forward MAVLink to a ground station (overrides the config).")
    ] = None,
    allow_gcs_manual: Annotated[
        bool,
        typer.Option("--allow-gcs-manual", help="Forward RC_CHANNELS_OVERRIDE/MANUAL_CONTROL from the GCS."),
    ] = False,
    telemetry_rate: Annotated[
        float | None,
        typer.Option(
            "--telemetry-rate", help="Raw telemetry per message type, Hz (0: none; default: config)."
        ),
    ] = None,
    state_rate: Annotated[
        float | None, typer.Option("--state-rate", help="State publications per second (default: config).")
    ] = None,
    origin: Annotated[
        str,
        typer.Option(
            "--origin",
            help="EKF global origin sent to the autopilot: LAT,LON,ALT (deg, deg, m AMSL), or 'off'.",
        ),
    ] = "0,0,0",
) -> None:
    """MAVLink gateway of one vehicle: vision out, state/telemetry/events in, commands, setpoints."""
    if not 1 <= sysid <= 254:
        raise typer.BadParameter(f"--sysid must be within 1..254, got {sysid}")
    if state_rate is not None and not state_rate > 0:
        raise typer.BadParameter(f"--state-rate must be positive, got {state_rate}")
    if telemetry_rate is not None and not telemetry_rate >= 0:
        raise typer.BadParameter(f"--telemetry-rate must not be negative, got {telemetry_rate}")
    try:
        origin_lla = parse_origin(origin)
    except GatewayError as exc:
        raise typer.BadParameter(f"--origin: {exc}") from None
    options = GatewayOptions(
        source_system=sysid,
        gcs=gcs,
        allow_gcs_manual=allow_gcs_manual,
        telemetry_rate=telemetry_rate,
        state_rate=state_rate,
        origin=origin_lla,
    )
    main(shared.config, shared.bus, vehicle=vehicle, gateway=options, host=shared.host)


if __name__ == "__main__":
    typer.run(cli)
