"""Before/after flame-graph summaries from two ``--profile`` runs of the bench.

``python -m bench.flames BEFORE AFTER`` reads the py-spy stacks (collapsed, ``--gil``: only samples in which
the thread held the GIL, i.e. where the Python CPU goes) that ``python -m bench --profile`` left in each
directory (``profile-<time>/<service>-<time>.txt``, one file per service and load point, in the order the
points ran) and prints, per service, the flame graph's widest frames before and after: *inclusive* (the
frame and everything it called: the width of its box in the flame graph) and *self* (the frame alone),
as shares of that service's samples, and how much of the time the process held the GIL (its samples over
the samples the rate and duration allow: its Python work, comparable across the two runs).

Run the same points in both (e.g. ``-p pipeline -n 20 -r 180 -d 10 --decimate transform --overload 0
--profile`` in a checkout of each revision) and pick the point with ``--point`` (0: the first that ran).
``docs/profiles/before`` and ``docs/profiles/after`` hold the profiles of docs/performance.md (collapsed
stacks: speedscope or any flame-graph tool draws them).
"""

from __future__ import annotations

import argparse
import collections
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

SERVICES = ("ingest", "transform", "gateway.d1")
# Inclusive widths are shown for the arena's own frames, less the entry points every stack passes through
# (a service's ``main``, its command line): as wide as the whole graph, they say nothing.
_OWN = re.compile(r"\((?:.*/)?(arena_common|services)/")
_ENTRY = frozenset({"main", "cli", "<module>", "run"})
_LINE = re.compile(r":\d+\)$")


@dataclass(frozen=True)
class Flame:
    """One service's profile at one load point."""

    samples: int
    inclusive: list[tuple[str, float]]  # (frame, % of samples), widest first
    self_time: list[tuple[str, float]]


def _frame(raw: str) -> str:
    """``fn (path/to/file.py:123)`` → ``fn (file.py)``."""
    name, _, where = _LINE.sub(")", raw).partition(" (")
    return f"{name} ({Path(where.rstrip(')')).name})" if where else name


def read(path: Path, limit: int = 6) -> Flame:
    """Summarise one collapsed py-spy file (``stack count`` per line)."""
    incl: collections.Counter[str] = collections.Counter()
    own: collections.Counter[str] = collections.Counter()
    total = 0
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        n = int(count)
        total += n
        raw = stack.split(";")
        for f in dict.fromkeys(_frame(r) for r in raw if _OWN.search(r)):  # once per stack, if recursive
            if f.partition(" ")[0] not in _ENTRY:
                incl[f] += n
        if raw:
            own[_frame(raw[-1])] += n

    def top(c: collections.Counter[str]) -> list[tuple[str, float]]:
        return [(f, 100.0 * n / total) for f, n in c.most_common(limit)] if total else []

    return Flame(total, top(incl), top(own))


def profile_file(run_dir: Path, service: str, point: int) -> Path | None:
    """The service's profile at load point ``point`` of a run (``<service>.txt`` when the directory holds
    one profile per service, as ``docs/profiles/`` does), or None."""
    single = run_dir / f"{service}.txt"
    if single.exists():
        return single
    files = sorted(run_dir.glob(f"profile-*/{service}-*.txt"), key=lambda p: int(p.stem.rsplit("-", 1)[1]))
    return files[point] if point < len(files) else None


def table(before: Path, after: Path, point: int, rate: float, seconds: float) -> str:
    """The markdown comparison of two runs at one load point."""
    rows = [
        "| service | | holds the GIL | widest frames (inclusive) | top frames (self) |",
        "|---|---|---|---|---|",
    ]
    for service in SERVICES:
        for label, run in (("before", before), ("after", after)):
            path = profile_file(run, service, point)
            if path is None:
                rows.append(f"| {service} | {label} | — | (no profile) | |")
                continue
            f = read(path)
            incl = "; ".join(f"{name} {pct:.0f} %" for name, pct in f.inclusive)
            own = "; ".join(f"{name} {pct:.0f} %" for name, pct in f.self_time)
            held = 100.0 * f.samples / (rate * seconds)
            rows.append(f"| {service} | {label} | {held:.1f} % | {incl} | {own} |")
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> None:
    """Command line: see the module's docstring."""
    parser = argparse.ArgumentParser(prog="python -m bench.flames", description=__doc__)
    parser.add_argument("before", type=Path, help="The --out directory of the run before.")
    parser.add_argument("after", type=Path, help="The --out directory of the run after.")
    parser.add_argument("--point", type=int, default=0, help="Which load point (0: the first that ran).")
    parser.add_argument("--rate", type=float, default=500.0, help="py-spy's sampling rate (Hz).")
    parser.add_argument("--seconds", type=float, required=True, help="Seconds each profile lasted.")
    args = parser.parse_args(argv)
    print(table(args.before, args.after, args.point, args.rate, args.seconds))


if __name__ == "__main__":
    main()
