"""The wire contract: typed payloads for every key, encoded as msgpack maps with short field names.

Every payload is a frozen :class:`msgspec.Struct`. Each field's annotation says everything about it:
its type (msgspec decodes and validates it), its range, and its description and unit
(``Annotated[int, _int("Measurement time", unit="ns")]``). The field names are the wire names. The
same annotations drive encoding, validated decoding, the JSON Schemas in ``docs/schemas/`` and
``docs/wire.md``. What a type cannot say (the names a string may take, unit quaternions, rules
between fields) is :meth:`Payload.check`, run on every decode.

SI units everywhere; times are integer nanoseconds since the Unix epoch (``t`` = when it was measured
or happened, ``tp`` = when it was published). The Zenoh encoding names the schema and its version:
``application/msgpack;arena.Pose/1``.
"""

from __future__ import annotations

import functools
import math
from typing import Annotated, Any

from msgspec import Meta

from arena_common.core import keys
from arena_common.core.errors import InvalidName, PayloadError
from arena_common.core.ops import OPS
from arena_common.core.payload import (
    ENCODING_PREFIX,
    F64,
    REGISTRY,
    Map,
    Payload,
    Quat,
    Spec,
    Str,
    Strs,
    Vec3,
    _always,
    _doc,
    _float,
    _int,
    _quat_problem,
    default_of,
    now_ns,
    part,
    payload,
)

__all__ = [  # the machinery's public names, re-exported: users import the wire from here
    "COMMAND_OPS",
    "ENCODING_PREFIX",
    "F64",
    "REGISTRY",
    "RESULTS",
    "ClockOffset",
    "Command",
    "CommandResult",
    "Estop",
    "Event",
    "Fleet",
    "FleetVehicle",
    "Map",
    "MocapBody",
    "MocapFrame",
    "MocapPose",
    "Payload",
    "Pose",
    "Quat",
    "Setpoint",
    "Spec",
    "State",
    "Stats",
    "Str",
    "Strs",
    "Telemetry",
    "Vec3",
    "decode_any",
    "default_of",
    "json_schema",
    "now_ns",
    "part",
    "payload",
    "to_jsonable",
    "type_for_encoding",
    "type_for_key",
]

# -- the payload types ---------------------------------------------------------------------------------

_LANDED = ("undefined", "on_ground", "in_air", "takeoff", "landing")
_TSRC = ("echo", "latency", "arrival", "sim")

# Fields a MocapPose shares with a MocapFrame (the frame's) and with a MocapBody (the body's).
_MeasuredAt = Annotated[int, _int("Measurement time (camera mid-exposure on the local clock)", unit="ns")]
_FrameNumber = Annotated[int, _int("Motive frame number", lo=0)]
_BodyId = Annotated[int, _int("Motive rigid-body id")]
_MotiveP = Annotated[Vec3, _doc("Position x, y, z in Motive's frame", unit="m")]
_MotiveQ = Annotated[Quat, _doc("Attitude quaternion w, x, y, z in Motive's frame (body to world)")]
_Tracked = Annotated[bool, _doc("Tracking valid (Motive's rigid-body params bit 0)")]
_BodyName = Annotated[Str, _doc("Rigid-body name from Motive's model definitions")]
_MarkerError = Annotated[float, _float("Mean marker error (NaN when unknown)", unit="m", nan_ok=True)]
_Latency = Annotated[int, _int("System latency, camera exposure to transmit (-1 unknown)", unit="ns")]
_MotiveTime = Annotated[float, _float("Motive's session timestamp", unit="s")]
_TimeSource = Annotated[Str, _doc("How `t` was obtained", choices=_TSRC)]
_Published = Annotated[int, _int("Publish time", unit="ns")]


@payload
class MocapPose(Payload, frozen=True):
    """A rigid body as Motive streamed it, in Motive's own frame (Y-up or Z-up)."""

    SCHEMA = "MocapPose"
    DOC = "A rigid body as Motive streamed it, in Motive's frame; `ok` false when Motive lost tracking."
    t: _MeasuredAt
    fn: _FrameNumber
    id: _BodyId
    p: _MotiveP
    q: _MotiveQ
    ok: _Tracked
    name: _BodyName = _always("")
    err: _MarkerError = _always(math.nan)
    lat: _Latency = _always(-1)
    mts: _MotiveTime = _always(0.0)
    tsrc: _TimeSource = _always("arrival")
    tp: _Published = _always(0)

    def check(self) -> tuple[str, str] | None:
        return super().check() or (_quat_problem(self.q, "q") if self.ok else None)


