"""The arena configuration: one TOML file describes the room, the mocap, the bus, the hosts and the vehicles.

:func:`load` reads and validates a file into frozen msgspec Structs: each section is one Struct, and a
field's type, bounds and default are written once, on the field.  Every error names the file, the field
and what was expected (``deploy/sim.toml: vehicles.d1.system_id: expected an integer >= 1, got 0``).
``deploy/sim.toml``, ``deploy/px4-sitl.toml`` and ``deploy/lab.example.toml`` are the documented examples.

Each vehicle says what flies it (``autopilot``): ``"sim"`` (default; the arena's simulated autopilot, run
by the host service ``sim``), ``"px4"`` (an external PX4: hardware, or a SITL started by hand; nothing is
started for it) or ``"px4-sitl"`` with ``px4_instance = N`` (0..9; ``arena up`` starts PX4 SITL instance N
and its truth bridge next to the vehicle's gateway; ``mavlink`` defaults to ``udpin:127.0.0.1:<14540+N>``
and ``system_id`` to N+1, and must agree with them when given; ``px4_params`` adds boot parameters).
"""

from __future__ import annotations

import ipaddress
import re
import socket
import tomllib
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Self, get_args, get_origin

import msgspec
from msgspec import Meta

from arena_common.core import keys
from arena_common.core.endpoints import endpoint_host, is_loopback, mirror_connection, udp_listen_port
from arena_common.core.errors import ConfigError, InvalidName
from arena_common.core.services import VEHICLE_SERVICES, HostService, VehicleService

ZenohMode = Literal["peer", "client", "router"]
ZENOH_MODES: tuple[ZenohMode, ...] = get_args(ZenohMode)
PX4_SITL_MAX_INSTANCE = 9  # instance 10 would send its offboard link to 14550, the ground stations' port
PX4_SITL_OFFBOARD_PORT = 14540  # + instance: where PX4 SITL sends its offboard link


