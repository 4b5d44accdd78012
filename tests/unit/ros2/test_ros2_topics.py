"""The one table of ROS 2 topics (arena_common/ros2/topics.py) against everything that repeats it: the
bridge's declared publishers and subscriptions (on a real router), its arena subscriptions, the bag
export's channels, docs/ros2.md's generated table; and the bridge's typed reader on bad arena samples."""

from __future__ import annotations

import math
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.reader import make_reader

from arena_common.bus.session import Bus
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig, RecorderSpec
from arena_common.recording.mcap import Recorder, Sample
from arena_common.ros2 import messages, types
from arena_common.ros2.bridge import Bridge, BridgeOptions
from arena_common.ros2.export import export_ros2
from arena_common.ros2.node import RosPublisher
from arena_common.ros2.topics import TOPICS, Direction, endpoints, rows, sources
from tests.helpers import REPO
from tests.ros2_samples import SAMPLES, T0, sample
from tools import rosdoc


# -- the table itself --------------------------------------------------------------------------------------
def test_every_row_names_a_real_key_type_and_conversion() -> None:
    specs = {k.pattern: k for k in keys.KEYS}
    names = [t.name for t in TOPICS]
    assert len(names) == len(set(names)), "a topic twice"
    for row in TOPICS:
        types.msg_type(row.msg_type)  # a type the store knows, with its hash
        if row.arena_key is not None:
            assert row.arena_key in specs, f"{row.name}: {row.arena_key} is not in the key table"
        if row.direction == Direction.OUT:
            if row.payload is not None:
                assert specs[row.arena_key or ""].payload == row.payload.__name__, row.name
            msg = row.convert("d1", sample(row), "arena_bridge")
            assert msg.__msgtype__ == row.msg_type, row.name
            types.deserialize(types.serialize(msg, row.msg_type), row.msg_type)
        else:
            assert row.per_vehicle and row.key is not None and row.payload is None, row.name
            assert row.convert in (messages.goto, messages.velocity), row.name  # tested below
    # every key the bridge reads carries one payload type
    for key, out in sources().items():
        assert len({r.payload for r in out}) == 1, key


