"""Every operation a :class:`~arena_common.core.wire.Command` names: its arguments (type, unit, range,
default), what it does, and who sends it — the one table the client, the asyncio facade, the gateway, the
recorder, the clock, the CLI and ``docs/wire.md`` use.

:func:`check` turns a command's ``args`` into checked values (defaults filled in) or raises
:class:`OpError` naming the operation and the argument: the client calls it before it sends, the
gateway before it acts, so neither end can take an argument the other does not.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from arena_common.core.errors import ArenaError

__all__ = ["OPS", "REQUIRED", "Arg", "Op", "OpError", "check", "vehicle_ops"]


class OpError(ArenaError, ValueError):
    """A command's operation or arguments are not what the operation takes."""


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()
Kind = Literal["number", "vec3", "text", "flag"]


@dataclass(frozen=True, slots=True)
class Arg:
    """One argument of an operation."""

    name: str
    kind: Kind
    doc: str
    unit: str = ""
    default: Any = REQUIRED  # None: optional, no value
    lo: float | None = None
    hi: float | None = None

    def describe(self) -> str:
        """``height`` (m, 0.1…10, default 1.0) — for tables."""
        bits = [b for b in (self.unit, self._range()) if b]
        if self.default is REQUIRED:
            bits.append("required")
        elif self.default is not None:
            bits.append(f"default {self.default}")
        return f"{self.name} ({self.kind}{', ' if bits else ''}{', '.join(bits)}): {self.doc}"

    def _range(self) -> str:
        if self.lo is None and self.hi is None:
            return ""
        return f"{'' if self.lo is None else self.lo}…{'' if self.hi is None else self.hi}"

    def value(self, op: str, raw: Any) -> Any:
        """``raw`` checked against this argument (None passes for an optional argument)."""
        where = f"{op}: argument {self.name!r}"
        if raw is None:
            if self.default is REQUIRED:
                raise OpError(f"{where} is missing")
            return self.default
        if self.kind == "flag":
            if not isinstance(raw, bool):
                raise OpError(f"{where} must be true or false, got {raw!r}")
            return raw
        if self.kind == "text":
            if not isinstance(raw, str) or not raw:
                raise OpError(f"{where} must be a non-empty string, got {raw!r}")
            return raw
        if self.kind == "vec3":
            if not isinstance(raw, (list, tuple)) or len(raw) != 3:
                raise OpError(f"{where} must be [north, east, down], got {raw!r}")
            return tuple(self._number(where, v) for v in raw)
        return self._number(where, raw)

    def _number(self, where: str, raw: Any) -> float:
        if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw):
            raise OpError(f"{where} must be a finite number, got {raw!r}")
        if (self.lo is not None and raw < self.lo) or (self.hi is not None and raw > self.hi):
            raise OpError(
                f"{where} must be within {self._range()} {self.unit}, got {raw!r}".replace("  ", " ")
            )
        return float(raw)


@dataclass(frozen=True, slots=True)
class Op:
    """One operation: who answers it (``vehicle``: a gateway on ``arena/<drone>/cmd``; ``recorder`` on
    ``arena/sys/rec/<host>``; ``clock``: the mocap ingest on ``arena/sys/time``), its arguments, what it
    does and the client's method that sends it."""

    name: str
    targets: tuple[Literal["vehicle", "recorder", "clock"], ...]
    doc: str
    args: tuple[Arg, ...] = ()
    client: str = ""  # the Vehicle method that sends it ("params.get": a facet's), "" : none
    aio: str = ""  # the AsyncVehicle method (default: the same name as ``client``)

    @property
    def aio_method(self) -> str:
        """The :class:`~arena_common.client.aio.AsyncVehicle` method that sends it ("": none)."""
        return self.aio or self.client


