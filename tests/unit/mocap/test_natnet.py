"""Tests of the NatNet codec against real Motive captures, round trips and fuzzing."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import statistics
import struct
from datetime import timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from arena_common.mocap import natnet
from arena_common.mocap.capture import read_frames_jsonl, read_udp
from arena_common.mocap.natnet import (
    Analog,
    Asset,
    AssetDef,
    CameraDef,
    DeviceDef,
    ForcePlateDef,
    Frame,
    LabeledMarker,
    MarkerDef,
    MarkerSet,
    MarkerSetDef,
    MessageId,
    ModelDefs,
    NatNetError,
    RigidBody,
    RigidBodyDef,
    RigidBodyMarker,
    ServerInfo,
    Skeleton,
    SkeletonDef,
    Version,
)
from bench.micro import natnet_bench_frame, natnet_decode_us
from tests.helpers import TESTS

DATA = TESTS / "data" / "natnet"
V3_DIR = DATA / "motive-2.1-natnet-3.0"
V2_DIR = DATA / "motive-1.x-natnet-2.x"
V3 = Version(3)

FUZZ = settings(
    max_examples=1000,
    deadline=timedelta(milliseconds=250),
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def packet(path: Path) -> tuple[int, bytes]:
    return natnet.split_packet(path.read_bytes())


def v3_payload(name: str) -> bytes:
    return packet(V3_DIR / name)[1]


# ------------------------------------------------------------------------------------------------------------
# Packets, ids, versions
# ------------------------------------------------------------------------------------------------------------


def test_message_ids_match_the_protocol() -> None:
    expected = {
        "CONNECT": 0,
        "SERVERINFO": 1,
        "REQUEST": 2,
        "RESPONSE": 3,
        "REQUEST_MODELDEF": 4,
        "MODELDEF": 5,
        "REQUEST_FRAMEOFDATA": 6,
        "FRAMEOFDATA": 7,
        "MESSAGESTRING": 8,
        "DISCONNECT": 9,
        "KEEPALIVE": 10,
        "ECHOREQUEST": 12,
        "ECHORESPONSE": 13,
        "DISCOVERY": 14,
        "UNRECOGNIZED_REQUEST": 100,
    }
    for name, value in expected.items():
        assert MessageId[name] == value


def test_split_packet_trusts_the_datagram_length() -> None:
    assert natnet.split_packet(b"\x04\x00\x00\x00") == (4, b"")
    big = b"\x01" * 70_000
    # The u16 length wrapped (70000 & 0xFFFF); the datagram length wins.
    message_id, payload = natnet.split_packet(struct.pack("<HH", 5, 70_000 & 0xFFFF) + big)
    assert (message_id, payload) == (5, big)
    with pytest.raises(NatNetError, match="header needs 4 bytes"):
        natnet.split_packet(b"\x07\x00")
    with pytest.raises(NatNetError, match="FRAMEOFDATA: length field says 10 bytes, datagram holds 3"):
        natnet.split_packet(struct.pack("<HH", 7, 10) + b"abc")


def test_encode_packet_refuses_what_udp_cannot_carry() -> None:
    raw = natnet.encode_packet(MessageId.MODELDEF, b"\0" * 65_503)
    assert struct.unpack_from("<HH", raw) == (5, 65_503) and len(raw) == 65_507
    with pytest.raises(NatNetError, match="do not fit in a UDP datagram"):
        natnet.encode_packet(MessageId.MODELDEF, b"\0" * 65_504)


def test_version_parse_compare_and_bytes() -> None:
    assert Version.parse("4.1") == Version(4, 1, 0, 0)
    assert Version.parse("3.0.0.0") == Version(3)
    assert str(Version(2, 11, 1, 0)) == "2.11.1.0"
    assert Version(2, 9) < Version(2, 11) < Version(3) < Version(4, 0) < Version(4, 1)
    assert Version.from_bytes(b"\x04\x01\x00\x00") == Version(4, 1)
    assert Version(4, 1).to_bytes() == b"\x04\x01\x00\x00"
    for bad in ("", "4.x", "1.2.3.4.5", "256.0", "-1"):
        with pytest.raises(NatNetError):
            Version.parse(bad)
    with pytest.raises(NatNetError):
        Version(300).to_bytes()


@pytest.mark.parametrize("version", [Version(1, 9), Version(5, 0), Version(0)])
def test_unsupported_versions_are_refused(version: Version) -> None:
    with pytest.raises(NatNetError, match="unsupported NatNet version"):
        natnet.decode_frame(v3_payload("mocapframe_packet_v3.bin"), version)
    with pytest.raises(NatNetError, match="unsupported NatNet version"):
        natnet.decode_model_defs(v3_payload("modeldef_packet_v3.bin"), version)


# ------------------------------------------------------------------------------------------------------------
# Real Motive 2.1 / NatNet 3.0 captures
# ------------------------------------------------------------------------------------------------------------


def test_connect_and_discovery_v3() -> None:
    for name, message_id, encode in (
        ("connect_packet_v3.bin", MessageId.CONNECT, natnet.encode_connect),
        ("discovery_packet_v3.bin", MessageId.DISCOVERY, natnet.encode_discovery),
    ):
        got_id, payload = packet(V3_DIR / name)
        assert got_id == message_id
        request = natnet.decode_connect(payload)
        assert request == natnet.ConnectRequest("NatNetLib", Version(3), Version(3))
        assert encode("NatNetLib", Version(3), Version(3)) == (V3_DIR / name).read_bytes()
    # A bare CONNECT (what some clients send) and the NatNet SDK Python sample's layout.
    assert natnet.decode_connect(b"") == natnet.ConnectRequest("", None, None)
    sample = bytearray(b"Ping".ljust(270, b"\0"))
    sample[265:269] = bytes([4, 1, 0, 0])
    assert natnet.decode_connect(bytes(sample) + b"\0").natnet_version == Version(4, 1)


def test_server_info_v3() -> None:
    message_id, payload = packet(V3_DIR / "serverinfo_packet_v3.bin")
    assert message_id == MessageId.SERVERINFO
    info = natnet.decode_server_info(payload)
    assert info == ServerInfo(
        app_name="Motive",
        app_version=Version(2, 1),
        natnet_version=Version(3),
        clock_frequency=3_312_787,
        data_port=1511,
        is_multicast=True,
        multicast_group="239.255.42.99",
    )
    encoded = natnet.encode_server_info(info)
    # Motive leaves garbage after the name's NUL; everything else is reproduced.
    raw = (V3_DIR / "serverinfo_packet_v3.bin").read_bytes()
    assert len(encoded) == len(raw) == 283
    assert encoded[:11] == raw[:11] and encoded[260:] == raw[260:]
    assert natnet.decode_server_info(natnet.split_packet(encoded)[1]) == info


def test_server_info_errors_and_pre_3_layout() -> None:
    with pytest.raises(NatNetError, match=r"SERVERINFO: versions at byte 256: payload has 100 bytes"):
        natnet.decode_server_info(b"x" * 100)
    v3 = v3_payload("serverinfo_packet_v3.bin")
    with pytest.raises(
        NatNetError, match=r"SERVERINFO: NatNet 3.0.0.0 clock/port/multicast fields at byte 264"
    ):
        natnet.decode_server_info(v3[:270])
    old = ServerInfo("Motive", Version(1, 9), Version(2, 9))
    raw = natnet.encode_server_info(old)
    assert len(raw) == 268
    assert natnet.decode_server_info(natnet.split_packet(raw)[1]) == old
    with pytest.raises(NatNetError, match="needs clock_frequency"):
        natnet.encode_server_info(ServerInfo("Motive", Version(3, 1), Version(4, 1)))


def test_model_defs_v3() -> None:
    message_id, payload = packet(V3_DIR / "modeldef_packet_v3.bin")
    assert message_id == MessageId.MODELDEF
    defs = natnet.decode_model_defs(payload, V3)
    assert [type(d).__name__ for d in defs.datasets] == ["RigidBodyDef", "MarkerSetDef", "MarkerSetDef"]
    (body,) = defs.rigid_bodies
    assert (body.name, body.id, body.parent_id, body.offset) == ("RaceQuad", 2, -1, (0.0, 0.0, 0.0))
    assert len(body.marker_offsets) == 5 and body.marker_labels == (0,) * 5 and body.marker_names == ()
    assert body.marker_offsets[0] == pytest.approx((0.16115899, 0.0350516, -0.0321813), abs=1e-7)
    sets = defs.marker_sets
    assert [s.name for s in sets] == ["RaceQuad", "all"]
    assert sets[0].marker_names == tuple(f"Marker{i}" for i in range(1, 6))
    assert sets[1].marker_names == tuple(f"RaceQuad_{i}" for i in range(1, 6))
    assert defs.rigid_body_names() == {2: "RaceQuad"}
    assert natnet.encode_model_defs(defs, V3) == (V3_DIR / "modeldef_packet_v3.bin").read_bytes()


def test_frame_v3_matches_readme() -> None:
    message_id, payload = packet(V3_DIR / "mocapframe_packet_v3.bin")
    assert message_id == MessageId.FRAMEOFDATA
    frame = natnet.decode_frame(payload, V3)
    assert frame.frame_number == 162734
    (body,) = frame.rigid_bodies
    assert body.id == 2
    assert body.pos == pytest.approx((0.1744466, 1.4471314, -0.7343040), abs=1e-7)
    assert body.quat_xyzw == pytest.approx((-0.05459423, 0.5099482, 0.04370357, -0.8573577), abs=1e-7)
    assert body.mean_error == pytest.approx(0.0005152203, rel=1e-6)
    assert body.params == 1 and body.tracking_valid
    assert (frame.n_marker_sets, frame.n_unlabeled_markers, frame.n_labeled_markers) == (0, 5, 6)
    assert (frame.n_skeletons, frame.n_force_plates, frame.n_devices, frame.n_assets) == (0, 0, 0, 0)
    assert (frame.timecode, frame.subframe, frame.params) == (0, 0, 0)
    assert frame.timestamp == pytest.approx(1356.1167, abs=1e-4)
    assert (frame.cam_mid_exposure, frame.data_received, frame.transmit) == (
        1416497730518,
        1416497745808,
        1416497748722,
    )
    assert frame.precision_secs is None and frame.latency is None
    assert not frame.models_changed and not frame.is_recording
    assert frame.system_latency(3_312_787) == pytest.approx((1416497748722 - 1416497730518) / 3_312_787)
    assert payload[-4:] == b"\0\0\0\0"

    full = natnet.decode_frame(payload, V3, full=True)
    assert full.rigid_bodies == frame.rigid_bodies
    assert len(full.unlabeled_markers) == 5 and len(full.labeled_markers) == 6
    assert all(m.residual is not None and m.params is not None for m in full.labeled_markers)
    assert natnet.encode_frame(full, V3) == (V3_DIR / "mocapframe_packet_v3.bin").read_bytes()


def test_occluded_frame_v3() -> None:
    payload = v3_payload("mocapframe_packet_occluded_v3.bin")
    frame = natnet.decode_frame(payload, V3, full=True)
    assert frame.frame_number == 269007
    assert [(s.name, len(s.markers)) for s in frame.marker_sets] == [("FakeTree", 5), ("all", 5)]
    assert [b.id for b in frame.rigid_bodies] == [7]
    assert [m.occluded for m in frame.labeled_markers].count(True) == 1
    assert natnet.encode_frame(frame, V3) == (V3_DIR / "mocapframe_packet_occluded_v3.bin").read_bytes()


def test_echo_v3() -> None:
    message_id, payload = packet(V3_DIR / "echorequest_packet_v3.bin")
    assert message_id == MessageId.ECHOREQUEST
    assert natnet.decode_echo_request(payload) == 278554190
    assert natnet.encode_echo_request(278554190) == (V3_DIR / "echorequest_packet_v3.bin").read_bytes()
    message_id, payload = packet(V3_DIR / "echoresponse_packet_v3.bin")
    assert message_id == MessageId.ECHORESPONSE
    assert natnet.decode_echo_response(payload) == (278554190, 1416498545924)
    raw = natnet.encode_echo_response(278554190, 1416498545924)
    assert raw == (V3_DIR / "echoresponse_packet_v3.bin").read_bytes()
    with pytest.raises(NatNetError, match="ECHORESPONSE: timestamps at byte 0: payload has 8 bytes"):
        natnet.decode_echo_response(payload[:8])
    with pytest.raises(NatNetError, match="ECHOREQUEST"):
        natnet.decode_echo_request(b"\1\2")


def test_request_model_defs_v3() -> None:
    assert packet(V3_DIR / "requestmodeldef_packet_v3.bin") == (MessageId.REQUEST_MODELDEF, b"")
    assert natnet.encode_request_model_defs() == (V3_DIR / "requestmodeldef_packet_v3.bin").read_bytes()


# ------------------------------------------------------------------------------------------------------------
# Real Motive 1.x / NatNet 2.x captures
# ------------------------------------------------------------------------------------------------------------


def v2_version(motive: str) -> Version:
    message_id, payload = packet(V2_DIR / f"frame-motive-{motive}-000.bin")
    assert message_id == MessageId.SERVERINFO
    info = natnet.decode_server_info(payload)
    assert info.app_name == "NatNetLib" and info.clock_frequency is None and info.data_port is None
    return info.natnet_version


def v2_frames(motive: str) -> list[tuple[bytes, Frame]]:
    version = v2_version(motive)
    frames = []
    for index in (1, 2):
        raw = (V2_DIR / f"frame-motive-{motive}-00{index}.bin").read_bytes()
        message_id, payload = natnet.split_packet(raw)
        assert message_id == MessageId.FRAMEOFDATA
        frames.append((raw, natnet.decode_frame(payload, version, full=True)))
    return frames


@pytest.mark.parametrize(
    ("motive", "version"), [("1.5.0", Version(2, 5)), ("1.7.2", Version(2, 7)), ("1.9.0", Version(2, 9))]
)
def test_v2_frames_reencode_exactly(motive: str, version: Version) -> None:
    assert v2_version(motive) == version
    for raw, frame in v2_frames(motive):
        assert natnet.encode_frame(frame, version) == raw
        fast = natnet.decode_frame(natnet.split_packet(raw)[1], version)
        assert [dataclasses.replace(b, markers=()) for b in frame.rigid_bodies] == list(fast.rigid_bodies)
        assert fast.n_labeled_markers == len(frame.labeled_markers)


def test_v25_frames() -> None:
    (_, first), (_, second) = v2_frames("1.5.0")
    assert (first.frame_number, second.frame_number) == (92881, 92882)
    assert [s.name for s in first.marker_sets] == ["Rigid Body 1", "all"]
    assert first.marker_sets[0].markers[0] == pytest.approx((-0.30157, 0.08478, 1.11433), abs=1e-5)
    (body,) = first.rigid_bodies
    assert body.id == 1 and body.params is None and body.tracking_valid
    assert [m.id for m in body.markers] == [1, 2, 3]
    assert body.markers[0].pos == pytest.approx((-0.30156, 0.08478, 1.11433), abs=1e-5)
    assert first.timestamp is None and first.cam_mid_exposure is None and first.latency is not None
    assert first.n_labeled_markers == 3 and first.labeled_markers[0].params is None


def test_v27_frames() -> None:
    (_, first), (_, second) = v2_frames("1.7.2")
    assert (first.frame_number, second.frame_number) == (411213, 411214)
    (body,) = first.rigid_bodies
    assert body.params == 1 and body.tracking_valid
    assert body.pos[1] == pytest.approx(0.096, abs=0.001)  # Y-up: just above the floor
    assert first.timestamp == pytest.approx(3426.775, abs=1e-9)
    assert first.latency == pytest.approx(first.timestamp, abs=1e-3)  # the legacy float repeats it
    assert first.labeled_markers[0].params is not None and first.labeled_markers[0].residual is None


def test_v29_frames() -> None:
    (_, first), (_, second) = v2_frames("1.9.0")
    assert (first.frame_number, second.frame_number) == (11823217, 11823218)
    assert first.marker_sets[0].name == "Triangle"
    assert [b.id for b in first.rigid_bodies] == [2]
    assert first.n_force_plates == 0 and first.force_plates == ()
    assert first.labeled_markers[0].model_id == 2 and first.labeled_markers[0].marker_id == 1


def test_frame_decoded_with_the_wrong_version_fails() -> None:
    raw27 = (V2_DIR / "frame-motive-1.7.2-001.bin").read_bytes()
    with pytest.raises(NatNetError, match="FRAMEOFDATA"):
        natnet.decode_frame(natnet.split_packet(raw27)[1], V3)
    with pytest.raises(NatNetError, match="FRAMEOFDATA"):
        natnet.decode_frame(v3_payload("mocapframe_packet_v3.bin"), Version(2, 7))


# ------------------------------------------------------------------------------------------------------------
# The whole captured session
# ------------------------------------------------------------------------------------------------------------


def session() -> list[tuple[float, int, bytes]]:
    return [(d.timestamp, *natnet.split_packet(d.payload)) for d in read_udp(V3_DIR / "traffic.pcapng")]


def test_all_518_frames_match_the_expected_decode() -> None:
    datagrams = session()
    frames = [(t, natnet.decode_frame(p, V3)) for t, i, p in datagrams if i == MessageId.FRAMEOFDATA]
    expected = list(read_frames_jsonl(V3_DIR / "traffic_frames_decoded.jsonl"))
    assert len(frames) == len(expected) == 518
    for (receive_time, got), (expected_time, want) in zip(frames, expected, strict=True):
        assert receive_time == pytest.approx(expected_time, abs=1e-6)
        assert got.frame_number == want.frame_number
        assert got.timestamp == pytest.approx(want.timestamp, rel=1e-15)
        assert (got.cam_mid_exposure, got.data_received, got.transmit) == (
            want.cam_mid_exposure,
            want.data_received,
            want.transmit,
        )
        assert got.n_labeled_markers == want.n_labeled_markers
        assert len(got.rigid_bodies) == len(want.rigid_bodies)
        for a, b in zip(got.rigid_bodies, want.rigid_bodies, strict=True):
            assert (a.id, a.tracking_valid) == (b.id, b.tracking_valid)
            assert a.pos == pytest.approx(b.pos, rel=1e-12, abs=1e-12)
            assert a.quat_xyzw == pytest.approx(b.quat_xyzw, rel=1e-12, abs=1e-12)
            assert a.mean_error == pytest.approx(b.mean_error, rel=1e-12)
    numbers = [f.frame_number for _, f in frames]
    assert numbers == list(range(162734, 163252))
    assert all(b.tracking_valid and b.id == 2 for _, f in frames for b in f.rigid_bodies)


def test_session_latencies_and_reencoding() -> None:
    datagrams = session()
    info = next(natnet.decode_server_info(p) for _, i, p in datagrams if i == MessageId.SERVERINFO)
    assert info.clock_frequency == 3_312_787
    clock = info.clock_frequency
    frames = [natnet.decode_frame(p, info.natnet_version, full=True) for _, i, p in datagrams if i == 7]
    system = statistics.median(f.system_latency(clock) or 0.0 for f in frames)
    camera = statistics.median(((f.data_received or 0) - (f.cam_mid_exposure or 0)) / clock for f in frames)
    assert system == pytest.approx(5.40e-3, abs=0.01e-3)
    assert camera == pytest.approx(4.57e-3, abs=0.01e-3)
    payloads = [p for _, i, p in datagrams if i == 7]
    for frame, payload in zip(frames, payloads, strict=True):
        assert natnet.split_packet(natnet.encode_frame(frame, V3))[1] == payload


def test_session_commands_echo_and_responses() -> None:
    datagrams = session()
    requests = [natnet.decode_request_text(p) for _, i, p in datagrams if i == MessageId.REQUEST]
    assert requests[1:] == ["FrameRate", "AnalogSamplesPerMocapFrame", "TestRequest"]
    assert requests[0].startswith("service20,-1,")
    responses = [natnet.decode_response(p) for _, i, p in datagrams if i == MessageId.RESPONSE]
    assert responses[1].float_value == 120.0 and responses[1].text is None
    assert responses[2].int_value == 0
    assert natnet.encode_response(120.0) == natnet.encode_packet(MessageId.RESPONSE, responses[1].raw)
    assert natnet.encode_request("FrameRate") == natnet.encode_packet(MessageId.REQUEST, b"FrameRate\0")
    assert sum(1 for _, i, _ in datagrams if i == MessageId.UNRECOGNIZED_REQUEST) == 1
    echo_requests = [natnet.decode_echo_request(p) for _, i, p in datagrams if i == MessageId.ECHOREQUEST]
    echo_responses = [natnet.decode_echo_response(p) for _, i, p in datagrams if i == MessageId.ECHORESPONSE]
    assert len(echo_requests) == len(echo_responses) == 9
    assert [c for c, _ in echo_responses] == echo_requests
    ticks = [s for _, s in echo_responses]
    assert ticks == sorted(ticks)


def test_text_messages() -> None:
    assert natnet.decode_response(b"OK\0").text == "OK"
    assert natnet.decode_response(b"\x00<\x7f^").text is None
    assert natnet.decode_response(b"\x00\x00\xf0B").float_value == 120.0
    assert natnet.decode_response(b"abc").int_value is None
    assert natnet.split_packet(natnet.encode_response("Bitstream,4.1"))[1] == b"Bitstream,4.1\0"
    assert natnet.split_packet(natnet.encode_response(7))[1] == struct.pack("<i", 7)
    assert natnet.split_packet(natnet.encode_response(b"\1\2"))[1] == b"\1\2"
    assert natnet.decode_message_string(b"hello\0junk") == "hello"
    assert natnet.decode_request_text(b"no terminator") == "no terminator"
    assert natnet.encode_message_string("hi") == b"\x08\x00\x03\x00hi\0"
    assert natnet.encode_keepalive() == b"\x0a\x00\x00\x00"
    assert natnet.encode_disconnect() == b"\x09\x00\x00\x00"
    assert natnet.encode_request_frame() == b"\x06\x00\x00\x00"
    assert natnet.encode_unrecognized() == b"\x64\x00\x00\x00"
    with pytest.raises(NatNetError, match="NUL"):
        natnet.encode_request("bad\0command")


# ------------------------------------------------------------------------------------------------------------
# Round trips of every section, per version
# ------------------------------------------------------------------------------------------------------------

ROUND_TRIP_VERSIONS = [
    Version(2, 0),
    Version(2, 1),
    Version(2, 3),
    Version(2, 5),
    Version(2, 6),
    Version(2, 7),
    Version(2, 9),
    Version(2, 11),
    Version(3, 0),
    Version(3, 1),
    Version(4, 0),
    Version(4, 1),
]


def body(rid: int, version: Version, *, valid: bool = True, markers: int = 0) -> RigidBody:
    """A rigid body with values exact in float32, shaped as ``version`` streams it."""
    has_params = version >= Version(2, 6)
    block = tuple(RigidBodyMarker(k + 1, (0.25 * k, 1.0, -0.5), 0.015625) for k in range(markers))
    return RigidBody(
        rid,
        (0.5 * rid, 1.25, -0.75),
        (0.0, 0.5, 0.0, -0.875),
        0.00048828125,
        valid if has_params else True,
        (1 if valid else 0) if has_params else None,
        block if version < V3 else (),
    )


def rich_frame(version: Version) -> Frame:
    """A frame with every section the version has, including untracked bodies and skeleton bones."""
    pre3 = version < V3
    lm_params = 10 if version >= Version(2, 6) else None
    lm_residual = 0.0009765625 if version >= V3 else None
    labeled = tuple(
        LabeledMarker((7 << 16) | k, (0.125 * k, 1.5, -0.25), 0.0234375, lm_params, lm_residual)
        for k in range(5)
    )
    return Frame(
        frame_number=424242,
        rigid_bodies=(
            body(3, version, markers=3 if pre3 else 0),
            body(4, version, valid=False, markers=2 if pre3 else 0),
            body(9, version),
        ),
        timecode=0x01020304,
        subframe=2,
        timestamp=(1234.5 if version >= Version(2, 6) else None),
        cam_mid_exposure=10**12 if not pre3 else None,
        data_received=10**12 + 15_000 if not pre3 else None,
        transmit=10**12 + 18_000 if not pre3 else None,
        precision_secs=86_399 if version >= Version(4, 1) else None,
        precision_fraction=123_456_789 if version >= Version(4, 1) else None,
        params=0x02 if version >= Version(2, 6) else 0,
        latency=0.25 if pre3 else None,
        marker_sets=(MarkerSet("Drone1", ((0.0, 1.0, 2.0), (0.5, 1.5, 2.5))), MarkerSet("all", ())),
        unlabeled_markers=((9.0, 8.0, 7.0),),
        skeletons=(
            (Skeleton(11, (body(21, version, markers=1 if pre3 else 0), body(22, version, valid=False))),)
            if version >= Version(2, 1)
            else ()
        ),
        assets=(
            (Asset(31, (body(41, version), body(42, version, valid=False)), labeled[:2]), Asset(32))
            if version >= Version(4, 1)
            else ()
        ),
        labeled_markers=labeled if version >= Version(2, 3) else (),
        force_plates=((Analog(1, ((1.0, 2.0), (3.0,), ())), Analog(2)) if version >= Version(2, 9) else ()),
        devices=((Analog(5, ((0.5,) * 4,)),) if version >= Version(2, 11) else ()),
    )


@pytest.mark.parametrize("version", ROUND_TRIP_VERSIONS, ids=str)
def test_frame_round_trip_with_every_section(version: Version) -> None:
    frame = rich_frame(version)
    message_id, payload = natnet.split_packet(natnet.encode_frame(frame, version))
    assert message_id == MessageId.FRAMEOFDATA
    assert natnet.decode_frame(payload, version, full=True) == frame
    fast = natnet.decode_frame(payload, version)
    assert fast.rigid_bodies == tuple(dataclasses.replace(b, markers=()) for b in frame.rigid_bodies)
    assert [b.tracking_valid for b in fast.rigid_bodies] == (
        [True, True, True] if version < Version(2, 6) else [True, False, True]
    )
    assert (fast.n_marker_sets, fast.n_unlabeled_markers) == (2, 1)
    assert fast.n_skeletons == len(frame.skeletons) and fast.n_assets == len(frame.assets)
    assert fast.n_labeled_markers == len(frame.labeled_markers)
    assert (fast.n_force_plates, fast.n_devices) == (len(frame.force_plates), len(frame.devices))
    assert fast.models_changed == (version >= Version(2, 6))
    assert (fast.timestamp, fast.cam_mid_exposure, fast.precision_secs) == (
        frame.timestamp,
        frame.cam_mid_exposure,
        frame.precision_secs,
    )


def reference_walk(payload: bytes, major: int, minor: int) -> tuple[list[tuple[int, bool]], int, int]:
    """An independent, straight-line reading of a 3.x/4.x frame as the brief describes it (and as
    libmotioncapture reads it): returns the (id, tracking valid) of the rigid bodies, the frame params and
    the offset after the end tag."""
    sized = (major, minor) >= (4, 1)
    pos = 0

    def i32() -> int:
        nonlocal pos
        (value,) = struct.unpack_from("<i", payload, pos)
        pos += 4
        return value

    def count() -> int:
        n = i32()
        if sized:
            i32()
        return n

    i32()  # frame number
    # (``pos += n * i32()`` would lose i32's own advance: read counts first.)
    for _ in range(count()):
        pos = payload.index(b"\0", pos) + 1
        markers = i32()
        pos += 12 * markers
    unlabeled = count()
    pos += 12 * unlabeled
    bodies = []
    for _ in range(count()):
        rid = i32()
        pos += 32
        (params,) = struct.unpack_from("<h", payload, pos)
        pos += 2
        bodies.append((rid, bool(params & 1)))
    for _ in range(count()):
        i32()
        bones = i32()
        pos += 38 * bones
    if sized:
        i32()
        asset_bytes = i32()
        pos += asset_bytes  # assets: skipped by their byte count
    labeled = count()
    pos += 26 * labeled
    for _ in range(2):  # force plates, devices
        for _ in range(count()):
            i32()
            for _ in range(i32()):
                samples = i32()
                pos += 4 * samples
    pos += 8 + 8 + 24  # timecode, subframe, timestamp, three tick stamps
    if sized:
        pos += 8
    (params,) = struct.unpack_from("<h", payload, pos)
    pos += 2 + 4
    return bodies, params, pos


@pytest.mark.parametrize("version", [Version(3, 0), Version(3, 1), Version(4, 0), Version(4, 1)], ids=str)
def test_encoded_frames_read_by_an_independent_walk(version: Version) -> None:
    frame = rich_frame(version)
    _, payload = natnet.split_packet(natnet.encode_frame(frame, version))
    bodies, params, end = reference_walk(payload, version.major, version.minor)
    assert bodies == [(3, True), (4, False), (9, True)]
    assert params == frame.params
    assert end == len(payload)


def test_minimal_41_frame_layout() -> None:
    frame = Frame(1, (RigidBody(5, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 0.0, True, 1),))
    _, payload = natnet.split_packet(natnet.encode_frame(frame, Version(4, 1)))
    # frame#, 8 sections of (count, bytes), one 38-byte body, timecode+subframe, f64, 3×u64, precision,
    # params, end tag.
    assert len(payload) == 4 + 8 * 8 + 38 + 8 + 8 + 24 + 8 + 2 + 4
    assert struct.unpack_from("<ii", payload, 20) == (1, 38)
    assert struct.unpack_from("<i", payload, 28)[0] == 5
    _, payload40 = natnet.split_packet(natnet.encode_frame(frame, Version(4, 0)))
    assert len(payload40) == len(payload) - 8 * 4 - 4 - 8  # no byte counts, no assets, no precision stamp


def test_40_41_ambiguity_is_resolved_by_the_bytes_left() -> None:
    frame = rich_frame(Version(4, 0))
    _, payload = natnet.split_packet(natnet.encode_frame(frame, Version(4, 0)))
    assert natnet.decode_frame(payload, Version(4, 0)).precision_secs is None
    # A server reporting 4.0 that appends the 4.1 precision stamp after the ticks.
    with_stamp = payload[:-6] + struct.pack("<II", 77, 88) + payload[-6:]
    decoded = natnet.decode_frame(with_stamp, Version(4, 0), full=True)
    assert (decoded.precision_secs, decoded.precision_fraction) == (77, 88)
    assert decoded.rigid_bodies == frame.rigid_bodies and decoded.params == frame.params
    with pytest.raises(
        NatNetError, match=r"frame suffix: 9 bytes after the tick stamps, expected 6 \(4.0\) or 14"
    ):
        natnet.decode_frame(payload[:-6] + b"\0\0\0" + payload[-6:], Version(4, 0))


def test_41_sections_step_over_unknown_trailing_bytes() -> None:
    frame = rich_frame(Version(4, 1))
    _, payload = natnet.split_packet(natnet.encode_frame(frame, Version(4, 1)))
    # Find the labeled-marker section (count 5, then its byte count) and grow it by 4 unknown bytes.
    count_at = payload.index(struct.pack("<ii", 5, 5 * 26))
    size_end = count_at + 8 + 5 * 26
    grown = (
        payload[:count_at]
        + struct.pack("<ii", 5, 5 * 26 + 4)
        + payload[count_at + 8 : size_end]
        + b"\xde\xad\xbe\xef"
        + payload[size_end:]
    )
    for full in (False, True):
        decoded = natnet.decode_frame(grown, Version(4, 1), full=full)
        assert decoded.rigid_bodies == natnet.decode_frame(payload, Version(4, 1), full=full).rigid_bodies
        assert decoded.n_labeled_markers == 5 and decoded.n_force_plates == 2
    shrunk = payload[:count_at] + struct.pack("<ii", 5, 5 * 26 - 4) + payload[count_at + 8 :]
    with pytest.raises(NatNetError, match="labeled markers"):
        natnet.decode_frame(shrunk, Version(4, 1))


def test_encode_frame_refuses_what_it_cannot_write() -> None:
    fast = natnet.decode_frame(v3_payload("mocapframe_packet_v3.bin"), V3)
    with pytest.raises(NatNetError, match="decode with full=True"):
        natnet.encode_frame(fast, V3)
    with pytest.raises(NatNetError, match="no assets"):
        natnet.encode_frame(Frame(1, assets=(Asset(1),)), V3)
    with pytest.raises(NatNetError, match="n_labeled_markers=2 but 1 labeled_markers"):
        Frame(1, n_labeled_markers=2, labeled_markers=(LabeledMarker(1, (0.0, 0.0, 0.0)),))
    with pytest.raises(NatNetError, match="cannot encode frame 1"):
        natnet.encode_frame(Frame(1, (RigidBody(2**40, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),)), V3)


def test_tracking_flag_is_authoritative_when_encoding() -> None:
    lost = RigidBody(1, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 0.0, tracking_valid=False, params=1)
    _, payload = natnet.split_packet(natnet.encode_frame(Frame(1, (lost,)), V3))
    (decoded,) = natnet.decode_frame(payload, V3).rigid_bodies
    assert not decoded.tracking_valid and decoded.params == 0


def all_dataset_defs(version: Version) -> ModelDefs:
    names = version >= Version(4)
    markers = version >= V3
    rb = RigidBodyDef(
        "Drone1",
        1,
        -1,
        (0.0, 0.25, 0.0),
        ((0.125, 0.0, 0.0), (0.0, 0.125, 0.0)) if markers else (),
        (0, 7) if markers else (),
        ("M1", "M2") if names and markers else (),
    )
    bone = dataclasses.replace(rb, name="Hip", id=2, parent_id=0)
    datasets: list[natnet.DataSetDef] = [
        MarkerSetDef("Drone1", ("M1", "M2")),
        rb,
        SkeletonDef("Walker", 5, (bone, dataclasses.replace(bone, name="Spine", id=3, parent_id=2))),
        CameraDef("Cam 1", (1.0, 2.5, -3.0), (0.0, 0.0, 0.5, 0.75)),
    ]
    if version >= V3:
        datasets.append(
            ForcePlateDef(
                9,
                "FP-001",
                0.5,
                0.75,
                (0.0, 0.0, 0.0),
                tuple(float(i) for i in range(144)),
                tuple(float(i) / 4 for i in range(12)),
                1,
                2,
                ("Fx", "Fy", "Fz"),
            )
        )
        datasets.append(DeviceDef(10, "EMG", "SN42", 3, 1, ("ch1", "ch2")))
    if version >= Version(4, 1):
        datasets.append(
            AssetDef("Trained", 1, 11, (rb,), (MarkerDef("A1", 3, (0.5, 0.5, 0.5), 0.015625, 2),))
        )
    return ModelDefs(tuple(datasets))


@pytest.mark.parametrize(
    "version", [Version(2, 7), Version(3, 0), Version(3, 1), Version(4, 0), Version(4, 1)], ids=str
)
def test_model_defs_round_trip(version: Version) -> None:
    defs = all_dataset_defs(version)
    message_id, payload = natnet.split_packet(natnet.encode_model_defs(defs, version))
    assert message_id == MessageId.MODELDEF
    decoded = natnet.decode_model_defs(payload, version)
    assert decoded == defs
    assert decoded.rigid_body_names() == {1: "Drone1"}
    assert [s.name for s in decoded.skeletons] == ["Walker"]
    assert len(decoded.cameras) == 1 and len(decoded.assets) == (1 if version >= Version(4, 1) else 0)


def test_model_defs_41_skips_unknown_types_by_size() -> None:
    defs = all_dataset_defs(Version(4, 1))
    _, payload = natnet.split_packet(natnet.encode_model_defs(defs, Version(4, 1)))
    extended = struct.pack("<i", len(defs.datasets) + 1) + payload[4:] + struct.pack("<ii", 42, 3) + b"xyz"
    decoded = natnet.decode_model_defs(extended, Version(4, 1))
    assert decoded.datasets == defs.datasets and decoded.skipped == 1
    with pytest.raises(NatNetError, match=r"MODELDEF \(NatNet 4.0\): data set 0: unknown data set type 42"):
        natnet.decode_model_defs(struct.pack("<ii", 1, 42) + b"xyz", Version(4, 0))
    with pytest.raises(NatNetError, match=r"force plate descriptions need NatNet 3\.0"):
        natnet.encode_model_defs(all_dataset_defs(V3), Version(2, 9))


# ------------------------------------------------------------------------------------------------------------
# Errors name the message, section and offset
# ------------------------------------------------------------------------------------------------------------


def test_error_messages_locate_the_fault() -> None:
    payload = v3_payload("mocapframe_packet_v3.bin")
    with pytest.raises(NatNetError) as info:
        natnet.decode_frame(payload[:200], V3)
    assert str(info.value) == (
        "FRAMEOFDATA (NatNet 3.0): labeled markers: labeled marker count 6 does not fit in the 78 bytes "
        "left at byte 122"
    )
    corrupt = payload[:72] + struct.pack("<i", 1_000_000) + payload[76:]
    with pytest.raises(
        NatNetError, match=r"rigid bodies: rigid body count 1000000 does not fit .* at byte 76"
    ):
        natnet.decode_frame(corrupt, V3)
    negative = payload[:8] + struct.pack("<i", -3) + payload[12:]
    with pytest.raises(NatNetError, match="unlabeled markers: unlabeled marker count -3"):
        natnet.decode_frame(negative, V3)
    with pytest.raises(NatNetError, match="end-of-data tag: 1 unexpected trailing bytes at byte 332"):
        natnet.decode_frame(payload + b"\0", V3)
    with pytest.raises(NatNetError, match=r"frame suffix: truncated or malformed at byte 294"):
        natnet.decode_frame(payload[:300], V3)
    modeldef = v3_payload("modeldef_packet_v3.bin")
    with pytest.raises(NatNetError, match=r"MODELDEF \(NatNet 3.0\): data set 2 \(marker set\)"):
        natnet.decode_model_defs(modeldef[:-3], V3)


def test_every_truncation_of_real_frames_fails_cleanly() -> None:
    for payload, version in real_payloads("frame"):
        for cut in range(len(payload)):
            if version == Version(4, 1) and cut == len(payload) - 8:
                # Without its last 8 bytes a 4.1 frame has a valid 4.0 suffix (no precision stamp):
                # the 4.0/4.1 ambiguity rule accepts it.
                assert natnet.decode_frame(payload[:cut], version).precision_secs is None
                continue
            with pytest.raises(NatNetError, match="FRAMEOFDATA"):
                natnet.decode_frame(payload[:cut], version, full=cut % 2 == 0)


# ------------------------------------------------------------------------------------------------------------
# Fuzzing: nothing but NatNetError, and quickly
# ------------------------------------------------------------------------------------------------------------


def real_payloads(kind: str) -> list[tuple[bytes, Version]]:
    """Real (and, for 4.x, encoded) payloads of one kind with the version to decode them with."""
    if kind == "frame":
        found = [
            (v3_payload(n), V3) for n in ("mocapframe_packet_v3.bin", "mocapframe_packet_occluded_v3.bin")
        ]
        for motive, version in (("1.5.0", Version(2, 5)), ("1.7.2", Version(2, 7)), ("1.9.0", Version(2, 9))):
            found.append((packet(V2_DIR / f"frame-motive-{motive}-001.bin")[1], version))
        for version in (Version(4, 0), Version(4, 1)):
            found.append((natnet.split_packet(natnet.encode_frame(rich_frame(version), version))[1], version))
        return found
    found = [(v3_payload("modeldef_packet_v3.bin"), V3)]
    for version in (Version(4, 0), Version(4, 1)):
        found.append(
            (natnet.split_packet(natnet.encode_model_defs(all_dataset_defs(version), version))[1], version)
        )
    return found


FRAME_SOURCES = real_payloads("frame")
MODELDEF_SOURCES = real_payloads("modeldef")
OTHER_SOURCES = [
    v3_payload(n)
    for n in (
        "serverinfo_packet_v3.bin",
        "connect_packet_v3.bin",
        "echoresponse_packet_v3.bin",
        "echorequest_packet_v3.bin",
    )
]
EXTREMES = [-1, -(2**31), 2**31 - 1, 0x10000, 0x7FFF, 1_000_000]


@st.composite
def mutations(draw: st.DrawFn, sources: list[bytes]) -> bytes:
    data = bytearray(draw(st.sampled_from(sources)))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "truncate", "insert", "delete", "count"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "truncate":
            del data[at:]
        elif op == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[at : at + draw(st.integers(1, 8))]
        elif op == "count" and len(data) >= at + 4:
            data[at : at + 4] = struct.pack("<i", draw(st.sampled_from(EXTREMES)))
    return bytes(data)


ALL_VERSIONS = st.sampled_from(ROUND_TRIP_VERSIONS)


def decode_everything(data: bytes, version: Version) -> None:
    """Run every decoder on ``data``; each must return or raise NatNetError."""
    decoders = (
        lambda: natnet.split_packet(data),
        lambda: natnet.decode_frame(data, version),
        lambda: natnet.decode_frame(data, version, full=True),
        lambda: natnet.decode_model_defs(data, version),
        lambda: natnet.decode_server_info(data),
        lambda: natnet.decode_connect(data),
        lambda: natnet.decode_echo_request(data),
        lambda: natnet.decode_echo_response(data),
        lambda: natnet.decode_request_text(data),
        lambda: natnet.decode_message_string(data),
        lambda: natnet.decode_response(data),
    )
    for decode in decoders:
        with contextlib.suppress(NatNetError):
            decode()


@FUZZ
@given(data=st.binary(max_size=400), version=ALL_VERSIONS)
def test_fuzz_random_bytes(data: bytes, version: Version) -> None:
    decode_everything(data, version)


@FUZZ
@given(source=st.sampled_from(range(len(FRAME_SOURCES))), data=st.data())
def test_fuzz_mutated_frames(source: int, data: st.DataObject) -> None:
    original, version = FRAME_SOURCES[source]
    mutated = data.draw(mutations([original]))
    for full in (False, True):
        try:
            frame = natnet.decode_frame(mutated, version, full=full)
        except NatNetError:
            continue
        assert isinstance(frame, Frame)
        if full:
            # Whatever decoded must encode back to a frame that decodes to the same values.
            again = natnet.decode_frame(
                natnet.split_packet(natnet.encode_frame(frame, version))[1], version, full=True
            )
            assert again.frame_number == frame.frame_number
            assert [b.id for b in again.rigid_bodies] == [b.id for b in frame.rigid_bodies]


@FUZZ
@given(source=st.sampled_from(range(len(MODELDEF_SOURCES))), data=st.data())
def test_fuzz_mutated_model_defs(source: int, data: st.DataObject) -> None:
    original, version = MODELDEF_SOURCES[source]
    mutated = data.draw(mutations([original]))
    try:
        defs = natnet.decode_model_defs(mutated, version)
    except NatNetError:
        return
    assert all(isinstance(name, str) for name in defs.rigid_body_names().values())


@FUZZ
@given(data=mutations(OTHER_SOURCES + [p for p, _ in FRAME_SOURCES]), version=ALL_VERSIONS)
def test_fuzz_mutated_other_messages(data: bytes, version: Version) -> None:
    decode_everything(data, version)


# ------------------------------------------------------------------------------------------------------------
# Benchmark helper
# ------------------------------------------------------------------------------------------------------------


def test_bench_decode_measures_real_frames() -> None:
    frame = natnet_bench_frame(10)
    assert len(frame.rigid_bodies) == 10 and frame.n_labeled_markers == 40 and frame.n_marker_sets == 11
    micros = natnet_decode_us(10, iterations=200)
    assert math.isfinite(micros) and micros > 0  # the figure itself is make bench's
