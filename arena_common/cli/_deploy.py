"""``arena up`` (run this computer's share of the arena) and ``arena deploy systemd`` (install it as units).

``arena up deploy/sim.toml`` starts, as separate processes, every service the config assigns to this
host (``--host``, else ``$ARENA_HOST``, else the hostname), the router first; restarts any that dies;
stops them all on Ctrl-C.  ``arena deploy systemd CONFIG --host NAME`` writes the same table as systemd
units (from ``deploy/systemd/``) so that the lab computers run the arena at boot.
"""

from __future__ import annotations

import getpass
import os
import shlex
import socket
import sys
import threading
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import typer

from arena_common.cli._globals import bus as global_bus
from arena_common.cli._globals import config as global_config
from arena_common.core import keys
from arena_common.core.config import ArenaConfig, HostSpec
from arena_common.core.errors import ArenaError, BusError, ConfigError
from arena_common.core.services import ROUTER_CPU, CpuShare, ServiceInfo, missing_extra, started_by
from arena_common.runtime.options import (
    HostOpt,
)
from arena_common.runtime.ports import taken_ports
from arena_common.runtime.service import BACKGROUND_NICE, VISION_NICE, Service, running
from arena_common.runtime.supervisor import SUPERVISOR_SERVICE, Supervisor, host_options, plan, supervise

REPO = Path(__file__).resolve().parents[2]
TEMPLATE_DIR = REPO / "deploy" / "systemd"
ENV_FILE = "/etc/arena/arena.env"
UNIT_DIR = "etc/systemd/system"

ROUTER_UNIT = "arena-router.service"  # the router is no service module: its unit is its own

ConfigArg = Annotated[
    Path | None,
    typer.Argument(help="Arena config file (or --config; default: $ARENA_CONFIG, else deploy/sim.toml)."),
]


class DeployError(ArenaError):
    """Units that cannot be generated (missing templates, a host the config does not name)."""


# -- systemd ------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class UnitSet:
    """Generated files (path relative to the install root → text) and the units to enable."""

    host: str
    files: dict[str, str] = field(default_factory=dict)
    enable: tuple[str, ...] = ()

    def instructions(self, prefix: Path | str = "/") -> str:
        """What to run after writing the files."""
        staged = Path(prefix).resolve() != Path("/")
        lines = []
        if staged:
            lines.append(f"# Files were staged under {prefix}; copy them to / on {self.host} first:")
            lines.append(f"sudo cp -r {shlex.quote(str(prefix))}/etc/. /etc/")
        lines += [
            "sudo systemctl daemon-reload",
            "sudo systemctl enable " + " ".join(self.enable),
            "sudo systemctl start arena.target",
            "systemctl status 'arena*'           # state of every arena unit",
            "journalctl -f -u 'arena*'           # their logs",
        ]
        return "\n".join(lines)


def _recordings_dir(cfg: ArenaConfig, workdir: Path) -> str:
    d = Path(cfg.recorder.directory)
    return str(d if d.is_absolute() else workdir / d)


def missing_extras(host: HostSpec) -> list[tuple[str, str]]:
    """The host's services whose optional extra is not installed here, each with why."""
    found = [(s.name, missing_extra(s.extra)) for w in host.services for s in started_by(w) if s.extra]
    return [(name, why) for name, why in found if why]


#: A unit's CPU share by the table's :data:`~arena_common.core.services.CpuShare`: systemd sets the niceness
#: (as ``runtime.service.take_cpu_share`` asks for under ``arena up``) and weighs the unit's own cgroup, which
#: is what shares the CPU between services under systemd.
CPU_DIRECTIVES: dict[CpuShare, str] = {
    "vision": f"# The vehicles' vision passes through it: it goes first.\nNice={VISION_NICE}\nCPUWeight=300",
    "normal": "# The default CPU share.",
    "background": f"# No vehicle depends on it: it yields.\nNice={BACKGROUND_NICE}\nCPUWeight=20",
}


def unit_fields(service: ServiceInfo) -> dict[str, str]:
    """What a service's unit template is filled with from the table of services: its name, module,
    description (a vehicle's unit names its vehicle, ``%i``) and CPU share."""
    summary = f"{service.summary} (%i)" if service.scope == "vehicle" else service.summary
    return {
        "@SUMMARY@": summary,
        "@MODULE@": service.module,
        "@NAME@": service.name,
        "@CPU@": CPU_DIRECTIVES[service.cpu],
    }