def _items_problem(items: tuple[Payload, ...], name: str) -> tuple[str, str] | None:
    """The first problem of an ``items`` field's elements, named ``name[i].field``, or None."""
    for i, item in enumerate(items):
        problem = item.check()
        if problem:
            return f"{name}[{i}].{problem[0]}", problem[1]
    return None


@part
class MocapBody(Payload, frozen=True):
    """One rigid body of a :class:`MocapFrame`: what a :class:`MocapPose` says of it beyond the frame."""

    SCHEMA = "MocapBody"
    DOC = "One rigid body of a mocap frame, in Motive's frame."
    v: Annotated[Str, _doc("The vehicle that claims this body")]
    id: _BodyId
    p: _MotiveP
    q: _MotiveQ
    ok: _Tracked
    name: _BodyName = _always("")
    err: _MarkerError = _always(math.nan)

    def check(self) -> tuple[str, str] | None:
        problem = super().check() or (_quat_problem(self.q, "q") if self.ok else None)
        if problem is None:
            try:
                keys.validate_name(self.v)
            except InvalidName as exc:
                return "v", str(exc)
        return problem


@payload
class MocapFrame(Payload, frozen=True):
    """Every claimed rigid body of one mocap frame: one message per frame for a stage that handles all
    bodies (the frame transform), instead of one per body."""

    SCHEMA = "MocapFrame"
    DOC = "Every vehicle's rigid body of one Motive frame, in Motive's frame (one message per frame)."
    t: _MeasuredAt
    fn: _FrameNumber
    b: Annotated[tuple[MocapBody, ...], Meta(max_length=256), _doc("The bodies, one per claimed vehicle")]
    lat: _Latency = _always(-1)
    mts: _MotiveTime = _always(0.0)
    tsrc: _TimeSource = _always("arrival")
    tp: _Published = _always(0)

    def check(self) -> tuple[str, str] | None:
        return super().check() or _items_problem(self.b, "b")

    def pose(self, body: MocapBody) -> MocapPose:
        """``body`` as the :class:`MocapPose` the per-vehicle ``mocap`` key carries for this frame."""
        return MocapPose(
            self.t,
            self.fn,
            body.id,
            body.p,
            body.q,
            body.ok,
            body.name,
            body.err,
            self.lat,
            self.mts,
            self.tsrc,
            self.tp,
        )


# A pose's fields, shared by :class:`Pose` and each :class:`VisionBody` of a :class:`VisionFrame`.
_PoseT = Annotated[int, _int("Measurement time", unit="ns")]
_PoseP = Annotated[Vec3, _doc("Position north, east, down", unit="m")]
_PoseQ = Annotated[Quat, _doc("Attitude quaternion w, x, y, z, body FRD to arena NED")]
_PoseOk = Annotated[bool, _doc("Pose valid (tracked); never send an invalid pose to an autopilot")]
_PoseFn = Annotated[int, _int("Motive frame number (0 when not from Motive)", lo=0)]
_PoseV = Annotated[Vec3, _doc("Velocity north, east, down", unit="m/s")]
_PoseW = Annotated[Vec3, _doc("Angular velocity, body FRD", unit="rad/s")]
_PoseVok = Annotated[bool, _doc("Velocities valid")]
_PoseRc = Annotated[
    int, _int("Reset counter: changes when the pose jumps (re-acquired, recalibrated)", lo=0, hi=255)
]


@payload
class Pose(Payload, frozen=True):
    """A pose in the arena frame: NED position, FRD body attitude, with estimated velocities."""

    SCHEMA = "Pose"
    DOC = "Pose in the arena frame (NED position, FRD body quaternion) with finite-difference velocities."
    t: _PoseT
    p: _PoseP
    q: _PoseQ
    ok: _PoseOk
    fn: _PoseFn = _always(0)
    v: _PoseV = _always((0.0, 0.0, 0.0))
    w: _PoseW = _always((0.0, 0.0, 0.0))
    vok: _PoseVok = _always(False)
    rc: _PoseRc = _always(0)
    tp: _Published = _always(0)

    def check(self) -> tuple[str, str] | None:
        return super().check() or (_quat_problem(self.q, "q") if self.ok else None)


