"""One command line for every service: the shared options declared once (as zenoh-python's examples share
``common.py``), each service adding only its own.

    @service_command
    def cli(shared: Shared, vehicle: VehicleOpt) -> None:
        \"\"\"One vehicle's poses decimated to its vision rate.\"\"\"
        main(shared.config, shared.bus, vehicle=vehicle, host=shared.host)

gives ``python -m services.downsampler --vehicle d1 -c lab.toml --mode client --log-level DEBUG``: logging is
set up, the config named (else ``$ARENA_CONFIG``, else ``deploy/sim.toml``) is loaded — an unreadable or
invalid one exits with status 2 naming it — and an :class:`~arena_common.core.errors.ArenaError` the
service raises (a bad config value, a missing PX4 build) exits with status 2 and its message.
"""

from __future__ import annotations

import functools
import inspect
import logging
import sys
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import typer

from arena_common.bus.session import BusOptions
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ArenaError
from arena_common.core.services import ServiceInfo, by_module
from arena_common.runtime.options import (
    ConfigOpt,
    ConnectOpt,
    HostOpt,
    ListenOpt,
    LogOpt,
    ModeOpt,
    ZConfigOpt,
    bus_options,
    load_config,
)
from arena_common.runtime.process import lead_own_session
from arena_common.runtime.service import setup_logging, take_cpu_share

__all__ = ["SHARED_OPTIONS", "Shared", "service_command"]


@dataclass(frozen=True, slots=True)
class Shared:
    """What the shared options of a service's command line give it."""

    config: ArenaConfig
    bus: BusOptions
    host: str | None
    log_level: str


#: The shared options: (parameter name, annotation, default).
SHARED_OPTIONS: tuple[tuple[str, Any, Any], ...] = (
    ("config", ConfigOpt, None),
    ("mode", ModeOpt, None),
    ("connect", ConnectOpt, None),
    ("listen", ListenOpt, None),
    ("zconfig", ZConfigOpt, None),
    ("host", HostOpt, None),
    ("log_level", LogOpt, "INFO"),
)


def service_command(func: Callable[..., None]) -> Callable[..., None]:
    """``func(shared, **own_options)`` as a typer command that also takes :data:`SHARED_OPTIONS`."""
    hints = typing.get_type_hints(func, include_extras=True)  # the service module's names, resolved here
    own = [p.replace(annotation=hints[p.name]) for p in list(inspect.signature(func).parameters.values())[1:]]
    shared_params = [
        inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)
        for name, annotation, default in SHARED_OPTIONS
    ]

    info = _service_of(func)

    @functools.wraps(func)
    def command(**kwargs: Any) -> None:
        given = {name: kwargs.pop(name) for name, _, _ in SHARED_OPTIONS}
        if info is not None and info.cpu == "background":
            lead_own_session()  # its session's group can then yield without the terminal's other jobs
        setup_logging(given["log_level"])
        if info is not None:
            take_cpu_share(info.cpu, logging.getLogger(f"arena.{info.name}"))
        cfg = load_config(given["config"])
        bus = bus_options(given["mode"], given["connect"], given["listen"], given["zconfig"])
        try:
            func(Shared(cfg, bus, given["host"], given["log_level"]), **kwargs)
        except ArenaError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None

    params = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in own] + shared_params
    command.__signature__ = inspect.Signature(params, return_annotation=None)  # type: ignore[attr-defined]
    command.__annotations__ = {p.name: p.annotation for p in params}
    del command.__wrapped__  # typer reads the signature above, not the wrapped function's
    return command


def _service_of(func: Callable[..., None]) -> ServiceInfo | None:
    """The service whose command ``func`` is (its module, also when run as ``python -m``), if it is one."""
    module = func.__module__
    if module == "__main__":
        spec = getattr(sys.modules["__main__"], "__spec__", None)
        module = spec.name if spec is not None else module
    try:
        return by_module(module)
    except KeyError:
        return None
