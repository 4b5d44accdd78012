"""The simulated world: the simulated vehicles and the Motive emulator, as two supervised processes.

``arena sim world deploy/sim.toml`` stands in for the room itself (the vehicles' autopilots and Motive);
the arena's own services then run as in the lab (``arena up``, or ``arena run …`` one by one).  Each
part is restarted if it dies and both stop on Ctrl-C, like every process ``arena up`` supervises.
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path
from typing import Annotated

import typer

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig
from arena_common.runtime.options import (
    ConfigOpt,
    ConnectOpt,
    HostOpt,
    ListenOpt,
    LogOpt,
    ModeOpt,
    ZConfigOpt,
    bus_options,
    chosen_config,
    load_config,
)
from arena_common.runtime.supervisor import Supervisor, sim_world_plan, supervise


def main(
    cfg: ArenaConfig,
    options: BusOptions | None = None,
    *,
    host: str | None = None,
    stop: threading.Event | None = None,
    log_level: str | None = None,
    python: str = sys.executable,
) -> Supervisor:
    """Run ``services.sim_vehicle`` and ``services.sim_mocap`` until ``stop`` (or SIGINT/SIGTERM)."""
    specs = sim_world_plan(cfg, host, options=options, python=python, log_level=log_level)
    return supervise(specs, stop)


def cli(
    config_arg: Annotated[Path | None, typer.Argument(help="Arena config file (or --config).")] = None,
    config: ConfigOpt = None,
    mode: ModeOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    zconfig: ZConfigOpt = None,
    host: HostOpt = None,
    log_level: LogOpt = "INFO",
) -> None:
    """The simulated world: simulated PX4 vehicles and a Motive emulator, each its own process."""
    cfg = load_config(chosen_config(config_arg, config))
    main(cfg, bus_options(mode, connect, listen, zconfig), host=host, log_level=log_level)


if __name__ == "__main__":
    typer.run(cli)
