"""The arena's dependency rules, checked on every import of the library, the services, the benchmarks, the
tools and the examples (``make lint``); the picture in ``docs/architecture.md`` is drawn from the same table.

    python -m tools.layers            # prints every import that breaks a rule; exit status 1 if any
    python -m tools.layers --write    # redraws the picture in docs/architecture.md

The rules:

1. The library's packages are in layers (:data:`LAYERS`, lowest first): a package imports its own layer
   and those below, never one above and never a sibling of its layer.
2. Some packages may not import every layer below them (:data:`NEVER`): the client, the user's API, loads
   no process runtime, no NatNet and no pipeline.
3. Only ``arena_common.sim``, the ``services.sim_*`` processes and the benchmarks import the simulator.
4. The library imports no ``services``, ``bench``, ``tools`` or ``tests``.
5. A service imports the library below ``cli``, never another service, ``cli``, ``bench``, ``tools`` or
   ``tests``; every module the table of services (``core/services.py``, which the supervisor, ``arena
   run``/``arena sim`` and the systemd units read) names exists and has a ``main`` and a ``cli``, and
   every service module is in that table.
6. ``bench`` imports the library, ``bench`` and ``tools``; ``tools`` the library and ``tools``; the
   examples only the user's API (``arena_common`` itself).
7. ``import arena_common`` (the user's API) loads neither the service runtime nor the bus security.
"""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LAYERS: tuple[tuple[str, ...], ...] = (
    ("core",),
    ("geometry",),
    ("bus",),
    ("mocap",),
    ("mavlink",),
    ("runtime",),
    ("pipeline",),
    ("gateway", "client", "recording", "sim"),
    ("ros2",),
    ("cli",),
)
RANK = {pkg: i for i, group in enumerate(LAYERS) for pkg in group}
#: Lower layers a package may still not import.
NEVER: dict[str, tuple[str, ...]] = {"client": ("runtime", "mocap", "pipeline")}
FOREIGN = ("services", "bench", "tools", "tests")
#: Who may import each top-level tree besides itself (None: anything of the library).
OUTSIDE = {"bench": ("arena_common", "bench", "tools"), "tools": ("arena_common", "tools")}
#: What ``import arena_common`` must not load.
NOT_FOR_USERS = ("arena_common.runtime.service", "arena_common.bus.security")
#: Where services are named by strings: the one table of services.
NAMERS = ("arena_common/core/services.py",)
DOC = "docs/architecture.md"
BEGIN, END = "<!-- layers: drawn by python -m tools.layers --write -->", "<!-- /layers -->"


def imports(path: Path, root: Path = ROOT) -> Iterator[tuple[int, str]]:
    """(line, module) of every import in a file, relative imports resolved."""
    tree = ast.parse(path.read_text(), str(path))
    package = ".".join(path.relative_to(root).with_suffix("").parts[:-1])
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, base]) if base else ".".join(parts)
            for alias in node.names:
                yield node.lineno, f"{base}.{alias.name}" if base else alias.name


def layer_of(module: str) -> str | None:
    """The arena_common subpackage a module belongs to (None for the package's own __init__)."""
    parts = module.split(".")
    return parts[1] if parts[0] == "arena_common" and len(parts) > 1 and parts[1] in RANK else None


def _library(rel: str, me: str, mine: str | None, target: str) -> list[str]:
    top = target.split(".")[0]
    if top in FOREIGN:
        return [f"{rel}: the library imports {target}"]
    other = layer_of(target)
    out: list[str] = []
    if other == "sim" and mine != "sim":
        out.append(f"{rel}: {target} — only the simulator, services.sim_* and bench import arena_common.sim")
    if other is None or mine is None or other == mine:
        return out
    if RANK[other] > RANK[mine]:
        out.append(f"{rel}: {mine} imports {target}, a layer above it ({other})")
    elif RANK[other] == RANK[mine]:
        out.append(f"{rel}: {mine} imports its sibling {other} ({target})")
    elif other in NEVER.get(mine, ()):
        out.append(f"{rel}: {mine} imports {target}: {mine} never loads {other}")
    return out


def _service(rel: str, me: str, target: str) -> list[str]:
    top = target.split(".")[0]
    if top == "services" and target.split(".")[:2] != me.split(".")[:2] and target != "services":
        return [f"{rel}: a service imports another service ({target}): shared code belongs in the library"]
    if top in ("bench", "tools", "tests"):
        return [f"{rel}: a service imports {target}"]
    if layer_of(target) == "cli":
        return [f"{rel}: a service imports the command line ({target})"]
    if layer_of(target) == "sim" and not me.startswith("services.sim_"):
        return [f"{rel}: {target} — only the simulator, services.sim_* and bench import arena_common.sim"]
    return []


