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
from arena_common.core.services import SERVICES, Group, ServiceInfo, missing_extra


def _lazy(service: ServiceInfo) -> Callable[[typer.Context], None]:
    """A command that imports the service's module when run and hands it every argument: its own, and the
    shared ones (``--config``, ``--mode``…) that the ``arena`` group took in front of the sub-command
    (:func:`~arena_common.cli._globals.hoist`).  A missing optional extra is said, exit 2, before any
    import of it."""

    def command(ctx: typer.Context) -> None:
        why = missing_extra(service.extra) if service.extra else None
        if why:
            typer.echo(f"error: {ctx.command_path}: {why}", err=True)
            raise typer.Exit(2)
        module = importlib.import_module(service.module)
        app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
        app.command()(module.cli)
        typer.main.get_command(app).main(
            args=[*_globals.current().argv(), *ctx.args], prog_name=ctx.command_path, standalone_mode=True
        )

    return command


def _group(help_text: str, group: Group) -> typer.Typer:
    app = typer.Typer(help=help_text, no_args_is_help=True)
    settings = {"allow_extra_args": True, "ignore_unknown_options": True}
    for s in SERVICES:
        if s.group == group:
            text = f"{s.summary[:1].upper()}{s.summary[1:]}."
            app.command(s.command, help=text, context_settings=settings, add_help_option=False)(_lazy(s))
    return app


def register(app: typer.Typer) -> None:
    """Add ``run`` and ``sim`` to ``app``: one command per service of :data:`~arena_common.core.services.SERVICES`."""
    app.add_typer(_group("Run one arena service in the foreground.", "run"), name="run")
    app.add_typer(
        _group("Run the simulated world: vehicles that speak MAVLink, a Motive emulator.", "sim"), name="sim"
    )