@part
class VisionBody(Payload, frozen=True):
    """One vehicle's vision pose in a :class:`VisionFrame`: the :class:`Pose` its ``vision`` key carries,
    with the vehicle's name."""

    SCHEMA = "VisionBody"
    DOC = "One vehicle's vision pose (arena frame) of one mocap frame."
    n: Annotated[Str, _doc("The vehicle")]
    t: _PoseT
    p: _PoseP
    q: _PoseQ
    ok: _PoseOk
    fn: _PoseFn = _always(0)
    v: _PoseV = _always((0.0, 0.0, 0.0))
    w: _PoseW = _always((0.0, 0.0, 0.0))
    vok: _PoseVok = _always(False)
    rc: _PoseRc = _always(0)
    tp: _Published = _always(0)

    def check(self) -> tuple[str, str] | None:
        problem = super().check() or (_quat_problem(self.q, "q") if self.ok else None)
        if problem is None:
            try:
                keys.validate_name(self.n)
            except InvalidName as exc:
                return "n", str(exc)
        return problem

    @classmethod
    def of(cls, name: str, pose: Pose) -> VisionBody:
        """``pose`` as ``name``'s element of a frame."""
        return cls(name, pose.t, pose.p, pose.q, pose.ok, pose.fn, pose.v, pose.w, pose.vok, pose.rc, pose.tp)

    def pose(self) -> Pose:
        """The :class:`Pose` the vehicle's own ``vision`` key carries for this frame."""
        return Pose(self.t, self.p, self.q, self.ok, self.fn, self.v, self.w, self.vok, self.rc, self.tp)


@payload
class VisionFrame(Payload, frozen=True):
    """Every vehicle's vision pose of one mocap frame, in one message (the transform decimating): what a
    gateway serving several vehicles reads, woken once per frame instead of once per vehicle."""

    SCHEMA = "VisionFrame"
    DOC = "Every vehicle's vision pose (arena frame) of one mocap frame, one message per frame."
    fn: Annotated[int, _int("Motive frame number (0 when not from Motive)", lo=0)]
    b: Annotated[tuple[VisionBody, ...], Meta(max_length=256), _doc("The vehicles' poses, one each")]
    tp: _Published = _always(0)

    def check(self) -> tuple[str, str] | None:
        return super().check() or _items_problem(self.b, "b")


@payload
class State(Payload, frozen=True):
    """The vehicle as its autopilot reports it, plus the health of the gateway's link and vision."""

    SCHEMA = "State"
    DOC = "The vehicle as its autopilot reports it, with link and vision-pipeline health."
    t: Annotated[int, _int("Time of this snapshot", unit="ns")]
    sysid: Annotated[int, _int("MAVLink system id of the autopilot", lo=0, hi=255)] = _always(0)
    link: Annotated[bool, _doc("Heartbeats arriving (none for 3 s = link lost)")] = _always(False)
    armed: Annotated[bool, _doc("Motors armed")] = _always(False)
    mode: Annotated[Str, _doc("Flight mode by name (PX4 naming, e.g. OFFBOARD, AUTO.LAND)")] = _always(
        "UNKNOWN"
    )
    landed: Annotated[Str, _doc("Landed state", choices=_LANDED)] = _always("undefined")
    p: Annotated[Vec3, _doc("Autopilot's local position estimate, NED", unit="m")] | None = None
    v: Annotated[Vec3, _doc("Autopilot's velocity estimate, NED", unit="m/s")] | None = None
    q: Annotated[Quat, _doc("Autopilot's attitude, FRD to NED")] | None = None
    mp: Annotated[Vec3, _doc("Last mocap position sent as vision", unit="m")] | None = None
    bat: Annotated[float, _float("Battery remaining, 0–1", lo=0.0, hi=1.0)] | None = None
    volt: Annotated[float, _float("Battery voltage", unit="V")] | None = None
    rtt: Annotated[float, _float("Link round-trip time from TIMESYNC", unit="s")] | None = None
    rtt_jit: (
        Annotated[
            float, _float("Jitter of the link's round trip (RFC 3550's running mean of changes)", unit="s")
        ]
        | None
    ) = None
    stamps: Annotated[
        Str,
        _doc(
            "Whose clock stamps vision at the autopilot: 'ours' (PX4's TIMESYNC took the gateway's clock), "
            "'arrival' (PX4 stamps each sample on arrival: the link's delay is in every one), or empty before "
            "a round trip was measured",
            choices=("", "ours", "arrival"),
        ),
    ] = _always("")
    hb_age: Annotated[float, _float("Age of the last heartbeat", unit="s")] | None = None
    vis_rate: Annotated[float, _float("Vision samples sent per second", unit="Hz", lo=0.0)] = _always(0.0)
    vis_age: Annotated[float, _float("Age of the last vision sample sent", unit="s")] | None = None
    vis_fused: Annotated[bool, _doc("The autopilot's estimate follows the vision input")] = _always(False)
    ofb: Annotated[bool, _doc("Offboard setpoints are being streamed to the autopilot")] = _always(False)
    setup_ok: Annotated[bool, _doc("The arena's required autopilot parameters are set")] = _always(False)
    fs: Annotated[Strs, _doc("Active failsafes or warnings")] = _always(())
    tp: Annotated[int, _int("Publish time", unit="ns")] = _always(0)
    auth: Annotated[
        Str,
        _doc(
            "Who holds the vehicle: 'stream <id> (<source>)', 'goto (<source>)' (the gateway's hold), or "
            "empty (the autopilot's own mode)"
        ),
    ] = _always("")

    def check(self) -> tuple[str, str] | None:
        return super().check() or _quat_problem(self.q, "q")


