"""The wire contract: typed payloads for every key, encoded as msgpack maps with short field names.

Every payload is a frozen dataclass whose fields carry their wire name, kind, unit and range.  The
same metadata drives encoding, validated decoding and the JSON Schemas in ``docs/schemas/``.  SI units
everywhere; times are integer nanoseconds since the Unix epoch (``t`` = when it was measured or
happened, ``tp`` = when it was published).  The Zenoh encoding names the schema and its version:
``application/msgpack;arena.Pose/1``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar, dataclass_transform

import msgpack

from arena_common import keys
from arena_common.errors import InvalidName, PayloadError

ENCODING_PREFIX = "application/msgpack;"
_MAX_INT = 2**63 - 1


@dataclass(frozen=True, slots=True)
class Spec:
    """How one field travels: its short wire name, kind, unit, range and description."""

    wire: str
    kind: str  # int, float, bool, str, vec3, quat, map, strs
    doc: str
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    optional: bool = False
    nan_ok: bool = False
    choices: tuple[str, ...] = ()


def _f(wire: str, kind: str, doc: str, *, default: Any = dataclasses.MISSING, **kw: Any) -> Any:
    spec = Spec(wire, kind, doc, **kw)
    if default is dataclasses.MISSING:
        return field(metadata={"wire": spec})
    if isinstance(default, (dict, list)):
        return field(default_factory=lambda: type(default)(default), metadata={"wire": spec})
    return field(default=default, metadata={"wire": spec})


def now_ns() -> int:
    """Wall-clock time in integer nanoseconds, the arena's common time base."""
    return time.time_ns()


Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
T = TypeVar("T", bound="Payload")


class Payload:
    """Base of every wire type. Subclasses are frozen dataclasses with ``SCHEMA`` and ``VERSION``."""

    SCHEMA: ClassVar[str]
    VERSION: ClassVar[int] = 1
    DOC: ClassVar[str] = ""
    _specs: ClassVar[tuple[tuple[str, Spec], ...]]
    _encode_plan: ClassVar[tuple[tuple[str, str, bool], ...]]
    _decode_plan: ClassVar[tuple[tuple[str, Spec, Callable[[Any], Any]], ...]]

    @classmethod
    def encoding(cls) -> str:
        """The Zenoh encoding string, e.g. ``application/msgpack;arena.Pose/1``."""
        return f"{ENCODING_PREFIX}arena.{cls.SCHEMA}/{cls.VERSION}"

    def to_dict(self) -> dict[str, Any]:
        """The wire map (short field names)."""
        out: dict[str, Any] = {}
        for name, spec in self._specs:
            value = getattr(self, name)
            if value is None and spec.optional:
                continue
            if spec.kind in ("vec3", "quat", "strs"):
                value = list(value)
            out[spec.wire] = value
        return out

    def encode(self) -> bytes:
        """msgpack bytes of :meth:`to_dict` (msgpack packs the tuples as arrays itself)."""
        out: dict[str, Any] = {}
        for name, wire_name, optional in self._encode_plan:
            value = getattr(self, name)
            if value is None and optional:
                continue
            out[wire_name] = value
        return msgpack.packb(out, use_bin_type=True)

    @classmethod
    def from_dict(cls: type[T], data: Any, key: str = "") -> T:
        """Validate a wire map and build the payload; raise :class:`PayloadError` naming the field."""
        if not isinstance(data, Mapping):
            raise PayloadError(f"expected a map, got {type(data).__name__}", key=key, type_name=cls.SCHEMA)
        kwargs: dict[str, Any] = {}
        for name, spec, fast in cls._decode_plan:
            value = data.get(spec.wire, _ABSENT)
            if value is _ABSENT:
                if spec.optional:
                    continue
                default = _default_of(cls, name)
                if default is dataclasses.MISSING:
                    raise PayloadError("missing field", key=key, type_name=cls.SCHEMA, field=spec.wire)
                continue
            # The fast check accepts only plain well-formed values; anything else takes the full check,
            # which converts or names what is wrong.
            checked = fast(value)
            kwargs[name] = _check(spec, value, key, cls.SCHEMA) if checked is _ABSENT else checked
        try:
            obj = cls(**kwargs)
        except (TypeError, ValueError) as exc:
            raise PayloadError(str(exc), key=key, type_name=cls.SCHEMA) from None
        problem = obj.check()
        if problem:
            raise PayloadError(problem[1], key=key, type_name=cls.SCHEMA, field=problem[0])
        return obj

    @classmethod
    def decode(cls: type[T], raw: bytes, key: str = "") -> T:
        """Decode msgpack bytes of this type."""
        return cls.from_dict(_unpack(raw, key, cls.SCHEMA), key)

    def check(self) -> tuple[str, str] | None:
        """Cross-field rules; return ``(field, reason)`` when broken."""
        return None

    def replace(self: T, **changes: Any) -> T:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]


