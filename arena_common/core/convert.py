"""A parsed document turned into a msgspec Struct, with errors that name the file, the dotted field, what it
expects in words and the value given (``arena.toml: vehicles.d1.system_id: expected an integer in 1..250,
got 0``).

msgspec (0.22) says where a value failed only inside its message text (`` - at `$.a.b[...]` ``): its
``ValidationError`` carries no path.  :func:`convert` therefore walks the Struct's fields itself and
converts each value with that field's own type, so the failing field is known without reading msgspec's
text, and :func:`expected` says what the field wants from its annotation (type, ``Literal`` choices,
``Meta`` bounds, pattern or description).
"""

from __future__ import annotations

import functools
import types
import typing
from typing import Annotated, Any, Literal, Self, TypeVar, get_args, get_origin

import msgspec
from msgspec import Meta

from arena_common.core.errors import ConfigError

S = TypeVar("S", bound=msgspec.Struct)


class Spec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A section of the config: frozen, typed, every default on its field."""

    def replace(self, **changes: Any) -> Self:
        """A copy with some fields replaced."""
        return msgspec.structs.replace(self, **changes)


_KINDS: dict[Any, str] = {int: "an integer", float: "a number", str: "a string", bool: "true or false"}


def field_error(path: str, where: str, expected: str, got: Any = ...) -> ConfigError:
    """``path: where: expected <expected>, got <got>`` (``got`` left out when not given)."""
    tail = "" if got is ... else f", got {got!r}"
    return ConfigError(f"{path}: {where}: expected {expected}{tail}")


def convert(cls: type[S], data: Any, path: str, where: str) -> S:
    """``data`` as Struct ``cls``; :class:`ConfigError` naming ``path``, the field below ``where``, what it
    expects and the value given, or ``unknown field``."""
    _check(cls, data, path, where)
    try:
        return msgspec.convert(data, cls)
    except msgspec.ValidationError as exc:  # a constraint no field carries alone: msgspec's own words
        raise ConfigError(f"{path}: {where}: {exc}") from None


def _check(t: Any, value: Any, path: str, where: str) -> None:
    bare = _bare(t)
    if isinstance(value, dict) and isinstance(bare, type) and issubclass(bare, msgspec.Struct):
        fields = _fields(bare)
        for key, item in value.items():
            if key not in fields:
                raise ConfigError(f"{path}: {where}.{key}: unknown field")
            _check(fields[key], item, path, f"{where}.{key}")
    elif isinstance(value, dict) and get_origin(bare) is dict:
        key_type, value_type = get_args(bare)
        for key, item in value.items():
            if not _fits(key_type, key):  # a table's key is wrong (e.g. a PX4 parameter name)
                raise field_error(path, where, expected(key_type, plural=True), key)
            _check(value_type, item, path, f"{where}.{key}")
    elif not _fits(t, value):
        wanted = expected(t)
        if isinstance(value, list) and (choices := _choices(bare)) is not None:
            value = next((v for v in value if v not in choices), value)  # the name that is not a choice
        raise field_error(path, where, wanted, value)


@functools.cache
def _fields(cls: type[msgspec.Struct]) -> dict[str, Any]:
    return {f.name: f.type for f in msgspec.structs.fields(cls)}


def _fits(t: Any, value: Any) -> bool:
    try:
        msgspec.convert(value, t)
    except msgspec.ValidationError:
        return False
    return True


def _bare(t: Any) -> Any:
    """``t`` without ``Annotated`` and without ``| None``."""
    while True:
        if get_origin(t) is Annotated:
            t = get_args(t)[0]
        elif isinstance(t, types.UnionType) or get_origin(t) is typing.Union:
            t = next(a for a in get_args(t) if a is not type(None))
        else:
            return t


def _choices(t: Any) -> tuple[Any, ...] | None:
    """The names a ``tuple[Literal[...], ...]`` may hold; None for any other type."""
    args = get_args(t) if get_origin(t) is tuple else ()
    if len(args) == 2 and args[1] is Ellipsis and get_origin(args[0]) is Literal:
        return get_args(args[0])
    return None


def _bounds(t: Any) -> str:
    """``"ge..le"`` of an ``Annotated`` type with both bounds; "" otherwise."""
    meta = next((m for m in get_args(t) if isinstance(m, Meta)), None) if get_origin(t) is Annotated else None
    return f"{meta.ge}..{meta.le}" if meta is not None and meta.ge is not None and meta.le is not None else ""


def expected(t: Any, plural: bool = False) -> str:
    """What a value of type ``t`` must be, in words (``plural``: said of a table's keys)."""
    meta = next((m for m in get_args(t) if isinstance(m, Meta)), None) if get_origin(t) is Annotated else None
    if plural:
        return meta.description if meta is not None and meta.description else expected(t)
    if meta is None and (isinstance(t, types.UnionType) or get_origin(t) is typing.Union):
        return " or ".join(expected(a) for a in get_args(t) if a is not type(None))
    bare = _bare(t)
    if get_origin(bare) is Literal:
        words = get_args(bare)
        return f"the word {words[0]}" if len(words) == 1 else "one of " + ", ".join(str(a) for a in words)
    if (choices := _choices(bare)) is not None:
        return "names among " + ", ".join(str(a) for a in choices)
    if get_origin(bare) is tuple:
        args = get_args(bare)
        if args and args[-1] is not Ellipsis and all(_bare(a) is float for a in args):
            each = [_bounds(a) for a in args]
            within = f" (within {', '.join(b or 'any' for b in each)})" if any(each) else ""
            return f"a list of {len(args)} numbers{within}"
        return "a list of strings" if args == (str, Ellipsis) else "a list"
    if get_origin(bare) is dict or (isinstance(bare, type) and issubclass(bare, msgspec.Struct)):
        return "a table"
    kind = _KINDS.get(bare, f"a {getattr(bare, '__name__', bare)}")
    if bounds := _bounds(t):
        return f"{kind} in {bounds}"
    if meta is not None and meta.pattern is not None:
        return f"{kind} matching {meta.pattern}"
    return kind
