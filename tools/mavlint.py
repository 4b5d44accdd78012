"""MAVLink numbers live in one place: ``arena_common/mavlink/px4.py`` names them, or pymavlink's dialect does
(``mavlink2.MAV_…``, ``mavlink2.MAVLINK_MSG_ID_…``); anywhere else a MAVLink number written as a literal
is a finding (``make lint``).

    python -m tools.mavlint        # prints file:line: what for each literal; exit status 1 if any

What is flagged in ``arena_common`` (but ``mavlink/px4.py``), ``services``, ``bench``, ``tools`` and
``examples`` (:data:`SCOPE`), pymavlink telling which enum each message field has:

1. **a MAVLink name given a number**: ``MAV_TYPE_GCS = 6``, ``MSG_ESTIMATOR_STATUS = 230``,
   ``CMD_SET_MESSAGE_INTERVAL = 511``, ``COLLISION = 247``, ``OP_READ_FILE = 5``: a name starting ``MAV_``
   or ``MAVLINK_``, or named like a message, or ending like an enum entry (MAV_FTP_OPCODE_READFILE), and
   given its value;
2. **a message built with a number in an enum field**, by position or by name:
   ``mav.heartbeat_encode(6, 8, 0, 0, 4)``, ``mav.command_long_send(1, 1, 400, …)``,
   ``mavlink2.MAVLink_command_ack_message(…)``;
3. **a field or a message id read against a number**, compared, masked or matched: ``msg.command == 400``,
   ``hb.base_mode & 128``, ``ack.result in (0, 5)``, ``getattr(m, "severity", 6) <= 4``,
   ``m.get_msgid() == 230``, ``msgid == 0``, ``frame == 5`` (the fields: :data:`FIELDS`), or given it as
   a default (``getattr(msg, "mission_type", 0)``, ``def ack(mission_type: int = 0)``);
4. **a table of numbers read with such a field**: the keys of a dict, the members of a set, the terms of
   an ``|`` bound to a name that a field then reads (``_FLAGS = {2: "low"}`` … ``_FLAGS.get(msg.charge_state)``,
   ``FRAMES = frozenset({3, 6})`` … ``item.frame in FRAMES``) or that fills an enum field of a message;
5. **a message id asked for**: the first argument of ``…request_message(49)``;
6. **a number beside MAVLink names** in one tuple, list, set or dict's keys:
   ``(px4.MAV_PARAM_TYPE_REAL32, 10)``;
7. **a component id**: ``srcComponent=191``, ``source_component=190``, ``component = 191``;
8. **a table of MAVLink names by number**: ``{1: "TerminateSession", 6: "EOF", …}`` (most of its names
   spell the enum entry of their number).

A variable given a field (``frame = msg.frame``, ``self._cmd_frame = frame``) is read as that field.
What it cannot see: a number that reaches a field through a function's return or through a parameter of
the arena's own functions, and an argument after ``*args``.

0 and 1 pass where they are no value of the field's enums (``base_mode & 1`` is flagged:
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED; HEARTBEAT's empty ``base_mode`` 0 is not); a message id never passes.
"""

from __future__ import annotations

import argparse
import ast
import itertools
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SCOPE = ("arena_common", "services", "bench", "tools", "examples")
HOME = "arena_common/mavlink/px4.py"
#: Fields read against numbers anywhere (as ``x.field`` or ``getattr(x, "field")``); the generic names many
#: messages share (``state``, ``status``, ``mode``, ``flags``…) are judged only where a message is built,
#: where pymavlink says what they are.
FIELDS = frozenset(
    {
        "autopilot", "base_mode", "battery_function", "charge_state", "child_frame_id", "command",
        "coordinate_frame", "custom_mode", "estimator_type", "fix_type", "frame", "frame_id",
        "landed_state", "mission_type", "param_type", "result", "severity", "system_status", "type",
        "type_mask", "vtol_state",
    }
)  # fmt: skip
#: Variables of these names are fields too (``frame == 5``, ``mid`` a message id); ``type``, ``result``…
#: are too common.
VARIABLES = {"frame": "frame", "mission_type": "mission_type", "msgid": "msgid", "mid": "msgid"}
NUMBER_FIELDS = frozenset({"custom_mode"})  # no enum, yet every value is a MAVLink number (PX4's modes)
MSGID = frozenset({"msgid", "get_msgid", "get_msgId"})
_BITWISE = (ast.BitAnd, ast.BitOr, ast.BitXor)


