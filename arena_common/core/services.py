"""The arena's processes, in one table: what each is called, which module runs it, where and what for.

Every place that names a service reads :data:`SERVICES`: the config's validation (the names a host's
``services`` and ``vehicle_services`` may list), the supervisor of ``arena up`` (which processes a host
runs), ``arena run NAME`` and ``arena sim NAME`` (the commands and their help), ``arena deploy systemd``
(which unit files, and their descriptions), the services' own presence names and the layer check (every
``services.*`` module is in the table, and the table names only modules that exist).

A service's :attr:`ServiceInfo.name` is its one spelling: the log prefix under ``arena up`` (``[gateway.d1]``),
its presence key (``arena/sys/alive/<host>/<name>``), its systemd unit (``arena-<name>.service``) and the
word typed after ``arena run``; a service of the simulated world is typed after ``arena sim`` without its
``sim-`` prefix (``arena sim vehicle`` runs ``sim-vehicle``), so no word means two programs.

A service that needs an optional extra (:data:`EXTRAS`) says so, naming the ``pip install`` line, before
it imports anything of it (:func:`missing_extra`).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from typing import Literal, get_args

__all__ = [
    "EXTRAS",
    "ROUTER_CPU",
    "SERVICES",
    "CpuShare",
    "HostService",
    "ServiceInfo",
    "VehicleService",
    "by_module",
    "by_name",
    "missing_extra",
    "started_by",
]

#: What ``hosts.<h>.services`` may list: the router, and each host-wide service by its ``config`` word.
HostService = Literal["router", "mocap", "transform", "recorder", "sim", "ros2"]
#: What ``hosts.<h>.vehicle_services`` may list (one process of each per vehicle of the host).
VehicleService = Literal["downsampler", "gateway"]
Scope = Literal["host", "vehicle", "px4-sitl"]
Group = Literal["run", "sim"]
#: How a process shares the CPU (:func:`~arena_common.runtime.service.take_cpu_share`): ``vision`` for what the
#: vehicles' vision passes through or stands for (the mocap, the transform, the downsamplers, the gateways, the
#: router, and the simulated world, which stands for cameras and vehicles with processors of their own) goes
#: first; ``background`` (the recorder, the live viewer) yields; ``normal`` keeps what it was given.
CpuShare = Literal["vision", "normal", "background"]
SIM_PREFIX = "sim-"

#: Optional extra → the modules it brings (pyproject.toml's ``[project.optional-dependencies]``).
EXTRAS: dict[str, tuple[str, ...]] = {
    "ros2": ("rosbags", "xxhash"),
    "mocap": ("motioncapture",),
}


@dataclass(frozen=True, slots=True)
class ServiceInfo:
    """One arena process."""

    name: str  # the one spelling: log prefix, presence key, unit name, the command's word
    module: str  # what ``python -m`` runs; it has ``main`` (the service) and ``cli`` (its typer entry)
    scope: Scope  # one per host, one per vehicle, or one per PX4 SITL vehicle (beside its gateway)
    group: Group  # ``arena run`` or ``arena sim``
    summary: str  # what it does, in one line: the command's help and the systemd unit's description
    config: HostService | VehicleService | None = None  # the config word that starts it under ``arena up``
    extra: str | None = None  # the optional extra it needs
    cpu: CpuShare = "normal"  # how its process shares the CPU

    @property
    def command(self) -> str:
        """The word typed after ``arena run`` / ``arena sim``."""
        return self.name.removeprefix(SIM_PREFIX) if self.group == "sim" else self.name

    @property
    def unit(self) -> str:
        """Its systemd unit (a template, instantiated per vehicle, for a vehicle's service)."""
        return f"arena-{self.name}@.service" if self.scope == "vehicle" else f"arena-{self.name}.service"


SERVICES: tuple[ServiceInfo, ...] = (
    ServiceInfo(
        "mocap",
        "services.mocap_ingest",
        "host",
        "run",
        "mocap ingest: NatNet (or another source) → arena/sys/frames (and arena/<drone>/mocap)",
        config="mocap",
        cpu="vision",
    ),
    ServiceInfo(
        "transform",
        "services.frame_transform",
        "host",
        "run",
        "frame transform: arena/sys/frames → arena/<drone>/pose (NED/FRD)",
        config="transform",
        cpu="vision",
    ),
    ServiceInfo(
        "downsampler",
        "services.downsampler",
        "vehicle",
        "run",
        "downsampler: arena/<drone>/pose → arena/<drone>/vision",
        config="downsampler",
        cpu="vision",
    ),
    ServiceInfo(
        "gateway",
        "services.mavlink_gateway",
        "vehicle",
        "run",
        "MAVLink gateway of one vehicle: the bus ↔ its PX4",
        config="gateway",
        cpu="vision",
    ),
    ServiceInfo(
        "recorder",
        "services.recorder",
        "host",
        "run",
        "telemetry recorder: arena keys → MCAP files",
        config="recorder",
        cpu="background",
    ),
    ServiceInfo(
        "ros2",
        "services.ros2",
        "host",
        "run",
        "ROS 2 over rmw_zenoh: arena topics, TF, goto/cmd_vel (docs/ros2.md)",
        config="ros2",
        extra="ros2",
    ),
    ServiceInfo(
        "px4-sitl",
        "services.px4_sitl",
        "px4-sitl",
        "run",
        'PX4 SITL autopilot of one autopilot = "px4-sitl" vehicle',
    ),
    ServiceInfo(
        "px4-truth",
        "services.px4_truth",
        "px4-sitl",
        "run",
        "PX4 SITL ground truth → arena/<drone>/truth (Motive emulator)",
    ),
    ServiceInfo(
        "sim-vehicle",
        "services.sim_vehicle",
        "host",
        "sim",
        "simulated PX4 vehicles speaking MAVLink 2",
        config="sim",
        cpu="vision",
    ),
    ServiceInfo(
        "sim-motive",
        "services.sim_mocap",
        "host",
        "sim",
        "Motive emulator: a NatNet server streaming the simulated vehicles",
        config="sim",
        cpu="vision",
    ),
    ServiceInfo(
        "sim-world",
        "services.sim_world",
        "host",
        "sim",
        "the whole simulated world in one process: vehicles and Motive emulator",
        cpu="vision",
    ),
)

#: The router carries every pose from the mocap to the gateways: it shares the CPU as the vision pipeline.
ROUTER_CPU: CpuShare = "vision"

_BY_NAME = {s.name: s for s in SERVICES}
_BY_MODULE = {s.module: s for s in SERVICES}


def by_name(name: str) -> ServiceInfo:
    """The service called ``name``; :class:`KeyError` naming the known ones."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"no service {name!r} (known: {', '.join(_BY_NAME)})") from None


def by_module(module: str) -> ServiceInfo:
    """The service that ``python -m module`` runs."""
    try:
        return _BY_MODULE[module]
    except KeyError:
        raise KeyError(f"no service runs {module!r}") from None


def started_by(word: str) -> tuple[ServiceInfo, ...]:
    """The services a config word (``hosts.<h>.services`` / ``vehicle_services``) starts, in order."""
    return tuple(s for s in SERVICES if s.config == word)


def missing_extra(extra: str) -> str | None:
    """Why the optional ``extra`` cannot be used here (with the line that installs it), or ``None``."""
    absent = [m for m in EXTRAS[extra] if importlib.util.find_spec(m) is None]
    if not absent:
        return None
    return (
        f"this needs the optional extra {extra!r} (no module named {', '.join(map(repr, absent))}): "
        f"pip install 'flying-arena[{extra}]'"
    )


HOST_SERVICES: tuple[HostService, ...] = get_args(HostService)
VEHICLE_SERVICES: tuple[VehicleService, ...] = get_args(VehicleService)