@payload
class Telemetry(Payload, frozen=True):
    """One raw MAVLink message from the autopilot, its fields as a map."""

    SCHEMA = "Telemetry"
    DOC = "One raw MAVLink message from the autopilot: its name and fields."
    t: Annotated[int, _int("Receive time", unit="ns")]
    msg: Annotated[Str, _doc("MAVLink message name")]
    f: Annotated[Map, _doc("Message fields by MAVLink name")] = _always({})


_EVENT_KINDS = (
    "statustext",
    "mode",
    "armed",
    "failsafe",
    "command",
    "safety",
    "link",
    "setup",
    "estimator",
    "clock",
    "authority",
    "info",
)


@payload
class Event(Payload, frozen=True):
    """Something that happened: status text, a mode or arming change, a failsafe, a command result."""

    SCHEMA = "Event"
    DOC = "Something that happened to a vehicle or service; severity as MAV_SEVERITY (0 emergency … 7 debug)."
    t: Annotated[int, _int("Time it happened", unit="ns")]
    kind: Annotated[Str, _doc(", ".join(_EVENT_KINDS), choices=_EVENT_KINDS)]
    text: Annotated[Str, _doc("Human-readable text")]
    sev: Annotated[int, _int("Severity (MAV_SEVERITY)", lo=0, hi=7)] = _always(6)
    data: Annotated[Map, _doc("Details")] = _always({})


COMMAND_OPS = tuple(OPS)  # every operation: arena_common/core/ops.py


@payload
class Command(Payload, frozen=True):
    """A request to a vehicle's gateway (or a service), answered by a :class:`CommandResult`."""

    SCHEMA = "Command"
    DOC = "A command; `args` per op: takeoff {height}, mode {mode}, goto {p, yaw}, param_get {name}, …"
    op: Annotated[Str, _doc("Operation", choices=COMMAND_OPS)]
    args: Annotated[Map, _doc("Arguments of the operation")] = _always({})
    src: Annotated[Str, _doc("Who sends it (host/program)")] = _always("")
    timeout: Annotated[float, _float("How long the caller waits", unit="s", lo=0.0, hi=600.0)] = _always(5.0)
    t: Annotated[int, _int("Time sent", unit="ns")] = _always(0)


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
class CommandResult(Payload, frozen=True):
    """The answer to a :class:`Command`: the autopilot's result, a timeout, or a refusal with its reason."""

    SCHEMA = "CommandResult"
    DOC = "Answer to a Command: MAV_RESULT name, TIMEOUT, REFUSED (safety rules) or ERROR (bad request)."
    ok: Annotated[bool, _doc("True when the command succeeded")]
    result: Annotated[Str, _doc("Outcome", choices=RESULTS)]
    reason: Annotated[Str, _doc("Why, in words")] = _always("")
    value: Annotated[Map, _doc("Returned data (e.g. parameter values)")] = _always({})
    t: Annotated[int, _int("Time answered", unit="ns")] = _always(0)