@dataclass(frozen=True, slots=True)
class Finding:
    """One MAVLink literal outside px4.py."""

    path: str
    line: int
    what: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.what}"


# -- what pymavlink knows ---------------------------------------------------------------------------------
@cache
def _dialect() -> Any:
    from arena_common.mavlink.link import mavlink2  # the arena's dialect: common, development and the rest

    return mavlink2


def _generated() -> list[Any]:
    """The dialect's own messages (not those the arena adds to it: arena_common.mavlink.metadata defines
    the two pymavlink lacks, with their ids)."""
    dialect = _dialect()
    return [cls for cls in dialect.mavlink_map.values() if cls.__module__ == dialect.__name__]


@cache
def _enums() -> dict[str, dict[int, str]]:
    """Each enum's entries, value → name (its ENUM_END left out)."""
    return {
        enum: {v: e.name for v, e in entries.items() if not e.name.endswith("_ENUM_END")}
        for enum, entries in _dialect().enums.items()
    }


@cache
def _numbers() -> dict[str, int]:
    """Every enum entry and every message (``MSG_<NAME>``), by name."""
    out = {name: v for entries in _enums().values() for v, name in entries.items()}
    out.update({f"MSG_{cls.msgname}": cls.id for cls in _generated()})
    return out


@cache
def _messages() -> dict[str, tuple[tuple[str, ...], dict[str, str]]]:
    """Lower-case message name → (its fields in argument order, field → enum)."""
    return {
        cls.msgname.lower(): (tuple(cls.fieldnames), dict(cls.fieldenums_by_name)) for cls in _generated()
    }


@cache
def _field_enums() -> dict[str, frozenset[str]]:
    """Field name → the enums it has in any message."""
    out: dict[str, set[str]] = {}
    for _, enums in _messages().values():
        for field, enum in enums.items():
            out.setdefault(field, set()).add(enum)
    return {field: frozenset(enums) for field, enums in out.items()}


def _flagged(value: int, field: str, enums: frozenset[str] | None = None) -> bool:
    """Whether ``value`` given to, or read against, ``field`` (with ``enums``: its own) is a MAVLink number."""
    if field in MSGID:
        return True
    enums = _field_enums().get(field, frozenset()) if enums is None else enums
    if value not in (0, 1):
        return bool(enums) or field in NUMBER_FIELDS
    return any(value in _enums().get(e, {}) for e in enums)


def _mavlink_name(name: str, value: int) -> bool:
    """Whether ``name`` given ``value`` names a MAVLink number (rule 1)."""
    bare = name.lstrip("_")
    if bare.startswith(("MAV_", "MAVLINK_")):
        return True
    numbers = _numbers()
    if numbers.get(f"MSG_{bare}") == value or numbers.get(f"MSG_{bare.removesuffix('_ID')}") == value:
        return True  # a message: RADIO_STATUS = 109, ODOMETRY_ID = 331
    if bare.count("_") < 1:
        return False
    # ``LOITER_TIME`` (MAV_CMD_NAV_LOITER_TIME); ``OP_READ_FILE``: a prefix of the module's own, then two
    # words or more spelled without underscores (MAV_FTP_OPCODE_READFILE)
    words = bare.split("_")
    tail, squeezed = f"_{bare}", "".join(words[1:]) if len(words) > 2 else None
    return any(
        v == value and (n == bare or n.endswith(tail) or (squeezed and n.replace("_", "").endswith(squeezed)))
        for n, v in numbers.items()
    )


