"""Every ``arena`` command of ``arena --help``, typed as a user types it against a running simulated arena.

One arena per module (``arena up CONFIG --host typed``: router, Motive emulator, simulated x7, ingest,
transform, recorder, x7's downsampler and gateway, all on free ports).  Each command runs as the real
console script in a session of its own, with the shared options (``-c/--config``) before the
sub-command in one run and after it in another, and the test checks what the command promises: what it
prints, the vehicle's state it changes (read back with ``arena echo … --json``), the files it writes,
its exit status — and that nothing of it is left running.
"""

from __future__ import annotations

import collections
import csv
import json
import math
import re
import signal
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena_common.recording.reader import RecordingReader
from tests.helpers import free_port, wait_for
from tests.typed.harness import ARENA, START_S, Command, Typed, bound, commands, leftovers, stops_cleanly

pytestmark = pytest.mark.timeout(600)


class Arena:
    """The module's running arena, and a way to type one-shot commands at it."""

    def __init__(self, cfg: Typed, up: Command) -> None:
        self.cfg, self.up = cfg, up

    def run(self, *args: str, where: str = "after", timeout: float = 90, check: bool = True) -> str:
        """``arena ARGS`` with ``-c CONFIG`` ``where`` ("before", "after" the sub-command, or "none");
        its output (stdout and stderr), which must come with exit status 0 unless ``check`` is off."""
        c = ["-c", str(self.cfg.path)]
        argv = [*c, *args] if where == "before" else [*args, *c] if where == "after" else list(args)
        res = subprocess.run(
            [str(ARENA), *argv],
            cwd=self.cfg.dir,
            capture_output=True,
            text=True,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
            env={"PATH": "/usr/bin:/bin", "NO_COLOR": "1", "COLUMNS": "200", "PYTHONUNBUFFERED": "1"},
        )
        out = res.stdout + res.stderr
        if check:
            assert res.returncode == 0, f"`arena {' '.join(argv)}` exited {res.returncode}:\n{out}"
        assert not leftovers([f"{ARENA} {' '.join(argv)}"]), f"`arena {' '.join(argv)}` left a process"
        return out

    def state(self, vehicle: str = "x7") -> dict[str, Any]:
        """The vehicle's newest state, as ``arena echo arena/<d>/state -n 1 --json`` prints it."""
        out = self.run("echo", f"arena/{vehicle}/state", "-n", "1", "--json")
        # The JSON line on stdout; a warning of the command's own (its clock, say) may follow on stderr.
        line = next(line for line in reversed(out.splitlines()) if line.startswith("{"))
        payload: dict[str, Any] = json.loads(line)["payload"]
        return payload

    def wait_state(self, what: str, predicate: Callable[[dict[str, Any]], bool], timeout: float = 60) -> None:
        wait_for(lambda: predicate(self.state()), timeout=timeout, interval=0.5, what=what)


@pytest.fixture(scope="module")
def arena(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Arena]:
    d = tmp_path_factory.mktemp("typed-arena")
    cfg = Typed(d, f"tcp/127.0.0.1:{free_port()}", router=True, px4=False, services=["recorder"])
    with commands(d) as start:
        up = start("up", str(cfg.path), "--host", "typed")
        up.wait_line(r"starting router, sim-vehicle, sim-motive, mocap, transform, recorder")
        the_arena = Arena(cfg, up)
        the_arena.wait_state("x7's vision fused", lambda s: bool(s.get("vis_fused")), timeout=START_S * 2)
        yield the_arena
        assert stops_cleanly(up, [str(d)]) == 0, up.output()


@pytest.mark.covers("arena up", "arena status", "arena keys", "arena config check", "arena echo", "arena top")
@pytest.mark.parametrize("where", ["before", "after"])
def test_reading_commands(arena: Arena, where: str) -> None:
    status = arena.run("status", where=where)
    for expected in ("router", "gateway.x7", "downsampler.x7", "transform", "mocap", "recorder", "x7"):
        assert expected in status, status
    keys = arena.run("keys", where=where)
    assert "arena/<drone>/vision" in keys and "arena/sys/frames" in keys
    check = arena.run("config", "check", str(arena.cfg.path), where="none")
    assert "ok — arena 'typed'" in check and "1 vehicles (x7)" in check.replace(
        "1 vehicle (x7)", "1 vehicles (x7)"
    )
    lines = arena.run("echo", "arena/x7/pose", "-n", "3", where=where).strip().splitlines()
    assert len(lines) == 3 and all("arena/x7/pose" in line for line in lines), lines
    top = arena.run("top", "arena/x7/**", "--duration", "2", where=where)
    assert "arena/x7/pose" in top and "arena/x7/vision" in top and "lost" in top, top


