"""The arena configuration: one TOML file describes the room, the mocap, the bus, the hosts and the vehicles.

The config's shape: each section is one frozen msgspec Struct, a field's type, bounds and default written
once, on the field.  :func:`load` checks every field (:mod:`arena_common.core.convert`) and the rules
across fields (distinct system ids, hosts naming configured vehicles...); every error names the file, the
field and what was expected (``deploy/sim.toml: vehicles.d1.system_id: expected an integer in 1..250,
got 0``).  ``deploy/sim.toml``, ``deploy/px4-sitl.toml`` and ``deploy/lab.example.toml`` are the examples.

Higher layers own their rules: what may listen beyond loopback (:mod:`arena_common.bus.exposure`), what a
PX4 SITL instance implies (:mod:`arena_common.runtime.px4_sitl_rules`).  Programs load through a loader
that applies them: :func:`arena_common.runtime.options.read_config` (every arena process and command),
:func:`arena_common.bus.exposure.load` (the user's client).

Each vehicle says what flies it (``autopilot``): ``"sim"`` (default; the arena's simulated autopilot, run
by the host service ``sim``), ``"px4"`` (an external PX4: hardware, or a SITL started by hand; nothing is
started for it) or ``"px4-sitl"`` with ``px4_instance = N`` (``arena up`` starts PX4 SITL instance N and
its truth bridge next to the vehicle's gateway; its ``mavlink`` and ``system_id`` follow from N, and
``px4_params`` adds boot parameters).
"""

from __future__ import annotations

import socket
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import msgspec
from msgspec import Meta

from arena_common.core import keys
from arena_common.core.convert import Spec, convert, field_error
from arena_common.core.endpoints import udp_listen_port
from arena_common.core.errors import ConfigError, InvalidName
from arena_common.core.services import VEHICLE_SERVICES, HostService, VehicleService
from arena_common.core.vehiclespec import VehicleSpec

ZenohMode = Literal["peer", "client", "router"]
ZENOH_MODES: tuple[ZenohMode, ...] = get_args(ZenohMode)


class ArenaSpec(Spec, frozen=True):
    """The flight volume and the safety limits the gateways enforce."""

    name: str = "arena"
    size: tuple[float, float, float] = (7.0, 4.0, 2.5)  # north (long side), east, height, metres
    margin: Annotated[float, Meta(ge=0.0, le=5.0)] = 0.3
    max_speed: Annotated[float, Meta(ge=0.0, le=20.0)] = 2.0  # m/s, horizontal setpoint limit
    max_climb: Annotated[float, Meta(ge=0.0, le=10.0)] = 1.0  # m/s, vertical setpoint limit
    # m, centre to centre, that no vehicle is flown within of another (docs/safety.md: why 0.6 m)
    min_separation: Annotated[float, Meta(ge=0.0, le=10.0)] = 0.6

    def safe_box(self) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
        """(north, east, down) limits of the safe volume: the room minus the margin, origin floor centre."""
        n, e, h = self.size
        m = self.margin
        return ((-n / 2 + m, n / 2 - m), (-e / 2 + m, e / 2 - m), (-(h - m), 0.0))


class CalibrationSpec(Spec, frozen=True):
    """Rotation about Down then offset, from Motive's (up-axis corrected) frame to the arena NED frame."""

    yaw_deg: Annotated[float, Meta(ge=-360.0, le=360.0)] = 0.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


class MocapSpec(Spec, frozen=True):
    """Where poses come from."""

    source: Literal["natnet", "motioncapture", "csv"] = "natnet"
    server: str = "127.0.0.1"
    interface: str = "127.0.0.1"
    multicast: bool = True
    group: str = "239.255.42.99"
    command_port: Annotated[int, Meta(ge=1, le=65535)] = 1510
    data_port: Annotated[int, Meta(ge=1, le=65535)] = 1511
    up_axis: Literal["y", "z", "enu"] = "y"
    publish_unknown: bool = False
    csv_file: str = ""
    motioncapture_type: str = "vrpn"


class ZenohSpec(Spec, frozen=True):
    """How services reach each other."""

    mode: ZenohMode = "peer"
    # How each vehicle's own processes (its gateway, its downsampler) join the bus: as ``mode`` says
    # ("same": peers keep vision flowing when the router dies) or "client" of the router (they listen on
    # nothing and keep one link however large the fleet; the router then carries every vision stream:
    # docs/performance.md, "Fifty vehicles").
    vehicle_mode: Literal["client", "same"] = "same"
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    listen: tuple[str, ...] = ()
    router_listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    multicast_scouting: bool = False
    lease_ms: Annotated[int, Meta(ge=100, le=600000)] = 10000
    batching_ms: Annotated[int, Meta(ge=0, le=100)] = 1
    extra: dict[str, Any] = msgspec.field(default_factory=dict)  # raw Zenoh settings (path = value)


