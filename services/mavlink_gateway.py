"""MAVLink gateway: one process per vehicle between the arena bus and its PX4.

Vision poses (``arena/<drone>/vision``) go to the autopilot as ODOMETRY; its state, telemetry and events
come back (``arena/<drone>/state``, ``…/telemetry/<MSG>``, ``…/events``); commands are served on
``arena/<drone>/cmd``, offboard setpoints streamed from ``arena/<drone>/setpoint`` under leases and the
arena's safety rules, and ``arena/estop`` lands (or kills) the vehicle.  See
:mod:`arena_common.gateway.gateway`.
"""

from __future__ import annotations

import threading
from typing import Annotated, Any

import typer

from arena_common.bus.exposure import check_exposure
from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.core.services import by_module
from arena_common.core.vehiclespec import override
from arena_common.gateway.gateway import Gateway, GatewayOptions
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


#: Each flag and the field of the vehicle's config section it overrides (checked with that field's bounds).
FLAGS: dict[str, str] = {
    "--sysid": "gateway_system_id",
    "--gcs": "gcs",
    "--allow-gcs-manual": "allow_gcs_manual",
    "--telemetry-rate": "telemetry_rate",
    "--state-rate": "state_rate",
    "--origin": "origin",
}


def overridden(cfg: ArenaConfig, vehicle: str, given: dict[str, Any]) -> ArenaConfig:
    """``cfg`` with the flags ``given`` (flag → value; None: not given) in the vehicle's section, each
    checked against the config field's own bounds, the whole against the network-exposure rules (a
    ``--gcs`` listening beyond loopback is refused as in the config); :class:`typer.BadParameter` naming
    flag and field."""
    v = cfg.vehicle(vehicle)
    for flag, value in given.items():
        if value is None:
            continue
        if flag == "--origin":
            value = "off" if value.strip().lower() in ("off", "none", "no") else _numbers(value)
        try:
            v = override(v, {FLAGS[flag]: value}, flag)
        except ConfigError as exc:
            raise typer.BadParameter(str(exc)) from None
    cfg = cfg.replace(vehicles={**cfg.vehicles, vehicle: v})
    try:
        check_exposure(cfg)  # a flag may not open to the network what the config may not
    except ConfigError as exc:
        raise typer.BadParameter(f"with the flags given: {exc}") from None
    return cfg


def _numbers(text: str) -> list[float] | str:
    """``"LAT,LON,ALT"`` as numbers (the text itself when it is not, for the field's error to name)."""
    try:
        return [float(p) for p in text.split(",")]
    except ValueError:
        return text


@service_command
def cli(
    shared: Shared,
    vehicle: Annotated[str, typer.Option("--vehicle", "-v", help="The vehicle to serve (config name).")],
    sysid: Annotated[
        int | None,
        typer.Option("--sysid", help="Our own MAVLink system id, 1..254 (default: config, 245)."),
    ] = None,
    gcs: Annotated[
        str | None, typer.Option("--gcs", help="Forward MAVLink to a ground station (default: config).")
    ] = None,
    allow_gcs_manual: Annotated[
        bool,
        typer.Option(
            "--allow-gcs-manual",
            help="Forward RC_CHANNELS_OVERRIDE/MANUAL_CONTROL from the GCS (default: config, no).",
        ),
    ] = False,
    telemetry_rate: Annotated[
        float | None,
        typer.Option(
            "--telemetry-rate", help="Raw telemetry per message type, Hz, 0..200 (0: none; default: config)."
        ),
    ] = None,
    state_rate: Annotated[
        float | None,
        typer.Option("--state-rate", help="State publications per second, 1..200 (default: config)."),
    ] = None,
    origin: Annotated[
        str | None,
        typer.Option(
            "--origin",
            help="EKF global origin sent to the autopilot: LAT,LON,ALT (deg, deg, m AMSL), or 'off' "
            "(default: config, 0,0,0).",
        ),
    ] = None,
) -> None:
    """MAVLink gateway of one vehicle: vision out, state/telemetry/events in, commands, setpoints.

    Its settings are the vehicle's config section; each flag overrides one field, within its bounds."""
    given = {
        "--sysid": sysid,
        "--gcs": gcs,
        "--allow-gcs-manual": True if allow_gcs_manual else None,  # given: allowed; not given: the config
        "--telemetry-rate": telemetry_rate,
        "--state-rate": state_rate,
        "--origin": origin,
    }
    cfg = overridden(shared.config, vehicle, given)
    main(cfg, shared.bus, vehicle=vehicle, host=shared.host)


if __name__ == "__main__":
    typer.run(cli)
