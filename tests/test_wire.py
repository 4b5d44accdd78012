import dataclasses
import math

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena_common.core import wire
from arena_common.core.errors import PayloadError

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


# -- the Struct encoding is msgpack's own: same bytes as msgpack-python packing the same map ----------------

_FLOATS = st.floats(allow_nan=True, allow_infinity=True)
_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | _FLOATS
    | st.text(max_size=40)
    | st.binary(max_size=4),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=8,
)


def _field_values(spec: wire.Spec) -> st.SearchStrategy[object]:
    return {
        "int": st.integers(-(2**63) + 1, 2**63 - 1),
        "float": _FLOATS,
        "bool": st.booleans(),
        "str": st.sampled_from(spec.choices) if spec.choices else st.text(max_size=300),
        "vec3": st.tuples(_FLOATS, _FLOATS, _FLOATS),
        "quat": st.tuples(_FLOATS, _FLOATS, _FLOATS, _FLOATS),
        "strs": st.lists(st.text(max_size=5), max_size=4).map(tuple),
        "map": st.dictionaries(st.text(max_size=8), _VALUES, max_size=5),
    }[spec.kind]


@st.composite
def any_payload(draw: st.DrawFn) -> wire.Payload:
    cls = draw(st.sampled_from(sorted(wire.REGISTRY.values(), key=lambda c: c.SCHEMA)))
    kwargs: dict[str, object] = {}
    for name, spec in cls._specs:
        if spec.required or draw(st.booleans()):
            kwargs[name] = None if spec.optional and draw(st.booleans()) else draw(_field_values(spec))
    return cls(**kwargs)


@settings(max_examples=500, deadline=None)
@given(any_payload())
def test_encode_is_what_msgpack_packs_for_the_wire_map(p: wire.Payload) -> None:
    raw = p.encode()
    assert raw == msgpack.packb(p.to_dict(), use_bin_type=True)  # smallest headers, float64, str not bin
    wire_map = msgpack.unpackb(raw)
    assert list(wire_map) == [s.wire for name, s in p._specs if not (s.optional and getattr(p, name) is None)]


def test_defaults_travel_and_unknown_optional_fields_are_omitted() -> None:
    state = wire.State(t=1)
    raw = state.encode()
    assert raw[0] == 0x80 | 12  # a fixmap: 12 of State's 21 fields (map16 only from 16 fields on)
    assert msgpack.unpackb(raw) == {
        "t": 1,
        "sysid": 0,
        "link": False,
        "armed": False,
        "mode": "UNKNOWN",
        "landed": "undefined",
        "vis_rate": 0.0,
        "vis_fused": False,
        "ofb": False,
        "setup_ok": False,
        "fs": [],
        "tp": 0,
    }
    assert wire.State.decode(raw) == state
    assert msgpack.unpackb(wire.Setpoint(t=1, v=(0.0, 0.0, 0.0)).encode()) == {
        "t": 1,
        "lease": 0.5,
        "v": [0.0, 0.0, 0.0],
        "src": "",
    }


def test_numpy_floats_encode_as_floats() -> None:
    np = pytest.importorskip("numpy")
    pose = wire.Pose(t=1, p=tuple(np.array([1.0, 2.0, 3.0])), q=(1.0, 0.0, 0.0, 0.0), ok=True)
    assert pose.encode() == POSE.replace(t=1, fn=0, p=(1.0, 2.0, 3.0)).encode()
    with pytest.raises(TypeError, match="can not serialize"):
        wire.Telemetry(t=1, msg="X", f={"x": object()}).encode()


def test_rules_run_on_decode_not_on_construction() -> None:
    bad = wire.Pose(t=1, p=(0.0, 0.0, 0.0), q=(2.0, 0.0, 0.0, 0.0), ok=True)  # a test may build one
    with pytest.raises(PayloadError, match=r"norm 2.0000 is not 1.*field=q"):
        wire.Pose.decode(bad.encode())
    assert bad.check() == ("q", "quaternion norm 2.0000 is not 1")
    assert wire.Pose.decode(bad.replace(ok=False).encode()).q == (2.0, 0.0, 0.0, 0.0)  # untracked: anything


