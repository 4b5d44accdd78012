"""Real ROS 2 is the authority: the bridge's messages against ROS 2's own rclpy and message packages.

The package index carries ROS 2's wheels (``ros-rclpy``, ``ros-rmw-fastrtps-cpp``, ``ros-geometry-msgs``
…).  They are installed once, in a virtual environment of their own (:func:`ros_python`: under
``~/.cache/flying-arena/ros2-venv``, ``$ARENA_ROS2_VENV`` to put it elsewhere; bounded by
:data:`INSTALL_TIMEOUT`; reused while its stamp matches), and ``tests/ros2_rclpy_worker.py`` runs there.
For every row of the topic table (:data:`arena_common.ros2.topics.TOPICS`):

- published: the arena's own conversion makes the message, the arena serializes it, and real
  ``rclpy.serialization.deserialize_message`` must read back every field the arena put in;
- subscribed (goto, cmd_vel): real rclpy builds and serializes the message a ROS 2 user sends, and the
  arena's decoding and conversion must give the command the docs promise;
- every type hash the arena puts in its key expressions and liveliness tokens must equal the RIHS01 hash
  in the wheel's ``share/<pkg>/msg/<Type>.json``.

A type whose package has no wheel on the index (``tf2_msgs`` today) is skipped with pip's own words; the
whole module is skipped with them when the index lacks rclpy or the install fails.
"""

from __future__ import annotations

import dataclasses
import fcntl
import json
import math
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from arena_common.ros2 import messages, types
from arena_common.ros2.topics import TOPICS, Direction, Topic, rows
from tests.helpers import TESTS
from tests.ros2_samples import sample

pytestmark = [pytest.mark.system, pytest.mark.timeout(1500)]

INSTALL_TIMEOUT = 1200.0  # s for every pip install of a fresh environment together
BASE = ("ros-rclpy", "ros-rmw-fastrtps-cpp")  # rclpy, and an rmw for its serialization
WORKER = TESTS / "ros2_rclpy_worker.py"


def wheel(type_name: str) -> str:
    """The wheel of a message type's package: ``geometry_msgs/msg/Pose`` → ``ros-geometry-msgs``."""
    return "ros-" + type_name.split("/")[0].replace("_", "-")


MESSAGE_WHEELS = tuple(sorted({wheel(t.msg_type) for t in TOPICS}))


