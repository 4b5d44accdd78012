"""``arena view``: the live 3D scene for Foxglove, from any computer on the bus."""

from __future__ import annotations

import logging
from typing import Annotated

import typer

from arena_common.cli._globals import bus as global_bus
from arena_common.cli._globals import config as global_config
from arena_common.core.endpoints import is_loopback
from arena_common.recording.live import DEFAULT_PORT, LiveView, serve
from arena_common.runtime.options import (
    HostOpt,
    LogOpt,
)
from arena_common.runtime.process import lead_own_session
from arena_common.runtime.service import setup_logging, yield_cpu


def view_cmd(
    port: Annotated[
        int, typer.Option("--port", "-p", help="WebSocket port (0: any free port).")
    ] = DEFAULT_PORT,
    address: Annotated[
        str,
        typer.Option("--address", help="Address to listen on (0.0.0.0: let other computers connect)."),
    ] = "127.0.0.1",
    key_exprs: Annotated[
        list[str] | None, typer.Option("--keys", "-k", help="Keys to show (repeatable; default arena/**).")
    ] = None,
    public: Annotated[
        bool,
        typer.Option(
            "--public",
            help="Allow an --address beyond loopback: anyone who reaches the port sees every vehicle.",
        ),
    ] = False,
    host: HostOpt = None,
    log_level: LogOpt = "WARNING",
) -> None:
    """Serve the arena live in 3D over the Foxglove WebSocket protocol (open ws://ADDRESS:PORT in Foxglove).

    The Foxglove WebSocket protocol has no login: beyond loopback the view is for anyone on the network,
    so an address that is not loopback needs ``--public`` (and is announced as such).
    """
    lead_own_session()  # first: what follows runs once, in the leader of a session of its own
    setup_logging(log_level)
    if not is_loopback(address) and not public:
        typer.echo(
            f"error: --address {address}: the live view has no login, so anyone who reaches the port would "
            "see every vehicle; add --public to serve it beyond this computer anyway, or reach it through "
            "an SSH tunnel (ssh -L 8765:127.0.0.1:8765 HOST)",
            err=True,
        )
        raise typer.Exit(2)
    if public and not is_loopback(address):
        typer.echo(
            f"warning: public view on {address}: no login, anyone on the network sees every vehicle", err=True
        )
    cfg = global_config(required=False)
    yield_cpu(logging.getLogger("arena.viewer"))

    def ready(view: LiveView) -> None:
        typer.echo(
            f"live 3D view on ws://{address}:{view.port} — in Foxglove: Open connection → Foxglove WebSocket, "
            f"then import the layout deploy/foxglove/arena.json (docs/viewer.md). Ctrl-C stops."
        )

    try:
        serve(
            cfg,
            global_bus(),
            address=address,
            port=port,
            key_exprs=key_exprs or ["arena/**"],
            host=host,
            on_ready=ready,
        )
    except RuntimeError as exc:  # the SDK's server cannot listen (port taken, bad address)
        typer.echo(f"error: cannot serve on {address}:{port}: {exc}", err=True)
        raise typer.Exit(2) from None


def register(app: typer.Typer) -> None:
    """Add ``view`` to ``app``."""
    app.command("view")(view_cmd)