def test_nan_where_allowed_nil_reads_as_nan_and_infinity_is_refused() -> None:
    m = wire.MocapPose(t=1, fn=1, id=1, p=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), ok=True).to_dict()
    assert math.isnan(wire.MocapPose.decode(msgpack.packb(m)).err)
    assert math.isnan(wire.MocapPose.decode(msgpack.packb(m | {"err": None})).err)  # JSON has no NaN
    with pytest.raises(PayloadError, match=r"not a finite number: inf.*field=err"):
        wire.MocapPose.decode(msgpack.packb(m | {"err": math.inf}))
    with pytest.raises(PayloadError, match=r"not a finite number: nan.*field=mts"):
        wire.MocapPose.decode(msgpack.packb(m | {"mts": math.nan}))


@pytest.mark.parametrize(
    ("mutation", "field", "reason"),
    [
        ({"t": None}, "t", "must not be nil"),
        ({"t": 1.5}, "t", "expected an integer"),
        ({"t": 2**64 - 1}, "t", "integer out of range"),
        ({"fn": -1}, "fn", "-1 outside [0, None]"),
        ({"p": "x"}, "p", "expected an array of 3 numbers"),
        ({"p": [0.0, "x", 0.0]}, "p", "expected a number, got str"),
        ({"p": [0.0, -math.inf, 0.0]}, "p", "not a finite number: -inf"),
        ({"tsrc": "guess"}, "tsrc", "'guess' not one of echo, latency, arrival, sim"),
        ({"name": "x" * 4097}, "name", "string longer than 4096"),
        ({"name": b"cf1"}, "name", "expected a string, got bytes"),
    ],
)
def test_mocap_pose_errors_say_what_is_wrong(mutation: dict, field: str, reason: str) -> None:
    m = wire.MocapPose(t=1, fn=1, id=1, p=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), ok=True).to_dict()
    with pytest.raises(PayloadError) as err:
        wire.MocapPose.decode(msgpack.packb(m | mutation, use_bin_type=True), "arena/d1/mocap")
    assert err.value.field == field and str(err.value).startswith(reason), str(err.value)


@pytest.mark.parametrize(
    ("mutation", "field", "reason"),
    [
        ({"fs": ["a"] * 257}, "fs", "more than 256 strings"),
        ({"fs": ["a", 1]}, "fs", "expected an array of strings"),
        ({"bat": 1.5}, "bat", "1.5 outside [0.0, 1.0]"),
        ({"q": [2.0, 0.0, 0.0, 0.0]}, "q", "quaternion norm"),
        ({"landed": "flying"}, "landed", "'flying' not one of"),
    ],
)
def test_state_errors_say_what_is_wrong(mutation: dict, field: str, reason: str) -> None:
    with pytest.raises(PayloadError) as err:
        wire.State.decode(msgpack.packb({"t": 1} | mutation))
    assert err.value.field == field and str(err.value).startswith(reason), str(err.value)


def test_maps_need_string_keys() -> None:
    with pytest.raises(PayloadError, match=r"expected a map with string keys.*field=f"):
        wire.Telemetry.decode(msgpack.packb({"t": 1, "msg": "X", "f": {1: 2}}))
    with pytest.raises(PayloadError, match="expected a map with string keys"):
        wire.Telemetry.decode(msgpack.packb({"t": 1, "msg": "X", 7: 2}))


def test_specs_come_from_the_struct_annotations() -> None:
    specs = dict(wire.State._specs)
    assert specs["t"] == wire.Spec("t", "int", "Time of this snapshot", unit="ns", required=True)
    assert specs["bat"] == wire.Spec("bat", "float", "Battery remaining, 0–1", lo=0.0, hi=1.0, optional=True)
    assert specs["landed"].choices == ("undefined", "on_ground", "in_air", "takeoff", "landing")
    assert dict(wire.MocapPose._specs)["err"].nan_ok
    assert wire.default_of(wire.State, "mode") == "UNKNOWN"
    assert wire.default_of(wire.State, "fs") == ()
    assert wire.default_of(wire.State, "p") is None
    assert wire.default_of(wire.State, "t") is dataclasses.MISSING
