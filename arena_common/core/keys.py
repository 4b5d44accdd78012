"""Every Zenoh key expression the arena uses, with builders, parsers and name validation.

The table :data:`KEYS` is the single documented list; ``arena keys`` prints it and ``docs/wire.md`` is
generated from the same data.  Vehicle keys all live under ``arena/<drone>/``; system keys live under
``arena/sys/`` so they never collide with a vehicle (``sys`` and ``estop`` are reserved names).
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

from arena_common.core.errors import InvalidName

ROOT = "arena"
RESERVED_NAMES = frozenset({"sys", "estop"})
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,62}$")
_FORBIDDEN = "*$/#?@ "


@dataclass(frozen=True, slots=True)
class KeySpec:
    """One row of the key table."""

    pattern: str
    payload: str
    qos: str
    description: str


KEYS: tuple[KeySpec, ...] = (
    KeySpec(
        "arena/<drone>/mocap", "MocapPose", "stream", "Rigid-body pose as Motive streamed it (Motive frame)."
    ),
    KeySpec(
        "arena/<drone>/pose", "Pose", "stream", "Pose in the arena NED frame, body FRD, full mocap rate."
    ),
    KeySpec(
        "arena/<drone>/vision", "Pose", "stream", "Decimated pose: what goes to the autopilot as vision."
    ),
    KeySpec("arena/<drone>/state", "State", "stream", "The vehicle as its autopilot reports it."),
    KeySpec(
        "arena/<drone>/telemetry/<msg>", "Telemetry", "stream", "Raw MAVLink messages from the autopilot."
    ),
    KeySpec("arena/<drone>/events", "Event", "reliable", "Status text, failsafes, mode and arming changes."),
    KeySpec(
        "arena/<drone>/cmd", "Command → CommandResult", "query", "Commands, request/response (queryable)."
    ),
    KeySpec(
        "arena/<drone>/setpoint", "Setpoint", "stream", "Streamed offboard setpoints, each with a lease."
    ),
    KeySpec(
        "arena/<drone>/truth",
        "Pose",
        "stream",
        "Simulation only: a simulated (or PX4 SITL) vehicle's true pose, for the Motive emulator.",
    ),
    KeySpec("arena/estop", "Estop", "reliable", "Stop everything: land every vehicle (or kill)."),
    KeySpec("arena/sys/alive/<host>/<service>", "—", "liveliness", "Presence token of each running service."),
    KeySpec("arena/sys/stats/<host>/<service>", "Stats", "stream", "Counters of each service, every second."),
    KeySpec(
        "arena/sys/frames",
        "MocapFrame",
        "stream",
        "Every vehicle's rigid body of one mocap frame (Motive frame), one message per frame.",
    ),
    KeySpec(
        "arena/sys/vision",
        "VisionFrame",
        "stream",
        "Every vehicle's vision pose of one mocap frame (the transform decimating), one message per frame: "
        "what a gateway serving several vehicles reads.",
    ),
    KeySpec("arena/sys/bodies/<body>", "MocapPose", "stream", "Rigid bodies no vehicle claims (optional)."),
    KeySpec(
        "arena/sys/fleet",
        "Fleet",
        "stream",
        "Every vehicle's position and velocity (arena NED) at 10 Hz, one message: what keeps vehicles apart.",
    ),
    KeySpec("arena/sys/rec/<host>", "Command → CommandResult", "query", "Recorder control (start/stop)."),
    KeySpec(
        "arena/sys/time",
        "Command → CommandResult",
        "query",
        "The mocap host's clock (op time): answered by the mocap ingest, for every host's clock offset.",
    ),
    KeySpec(
        "arena/sys/clock/<host>/<service>",
        "ClockOffset",
        "stream",
        "Each host's clock offset to the mocap host's, as each of its services measures it.",
    ),
)


def validate_name(name: str, what: str = "vehicle name") -> str:
    """Return ``name`` if it can be one chunk of a key expression, else raise :class:`InvalidName`.

    Refused: empty, anything with ``* $ / # ? @`` or spaces, a leading ``@`` (Zenoh verbatim chunk),
    names longer than 63 characters and the reserved names ``sys`` and ``estop``.
    """
    if not isinstance(name, str) or not name:
        raise InvalidName(f"invalid {what} {name!r}: must be a non-empty string")
    problem = _name_problem(name, what)
    if problem:
        raise InvalidName(f"invalid {what} {name!r}: {problem}")
    return name


@functools.lru_cache(maxsize=1024)  # the same few names are checked in every frame and every key
def _name_problem(name: str, what: str) -> str:
    bad = sorted({c for c in name if c in _FORBIDDEN})
    if bad:
        return f"contains {' '.join(repr(c) for c in bad)}"
    if not _NAME_RE.match(name):
        return "use letters, digits, '_', '-', '.' (at most 63)"
    if what == "vehicle name" and name in RESERVED_NAMES:
        return "reserved"
    return ""


def _vehicle(drone: str, leaf: str) -> str:
    return f"{ROOT}/{validate_name(drone)}/{leaf}"


def mocap(drone: str) -> str:
    """``arena/<drone>/mocap``."""
    return _vehicle(drone, "mocap")


def pose(drone: str) -> str:
    """``arena/<drone>/pose``."""
    return _vehicle(drone, "pose")


def vision(drone: str) -> str:
    """``arena/<drone>/vision``."""
    return _vehicle(drone, "vision")


def state(drone: str) -> str:
    """``arena/<drone>/state``."""
    return _vehicle(drone, "state")


def telemetry(drone: str, msg: str) -> str:
    """``arena/<drone>/telemetry/<msg>``."""
    return f"{_vehicle(drone, 'telemetry')}/{validate_name(msg, 'message name')}"


def events(drone: str) -> str:
    """``arena/<drone>/events``."""
    return _vehicle(drone, "events")


def cmd(drone: str) -> str:
    """``arena/<drone>/cmd``."""
    return _vehicle(drone, "cmd")


def setpoint(drone: str) -> str:
    """``arena/<drone>/setpoint``."""
    return _vehicle(drone, "setpoint")


def truth(drone: str) -> str:
    """``arena/<drone>/truth`` (simulation only)."""
    return _vehicle(drone, "truth")


ESTOP = f"{ROOT}/estop"


def alive(host: str, service: str) -> str:
    """Liveliness token key of one service: ``arena/sys/alive/<host>/<service>``."""
    return f"{ROOT}/sys/alive/{validate_name(host, 'host name')}/{validate_name(service, 'service name')}"


def stats(host: str, service: str) -> str:
    """Stats key of one service: ``arena/sys/stats/<host>/<service>``."""
    return f"{ROOT}/sys/stats/{validate_name(host, 'host name')}/{validate_name(service, 'service name')}"


def body(name: str) -> str:
    """Key for a rigid body no vehicle claims: ``arena/sys/bodies/<body>``."""
    return f"{ROOT}/sys/bodies/{validate_name(name, 'rigid-body name')}"


def rec_control(host: str) -> str:
    """Recorder control queryable of one host."""
    return f"{ROOT}/sys/rec/{validate_name(host, 'host name')}"


def clock(host: str, service: str) -> str:
    """Clock offset key of one service's host: ``arena/sys/clock/<host>/<service>``."""
    return f"{ROOT}/sys/clock/{validate_name(host, 'host name')}/{validate_name(service, 'service name')}"


