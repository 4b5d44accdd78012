"""``arena calibrate``: solve the arena calibration from a rigid body placed on surveyed marks.

The calibration maps Motive's frame (after the ``mocap.up_axis`` conversion to NED) onto the arena frame:
a rotation about Down and an offset (``[calibration] yaw_deg, offset``). Place one rigid body on two or
more marks whose arena coordinates (north, east, down from the floor's centre) are known; the command
averages the body's raw Motive position at each mark over about a second, solves the least-squares yaw
and offset (:func:`~arena_common.geometry.frames.solve_calibration`), prints them with the residual at each mark,
and with ``--write`` sets the two values of the ``[calibration]`` table in the config file (the file's
comments and everything else in it are kept).

Three ways to give the marks:

* interactive (default): at each mark type its coordinates ``N,E,D`` and press Enter; a blank line solves;
* ``--mark N,E,D`` repeated: the command prompts for each mark in turn and samples when Enter is pressed;
* ``--points FILE``: offline, a CSV of measured Motive positions and known arena positions, one mark per
  row ``x,y,z,n,e,d`` (an optional header names the columns in any order; ``#`` starts a comment).

The body is read from ``arena/<body>/mocap`` (a vehicle's rigid body) and ``arena/sys/bodies/<body>`` (a
body no vehicle claims, published when ``mocap.publish_unknown`` is on).
"""

from __future__ import annotations

import csv
import math
import os
import re
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, TextIO

import tomlkit
import typer
from tomlkit.container import OutOfOrderTableProxy
from tomlkit.exceptions import TOMLKitError
from tomlkit.items import InlineTable, Item, Table

from arena_common.bus.session import Subscription, open_bus
from arena_common.cli._globals import bus as global_bus
from arena_common.cli._globals import config as global_config
from arena_common.cli._globals import config_file as global_config_file
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.core.errors import ArenaError, ConfigError, InvalidName
from arena_common.geometry.frames import (
    Calibration,
    CalibrationError,
    FrameError,
    UpAxis,
    Vec3,
    calibration_residuals,
    motive_to_ned,
    solve_calibration,
)

__all__ = [
    "CalibrateError",
    "MarkSample",
    "PointPair",
    "Solution",
    "format_calibration",
    "parse_mark",
    "read_points_csv",
    "register",
    "sample_body",
    "solve",
    "update_calibration_text",
    "write_calibration",
]

RESIDUAL_WARN_M = 0.01  # a mark further off than this after the fit points to a wrong mark or up axis
_CSV_COLUMNS = ("x", "y", "z", "n", "e", "d")


class CalibrateError(ArenaError):
    """The calibration could not be measured, solved or written; the message says what and where."""


@dataclass(frozen=True)
class PointPair:
    """One mark: the body's position as Motive measured it (Motive's frame) and the mark's arena NED."""

    motive: Vec3
    arena: Vec3


@dataclass(frozen=True)
class MarkSample:
    """The body averaged over a sampling window: mean Motive position, sample count, largest deviation."""

    motive: Vec3
    count: int
    spread_m: float


@dataclass(frozen=True)
class Solution:
    """A solved calibration with the residual (m) of each mark after applying it."""

    calibration: Calibration
    residuals: tuple[float, ...]

    @property
    def rms(self) -> float:
        """Root mean square residual (m)."""
        return math.sqrt(sum(r * r for r in self.residuals) / len(self.residuals))


# --------------------------------------------------------------------------------------------------
# Parsing
# --------------------------------------------------------------------------------------------------


def parse_mark(text: str) -> Vec3:
    """``"N,E,D"`` (commas and/or spaces) → arena NED coordinates; :class:`CalibrateError` otherwise."""
    parts = [p for p in re.split(r"[,\s]+", text.strip().strip("()[]")) if p]
    if len(parts) != 3:
        raise CalibrateError(f"mark {text!r}: expected three numbers N,E,D (metres)")
    try:
        n, e, d = (float(p) for p in parts)
    except ValueError:
        raise CalibrateError(f"mark {text!r}: expected three numbers N,E,D (metres)") from None
    if not math.isfinite(n + e + d):
        raise CalibrateError(f"mark {text!r}: coordinates must be finite")
    return (n, e, d)


