import dataclasses
import math
from typing import Annotated

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena_common.core import wire
from arena_common.core.errors import PayloadError
from arena_common.core.payload import _doc, _int

POSE = wire.Pose(t=1_700_000_000_000_000_000, p=(1.0, -2.0, -0.5), q=(1.0, 0.0, 0.0, 0.0), ok=True, fn=7)
BODY = wire.MocapBody(
    v="d1", id=1, p=(0.5, 1.2, -0.75), q=(1.0, 0.0, 0.0, 0.0), ok=True, name="cf1", err=2e-4
)
FRAME = wire.MocapFrame(
    t=1_700_000_000_000_000_000,
    fn=42,
    b=(BODY, wire.MocapBody(v="d2", id=2, p=(0.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 0.0), ok=False)),
    lat=4_000_000,
    tsrc="echo",
)


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
        FRAME.replace(b=(BODY,)),
        FRAME.replace(b=()),
    ]
    for p in samples:
        assert type(p).decode(p.encode()) == p
        assert wire.decode_any("", p.encode(), p.encoding()) == p
    assert wire.decode_any("arena/sys/frames", FRAME.encode()).encode() == FRAME.encode()  # err NaN != NaN


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


# Any value a msgpack map may hold for a field, right or wrong.
ANY_VALUE = st.one_of(
    st.none(),
    st.integers(-(2**63), 2**64 - 1),
    st.floats(),
    st.text(max_size=3),
    st.booleans(),
    st.lists(st.floats(), max_size=5),
)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.sampled_from(["t", "p", "q", "ok", "v", "fn", "rc", "zz"]), ANY_VALUE, max_size=8))
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
    if spec.kind == "items":
        assert spec.item is not None
        return st.lists(_instances(spec.item), max_size=4).map(tuple)
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
def _instances(draw: st.DrawFn, cls: type[wire.Payload]) -> wire.Payload:
    """Any instance of ``cls`` (``items`` elements included), valid or not: every field of its kind."""
    kwargs: dict[str, object] = {}
    for name, spec in cls._specs:
        if spec.required or draw(st.booleans()):
            kwargs[name] = None if spec.optional and draw(st.booleans()) else draw(_field_values(spec))
    return cls(**kwargs)


def any_payload() -> st.SearchStrategy[wire.Payload]:
    types = sorted(wire.REGISTRY.values(), key=lambda c: c.SCHEMA)
    return st.sampled_from(types).flatmap(_instances)


def _wire_names(p: wire.Payload) -> list[str]:
    return [s.wire for name, s in p._specs if not (s.optional and getattr(p, name) is None)]


@settings(max_examples=500, deadline=None)
@given(any_payload())
def test_encode_is_what_msgpack_packs_for_the_wire_map(p: wire.Payload) -> None:
    raw = p.encode()
    assert raw == msgpack.packb(p.to_dict(), use_bin_type=True)  # smallest headers, float64, str not bin
    wire_map = msgpack.unpackb(raw)
    assert list(wire_map) == _wire_names(p)
    for name, spec in p._specs:
        if spec.kind == "items":  # every element is a whole map of its own type's fields
            assert [list(e) for e in wire_map[spec.wire]] == [_wire_names(e) for e in getattr(p, name)]


def test_the_strategies_know_every_kind() -> None:
    specs = [spec for cls in wire.REGISTRY.values() for _, spec in cls._specs]
    specs += [spec for s in specs if s.item is not None for _, spec in s.item._specs]
    assert {s.kind for s in specs} == {"int", "float", "bool", "str", "vec3", "quat", "strs", "map", "items"}
    for spec in specs:
        _field_values(spec)  # no KeyError: any_payload draws every field of every type


# -- MocapFrame: an array of MocapBody maps (kind ``items``) -------------------------------------------------

_FINITE = st.floats(-1e6, 1e6, allow_nan=False)
_NAMES = st.from_regex(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,62}", fullmatch=True).filter(
    lambda n: n not in ("sys", "estop")
)


@st.composite
def _unit_quats(draw: st.DrawFn) -> tuple[float, float, float, float]:
    q = draw(st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 4).filter(lambda q: math.hypot(*q) > 0.1))
    n = math.hypot(*q)
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@st.composite
def valid_bodies(draw: st.DrawFn) -> wire.MocapBody:
    ok = draw(st.booleans())
    return wire.MocapBody(
        v=draw(_NAMES),
        id=draw(st.integers(-(2**63) + 1, 2**63 - 1)),
        p=draw(st.tuples(_FINITE, _FINITE, _FINITE)),
        q=draw(_unit_quats() if ok else st.tuples(_FINITE, _FINITE, _FINITE, _FINITE)),
        ok=ok,
        name=draw(st.text(max_size=20)),
        err=draw(st.just(math.nan) | st.floats(0.0, 0.01)),
    )