def _outside(rel: str, tree: str, target: str) -> list[str]:
    top = target.split(".")[0]
    if tree == "examples":
        if top in ("arena_common", *FOREIGN) and target.rsplit(".", 1)[0] != "arena_common":
            return [
                f"{rel}: an example imports {target}: examples use the user's API (`from arena_common import …`)"
            ]
        return []
    allowed = OUTSIDE[tree]
    if top in (*FOREIGN, "arena_common", "examples") and top not in allowed:
        return [f"{rel}: {tree} imports {target}"]
    return []


def named_services(root: Path = ROOT) -> dict[str, str]:
    """``services.X`` module → where it is named (the table of services; a systemd unit naming one itself)."""
    found: dict[str, str] = {}
    for rel in NAMERS:
        path = root / rel
        if path.exists():
            for m in re.finditer(r'"(services\.[a-z0-9_]+)"', path.read_text()):
                found.setdefault(m.group(1), rel)
    for unit in sorted((root / "deploy" / "systemd").glob("*.service")):
        for m in re.finditer(r"-m (services\.[a-z0-9_]+)", unit.read_text()):
            found.setdefault(m.group(1), f"deploy/systemd/{unit.name}")
    return found


def _services_named(root: Path) -> list[str]:
    out: list[str] = []
    named = named_services(root)
    for module, where in sorted(named.items()):
        path = root / (module.replace(".", "/") + ".py")
        if not path.exists():
            out.append(f"{where}: names {module}, which does not exist")
            continue
        defined = {n.name for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef)}
        for needed in ("main", "cli"):
            if needed not in defined:
                out.append(f"{path.relative_to(root)}: a service module without `{needed}`")
    for path in sorted((root / "services").glob("*.py")):
        module = f"services.{path.stem}"
        if path.stem != "__init__" and module not in named:
            out.append(f"services/{path.name}: not in the table of services ({NAMERS[0]})")
    return out


def problems(root: Path = ROOT, probe: bool = True) -> list[str]:
    """Every import (and service name) of the tree at ``root`` that breaks a rule."""
    found: list[str] = []
    trees = ["arena_common/**/*.py", "services/*.py", "bench/**/*.py", "tools/**/*.py", "examples/**/*.py"]
    for path in sorted({p for pattern in trees for p in root.glob(pattern)}):
        rel = path.relative_to(root)
        me = ".".join(rel.with_suffix("").parts)
        tree = rel.parts[0]
        for line, target in imports(path, root):
            where = f"{rel}:{line}"
            if tree == "arena_common":
                found += _library(where, me, layer_of(me), target)
            elif tree == "services":
                found += _service(where, me, target)
            else:
                found += _outside(where, tree, target)
    found += _services_named(root)
    if probe and (root / "arena_common" / "__init__.py").exists():
        code = f"import sys, arena_common; print(' '.join(m for m in {NOT_FOR_USERS!r} if m in sys.modules))"
        loaded = subprocess.run(
            [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True
        ).stdout.split()
        found += [f"`import arena_common` loads {m}" for m in loaded]
    found += _picture_problems(root)
    return found


def picture() -> str:
    """The layers and their allowed arrows, as ``docs/architecture.md`` draws them."""
    lines = ["```", "  imports point down only; a package never imports a sibling of its row", ""]
    for i, group in reversed(list(enumerate(LAYERS))):
        lines.append(f"  {i:>2}  " + "   ".join(f"{g}/" for g in group))
        if i:
            lines.append("       │")
    lines += [
        "",
        "  services/  → any layer but cli/ (no other service; arena_common.sim only in services.sim_*)",
        "  bench/     → arena_common, tools/        tools/ → arena_common",
        "  examples/  → arena_common (the user's API) only",
    ]
    for pkg, never in NEVER.items():
        lines.append(
            f"  {pkg}/ never imports "
            + ", ".join(f"{n}/" for n in never)
            + " (below it, but not its business)"
        )
    lines.append("```")
    return "\n".join(lines)


def _picture_problems(root: Path) -> list[str]:
    doc = root / DOC
    if not doc.exists():
        return []
    text = doc.read_text()
    if BEGIN not in text or END not in text:
        return [f"{DOC}: no picture of the layers ({BEGIN} … {END})"]
    drawn = text.split(BEGIN, 1)[1].split(END, 1)[0].strip()
    return (
        []
        if drawn == picture()
        else [f"{DOC}: the picture of the layers is stale: python -m tools.layers --write"]
    )


def write_picture(root: Path = ROOT) -> None:
    doc = root / DOC
    text = doc.read_text()
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    doc.write_text(f"{head}{BEGIN}\n{picture()}\n{END}{tail}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="the arena's import layering")
    parser.add_argument("--write", action="store_true", help=f"redraw the picture in {DOC}")
    args = parser.parse_args(argv)
    if args.write:
        write_picture()
    found = problems()
    for p in found:
        print(p)
    if found:
        print(f"{len(found)} problem(s) with the layering (see tools/layers.py)", file=sys.stderr)
        sys.exit(1)
    print("layers: every import points down")


if __name__ == "__main__":
    main()
