"""The arena configuration: one TOML file describes the room, the mocap, the bus, the hosts and the vehicles.

:func:`load` reads and validates a file into frozen value objects; every error names the file, the
field and what was expected (``deploy/sim.toml: vehicles.d1.system_id: expected an integer in 1..250,
got 0``).  ``deploy/sim.toml``, ``deploy/px4-sitl.toml`` and ``deploy/lab.example.toml`` are the documented
examples.

Each vehicle says what flies it (``autopilot``): ``"sim"`` (default; the arena's simulated autopilot, run
by the host service ``sim``), ``"px4"`` (an external PX4: hardware, or a SITL started by hand; nothing is
started for it) or ``"px4-sitl"`` with ``px4_instance = N`` (0..9; ``arena up`` starts PX4 SITL instance N
and its truth bridge next to the vehicle's gateway; ``mavlink`` defaults to ``udpin:127.0.0.1:<14540+N>``
and ``system_id`` to N+1, and must agree with them when given; ``px4_params`` adds boot parameters).
"""

from __future__ import annotations

import re
import socket
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from arena_common.core import keys
from arena_common.core.errors import ConfigError, InvalidName

SERVICES = ("router", "mocap", "transform", "recorder", "sim")
VEHICLE_SERVICES = ("downsampler", "gateway")
UP_AXES = ("y", "z", "enu")
MOCAP_SOURCES = ("natnet", "motioncapture", "csv")
ZENOH_MODES = ("peer", "client", "router")
DECIMATE_IN = ("downsampler", "transform")
AUTOPILOTS = ("sim", "px4", "px4-sitl")
PX4_SITL_MAX_INSTANCE = 9  # instance 10 would send its offboard link to 14550, the ground stations' port
PX4_SITL_OFFBOARD_PORT = 14540  # + instance: where PX4 SITL sends its offboard link


@dataclass(frozen=True, slots=True)
class ArenaSpec:
    """The flight volume and the safety limits the gateways enforce."""

    name: str = "arena"
    size: tuple[float, float, float] = (7.0, 4.0, 2.5)  # north (long side), east, height, metres
    margin: float = 0.3
    max_speed: float = 2.0  # m/s, horizontal setpoint limit
    max_climb: float = 1.0  # m/s, vertical setpoint limit

    def safe_box(self) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
        """(north, east, down) limits of the safe volume: the room minus the margin, origin floor centre."""
        n, e, h = self.size
        m = self.margin
        return ((-n / 2 + m, n / 2 - m), (-e / 2 + m, e / 2 - m), (-(h - m), 0.0))


@dataclass(frozen=True, slots=True)
class CalibrationSpec:
    """Rotation about Down then offset, from Motive's (up-axis corrected) frame to the arena NED frame."""

    yaw_deg: float = 0.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class MocapSpec:
    """Where poses come from."""

    source: str = "natnet"
    server: str = "127.0.0.1"
    interface: str = "127.0.0.1"
    multicast: bool = True
    group: str = "239.255.42.99"
    command_port: int = 1510
    data_port: int = 1511
    up_axis: str = "y"
    publish_unknown: bool = False
    csv_file: str = ""
    motioncapture_type: str = "vrpn"


@dataclass(frozen=True, slots=True)
class ZenohSpec:
    """How services reach each other."""

    mode: str = "peer"
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    listen: tuple[str, ...] = ()
    router_listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    multicast_scouting: bool = False
    lease_ms: int = 10000
    batching_ms: int = 1
    extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class HostSpec:
    """One computer: what it runs."""

    name: str
    services: tuple[str, ...] = ()
    vehicles: tuple[str, ...] = ()
    vehicle_services: tuple[str, ...] = VEHICLE_SERVICES
    address: str = ""


@dataclass(frozen=True, slots=True)
class SimVehicleSpec:
    """Settings of a simulated vehicle (``start`` and ``yaw_deg`` also place a PX4 SITL vehicle)."""

    start: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    mavlink: str = ""  # the simulated autopilot's side; derived from the gateway's string when empty