@st.composite
def valid_frames(draw: st.DrawFn) -> wire.MocapFrame:
    return wire.MocapFrame(
        t=draw(st.integers(-(2**63) + 1, 2**63 - 1)),
        fn=draw(st.integers(0, 2**63 - 1)),
        b=tuple(draw(st.lists(valid_bodies(), max_size=6))),
        lat=draw(st.integers(-1, 10**9)),
        mts=draw(_FINITE),
        tsrc=draw(st.sampled_from(("echo", "latency", "arrival", "sim"))),
        tp=draw(st.integers(0, 2**63 - 1)),
    )


@settings(max_examples=300, deadline=None)
@given(valid_frames())
def test_valid_frames_round_trip_byte_exact(frame: wire.MocapFrame) -> None:
    raw = frame.encode()
    back = wire.decode_any("arena/sys/frames", raw, frame.encoding())
    assert type(back) is wire.MocapFrame and back.encode() == raw  # bytes, not ==: an unknown err is NaN
    assert len(back.b) == len(frame.b) and all(type(e) is wire.MocapBody for e in back.b)
    m = frame.to_dict()
    assert wire.MocapFrame.from_dict(m).encode() == raw
    assert [list(e) for e in m["b"]] == [["v", "id", "p", "q", "ok", "name", "err"]] * len(frame.b)
    # The JSON rendering (NaN as null) holds each element's own rendering and reads back as the same frame.
    jsonable = wire.to_jsonable(frame)
    assert jsonable["b"] == [wire.to_jsonable(b) for b in frame.b]
    assert all((e["err"] is None) == math.isnan(b.err) for e, b in zip(jsonable["b"], frame.b, strict=True))
    assert wire.MocapFrame.from_dict(jsonable).encode() == raw
    for body in frame.b:
        pose = frame.pose(body)
        assert wire.MocapPose.decode(pose.encode()).encode() == pose.encode()


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.dictionaries(
                st.sampled_from(["v", "id", "p", "q", "ok", "name", "err", "zz"]), ANY_VALUE, max_size=8
            ),
            st.integers(-(2**63), 2**64 - 1),
            st.text(max_size=3),
        ),
        max_size=3,
    )
)
def test_random_elements_only_raise_payload_error_naming_the_element(elements: list) -> None:
    data = FRAME.to_dict() | {"b": elements}
    try:
        frame = wire.MocapFrame.decode(msgpack.packb(data))
    except PayloadError as err:
        assert err.field and err.field.startswith("b["), err
        return
    for body in frame.b:
        assert all(math.isfinite(x) for x in body.p) and not math.isinf(body.err)


