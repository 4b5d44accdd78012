"""The arena's dependency rules, checked on every import of the library and the services (``make lint``).

    python -m tools.layers          # prints every import that breaks a rule; exit status 1 if any

Layers, lowest first; a package may import its own layer and those below, never one above and never a
sibling of its layer (the gateway does not import the client, nor the simulator the gateway)::

    core        errors, keys, wire, config: plain data, no I/O
    geometry    frames, filters
    bus         the Zenoh session, security
    mocap       NatNet codec and client, mocap sources, captures
    mavlink     the MAVLink link, signing, PX4 parameters and protocols, PX4's metadata
    runtime     what a process needs: service runtime, options, supervisor, the PX4 SITL launcher
    pipeline    the vision filter the transform and downsampler share
    gateway | client | recording | sim      (siblings: none imports another)
    ros2        ROS 2 over rmw_zenoh: the client for commands, recordings for the MCAP export
    cli

Also: no library module imports ``services``, ``bench``, ``tools`` or ``tests``; nothing but
``arena_common.sim`` and the ``services.sim_*`` processes imports ``arena_common.sim``; and
``import arena_common`` (the user's API) loads neither the service runtime nor the bus security.
"""

from __future__ import annotations

import ast
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
FOREIGN = ("services", "bench", "tools", "tests")
#: What ``import arena_common`` must not load.
NOT_FOR_USERS = ("arena_common.runtime.service", "arena_common.bus.security")


def imports(path: Path) -> Iterator[tuple[int, str]]:
    """(line, module) of every import in a file, relative imports resolved."""
    tree = ast.parse(path.read_text(), str(path))
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
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


def problems() -> list[str]:
    found: list[str] = []
    for path in sorted([*ROOT.glob("arena_common/**/*.py"), *ROOT.glob("services/*.py")]):
        rel = path.relative_to(ROOT)
        me = ".".join(rel.with_suffix("").parts)
        mine = layer_of(me)
        for line, target in imports(path):
            where = f"{rel}:{line}"
            top = target.split(".")[0]
            if me.startswith("arena_common") and top in FOREIGN:
                found.append(f"{where}: the library imports {target}")
                continue
            other = layer_of(target)
            if other is None:
                continue
            if other == "sim" and not (mine == "sim" or me.startswith("services.sim_")):
                found.append(
                    f"{where}: {target} — only the simulator and services.sim_* import arena_common.sim"
                )
            if mine is None or other == mine:
                continue
            if RANK[other] > RANK[mine]:
                found.append(f"{where}: {mine} imports {target}, a layer above it ({other})")
            elif RANK[other] == RANK[mine]:
                found.append(f"{where}: {mine} imports its sibling {other} ({target})")
    probe = f"import sys, arena_common; print(' '.join(m for m in {NOT_FOR_USERS!r} if m in sys.modules))"
    loaded = subprocess.run(
        [sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    found += [f"`import arena_common` loads {m}" for m in loaded]
    return found


def main() -> None:
    found = problems()
    for p in found:
        print(p)
    if found:
        print(f"{len(found)} import(s) break the layering (see tools/layers.py)", file=sys.stderr)
        sys.exit(1)
    print("layers: every import points down")


if __name__ == "__main__":
    main()
