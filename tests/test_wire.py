import math

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena_common import wire
from arena_common.errors import PayloadError

POSE = wire.Pose(t=1_700_000_000_000_000_000, p=(1.0, -2.0, -0.5), q=(1.0, 0.0, 0.0, 0.0), ok=True, fn=7)


def test_round_trip_every_type() -> None:
    samples: list[wire.Payload] = [
        POSE,
        wire.MocapPose(
            t=5, fn=1, id=2, p=(0.1, 1.4, -0.7), q=(0.86, -0.05, 0.51, 0.04 - 0.0009), ok=False, err=0.0005
        ),
        wire.State(t=1, armed=True, mode="OFFBOARD", landed="in_air", p=(0.0, 0.0, -1.0), bat=0.8, fs=("x",)),
        wire.Telemetry(t=1, msg="HEARTBEAT", f={"custom_mode": 1}),
        wire.Event(t=1, kind="statustext", text="hello", sev=4),
        wire.Command(op="takeoff", args={"height": 1.0}),
        wire.CommandResult(ok=True, result="ACCEPTED"),
        wire.Setpoint(t=1, p=(0.0, 0.0, -1.0), yaw=0.0),
        wire.Estop(t=1, kill=True),
        wire.Stats(t=1, service="s", host="h", counts={"in": 3}),
    ]
    for p in samples:
        assert type(p).decode(p.encode()) == p
        assert wire.decode_any("", p.encode(), p.encoding()) == p


def test_encoding_names_schema_and_version() -> None:
    assert wire.Pose.encoding() == "application/msgpack;arena.Pose/1"
    assert wire.type_for_encoding("application/msgpack;arena.State/1") is wire.State
    with pytest.raises(PayloadError, match="version '9' not supported"):
        wire.type_for_encoding("application/msgpack;arena.State/9")


def test_decode_by_key_when_encoding_is_absent() -> None:
    assert wire.decode_any("arena/d1/vision", POSE.encode()) == POSE


@pytest.mark.parametrize(
    ("mutation", "field", "reason"),
    [
        ({"t": "now"}, "field=t", "expected a number"),
        ({"p": [1.0, 2.0]}, "field=p", "array of 3"),
        ({"p": [1.0, math.nan, 0.0]}, "field=p", "not a finite"),
        ({"q": [2.0, 0.0, 0.0, 0.0]}, "field=q", "norm"),
        ({"ok": 1}, "field=ok", "boolean"),
        ({"rc": 300}, "field=rc", "outside"),
    ],
)
def test_bad_fields_name_key_type_and_field(mutation: dict, field: str, reason: str) -> None:
    data = POSE.to_dict() | mutation
    with pytest.raises(PayloadError) as err:
        wire.Pose.decode(msgpack.packb(data), "arena/d1/pose")
    text = str(err.value)
    assert "key=arena/d1/pose" in text and "type=Pose" in text and field in text and reason in text


def test_missing_field_and_not_msgpack() -> None:
    with pytest.raises(PayloadError, match=r"missing field.*field=q"):
        wire.Pose.decode(msgpack.packb({"t": 1, "p": [0, 0, 0], "ok": True}))
    with pytest.raises(PayloadError, match="not valid msgpack"):
        wire.Pose.decode(b"\xc1\xc1")
    with pytest.raises(PayloadError, match="expected a map"):
        wire.Pose.decode(msgpack.packb([1, 2]))


def test_setpoint_rules() -> None:
    with pytest.raises(PayloadError, match="needs a position"):
        wire.Setpoint.decode(msgpack.packb({"t": 1}))
    with pytest.raises(PayloadError, match="field=lease"):
        wire.Setpoint.decode(msgpack.packb({"t": 1, "p": [0, 0, -1], "lease": 60.0}))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_random_bytes_only_raise_payload_error(data: bytes) -> None:
    for cls in wire.REGISTRY.values():
        try:
            cls.decode(data, "arena/d1/x")
        except PayloadError:
            pass


@settings(max_examples=300, deadline=None)
@given(
    st.dictionaries(
        st.sampled_from(["t", "p", "q", "ok", "v", "fn", "rc", "zz"]),
        st.one_of(
            st.none(),
            st.integers(-(2**63), 2**64 - 1),
            st.floats(),
            st.text(max_size=3),
            st.booleans(),
            st.lists(st.floats(), max_size=5),
        ),
        max_size=8,
    )
)
def test_random_maps_only_raise_payload_error(data: dict) -> None:
    try:
        p = wire.Pose.decode(msgpack.packb(data))
    except PayloadError:
        return
    assert all(math.isfinite(x) for x in p.p)