@dataclasses.dataclass(frozen=True)
class RosEnv:
    """The ROS 2 environment: its python, and the message wheels pip could not install (with why)."""

    python: Path
    missing: dict[str, str]

    def ask(self, requests: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """One run of the worker for all ``requests``."""
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
        proc = subprocess.run(
            [str(self.python), str(WORKER)],
            input=json.dumps(requests),
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        answers: list[dict[str, Any]] = json.loads(proc.stdout)
        return answers

    def need(self, type_name: str, answer: dict[str, Any]) -> None:
        """Skip (with pip's reason) when the type's package could not be installed here."""
        if "missing" in answer:
            why = self.missing.get(wheel(type_name), "installed, yet not importable")
            pytest.skip(f"{type_name}: {wheel(type_name)}: {why} ({answer['missing']})")


def _cache() -> Path:
    if os.environ.get("ARENA_ROS2_VENV"):
        return Path(os.environ["ARENA_ROS2_VENV"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "flying-arena" / "ros2-venv"


def _pip_error(proc: subprocess.CompletedProcess[str]) -> str:
    lines = [ln.strip() for ln in (proc.stderr + proc.stdout).splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("ERROR")]
    return "; ".join(errors[:3]) or (lines[-1] if lines else f"pip exited {proc.returncode}")


def _install(venv: Path) -> dict[str, str]:
    """Make ``venv`` with ROS 2's wheels; the message wheels that did not install, with pip's reason.
    ``pytest.skip`` when rclpy itself does not install."""
    shutil.rmtree(venv, ignore_errors=True)
    deadline = time.monotonic() + INSTALL_TIMEOUT
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    pip = [
        str(venv / "bin" / "python"),
        "-m",
        "pip",
        "install",
        "-q",
        "--no-input",
        "--disable-pip-version-check",
    ]
    missing: dict[str, str] = {}
    for group in (BASE, *((w,) for w in MESSAGE_WHEELS)):
        left = deadline - time.monotonic()
        try:
            proc = subprocess.run([*pip, *group], capture_output=True, text=True, timeout=max(left, 1.0))
        except subprocess.TimeoutExpired:
            shutil.rmtree(venv, ignore_errors=True)
            pytest.skip(
                f"ROS 2 wheels: pip install {' '.join(group)} did not finish within {INSTALL_TIMEOUT:.0f} s"
            )
        if proc.returncode == 0:
            continue
        if group == BASE:
            shutil.rmtree(venv, ignore_errors=True)
            pytest.skip(f"ROS 2 wheels: pip install {' '.join(BASE)} failed: {_pip_error(proc)}")
        missing[group[0]] = _pip_error(proc)
    return missing


@pytest.fixture(scope="session")
def ros() -> Iterator[RosEnv]:
    """ROS 2's rclpy and message packages in their own environment, installed once and cached."""
    venv = _cache()
    venv.parent.mkdir(parents=True, exist_ok=True)
    want = {"python": sys.version, "wheels": [*BASE, *MESSAGE_WHEELS]}
    stamp = venv / "arena-stamp.json"
    with open(venv.parent / f"{venv.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one installer at a time, whatever runs the tests
        try:
            have = json.loads(stamp.read_text())
        except (OSError, ValueError):
            have = {}
        if {k: have.get(k) for k in want} != want:
            missing = _install(venv)
            stamp.write_text(json.dumps({**want, "missing": missing}, indent=1))
            have = {**want, "missing": missing}
    yield RosEnv(venv / "bin" / "python", dict(have.get("missing", {})))


# -- comparing the arena's message with what rclpy read ----------------------------------------------------
def _plain(msg: Any) -> Any:
    """A rosbags message as plain values, field by field (what the arena put in); rosbags keeps the
    type's name and constants (upper case, as ROS names them) as fields too."""
    if dataclasses.is_dataclass(msg) and not isinstance(msg, type):
        names = [f.name for f in dataclasses.fields(msg) if not (f.name.startswith("__") or f.name.isupper())]
        return {n: _plain(getattr(msg, n)) for n in names}
    if hasattr(msg, "tolist"):
        return msg.tolist()
    if isinstance(msg, list | tuple):
        return [_plain(v) for v in msg]
    return msg


def _same(put: Any, read: Any, where: str = "") -> list[str]:
    """Where the two differ (floats to float32's precision, NaN equal to NaN)."""
    if isinstance(put, dict):
        if not isinstance(read, dict) or set(put) != set(read):
            return [f"{where}: fields {sorted(put)} vs {sorted(read) if isinstance(read, dict) else read!r}"]
        return [d for k in put for d in _same(put[k], read[k], f"{where}.{k}")]
    if isinstance(put, list):
        if not isinstance(read, list) or len(put) != len(read):
            return [f"{where}: {put!r} vs {read!r}"]
        return [
            d for i, (a, b) in enumerate(zip(put, read, strict=True)) for d in _same(a, b, f"{where}[{i}]")
        ]
    if isinstance(put, float) or isinstance(read, float):
        if math.isnan(put) and math.isnan(read):
            return []
        return (
            [] if math.isclose(put, read, rel_tol=1e-6, abs_tol=1e-9) else [f"{where}: {put!r} vs {read!r}"]
        )
    return [] if put == read else [f"{where}: {put!r} vs {read!r}"]


@pytest.mark.parametrize("row", rows(Direction.OUT), ids=lambda r: r.name)
def test_rclpy_decodes_what_the_bridge_publishes(ros: RosEnv, row: Topic) -> None:
    msg = row.convert("d1", sample(row), "arena_bridge")
    (answer,) = ros.ask(
        [{"op": "decode", "type": row.msg_type, "hex": types.serialize(msg, row.msg_type).hex()}]
    )
    ros.need(row.msg_type, answer)
    read = answer["fields"]
    assert _same(_plain(msg), read) == []
    # …and a few values by hand, so that a conversion wrong on both sides still shows
    if row.msg_type == types.POSE_STAMPED:
        assert (read["header"]["stamp"]["sec"], read["header"]["stamp"]["nanosec"]) == (
            1_700_000_000,
            123_456_789,
        )
        assert read["pose"]["position"] == {"x": -0.5, "y": 1.25, "z": 1.0}
    if row.msg_type == types.ODOMETRY:
        assert read["child_frame_id"] == "d1" and len(read["pose"]["covariance"]) == 36
        assert read["twist"]["twist"]["angular"]["z"] == pytest.approx(-0.05)
    if row.msg_type == types.BATTERY_STATE:
        assert read["voltage"] == pytest.approx(11.7) and math.isnan(read["percentage"]) and read["present"]
    if row.msg_type == types.DIAGNOSTIC_ARRAY:
        assert [s["level"] for s in read["status"]] == [0, 1, 1, 0]  # bytes in rclpy: levels as ints
    if row.msg_type == types.LOG:
        assert (read["level"], read["name"], read["msg"]) == (50, "arena_bridge.d1", "RC lost")


def _goto(frame: str, x: float, y: float, z: float, yaw_deg: float | None) -> dict[str, Any]:
    q = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}
    if yaw_deg is not None:
        q = {
            "x": 0.0,
            "y": 0.0,
            "z": math.sin(math.radians(yaw_deg) / 2),
            "w": math.cos(math.radians(yaw_deg) / 2),
        }
    return {"header": {"frame_id": frame}, "pose": {"position": {"x": x, "y": y, "z": z}, "orientation": q}}


def _twist(lin: tuple[float, float, float], yaw_rate: float) -> dict[str, Any]:
    return {"linear": dict(zip("xyz", lin, strict=True)), "angular": {"x": 0.0, "y": 0.0, "z": yaw_rate}}


# What a ROS 2 user sends, and what the arena must make of it (docs/ros2.md: Commands from ROS 2, Frames).
INPUTS: dict[str, list[tuple[dict[str, Any], messages.Goto | messages.Velocity | str]]] = {
    "goto": [
        (_goto("map", 0.5, 0.3, 1.2, 90.0), messages.Goto((0.3, 0.5, -1.2), 0.0)),
        (_goto("", 0.5, 0.3, 1.2, None), messages.Goto((0.3, 0.5, -1.2), None)),
        (_goto("map", -1.0, 2.0, 0.5, 0.0), messages.Goto((2.0, -1.0, -0.5), math.pi / 2)),
        (_goto("arena_ned", 0.3, 0.5, -1.2, 90.0), messages.Goto((0.3, 0.5, -1.2), math.pi / 2)),
        (_goto("odom", 0.0, 0.0, 1.0, None), "frame 'odom' unknown"),
    ],
    "cmd_vel": [
        (_twist((0.3, 0.2, 0.1), 0.4), messages.Velocity((0.3, -0.2, -0.1), -0.4)),
        (_twist((0.0, 0.0, 0.0), 0.0), messages.Velocity((0.0, 0.0, 0.0), 0.0)),
        (_twist((math.nan, 0.0, 0.0), 0.0), "velocity not finite"),
    ],
}


@pytest.mark.parametrize("row", rows(Direction.IN), ids=lambda r: r.name)
def test_the_bridge_reads_what_rclpy_sends(ros: RosEnv, row: Topic) -> None:
    cases = INPUTS[row.leaf]
    answers = ros.ask([{"op": "encode", "type": row.msg_type, "fields": fields} for fields, _ in cases])
    for (fields, want), answer in zip(cases, answers, strict=True):
        ros.need(row.msg_type, answer)
        msg = types.deserialize(bytes.fromhex(answer["hex"]), row.msg_type)
        if isinstance(want, str):
            with pytest.raises(messages.RosInputError, match=want):
                row.convert(msg)
            continue
        got = row.convert(msg)
        if isinstance(want, messages.Goto):
            assert isinstance(got, messages.Goto), fields
            assert got.p == pytest.approx(want.p) and (got.yaw is None) == (want.yaw is None), fields
            if got.yaw is not None and want.yaw is not None:
                assert math.remainder(got.yaw - want.yaw, math.tau) == pytest.approx(0.0, abs=1e-9), fields
        else:
            assert isinstance(got, messages.Velocity), fields
            assert got.body == pytest.approx(want.body) and got.yaw_rate == pytest.approx(want.yaw_rate)


@pytest.mark.parametrize("type_name", sorted({t.msg_type for t in TOPICS}))
def test_type_hashes_are_ros2s_own(ros: RosEnv, type_name: str) -> None:
    (answer,) = ros.ask([{"op": "hash", "type": type_name}])
    ros.need(type_name, answer)
    assert types.msg_type(type_name).hash == answer["hash"]