def read_points_csv(path: Path | str) -> list[PointPair]:
    """Read ``x,y,z,n,e,d`` rows: measured Motive position, then the mark's known arena NED position.

    A first row of column names (``x y z n e d`` in any order) is optional; blank lines and lines starting
    with ``#`` are skipped. Errors name the file and line.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CalibrateError(f"{p}: cannot read: {exc.strerror or exc}") from None
    order = list(range(6))
    pairs: list[PointPair] = []
    first = True
    for lineno, row in enumerate(csv.reader(text.splitlines()), start=1):
        cells = [c.strip() for c in row]
        if not any(cells) or cells[0].startswith("#"):
            continue
        if first and not _numeric(cells[0]):
            names = [c.lower() for c in cells]
            if sorted(names) != sorted(_CSV_COLUMNS):
                raise CalibrateError(
                    f"{p}:{lineno}: header must name the columns {', '.join(_CSV_COLUMNS)}, got {cells}"
                )
            order = [names.index(c) for c in _CSV_COLUMNS]
            first = False
            continue
        first = False
        if len(cells) != 6:
            raise CalibrateError(f"{p}:{lineno}: expected 6 values x,y,z,n,e,d, got {len(cells)}")
        try:
            values = [float(cells[i]) for i in order]
        except ValueError:
            raise CalibrateError(f"{p}:{lineno}: not a number in {cells}") from None
        if not all(math.isfinite(v) for v in values):
            raise CalibrateError(f"{p}:{lineno}: non-finite value in {cells}")
        pairs.append(PointPair((values[0], values[1], values[2]), (values[3], values[4], values[5])))
    if not pairs:
        raise CalibrateError(f"{p}: no points")
    return pairs


def _numeric(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


# --------------------------------------------------------------------------------------------------
# Measuring and solving
# --------------------------------------------------------------------------------------------------


def body_keys(body: str) -> tuple[str, str]:
    """The two keys a body can arrive on: a vehicle's ``mocap`` key and the unclaimed-body key."""
    try:
        return keys.mocap(body), keys.body(body)
    except InvalidName as exc:
        raise CalibrateError(str(exc)) from None


def sample_body(
    subs: Sequence[Subscription],
    duration: float = 1.0,
    timeout: float = 5.0,
    min_samples: int = 5,
    max_spread_m: float = 0.01,
) -> MarkSample:
    """Average the tracked samples arriving on ``subs`` over ``duration`` seconds (older ones are dropped).

    Raises :class:`CalibrateError` when fewer than ``min_samples`` tracked samples arrive within
    ``timeout`` seconds, or when a sample lies further than ``max_spread_m`` from the mean (the body moved).
    """
    for s in subs:
        s.channel.drain()
    points: list[Vec3] = []
    untracked = 0
    start = time.monotonic()
    first: float | None = None
    while True:  # bounded: each pass waits at most 20 ms and the deadlines below end the loop
        now = time.monotonic()
        if first is not None and now - first >= duration and len(points) >= min_samples:
            break
        if now - start >= max(timeout, duration):
            names = " or ".join(s.keyexpr for s in subs)
            why = f" ({untracked} untracked)" if untracked else ""
            raise CalibrateError(
                f"only {len(points)} tracked samples{why} on {names} within {max(timeout, duration):.1f} s "
                f"(need {min_samples}): is the body in view and named right?"
            )
        got = False
        for s in subs:
            for item in s.channel.drain():
                got = True
                m = item.payload
                if item.error is not None or not isinstance(m, wire.MocapPose):
                    continue
                if not m.ok:
                    untracked += 1
                    continue
                points.append(m.p)
                if first is None:
                    first = time.monotonic()
        if not got:
            time.sleep(0.02)  # two channels cannot be waited on together: poll them
    n = len(points)
    mean = (sum(p[0] for p in points) / n, sum(p[1] for p in points) / n, sum(p[2] for p in points) / n)
    spread = max(math.dist(p, mean) for p in points)
    if spread > max_spread_m:
        raise CalibrateError(
            f"the body moved while being sampled (a sample {spread * 1000:.1f} mm from the mean, limit "
            f"{max_spread_m * 1000:.1f} mm): hold it still on the mark and retry"
        )
    return MarkSample(mean, n, spread)


