"""The options every ``arena`` command shares, declared once on the command itself (a typer callback).

``arena --config lab.toml status`` and ``arena status --config lab.toml`` both work: :class:`Group` moves
these options in front of the sub-command (:func:`hoist`) before typer parses the line.  Commands read them with
:func:`config`, :func:`config_file` and :func:`bus`; a command that runs another program (``arena run``,
``arena sim``) hands them on as a command line, :meth:`Globals.argv`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, overload

import typer
from typer.core import TyperGroup

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig
from arena_common.runtime.options import (
    ConfigOpt,
    ConnectOpt,
    ListenOpt,
    ModeOpt,
    ZConfigOpt,
    bus_options,
    chosen_config,
    config_path,
    load_config,
)

#: The shared options and whether each takes a value (for :func:`hoist`).
OPTIONS = {
    "--config": True,
    "-c": True,
    "--mode": True,
    "-m": True,
    "--connect": True,
    "-e": True,
    "--listen": True,
    "-l": True,
    "--zconfig": True,
}


@dataclass(frozen=True, slots=True)
class Globals:
    """The shared options of one ``arena`` invocation."""

    config: Path | None = None
    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zconfig: Path | None = None

    def argv(self) -> list[str]:
        """These options as a command line (long forms), for whatever runs the command: ``arena run`` and
        ``arena sim`` hand them to their service this way, so ``arena sim motive -c lab.toml`` and
        ``python -m services.sim_mocap -c lab.toml`` are one command line."""
        args: list[str] = []
        if self.config is not None:
            args += ["--config", str(self.config)]
        if self.mode is not None:
            args += ["--mode", self.mode]
        for endpoint in self.connect:
            args += ["--connect", endpoint]
        for endpoint in self.listen:
            args += ["--listen", endpoint]
        if self.zconfig is not None:
            args += ["--zconfig", str(self.zconfig)]
        return args


_current: Globals | None = None  # set by the callback for the command being run


def options(
    config: ConfigOpt = None,
    mode: ModeOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    zconfig: ZConfigOpt = None,
) -> None:
    """Flying Arena: motion capture to PX4 vehicles over Zenoh, in the lab or in simulation."""
    bus_options(mode, connect, listen, zconfig)  # checks --mode now, before any command runs
    if config is not None:  # a file the user named is never dropped, whatever the command does with it
        try:
            config.open("rb").close()
        except OSError as exc:
            typer.echo(f"error: {config}: cannot read: {exc.strerror or exc}", err=True)
            raise typer.Exit(2) from None
    global _current
    _current = Globals(config, mode, tuple(connect or ()), tuple(listen or ()), zconfig)


def current() -> Globals:
    """The shared options of the running command (defaults outside a command line)."""
    return _current if isinstance(_current, Globals) else Globals()


def config_file(path: Path | str | None = None) -> Path:
    """The config file: ``path`` (a command's positional argument) else ``--config`` else the default
    (two different files named: an error, status 2)."""
    return config_path(chosen_config(path, current().config))


@overload
def config(required: Literal[True] = True, path: Path | str | None = None) -> ArenaConfig: ...
@overload
def config(required: bool, path: Path | str | None = None) -> ArenaConfig | None: ...
def config(required: bool = True, path: Path | str | None = None) -> ArenaConfig | None:
    """The arena config (exits with its error on stderr, status 2); ``required=False`` tolerates the
    absence of a default one, never of a file the command line names."""
    return load_config(chosen_config(path, current().config), required)


def bus(mode: str | None = None, listen: list[str] | None = None) -> BusOptions:
    """The bus options of the command line (``mode`` / ``listen`` override, e.g. for the router)."""
    g = current()
    return bus_options(
        mode or g.mode,
        list(g.connect) if mode != "router" else None,
        listen if listen is not None else list(g.listen),
        g.zconfig,
    )


def hoist(argv: list[str]) -> list[str]:
    """``argv`` with the shared options (and their values) moved in front of the sub-command."""
    front: list[str] = []
    rest: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg == "--":
            rest += argv[i:]
            break
        name = arg.split("=", 1)[0]
        if name in OPTIONS and name.startswith("--") and "=" in arg:
            front.append(arg)
        elif name in OPTIONS and i + 1 < len(argv):
            front += argv[i : i + 2]
            i += 1
        else:
            rest.append(arg)
        i += 1
    return front + rest


class Group(TyperGroup):
    """The ``arena`` command group: shared options may follow the sub-command."""

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:
        return list(super().parse_args(ctx, hoist(args)))
