"""The ``arena`` command: one entry point for every tool, each group in its own module.

Each module ``arena_common/cli/_<group>.py`` defines ``register(app)``, loaded in the order of
:data:`GROUPS`.  The options every command shares are declared once, in :mod:`._globals`.
"""

from __future__ import annotations

import importlib

import typer

from arena_common.cli import _globals

app = typer.Typer(
    name="arena",
    cls=_globals.Group,
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
    "_security",
)

app.callback()(_globals.options)  # --config, --mode, --connect, --listen, --zconfig: declared once
for _name in GROUPS:
    importlib.import_module(f"{__name__}.{_name}").register(app)


def main() -> None:
    """Console-script entry point."""
    app()