def solve(pairs: Sequence[PointPair], up_axis: UpAxis | str) -> Solution:
    """Solve the calibration from mark pairs, Motive positions converted to NED with ``up_axis``."""
    up = UpAxis.parse(up_axis)
    measured = [motive_to_ned(p.motive, up) for p in pairs]
    known = [p.arena for p in pairs]
    try:
        cal = solve_calibration(measured, known)
        res = calibration_residuals(cal, measured, known)
    except CalibrationError as exc:
        raise CalibrateError(str(exc)) from None
    return Solution(cal, tuple(float(r) for r in res))


# --------------------------------------------------------------------------------------------------
# Writing the [calibration] table
# --------------------------------------------------------------------------------------------------


def _num(v: float, digits: int) -> str:
    s = f"{v:.{digits}f}"
    return "0." + "0" * digits if float(s) == 0.0 else s  # never "-0.0000"


def format_calibration(cal: Calibration) -> tuple[str, str]:
    """The TOML values written for ``yaw_deg`` (0.0001°) and ``offset`` (0.1 mm)."""
    return _num(cal.yaw_deg, 4), "[" + ", ".join(_num(v, 4) for v in cal.offset_ned) + "]"


def update_calibration_text(text: str, cal: Calibration) -> str:
    """``text`` (a TOML config) with its ``[calibration]`` ``yaw_deg`` and ``offset`` set to ``cal``.

    Only those two values change (edited with :mod:`tomlkit`): their keys, comments (kept in the same
    column when the new value fits on the line) and everything else in the file stay as they were; a
    multi-line ``offset`` becomes one line. A missing key is added at the end of the table, a missing table
    at the end of the file. Inline and dotted ``calibration`` tables are edited where they are.
    """
    try:
        doc = tomlkit.parse(text)
    except TOMLKitError as exc:
        raise CalibrateError(f"not valid TOML: {exc}") from None
    table = doc.get("calibration")
    if table is None:
        table = tomlkit.table()
        doc.add(tomlkit.nl())  # a blank line before the new table ...
        if text and not text.endswith("\n"):
            doc.add(tomlkit.nl())  # ... after the last line's own end
        doc.add("calibration", table)
    elif not isinstance(table, Table | InlineTable | OutOfOrderTableProxy):
        raise CalibrateError(f"calibration must be a table, got {type(table.unwrap()).__name__}")
    for key, value in zip(("yaw_deg", "offset"), format_calibration(cal), strict=True):
        new = tomlkit.value(value)
        old = table.get(key)
        if isinstance(old, Item) and old.trivia.comment and "\n" not in old.as_string():
            # keep the comment in its column when the new value leaves room
            width = len(old.trivia.comment_ws) + len(old.as_string()) - len(value)
            new.trivia.comment_ws = " " * max(1, width)
        table[key] = new
    new_text = doc.as_string()
    if "\r\n" in text and not re.search(r"(?<!\r)\n", text):  # a CRLF file: its added lines end in CRLF
        new_text = re.sub(r"(?<!\r)\n", "\r\n", new_text)
    return new_text