class Spec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A section of the config: frozen, typed, every default on its field."""

    def replace(self, **changes: Any) -> Self:
        """A copy with some fields replaced."""
        return msgspec.structs.replace(self, **changes)


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


class SimVehicleSpec(Spec, frozen=True):
    """Settings of a simulated vehicle (``start`` and ``yaw_deg`` also place a PX4 SITL vehicle)."""

    start: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    mavlink: str = ""  # the simulated autopilot's side; derived from the gateway's string when empty


Px4ParamName = Annotated[str, Meta(pattern=r"^[A-Z][A-Z0-9_]{0,15}$")]
MavlinkName = Annotated[str, Meta(pattern=r"^[A-Z][A-Z0-9_]{0,49}$")]


class VehicleSpec(Spec, frozen=True):
    """One vehicle: its rigid body, its MAVLink link and its pipeline settings."""

    name: str
    rigid_body: str | int = ""  # the vehicle's name when empty
    mavlink: str = ""  # a pymavlink connection string; required unless a PX4 SITL instance implies it
    # udpin links only: the autopilot's "IP:PORT".  The gateway then talks to that address only and drops
    # (and counts) datagrams from any other; without it, it replies to whoever last sent the vehicle's
    # frames (on an unsigned link, anyone on the network: docs/safety.md §3.3).
    mavlink_peer: str = ""
    system_id: Annotated[int, Meta(ge=1, le=250)] = (
        0  # MAV_SYS_ID, never 0; required unless a PX4 SITL instance implies it
    )
    vision_rate: Annotated[float, Meta(ge=1.0, le=400.0)] = 50.0
    max_pose_age: Annotated[float, Meta(ge=0.001, le=1.0)] = 0.1
    vision_message: Literal["odometry", "vision_position_estimate"] = "odometry"
    # Rates of what the gateway publishes, while anyone subscribes: arena/<d>/state, and each raw MAVLink
    # message type on arena/<d>/telemetry/<MSG> (0: none).
    state_rate: Annotated[float, Meta(ge=1.0, le=200.0)] = 50.0
    telemetry_rate: Annotated[float, Meta(ge=0.0, le=200.0)] = 10.0
    # Rates (Hz) the gateway asks the autopilot to stream messages at, by MAVLink name, whenever the link
    # comes up (MAV_CMD_SET_MESSAGE_INTERVAL; 0 stops the stream): e.g. { ATTITUDE = 10, HIGHRES_IMU = 0 }
    # (what mavros' stream rates and MAVSDK's set_rate_* do). Every stream PX4 sends, the gateway reads.
    stream_rates: dict[MavlinkName, Annotated[float, Meta(ge=0.0, le=1000.0)]] = msgspec.field(
        default_factory=dict
    )
    require_setup: bool = True
    gcs: str = ""
    signing_key_file: str = ""  # MAVLink 2 signing: a file holding the 32-byte secret key as 64 hex digits
    sim: SimVehicleSpec = msgspec.field(default_factory=SimVehicleSpec)
    # What flies it: "sim" (the arena's simulated autopilot, started by the ``sim`` service), "px4" (an
    # external PX4: hardware, or a SITL started by hand; nothing is started for it) or "px4-sitl" (PX4
    # SITL instance ``px4_instance``, started by ``arena up`` with its ground-truth bridge).
    autopilot: Literal["sim", "px4", "px4-sitl"] = "sim"
    px4_instance: Annotated[int, Meta(ge=0, le=PX4_SITL_MAX_INSTANCE)] | None = None
    px4_params: dict[Px4ParamName, float] = msgspec.field(default_factory=dict)  # PX4 SITL boot parameters

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


class SimSpec(Spec, frozen=True):
    """The simulated world: Motive emulator and simulated vehicles."""

    speed: Annotated[float, Meta(ge=0.01, le=100.0)] = 1.0
    mocap_rate: Annotated[float, Meta(ge=1.0, le=1000.0)] = 180.0
    natnet_version: Literal["3.0", "3.1", "4.0", "4.1"] = "3.1"
    noise_m: Annotated[float, Meta(ge=0.0, le=0.1)] = 0.0002
    dropout: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.0
    seed: int = 0
    px4_params: Literal["arena", "px4"] = (
        "arena"  # "arena": vehicles set up for the arena; "px4": PX4's defaults
    )
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
# Reading: msgspec checks types, bounds and unknown fields; the rules across fields follow.
# --------------------------------------------------------------------------------------------------

_KINDS = {
    "int": "an integer",
    "float": "a number",
    "str": "a string",
    "bool": "true or false",
    "array": "a list",
    "object": "a table",
}
_AT = re.compile(r" - at (`key` in )?`\$([^`]*)`$")


def _fail(path: str, where: str, expected: str, got: Any = ...) -> ConfigError:
    tail = "" if got is ... else f", got {got!r}"
    return ConfigError(f"{path}: {where}: expected {expected}{tail}")


def _field_type(cls: Any, names: list[str]) -> Any:
    """The annotation (with its ``Annotated`` bounds) at a dotted path below Struct ``cls``; None if unknown."""
    t: Any = cls
    for name in names:
        t = _bare(t)
        if isinstance(t, type) and issubclass(t, msgspec.Struct):
            t = typing.get_type_hints(t, include_extras=True).get(name)
        elif get_origin(t) is dict:
            t = get_args(t)[1]
        else:
            return None
    return t


def _bare(t: Any) -> Any:
    """``t`` without ``Annotated`` and without ``| None``."""
    while True:
        if get_origin(t) is Annotated:
            t = get_args(t)[0]
        elif isinstance(t, types.UnionType) or get_origin(t) is typing.Union:
            t = next(a for a in get_args(t) if a is not type(None))
        else:
            return t


def _expected(t: Any) -> str | None:
    """What a field of type ``t`` wants, in words (None when it cannot be said simply)."""
    meta = next((m for m in get_args(t) if isinstance(m, Meta)), None) if get_origin(t) is Annotated else None
    if meta is None and (isinstance(t, types.UnionType) or get_origin(t) is typing.Union):
        return _expected(next(a for a in get_args(t) if a is not type(None)))
    bare = _bare(t)
    if get_origin(bare) is Literal:
        return "one of " + ", ".join(str(a) for a in get_args(bare))
    if get_origin(bare) is tuple:
        args = get_args(bare)
        if args and args[-1] is not Ellipsis and all(a is float for a in args):
            return f"a list of {len(args)} numbers"
        if len(args) == 2 and args[1] is Ellipsis:
            if get_origin(args[0]) is Literal:
                return "names among " + ", ".join(str(a) for a in get_args(args[0]))
            return "a list of strings" if args[0] is str else None
    kind = {
        int: "an integer",
        float: "a number",
        str: "a string",
        bool: "true or false",
        dict: "a table",
    }.get(get_origin(bare) or bare)
    if kind and meta is not None and meta.ge is not None and meta.le is not None:
        return f"{kind} in {meta.ge}..{meta.le}"
    if kind and meta is not None and meta.pattern is not None:
        return f"{kind} matching {meta.pattern}"
    return kind


def _convert(cls: type[Any], data: Any, path: str, prefix: str) -> Any:
    """``data`` as ``cls``, or a :class:`ConfigError` naming the file, the dotted field, what was expected
    and the value given."""
    try:
        return msgspec.convert(data, cls)
    except msgspec.ValidationError as exc:
        text = str(exc)
        m = _AT.search(text)
        names = [] if m is None else re.findall(r"\.([^.\[]+)", re.sub(r"\[[^\]]*\]", "", m.group(2)))
        is_key = m is not None and m.group(1) is not None
        text = text if m is None else text[: m.start()]
        got: Any = data
        for n in names:
            got = got.get(n, ...) if isinstance(got, dict) else ...
        if unknown := re.fullmatch(r"Object contains unknown field `(.+)`", text):
            where = ".".join([prefix, *names, unknown.group(1)] if prefix else [*names, unknown.group(1)])
            raise ConfigError(f"{path}: {where}: unknown field") from None
        t = _field_type(cls, names)
        if is_key and isinstance(got, dict):  # a table's key is wrong (e.g. a PX4 parameter name)
            key_type = get_args(_bare(t))[0] if get_origin(_bare(t)) is dict else None
            names_wanted = "PX4 parameter names (capitals, digits, _; up to 16 characters)"
            if key_type is not None and key_type is not Px4ParamName:
                names_wanted = _expected(key_type) or "valid names"
            bad = next(
                (k for k in got if not isinstance(k, str) or not re.fullmatch(r"[A-Z][A-Z0-9_]{0,15}", k)),
                got,
            )
            raise _fail(path, ".".join([prefix, *names]), names_wanted, bad) from None
        if (
            m is not None and m.group(2).endswith("[...]") and isinstance(got, dict)
        ):  # a table's value is wrong
            value_type = get_args(_bare(t))[1] if get_origin(_bare(t)) is dict else None
            for key, value in got.items():
                try:
                    msgspec.convert(value, value_type)
                except msgspec.ValidationError:
                    wanted = _expected(value_type) or text[:1].lower() + text[1:]
                    raise _fail(path, ".".join([prefix, *names, str(key)]), wanted, value) from None
        where = ".".join([prefix, *names] if prefix else names) or "(top level)"
        expected = _expected(t) if t is not None else None
        if expected is None:
            kind = re.match(r"Expected `([^`]+)`(.*?)(?:, got .*)?$", text)
            expected = text[:1].lower() + text[1:]
            if kind is not None:
                words = [_KINDS.get(k, k) for k in kind.group(1).split(" | ") if k != "null"]
                expected = " or ".join(words) + kind.group(2).replace("`", "")
        if isinstance(got, list) and expected.startswith("names among "):
            choices = expected[len("names among ") :].split(", ")
            got = next((g for g in got if g not in choices), got)
        raise _fail(path, where, expected, got) from None


def _named(path: str, section: str, data: Any) -> dict[str, Any]:
    if not isinstance(data, dict):
        raise _fail(path, section, "a table of named tables", data)
    for name in data:
        try:
            keys.validate_name(name, f"{section[:-1]} name")
        except InvalidName as exc:
            raise ConfigError(f"{path}: {section}.{name}: {exc}") from None
    return data


def _vehicle(path: str, name: str, table: Any) -> VehicleSpec:
    """One vehicle: a PX4 SITL vehicle's link and id follow from its instance (and must agree with it)."""
    where = f"vehicles.{name}"
    if not isinstance(table, dict):
        raise _fail(path, where, "a table", table)
    v: VehicleSpec = _convert(VehicleSpec, {"name": name, **table}, path, where)
    fix: dict[str, Any] = {} if v.rigid_body != "" else {"rigid_body": name}
    if v.sim.mavlink and v.autopilot != "sim":
        raise _fail(
            path,
            f"{where}.sim.mavlink",
            f'no simulated side unless autopilot = "sim" (got {v.autopilot!r})',
            v.sim.mavlink,
        )
    if v.autopilot != "px4-sitl":
        for key in ("px4_instance", "px4_params"):
            if key in table:
                raise _fail(
                    path, f"{where}.{key}", f'no {key} unless autopilot = "px4-sitl" (got {v.autopilot!r})'
                )
    else:
        if v.px4_instance is None:
            raise _fail(
                path,
                f"{where}.px4_instance",
                f'the PX4 SITL instance number (0..{PX4_SITL_MAX_INSTANCE}) of a "px4-sitl" vehicle',
            )
        n = v.px4_instance
        port = PX4_SITL_OFFBOARD_PORT + n
        expected = f"udpin:127.0.0.1:{port}"
        if not v.mavlink:
            fix["mavlink"] = expected
        else:
            scheme, _, rest = v.mavlink.partition(":")
            host, _, port_s = rest.rpartition(":")
            if (
                scheme not in ("udpin", "udp")
                or host not in ("127.0.0.1", "localhost", "0.0.0.0")
                or port_s != str(port)
            ):
                raise _fail(
                    path,
                    f"{where}.mavlink",
                    f"{expected} for PX4 SITL instance {n} (px4_instance; or leave mavlink out)",
                    v.mavlink,
                )
        if "system_id" not in table:
            fix["system_id"] = n + 1
        elif v.system_id != n + 1:
            raise _fail(
                path,
                f"{where}.system_id",
                f"{n + 1}, the MAV_SYS_ID of PX4 SITL instance {n} (or leave it out)",
                v.system_id,
            )
    if not v.mavlink and "mavlink" not in fix:
        raise _fail(
            path,
            f"{where}.mavlink",
            "a pymavlink connection string (udpin:HOST:PORT, tcp:HOST:PORT, /dev/tty…)",
        )
    if "system_id" not in table and "system_id" not in fix:
        raise _fail(path, f"{where}.system_id", "an integer in 1..250 (MAV_SYS_ID; never 0)")
    if v.mavlink_peer:
        _check_peer(path, where, v, fix.get("mavlink", v.mavlink))
    return v.replace(**fix) if fix else v


