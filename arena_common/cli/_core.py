"""Core commands: ``config check``, ``keys``, ``echo`` and ``router``."""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from arena_common.bus import security
from arena_common.bus.session import Received
from arena_common.cli._globals import bus as global_bus
from arena_common.cli._globals import config as global_config
from arena_common.cli._globals import current as global_options
from arena_common.core import keys, wire
from arena_common.core.errors import ConfigError
from arena_common.core.services import ROUTER_CPU
from arena_common.runtime.options import HostOpt, read_config
from arena_common.runtime.service import host_name, running, setup_logging, take_cpu_share

config_app = typer.Typer(help="Check arena config files.", no_args_is_help=True)


@config_app.command("check")
def config_check(files: Annotated[list[Path], typer.Argument(help="Config files to check.")]) -> None:
    """Validate config files; print a summary of each, or the first error with file and field."""
    failed = False
    for f in files:
        try:
            cfg = read_config(f)
            if any(v.stream_rates for v in cfg.vehicles.values()):  # MAVLink names: the dialect, on demand
                from arena_common.gateway.options import stream_ids

                for name in cfg.vehicles:
                    stream_ids(cfg, name)
        except ConfigError as exc:
            typer.echo(f"error: {exc}", err=True)
            failed = True
            continue
        typer.echo(
            f"{f}: ok — arena {cfg.arena.name!r} {cfg.arena.size[0]}×{cfg.arena.size[1]}×"
            f"{cfg.arena.size[2]} m, {len(cfg.vehicles)} vehicles ({', '.join(cfg.vehicles)}), "
            f"hosts {', '.join(cfg.hosts) or 'none'}"
        )
    if failed:
        raise typer.Exit(2)


def keys_cmd() -> None:
    """Print the table of every key the arena uses."""
    width = max(len(k.pattern) for k in keys.KEYS)
    typer.echo(f"{'key':<{width}}  {'payload':<24} {'qos':<10} description")
    for k in keys.KEYS:
        typer.echo(f"{k.pattern:<{width}}  {k.payload:<24} {k.qos:<10} {k.description}")


def _format(item: Received[wire.Payload]) -> str:
    assert item.payload is not None
    body = " ".join(f"{k}={v}" for k, v in wire.to_jsonable(item.payload).items())
    return f"{item.key} [{item.payload.SCHEMA}] {body}"


def echo(
    keyexpr: Annotated[str, typer.Argument(help="Key expression, e.g. 'arena/**' or 'arena/d1/pose'.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object a line.")] = False,
    rate: Annotated[bool, typer.Option("--rate", help="Show message rates per key instead.")] = False,
    count: Annotated[int, typer.Option("--count", "-n", help="Stop after N messages (0: never).")] = 0,
    duration: Annotated[float, typer.Option("--duration", help="Stop after S seconds (0: never).")] = 0.0,
) -> None:
    """Print every payload published on KEYEXPR, decoded; undecodable ones are reported and skipped."""
    cfg = global_config(required=False)
    setup_logging("WARNING")
    stop = threading.Event()
    shown = 0
    t_end = time.monotonic() + duration if duration > 0 else float("inf")
    counts: dict[str, int] = {}
    with running("echo", cfg, global_bus(), stop=stop) as svc:
        sub = svc.bus.subscribe(keyexpr, capacity=10_000, ring=False)
        last_print = time.monotonic()
        while not svc.stopped and time.monotonic() < t_end:
            item = sub.get(0.2)
            if rate and time.monotonic() - last_print >= 1.0:
                dt = time.monotonic() - last_print
                last_print = time.monotonic()
                for k in sorted(counts):
                    typer.echo(f"{k:<40} {counts[k] / dt:8.1f} Hz")
                typer.echo("")
                counts.clear()
            if item is None:
                continue
            if item.error is not None:
                svc.stats.reject("bad_payload")
                msg = {"key": item.key, "error": str(item.error)}
                typer.echo(json.dumps(msg) if as_json else f"error: {item.key}: {item.error}", err=True)
            elif rate:
                counts[item.key] = counts.get(item.key, 0) + 1
            elif as_json:
                assert item.payload is not None
                typer.echo(
                    json.dumps(
                        {
                            "key": item.key,
                            "type": item.payload.SCHEMA,
                            "t_recv": item.t_recv,
                            "payload": wire.to_jsonable(item.payload),
                        }
                    )
                )
            else:
                typer.echo(_format(item))
            sys.stdout.flush()
            shown += 1
            if count and shown >= count:
                break


def router(
    host: HostOpt = None,
) -> None:
    """Run a Zenoh router (a Python session in router mode; no separate binary needed)."""
    cfg = global_config(required=False)
    setup_logging()
    take_cpu_share(ROUTER_CPU, logging.getLogger("arena.router"))
    opts = global_bus("router", list(global_options().listen) or list(cfg.zenoh.router_listen if cfg else ()))
    extra = security.router_settings(cfg, cfg.security, host_name(host)) if cfg else {}
    opts = replace(opts, mode="router", connect=(), settings={"connect/endpoints": [], **extra})
    with running("router", cfg, opts, host=host) as svc:
        svc.log.info("routing on %s", ", ".join(opts.listen) or "default endpoints")
        while not svc.sleep(1.0):
            pass


def register(app: typer.Typer) -> None:
    """Add the core commands to ``app``."""
    app.add_typer(config_app, name="config")
    app.command("keys")(keys_cmd)
    app.command("echo")(echo)
    app.command("router")(router)
