"""``arena export --ros2``: a recording as a ROS 2 MCAP (``ros2msg`` schemas, ``cdr`` messages), read back
with an independent reader: ``mcap`` + ``mcap-ros2-support``'s decoder (not rosbags)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from typer.testing import CliRunner

from arena_common.cli import app
from arena_common.core import keys, wire
from arena_common.core.config import RecorderSpec
from arena_common.recording.mcap import Recorder, Sample

T0 = 1_700_000_000_123_456_789


def _recording(tmp_path: Path) -> Path:
    rec = Recorder(RecorderSpec(min_free_mb=0.0, encoding="msgpack"), "h1", directory=tmp_path / "rec")
    path = rec.start("flight")
    assert path is not None
    for i in range(3):
        p = wire.Pose(t=T0 + i * 10_000_000, p=(1.25, -0.5, -1.0 - 0.1 * i), q=(1.0, 0.0, 0.0, 0.0), ok=True)
        rec.write(Sample(keys.pose("d1"), p.encode(), p.encoding(), p.t))
    v = wire.Pose(t=T0, p=(1.25, -0.5, -1.0), q=(1.0, 0.0, 0.0, 0.0), ok=True, v=(0.2, 0.0, 0.0), vok=True)
    rec.write(Sample(keys.vision("d1"), v.encode(), v.encoding(), v.t))
    s = wire.State(t=T0, link=True, volt=11.7, bat=0.5)
    rec.write(Sample(keys.state("d1"), s.encode(), s.encoding(), s.t))
    e = wire.Event(t=T0, kind="failsafe", text="battery low", sev=4)
    rec.write(Sample(keys.events("d1"), e.encode(), e.encoding(), e.t))
    rec.close()
    return rec.files[0]


def test_export_ros2_mcap_reads_back_with_an_independent_decoder(tmp_path: Path) -> None:
    src = _recording(tmp_path)
    result = CliRunner().invoke(app, ["export", str(src), "--ros2", "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    target = tmp_path / "out" / f"{src.stem}.ros2.mcap"
    assert str(target) in result.output
    with open(target, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        assert header.profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
        assert schemas["geometry_msgs/msg/PoseStamped"] == "ros2msg"
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        got: dict[str, list[object]] = {}
        for _schema, channel, _message, msg in reader.iter_decoded_messages():
            got.setdefault(channel.topic, []).append(msg)
    assert set(got) == {
        "/tf_static",
        "/arena/d1/pose",
        "/tf",
        "/arena/d1/odom",
        "/arena/d1/battery",
        "/diagnostics",
        "/rosout",
    }
    poses = got["/arena/d1/pose"]
    assert len(poses) == 3
    p0: object = poses[0]
    assert (p0.pose.position.x, p0.pose.position.y, p0.pose.position.z) == (-0.5, 1.25, 1.0)  # type: ignore[attr-defined]
    assert p0.header.stamp.sec == 1_700_000_000 and p0.header.stamp.nanosec == 123_456_789  # type: ignore[attr-defined]
    assert poses[2].pose.position.z == pytest.approx(1.2)  # type: ignore[attr-defined]
    odom: object = got["/arena/d1/odom"][0]
    assert odom.twist.twist.linear.x == pytest.approx(0.2)  # type: ignore[attr-defined]
    bat: object = got["/arena/d1/battery"][0]
    assert bat.voltage == pytest.approx(11.7) and math.isnan(bat.current)  # type: ignore[attr-defined]
    log: object = got["/rosout"][0]
    assert log.msg == "battery low" and log.level == 30  # type: ignore[attr-defined]
    assert got["/tf_static"][0].transforms[0].child_frame_id == "arena_ned"  # type: ignore[attr-defined]