def _check_peer(path: str, where: str, v: VehicleSpec, mavlink: str) -> None:
    """``mavlink_peer``: one host's IPv4 address and a port, on a listening UDP link to a real autopilot."""
    host, _, port = v.mavlink_peer.rpartition(":")
    try:
        ip = ipaddress.IPv4Address(host)
    except ValueError:
        ip = None
    if (
        ip is None
        or ip.is_unspecified
        or ip.is_multicast
        or ip == ipaddress.IPv4Address("255.255.255.255")
        or not re.fullmatch(r"[0-9]{1,5}", port, re.ASCII)
        or not 0 < int(port) < 65536
    ):
        raise _fail(
            path,
            f"{where}.mavlink_peer",
            "the autopilot's IPv4 address and UDP port, IP:PORT (e.g. 192.168.1.31:14550)",
            v.mavlink_peer,
        )
    if mavlink.partition(":")[0] not in ("udpin", "udp"):
        raise _fail(
            path,
            f"{where}.mavlink_peer",
            f"no mavlink_peer unless mavlink is udpin:HOST:PORT (got {mavlink!r})",
            v.mavlink_peer,
        )
    if v.autopilot == "sim":
        raise _fail(
            path,
            f"{where}.mavlink_peer",
            'no mavlink_peer with autopilot = "sim" (the simulated autopilot sends from any port)',
            v.mavlink_peer,
        )