def write_calibration(path: Path | str, cal: Calibration) -> str:
    """Rewrite the ``[calibration]`` table of config file ``path`` in place; returns the new text.

    The new text is checked before the file is replaced (atomically): it must still be a valid arena
    config, carry exactly the new values, and differ from the old one in the calibration only.
    """
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except OSError as exc:
        raise CalibrateError(f"{p}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise CalibrateError(f"{p}: not UTF-8 text") from None
    try:
        new = update_calibration_text(text, cal)
    except CalibrateError as exc:
        raise CalibrateError(f"{p}: {exc}") from None
    _check_rewrite(p, text, new, cal)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(new.encode("utf-8"))
        os.chmod(tmp, p.stat().st_mode & 0o7777)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return new


def _check_rewrite(p: Path, old: str, new: str, cal: Calibration) -> None:
    try:
        before, after = tomllib.loads(old), tomllib.loads(new)
        cfg = config_mod.parse(after, str(p))
    except (tomllib.TOMLDecodeError, ConfigError) as exc:
        raise CalibrateError(f"{p}: refusing to write, the rewritten file would be invalid: {exc}") from None
    yaw_s, _ = format_calibration(cal)
    got = cfg.calibration
    if got.yaw_deg != float(yaw_s) or any(
        abs(a - b) > 1e-4 for a, b in zip(got.offset, cal.offset_ned, strict=True)
    ):
        raise CalibrateError(f"{p}: refusing to write, the rewritten [calibration] does not read back")
    for doc in (before, after):  # all but the two values written
        table = doc.pop("calibration", {})
        doc["calibration"] = {k: v for k, v in table.items() if k not in ("yaw_deg", "offset")}
    if before != after:
        raise CalibrateError(f"{p}: refusing to write, the rewrite would change more than [calibration]")


# --------------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------------


def _read_line(stream: TextIO, prompt: str) -> str | None:
    typer.echo(prompt, nl=False)
    sys.stdout.flush()
    line = stream.readline()
    if not line:
        typer.echo("")
        return None
    return line.strip()


def _measure(
    sample: Callable[[], MarkSample], marks: Sequence[Vec3] | None, stream: TextIO
) -> list[PointPair]:
    """Drive the prompts: ``marks`` given (one Enter per mark) or typed (interactive)."""
    pairs: list[PointPair] = []
    if marks is not None:
        for i, mark in enumerate(marks, start=1):
            where = ", ".join(f"{c:g}" for c in mark)
            prompt = f"mark {i}/{len(marks)} at N,E,D = ({where}): place the body, press Enter "
            if _read_line(stream, prompt) is None:
                raise CalibrateError(f"input ended before mark {i}")
            s = sample()
            typer.echo(_sampled(s))
            pairs.append(PointPair(s.motive, mark))
        return pairs
    typer.echo("Place the body on a mark, type the mark's arena coordinates N,E,D and press Enter.")
    typer.echo("A blank line solves (two marks at least; more marks, spread out, give a better fit).")
    while True:
        line = _read_line(stream, f"mark {len(pairs) + 1} N,E,D: ")
        if line is None or line == "":
            if len(pairs) >= 2:
                return pairs
            if line is None:
                raise CalibrateError(f"input ended after {len(pairs)} marks; at least 2 are needed")
            typer.echo("at least two marks are needed")
            continue
        try:
            mark = parse_mark(line)
            s = sample()
        except CalibrateError as exc:
            typer.echo(f"  {exc}")
            continue
        typer.echo(_sampled(s))
        pairs.append(PointPair(s.motive, mark))


def _sampled(s: MarkSample) -> str:
    x, y, z = s.motive
    return f"  {s.count} samples: Motive ({x:.4f}, {y:.4f}, {z:.4f}), spread {s.spread_m * 1000:.1f} mm"


def _report(pairs: Sequence[PointPair], sol: Solution) -> None:
    yaw_s, offset_s = format_calibration(sol.calibration)
    typer.echo(f"{len(pairs)} marks:")
    for i, (pair, r) in enumerate(zip(pairs, sol.residuals, strict=True), start=1):
        motive = ", ".join(f"{c:.4f}" for c in pair.motive)
        arena = ", ".join(f"{c:.4f}" for c in pair.arena)
        typer.echo(f"  mark {i}: Motive ({motive}) → arena ({arena})  residual {r * 1000:.1f} mm")
    typer.echo(f"residuals: rms {sol.rms * 1000:.1f} mm, max {max(sol.residuals) * 1000:.1f} mm")
    if max(sol.residuals) > RESIDUAL_WARN_M:
        typer.echo(
            f"warning: a residual exceeds {RESIDUAL_WARN_M * 1000:.0f} mm: check the marks' coordinates, "
            "that the body sat on each mark, and mocap.up_axis",
            err=True,
        )
    typer.echo("[calibration]")
    typer.echo(f"yaw_deg = {yaw_s}")
    typer.echo(f"offset = {offset_s}")


def calibrate(
    body: Annotated[
        str | None, typer.Option("--body", "-b", help="Rigid body to sample (a vehicle or unclaimed body).")
    ] = None,
    mark: Annotated[
        list[str] | None,
        typer.Option("--mark", help="Known arena coordinates 'N,E,D' of the next mark (repeatable)."),
    ] = None,
    points: Annotated[
        Path | None, typer.Option("--points", help="CSV of x,y,z (Motive) and n,e,d (arena) per mark.")
    ] = None,
    write: Annotated[
        bool, typer.Option("--write", help="Update the \\[calibration] table of the config file.")
    ] = False,
    up_axis: Annotated[
        str | None, typer.Option("--up-axis", help="Motive's up axis: y, z or enu (default: mocap.up_axis).")
    ] = None,
    duration: Annotated[float, typer.Option("--duration", help="Seconds to average at each mark.")] = 1.0,
    timeout: Annotated[float, typer.Option("--timeout", help="Seconds to wait for the body.")] = 5.0,
    max_spread: Annotated[
        float, typer.Option("--max-spread", help="Largest deviation (m) from the mean while sampling.")
    ] = 0.01,
) -> None:
    """Solve the arena calibration (yaw about Down, NED offset) from a body on known marks."""
    cfg = global_config(required=write or up_axis is None or points is None)
    try:
        up = UpAxis.parse(up_axis if up_axis is not None else cfg.mocap.up_axis if cfg else "y")
        if points is not None:
            if body or mark:
                raise CalibrateError("--points is offline: do not combine it with --body or --mark")
            pairs = read_points_csv(points)
        else:
            if not body:
                raise CalibrateError("name the rigid body to sample with --body")
            if not (duration > 0 and timeout > 0 and max_spread > 0):
                raise CalibrateError("--duration, --timeout and --max-spread must be positive")
            marks = [parse_mark(m) for m in mark] if mark else None
            if marks is not None and len(marks) < 2:
                raise CalibrateError("give at least two --mark (yaw needs two points)")
            key_names = body_keys(body)
            with open_bus(cfg.zenoh if cfg else None, global_bus()) as bus:
                subs = [bus.subscribe(k, capacity=4096, ring=False) for k in key_names]
                typer.echo(f"sampling {' / '.join(key_names)}; Motive up axis {up.value}")
                pairs = _measure(
                    lambda: sample_body(subs, duration, timeout, max_spread_m=max_spread), marks, sys.stdin
                )
        sol = solve(pairs, up)
        _report(pairs, sol)
        if write:
            path = global_config_file()
            write_calibration(path, sol.calibration)
            typer.echo(f"wrote [calibration] to {path} (restart the transform service to apply it)")
    except (CalibrateError, FrameError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None


def register(app: typer.Typer) -> None:
    """Add ``calibrate`` to ``app``."""
    app.command("calibrate")(calibrate)
