"""The machinery of the wire payloads: field metadata, the :class:`Payload` base, validated decoding.

:mod:`arena_common.core.wire` declares the payload types with it (and re-exports what users need);
read that module for the contract itself.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
import sys
import time
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, TypeVar

import msgspec
from msgspec import Meta

from arena_common.core.errors import PayloadError

ENCODING_PREFIX = "application/msgpack;"
_MAX_INT = 2**63 - 1  # int fields are int64 (a msgpack uint64 above this is refused)
_MAX_FLOAT = sys.float_info.max  # float fields are finite: NaN and ±inf fail ``ge``/``le``


def now_ns() -> int:
    """Wall-clock time in integer nanoseconds, the arena's common time base."""
    return time.time_ns()


# -- field types and their metadata --------------------------------------------------------------------

F64 = Annotated[float, Meta(ge=-_MAX_FLOAT, le=_MAX_FLOAT)]  # a finite float64
Vec3 = tuple[F64, F64, F64]
Quat = tuple[F64, F64, F64, F64]
Str = Annotated[str, Meta(max_length=4096)]
Strs = Annotated[tuple[str, ...], Meta(max_length=256)]
Map = dict[str, Any]


def _int(doc: str, *, unit: str = "", lo: int = -_MAX_INT, hi: int = _MAX_INT) -> Meta:
    """An integer field: int64, or ``lo``…``hi``."""
    return Meta(ge=lo, le=hi, description=doc, extra={"unit": unit})


def _float(
    doc: str, *, unit: str = "", lo: float = -_MAX_FLOAT, hi: float = _MAX_FLOAT, nan_ok: bool = False
) -> Meta:
    """A float64 field: finite, or ``lo``…``hi``; ``nan_ok`` lets NaN (= unknown) through, not ±inf."""
    if nan_ok:
        return Meta(description=doc, extra={"unit": unit, "nan_ok": True})
    return Meta(ge=lo, le=hi, description=doc, extra={"unit": unit})


def _doc(doc: str, *, unit: str = "", choices: tuple[str, ...] = ()) -> Meta:
    """Any other field: its description, unit, and for a string the names it may take."""
    return Meta(description=doc, extra={"unit": unit, "choices": choices})


def _always(value: Any) -> Any:
    """A field default that still travels when the field holds it.

    Payloads set ``omit_defaults`` so that an optional field (default ``None``) is left out of the map
    while ``None``; every other field is always sent, as the golden vectors say. msgspec leaves out a
    value only when it *is* the default object or an empty ``dict``/``list``/``set`` made by that type,
    so a default made by any other factory is never left out.
    """
    if isinstance(value, dict):
        return msgspec.field(default_factory=value.copy)
    return msgspec.field(default_factory=itertools.repeat(value).__next__)


@dataclasses.dataclass(frozen=True, slots=True)
class Spec:
    """How one field travels, read from its annotation: wire name, kind, unit, range and description."""

    wire: str
    kind: str  # int, float, bool, str, vec3, quat, map, strs, items
    doc: str
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    optional: bool = False
    nan_ok: bool = False
    choices: tuple[str, ...] = ()
    required: bool = False
    item: type[Payload] | None = None  # kind ``items``: the type of each element (declared with ``part``)
    max_items: int | None = None


_KINDS: dict[type, str] = {
    msgspec.inspect.IntType: "int",
    msgspec.inspect.FloatType: "float",
    msgspec.inspect.BoolType: "bool",
    msgspec.inspect.StrType: "str",
    msgspec.inspect.VarTupleType: "strs",
    msgspec.inspect.DictType: "map",
}