class HostSpec(Spec, frozen=True):
    """One computer: what it runs."""

    name: str
    services: tuple[HostService, ...] = ()
    vehicles: tuple[str, ...] = ()
    # Default: both, or only the gateway when the transform decimates (pipeline.decimate).
    vehicle_services: tuple[VehicleService, ...] = VEHICLE_SERVICES
    address: str = ""


class SimSpec(Spec, frozen=True):
    """The simulated world: Motive emulator and simulated vehicles."""

    speed: Annotated[float, Meta(ge=0.01, le=100.0)] = 1.0
    mocap_rate: Annotated[float, Meta(ge=1.0, le=1000.0)] = 180.0
    natnet_version: Literal["3.0", "3.1", "4.0", "4.1"] = "3.1"
    noise_m: Annotated[float, Meta(ge=0.0, le=0.1)] = 0.0002
    dropout: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.0
    seed: int = 0
    # "arena": vehicles set up for the arena; "px4": PX4's defaults
    px4_params: Literal["arena", "px4"] = "arena"
    # "px4": simulated vehicles take off, hold and wander as PX4 v1.16 SITL was measured to (docs/px4.md);
    # "ideal": they climb at once, hold exactly and estimate their pose without error.
    fidelity: Literal["px4", "ideal"] = "px4"


class RecorderSpec(Spec, frozen=True):
    """The telemetry recorder."""

    keys: tuple[str, ...] = ("arena/**",)
    directory: str = "recordings"
    encoding: Literal["json", "msgpack"] = "json"
    flush_s: Annotated[float, Meta(ge=0.01, le=60.0)] = 1.0
    split_mb: Annotated[float, Meta(ge=1.0, le=1e6)] = 512.0
    split_s: Annotated[float, Meta(ge=1.0, le=1e6)] = 3600.0
    min_free_mb: Annotated[float, Meta(ge=0.0, le=1e7)] = 200.0
    auto_on_arm: bool = False


class SecuritySpec(Spec, frozen=True):
    """The ``[security]`` table of the arena config.  ``{host}`` in a path is replaced by the host name."""

    enabled: bool = False
    users_file: str = ""  # the router's "user:password" lines, one user per host
    password_file: str = ""  # each host's own password (its user name is the host name)
    command_hosts: tuple[str, ...] = ()  # hosts that may send commands; empty: every host
    acl: bool = True  # enforce key ownership and command rights on the router
    tls: bool = False  # require tls/ on every endpoint that is not loopback
    ca: str = ""  # the lab CA certificate (PEM)
    cert: str = ""  # this host's certificate (PEM), common name = host name
    key: str = ""  # this host's private key (PEM)
    mtls: bool = True  # the router asks for client certificates (identity by certificate)
    observers: tuple[str, ...] = ()  # identities (not hosts) that may read the arena's keys, nothing else
    insecure: bool = False  # consent to listen beyond loopback without authentication (warned at each start)


class PipelineSpec(Spec, frozen=True):
    """Where a vehicle's full-rate poses are decimated into its vision stream.

    ``downsampler``: one downsampler process per vehicle (``hosts.<h>.vehicle_services``), which can run
    on the vehicle's companion computer.  ``transform``: the frame transform decimates every configured
    vehicle in-process — one process and one hop less per vehicle, and only the vision rate leaves the
    ground computer.

    ``shed_after`` (s, transform decimating only; 0: never): a sample that waited longer than this in
    the transform's queue (it cannot keep up) still feeds its vehicle's vision, but its full-rate pose is
    shed (counted ``shed``): vision before everything else.
    """

    decimate: Literal["downsampler", "transform"] = "downsampler"
    shed_after: Annotated[float, Meta(ge=0.0, le=10.0)] = 0.05


class ClockSpec(Spec, frozen=True):
    """How every host's wall clock is compared with the mocap host's (the time base of every pose).

    Every service measures its host's offset to the mocap ingest's clock every ``period`` s (request and
    answer on ``arena/sys/time``, like NTP).  An offset beyond ``max_offset`` raises an event (time to
    set up chrony); a gateway corrects pose times by the offset, and refuses arming while the offset is
    unknown or less certain than ``max_uncertainty``.  ``require``: refuse arming also when no mocap time
    reference answers at all (otherwise pose times are then taken as the gateway host's, and flagged).
    """

    period: Annotated[float, Meta(ge=0.05, le=60.0)] = 1.0
    max_offset: Annotated[float, Meta(ge=0.0, le=3600.0)] = 0.01
    max_uncertainty: Annotated[float, Meta(ge=1e-6, le=10.0)] = 0.01
    drift_ppm: Annotated[float, Meta(ge=0.0, le=10000.0)] = 200.0  # assumed worst clock drift between samples
    require: bool = True


