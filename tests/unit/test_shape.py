"""The code keeps a readable shape: no function longer than a screen or two, every bench module saying what
it measures.

A function's length is its lines from ``def`` to its last line, docstring included (a nested function
counts within its parent and on its own).  ``bench/`` holds at most :data:`BENCH_MAX` lines a function,
the rest of the code :data:`MAX`; the functions that were longer when the limit came are listed in
:data:`KNOWN_LONG` with their length then: each may shrink, never grow, and leaves the list once split.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import REPO

ROOTS = ("arena_common", "services", "bench", "tools")
MAX = 100  # lines a function
BENCH_MAX = 80
# Longer than MAX when the check came (lines then): to be split, meanwhile never longer.
KNOWN_LONG = {
    "arena_common/mocap/natnet/frames.py:decode_frame": 218,
    "tools/ulog_report.py:analyse": 121,
    "arena_common/mocap/sources.py:read_csv_take": 112,
    "arena_common/cli/_demo.py:_run": 111,
    "arena_common/sim/estimator.py:Estimator.fuse_vision": 104,
}


def functions(path: Path) -> Iterator[tuple[str, int, int]]:
    """``(qualified name, first line, length)`` of every function and method in ``path``."""

    def walk(node: ast.AST, prefix: str) -> Iterator[tuple[str, int, int]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = prefix + child.name
                yield name, child.lineno, (child.end_lineno or child.lineno) - child.lineno + 1
                yield from walk(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, prefix + child.name + ".")
            else:
                yield from walk(child, prefix)

    yield from walk(ast.parse(path.read_text(encoding="utf-8"), str(path)), "")


def too_long(root: Path) -> tuple[list[str], set[str]]:
    """Every function of the :data:`ROOTS` under ``root`` over its limit (``file:line name: n lines``), and
    the :data:`KNOWN_LONG` entries seen."""
    found: list[str] = []
    seen: set[str] = set()
    for top in ROOTS:
        for path in sorted((root / top).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            for name, line, length in functions(path):
                limit = BENCH_MAX if top == "bench" else MAX
                key = f"{rel}:{name}"
                if key in KNOWN_LONG and length > limit:
                    seen.add(key)
                    limit = KNOWN_LONG[key]
                if length > limit:
                    found.append(f"{rel}:{line} {name}: {length} lines (limit {limit})")
    return found, seen


def test_no_function_is_over_its_limit() -> None:
    found, seen = too_long(REPO)
    assert not found, "functions too long; split them into named steps:\n" + "\n".join(found)
    stale = sorted(set(KNOWN_LONG) - seen)
    assert not stale, f"now within the limit, take them off KNOWN_LONG: {stale}"


def test_the_check_finds_long_functions(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A long function in bench/ and a longer one elsewhere, nested and in a class, are all reported."""
    body = "".join(f"    x{i} = {i}\n" for i in range(85))
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "a.py").write_text(f"def long():\n{body}\n\ndef short():\n    pass\n")
    (tmp_path / "tools").mkdir()
    nested = "".join(f"            y{i} = {i}\n" for i in range(101))
    (tmp_path / "tools" / "b.py").write_text(
        f"def fits():\n{body}\n\nclass C:\n    def m(self):\n        def inner():\n{nested}"
    )
    found, _ = too_long(tmp_path)
    assert found == [
        "bench/a.py:1 long: 86 lines (limit 80)",
        "tools/b.py:90 C.m: 103 lines (limit 100)",
        "tools/b.py:91 C.m.inner: 102 lines (limit 100)",
    ]
    # A known long function may stay as long as it was, not grow.
    monkeypatch.setitem(KNOWN_LONG, "tools/b.py:C.m", 103)
    monkeypatch.setitem(KNOWN_LONG, "tools/b.py:C.m.inner", 101)
    found, seen = too_long(tmp_path)
    assert found == [
        "bench/a.py:1 long: 86 lines (limit 80)",
        "tools/b.py:91 C.m.inner: 102 lines (limit 101)",
    ]
    assert seen == {"tools/b.py:C.m", "tools/b.py:C.m.inner"}


def test_every_bench_module_says_what_it_is_for() -> None:
    missing = [
        p.relative_to(REPO).as_posix()
        for p in sorted((REPO / "bench").glob("*.py"))
        if not ast.get_docstring(ast.parse(p.read_text(encoding="utf-8")))
    ]
    assert not missing, f"bench modules without a docstring: {missing}"
