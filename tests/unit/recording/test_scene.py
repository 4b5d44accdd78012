"""The Foxglove 3D scene in recordings: frames (NED under an ENU world, known vectors), the room and its
safe volume, vehicles' paths, estimates, setpoints and events — read back with an independent reader."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from arena_common.core import keys, wire
from arena_common.core.config import ArenaSpec
from arena_common.recording import mcap as recording
from arena_common.recording.mcap import RecordingWriter, Sample
from arena_common.recording.scene import Scene
from tests.foxglove_decode import Frames, entity_points, read_foxglove
from tests.helpers import REPO

T0 = 1_700_000_000 * 10**9
ARENA = ArenaSpec(name="lab", size=(7.0, 4.0, 2.5), margin=0.3)


def _yaw_q(yaw: float) -> tuple[float, float, float, float]:
    return (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))


def _sample(key: str, p: wire.Payload, t_recv: int) -> Sample:
    return Sample(key, p.encode(), p.encoding(), t_recv)


def _write(path: Path, samples: list[Sample], arena: ArenaSpec = ARENA) -> None:
    w = RecordingWriter(path, scene=Scene(arena))
    for s in samples:
        w.record(s)
    w.close()


def _frames(dec: object, upto: int | None = None) -> Frames:
    """Every transform of the recording (up to a log time), latest last."""
    frames = Frames()
    msgs = sorted(
        (
            (lt, m)
            for topic, items in dec.topics.items()  # type: ignore[attr-defined]
            for lt, schema, m in items
            if schema == "foxglove.FrameTransforms"
        ),
        key=lambda x: x[0],
    )
    for lt, m in msgs:  # (sorted by log time alone)
        if upto is None or lt <= upto:
            frames.add(m)
    return frames


def test_world_is_enu_and_arena_ned_hangs_under_it_known_vectors(tmp_path: Path) -> None:
    """A vehicle 1 m north, 2 m east, 1.5 m up, facing east: where Foxglove's z-up world puts it."""
    path = tmp_path / "v.mcap"
    pose = wire.Pose(t=T0, p=(1.0, 2.0, -1.5), q=_yaw_q(math.pi / 2), ok=True)
    est = wire.State(t=T0, p=(1.1, 2.0, -1.4), q=_yaw_q(math.pi), link=True, armed=True, mode="OFFBOARD")
    _write(
        tmp_path / "v.mcap",
        [_sample(keys.pose("d1"), pose, T0 + 1000), _sample(keys.state("d1"), est, T0 + 2000)],
    )
    dec = read_foxglove(path)
    frames = _frames(dec)
    assert frames.parent == {"arena_ned": "world", "d1": "arena_ned", "d1/estimate": "arena_ned"}
    r_world_ned = frames.pose["arena_ned"][0]
    assert np.allclose(r_world_ned, [[0, 1, 0], [1, 0, 0], [0, 0, -1]], atol=1e-12)
    assert np.isclose(np.linalg.det(r_world_ned), 1.0)
    # arena axes in the world: north → +y, east → +x, down → −z
    assert np.allclose(frames.to_root("arena_ned", (1, 0, 0)), (0, 1, 0))
    assert np.allclose(frames.to_root("arena_ned", (0, 1, 0)), (1, 0, 0))
    assert np.allclose(frames.to_root("arena_ned", (0, 0, 1)), (0, 0, -1))
    # the vehicle: origin at (e, n, up), forward (FRD x) east, right south, down down
    assert np.allclose(frames.to_root("d1", (0, 0, 0)), (2.0, 1.0, 1.5))
    assert np.allclose(frames.to_root("d1", (1, 0, 0), vector=True), (1, 0, 0), atol=1e-9)
    assert np.allclose(frames.to_root("d1", (0, 1, 0), vector=True), (0, -1, 0), atol=1e-9)
    assert np.allclose(frames.to_root("d1", (0, 0, 1), vector=True), (0, 0, -1), atol=1e-9)
    # a point 1 m ahead of the vehicle is 1 m further east
    assert np.allclose(frames.to_root("d1", (1, 0, 0)), (3.0, 1.0, 1.5))
    # the estimate, facing south
    assert np.allclose(frames.to_root("d1/estimate", (0, 0, 0)), (2.0, 1.1, 1.4))
    assert np.allclose(frames.to_root("d1/estimate", (1, 0, 0), vector=True), (0, -1, 0), atol=1e-9)
    tf = dec.last("/arena/d1/tf").transforms[0]
    assert (tf.timestamp.seconds, tf.timestamp.nanos) == (T0 // 10**9, T0 % 10**9)  # measurement time


def test_room_and_safe_volume_are_boxes_in_the_world(tmp_path: Path) -> None:
    path = tmp_path / "room.mcap"
    _write(
        path, [_sample(keys.pose("d1"), wire.Pose(t=T0, p=(0.0, 0.0, 0.0), q=(1.0, 0, 0, 0), ok=True), T0)]
    )
    dec = read_foxglove(path)
    frames = _frames(dec)
    room = {e.id: e for e in dec.last("/arena/scene/room").entities}
    assert set(room) == {"room", "safe_volume"}
    walls = entity_points(room["room"], frames)
    assert len(walls) == 24  # 12 edges
    assert np.allclose(walls.min(axis=0), (-2.0, -3.5, 0.0)) and np.allclose(
        walls.max(axis=0), (2.0, 3.5, 2.5)
    )
    safe = entity_points(room["safe_volume"], frames)
    assert np.allclose(safe.min(axis=0), (-1.7, -3.2, 0.0)) and np.allclose(safe.max(axis=0), (1.7, 3.2, 2.2))
    assert room["room"].frame_id == "arena_ned" and frames.root("arena_ned") == "world"
    assert any("lab 7 × 4 × 2.5 m" in t.text for t in room["room"].texts)


def test_paths_estimates_setpoints_and_events(tmp_path: Path) -> None:
    """Three vehicles fly circles for 12 s: their trails are their paths; setpoints, events, labels."""
    path = tmp_path / "fly.mcap"
    samples: list[Sample] = []
    centres = {"d1": (-1.0, -1.0), "d2": (0.0, 0.0), "d3": (1.0, 1.0)}
    truth: dict[str, list[tuple[float, float, float]]] = {n: [] for n in centres}
    for i in range(12 * 100):  # 100 Hz for 12 s
        t = T0 + i * 10_000_000
        for n, (cn, ce) in centres.items():
            a = i / 100 * 0.5
            p = (cn + 0.5 * math.cos(a), ce + 0.5 * math.sin(a), -1.0 - 0.1 * math.sin(a))
            truth[n].append(p)
            samples.append(_sample(keys.pose(n), wire.Pose(t=t, p=p, q=_yaw_q(a), ok=True), t + 1_000_000))
            if i % 10 == 0:
                st = wire.State(
                    t=t,
                    p=(p[0] + 0.05, p[1], p[2]),
                    q=_yaw_q(a),
                    link=True,
                    armed=True,
                    mode="OFFBOARD",
                    bat=0.5,
                )
                samples.append(_sample(keys.state(n), st, t + 2_000_000))
                sp = wire.Setpoint(t=t, p=(cn, ce, -1.0), yaw=0.5, lease=0.5)
                samples.append(_sample(keys.setpoint(n), sp, t + 3_000_000))
    ev = wire.Event(t=T0 + 5 * 10**9, kind="failsafe", text="battery low", sev=4)
    samples.append(_sample(keys.events("d2"), ev, T0 + 5 * 10**9))
    samples.sort(key=lambda s: s.t_recv)
    # the last pose of d3 is untracked and far away: it must not move the frame
    t_end = T0 + 12 * 10**9
    samples.append(
        _sample(keys.pose("d3"), wire.Pose(t=t_end, p=(9.0, 9.0, 9.0), q=(1.0, 0, 0, 0), ok=False), t_end)
    )
    _write(path, samples)

    dec = read_foxglove(path)
    assert dec.schemas["/arena/scene/trails"] == "foxglove.SceneUpdate"
    assert dec.schemas["/arena/log"] == "foxglove.Log"
    frames = _frames(dec)
    trails = {e.id: e for e in dec.last("/arena/scene/trails").entities}
    assert set(trails) == {f"{n}/{k}" for n in centres for k in ("trail", "estimate_trail")}
    for n, path_ned in truth.items():
        pts = entity_points(trails[f"{n}/trail"], frames)
        assert len(pts) >= 50  # ≈ 5 points a second for 12 s
        want = np.array([(e, nn, -d) for nn, e, d in path_ned])  # the path in the ENU world
        # every trail point lies on the flown path, and the trail covers the whole path
        dist = np.linalg.norm(pts[:, None, :] - want[None, :, :], axis=2)
        assert dist.min(axis=1).max() < 1e-9
        assert dist.min(axis=0).max() < 0.03
        est = entity_points(trails[f"{n}/estimate_trail"], frames)
        assert len(est) >= 20  # the estimate is 5 cm north of the pose: 5 cm along the world's y
        d_est = np.linalg.norm((est - (0.0, 0.05, 0.0))[:, None, :] - want[None, :, :], axis=2)
        assert d_est.min(axis=1).max() < 1e-9
        assert np.allclose(frames.to_root(n, (0, 0, 0)), want[-1])  # the body frame: its last tracked pose

    # setpoints: a sphere at the commanded position, alive for the lease
    sps = {e.id: e for e in dec.last("/arena/scene/setpoints").entities}
    assert set(sps) == {"d1/setpoint", "d2/setpoint", "d3/setpoint"}
    s1 = sps["d1/setpoint"]
    sphere = s1.spheres[0].pose.position
    assert np.allclose(frames.to_root("arena_ned", (sphere.x, sphere.y, sphere.z)), (-1.0, -1.0, 1.0))
    assert 0 < s1.lifetime.seconds + s1.lifetime.nanos / 1e9 <= 0.5

    # vehicles: a body frame-locked to each vehicle, an estimate ghost, labels with mode and battery
    vehicles = {e.id: e for e in dec.last("/arena/scene/vehicles").entities}
    assert set(vehicles) == {"d1", "d2", "d3", "d1/estimate", "d2/estimate", "d3/estimate"}
    assert vehicles["d1"].frame_id == "d1" and vehicles["d1"].frame_locked
    assert vehicles["d1"].texts[0].text == "d1 · OFFBOARD · armed · 50%"
    assert vehicles["d3"].texts[0].text.endswith("LOST")

    logs = [m for _, _, m in dec.topics["/arena/log"]]
    assert len(logs) == 1 and logs[0].name == "d2" and logs[0].message == "[failsafe] battery low"
    assert logs[0].level == 3  # WARNING

    # the arena's own channels are all there too, and the tools read past the scene's topics
    counts = recording.info(path).counts_by_key()
    assert counts[keys.pose("d1")] == 1200 and not any(k.startswith("/") for k in counts)
    series, _ = recording.load_series(path)
    assert set(series) == {keys.pose(n) for n in centres} | {keys.state(n) for n in centres} | {
        keys.setpoint(n) for n in centres
    } | {keys.events("d2")}


def test_static_scene_repeats_every_second_and_tf_rate_is_limited(tmp_path: Path) -> None:
    """So that a viewer that joins late, or a seek, finds the room and the world frame within a second."""
    path = tmp_path / "rate.mcap"
    samples = [
        _sample(
            keys.pose("d1"),
            wire.Pose(t=T0 + i * 5_000_000, p=(0.0, 0.0, -1.0), q=(1.0, 0, 0, 0), ok=True),
            T0 + i * 5_000_000,
        )
        for i in range(1000)  # 200 Hz for 5 s
    ]
    _write(path, samples)
    dec = read_foxglove(path)
    rooms = [lt for lt, _, _ in dec.topics["/arena/scene/room"]]
    assert len(rooms) == 5 and all(0.99e9 <= b - a <= 1.01e9 for a, b in itertools.pairwise(rooms))
    assert len(dec.topics["/arena/tf"]) == 5
    n_tf = len(dec.topics["/arena/d1/tf"])
    assert 150 <= n_tf <= 301  # at most 60 Hz (and not far below) of a 200 Hz pose


@pytest.mark.parametrize("encoding", ["json", "msgpack"])
def test_replay_export_and_repair_leave_the_scene_alone(tmp_path: Path, encoding: str) -> None:
    path = tmp_path / "r.mcap"
    w = RecordingWriter(path, encoding=encoding, scene=Scene(ARENA))
    for i in range(50):
        t = T0 + i * 20_000_000
        w.record(
            _sample(keys.pose("d1"), wire.Pose(t=t, p=(0.01 * i, 0.0, -1.0), q=(1.0, 0, 0, 0), ok=True), t)
        )
    w.close()
    sent: list[str] = []
    rep = recording.replay(path, lambda k, d, e: sent.append(k), speed=1000.0)
    assert rep.sent == 50 and set(sent) == {keys.pose("d1")}
    tables = recording.export(path, tmp_path / "x")
    assert [p.name for p in tables] == ["arena.d1.pose.csv"]
    fixed = recording.repair(path, tmp_path / "fixed.mcap")
    assert read_foxglove(fixed.output).topics.keys() == read_foxglove(path).topics.keys()
    text = recording.format_info(recording.info(path))
    assert "3D scene:" in text and "/arena/scene/room" in text


def test_the_foxglove_layout_names_only_what_recordings_hold(tmp_path: Path) -> None:
    """Every topic of deploy/foxglove/arena.json's 3D panel is a scene topic the recordings have, every
    plotted path a field of the payload its key carries."""
    layout = json.loads((REPO / "deploy" / "foxglove" / "arena.json").read_text())
    cfg = layout["configById"]
    names = ("d1", "d2", "d3")
    path = tmp_path / "l.mcap"
    samples = []
    for n in names:
        samples.append(
            _sample(keys.pose(n), wire.Pose(t=T0, p=(0.0, 0.0, -1.0), q=(1.0, 0, 0, 0), ok=True), T0)
        )
        st = wire.State(t=T0, p=(0.0, 0.0, -1.0), q=(1.0, 0, 0, 0), link=True)
        samples.append(_sample(keys.state(n), st, T0))
        samples.append(_sample(keys.setpoint(n), wire.Setpoint(t=T0, p=(0.0, 0.0, -1.0)), T0))
    _write(path, samples)
    topics = set(read_foxglove(path).topics)
    three_d = cfg["3D!arena"]
    assert three_d["followTf"] == "world" and set(three_d["topics"]) <= topics
    assert {"/arena/scene/room", "/arena/scene/trails", "/arena/d1/tf"} <= set(three_d["topics"])
    assert cfg["Log!events"]["topicToRender"] == "/arena/log"
    plotted = [p["value"] for k, c in cfg.items() if k.startswith("Plot!") for p in c["paths"]]
    assert len(plotted) == 3 * (9 + 2)
    for value in plotted:
        key, _, field_path = value.partition(".")
        cls = wire.type_for_key(key)
        field_name = field_path.split("[")[0]
        assert field_name in cls._by_wire, value
    tabs = [t["title"] for t in cfg["Tab!vehicles"]["tabs"]]
    assert tabs == list(names)