_INSECURE = "enable [security] (arena security init) or, knowingly, set security.insecure = true"


def _check_exposure(
    path: str,
    zenoh: ZenohSpec,
    hosts: dict[str, HostSpec],
    vehicles: dict[str, VehicleSpec],
    *,
    zenoh_too: bool,
) -> None:
    """Nothing listens beyond loopback unauthenticated unless the config says ``insecure``.

    Zenoh endpoints (``zenoh_too``: without ``[security]``) and MAVLink links that listen on the network
    without signing or a pinned peer (``mavlink_peer``).
    """
    for field_name, endpoints in (("router_listen", zenoh.router_listen), ("listen", zenoh.listen)):
        for e in endpoints:
            if zenoh_too and not is_loopback(endpoint_host(e)):
                raise _fail(path, f"zenoh.{field_name}", f"loopback endpoints only: {_INSECURE}", e)
    for name, h in hosts.items():
        if (
            zenoh_too
            and h.address
            and not is_loopback(h.address)
            and zenoh.mode == "peer"
            and not zenoh.listen
        ):
            raise _fail(
                path,
                f"hosts.{name}.address",
                f"no address to listen on without authentication (its peers would): {_INSECURE}",
                h.address,
            )
    for name, v in vehicles.items():
        scheme = v.mavlink.partition(":")[0]
        listens = scheme in ("udpin", "tcpin", "udp") and not is_loopback(endpoint_host(v.mavlink))
        gcs_scheme = v.gcs.partition(":")[0]
        if gcs_scheme in ("udpin", "tcpin", "udp") and not is_loopback(endpoint_host(v.gcs)):
            raise _fail(
                path,
                f"vehicles.{name}.gcs",
                "a ground-station link on loopback only (it forwards whatever it receives to the vehicle, "
                "unauthenticated): use udpout:GCS_IP:PORT, or, knowingly, set security.insecure = true",
                v.gcs,
            )
        if listens and not v.signing_key_file and not v.mavlink_peer:
            raise _fail(
                path,
                f"vehicles.{name}.mavlink",
                f"an unsigned MAVLink link listening on loopback only: sign it (vehicles.{name}."
                f"signing_key_file), pin the autopilot's address (vehicles.{name}.mavlink_peer) or, "
                "knowingly, set security.insecure = true",
                v.mavlink,
            )