TIME = f"{ROOT}/sys/time"
FRAMES = f"{ROOT}/sys/frames"
FLEET = f"{ROOT}/sys/fleet"
VISIONS = f"{ROOT}/sys/vision"
CLOCK_ALL = f"{ROOT}/sys/clock/**"
ALIVE_ALL = f"{ROOT}/sys/alive/**"
STATS_ALL = f"{ROOT}/sys/stats/**"


@dataclass(frozen=True, slots=True)
class ParsedKey:
    """What a concrete key is: its kind (``pose``, ``state``, ``telemetry``, ``estop``…) and names."""

    kind: str
    drone: str | None = None
    extra: str | None = None


def parse(key: str) -> ParsedKey:
    """Classify a concrete key; raise :class:`InvalidName` for a key outside the table."""
    parts = str(key).split("/")
    if len(parts) < 2 or parts[0] != ROOT:
        raise InvalidName(f"not an arena key: {key!r}")
    if parts[1] == "estop" and len(parts) == 2:
        return ParsedKey("estop")
    if parts[1] == "sys":
        if len(parts) == 5 and parts[2] in ("alive", "stats", "clock"):
            return ParsedKey(parts[2], extra=f"{parts[3]}/{parts[4]}")
        if len(parts) == 4 and parts[2] == "bodies":
            return ParsedKey("bodies", extra=parts[3])
        if len(parts) == 4 and parts[2] == "rec":
            return ParsedKey("rec", extra=parts[3])
        if len(parts) == 3 and parts[2] in ("time", "frames", "fleet"):
            return ParsedKey(parts[2])
        if len(parts) == 3 and parts[2] == "vision":
            return ParsedKey("visions")  # every vehicle's vision of a frame (a vehicle's own: "vision")
        raise InvalidName(f"unknown system key: {key!r}")
    drone = validate_name(parts[1])
    if len(parts) == 3 and parts[2] in (
        "mocap",
        "pose",
        "vision",
        "state",
        "events",
        "cmd",
        "setpoint",
        "truth",
    ):
        return ParsedKey(parts[2], drone)
    if len(parts) == 4 and parts[2] == "telemetry":
        return ParsedKey("telemetry", drone, parts[3])
    raise InvalidName(f"unknown vehicle key: {key!r}")