def _default_of(cls: type, name: str) -> Any:
    f = cls.__dataclass_fields__[name]  # type: ignore[attr-defined]
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _unpack(raw: bytes, key: str, type_name: str) -> Any:
    try:
        return msgpack.unpackb(bytes(raw), raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types on bad input
        raise PayloadError(f"not valid msgpack: {exc}", key=key, type_name=type_name) from None


def _number(spec: Spec, v: Any, key: str, schema: str, want_int: bool) -> float | int:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise PayloadError(
            f"expected a number, got {type(v).__name__}", key=key, type_name=schema, field=spec.wire
        )
    if want_int:
        if not isinstance(v, int):
            raise PayloadError("expected an integer", key=key, type_name=schema, field=spec.wire)
        if abs(v) > _MAX_INT:
            raise PayloadError("integer out of range", key=key, type_name=schema, field=spec.wire)
    else:
        v = float(v)
        if not math.isfinite(v) and not (spec.nan_ok and math.isnan(v)):
            raise PayloadError(f"not a finite number: {v}", key=key, type_name=schema, field=spec.wire)
    if (spec.lo is not None and v < spec.lo) or (spec.hi is not None and v > spec.hi):
        raise PayloadError(f"{v} outside [{spec.lo}, {spec.hi}]", key=key, type_name=schema, field=spec.wire)
    return v


def _check(spec: Spec, v: Any, key: str, schema: str) -> Any:
    if v is None:
        if spec.optional:
            return None
        if spec.nan_ok:
            return math.nan  # JSON has no NaN: nil stands for "unknown" where NaN is allowed
        raise PayloadError("must not be nil", key=key, type_name=schema, field=spec.wire)
    kind = spec.kind
    if kind == "int":
        return _number(spec, v, key, schema, True)
    if kind == "float":
        return _number(spec, v, key, schema, False)
    if kind == "bool":
        if not isinstance(v, bool):
            raise PayloadError(
                f"expected a boolean, got {type(v).__name__}", key=key, type_name=schema, field=spec.wire
            )
        return v
    if kind == "str":
        if not isinstance(v, str):
            raise PayloadError(
                f"expected a string, got {type(v).__name__}", key=key, type_name=schema, field=spec.wire
            )
        if len(v) > 4096:
            raise PayloadError("string longer than 4096", key=key, type_name=schema, field=spec.wire)
        if spec.choices and v not in spec.choices:
            raise PayloadError(
                f"{v!r} not one of {', '.join(spec.choices)}", key=key, type_name=schema, field=spec.wire
            )
        return v
    if kind in ("vec3", "quat"):
        n = 3 if kind == "vec3" else 4
        if not isinstance(v, (list, tuple)) or len(v) != n:
            raise PayloadError(
                f"expected an array of {n} numbers", key=key, type_name=schema, field=spec.wire
            )
        return tuple(_number(spec, x, key, schema, False) for x in v)
    if kind == "strs":
        if not isinstance(v, (list, tuple)) or not all(isinstance(x, str) for x in v) or len(v) > 256:
            raise PayloadError("expected an array of strings", key=key, type_name=schema, field=spec.wire)
        return tuple(v)
    if kind == "map":
        if not isinstance(v, Mapping) or not all(isinstance(k, str) for k in v):
            raise PayloadError("expected a map with string keys", key=key, type_name=schema, field=spec.wire)
        return dict(v)
    raise AssertionError(kind)


_ABSENT: Any = object()  # a field not in the map; also what a fast check returns to ask for the full one


def _fast_check(spec: Spec) -> Callable[[Any], Any]:
    """A check that returns a plain, valid value as it will be stored, else ``_ABSENT``.

    It accepts a subset of what :func:`_check` accepts and returns the same value for it, so the hot
    path (poses at the mocap rate) skips the general dispatch.  ``v - v == 0.0`` is false for NaN and ±inf.
    """
    lo = -math.inf if spec.lo is None else spec.lo
    hi = math.inf if spec.hi is None else spec.hi
    if spec.kind == "float":
        return lambda v: v if type(v) is float and v - v == 0.0 and lo <= v <= hi else _ABSENT
    if spec.kind == "int":
        ilo, ihi = max(lo, -_MAX_INT), min(hi, _MAX_INT)
        return lambda v: v if type(v) is int and ilo <= v <= ihi else _ABSENT
    if spec.kind == "bool":
        return lambda v: v if type(v) is bool else _ABSENT
    if spec.kind == "str" and not spec.choices:
        return lambda v: v if type(v) is str and len(v) <= 4096 else _ABSENT
    if spec.kind == "str":
        choices = frozenset(spec.choices)
        return lambda v: v if type(v) is str and v in choices else _ABSENT
    if spec.kind in ("vec3", "quat") and spec.lo is None and spec.hi is None:
        n = 3 if spec.kind == "vec3" else 4

        def vector(v: Any) -> Any:
            if type(v) is not list or len(v) != n:
                return _ABSENT
            for x in v:
                if type(x) is not float or x - x != 0.0:
                    return _ABSENT
            return tuple(v)

        return vector
    return lambda v: _ABSENT


def _quat_problem(q: Quat | None, wire: str) -> tuple[str, str] | None:
    if q is None:
        return None
    n = math.sqrt(sum(c * c for c in q))
    if abs(n - 1.0) > 1e-3:
        return wire, f"quaternion norm {n:.4f} is not 1"
    return None


REGISTRY: dict[str, type[Payload]] = {}


@dataclass_transform(frozen_default=True, field_specifiers=(field, _f))
def payload(cls: type[T]) -> type[T]:
    """Class decorator: freeze as a slotted dataclass, collect field specs, register the schema."""
    dc = dataclass(frozen=True, slots=True)(cls)
    dc._specs = tuple((f.name, f.metadata["wire"]) for f in dataclasses.fields(dc))  # type: ignore[arg-type]
    dc._encode_plan = tuple((name, spec.wire, spec.optional) for name, spec in dc._specs)
    dc._decode_plan = tuple((name, spec, _fast_check(spec)) for name, spec in dc._specs)
    REGISTRY[dc.SCHEMA] = dc
    return dc


_LANDED = ("undefined", "on_ground", "in_air", "takeoff", "landing")
_TSRC = ("echo", "latency", "arrival", "sim")


@payload
class MocapPose(Payload):
    """A rigid body as Motive streamed it, in Motive's own frame (Y-up or Z-up)."""

    SCHEMA = "MocapPose"
    DOC = "A rigid body as Motive streamed it, in Motive's frame; `ok` false when Motive lost tracking."
    t: int = _f("t", "int", "Measurement time (camera mid-exposure on the local clock)", unit="ns")
    fn: int = _f("fn", "int", "Motive frame number", lo=0)
    id: int = _f("id", "int", "Motive rigid-body id")
    p: Vec3 = _f("p", "vec3", "Position x, y, z in Motive's frame", unit="m")
    q: Quat = _f("q", "quat", "Attitude quaternion w, x, y, z in Motive's frame (body to world)")
    ok: bool = _f("ok", "bool", "Tracking valid (Motive's rigid-body params bit 0)")
    name: str = _f("name", "str", "Rigid-body name from Motive's model definitions", default="")
    err: float = _f(
        "err", "float", "Mean marker error (NaN when unknown)", default=math.nan, unit="m", nan_ok=True
    )
    lat: int = _f(
        "lat", "int", "System latency, camera exposure to transmit (-1 unknown)", default=-1, unit="ns"
    )
    mts: float = _f("mts", "float", "Motive's session timestamp", default=0.0, unit="s")
    tsrc: str = _f("tsrc", "str", "How `t` was obtained", default="arrival", choices=_TSRC)
    tp: int = _f("tp", "int", "Publish time", default=0, unit="ns")

    def check(self) -> tuple[str, str] | None:
        return _quat_problem(self.q, "q") if self.ok else None


@payload
class Pose(Payload):
    """A pose in the arena frame: NED position, FRD body attitude, with estimated velocities."""

    SCHEMA = "Pose"
    DOC = "Pose in the arena frame (NED position, FRD body quaternion) with finite-difference velocities."
    t: int = _f("t", "int", "Measurement time", unit="ns")
    p: Vec3 = _f("p", "vec3", "Position north, east, down", unit="m")
    q: Quat = _f("q", "quat", "Attitude quaternion w, x, y, z, body FRD to arena NED")
    ok: bool = _f("ok", "bool", "Pose valid (tracked); never send an invalid pose to an autopilot")
    fn: int = _f("fn", "int", "Motive frame number (0 when not from Motive)", default=0, lo=0)
    v: Vec3 = _f("v", "vec3", "Velocity north, east, down", default=(0.0, 0.0, 0.0), unit="m/s")
    w: Vec3 = _f("w", "vec3", "Angular velocity, body FRD", default=(0.0, 0.0, 0.0), unit="rad/s")
    vok: bool = _f("vok", "bool", "Velocities valid", default=False)
    rc: int = _f(
        "rc",
        "int",
        "Reset counter: changes when the pose jumps (re-acquired, recalibrated)",
        default=0,
        lo=0,
        hi=255,
    )
    tp: int = _f("tp", "int", "Publish time", default=0, unit="ns")

    def check(self) -> tuple[str, str] | None:
        return _quat_problem(self.q, "q") if self.ok else None


@payload
class State(Payload):
    """The vehicle as its autopilot reports it, plus the health of the gateway's link and vision."""

    SCHEMA = "State"
    DOC = "The vehicle as its autopilot reports it, with link and vision-pipeline health."
    t: int = _f("t", "int", "Time of this snapshot", unit="ns")
    sysid: int = _f("sysid", "int", "MAVLink system id of the autopilot", default=0, lo=0, hi=255)
    link: bool = _f("link", "bool", "Heartbeats arriving (none for 3 s = link lost)", default=False)
    armed: bool = _f("armed", "bool", "Motors armed", default=False)
    mode: str = _f(
        "mode", "str", "Flight mode by name (PX4 naming, e.g. OFFBOARD, AUTO.LAND)", default="UNKNOWN"
    )
    landed: str = _f("landed", "str", "Landed state", default="undefined", choices=_LANDED)
    p: Vec3 | None = _f(
        "p", "vec3", "Autopilot's local position estimate, NED", default=None, unit="m", optional=True
    )
    v: Vec3 | None = _f(
        "v", "vec3", "Autopilot's velocity estimate, NED", default=None, unit="m/s", optional=True
    )
    q: Quat | None = _f("q", "quat", "Autopilot's attitude, FRD to NED", default=None, optional=True)
    mp: Vec3 | None = _f(
        "mp", "vec3", "Last mocap position sent as vision", default=None, unit="m", optional=True
    )
    bat: float | None = _f(
        "bat", "float", "Battery remaining, 0–1", default=None, lo=0.0, hi=1.0, optional=True
    )
    volt: float | None = _f("volt", "float", "Battery voltage", default=None, unit="V", optional=True)
    rtt: float | None = _f(
        "rtt", "float", "Link round-trip time from TIMESYNC", default=None, unit="s", optional=True
    )
    hb_age: float | None = _f(
        "hb_age", "float", "Age of the last heartbeat", default=None, unit="s", optional=True
    )
    vis_rate: float = _f(
        "vis_rate", "float", "Vision samples sent per second", default=0.0, unit="Hz", lo=0.0
    )
    vis_age: float | None = _f(
        "vis_age", "float", "Age of the last vision sample sent", default=None, unit="s", optional=True
    )
    vis_fused: bool = _f(
        "vis_fused", "bool", "The autopilot's estimate follows the vision input", default=False
    )
    ofb: bool = _f("ofb", "bool", "Offboard setpoints are being streamed to the autopilot", default=False)
    setup_ok: bool = _f(
        "setup_ok", "bool", "The arena's required autopilot parameters are set", default=False
    )
    fs: tuple[str, ...] = _f("fs", "strs", "Active failsafes or warnings", default=())
    tp: int = _f("tp", "int", "Publish time", default=0, unit="ns")

    def check(self) -> tuple[str, str] | None:
        return _quat_problem(self.q, "q")


@payload
class Telemetry(Payload):
    """One raw MAVLink message from the autopilot, its fields as a map."""

    SCHEMA = "Telemetry"
    DOC = "One raw MAVLink message from the autopilot: its name and fields."
    t: int = _f("t", "int", "Receive time", unit="ns")
    msg: str = _f("msg", "str", "MAVLink message name")
    f: dict[str, Any] = _f("f", "map", "Message fields by MAVLink name", default={})


@payload
class Event(Payload):
    """Something that happened: status text, a mode or arming change, a failsafe, a command result."""

    SCHEMA = "Event"
    DOC = "Something that happened to a vehicle or service; severity as MAV_SEVERITY (0 emergency … 7 debug)."
    t: int = _f("t", "int", "Time it happened", unit="ns")
    kind: str = _f(
        "kind",
        "str",
        "statustext, mode, armed, failsafe, command, safety, link, setup, info",
        choices=("statustext", "mode", "armed", "failsafe", "command", "safety", "link", "setup", "info"),
    )
    text: str = _f("text", "str", "Human-readable text")
    sev: int = _f("sev", "int", "Severity (MAV_SEVERITY)", default=6, lo=0, hi=7)
    data: dict[str, Any] = _f("data", "map", "Details", default={})


COMMAND_OPS = (
    "arm",
    "disarm",
    "kill",
    "takeoff",
    "land",
    "hold",
    "mode",
    "goto",
    "reboot",
    "param_get",
    "param_set",
    "check",
    "setup",
    "ping",
    "start",
    "stop",
)


@payload
class Command(Payload):
    """A request to a vehicle's gateway (or a service), answered by a :class:`CommandResult`."""

    SCHEMA = "Command"
    DOC = "A command; `args` per op: takeoff {height}, mode {mode}, goto {p, yaw}, param_get {name}, …"
    op: str = _f("op", "str", "Operation", choices=COMMAND_OPS)
    args: dict[str, Any] = _f("args", "map", "Arguments of the operation", default={})
    src: str = _f("src", "str", "Who sends it (host/program)", default="")
    timeout: float = _f(
        "timeout", "float", "How long the caller waits", default=5.0, unit="s", lo=0.0, hi=600.0
    )
    t: int = _f("t", "int", "Time sent", default=0, unit="ns")


RESULTS = (
    "ACCEPTED",
    "TEMPORARILY_REJECTED",
    "DENIED",
    "UNSUPPORTED",
    "FAILED",
    "IN_PROGRESS",
    "CANCELLED",
    "TIMEOUT",
    "REFUSED",
    "ERROR",
)


@payload
class CommandResult(Payload):
    """The answer to a :class:`Command`: the autopilot's result, a timeout, or a refusal with its reason."""

    SCHEMA = "CommandResult"
    DOC = "Answer to a Command: MAV_RESULT name, TIMEOUT, REFUSED (safety rules) or ERROR (bad request)."
    ok: bool = _f("ok", "bool", "True when the command succeeded")
    result: str = _f("result", "str", "Outcome", choices=RESULTS)
    reason: str = _f("reason", "str", "Why, in words", default="")
    value: dict[str, Any] = _f("value", "map", "Returned data (e.g. parameter values)", default={})
    t: int = _f("t", "int", "Time answered", default=0, unit="ns")


@payload
class Setpoint(Payload):
    """An offboard setpoint in the arena NED frame, valid for ``lease`` seconds."""

    SCHEMA = "Setpoint"
    DOC = "Offboard setpoint in the arena NED frame; forwarded only while its lease runs."
    t: int = _f("t", "int", "Time sent", unit="ns")
    lease: float = _f("lease", "float", "How long it stays valid", default=0.5, unit="s", lo=0.05, hi=5.0)
    p: Vec3 | None = _f("p", "vec3", "Position north, east, down", default=None, unit="m", optional=True)
    v: Vec3 | None = _f(
        "v", "vec3", "Velocity (or feed-forward with p)", default=None, unit="m/s", optional=True
    )
    yaw: float | None = _f("yaw", "float", "Yaw", default=None, unit="rad", optional=True)
    yr: float | None = _f("yr", "float", "Yaw rate", default=None, unit="rad/s", optional=True)
    src: str = _f("src", "str", "Who sends it", default="")

    def check(self) -> tuple[str, str] | None:
        if self.p is None and self.v is None:
            return "p", "a setpoint needs a position (p) or a velocity (v)"
        if self.yaw is not None and self.yr is not None:
            return "yr", "give yaw or yaw rate, not both"
        return None


@payload
class Estop(Payload):
    """Stop everything: every gateway lands its vehicle (or cuts its motors with ``kill``)."""

    SCHEMA = "Estop"
    DOC = "Emergency stop for every vehicle: land, or kill motors when `kill` is true."
    t: int = _f("t", "int", "Time sent", unit="ns")
    kill: bool = _f("kill", "bool", "Cut motors instead of landing", default=False)
    reason: str = _f("reason", "str", "Why", default="")
    src: str = _f("src", "str", "Who sent it", default="")


@payload
class Stats(Payload):
    """A service's counters, published every second."""

    SCHEMA = "Stats"
    DOC = "A service's counters: messages in/out, rejected inputs by reason, rates, latencies, resources."
    t: int = _f("t", "int", "Time of the snapshot", unit="ns")
    service: str = _f("service", "str", "Service id")
    host: str = _f("host", "str", "Host name")
    pid: int = _f("pid", "int", "Process id", default=0)
    up: float = _f("up", "float", "Uptime", default=0.0, unit="s")
    counts: dict[str, Any] = _f("counts", "map", "Counters since start (in, out, …)", default={})
    rejected: dict[str, Any] = _f("rejected", "map", "Rejected inputs since start, by reason", default={})
    rates: dict[str, Any] = _f(
        "rates", "map", "Per-second rates over the last interval", default={}, unit="Hz"
    )
    lat: dict[str, Any] = _f(
        "lat", "map", "Latency figures (p50, p99, max) over the last interval", default={}, unit="s"
    )
    cpu: float = _f("cpu", "float", "CPU use over the last interval, percent of one core", default=0.0)
    rss: int = _f("rss", "int", "Resident memory", default=0, unit="byte")
    vehicle: str = _f("vehicle", "str", "Vehicle served, if any", default="")


_KIND_TO_TYPE: dict[str, type[Payload]] = {
    "mocap": MocapPose,
    "pose": Pose,
    "vision": Pose,
    "truth": Pose,
    "state": State,
    "telemetry": Telemetry,
    "events": Event,
    "setpoint": Setpoint,
    "estop": Estop,
    "stats": Stats,
    "bodies": MocapPose,
    "cmd": Command,
    "rec": Command,
}


def type_for_key(key: str) -> type[Payload]:
    """The payload type a key carries (queries carry :class:`Command`)."""
    try:
        kind = keys.parse(key).kind
    except InvalidName as exc:
        raise PayloadError(str(exc), key=key) from None
    if kind not in _KIND_TO_TYPE:
        raise PayloadError("this key carries no payload", key=key)
    return _KIND_TO_TYPE[kind]


def type_for_encoding(encoding: str) -> type[Payload] | None:
    """The payload type named by an ``application/msgpack;arena.X/N`` encoding, if any."""
    if not encoding.startswith(ENCODING_PREFIX):
        return None
    schema = encoding[len(ENCODING_PREFIX) :]
    if not schema.startswith("arena."):
        return None
    name, _, version = schema[len("arena.") :].partition("/")
    cls = REGISTRY.get(name)
    if cls is None:
        raise PayloadError(f"unknown schema {schema!r}")
    if version != str(cls.VERSION):
        raise PayloadError(
            f"schema version {version!r} not supported (this build speaks {cls.VERSION})", type_name=name
        )
    return cls


_DECODERS: dict[tuple[str, str], type[Payload]] = {}  # (key, encoding) → type, for pairs seen valid
_DECODERS_MAX = 4096


def decode_any(key: str, raw: bytes, encoding: str = "") -> Payload:
    """Decode a payload as the type its key carries.

    An encoding that names a schema must name that same type (a ``State`` sent on a vision key is
    refused, never handed on as a State); keys outside the table are decoded by their encoding.
    """
    cls = _DECODERS.get((key, encoding))
    if cls is None:
        cls = _decoder_for(key, encoding)
        if len(_DECODERS) >= _DECODERS_MAX:  # bounded: a flood of odd keys only costs the slow path
            _DECODERS.clear()
        _DECODERS[(key, encoding)] = cls
    return cls.decode(raw, key)


def _decoder_for(key: str, encoding: str) -> type[Payload]:
    by_encoding = type_for_encoding(encoding) if encoding else None
    try:
        by_key: type[Payload] | None = type_for_key(key)
    except PayloadError:
        if by_encoding is None:
            raise
        by_key = None
    if by_key is Command and by_encoding is CommandResult:
        by_key = CommandResult  # a command key carries the query and its reply
    if by_key is not None and by_encoding is not None and by_encoding is not by_key:
        raise PayloadError(
            f"a {by_encoding.SCHEMA} payload on a key that carries {by_key.SCHEMA}",
            key=key,
            type_name=by_key.SCHEMA,
        )
    cls = by_key or by_encoding
    assert cls is not None
    return cls


_JSON_KIND: dict[str, Callable[[Spec], dict[str, Any]]] = {
    "int": lambda s: {"type": "integer"},
    "float": lambda s: {"type": "number"},
    "bool": lambda s: {"type": "boolean"},
    "str": lambda s: {"type": "string", **({"enum": list(s.choices)} if s.choices else {})},
    "vec3": lambda s: {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "quat": lambda s: {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
    "strs": lambda s: {"type": "array", "items": {"type": "string"}},
    "map": lambda s: {"type": "object"},
}


def json_schema(cls: type[Payload]) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of one payload type's wire map, generated from its field specs."""
    props: dict[str, Any] = {}
    required: list[str] = []
    for name, spec in cls._specs:
        prop = _JSON_KIND[spec.kind](spec)
        desc = spec.doc + (f" [{spec.unit}]" if spec.unit else "")
        prop["description"] = desc
        if spec.lo is not None:
            prop["minimum"] = spec.lo
        if spec.hi is not None:
            prop["maximum"] = spec.hi
        if spec.nan_ok:
            prop = {"description": desc, "anyOf": [{"type": "number"}, {"type": "null"}]}
        if spec.optional:
            prop = {
                "description": desc,
                "anyOf": [{k: v for k, v in prop.items() if k != "description"}, {"type": "null"}],
            }
        props[spec.wire] = prop
        if _default_of(cls, name) is dataclasses.MISSING:
            required.append(spec.wire)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"arena.{cls.SCHEMA}/{cls.VERSION}",
        "title": f"arena.{cls.SCHEMA}",
        "description": cls.DOC,
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": True,
    }


def to_jsonable(p: Payload) -> dict[str, Any]:
    """The wire map with NaN replaced by ``None`` so it is valid JSON."""

    def fix(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, list):
            return [fix(x) for x in v]
        if isinstance(v, dict):
            return {k: fix(x) for k, x in v.items()}
        return v

    return {k: fix(v) for k, v in p.to_dict().items()}