@dataclass(frozen=True, slots=True)
class VehicleSpec:
    """One vehicle: its rigid body, its MAVLink link and its pipeline settings."""

    name: str
    rigid_body: str | int
    mavlink: str
    system_id: int
    vision_rate: float = 50.0
    max_pose_age: float = 0.1
    vision_message: str = "odometry"
    require_setup: bool = True
    gcs: str = ""
    signing_key_file: str = ""  # MAVLink 2 signing: a file holding the 32-byte secret key as 64 hex digits
    sim: SimVehicleSpec = field(default_factory=SimVehicleSpec)
    # What flies it: "sim" (the arena's simulated autopilot, started by the ``sim`` service), "px4" (an
    # external PX4: hardware, or a SITL started by hand; nothing is started for it) or "px4-sitl" (PX4
    # SITL instance ``px4_instance``, started by ``arena up`` with its ground-truth bridge).
    autopilot: str = "sim"
    px4_instance: int | None = None
    px4_params: Mapping[str, float] = field(default_factory=dict)  # PX4 SITL boot parameters

    @property
    def simulated(self) -> bool:
        """True when the arena's simulated autopilot flies it."""
        return self.autopilot == "sim"

    @property
    def px4_sitl(self) -> bool:
        """True when ``arena up`` starts a PX4 SITL instance for it."""
        return self.autopilot == "px4-sitl"

    def sim_mavlink(self) -> str:
        """The connection string the simulated autopilot uses: the mirror of the gateway's."""
        if self.sim.mavlink:
            return self.sim.mavlink
        return mirror_connection(self.mavlink)


@dataclass(frozen=True, slots=True)
class SimSpec:
    """The simulated world: Motive emulator and simulated vehicles."""

    speed: float = 1.0
    mocap_rate: float = 180.0
    natnet_version: str = "3.1"
    noise_m: float = 0.0002
    dropout: float = 0.0
    seed: int = 0
    px4_params: str = "arena"  # "arena": vehicles already set up for the arena; "px4": PX4's defaults


@dataclass(frozen=True, slots=True)
class RecorderSpec:
    """The telemetry recorder."""

    keys: tuple[str, ...] = ("arena/**",)
    directory: str = "recordings"
    encoding: str = "json"
    flush_s: float = 1.0
    split_mb: float = 512.0
    split_s: float = 3600.0
    min_free_mb: float = 200.0
    auto_on_arm: bool = False


@dataclass(frozen=True, slots=True)
class SecuritySpec:
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


@dataclass(frozen=True, slots=True)
class PipelineSpec:
    """Where a vehicle's full-rate poses are decimated into its vision stream.

    ``downsampler``: one downsampler process per vehicle (``hosts.<h>.vehicle_services``), which can run
    on the vehicle's companion computer.  ``transform``: the frame transform decimates every configured
    vehicle in-process — one process and one hop less per vehicle, and only the vision rate leaves the
    ground computer.
    """

    decimate: str = "downsampler"


@dataclass(frozen=True, slots=True)
class ArenaConfig:
    """A whole arena, as one TOML file describes it."""

    path: str
    arena: ArenaSpec
    calibration: CalibrationSpec
    mocap: MocapSpec
    zenoh: ZenohSpec
    hosts: Mapping[str, HostSpec]
    vehicles: Mapping[str, VehicleSpec]
    sim: SimSpec
    recorder: RecorderSpec
    security: SecuritySpec = field(default_factory=SecuritySpec)
    pipeline: PipelineSpec = field(default_factory=PipelineSpec)

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

    def replace(self, **changes: Any) -> ArenaConfig:
        """A copy with some sections replaced."""
        return replace(self, **changes)


