"""``arena px4 check <drone>`` and ``arena px4 setup <drone>``: the arena's PX4 parameters, via the gateway.

Both go through the vehicle's gateway (its ``arena/<drone>/cmd`` queryable), which reads the parameters
the arena requires (:data:`arena_common.mavlink.px4.ARENA_REQUIRED_PARAMS`, INT32 values decoded bytewise) and,
for ``setup``, writes those that differ and reads every one back.  A table shows each parameter; the
exit status is 0 when all match, 1 when some differ or the vehicle did not answer.

``arena px4 keygen FILE`` writes a new MAVLink 2 signing key (64 hex digits, mode 600) for a vehicle's
``signing_key_file``; it prints the key's fingerprint, never the key.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import typer

from arena_common.bus.session import Bus, open_bus
from arena_common.cli._globals import bus as global_bus
from arena_common.cli._globals import config as global_config
from arena_common.core import keys, wire
from arena_common.core.errors import ArenaError
from arena_common.mavlink.signing import SigningError, generate_key_file, write_px4_secret

px4_app = typer.Typer(
    help="PX4 set-up of the arena's vehicles (through their gateways).", no_args_is_help=True
)

Drone = Annotated[str, typer.Argument(help="Vehicle name, as in the config.")]
Timeout = Annotated[float, typer.Option("--timeout", help="Seconds to wait for the vehicle's answer.")]
DISCOVERY_S = 3.0  # a fresh session may need a moment to learn the route to the gateway


def request(bus: Bus, drone: str, op: str, timeout: float) -> wire.CommandResult:
    """Send ``op`` to the gateway of ``drone``, retrying while no gateway answers (bus discovery)."""
    command = wire.Command(op=op, src="arena px4", timeout=timeout, t=wire.now_ns())
    key = keys.cmd(drone)
    give_up = time.monotonic() + DISCOVERY_S
    while True:
        result = bus.request(key, command)
        nobody = result.result == "TIMEOUT" and result.reason.startswith("no answer on")
        if not nobody or time.monotonic() >= give_up:
            return result
        time.sleep(0.2)


def _fmt(value: Any) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def table(report: dict[str, Any]) -> list[str]:
    """Lines of the parameter table of a check/setup report."""
    rows = report.get("params") or {}
    written = set(report.get("written") or ())
    lines = [f"{'parameter':<18} {'type':<7} {'want':>10} {'have':>10}  status"]
    for name, row in rows.items():
        if row.get("ok"):
            status = "ok (written)" if name in written else "ok"
        else:
            status = "NO ANSWER" if row.get("have") is None else "DIFFERS"
        want, have = _fmt(row.get("want")), _fmt(row.get("have"))
        lines.append(f"{name:<18} {row.get('type', ''):<7} {want:>10} {have:>10}  {status}")
    return lines


def _run(op: str, drone: str, timeout: float) -> None:
    cfg = global_config(required=False)
    try:
        keys.validate_name(drone)
        with open_bus(cfg.zenoh if cfg else None, global_bus()) as bus:
            result = request(bus, drone, op, timeout)
    except ArenaError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    if result.value.get("params"):
        for line in table(result.value):
            typer.echo(line)
    reboot = result.value.get("reboot_required") or []
    if reboot and result.value.get("rebooted"):
        typer.echo(
            f"rebooted the autopilot for {', '.join(reboot)} to take effect, then read every value back"
        )
    elif reboot:
        typer.echo(
            f"{', '.join(reboot)} take effect only after a reboot: `arena px4 reboot {drone}` or power-cycle"
            " the vehicle (arming is refused until then)"
        )
    verdict = f"{drone}: {op} {result.result}" + (f" — {result.reason}" if result.reason else "")
    typer.echo(verdict, err=not result.ok)
    if not result.ok:
        raise typer.Exit(1)


@px4_app.command("check")
def check(
    drone: Drone,
    timeout: Timeout = 10.0,
) -> None:
    """Read the arena's required PX4 parameters of DRONE and show which differ."""
    _run("check", drone, timeout)


@px4_app.command("setup")
def setup(
    drone: Drone,
    timeout: Timeout = 60.0,
) -> None:
    """Write the arena's required PX4 parameters of DRONE that differ, reboot it when one needs it, verify."""
    _run("setup", drone, timeout)


@px4_app.command("reboot")
def reboot(
    drone: Drone,
    timeout: Timeout = 60.0,
) -> None:
    """Reboot the autopilot of DRONE (refused when armed) and wait until it is back."""
    _run("reboot", drone, timeout)


@px4_app.command("keygen")
def keygen(
    file: Annotated[Path, typer.Argument(help="Key file to create (a vehicle's signing_key_file).")],
    force: Annotated[bool, typer.Option("--force", help="Replace an existing key file.")] = False,
    px4_file: Annotated[
        Path | None,
        typer.Option(
            "--px4-file",
            help="Also write the key in PX4's format, to copy to the SD card as /mavlink/.secret.",
        ),
    ] = None,
) -> None:
    """Write a new random MAVLink 2 signing key to FILE (64 hex digits, readable by you only)."""
    try:
        key = generate_key_file(file, overwrite=force)
        if px4_file is not None:
            write_px4_secret(px4_file, key)
    except SigningError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"{file}: new signing key {key.fingerprint} (fingerprint; the key itself stays in the file)")
    if px4_file is not None:
        typer.echo(f"{px4_file}: the same key for PX4 (copy it to the SD card as /mavlink/.secret)")
    typer.echo("set signing_key_file for the vehicle in the arena config; the vehicle needs the same key")


def register(app: typer.Typer) -> None:
    """Add ``px4`` to ``app``."""
    app.add_typer(px4_app, name="px4")