def _spec(cls: type, field: msgspec.inspect.Field) -> Spec:
    """A field's spec from msgspec's view of ``Annotated[X, _int/_float/_doc(…)]`` (or that ``| None``)."""
    t, optional = field.type, False
    if isinstance(t, msgspec.inspect.UnionType):
        (t,) = [m for m in t.types if not isinstance(m, msgspec.inspect.NoneType)]
        optional = True
    meta = t if isinstance(t, msgspec.inspect.Metadata) else None
    doc: str = (meta.extra_json_schema or {}).get("description", "") if meta else ""
    if meta is None or not doc:
        raise TypeError(f"{cls.__name__}.{field.name}: annotate it with _int, _float or _doc")
    extra, t = meta.extra or {}, meta.type
    item: Any = None
    if isinstance(t, msgspec.inspect.TupleType):
        kind = {3: "vec3", 4: "quat"}[len(t.item_types)]
    elif isinstance(t, msgspec.inspect.VarTupleType) and isinstance(t.item_type, msgspec.inspect.StructType):
        kind, item = "items", t.item_type.cls
        if not hasattr(item, "_specs"):
            raise TypeError(f"{cls.__name__}.{field.name}: declare {item.__name__} with @part")
    else:
        kind = _KINDS[type(t)]
    lo = getattr(t, "ge", None)  # int64 and finite-float bounds are the kind's, not a range
    hi = getattr(t, "le", None)
    return Spec(
        wire=field.encode_name,
        kind=kind,
        doc=doc,
        unit=extra.get("unit", ""),
        lo=None if lo in (-_MAX_INT, -_MAX_FLOAT) else lo,
        hi=None if hi in (_MAX_INT, _MAX_FLOAT) else hi,
        optional=optional,
        nan_ok=extra.get("nan_ok", False),
        choices=extra.get("choices", ()),
        required=field.required,
        item=item,
        max_items=getattr(t, "max_length", None) if item is not None else None,
    )


# -- the payload base ----------------------------------------------------------------------------------

T = TypeVar("T", bound="Payload")


class Payload(msgspec.Struct, frozen=True, omit_defaults=True):
    """Base of every wire type: a frozen Struct with ``SCHEMA``, ``VERSION`` and ``DOC``."""

    SCHEMA: ClassVar[str]
    VERSION: ClassVar[int] = 1
    DOC: ClassVar[str] = ""
    _specs: ClassVar[tuple[tuple[str, Spec], ...]]
    _by_wire: ClassVar[dict[str, Spec]]
    _choices: ClassVar[tuple[tuple[str, frozenset[str], str], ...]]
    _nan_ok: ClassVar[tuple[str, ...]]
    _decoder: ClassVar[msgspec.msgpack.Decoder[Any]]

    @classmethod
    def encoding(cls) -> str:
        """The Zenoh encoding string, e.g. ``application/msgpack;arena.Pose/1``."""
        return f"{ENCODING_PREFIX}arena.{cls.SCHEMA}/{cls.VERSION}"

    def encode(self) -> bytes:
        """The msgpack bytes."""
        raw = _ENCODER.encode(self)
        if raw[0] == 0xDE and raw[1] == 0 and raw[2] < 16:
            # msgspec sizes the map header by how many fields the Struct has (a State has 21); with
            # optional fields left out 15 or fewer may remain, which msgpack writes as a fixmap.
            return bytes((0x80 | raw[2],)) + raw[3:]
        return raw

    def to_dict(self) -> dict[str, Any]:
        """The wire map (short field names, arrays as lists), exactly as a receiver decodes it."""
        data: dict[str, Any] = msgspec.msgpack.decode(self.encode())
        return data

    @classmethod
    def decode(cls: type[T], raw: bytes, key: str = "") -> T:
        """Decode and validate msgpack bytes of this type; raise :class:`PayloadError` naming the field."""
        try:
            obj = cls._decoder.decode(raw)
        except (msgspec.MsgspecError, RecursionError):
            # Not valid as it is: decode it again as plain msgpack, to say which field is wrong and why
            # (or to read a nil where NaN is allowed: JSON has no NaN).
            return cls.from_dict(_unpack(raw, key, cls.SCHEMA), key)
        problem = obj.check()
        if problem:
            raise PayloadError(problem[1], key=key, type_name=cls.SCHEMA, field=problem[0])
        return obj

    @classmethod
    def from_dict(cls: type[T], data: Any, key: str = "") -> T:
        """Validate a wire map and build the payload; raise :class:`PayloadError` naming the field."""
        if not isinstance(data, Mapping):
            raise PayloadError(f"expected a map, got {type(data).__name__}", key=key, type_name=cls.SCHEMA)
        data = dict(data)
        _nil_to_nan(cls, data)
        try:
            obj = msgspec.convert(data, cls)
        except msgspec.ValidationError as exc:
            field, reason = _explain(cls, data, str(exc))
            raise PayloadError(reason, key=key, type_name=cls.SCHEMA, field=field) from None
        problem = obj.check()
        if problem:
            raise PayloadError(problem[1], key=key, type_name=cls.SCHEMA, field=problem[0])
        return obj

    def check(self) -> tuple[str, str] | None:
        """What the field types cannot say: allowed names, NaN but no infinity where NaN is allowed.

        Subclasses add their rules (unit quaternions, rules between fields); ``(field, reason)`` when
        broken. Run on every decode, not on construction.
        """
        for name, allowed, listed in self._choices:
            value = getattr(self, name)
            if value not in allowed:
                return name, f"{value!r} not one of {listed}"
        for name in self._nan_ok:
            value = getattr(self, name)
            if math.isinf(value):
                return name, f"not a finite number: {value}"
        return None

    def replace(self: T, **changes: Any) -> T:
        """A copy with some fields changed."""
        return msgspec.structs.replace(self, **changes)