class ArenaConfig(Spec, frozen=True):
    """A whole arena, as one TOML file describes it."""

    path: str = "<config>"
    arena: ArenaSpec = msgspec.field(default_factory=ArenaSpec)
    calibration: CalibrationSpec = msgspec.field(default_factory=CalibrationSpec)
    mocap: MocapSpec = msgspec.field(default_factory=MocapSpec)
    zenoh: ZenohSpec = msgspec.field(default_factory=ZenohSpec)
    hosts: dict[str, HostSpec] = msgspec.field(default_factory=dict)
    vehicles: dict[str, VehicleSpec] = msgspec.field(default_factory=dict)
    sim: SimSpec = msgspec.field(default_factory=SimSpec)
    recorder: RecorderSpec = msgspec.field(default_factory=RecorderSpec)
    security: SecuritySpec = msgspec.field(default_factory=SecuritySpec)
    pipeline: PipelineSpec = msgspec.field(default_factory=PipelineSpec)
    clock: ClockSpec = msgspec.field(default_factory=ClockSpec)

    def file(self, name: str) -> Path:
        """A file the config names: ``~`` expanded, a relative path taken from the config file's folder."""
        p = Path(name).expanduser()
        return p if p.is_absolute() or self.path.startswith("<") else Path(self.path).resolve().parent / p

    def vehicle(self, name: str) -> VehicleSpec:
        """A vehicle by name; :class:`ConfigError` listing the known names if absent."""
        try:
            return self.vehicles[name]
        except KeyError:
            raise ConfigError(
                f"{self.path}: no vehicle {name!r} (known: {', '.join(self.vehicles)})"
            ) from None

    def host(self, name: str | None = None) -> HostSpec:
        """A host by name, by default this machine's hostname; the error lists the known names."""
        name = name or socket.gethostname()
        try:
            return self.hosts[name]
        except KeyError:
            raise ConfigError(
                f"{self.path}: host {name!r} is not in the config (known hosts: {', '.join(self.hosts)})"
            ) from None

    def body_map(self) -> dict[str | int, str]:
        """Rigid-body name or id → vehicle name."""
        return {v.rigid_body: v.name for v in self.vehicles.values()}


# --------------------------------------------------------------------------------------------------
# Reading: each field checked on its own (core.convert), then the rules across fields.
# --------------------------------------------------------------------------------------------------


def _named(path: str, section: str, data: Any) -> dict[str, dict[str, Any]]:
    """A table of named tables (``vehicles``, ``hosts``), each name valid in a key expression."""
    if not isinstance(data, dict):
        raise field_error(path, section, "a table of named tables", data)
    for name in data:
        try:
            keys.validate_name(name, f"{section[:-1]} name")
        except InvalidName as exc:
            raise ConfigError(f"{path}: {section}.{name}: {exc}") from None
    for name, table in data.items():
        if not isinstance(table, dict):
            raise field_error(path, f"{section}.{name}", "a table", table)
    return data


def _vehicle(path: str, name: str, table: dict[str, Any]) -> VehicleSpec:
    """One vehicle.  A PX4 SITL vehicle's link and id may be left out: its instance implies them
    (:mod:`arena_common.runtime.px4_sitl_rules` fills them in)."""
    where = f"vehicles.{name}"
    v = convert(VehicleSpec, {"name": name, **table}, path, where)
    if v.sim.mavlink and v.autopilot != "sim":
        raise field_error(
            path,
            f"{where}.sim.mavlink",
            f'no simulated side unless autopilot = "sim" (got {v.autopilot!r})',
            v.sim.mavlink,
        )
    if v.sim.link_jitter_ms > v.sim.link_delay_ms:
        raise field_error(
            path,
            f"{where}.sim.link_jitter_ms",
            f"at most link_delay_ms ({v.sim.link_delay_ms})",
            v.sim.link_jitter_ms,
        )
    if v.sim.link_delay_ms and (v.autopilot != "sim" or v.mavlink_peer or not v.mavlink.startswith("udpin:")):
        raise field_error(
            path,
            f"{where}.sim.link_delay_ms",
            'a simulated vehicle (autopilot = "sim") on a udpin link without mavlink_peer',
            v.sim.link_delay_ms,
        )
    if not v.mavlink and not v.px4_sitl:
        raise field_error(
            path,
            f"{where}.mavlink",
            "a pymavlink connection string (udpin:HOST:PORT, tcp:HOST:PORT, /dev/tty…)",
        )
    if not v.system_id and not v.px4_sitl:
        raise field_error(path, f"{where}.system_id", "an integer in 1..250 (MAV_SYS_ID; never 0)")
    return v if v.rigid_body != "" else v.replace(rigid_body=name)


