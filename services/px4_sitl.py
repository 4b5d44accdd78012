"""PX4 SITL: a real PX4 v1.16 autopilot (SIH simulator) for one ``autopilot = "px4-sitl"`` vehicle.

``arena up`` runs one per PX4 SITL vehicle, on the host that runs the vehicle's gateway (PX4 SITL talks
on loopback only).  It boots instance ``px4_instance`` (:class:`~arena_common.runtime.px4_sitl.Px4Sitl`) with
the boot parameters :func:`~arena_common.runtime.px4_sitl.arena_boot_params` gives for ``sim.px4_params``
("arena": as ``arena px4 setup`` leaves a lab's vehicle; "px4": PX4's defaults) and the vehicle's own
``px4_params``; PX4's lines are printed as they come (``arena up`` prefixes them ``[px4-sitl.<d>]``).

When px4 exits while this service runs (``px4-shutdown --instance N``: SITL does not implement the
MAVLink reboot command, it answers DENIED), it is booted again with the same working directory, so the
parameters it saved survive, as across a real autopilot's reboot; boot parameters are applied again at
each boot.  Stats: ``boots`` (a counter) and ``up`` (1 while px4 runs).  The ground truth goes to the
Motive emulator through ``services.px4_truth``.
"""

from __future__ import annotations

import os
import sys
import threading
from typing import Annotated

import typer

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig
from arena_common.core.services import by_module
from arena_common.runtime.command import Shared, service_command
from arena_common.runtime.px4_sitl import Px4Sitl, boot_params, sitl_vehicle
from arena_common.runtime.service import running

SERVICE = by_module("services.px4_sitl").name  # its one name: arena_common/core/services.py
REBOOT_DELAY = 0.5  # s between px4 exiting and booting again


def _print(line: str) -> None:
    if not line.strip():
        return
    try:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()
    except (OSError, ValueError):
        pass


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    vehicle: str,
    host: str | None = None,
    stop: threading.Event | None = None,
    build: str | None = None,
    ready_timeout: float = 60.0,
) -> None:
    """Run ``vehicle``'s PX4 SITL instance until ``stop`` is set (or SIGINT/SIGTERM), booting it again
    whenever it exits.  :class:`~arena_common.runtime.px4_sitl.Px4SitlError` when it cannot start (no build,
    instance already running, boot failure)."""
    spec = sitl_vehicle(cfg, vehicle)
    assert spec.px4_instance is not None
    px4 = Px4Sitl(
        spec.px4_instance,
        build=build,
        params=boot_params(cfg, spec),
        output=_print,
        ready_timeout=ready_timeout,
    )
    with running(SERVICE, cfg, options, vehicle=vehicle, host=host, stop=stop) as svc:
        svc.log.info(
            "PX4 SITL instance %d (build %s): system id %d, offboard link → udp 127.0.0.1:%d, "
            "%d boot parameters",
            px4.instance,
            px4.build,
            px4.ports.system_id,
            px4.ports.offboard,
            len(px4.params),
        )
        try:
            while not svc.stopped:
                px4.start()
                boot = px4.wait_ready()
                svc.stats.count("boots")
                svc.stats.set("up", 1)
                svc.log.info(
                    "PX4 ready in %.2f s (boot %d, working directory %s)", boot, px4.boots, px4.workdir
                )
                while px4.alive and not svc.sleep(0.2):
                    pass
                svc.stats.set("up", 0)
                if svc.stopped:
                    break
                svc.log.warning(
                    "px4 exited with status %s: booting it again with its saved parameters", px4.returncode
                )
                svc.sleep(REBOOT_DELAY)
        finally:
            code = px4.stop(timeout=3.0)
            svc.log.info("px4 stopped (status %s)", code)


@service_command
def cli(
    shared: Shared,
    vehicle: Annotated[str, typer.Option("--vehicle", "-v", help="The PX4 SITL vehicle to fly.")],
    build: Annotated[
        str | None,
        typer.Option("--build", help="The PX4 SITL build (default: $PX4_SITL_DIR, else ../shared/px4-sitl)."),
    ] = None,
) -> None:
    """A real PX4 SITL autopilot (SIH) for one vehicle, booted again whenever it exits."""
    main(shared.config, shared.bus, vehicle=vehicle, host=shared.host, build=build)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    typer.run(cli)
