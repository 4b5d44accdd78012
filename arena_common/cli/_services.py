"""``arena run <service>`` and ``arena sim <part>``: run one arena process in the foreground.

Each service module under ``services/`` exposes ``cli`` (its typer entry, parsing arguments apart from
its pure ``main``); the ones present are registered here under their command names.
"""

from __future__ import annotations

import importlib

import typer

RUN = {
    "mocap": "services.mocap_ingest",
    "transform": "services.frame_transform",
    "downsampler": "services.downsampler",
    "gateway": "services.mavlink_gateway",
    "recorder": "services.recorder",
}
SIM = {
    "vehicle": "services.sim_vehicle",
    "mocap": "services.sim_mocap",
    "world": "services.sim_world",
}


def _group(help_text: str, table: dict[str, str]) -> typer.Typer:
    group = typer.Typer(help=help_text, no_args_is_help=True)
    for name, module_name in table.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            continue
        group.command(name)(module.cli)
    return group


def register(app: typer.Typer) -> None:
    """Add ``run`` and ``sim`` to ``app``."""
    app.add_typer(_group("Run one arena service in the foreground.", RUN), name="run")
    app.add_typer(_group("Run the simulated world: vehicles that speak MAVLink, a Motive emulator.", SIM),
                  name="sim")