def test_defaults_travel_and_unknown_optional_fields_are_omitted() -> None:
    state = wire.State(t=1)
    raw = state.encode()
    assert raw[0] == 0x80 | 14  # a fixmap: 14 of State's 24 fields (map16 only from 16 fields on)
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
        "auth": "",
        "stamps": "",
    }
    assert wire.State.decode(raw) == state
    assert msgpack.unpackb(wire.Setpoint(t=1, v=(0.0, 0.0, 0.0)).encode()) == {
        "t": 1,
        "lease": 0.5,
        "v": [0.0, 0.0, 0.0],
        "src": "",
        "stream": "",
        "seq": 0,
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


def _frame_map(**body_changes: object) -> dict:
    m = FRAME.to_dict()
    m["b"][1] |= body_changes
    return m


@pytest.mark.parametrize(
    ("data", "field", "reason"),
    [
        (_frame_map(p=[0.0, "x", 0.0]), "b[1].p", "expected a number, got str"),
        (_frame_map(p=[0.0, 0.0]), "b[1].p", "expected an array of 3 numbers"),
        (_frame_map(p=[0.0, math.inf, 0.0]), "b[1].p", "not a finite number: inf"),
        (_frame_map(p=None), "b[1].p", "must not be nil"),
        (_frame_map(ok=True), "b[1].q", "quaternion norm 0.0000 is not 1"),  # tracked: q must be a rotation
        (_frame_map(ok=True, q=[2.0, 0.0, 0.0, 0.0]), "b[1].q", "quaternion norm 2.0000 is not 1"),
        (_frame_map(v="a b"), "b[1].v", "invalid vehicle name 'a b'"),
        (_frame_map(v="sys"), "b[1].v", "invalid vehicle name 'sys': reserved"),
        (_frame_map(v=""), "b[1].v", "invalid vehicle name"),
        (_frame_map(v=7), "b[1].v", "expected a string, got int"),
        (_frame_map(id=1.5), "b[1].id", "expected an integer"),
        (_frame_map(id=2**64 - 1), "b[1].id", "integer out of range"),
        (_frame_map(ok=1), "b[1].ok", "expected a boolean, got int"),
        (_frame_map(err=math.inf), "b[1].err", "not a finite number: inf"),
        (_frame_map(name=b"cf2"), "b[1].name", "expected a string, got bytes"),
        (_frame_map(name="x" * 4097), "b[1].name", "string longer than 4096"),
        (
            FRAME.to_dict() | {"b": [{k: v for k, v in BODY.to_dict().items() if k != "q"}]},
            "b[0].q",
            "missing",
        ),
        (FRAME.to_dict() | {"b": [BODY.to_dict(), 5]}, "b[1]", "expected a map, got int"),
        (FRAME.to_dict() | {"b": [[1.0, 2.0]]}, "b[0]", "expected a map, got list"),
        (FRAME.to_dict() | {"b": [{1: 2}]}, "b[0]", "expected a map with string keys"),
        (FRAME.to_dict() | {"b": "x"}, "b", "expected an array of maps, got str"),
        (FRAME.to_dict() | {"b": {"v": "d1"}}, "b", "expected an array of maps, got dict"),
        (FRAME.to_dict() | {"b": None}, "b", "must not be nil"),
        (FRAME.to_dict() | {"b": [BODY.to_dict()] * 257}, "b", "more than 256 elements"),
        ({k: v for k, v in FRAME.to_dict().items() if k != "b"}, "b", "missing field"),
        (FRAME.to_dict() | {"fn": -1}, "fn", "-1 outside [0, None]"),
        (FRAME.to_dict() | {"tsrc": "guess"}, "tsrc", "'guess' not one of"),
    ],
)
def test_mocap_frame_errors_name_the_element_and_field(data: dict, field: str, reason: str) -> None:
    raw = msgpack.packb(data, use_bin_type=True)
    with pytest.raises(PayloadError) as err:
        wire.MocapFrame.decode(raw, "arena/sys/frames")
    assert err.value.field == field and str(err.value).startswith(reason), str(err.value)
    assert "key=arena/sys/frames" in str(err.value) and "type=MocapFrame" in str(err.value)
    with pytest.raises(PayloadError) as err:  # the same from a map (JSON, MCAP tools)
        wire.MocapFrame.from_dict(data)
    assert err.value.field == field and str(err.value).startswith(reason), str(err.value)


def test_mocap_frame_limits_and_unknowns() -> None:
    m = FRAME.to_dict()
    full = FRAME.replace(b=(BODY,) * 256)
    assert len(wire.MocapFrame.decode(full.encode()).b) == 256
    assert wire.MocapFrame.decode(FRAME.replace(b=()).encode()).b == ()
    # Untracked: p and q mean nothing, so anything finite goes.
    assert wire.MocapFrame.decode(msgpack.packb(_frame_map(q=[2.0, 0.0, 0.0, 0.0]))).b[1].q == (2.0, 0, 0, 0)
    # Unknown element keys are ignored, as unknown payload keys are.
    assert wire.MocapFrame.decode(msgpack.packb(_frame_map(zz=1))).encode() == FRAME.encode()
    # nil err (JSON has no NaN) reads as NaN, through decode and from_dict; an omitted err is NaN too.
    nil = _frame_map(err=None)
    assert math.isnan(wire.MocapFrame.decode(msgpack.packb(nil)).b[1].err)
    assert math.isnan(wire.MocapFrame.from_dict(nil).b[1].err)
    assert wire.MocapFrame.from_dict(nil).encode() == FRAME.encode()
    omitted = m | {"b": [m["b"][0], {k: v for k, v in m["b"][1].items() if k not in ("err", "name")}]}
    assert wire.MocapFrame.from_dict(omitted).encode() == FRAME.encode()
    assert wire.MocapFrame.from_dict(wire.to_jsonable(FRAME)).encode() == FRAME.encode()
    assert wire.to_jsonable(FRAME)["b"][1]["err"] is None
    # nil where NaN is not allowed stays an error, inside an element too.
    with pytest.raises(PayloadError, match=r"must not be nil.*field=b\[0\]\.id"):
        wire.MocapFrame.from_dict(m | {"b": [BODY.to_dict() | {"id": None}]})


def test_mocap_frame_pose_is_the_per_vehicle_mocap_pose() -> None:
    pose = FRAME.pose(FRAME.b[0])
    assert pose == wire.MocapPose(
        t=FRAME.t, fn=42, id=1, p=BODY.p, q=BODY.q, ok=True, name="cf1", err=2e-4, lat=4_000_000, tsrc="echo"
    )
    assert wire.MocapPose.decode(pose.encode(), "arena/d1/mocap") == pose


def test_items_specs_and_parts() -> None:
    spec = dict(wire.MocapFrame._specs)["b"]
    assert (spec.kind, spec.item, spec.max_items, spec.required) == ("items", wire.MocapBody, 256, True)
    assert dict(wire.MocapBody._specs)["err"].nan_ok
    assert "MocapBody" not in wire.REGISTRY and wire.REGISTRY["MocapFrame"] is wire.MocapFrame
    assert wire.type_for_key("arena/sys/frames") is wire.MocapFrame
    assert wire.type_for_encoding(wire.MocapFrame.encoding()) is wire.MocapFrame
    with pytest.raises(PayloadError, match="unknown schema"):
        wire.type_for_encoding("application/msgpack;arena.MocapBody/1")  # a part travels only inside

    class Loose(wire.Payload, frozen=True):  # an element type declared without @part
        x: Annotated[int, _int("x")]

    class Holder(wire.Payload, frozen=True):
        SCHEMA = "Holder"
        xs: Annotated[tuple[Loose, ...], _doc("xs")]

    with pytest.raises(TypeError, match="declare Loose with @part"):
        wire.part(Holder)


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
