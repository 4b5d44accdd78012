"""Command-line options every arena command and service shares (``--config``, ``--mode``, ``--connect``…).

Services build their own small typer entry points from these, so ``python -m services.X --help`` and
``arena …`` speak the same options, the way zenoh's examples all take ``--mode/--connect/--listen``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any, Literal, overload

import typer

from arena_common.bus.exposure import check_exposure
from arena_common.bus.session import BusOptions
from arena_common.core import config as config_mod
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.runtime import px4_sitl_rules

DEFAULT_CONFIG = "deploy/sim.toml"

ConfigOpt = Annotated[
    Path | None,
    typer.Option(
        "--config",
        "-c",
        help="Arena config file (default: $ARENA_CONFIG, else deploy/sim.toml).",
        show_default=False,
    ),
]
ModeOpt = Annotated[str | None, typer.Option("--mode", "-m", help="Zenoh mode: peer, client or router.")]
ConnectOpt = Annotated[
    list[str] | None, typer.Option("--connect", "-e", help="Zenoh endpoint to connect to (repeatable).")
]
ListenOpt = Annotated[list[str] | None, typer.Option("--listen", "-l", help="Zenoh endpoint to listen on.")]
ZConfigOpt = Annotated[
    Path | None, typer.Option("--zconfig", help="A Zenoh JSON5 config file, applied first.")
]
HostOpt = Annotated[str | None, typer.Option("--host", help="This host's name (default: the hostname).")]
LogOpt = Annotated[str, typer.Option("--log-level", help="DEBUG, INFO, WARNING or ERROR.")]


def bus_options(
    mode: str | None = None,
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    zconfig: Path | None = None,
) -> BusOptions:
    """The :class:`~arena_common.bus.session.BusOptions` of the shared command-line options."""
    if mode is not None and mode not in config_mod.ZENOH_MODES:
        raise typer.BadParameter(f"--mode must be one of {', '.join(config_mod.ZENOH_MODES)}, not {mode!r}")
    return BusOptions(
        mode=mode,
        connect=tuple(connect or ()),
        listen=tuple(listen or ()),
        zconfig=str(zconfig) if zconfig else None,
    )


def config_path(path: Path | str | None) -> Path:
    """The config file to use: the option, else ``$ARENA_CONFIG``, else ``deploy/sim.toml``."""
    return Path(path or os.environ.get("ARENA_CONFIG") or DEFAULT_CONFIG)


def chosen_config(argument: Path | str | None, option: Path | str | None) -> Path | None:
    """The config a command line names: its positional ``argument`` or ``--config`` (``None``: neither).

    Naming two different files is an error on stderr (status 2): neither may be dropped silently.
    """
    if argument and option and Path(argument) != Path(option):
        typer.echo(
            f"error: two config files named: {argument} (argument) and {option} (--config); name one",
            err=True,
        )
        raise typer.Exit(2)
    chosen = argument or option
    return Path(chosen) if chosen else None


def read_config(path: Path | str) -> ArenaConfig:
    """Read a config file and check it by every rule: the one loader of the arena's processes and commands.

    The config's shape and the rules across its fields (:func:`arena_common.core.config.load`), each PX4
    SITL vehicle's instance (:func:`arena_common.runtime.px4_sitl_rules.apply`, which fills in its link
    and system id), then what it may expose to the network
    (:func:`arena_common.bus.exposure.check_exposure`).  :class:`ConfigError` naming the file and the field.
    """
    return _checked(config_mod.load(path))


def parse_config(data: dict[str, Any], path: str = "<config>") -> ArenaConfig:
    """A parsed TOML document checked as :func:`read_config` checks a file."""
    return _checked(config_mod.parse(data, path))


def _checked(cfg: ArenaConfig) -> ArenaConfig:
    cfg = px4_sitl_rules.apply(cfg)
    check_exposure(cfg)
    return cfg


@overload
def load_config(path: Path | str | None, required: Literal[True] = True) -> ArenaConfig: ...
@overload
def load_config(path: Path | str | None, required: bool) -> ArenaConfig | None: ...
def load_config(path: Path | str | None, required: bool = True) -> ArenaConfig | None:
    """:func:`read_config`, or exit with its error on stderr (status 2); ``required=False`` tolerates absence."""
    p = config_path(path)
    if not required and path is None and not p.exists():
        return None
    try:
        return read_config(p)
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