def test_goto_and_twist_conversions() -> None:
    goto_row = next(r for r in rows(Direction.IN) if r.leaf == "goto")
    twist_row = next(r for r in rows(Direction.IN) if r.leaf == "cmd_vel")
    cls = types.cls
    yaw90 = cls("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=math.sqrt(0.5), w=math.sqrt(0.5))

    def pose(frame: str, x: float, y: float, z: float, q: object) -> object:
        header = types.header(0, frame)
        point = cls("geometry_msgs/msg/Point")(x=x, y=y, z=z)
        return cls(types.POSE_STAMPED)(
            header=header, pose=cls("geometry_msgs/msg/Pose")(position=point, orientation=q)
        )

    zero = cls("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=0.0)
    g = goto_row.convert(pose("map", 0.5, 0.3, 1.2, yaw90))  # docs/ros2.md's worked example
    assert g.p == pytest.approx((0.3, 0.5, -1.2)) and g.yaw == pytest.approx(0.0, abs=1e-12)
    g = goto_row.convert(pose("", 0.5, 0.3, 1.2, zero))  # empty frame: map; all-zero: keep the heading
    assert g.p == pytest.approx((0.3, 0.5, -1.2)) and g.yaw is None
    g = goto_row.convert(pose("arena_ned", 0.3, 0.5, -1.2, yaw90))  # NED as it is; yaw 90° = east
    assert g.p == (0.3, 0.5, -1.2) and g.yaw == pytest.approx(math.pi / 2)
    with pytest.raises(messages.RosInputError, match="frame 'odom' unknown"):
        goto_row.convert(pose("odom", 0.0, 0.0, 1.0, zero))
    with pytest.raises(messages.RosInputError, match="not finite"):
        goto_row.convert(pose("map", math.nan, 0.0, 1.0, zero))
    v3 = cls("geometry_msgs/msg/Vector3")
    v = twist_row.convert(cls(types.TWIST)(linear=v3(x=0.3, y=0.2, z=0.1), angular=v3(x=0.0, y=0.0, z=0.4)))
    assert v.body == (0.3, -0.2, -0.1) and v.yaw_rate == -0.4  # FLU → FRD, counter-clockwise → clockwise
    with pytest.raises(messages.RosInputError, match="velocity not finite"):
        twist_row.convert(
            cls(types.TWIST)(linear=v3(x=math.inf, y=0.0, z=0.0), angular=v3(x=0.0, y=0.0, z=0.0))
        )


# -- docs/ros2.md ------------------------------------------------------------------------------------------
def test_doc_table_is_the_generated_one_and_check_catches_drift(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert rosdoc.drift(REPO) == [], "docs/ros2.md's topic table drifts: run `python -m tools.rosdoc`"
    doc = tmp_path / rosdoc.DOC
    doc.parent.mkdir(parents=True)
    shutil.copy(REPO / rosdoc.DOC, doc)
    for row in TOPICS:
        assert f"| `{row.name}` | {row.direction.value} | {row.msg_type} |" in doc.read_text()
    doc.write_text(doc.read_text().replace("best effort, volatile, 5", "reliable, volatile, 5", 1))
    assert rosdoc.main(["--check", "--root", str(tmp_path)]) == 1
    assert "drifts from arena_common/ros2/topics.py" in capsys.readouterr().err
    assert rosdoc.main(["--root", str(tmp_path)]) == 0
    assert rosdoc.drift(tmp_path) == [] and doc.read_text() == (REPO / rosdoc.DOC).read_text()
    doc.write_text("# no table\n")
    assert rosdoc.drift(tmp_path) == [f"{rosdoc.DOC}: no topic table between {rosdoc.BEGIN} and {rosdoc.END}"]


# -- the bridge ------------------------------------------------------------------------------------------
def test_bridge_declares_the_table_and_reports_bad_arena_samples(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = arena_config(n_vehicles=2)
    vehicles = tuple(cfg.vehicles)
    rejected: list[tuple[str, str]] = []
    seen = threading.Event()

    def reject(reason: str, detail: str) -> None:
        rejected.append((reason, detail))
        seen.set()

    bridge = Bridge(cfg, bus_factory(), BridgeOptions(commands=True), reject=reject)
    try:
        declared = {
            (e.topic, e.type.name, e.qos, Direction.OUT if isinstance(e, RosPublisher) else Direction.IN)
            for e in bridge.node.entities
        }
        expected = {
            (name, row.msg_type, row.qos, d) for d in Direction for name, row in endpoints(vehicles, d)
        }
        assert declared == expected and len(bridge.node.entities) == len(expected)
        assert "/arena/d2/goto" in {e[0] for e in expected} and "/tf" in {e[0] for e in expected}
        assert {s.keyexpr for s in bridge._subs} == {f"arena/*/{k}" for k in sources() if k is not None}

        # A State on a pose key, and bytes that are no payload: refused by the typed reader, with the key.
        feeder = bus_factory()
        state = SAMPLES[wire.State]
        deadline = time.monotonic() + 10.0
        while len({r for r, _ in rejected}) < 2 and time.monotonic() < deadline:  # until both are routed
            feeder.put(keys.pose("d1"), state)
            feeder.session.put(keys.state("d2"), b"\xc1 not msgpack")
            time.sleep(0.05)
        reasons = {r: d for r, d in rejected}
        assert set(reasons) == {"pose: bad_payload", "state: bad_payload"}, rejected
        assert "key=arena/d1/pose" in reasons["pose: bad_payload"] and "State" in reasons["pose: bad_payload"]
        assert "key=arena/d2/state" in reasons["state: bad_payload"]
        assert all(p.sent == 0 for name, p in bridge.pubs.items() if name != "/tf_static")
    finally:
        bridge.close()


# -- the export --------------------------------------------------------------------------------------------
def test_export_writes_every_published_topic_of_the_table(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rec = Recorder(RecorderSpec(min_free_mb=0.0, encoding="msgpack"), "h1", directory=tmp_path / "rec")
    assert rec.start("flight") is not None
    for key in sources():
        if key is not None:
            p = SAMPLES[sources()[key][0].payload or wire.Payload]
            k = f"arena/d1/{key}"
            rec.write(Sample(k, p.encode(), p.encoding(), T0))
    bad = SAMPLES[wire.Event]
    rec.write(Sample(keys.pose("d1"), bad.encode(), bad.encoding(), T0))  # an Event on a pose key
    rec.close()
    with caplog.at_level("WARNING", logger="arena.ros2.export"):
        target, count = export_ros2(rec.files[0], tmp_path / "out")
    with open(target, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    channels = {(c.topic, summary.schemas[c.schema_id].name) for c in summary.channels.values()}
    assert channels == {(name, row.msg_type) for name, row in endpoints(("d1",), Direction.OUT)}
    assert count == sum(len(out) for out in sources().values())
    assert "arena/d1/pose: 1 sample(s) not exported" in caplog.text, caplog.text
