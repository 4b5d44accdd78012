"""The ``arena`` command: one entry point for every tool, each group in its own module.

Each module ``arena_common/cli/_<group>.py`` defines ``register(app)``; the ones present are loaded in
the order of :data:`GROUPS`.
"""

from __future__ import annotations

import importlib

import typer

app = typer.Typer(
    name="arena",
    help="Flying Arena: motion capture to PX4 vehicles over Zenoh, in the lab or in simulation.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

GROUPS = (
    "_core",
    "_mocap",
    "_calibrate",
    "_services",
    "_flight",
    "_demo",
    "_px4",
    "_rec",
    "_view",
    "_deploy",
)

for _name in GROUPS:
    importlib.import_module(f"{__name__}.{_name}").register(app)


def main() -> None:
    """Console-script entry point."""
    app()