def check_distinct(cfg: ArenaConfig, field: str, what: str, unset: object) -> None:
    """No two vehicles with the same ``field`` (``unset``: left out, clashes with nothing); the error names
    the later vehicle's field: ``expected <what> not used by <the earlier vehicle>``."""
    first: dict[object, str] = {}
    for name, v in cfg.vehicles.items():
        value = getattr(v, field)
        if value in first:
            raise field_error(
                cfg.path, f"vehicles.{name}.{field}", f"{what} not used by {first[value]}", value
            )
        if value != unset:
            first[value] = name


def check_links(cfg: ArenaConfig) -> None:
    """Every vehicle's system id its own, and on each host every gateway on a UDP port of its own.

    An id or link left out (a PX4 SITL vehicle's, until :func:`arena_common.runtime.px4_sitl_rules.apply`
    derives them and runs this check again) takes no part.
    """
    check_distinct(cfg, "system_id", "a system id", unset=0)
    for hname, host in cfg.hosts.items():
        listening: dict[int, str] = {}
        for vname in host.vehicles:
            port = udp_listen_port(cfg.vehicles[vname].mavlink)
            if port is None:
                continue
            if port in listening:
                raise field_error(
                    cfg.path,
                    f"hosts.{hname}.vehicles",
                    f"vehicles whose gateways listen on distinct UDP ports ({listening[port]} and {vname}"
                    f" both use {port} on this host)",
                    list(host.vehicles),
                )
            listening[port] = vname


#: The sections of one table each: every field of ArenaConfig but its path and its named tables.
_SECTIONS: dict[str, type[Spec]] = {
    f.name: f.type for f in msgspec.structs.fields(ArenaConfig) if f.name not in ("path", "hosts", "vehicles")
}


def parse(data: dict[str, Any], path: str = "<config>") -> ArenaConfig:
    """Check a parsed TOML document's shape and cross-field rules into an :class:`ArenaConfig`.

    Neither the PX4 SITL rules nor the network exposure's: programs use a loader that adds them
    (:func:`arena_common.runtime.options.parse_config`, :func:`arena_common.bus.exposure.parse`).
    """
    unknown = sorted(set(data) - set(_SECTIONS) - {"vehicles", "hosts"})
    if unknown:
        raise ConfigError(f"{path}: {unknown[0]}: unknown field")
    sections: dict[str, Any] = {n: convert(cls, data.get(n, {}), path, n) for n, cls in _SECTIONS.items()}
    arena: ArenaSpec = sections["arena"]
    if min(arena.size) <= 2 * arena.margin:
        raise field_error(
            path, "arena.size", "every dimension larger than twice the margin", list(arena.size)
        )
    pipeline: PipelineSpec = sections["pipeline"]
    vehicles = {
        n: _vehicle(path, n, t) for n, t in _named(path, "vehicles", data.get("vehicles", {})).items()
    }

    # With the transform decimating, no host runs per-vehicle downsamplers.
    default_vehicle_services = [
        s for s in VEHICLE_SERVICES if pipeline.decimate == "downsampler" or s != "downsampler"
    ]
    hosts: dict[str, HostSpec] = {}
    for hname, table in _named(path, "hosts", data.get("hosts", {})).items():
        where = f"hosts.{hname}"
        host = convert(
            HostSpec, {"name": hname, "vehicle_services": default_vehicle_services, **table}, path, where
        )
        if pipeline.decimate == "transform" and "downsampler" in host.vehicle_services:
            raise field_error(
                path,
                f"{where}.vehicle_services",
                'no "downsampler" while pipeline.decimate = "transform" (the transform decimates)',
                list(host.vehicle_services),
            )
        for vname in host.vehicles:
            if vname not in vehicles:
                raise field_error(
                    path,
                    f"{where}.vehicles",
                    f"names of configured vehicles ({', '.join(vehicles) or 'none'})",
                    vname,
                )
        hosts[hname] = host

    security: SecuritySpec = sections["security"]
    for cmd_host in security.command_hosts:
        if cmd_host not in hosts:
            raise field_error(
                path,
                "security.command_hosts",
                f"names of configured hosts ({', '.join(hosts) or 'none'})",
                cmd_host,
            )
    cfg = ArenaConfig(path=path, hosts=hosts, vehicles=vehicles, **sections)
    check_links(cfg)
    return cfg


def load(path: str | Path) -> ArenaConfig:
    """Read a TOML config file and check it as :func:`parse` does."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return parse(data, str(p))