def mirror_connection(conn: str) -> str:
    """The other end of a pymavlink connection string: udpin↔udpout, tcp↔tcpin."""
    scheme, sep, rest = conn.partition(":")
    mirror = {"udpin": "udpout", "udpout": "udpin", "udp": "udpout", "tcp": "tcpin", "tcpin": "tcp"}
    if not sep or scheme not in mirror:
        raise ConfigError(f"cannot derive the simulated side of MAVLink connection {conn!r}; set sim.mavlink")
    return f"{mirror[scheme]}:{rest}"


def udp_listen_port(conn: str) -> int | None:
    """The local UDP port a gateway binds for ``udpin:HOST:PORT`` (or ``udp:…``); None for other links."""
    scheme, _, rest = conn.partition(":")
    port = rest.rpartition(":")[2]
    return int(port) if scheme in ("udpin", "udp") and port.isdigit() else None


class _Reader:
    """Typed access to a TOML table that names the file and dotted field in every error."""

    def __init__(self, path: str, data: Mapping[str, Any], prefix: str) -> None:
        self.path, self.data, self.prefix = path, data, prefix
        self.used: set[str] = set()

    def fail(self, key: str, expected: str, got: Any = ...) -> ConfigError:
        where = f"{self.prefix}.{key}" if self.prefix else key
        tail = "" if got is ... else f", got {got!r}"
        return ConfigError(f"{self.path}: {where}: expected {expected}{tail}")

    def get(self, key: str, kind: type | tuple[type, ...], default: Any, expected: str) -> Any:
        self.used.add(key)
        if key not in self.data:
            return default
        value = self.data[key]
        if isinstance(value, bool) and kind in (int, float, (int, float)):
            raise self.fail(key, expected, value)
        if not isinstance(value, kind):
            raise self.fail(key, expected, value)
        return value

    def number(self, key: str, default: float, lo: float | None = None, hi: float | None = None) -> float:
        v = float(self.get(key, (int, float), default, "a number"))
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.fail(key, f"a number in {lo}..{hi}", v)
        return v

    def integer(self, key: str, default: int, lo: int | None = None, hi: int | None = None) -> int:
        v = self.get(key, int, default, "an integer" if lo is None else f"an integer in {lo}..{hi}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.fail(key, f"an integer in {lo}..{hi}", v)
        return int(v)

    def string(self, key: str, default: str, choices: tuple[str, ...] = ()) -> str:
        v = self.get(key, str, default, "a string" if not choices else f"one of {', '.join(choices)}")
        if choices and v not in choices:
            raise self.fail(key, f"one of {', '.join(choices)}", v)
        return str(v)

    def boolean(self, key: str, default: bool) -> bool:
        return bool(self.get(key, bool, default, "true or false"))

    def strings(self, key: str, default: tuple[str, ...], choices: tuple[str, ...] = ()) -> tuple[str, ...]:
        v = self.get(key, list, list(default), "a list of strings")
        if not all(isinstance(x, str) for x in v):
            raise self.fail(key, "a list of strings", v)
        for x in v:
            if choices and x not in choices:
                raise self.fail(key, f"names among {', '.join(choices)}", x)
        return tuple(v)

    def vector(self, key: str, default: tuple[float, ...]) -> tuple[float, ...]:
        n = len(default)
        v = self.get(key, list, list(default), f"a list of {n} numbers")
        if len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            raise self.fail(key, f"a list of {n} numbers", v)
        return tuple(float(x) for x in v)

    def table(self, key: str) -> _Reader:
        v = self.get(key, dict, {}, "a table")
        return _Reader(self.path, v, f"{self.prefix}.{key}" if self.prefix else key)

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            where = f"{self.prefix}." if self.prefix else ""
            raise ConfigError(f"{self.path}: {where}{unknown[0]}: unknown field")


def _name(r: _Reader, key: str, value: str, what: str) -> str:
    try:
        return keys.validate_name(value, what)
    except InvalidName as exc:
        raise ConfigError(f"{r.path}: {r.prefix + '.' if r.prefix else ''}{key}: {exc}") from None


def _px4_params(r: _Reader) -> dict[str, float]:
    table = r.get("px4_params", dict, {}, "a table of PX4 parameters (NAME = number)")
    out: dict[str, float] = {}
    for key, value in table.items():
        if not re.fullmatch(r"[A-Z][A-Z0-9_]{0,15}", key):
            raise r.fail("px4_params", "PX4 parameter names (capitals, digits, _; up to 16 characters)", key)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise r.fail(f"px4_params.{key}", "a number", value)
        out[key] = value
    return out


def _autopilot(r: _Reader) -> tuple[str, int | None, str | None, int | None]:
    """``(autopilot, px4_instance, mavlink, system_id)``; a PX4 SITL vehicle's link and id follow from
    its instance (and must agree with it when given)."""
    autopilot = r.string("autopilot", "sim", AUTOPILOTS)
    mav = r.get("mavlink", str, None, "a pymavlink connection string (udpin:HOST:PORT, tcp:…, /dev/ttyUSB0…)")
    sysid = r.integer("system_id", 1, 1, 250) if "system_id" in r.data else None
    if autopilot != "px4-sitl":
        if "px4_instance" in r.data:
            raise r.fail("px4_instance", f'no px4_instance unless autopilot = "px4-sitl" (got {autopilot!r})')
        if "px4_params" in r.data:
            raise r.fail("px4_params", f'no px4_params unless autopilot = "px4-sitl" (got {autopilot!r})')
        return autopilot, None, mav, sysid
    if "px4_instance" not in r.data:
        raise r.fail(
            "px4_instance",
            f'the PX4 SITL instance number (0..{PX4_SITL_MAX_INSTANCE}) of a "px4-sitl" vehicle',
        )
    n = r.integer("px4_instance", 0, 0, PX4_SITL_MAX_INSTANCE)
    port = PX4_SITL_OFFBOARD_PORT + n
    expected = f"udpin:127.0.0.1:{port}"
    if mav is None:
        mav = expected
    else:
        scheme, _, rest = mav.partition(":")
        host, _, port_s = rest.rpartition(":")
        if (
            scheme not in ("udpin", "udp")
            or host not in ("127.0.0.1", "localhost", "0.0.0.0")
            or port_s != str(port)
        ):
            raise r.fail(
                "mavlink",
                f"{expected} for PX4 SITL instance {n} (px4_instance; or leave mavlink out)",
                mav,
            )
    if sysid is None:
        sysid = n + 1
    elif sysid != n + 1:
        raise r.fail(
            "system_id", f"{n + 1}, the MAV_SYS_ID of PX4 SITL instance {n} (or leave it out)", sysid
        )
    return autopilot, n, mav, sysid


def _vehicle(r: _Reader, name: str) -> VehicleSpec:
    body = r.get("rigid_body", (str, int), name, "a rigid-body name or integer id")
    sim_r = r.table("sim")
    sim = SimVehicleSpec(
        start=sim_r.vector("start", (0.0, 0.0)),  # type: ignore[arg-type]
        yaw_deg=sim_r.number("yaw_deg", 0.0),
        mavlink=sim_r.string("mavlink", ""),
    )
    sim_r.done()
    autopilot, instance, mav, sysid = _autopilot(r)
    if autopilot != "sim" and sim.mavlink:
        raise sim_r.fail(
            "mavlink", f'no simulated side unless autopilot = "sim" (got {autopilot!r})', sim.mavlink
        )
    if mav is None:
        raise r.fail("mavlink", "a pymavlink connection string (udpin:HOST:PORT, tcp:HOST:PORT, /dev/tty…)")
    if sysid is None:
        raise r.fail("system_id", "an integer in 1..250 (MAV_SYS_ID; never 0)")
    v = VehicleSpec(
        name=name,
        rigid_body=body,
        mavlink=mav,
        system_id=sysid,
        vision_rate=r.number("vision_rate", 50.0, 1.0, 400.0),
        max_pose_age=r.number("max_pose_age", 0.1, 0.001, 1.0),
        vision_message=r.string("vision_message", "odometry", ("odometry", "vision_position_estimate")),
        require_setup=r.boolean("require_setup", True),
        gcs=r.string("gcs", ""),
        signing_key_file=r.string("signing_key_file", ""),
        sim=sim,
        autopilot=autopilot,
        px4_instance=instance,
        px4_params=_px4_params(r) if autopilot == "px4-sitl" else {},
    )
    r.done()
    return v


def parse(data: Mapping[str, Any], path: str = "<config>") -> ArenaConfig:
    """Validate a parsed TOML document into an :class:`ArenaConfig`."""
    root = _Reader(path, data, "")

    a = root.table("arena")
    arena = ArenaSpec(
        name=a.string("name", "arena"),
        size=a.vector("size", (7.0, 4.0, 2.5)),  # type: ignore[arg-type]
        margin=a.number("margin", 0.3, 0.0, 5.0),
        max_speed=a.number("max_speed", 2.0, 0.0, 20.0),
        max_climb=a.number("max_climb", 1.0, 0.0, 10.0),
    )
    if min(arena.size) <= 2 * arena.margin:
        raise a.fail("size", "every dimension larger than twice the margin", list(arena.size))
    a.done()

    c = root.table("calibration")
    calibration = CalibrationSpec(
        yaw_deg=c.number("yaw_deg", 0.0, -360.0, 360.0),
        offset=c.vector("offset", (0.0, 0.0, 0.0)),  # type: ignore[arg-type]
    )
    c.done()

    m = root.table("mocap")
    mocap = MocapSpec(
        source=m.string("source", "natnet", MOCAP_SOURCES),
        server=m.string("server", "127.0.0.1"),
        interface=m.string("interface", "127.0.0.1"),
        multicast=m.boolean("multicast", True),
        group=m.string("group", "239.255.42.99"),
        command_port=m.integer("command_port", 1510, 1, 65535),
        data_port=m.integer("data_port", 1511, 1, 65535),
        up_axis=m.string("up_axis", "y", UP_AXES),
        publish_unknown=m.boolean("publish_unknown", False),
        csv_file=m.string("csv_file", ""),
        motioncapture_type=m.string("motioncapture_type", "vrpn"),
    )
    m.done()

    z = root.table("zenoh")
    zenoh = ZenohSpec(
        mode=z.string("mode", "peer", ZENOH_MODES),
        connect=z.strings("connect", ("tcp/127.0.0.1:7447",)),
        listen=z.strings("listen", ()),
        router_listen=z.strings("router_listen", ("tcp/127.0.0.1:7447",)),
        multicast_scouting=z.boolean("multicast_scouting", False),
        lease_ms=z.integer("lease_ms", 10000, 100, 600000),
        batching_ms=z.integer("batching_ms", 1, 0, 100),
        extra=z.get("extra", dict, {}, "a table of raw Zenoh settings (path = value)"),
    )
    z.done()

    pl = root.table("pipeline")
    pipeline = PipelineSpec(decimate=pl.string("decimate", "downsampler", DECIMATE_IN))
    pl.done()
    # With the transform decimating, no host runs per-vehicle downsamplers.
    default_vehicle_services = (
        VEHICLE_SERVICES
        if pipeline.decimate == "downsampler"
        else tuple(s for s in VEHICLE_SERVICES if s != "downsampler")
    )

    vs = root.table("vehicles")
    vehicles: dict[str, VehicleSpec] = {}
    ids: dict[int, str] = {}
    instances: dict[int, str] = {}
    for vname in list(vs.data):
        _name(vs, vname, vname, "vehicle name")
        v = _vehicle(vs.table(vname), vname)
        if v.px4_instance is not None:
            if v.px4_instance in instances:
                raise vs.fail(
                    f"{vname}.px4_instance",
                    f"a PX4 SITL instance not used by {instances[v.px4_instance]}",
                    v.px4_instance,
                )
            instances[v.px4_instance] = vname
        if v.system_id in ids:
            raise vs.fail(f"{vname}.system_id", f"a system id not used by {ids[v.system_id]}", v.system_id)
        ids[v.system_id] = vname
        vehicles[vname] = v
    vs.done()

    hs = root.table("hosts")
    hosts: dict[str, HostSpec] = {}
    for hname in list(hs.data):
        _name(hs, hname, hname, "host name")
        h = hs.table(hname)
        host = HostSpec(
            name=hname,
            services=h.strings("services", (), SERVICES),
            vehicles=h.strings("vehicles", ()),
            vehicle_services=h.strings("vehicle_services", default_vehicle_services, VEHICLE_SERVICES),
            address=h.string("address", ""),
        )
        if pipeline.decimate == "transform" and "downsampler" in host.vehicle_services:
            raise h.fail(
                "vehicle_services",
                'no "downsampler" while pipeline.decimate = "transform" (the transform decimates)',
                list(host.vehicle_services),
            )
        listening: dict[int, str] = {}
        for vname in host.vehicles:
            if vname not in vehicles:
                raise h.fail(
                    "vehicles", f"names of configured vehicles ({', '.join(vehicles) or 'none'})", vname
                )
            port = udp_listen_port(vehicles[vname].mavlink)
            if port is not None and port in listening:
                raise h.fail(
                    "vehicles",
                    f"vehicles whose gateways listen on distinct UDP ports ({listening[port]} and {vname}"
                    f" both use {port} on this host)",
                    list(host.vehicles),
                )
            if port is not None:
                listening[port] = vname
        h.done()
        hosts[hname] = host
    hs.done()

    s = root.table("sim")
    sim = SimSpec(
        speed=s.number("speed", 1.0, 0.01, 100.0),
        mocap_rate=s.number("mocap_rate", 180.0, 1.0, 1000.0),
        natnet_version=s.string("natnet_version", "3.1", ("3.0", "3.1", "4.0", "4.1")),
        noise_m=s.number("noise_m", 0.0002, 0.0, 0.1),
        dropout=s.number("dropout", 0.0, 0.0, 1.0),
        seed=s.integer("seed", 0),
        px4_params=s.string("px4_params", "arena", ("arena", "px4")),
    )
    s.done()

    rr = root.table("recorder")
    recorder = RecorderSpec(
        keys=rr.strings("keys", ("arena/**",)),
        directory=rr.string("directory", "recordings"),
        encoding=rr.string("encoding", "json", ("json", "msgpack")),
        flush_s=rr.number("flush_s", 1.0, 0.01, 60.0),
        split_mb=rr.number("split_mb", 512.0, 1.0, 1e6),
        split_s=rr.number("split_s", 3600.0, 1.0, 1e6),
        min_free_mb=rr.number("min_free_mb", 200.0, 0.0, 1e7),
        auto_on_arm=rr.boolean("auto_on_arm", False),
    )
    rr.done()

    sc = root.table("security")
    security = SecuritySpec(
        enabled=sc.boolean("enabled", False),
        users_file=sc.string("users_file", ""),
        password_file=sc.string("password_file", ""),
        command_hosts=sc.strings("command_hosts", ()),
        acl=sc.boolean("acl", True),
        tls=sc.boolean("tls", False),
        ca=sc.string("ca", ""),
        cert=sc.string("cert", ""),
        key=sc.string("key", ""),
        mtls=sc.boolean("mtls", True),
    )
    for cmd_host in security.command_hosts:
        if cmd_host not in hosts:
            raise sc.fail(
                "command_hosts", f"names of configured hosts ({', '.join(hosts) or 'none'})", cmd_host
            )
    sc.done()
    root.done()
    return ArenaConfig(
        path, arena, calibration, mocap, zenoh, hosts, vehicles, sim, recorder, security, pipeline
    )


def load(path: str | Path) -> ArenaConfig:
    """Read and validate a TOML config file."""
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