def _entry_named(value: int, text: str) -> bool:
    """Whether ``text`` (``"TerminateSession"``) names an enum entry of ``value`` (MAV_FTP_OPCODE_TERMINATESESSION)."""
    if not re.fullmatch(r"[A-Za-z][\w -]+", text):
        return False
    squeezed = re.sub(r"[^A-Z0-9]", "", text.upper())
    return len(squeezed) >= 3 and any(
        v == value and n.replace("_", "").endswith(squeezed) for n, v in _numbers().items()
    )


def _component(name: str, value: int) -> bool:
    """Whether a keyword or variable ``name`` given ``value`` is a component id (rule 7)."""
    return value not in (0, 1) and name.lower().endswith("component") and value in _enums()["MAV_COMPONENT"]


def _mavlink_expr(node: ast.AST) -> bool:
    """Whether an expression is a MAVLink name: ``px4.MAV_X``, ``mavlink2.MAVLINK_MSG_ID_X``, ``MSG["X"]``."""
    if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == "MSG":
        return True
    name = node.attr if isinstance(node, ast.Attribute) else node.id if isinstance(node, ast.Name) else ""
    return name.startswith(("MAV_", "MAVLINK_MSG_ID_")) or (name.isupper() and name in _numbers())


# -- literals --------------------------------------------------------------------------------------------
def _int(node: ast.AST) -> int | None:
    """The value of an integer literal (``-1``, ``0x80`` too), else None."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.Invert)):
        inner = _int(node.operand)
        return None if inner is None else -inner if isinstance(node.op, ast.USub) else ~inner
    if isinstance(node, ast.Constant) and type(node.value) is int:
        return node.value
    return None


def _terms(node: ast.AST) -> Iterator[tuple[ast.AST, int]]:
    """The integer literals of a literal, of a tuple, list or set of them (or one of them:
    ``(1, 2)[i]``, ``2 if a else 4``), or of an ``|`` of them."""
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        for elt in node.elts:
            yield from _terms(elt)
    elif isinstance(node, ast.Subscript) and isinstance(node.value, (ast.Tuple, ast.List)):
        yield from _terms(node.value)
    elif isinstance(node, ast.IfExp):
        yield from _terms(node.body)
        yield from _terms(node.orelse)
    elif isinstance(node, ast.BinOp) and isinstance(node.op, _BITWISE):
        yield from _terms(node.left)
        yield from _terms(node.right)
    elif (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id in ("frozenset", "set")
    ):
        for arg in node.args:
            yield from _terms(arg)
    else:
        value = _int(node)
        if value is not None:
            yield node, value


def _table(node: ast.AST) -> list[tuple[ast.AST, int]]:
    """The numbers of a table bound to a name (rule 4): a dict's keys, a collection's members, ``|`` terms."""
    if isinstance(node, ast.Dict):
        return [t for k in node.keys if k is not None for t in _terms(k)]
    return list(_terms(node))


def _message_built(call: ast.Call) -> str | None:
    """The message a call builds: ``<mav>.<msg>_encode``/``_send``, ``MAVLink_<msg>_message``."""
    f = call.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
    m = re.fullmatch(r"(\w+?)_(?:encode|send)", name) or re.fullmatch(r"MAVLink_(\w+)_message", name)
    return m.group(1) if m is not None and m.group(1) in _messages() else None


def _ident(node: ast.AST) -> str | None:
    """The name a table is known by: ``NAME``, ``self.NAME``, ``Class.NAME``."""
    return node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else None


# -- the checks --------------------------------------------------------------------------------------------
class _Checker(ast.NodeVisitor):
    def __init__(self, path: str) -> None:
        self.path = path
        self.found: dict[tuple[int, int], Finding] = {}
        self.tables: dict[str, list[tuple[ast.AST, int]]] = {}  # rule 4: name → its numbers
        self.aliases: dict[str, str] = {}  # ``handlers = self._handlers``
        self.variables: dict[str, str] = dict(VARIABLES)  # name → the field it holds

    def flag(self, node: ast.AST, what: str) -> None:
        line, col = getattr(node, "lineno", 0), getattr(node, "col_offset", 0)
        self.found.setdefault((line, col), Finding(self.path, line, what))

    def field(self, node: ast.AST) -> str | None:
        """The MAVLink field (or message id) an expression reads: ``x.result``, ``getattr(x, "result", 0)``,
        ``int(x.result)``, ``x.get_msgid()``, ``frame.msgid``, a variable given a field."""
        if isinstance(node, ast.Call):
            f, args = node.func, node.args
            if isinstance(f, ast.Attribute) and f.attr in MSGID and not args:
                return f.attr
            if (
                isinstance(f, ast.Name)
                and f.id == "getattr"
                and len(args) >= 2
                and isinstance(args[1], ast.Constant)
            ):
                return args[1].value if args[1].value in FIELDS | MSGID else None
            if isinstance(f, ast.Name) and f.id == "int" and len(args) == 1:
                return self.field(args[0])
            return None
        if isinstance(node, ast.Attribute):
            return node.attr if node.attr in FIELDS | MSGID else self.variables.get(node.attr)
        if isinstance(node, ast.Name):
            return self.variables.get(node.id)
        return None

    def table_read(self, node: ast.AST, field: str, how: str, enums: frozenset[str] | None = None) -> None:
        """Rule 4: the table ``node`` names is read with ``field``: its numbers are MAVLink numbers."""
        name = _ident(node)
        if name is None:
            return
        for key in dict.fromkeys((name, self.aliases.get(name, name))):
            for lit, value in self.tables.get(key, []):
                if _flagged(value, field, enums):
                    self.flag(lit, f"{ast.unparse(lit)} in {key}, {how}")

    # rule 1, and the tables of rule 4
    def visit_Assign(self, node: ast.Assign) -> None:
        for target in node.targets:
            self.bind(target, node.value)
        self.generic_visit(node)

    def visit_AnnAssign(self, node: ast.AnnAssign) -> None:
        if node.value is not None:
            self.bind(node.target, node.value)
        self.generic_visit(node)

    def bind(self, target: ast.AST, value: ast.AST) -> None:
        if (
            isinstance(target, ast.Tuple)
            and isinstance(value, ast.Tuple)
            and len(target.elts) == len(value.elts)
        ):
            for t, v in zip(target.elts, value.elts, strict=True):
                self.bind(t, v)
            return
        name = _ident(target)
        if name is None:
            return
        literal = _int(value)
        if literal is not None and _mavlink_name(name, literal):
            self.flag(value, f"MAVLink number {name} = {literal}: name it in {HOME} or take pymavlink's")
        elif literal is not None and _component(name, literal):
            self.flag(value, f"component id {name} = {literal}")
        field = self.field(value)
        if field is not None and name not in FIELDS:
            self.variables[name] = field
        numbers = _table(value)
        if numbers:
            self.tables.setdefault(name, [])
            self.tables[name] += [n for n in numbers if n not in self.tables[name]]
        elif isinstance(value, (ast.Name, ast.Attribute)) and isinstance(target, ast.Name):
            source = _ident(value)
            if source is not None:
                self.aliases[name] = source

    def visit_AugAssign(self, node: ast.AugAssign) -> None:  # ``health &= ~0x80``: a term of the table
        name = _ident(node.target)
        if name is not None and isinstance(node.op, _BITWISE):
            self.tables.setdefault(name, [])
            self.tables[name] += [n for n in _terms(node.value) if n not in self.tables[name]]
        self.generic_visit(node)

    # rules 2 and 5
    def visit_Call(self, node: ast.Call) -> None:
        msg = _message_built(node)
        if msg is not None:
            fields, enums = _messages()[msg]
            # the arguments before a ``*x``: where those after it go is unknown
            placed = itertools.takewhile(lambda a: not isinstance(a, ast.Starred), node.args)
            given = [*zip(fields, placed, strict=False)]
            given += [(k.arg, k.value) for k in node.keywords if k.arg is not None]
            for field, arg in given:
                if field not in enums:
                    continue
                own = frozenset({enums[field]})
                for lit, value in _terms(arg):
                    if _flagged(value, field, own):
                        self.flag(lit, f"{value} as {msg.upper()}.{field} ({enums[field]})")
                self.table_read(arg, field, f"given as {msg.upper()}.{field}", own)
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
        if name == "getattr" and len(node.args) == 3:  # ``getattr(msg, "mission_type", 0)``
            self.given(self.field(ast.Call(f, node.args[:2], [])), node.args[2], "as the default of")
        if isinstance(f, ast.Attribute) and f.attr == "get" and node.args:  # rule 4: ``TABLE.get(msg.field)``
            self.read_with(f.value, node.args[0])
        if name.endswith("request_message") and node.args and _int(node.args[0]) is not None:
            self.flag(node.args[0], f"message id {_int(node.args[0])} asked for")
        for k in node.keywords:
            number = _int(k.value)
            if k.arg is not None and number is not None and _component(k.arg, number):
                self.flag(k.value, f"component id {k.arg}={number}")
        self.generic_visit(node)

    def given(self, field: str | None, value: ast.AST, how: str) -> None:
        """A field given ``value``: its numbers are MAVLink numbers."""
        if field is not None:
            for lit, number in _terms(value):
                if _flagged(number, field):
                    self.flag(lit, f"{number} {how} {_shown(field)}")

    def visit_FunctionDef(self, node: ast.FunctionDef | ast.AsyncFunctionDef) -> None:
        """A parameter named as a field with a number for default (``mission_type: int = 0``)."""
        a = node.args
        positional = [*a.posonlyargs, *a.args]
        pairs = [*zip(positional[len(positional) - len(a.defaults) :], a.defaults, strict=True)]
        pairs += [(arg, d) for arg, d in zip(a.kwonlyargs, a.kw_defaults, strict=True) if d is not None]
        for arg, default in pairs:
            field = arg.arg if arg.arg in FIELDS else VARIABLES.get(arg.arg)
            self.given(field, default, "as the default of")
        self.generic_visit(node)

    visit_AsyncFunctionDef = visit_FunctionDef

    # rule 3 (and 4: ``x in TABLE``)
    def visit_Compare(self, node: ast.Compare) -> None:
        sides = [node.left, *node.comparators]
        for op, a, b in zip(node.ops, sides, sides[1:], strict=False):
            for expr, other in ((a, b), (b, a)):
                field = self.field(expr)
                ordered = isinstance(op, (ast.Lt, ast.LtE, ast.Gt, ast.GtE))
                if field is None or (ordered and field in MSGID):  # ``msgid < 0``: pymavlink's bad data
                    continue
                for lit, value in _terms(other):
                    if _flagged(value, field) and not (ordered and value in (0, 1)):  # ``0 <= x < n``
                        self.flag(lit, f"{value} compared with {_shown(field)}")
                self.table_read(other, field, f"compared with {_shown(field)}")
        self.generic_visit(node)

    def visit_BinOp(self, node: ast.BinOp) -> None:
        if isinstance(node.op, _BITWISE):
            for expr, other in ((node.left, node.right), (node.right, node.left)):
                field = self.field(expr)
                if field is None or field in MSGID:  # a message id is split into bytes, not masked
                    continue
                value = _int(other)
                if value is not None and _flagged(value, field):
                    self.flag(other, f"{value} masked with {_shown(field)}")
                self.table_read(other, field, f"masked with {_shown(field)}")
        self.generic_visit(node)

    def visit_Match(self, node: ast.Match) -> None:
        field = self.field(node.subject)
        if field is not None:
            for case in node.cases:
                for pattern in ast.walk(case.pattern):
                    value = _int(pattern.value) if isinstance(pattern, ast.MatchValue) else None
                    if value is not None and _flagged(value, field):
                        self.flag(pattern, f"{value} matched with {_shown(field)}")
        self.generic_visit(node)

    def visit_Subscript(self, node: ast.Subscript) -> None:  # rule 4: ``TABLE[msg.field]``
        self.read_with(node.value, node.slice)
        self.generic_visit(node)

    def read_with(self, table: ast.AST, key: ast.AST) -> None:
        field = next((f for sub in ast.walk(key) if (f := self.field(sub)) is not None), None)
        if field is not None:
            self.table_read(table, field, f"read with {_shown(field)}")

    # rule 6
    def visit_Tuple(self, node: ast.Tuple) -> None:
        self.mixed(node.elts)
        self.generic_visit(node)

    def visit_List(self, node: ast.List) -> None:
        self.mixed(node.elts)
        self.generic_visit(node)

    def visit_Set(self, node: ast.Set) -> None:
        self.mixed(node.elts)
        self.generic_visit(node)

    def visit_Dict(self, node: ast.Dict) -> None:
        self.mixed([k for k in node.keys if k is not None])
        self.names_table(node)
        self.generic_visit(node)

    def names_table(self, node: ast.Dict) -> None:
        """Rule 8: ``{1: "TerminateSession", 6: "EOF", …}``: most values name the enum entry of their key."""
        items = [
            (k, value, v.value)
            for k, v in zip(node.keys, node.values, strict=True)
            if k is not None and (value := _int(k)) is not None and isinstance(v, ast.Constant)
            if isinstance(v.value, str)
        ]
        named = [(k, value) for k, value, text in items if _entry_named(value, text)]
        if len(named) >= 3 and 2 * len(named) >= len(items):
            for k, value, _ in items:
                self.flag(k, f"{value} in a table of MAVLink names")

    def mixed(self, elts: list[ast.expr]) -> None:
        if any(_mavlink_expr(e) for e in elts):
            for e in elts:
                value = _int(e)
                if value is not None:
                    self.flag(e, f"{value} beside MAVLink names")


def _shown(field: str) -> str:
    return "a message id" if field in MSGID else f".{field}"


def check_source(source: str, path: str = "<source>") -> list[Finding]:
    """The MAVLink literals of one module's source."""
    tree = ast.parse(source, path)
    checker = _Checker(path)
    checker.visit(tree)  # learns the tables and variables: one may be read above where it is bound
    checker.found.clear()
    checker.visit(tree)
    return sorted(checker.found.values(), key=lambda f: f.line)


def files(root: Path = ROOT) -> list[Path]:
    """The modules in :data:`SCOPE` but :data:`HOME`."""
    found = {p for top in SCOPE for p in (root / top).glob("**/*.py")}
    return sorted(p for p in found if p.relative_to(root).as_posix() != HOME)


def check_tree(root: Path = ROOT) -> list[Finding]:
    """Every MAVLink literal of the tree at ``root``."""
    out: list[Finding] = []
    for path in files(root):
        out += check_source(path.read_text(), path.relative_to(root).as_posix())
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=f"MAVLink numbers only in {HOME} (or pymavlink's names)")
    parser.add_argument("root", nargs="?", type=Path, default=ROOT, help="the tree to check")
    args = parser.parse_args(argv)
    found = check_tree(args.root)
    for f in found:
        print(f)
    if found:
        print(f"{len(found)} MAVLink literal(s): name them (see tools/mavlint.py)", file=sys.stderr)
        sys.exit(1)
    print(f"mavlint: no MAVLink literal outside {HOME}")


if __name__ == "__main__":
    main()
