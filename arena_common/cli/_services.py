"""``arena run <service>`` and ``arena sim <part>``: run one arena process in the foreground.

Each service module under ``services/`` exposes ``cli`` (its typer entry, parsing arguments apart from
its pure ``main``).  Modules are imported only when their command runs, so ``arena`` starts fast and one
service's dependencies never stand in another's way; ``arena run gateway --help`` shows the service's
own options.  The shared options (``-c/--config``, ``--mode``, ``--connect``, ``--listen``, ``--zconfig``),
before or after the sub-command, reach the service as its own (:meth:`Globals.argv
<arena_common.cli._globals.Globals.argv>`).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

import typer

from arena_common.cli import _globals

RUN = {
    "mocap": (
        "services.mocap_ingest",
        "Mocap ingest: NatNet (or another source) → arena/sys/frames (and arena/<drone>/mocap).",
    ),
    "transform": (
        "services.frame_transform",
        "Frame transform: arena/sys/frames → arena/<drone>/pose (NED/FRD).",
    ),
    "downsampler": ("services.downsampler", "Downsampler: arena/<drone>/pose → arena/<drone>/vision."),
    "gateway": ("services.mavlink_gateway", "MAVLink gateway of one vehicle: the bus ↔ its PX4."),
    "recorder": ("services.recorder", "Telemetry recorder: keys → MCAP files."),
    "px4-sitl": ("services.px4_sitl", 'PX4 SITL autopilot of one autopilot = "px4-sitl" vehicle.'),
    "px4-truth": ("services.px4_truth", "PX4 SITL ground truth → arena/<drone>/truth (Motive emulator)."),
    "ros2": ("services.ros2", "ROS 2 over rmw_zenoh: arena topics, TF, goto/cmd_vel (docs/ros2.md)."),
}
SIM = {
    "vehicle": ("services.sim_vehicle", "Simulated PX4 vehicles speaking MAVLink 2."),
    "mocap": ("services.sim_mocap", "Motive emulator: a NatNet server streaming the simulated vehicles."),
    "world": ("services.sim_world", "The whole simulated world: vehicles and Motive emulator."),
}


def _lazy(module_name: str) -> Callable[[typer.Context], None]:
    """A command that imports ``module_name`` when run and hands it every argument: its own, and the
    shared ones (``--config``, ``--mode``…) that the ``arena`` group took in front of the sub-command
    (:func:`~arena_common.cli._globals.hoist`)."""

    def command(ctx: typer.Context) -> None:
        module = importlib.import_module(module_name)
        app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
        app.command()(module.cli)
        typer.main.get_command(app).main(
            args=[*_globals.current().argv(), *ctx.args], prog_name=ctx.command_path, standalone_mode=True
        )

    return command


def _group(help_text: str, table: dict[str, tuple[str, str]]) -> typer.Typer:
    group = typer.Typer(help=help_text, no_args_is_help=True)
    settings = {"allow_extra_args": True, "ignore_unknown_options": True}
    for name, (module_name, text) in table.items():
        group.command(name, help=text, context_settings=settings, add_help_option=False)(_lazy(module_name))
    return group


def register(app: typer.Typer) -> None:
    """Add ``run`` and ``sim`` to ``app``."""
    app.add_typer(_group("Run one arena service in the foreground.", RUN), name="run")
    app.add_typer(
        _group("Run the simulated world: vehicles that speak MAVLink, a Motive emulator.", SIM), name="sim"
    )