def render_systemd(
    cfg: ArenaConfig,
    host: str,
    *,
    python: str = sys.executable,
    workdir: Path = REPO,
    user: str | None = None,
    template_dir: Path = TEMPLATE_DIR,
) -> UnitSet:
    """The unit files, ``arena.target`` and ``/etc/arena/arena.env`` for ``host`` of ``cfg``.

    ``python`` runs the services (a virtualenv's interpreter with the arena installed), ``workdir`` is
    their working directory (relative paths of the config resolve there), ``user`` runs them (default:
    the current user).
    """
    h: HostSpec = cfg.host(host)
    user = user or getpass.getuser()
    listen = host_options(cfg, h)
    subst = {
        "@BUSARGS@": "".join(f" --listen {e}" for e in listen.listen) if listen is not None else "",
        "@PYTHON@": str(Path(python).absolute()),
        "@WORKDIR@": str(Path(workdir).resolve()),
        "@USER@": user,
        "@RECORDINGS@": _recordings_dir(cfg, Path(workdir).resolve()),
    }

    def fill(name: str, extra: dict[str, str] | None = None) -> str:
        path = template_dir / name
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise DeployError(f"cannot read the unit template {path}: {exc.strerror or exc}") from None
        for k, v in {**subst, **(extra or {})}.items():
            text = text.replace(k, v)
        return text

    sitl = [v for v in h.vehicles if cfg.vehicle(v).px4_sitl and "gateway" in h.vehicle_services]
    if sitl:
        raise DeployError(
            f'{cfg.path}: host {h.name!r} serves autopilot = "px4-sitl" vehicles ({", ".join(sitl)}): '
            "PX4 SITL runs under `arena up`, not systemd"
        )
    files: dict[str, str] = {}
    wants: list[str] = []
    simulated = any(v.simulated for v in cfg.vehicles.values())
    if "router" in h.services:
        files[f"{UNIT_DIR}/{ROUTER_UNIT}"] = fill(ROUTER_UNIT, {"@CPU@": CPU_DIRECTIVES[ROUTER_CPU]})
        wants.append(ROUTER_UNIT)
    for service in (s for word in h.services for s in started_by(word)):
        if service.name == "sim-vehicle" and not simulated:
            continue  # no autopilot = "sim" vehicle: the Motive emulator runs alone
        files[f"{UNIT_DIR}/{service.unit}"] = fill(service.unit, unit_fields(service))
        wants.append(service.unit)
    for service in (s for word in h.vehicle_services for s in started_by(word)) if h.vehicles else ():
        files[f"{UNIT_DIR}/{service.unit}"] = fill(service.unit, unit_fields(service))
        wants += [service.unit.replace("@.", f"@{v}.") for v in h.vehicles]
    if not wants:
        raise DeployError(f"{cfg.path}: host {h.name!r} runs no service and no vehicle: nothing to install")
    files[f"{UNIT_DIR}/arena.target"] = fill("arena.target", {"@WANTS@": " ".join(wants)})
    config_path = Path(cfg.path).resolve()
    files[ENV_FILE.lstrip("/")] = (
        f"# Written by `arena deploy systemd` for host {h.name}.\n"
        f"ARENA_CONFIG={config_path}\nARENA_HOST={h.name}\n"
    )
    return UnitSet(h.name, files, (*wants, "arena.target"))


def write_units(units: UnitSet, prefix: Path | str = "/") -> list[Path]:
    """Write the files under ``prefix`` (``/`` installs them); returns the paths written."""
    root = Path(prefix)
    written = []
    for rel, text in units.files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written