@pytest.mark.covers(
    "arena arm", "arena takeoff", "arena goto", "arena hold", "arena land", "arena disarm", "arena estop",
    "arena kill",
)  # fmt: skip
def test_flying_from_the_shell(arena: Arena) -> None:
    arena.wait_state(
        "x7 on the ground, disarmed", lambda s: not s["armed"] and s.get("landed") == "on_ground"
    )
    arena.run("arm", "x7", where="before")
    assert arena.state()["armed"]
    out = arena.run("takeoff", "x7", "0.8", where="after", timeout=120)
    assert "x7" in out
    arena.wait_state("x7 at 0.8 m", lambda s: s["p"] is not None and abs(s["p"][2] + 0.8) < 0.15)
    arena.run("goto", "x7", "0.5", "0.3", "-0.9", "--tolerance", "0.15", where="before", timeout=120)
    p = arena.state()["p"]
    assert math.dist(p, (0.5, 0.3, -0.9)) < 0.3, p
    arena.run("hold", "x7", where="after")
    arena.wait_state("x7 holding", lambda s: s["mode"] == "AUTO.LOITER")
    arena.run("land", "x7", where="before", timeout=120)
    arena.wait_state("x7 landed", lambda s: s.get("landed") == "on_ground", timeout=90)
    arena.run("disarm", "x7", where="after")
    arena.wait_state("x7 disarmed", lambda s: not s["armed"])
    # The operator's stops: an estop lands a flying vehicle; kill cuts the motors.
    arena.run("arm", "x7", where="after")
    arena.run("takeoff", "x7", "0.6", where="before", timeout=120)
    out = arena.run("estop", "--reason", "typed test", where="after")
    arena.wait_state("x7 landing after the estop", lambda s: s["mode"] == "AUTO.LAND" or not s["armed"])
    arena.wait_state("x7 down", lambda s: s.get("landed") == "on_ground", timeout=90)
    arena.run("kill", "x7", where="before")
    arena.wait_state("x7 disarmed by kill", lambda s: not s["armed"])


@pytest.mark.covers("arena px4 check", "arena px4 setup", "arena px4 reboot", "arena px4 keygen")
def test_px4_parameters_and_keys(arena: Arena) -> None:
    arena.wait_state("x7 disarmed", lambda s: not s["armed"])
    assert "EKF2_EV_CTRL" in arena.run("px4", "check", "x7", where="after", timeout=120)
    assert "EKF2_EV_CTRL" in arena.run("px4", "setup", "x7", where="before", timeout=120)
    reboot = arena.run("px4", "reboot", "x7", where="after", timeout=120)
    assert "x7" in reboot
    arena.wait_state(
        "x7 back after its reboot", lambda s: bool(s.get("link")) and bool(s.get("vis_fused")), 90
    )
    key = arena.cfg.dir / "x7.key"
    out = arena.run("px4", "keygen", str(key), where="none")
    assert key.is_file() and oct(key.stat().st_mode & 0o777) == "0o600" and len(key.read_text().strip()) == 64
    assert key.read_text().strip() not in out  # the secret is never printed


