import pytest

from arena_common.core import keys
from arena_common.core.errors import InvalidName


@pytest.mark.parametrize(
    "bad", ["", "*", "d*1", "a/b", "$x", "#", "x?", "@d1", "a b", "sys", "estop", "x" * 64]
)
def test_invalid_vehicle_names_are_refused(bad: str) -> None:
    with pytest.raises(InvalidName, match="invalid vehicle name"):
        keys.pose(bad)


def test_builders_and_parser_agree() -> None:
    for build, kind in [
        (keys.mocap, "mocap"),
        (keys.pose, "pose"),
        (keys.vision, "vision"),
        (keys.state, "state"),
        (keys.events, "events"),
        (keys.cmd, "cmd"),
        (keys.setpoint, "setpoint"),
        (keys.truth, "truth"),
    ]:
        key = build("drone-1")
        assert key == f"arena/drone-1/{kind}"
        assert keys.parse(key) == keys.ParsedKey(kind, "drone-1")
    assert keys.parse(keys.telemetry("d1", "HEARTBEAT")) == keys.ParsedKey("telemetry", "d1", "HEARTBEAT")
    assert keys.parse(keys.ESTOP).kind == "estop"
    assert keys.parse(keys.alive("ground", "gateway.d1")) == keys.ParsedKey(
        "alive", extra="ground/gateway.d1"
    )
    assert keys.parse(keys.stats("ground", "mocap")).kind == "stats"
    assert keys.FRAMES == "arena/sys/frames"
    assert keys.parse(keys.FRAMES) == keys.ParsedKey("frames")
    assert keys.parse(keys.TIME) == keys.ParsedKey("time")


def test_parse_refuses_unknown_keys() -> None:
    for key in ["other/d1/pose", "arena/d1/nothing", "arena/sys/what", "arena", "arena/sys/frames/d1"]:
        with pytest.raises(InvalidName):
            keys.parse(key)


def test_every_table_row_is_a_known_kind() -> None:
    samples = {"<drone>": "d1", "<msg>": "HEARTBEAT", "<host>": "h", "<service>": "s", "<body>": "b"}
    for spec in keys.KEYS:
        key = spec.pattern
        for k, v in samples.items():
            key = key.replace(k, v)
        keys.parse(key)


def test_the_frames_key_is_in_the_table_once_as_a_stream_of_mocap_frames() -> None:
    rows = [spec for spec in keys.KEYS if spec.pattern == keys.FRAMES]
    assert [(r.payload, r.qos) for r in rows] == [("MocapFrame", "stream")]