@payload
class Setpoint(Payload, frozen=True):
    """An offboard setpoint in the arena NED frame, valid for ``lease`` seconds."""

    SCHEMA = "Setpoint"
    DOC = "Offboard setpoint in the arena NED frame; forwarded only while its lease runs."
    t: Annotated[int, _int("Time sent", unit="ns")]
    lease: Annotated[float, _float("How long it stays valid", unit="s", lo=0.05, hi=5.0)] = _always(0.5)
    p: Annotated[Vec3, _doc("Position north, east, down", unit="m")] | None = None
    v: Annotated[Vec3, _doc("Velocity (or feed-forward with p)", unit="m/s")] | None = None
    a: Annotated[Vec3, _doc("Acceleration feed-forward (with p or v)", unit="m/s²")] | None = None
    q: Annotated[Quat, _doc("Attitude w, x, y, z, body FRD to arena NED (with thrust; alone)")] | None = None
    thrust: (
        Annotated[float, _float("Collective thrust, 0 (none) to 1 (full), with q", lo=0.0, hi=1.0)] | None
    ) = None
    yaw: Annotated[float, _float("Yaw", unit="rad")] | None = None
    yr: Annotated[float, _float("Yaw rate", unit="rad/s")] | None = None
    src: Annotated[Str, _doc("Who sends it")] = _always("")
    stream: Annotated[
        Str, _doc("The stream it belongs to (unique per stream; a command engages or ends it by this)")
    ] = _always("")
    seq: Annotated[int, _int("Its number within the stream, from 1 (0: unnumbered)", lo=0)] = _always(0)

    def check(self) -> tuple[str, str] | None:
        if problem := super().check():
            return problem
        if self.q is not None or self.thrust is not None:
            if self.q is None or self.thrust is None:
                return (
                    "q" if self.q is None else "thrust"
                ), "an attitude setpoint needs q and thrust together"
            for name in ("p", "v", "a", "yaw", "yr"):
                if getattr(self, name) is not None:
                    return name, "an attitude setpoint (q, thrust) takes no position, velocity or yaw"
            return _quat_problem(self.q, "q")
        if self.p is None and self.v is None:
            return "p", "a setpoint needs a position (p) or a velocity (v)"
        if self.yaw is not None and self.yr is not None:
            return "yr", "give yaw or yaw rate, not both"
        return None


@part
class FleetVehicle(Payload, frozen=True):
    """One vehicle of a :class:`Fleet`."""

    SCHEMA = "FleetVehicle"
    DOC = "One tracked vehicle: its name, position and velocity (arena NED)."
    n: Annotated[Str, _doc("Vehicle name")]
    p: Annotated[Vec3, _doc("Position north, east, down", unit="m")]
    v: Annotated[Vec3, _doc("Velocity north, east, down (zeros when unknown)", unit="m/s")]


@payload
class Fleet(Payload, frozen=True):
    """Where every tracked vehicle is, in one message at a low rate: each gateway keeps its vehicle apart
    from the others with it (``arena.min_separation``), one subscription whatever the fleet's size."""

    SCHEMA = "Fleet"
    DOC = "Every tracked vehicle's position and velocity (arena NED) of one mocap frame, at 10 Hz."
    t: _MeasuredAt
    b: Annotated[tuple[FleetVehicle, ...], Meta(max_length=256), _doc("The vehicles")]

    def check(self) -> tuple[str, str] | None:
        return super().check() or _items_problem(self.b, "b")


@payload
class Estop(Payload, frozen=True):
    """Stop everything: every gateway lands its vehicle (or cuts its motors with ``kill``)."""

    SCHEMA = "Estop"
    DOC = "Emergency stop for every vehicle: land, or kill motors when `kill` is true."
    t: Annotated[int, _int("Time sent", unit="ns")]
    kill: Annotated[bool, _doc("Cut motors instead of landing")] = _always(False)
    reason: Annotated[Str, _doc("Why")] = _always("")
    src: Annotated[Str, _doc("Who sent it")] = _always("")


@payload
class Stats(Payload, frozen=True):
    """A service's counters, published every second."""

    SCHEMA = "Stats"
    DOC = "A service's counters: messages in/out, rejected inputs by reason, rates, latencies, resources."
    t: Annotated[int, _int("Time of the snapshot", unit="ns")]
    service: Annotated[Str, _doc("Service id")]
    host: Annotated[Str, _doc("Host name")]
    pid: Annotated[int, _int("Process id")] = _always(0)
    up: Annotated[float, _float("Uptime", unit="s")] = _always(0.0)
    counts: Annotated[Map, _doc("Counters since start (in, out, …)")] = _always({})
    rejected: Annotated[Map, _doc("Rejected inputs since start, by reason")] = _always({})
    rates: Annotated[Map, _doc("Per-second rates over the last interval", unit="Hz")] = _always({})
    lat: Annotated[Map, _doc("Latency figures (p50, p99, max) over the last interval", unit="s")] = _always(
        {}
    )
    cpu: Annotated[float, _float("CPU use over the last interval, percent of one core")] = _always(0.0)
    rss: Annotated[int, _int("Resident memory", unit="byte")] = _always(0)
    vehicle: Annotated[Str, _doc("Vehicle served, if any")] = _always("")
    lost: Annotated[
        Map, _doc("Samples lost on the bus since start, by key: gaps in their publishers' numbers")
    ] = _always({})