_SECTIONS = {
    "arena": ArenaSpec,
    "calibration": CalibrationSpec,
    "mocap": MocapSpec,
    "zenoh": ZenohSpec,
    "sim": SimSpec,
    "recorder": RecorderSpec,
    "security": SecuritySpec,
    "pipeline": PipelineSpec,
    "clock": ClockSpec,
}


def parse(data: dict[str, Any], path: str = "<config>") -> ArenaConfig:
    """Validate a parsed TOML document into an :class:`ArenaConfig`."""
    unknown = sorted(set(data) - set(_SECTIONS) - {"vehicles", "hosts"})
    if unknown:
        raise ConfigError(f"{path}: {unknown[0]}: unknown field")
    sections = {name: _convert(cls, data.get(name, {}), path, name) for name, cls in _SECTIONS.items()}
    arena: ArenaSpec = sections["arena"]
    if min(arena.size) <= 2 * arena.margin:
        raise _fail(path, "arena.size", "every dimension larger than twice the margin", list(arena.size))
    pipeline: PipelineSpec = sections["pipeline"]

    vehicles: dict[str, VehicleSpec] = {}
    ids: dict[int, str] = {}
    instances: dict[int, str] = {}
    for vname, table in _named(path, "vehicles", data.get("vehicles", {})).items():
        v = _vehicle(path, vname, table)
        if v.px4_instance is not None:
            if v.px4_instance in instances:
                raise _fail(
                    path,
                    f"vehicles.{vname}.px4_instance",
                    f"a PX4 SITL instance not used by {instances[v.px4_instance]}",
                    v.px4_instance,
                )
            instances[v.px4_instance] = vname
        if v.system_id in ids:
            raise _fail(
                path,
                f"vehicles.{vname}.system_id",
                f"a system id not used by {ids[v.system_id]}",
                v.system_id,
            )
        ids[v.system_id] = vname
        vehicles[vname] = v

    # With the transform decimating, no host runs per-vehicle downsamplers.
    default_vehicle_services = [
        s for s in VEHICLE_SERVICES if pipeline.decimate == "downsampler" or s != "downsampler"
    ]
    hosts: dict[str, HostSpec] = {}
    for hname, table in _named(path, "hosts", data.get("hosts", {})).items():
        where = f"hosts.{hname}"
        if not isinstance(table, dict):
            raise _fail(path, where, "a table", table)
        host: HostSpec = _convert(
            HostSpec, {"name": hname, "vehicle_services": default_vehicle_services, **table}, path, where
        )
        if pipeline.decimate == "transform" and "downsampler" in host.vehicle_services:
            raise _fail(
                path,
                f"{where}.vehicle_services",
                'no "downsampler" while pipeline.decimate = "transform" (the transform decimates)',
                list(host.vehicle_services),
            )
        listening: dict[int, str] = {}
        for vname in host.vehicles:
            if vname not in vehicles:
                raise _fail(
                    path,
                    f"{where}.vehicles",
                    f"names of configured vehicles ({', '.join(vehicles) or 'none'})",
                    vname,
                )
            port = udp_listen_port(vehicles[vname].mavlink)
            if port is not None and port in listening:
                raise _fail(
                    path,
                    f"{where}.vehicles",
                    f"vehicles whose gateways listen on distinct UDP ports ({listening[port]} and {vname}"
                    f" both use {port} on this host)",
                    list(host.vehicles),
                )
            if port is not None:
                listening[port] = vname
        hosts[hname] = host

    security: SecuritySpec = sections["security"]
    if not security.insecure:
        _check_exposure(path, sections["zenoh"], hosts, vehicles, zenoh_too=not security.enabled)
    for cmd_host in security.command_hosts:
        if cmd_host not in hosts:
            raise _fail(
                path,
                "security.command_hosts",
                f"names of configured hosts ({', '.join(hosts) or 'none'})",
                cmd_host,
            )
    return ArenaConfig(path=path, hosts=hosts, vehicles=vehicles, **sections)


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