def systemd_cmd(
    config: Annotated[Path, typer.Argument(help="Arena config file.")],
    host: Annotated[str, typer.Option("--host", help="The computer (a \\[hosts] name) to install.")],
    prefix: Annotated[Path, typer.Option("--prefix", help="Install root; stage elsewhere to review.")] = Path(
        "/"
    ),
    user: Annotated[str | None, typer.Option("--user", help="User running the services.")] = None,
    python: Annotated[
        str, typer.Option("--python", help="Interpreter with the arena installed.")
    ] = sys.executable,
    workdir: Annotated[Path, typer.Option("--workdir", help="Services' working directory.")] = REPO,
) -> None:
    """Write systemd units for HOST: one per service, gateway/downsampler per vehicle, arena.target."""
    cfg = global_config(path=config)
    try:
        units = render_systemd(cfg, host, python=python, workdir=workdir, user=user)
        written = write_units(units, prefix)
    except (ConfigError, DeployError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    except OSError as exc:
        typer.echo(f"error: cannot write under {prefix}: {exc.strerror or exc}", err=True)
        raise typer.Exit(1) from None
    for path in written:
        typer.echo(f"wrote {path}")
    typer.echo("")
    typer.echo(units.instructions(prefix))


# -- arena up -------------------------------------------------------------------------------------------


def _gauges(svc: Service, sup: Supervisor) -> None:
    with svc.stats._lock:
        svc.stats.counts["children"] = len(sup.children)
        svc.stats.counts["alive"] = sup.alive_count
        svc.stats.counts["restarts"] = sup.restart_count


def choose_host(cfg: ArenaConfig, host: str | None = None) -> HostSpec:
    """``--host``, else ``$ARENA_HOST``, else the hostname; a one-host config (the simulation) needs none.

    A name the config does not know is a :class:`ConfigError` listing the known ones.
    """
    explicit = host or os.environ.get("ARENA_HOST") or None
    if explicit is None and len(cfg.hosts) == 1 and socket.gethostname() not in cfg.hosts:
        return next(iter(cfg.hosts.values()))
    return cfg.host(explicit)


def up(
    config_arg: ConfigArg = None,
    host: HostOpt = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Print what would start.")] = False,
    grace: Annotated[float, typer.Option("--grace", help="Seconds between SIGTERM and SIGKILL.")] = 5.0,
    log_level: Annotated[
        str | None, typer.Option("--log-level", help="Passed to every service (DEBUG, INFO…).")
    ] = None,
) -> None:
    """Run every service the config assigns to this host, each its own process, restarted if it dies."""
    cfg = global_config(path=config_arg)
    options = global_bus()
    try:
        h = choose_host(cfg, host)
        specs = plan(cfg, h.name, options=options, log_level=log_level)
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    if not specs:
        typer.echo(f"error: {cfg.path}: host {h.name!r} runs no service and no vehicle", err=True)
        raise typer.Exit(2)
    for word, why in missing_extras(h):
        typer.echo(f"error: {cfg.path}: host {h.name!r} runs {word}: {why}", err=True)
        raise typer.Exit(2)
    if dry_run:
        typer.echo(f"# host {h.name} of {cfg.path}: {len(specs)} processes")
        for s in specs:
            ready = f"  # then wait for {s.ready_port[0]}:{s.ready_port[1]}" if s.ready_port else ""
            typer.echo(f"{s.name}: {s.command_line()}{ready}")
        return
    taken = taken_ports(cfg, h.name)
    if taken:
        for p in taken:
            typer.echo(
                f"error: {cfg.path}: {p} is taken by another program (ss -lntup shows which)", err=True
            )
        typer.echo("error: nothing started; free the port(s) or change the config field(s) named", err=True)
        raise typer.Exit(2)
    stop = threading.Event()
    with ExitStack() as stack:
        svc: Service | None = None
        try:
            svc = stack.enter_context(running(SUPERVISOR_SERVICE, cfg, options, host=h.name, stop=stop))
        except BusError as exc:  # supervise anyway: the services matter more than our own presence
            typer.echo(f"[arena] no presence on the bus ({exc}); supervising anyway", err=True)
        typer.echo(
            f"[arena] host {h.name}: starting {', '.join(s.name for s in specs)}"
            + (f" (presence {keys.alive(svc.host, SUPERVISOR_SERVICE)})" if svc else "")
        )
        sys.stdout.flush()
        supervise(
            specs,
            stop,
            tick=(lambda sup: _gauges(svc, sup)) if svc is not None else None,
            grace=grace,
        )


def register(app: typer.Typer) -> None:
    """Add ``up`` and ``deploy`` to ``app``."""
    app.command("up")(up)
    deploy = typer.Typer(help="Install the arena on lab computers.", no_args_is_help=True)
    deploy.command("systemd")(systemd_cmd)
    app.add_typer(deploy, name="deploy")