_CLOCK_STATES = ("reference", "ok", "uncertain", "unknown", "no_reference")


@payload
class ClockOffset(Payload, frozen=True):
    """How far one host's wall clock is from the mocap host's, as one of its services measured it."""

    SCHEMA = "ClockOffset"
    DOC = (
        "A host's wall-clock offset to the mocap host's clock (the time base of every pose), measured by "
        "request and answer on arena/sys/time like NTP: the true offset lies within `off` ± `unc`."
    )
    t: Annotated[int, _int("Time of the estimate (this host's clock)", unit="ns")]
    host: Annotated[Str, _doc("Host measured")]
    service: Annotated[Str, _doc("Service that measured it")]
    state: Annotated[
        Str,
        _doc(
            "reference (this is the mocap host), ok, uncertain (beyond clock.max_uncertainty), unknown "
            "(no recent answer), no_reference (nobody serves arena/sys/time)",
            choices=_CLOCK_STATES,
        ),
    ]
    ref: Annotated[Str, _doc("The reference (mocap) host")] = _always("")
    off: Annotated[float, _float("Reference clock minus this host's clock", unit="s")] | None = None
    unc: Annotated[float, _float("Bound of the offset's error", unit="s", lo=0.0)] | None = None
    rtt: Annotated[float, _float("Round trip of the last exchange", unit="s", lo=0.0)] | None = None
    n: Annotated[int, _int("Exchanges answered since start", lo=0)] = _always(0)
    steps: Annotated[int, _int("Clock steps seen (an estimate contradicted, and started again)", lo=0)] = (
        _always(0)
    )


# -- which type a sample carries -----------------------------------------------------------------------

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
    "frames": MocapFrame,
    "fleet": Fleet,
    "visions": VisionFrame,
    "cmd": Command,
    "rec": Command,
    "clock": ClockOffset,
    "time": Command,
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


def decode_any(key: str, raw: bytes, encoding: str = "") -> Payload:
    """Decode a payload as the type its key carries.

    An encoding that names a schema must name that same type (a ``State`` sent on a vision key is
    refused, never handed on as a State); keys outside the table are decoded by their encoding.
    """
    return _type_for(key, encoding).decode(raw, key)


@functools.lru_cache(maxsize=4096)  # a refused pair raises, so only pairs that decode are remembered
def _type_for(key: str, encoding: str) -> type[Payload]:
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


# -- JSON ------------------------------------------------------------------------------------------------

_JSON_KIND: dict[str, dict[str, Any]] = {
    "int": {"type": "integer"},
    "float": {"type": "number"},
    "bool": {"type": "boolean"},
    "str": {"type": "string"},
    "vec3": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "quat": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
    "strs": {"type": "array", "items": {"type": "string"}},
    "map": {"type": "object"},
}


def _json_properties(cls: type[Payload]) -> tuple[dict[str, Any], list[str]]:
    """The JSON Schema ``properties`` and ``required`` of one type's fields."""
    props: dict[str, Any] = {}
    required: list[str] = []
    for _, spec in cls._specs:
        if spec.item is not None:
            item_props, item_required = _json_properties(spec.item)
            prop: dict[str, Any] = {
                "type": "array",
                "items": {
                    "type": "object",
                    "description": spec.item.DOC,
                    "properties": item_props,
                    "required": item_required,
                    "additionalProperties": True,
                },
            }
            if spec.max_items is not None:
                prop["maxItems"] = spec.max_items
        else:
            prop = dict(_JSON_KIND[spec.kind])
        if spec.choices:
            prop["enum"] = list(spec.choices)
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
        if spec.required:
            required.append(spec.wire)
    return props, required


def json_schema(cls: type[Payload]) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of one payload type's JSON rendering, generated from its Struct fields.

    It describes :func:`to_jsonable`'s output rather than the msgpack bytes, so NaN is ``null``.
    """
    props, required = _json_properties(cls)
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