@pytest.mark.covers(
    "arena rec start", "arena rec status", "arena rec stop", "arena rec info", "arena rec repair",
    "arena export", "arena plot", "arena replay", "arena export recordings/rec_ground_….mcap --ros2 -o ros2/",
)  # fmt: skip
def test_recordings(arena: Arena, tmp_path: Path) -> None:
    arena.run("rec", "start", "typed-flight", where="before")
    assert "recording" in arena.run("rec", "status", where="after").lower()
    wait_for(
        lambda: list(arena.cfg.rec_dir.glob("**/*typed-flight*.mcap")), 30, 0.5, what="the recording file"
    )
    arena.run("echo", "arena/x7/state", "-n", "20", where="after")  # some seconds of the vehicle
    arena.run("rec", "stop", where="before")
    (mcap,) = sorted(arena.cfg.rec_dir.glob("**/*typed-flight*.mcap"))
    info = arena.run("rec", "info", str(mcap), where="none")
    assert "arena/x7/state" in info, info
    repaired = tmp_path / "repaired.mcap"
    arena.run("rec", "repair", str(mcap), "-o", str(repaired), where="none")
    assert repaired.stat().st_size > 0
    tables = tmp_path / "tables"
    arena.run("export", str(mcap), "-o", str(tables), where="none")
    state_csv = next(tables.glob("*state*.csv"))
    with state_csv.open() as f:
        assert len(list(csv.reader(f))) > 2
    ros2 = tmp_path / "ros2"
    arena.run("export", str(mcap), "--ros2", "-o", f"{ros2}/", where="none")  # docs/ros2.md's line
    (ros2_mcap,) = ros2.glob("*.ros2.mcap")
    # Read through (a schema may come anywhere in the file, in a compressed chunk or only in the summary).
    ros2_reader = RecordingReader(ros2_mcap)
    topics = collections.Counter(m.channel.key for m in ros2_reader.messages())
    assert ros2_reader.complete and ros2_reader.error is None, ros2_reader.error
    encodings = {(c.message_encoding, c.schema_encoding) for c in ros2_reader.channels.values()}
    assert encodings == {("cdr", "ros2msg")}, encodings
    assert topics["/arena/x7/battery"] > 0, topics  # from the recorded arena/x7/state
    plots = tmp_path / "plots"
    arena.run("plot", str(mcap), "-o", str(plots), where="none")
    assert list(plots.glob("*.png"))
    # Replayed under another name, while a reader waits for it.
    with commands(tmp_path) as start:
        reader = start("echo", "arena/replayed/state", "-n", "3", "-c", str(arena.cfg.path))
        arena.run(
            "replay",
            str(mcap),
            "--remap",
            "arena/x7=arena/replayed",
            "--speed",
            "4",
            "--start-delay",
            "30",
            where="after",
        )
        assert reader.exits_within(60) == 0, reader.output()
        assert reader.output().count("arena/replayed/state") == 3


@pytest.mark.covers("arena mocap probe")
def test_mocap_probe_sees_the_emulators_bodies(arena: Arena) -> None:
    out = arena.run(
        "mocap", "probe", "--server", "127.0.0.1", "--command-port", str(arena.cfg.command_port),
        "--unicast", "--duration", "2", where="none",
    )  # fmt: skip
    assert "x7" in out and re.search(r"\d+(\.\d+)? (Hz|frames)", out), out


@pytest.mark.covers("arena calibrate")
def test_calibrate_from_measured_points(arena: Arena, tmp_path: Path) -> None:
    # Marks measured in Motive (x, y, z; y up) and their arena NED positions: the arena rotated by 90°.
    points = tmp_path / "marks.csv"
    points.write_text("x,y,z,n,e,d\n1,0,0,0,1,0\n0,0,1,1,0,0\n2,0,1,1,2,0\n")
    out = arena.run("calibrate", "--points", str(points), where="after")
    assert re.search(r"yaw", out, re.I), out
    copy = tmp_path / "copy.toml"
    copy.write_text(arena.cfg.path.read_text())
    arena.run("calibrate", "--points", str(points), "--write", "--config", str(copy), where="none")
    assert "[calibration]" in copy.read_text() and "yaw_deg" in copy.read_text()


@pytest.mark.covers("arena router")
@pytest.mark.parametrize("where", ["before", "after"])
def test_router_serves_the_named_configs_endpoint(tmp_path: Path, where: str) -> None:
    port = free_port()
    cfg = Typed(tmp_path, f"tcp/127.0.0.1:{port}", px4=False)
    with commands(tmp_path) as start:
        c = ["-c", str(cfg.path)]
        router = start(*c, "router") if where == "before" else start("router", *c)
        router.wait_line(rf"routing on tcp/127\.0\.0\.1:{port}")
        wait_for(lambda: bound("tcp", port), timeout=20, what=f"the router on tcp {port}")
        assert stops_cleanly(router, [str(tmp_path)], signal.SIGINT) == 0, router.output()