def _nil_to_nan(cls: type[Payload], data: dict[str, Any]) -> None:
    """Nil stands for "unknown" where NaN is allowed (JSON has no NaN), here and in ``items`` elements."""
    for name in cls._nan_ok:
        if name in data and data[name] is None:
            data[name] = math.nan
    for _, spec in cls._specs:
        elements = data.get(spec.wire) if spec.item is not None else None
        if isinstance(elements, (list, tuple)):
            fixed = []
            for e in elements:
                if isinstance(e, Mapping):
                    e = dict(e)
                    _nil_to_nan(spec.item, e)  # type: ignore[arg-type]
                fixed.append(e)
            data[spec.wire] = fixed


def _enc_hook(obj: Any) -> Any:
    """Numbers of subclasses msgspec does not take as they are (e.g. numpy.float64), as plain ones."""
    if isinstance(obj, float):
        return float(obj)
    if isinstance(obj, int):
        return int(obj)
    raise TypeError(f"can not serialize {type(obj).__name__!r} object")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_enc_hook)


def _unpack(raw: bytes, key: str, type_name: str) -> Any:
    try:
        return msgspec.msgpack.decode(raw)
    except Exception as exc:  # DecodeError; RecursionError on absurd nesting
        raise PayloadError(f"not valid msgpack: {exc}", key=key, type_name=type_name) from None


_WHERE = re.compile(
    r"(?P<what>.*?)(?: - at (?P<in_key>`key` in )?`\$(?:\.(?P<field>\w+))?(?:\[(?P<i>\d+)\])?`)?"
)


_WITHIN = re.compile(
    r"(?P<what>.*) - at (?P<in_key>`key` in )?`\$\.(?P<field>\w+)\[(?P<i>\d+)\](?P<rest>(?:[.\[].*)?)`"
)


