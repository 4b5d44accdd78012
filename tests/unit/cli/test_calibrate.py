"""``arena calibrate``: solving from marks (offline, live, interactive) and rewriting the config file."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from arena_common.bus.session import Bus
from arena_common.cli import app
from arena_common.cli._calibrate import (
    CalibrateError,
    parse_mark,
    read_points_csv,
    update_calibration_text,
    write_calibration,
)
from arena_common.core import config as config_mod
from arena_common.core import keys, wire
from arena_common.geometry.frames import Calibration
from tests.helpers import REPO, wait_for, write_config

runner = CliRunner()
SIM_TOML = (REPO / "deploy" / "sim.toml").read_text(encoding="utf-8")
# The truth the tests calibrate back: 30° about Down, then this offset (m).
YAW_DEG, OFFSET = 30.0, (1.5, -0.7, 0.02)
MARKS = [(3.0, 1.5, 0.0), (-3.0, 1.5, 0.0), (-3.0, -1.5, 0.0), (3.0, -1.5, -1.0)]


def motive_of(mark: tuple[float, float, float], up_axis: str) -> tuple[float, float, float]:
    """Where Motive sees a body on ``mark`` under the truth calibration (by hand, not with the library)."""
    c, s = math.cos(math.radians(YAW_DEG)), math.sin(math.radians(YAW_DEG))
    dn, de, dd = (m - o for m, o in zip(mark, OFFSET, strict=True))
    n, e, d = c * dn + s * de, -s * dn + c * de, dd  # undo the rotation about Down
    if up_axis == "y":  # NED = (x, z, -y)
        return (n, -d, e)
    if up_axis == "z":  # NED = (x, -y, -z)
        return (n, -e, -d)
    raise AssertionError(up_axis)


def printed_yaw(output: str) -> float:
    m = re.search(r"^yaw_deg = (\S+)$", output, re.MULTILINE)
    assert m, output
    return float(m.group(1))


def changed_lines(old: str, new: str) -> list[tuple[str, str]]:
    a, b = old.splitlines(keepends=True), new.splitlines(keepends=True)
    assert len(a) == len(b)
    return [(x, y) for x, y in zip(a, b, strict=True) if x != y]


# --------------------------------------------------------------------------------------------------
# Rewriting the [calibration] table
# --------------------------------------------------------------------------------------------------


def test_update_changes_the_two_values_only() -> None:
    new = update_calibration_text(SIM_TOML, Calibration.from_degrees(-12.345678, (1.23456, -0.5, 0.01)))
    diff = changed_lines(SIM_TOML, new)
    assert [d[1] for d in diff] == [
        "yaw_deg = -12.3457          # rotation about Down from Motive's ground plane to the arena's north\n",
        "offset = [1.2346, -0.5000, 0.0100] # NED offset [m] added after the rotation\n",
    ]
    cal = config_mod.parse(tomllib.loads(new)).calibration
    assert cal.yaw_deg == -12.3457 and cal.offset == (1.2346, -0.5, 0.01)


def test_update_variants() -> None:
    cal = Calibration.from_degrees(5.0, (0.0, -0.0, 1.0))
    # CRLF line ends, quoted keys and a multi-line array; the table ends at the next header.
    head, tail = '[arena]\r\nname = "x"\r\n[calibration]\r\n', '\r\n[mocap]\r\nup_axis = "z"\r\n'
    crlf = head + '"yaw_deg" = 1\r\noffset = [\r\n  1.0,\r\n  2.0,\r\n  3.0,\r\n] # m\r\n' + tail
    assert update_calibration_text(crlf, cal) == (
        head + '"yaw_deg" = 5.0000\r\noffset = [0.0000, 0.0000, 1.0000] # m\r\n' + tail
    )
    # A key missing from the table is added to it; its comments stay.
    partial = "[calibration]\nyaw_deg = 0.0 # about Down\n\n# the room\n[arena]\n"
    new = update_calibration_text(partial, cal)
    assert "yaw_deg = 5.0000 # about Down\n" in new and "\n# the room\n" in new
    assert tomllib.loads(new) == {"calibration": {"yaw_deg": 5.0, "offset": [0.0, 0.0, 1.0]}, "arena": {}}
    # No table at all (and no final newline): one is appended, in the file's line ends.
    assert update_calibration_text('[arena]\nname = "x"', cal) == (
        '[arena]\nname = "x"\n\n[calibration]\nyaw_deg = 5.0000\noffset = [0.0000, 0.0000, 1.0000]\n'
    )
    assert update_calibration_text('[arena]\r\nname = "x"\r\n', cal) == (
        '[arena]\r\nname = "x"\r\n\r\n[calibration]\r\nyaw_deg = 5.0000\r\noffset = [0.0000, 0.0000, 1.0000]\r\n'
    )
    # Inline and dotted tables are edited where they stand.
    assert update_calibration_text("calibration = { yaw_deg = 1.0 } # c\n", cal) == (
        "calibration = { yaw_deg = 5.0000, offset = [0.0000, 0.0000, 1.0000]} # c\n"
    )
    dotted = update_calibration_text("calibration.yaw_deg = 1.0 # c\n[arena]\n", cal)
    assert dotted.startswith("calibration.yaw_deg = 5.0000 # c\n")
    assert tomllib.loads(dotted)["calibration"] == {"yaw_deg": 5.0, "offset": [0.0, 0.0, 1.0]}
    with pytest.raises(CalibrateError, match="already exists"):
        update_calibration_text("[calibration]\nyaw_deg = 1\nyaw_deg = 2\n", cal)
    with pytest.raises(CalibrateError, match="calibration must be a table, got int"):
        update_calibration_text("calibration = 3\n", cal)


def test_write_keeps_the_comments_and_changes_the_calibration_only(tmp_path: Path) -> None:
    """A commented config, calibrated: every comment and other line is kept, the new values read back."""
    path = tmp_path / "arena.toml"
    original = SIM_TOML.replace(
        "[calibration]\n",
        "# surveyed 2024-05: marks on the floor's grid\n[calibration]  # by `arena calibrate`\n",
    )
    path.write_text(original, encoding="utf-8")
    write_calibration(path, Calibration.from_degrees(30.0, (1.5, -0.7, 0.02)))
    new = path.read_text(encoding="utf-8")
    comments = [line.partition("#")[2] for line in original.splitlines() if "#" in line]
    assert comments and [line.partition("#")[2] for line in new.splitlines() if "#" in line] == comments
    assert [old for old, _ in changed_lines(original, new)] == [
        line for line in original.splitlines(keepends=True) if line.startswith(("yaw_deg", "offset"))
    ]
    got = config_mod.load(path)
    assert got.calibration.yaw_deg == 30.0 and got.calibration.offset == (1.5, -0.7, 0.02)
    before = config_mod.parse(tomllib.loads(original))
    assert got.mocap == before.mocap and got.vehicles == before.vehicles and got.zenoh == before.zenoh
    # A file the rewrite would break is left as it was, the error naming it.
    path.write_text("[calibration]\nyaw_deg = 1\nyaw_deg = 2\n", encoding="utf-8")
    with pytest.raises(CalibrateError, match=r"arena\.toml: not valid TOML"):
        write_calibration(path, Calibration.from_degrees(30.0, (0.0, 0.0, 0.0)))
    assert path.read_text(encoding="utf-8") == "[calibration]\nyaw_deg = 1\nyaw_deg = 2\n"


def test_parse_mark_and_csv_errors(tmp_path: Path) -> None:
    assert parse_mark(" 1, -2.5 ,0 ") == (1.0, -2.5, 0.0) and parse_mark("(1 2 3)") == (1.0, 2.0, 3.0)
    for bad in ("1,2", "1,2,x", "1,2,nan"):
        with pytest.raises(CalibrateError, match=r"mark '1,2.*': (expected three numbers|.* finite)"):
            parse_mark(bad)
    f = tmp_path / "p.csv"
    f.write_text("# measured, known\nn,e,d,x,y,z\n4,5,6,1,2,3\n")
    assert read_points_csv(f)[0].motive == (1.0, 2.0, 3.0) and read_points_csv(f)[0].arena == (4.0, 5.0, 6.0)
    f.write_text("1,2,3,4,5,6\n1,2,3,4,5\n")
    with pytest.raises(CalibrateError, match=r"p\.csv:2: expected 6 values"):
        read_points_csv(f)
    f.write_text("a,b,c,d,e,f\n")
    with pytest.raises(CalibrateError, match=r"p\.csv:1: header must name"):
        read_points_csv(f)


# --------------------------------------------------------------------------------------------------
# Offline: --points
# --------------------------------------------------------------------------------------------------


def test_points_file_solves_and_writes(tmp_path: Path) -> None:
    cfg = tmp_path / "arena.toml"
    original = SIM_TOML.replace('up_axis = "y"', 'up_axis = "z"')
    cfg.write_text(original, encoding="utf-8")
    rng = np.random.default_rng(3)
    rows = ["x,y,z,n,e,d"]
    for mark in MARKS:
        x, y, z = (c + rng.uniform(-2e-4, 2e-4) for c in motive_of(mark, "z"))
        rows.append(f"{x},{y},{z},{mark[0]},{mark[1]},{mark[2]}")
    points = tmp_path / "points.csv"
    points.write_text("\n".join(rows) + "\n")

    res = runner.invoke(app, ["calibrate", "--points", str(points), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    assert printed_yaw(res.output) == pytest.approx(YAW_DEG, abs=0.01) and "residuals: rms 0." in res.output
    assert cfg.read_text(encoding="utf-8") == original  # not written without --write

    res = runner.invoke(app, ["calibrate", "--points", str(points), "--config", str(cfg), "--write"])
    assert res.exit_code == 0, res.output
    new = cfg.read_text(encoding="utf-8")
    assert len(changed_lines(original, new)) == 2
    got = config_mod.load(cfg).calibration
    assert got.yaw_deg == pytest.approx(YAW_DEG, abs=0.01)
    assert got.offset == pytest.approx(OFFSET, abs=1e-3)

    # Inconsistent marks: solved anyway, with a warning naming the likely causes.
    points.write_text("\n".join([*rows[:-1], "0,0,0,3,-1.5,-1"]) + "\n")
    res = runner.invoke(app, ["calibrate", "--points", str(points), "--config", str(cfg)])
    assert res.exit_code == 0 and "warning: a residual exceeds" in res.output


def test_usage_errors(tmp_path: Path, router_endpoint: str) -> None:
    cfg = write_config(tmp_path, router_endpoint)
    one = runner.invoke(app, ["calibrate", "--config", str(cfg), "--body", "wand", "--mark", "1,0,0"])
    assert one.exit_code == 1 and "at least two --mark" in one.output
    nobody = runner.invoke(app, ["calibrate", "--config", str(cfg)])
    assert nobody.exit_code == 1 and "--body" in nobody.output
    both = runner.invoke(app, ["calibrate", "--config", str(cfg), "--points", "x.csv", "--body", "b"])
    assert both.exit_code == 1 and "offline" in both.output
    # A body that never shows up: a bounded wait, then an error naming the keys.
    args = ["calibrate", "--config", str(cfg), "--body", "ghost", "--mark", "0,0,0", "--mark", "1,0,0"]
    absent = runner.invoke(app, [*args, "--timeout", "0.5", "--duration", "0.2"], input="\n\n")
    assert absent.exit_code == 1, absent.output
    assert "only 0 tracked samples on arena/ghost/mocap or arena/sys/bodies/ghost" in absent.output


# --------------------------------------------------------------------------------------------------
# Live: a body published on the bus, the command run as a process
# --------------------------------------------------------------------------------------------------


class Body:
    """Publishes a rigid body at 200 Hz at a settable Motive position (with optional noise)."""

    def __init__(self, bus: Bus, key: str) -> None:
        self.pub = bus.stream_publisher(key, wire.MocapPose)
        self.name = key.rsplit("/", 1)[1]
        self.position = (0.0, 0.0, 0.0)
        self.noise = 1e-4
        self.since_move = 0
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        rng = np.random.default_rng(1)
        fn = 0
        while not self.stop.wait(0.005):
            with self.lock:
                x, y, z = (c + rng.uniform(-self.noise, self.noise) for c in self.position)
                self.since_move += 1
            fn += 1
            self.pub.put(
                wire.MocapPose(
                    t=time.time_ns(),
                    fn=fn,
                    id=7,
                    p=(x, y, z),
                    q=(1.0, 0.0, 0.0, 0.0),
                    ok=True,
                    name=self.name,
                )
            )

    def move(self, position: tuple[float, float, float], noise: float = 1e-4) -> None:
        """Put the body there and wait until 20 samples went out from there (older ones are in the past)."""
        with self.lock:
            self.position, self.noise, self.since_move = position, noise, 0
        wait_for(lambda: self.since_move >= 20, timeout=10, what="the body at its new place")

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)


class Console:
    """A command run as a process whose prompts (no newline) are read as they come."""

    def __init__(self, args: list[str]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "arena_common.cli", *args],
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"},
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        self.text = ""
        self.seen = 0
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        while chunk := os.read(self.proc.stdout.fileno(), 4096):
            self.text += chunk.decode()

    def expect(self, what: str, timeout: float = 30.0) -> None:
        """Wait until ``what`` appears after everything already expected."""
        wait_for(lambda: what in self.text[self.seen :], timeout=timeout, what=f"{what!r} in {self.text!r}")
        self.seen += self.text[self.seen :].index(what) + len(what)

    def type(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line.encode() + b"\n")
        self.proc.stdin.flush()

    def finish(self, timeout: float = 30.0) -> int:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout)
        self._reader.join(5)
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


@contextmanager
def running_console(args: list[str]) -> Iterator[Console]:
    console = Console(args)
    try:
        yield console
    finally:
        console.kill()


def test_marks_with_a_published_body_and_write(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus]
) -> None:
    """--mark mode, the body unclaimed by any vehicle (arena/sys/bodies/wand), Motive Y-up."""
    path = write_config(tmp_path, router_endpoint)
    original = path.read_text()
    body = Body(bus_factory(), keys.body("wand"))
    marks = ["--mark", "3,1.5,0", "--mark", "-3,1.5,0", "--mark", "-3,-1.5,0"]
    try:
        with running_console(
            ["calibrate", "--body", "wand", *marks, "--config", str(path), "--write", "--duration", "0.3"]
        ) as console:
            for i, mark in enumerate(MARKS[:3], start=1):
                console.expect(f"mark {i}/3 at N,E,D")
                body.move(motive_of(mark, "y"))
                console.type("")
                console.expect("samples: Motive")
            assert console.finish() == 0, console.text
    finally:
        body.close()
    out = console.text
    assert "wrote [calibration] to" in out and printed_yaw(out) == pytest.approx(YAW_DEG, abs=0.01)
    new = path.read_text()
    assert new.startswith(original) and new[len(original) :].startswith("\n[calibration]\n")
    got = config_mod.load(path).calibration
    assert got.yaw_deg == pytest.approx(YAW_DEG, abs=0.01)
    assert got.offset == pytest.approx(OFFSET, abs=1e-3)


def test_interactive_with_a_vehicle_body(
    tmp_path: Path, router_endpoint: str, bus_factory: Callable[[], Bus]
) -> None:
    """Interactive, on a vehicle's mocap key: a typo and a moving body are retried, a blank line solves."""
    path = write_config(tmp_path, router_endpoint)
    body = Body(bus_factory(), keys.mocap("d1"))
    try:
        with running_console(
            ["calibrate", "--body", "d1", "--config", str(path), "--duration", "0.3", "--up-axis", "z"]
        ) as console:
            console.expect("mark 1 N,E,D: ")
            console.type("3,1.5")
            console.expect("expected three numbers N,E,D")
            console.expect("mark 1 N,E,D: ")
            body.move(motive_of(MARKS[0], "z"), noise=0.05)  # still being carried
            console.type("3,1.5,0")
            console.expect("the body moved while being sampled")
            for i, mark in enumerate(MARKS, start=1):
                console.expect(f"mark {i} N,E,D: ")
                body.move(motive_of(mark, "z"))
                console.type(",".join(str(c) for c in mark))
                console.expect("samples: Motive")
            console.expect("mark 5 N,E,D: ")
            console.type("")
            console.expect("offset = [")
            assert console.finish() == 0, console.text
    finally:
        body.close()
    out = console.text
    assert "4 marks:" in out and printed_yaw(out) == pytest.approx(YAW_DEG, abs=0.01)
    m = re.search(r"^offset = \[(.*)\]$", out, re.MULTILINE)
    assert m and [float(v) for v in m.group(1).split(",")] == pytest.approx(OFFSET, abs=1e-3)
    assert "wrote" not in out and path.read_text().count("[calibration]") == 0