_VEHICLE: tuple[Op, ...] = (
    Op(
        "arm",
        ("vehicle",),
        "arm the motors (refused without heartbeat, with the arena's parameters unset, "
        "stale vision or this host's clock offset unknown: the reason says which)",
        client="arm",
    ),
    Op("disarm", ("vehicle",), "disarm (PX4 refuses in the air)", client="disarm"),
    Op("kill", ("vehicle",), "forced disarm: the motors stop, even in the air", client="kill"),
    Op(
        "takeoff",
        ("vehicle",),
        "take off to a height above the floor (AUTO.TAKEOFF, then Hold)",
        (Arg("height", "number", "height above the floor (inside the safe volume)", "m", 1.0),),
        client="takeoff",
    ),
    Op("land", ("vehicle",), "land where it is (AUTO.LAND)", client="land"),
    Op("hold", ("vehicle",), "hold where it is (AUTO.LOITER)", client="hold"),
    Op(
        "mode",
        ("vehicle",),
        "switch to a PX4 mode; OFFBOARD only in the air with a live setpoint stream, manual modes never",
        (
            Arg("mode", "text", "PX4 mode name: AUTO.LOITER, AUTO.LAND, OFFBOARD…"),
            Arg(
                "stream",
                "text",
                "with OFFBOARD: the setpoint stream to engage (default: the newest live)",
                "",
                None,
            ),
        ),
        client="set_mode",
    ),
    Op(
        "goto",
        ("vehicle",),
        "fly to a point inside the safe volume (the gateway streams a carrot, then holds the point)",
        (
            Arg("p", "vec3", "north, east, down in the arena frame", "m"),
            Arg("yaw", "number", "heading (default: the current one)", "rad", None),
            Arg("tol", "number", "tolerance of the position averaged over 1 s (default 0.3)", "m", None),
            Arg("wait", "flag", "answer only once arrived (core.arrival)", "", False),
        ),
        client="goto",
    ),
    Op(
        "reboot",
        ("vehicle",),
        "reboot the autopilot (refused when armed); answers once it is back",
        client="",
    ),
    Op(
        "param_get",
        ("vehicle",),
        "read one parameter: value {name, value, type}",
        (Arg("name", "text", "PX4 parameter name"),),
        client="params.get",
        aio="get_param",
    ),
    Op(
        "param_set",
        ("vehicle",),
        "write one parameter in the vehicle's type and read it back",
        (Arg("name", "text", "PX4 parameter name"), Arg("value", "number", "the value")),
        client="params.set",
        aio="set_param",
    ),
    Op("check", ("vehicle",), "the arena's parameters: value {ok, params}", client=""),
    Op(
        "setup",
        ("vehicle",),
        "write the arena's parameters (refused when armed), reboot when one needs it, check them again",
        client="",
    ),
    Op("ping", ("vehicle", "recorder"), "alive? a gateway: value {link, mode, armed, rtt, …}", client=""),
)
_SERVICES: tuple[Op, ...] = (
    Op("start", ("recorder",), "start a new recording file", (Arg("name", "text", "file name", "", None),)),
    Op("stop", ("recorder",), "close the recording file"),
    Op("time", ("clock",), "the mocap host's clock now (answered by the mocap ingest, like NTP)"),
)

#: Every operation, by name, in the table's order.
OPS: dict[str, Op] = {op.name: op for op in (*_VEHICLE, *_SERVICES)}


def vehicle_ops() -> list[Op]:
    """The operations a vehicle's gateway answers."""
    return [op for op in OPS.values() if "vehicle" in op.targets]


def check(name: str, args: Mapping[str, Any]) -> dict[str, Any]:
    """``args`` of operation ``name`` checked and completed; :class:`OpError` names what is wrong."""
    op = OPS.get(name)
    if op is None:
        raise OpError(f"{name!r} is no operation (known: {', '.join(OPS)})")
    unknown = sorted(set(args) - {a.name for a in op.args})
    if unknown:
        takes = ", ".join(a.name for a in op.args) or "none"
        raise OpError(f"{name}: unknown argument {unknown[0]!r} (it takes: {takes})")
    return {a.name: a.value(name, args.get(a.name)) for a in op.args}