def _explain(cls: type[Payload], data: Any, message: str) -> tuple[str, str]:
    """``(field, reason)`` in the wire's words for msgspec's ``message`` about ``data``."""
    within = _WITHIN.fullmatch(message)
    if within:  # inside one element of an ``items`` field: explained by the element's type
        spec = cls._by_wire.get(within["field"])
        i = int(within["i"])
        if spec is not None and spec.item is not None:
            element = data.get(spec.wire)[i]
            if not isinstance(element, Mapping):
                return f"{spec.wire}[{i}]", f"expected a map, got {type(element).__name__}"
            where = f" - at {within['in_key'] or ''}`${within['rest']}`"
            if not within["rest"] and not within["in_key"]:
                where = ""  # about the element itself (a field missing)
            field, reason = _explain(spec.item, element, within["what"] + where)
            return f"{spec.wire}[{i}]" + (f".{field}" if field else ""), reason
    m = _WHERE.fullmatch(message)
    assert m is not None  # the pattern matches any text
    missing = re.fullmatch(r"Object missing required field `(\w+)`", m["what"])
    if missing:
        return missing[1], "missing field"
    spec = cls._by_wire.get(m["field"] or "")
    if spec is None or m["in_key"]:
        return m["field"] or "", "expected a map with string keys" if m["in_key"] else m["what"]
    value = data.get(spec.wire)
    if value is None:
        return spec.wire, "must not be nil"
    if spec.kind == "items":
        if not isinstance(value, (list, tuple)):
            return spec.wire, f"expected an array of maps, got {type(value).__name__}"
        return spec.wire, f"more than {spec.max_items} elements"  # (an element's own faults: _WITHIN)
    if spec.kind in ("vec3", "quat"):
        n = 3 if spec.kind == "vec3" else 4
        if not isinstance(value, (list, tuple)) or len(value) != n or m["i"] is None:
            return spec.wire, f"expected an array of {n} numbers"
        value = value[int(m["i"])]
    kind = spec.kind
    if kind in ("int", "float", "vec3", "quat"):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return spec.wire, f"expected a number, got {type(value).__name__}"
        if kind == "int" and not isinstance(value, int):
            return spec.wire, "expected an integer"
        if kind != "int":
            value = float(value)
        if not math.isfinite(value):
            return spec.wire, f"not a finite number: {value}"
        if spec.lo is None and spec.hi is None:
            return spec.wire, "integer out of range"  # beyond int64
        return spec.wire, f"{value} outside [{spec.lo}, {spec.hi}]"
    wrong_type: dict[str, tuple[type | tuple[type, ...], str]] = {
        "bool": (bool, "expected a boolean"),
        "str": (str, "expected a string"),
        "strs": ((list, tuple), "expected an array of strings"),
        "map": (dict, "expected a map with string keys"),
    }
    want, reason = wrong_type[kind]
    if not isinstance(value, want):
        return spec.wire, f"{reason}, got {type(value).__name__}"
    if kind == "str":
        return spec.wire, "string longer than 4096"
    if kind == "strs" and isinstance(value, (list, tuple)) and len(value) > 256:
        return spec.wire, "more than 256 strings"
    return spec.wire, reason


def _quat_problem(q: Quat | None, wire: str) -> tuple[str, str] | None:
    if q is None:
        return None
    n = math.hypot(*q)
    if abs(n - 1.0) > 1e-3:
        return wire, f"quaternion norm {n:.4f} is not 1"
    return None


REGISTRY: dict[str, type[Payload]] = {}


def payload(cls: type[T]) -> type[T]:
    """Class decorator: read the field specs from the annotations, build the decoder, register the schema."""
    part(cls)
    REGISTRY[cls.SCHEMA] = cls
    return cls


def part(cls: type[T]) -> type[T]:
    """Class decorator for a type that travels only inside another payload (an ``items`` field's
    element): its field specs and decoder, not registered as a schema of its own."""
    info = msgspec.inspect.type_info(cls)
    assert isinstance(info, msgspec.inspect.StructType)
    fields = info.fields
    for f in fields:
        if f.default is not msgspec.NODEFAULT and f.default is not None:
            raise TypeError(f"{cls.__name__}.{f.name}: give its default as _always(...) so that it travels")
    cls._specs = tuple((f.name, _spec(cls, f)) for f in fields)
    cls._by_wire = {spec.wire: spec for _, spec in cls._specs}
    cls._choices = tuple(
        (name, frozenset(spec.choices), ", ".join(spec.choices)) for name, spec in cls._specs if spec.choices
    )
    cls._nan_ok = tuple(name for name, spec in cls._specs if spec.nan_ok)
    cls._decoder = msgspec.msgpack.Decoder(cls)
    return cls


def default_of(cls: type[Payload], name: str) -> Any:
    """The value field ``name`` takes when a sender omits it, or ``dataclasses.MISSING`` when required."""
    for f in msgspec.structs.fields(cls):
        if f.name == name:
            if f.default_factory is not msgspec.NODEFAULT:
                return f.default_factory()
            if f.default is not msgspec.NODEFAULT:
                return f.default
    return dataclasses.MISSING
