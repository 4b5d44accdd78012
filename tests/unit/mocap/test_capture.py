"""Tests of the capture readers: the real Motive session, synthetic pcap/pcapng files, JSON lines."""

from __future__ import annotations

import io
import itertools
import json
import socket
import statistics
import struct
from datetime import timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from arena_common.mocap import natnet
from arena_common.mocap.capture import (
    CaptureError,
    RecordedFrame,
    UdpDatagram,
    frame_to_record,
    iter_udp,
    read_frames_jsonl,
    read_udp,
)
from tests.helpers import TESTS

V3_DIR = TESTS / "data" / "natnet" / "motive-2.1-natnet-3.0"
PCAPNG = V3_DIR / "traffic.pcapng"
JSONL = V3_DIR / "traffic_frames_decoded.jsonl"


# ------------------------------------------------------------------------------------------------------------
# Builders of synthetic captures
# ------------------------------------------------------------------------------------------------------------


def udp(sport: int, dport: int, payload: bytes) -> bytes:
    return struct.pack(">HHHH", sport, dport, 8 + len(payload), 0) + payload


def ipv4(
    src: str, dst: str, body: bytes, *, proto: int = 17, ident: int = 1, offset: int = 0, more: bool = False
) -> bytes:
    flags = (0x2000 if more else 0) | (offset // 8)
    header = struct.pack(">BBHHHBBH4s4s", 0x45, 0, 20 + len(body), ident, flags, 64, proto, 0,
                         socket.inet_aton(src), socket.inet_aton(dst))  # fmt: skip
    return header + body


def ipv6(src: str, dst: str, body: bytes) -> bytes:
    return (
        struct.pack(">IHBB", 6 << 28, len(body), 17, 64)
        + socket.inet_pton(socket.AF_INET6, src)
        + socket.inet_pton(socket.AF_INET6, dst)
        + body
    )


def ethernet(ip: bytes, *, vlan: bool = False, ethertype: int | None = None) -> bytes:
    kind = ethertype if ethertype is not None else (0x86DD if ip[0] >> 4 == 6 else 0x0800)
    tag = struct.pack(">HH", 0x8100, 42) if vlan else b""
    return b"\x01" * 6 + b"\x02" * 6 + tag + struct.pack(">H", kind) + ip


def pcap(records: list[tuple[float, bytes]], link: int, *, order: str = "<", nanos: bool = False) -> bytes:
    magic = 0xA1B23C4D if nanos else 0xA1B2C3D4
    out = struct.pack(order + "IHHiIII", magic, 2, 4, 0, 0, 65535, link)
    scale = 1_000_000_000 if nanos else 1_000_000
    for timestamp, frame in records:
        seconds = int(timestamp)
        fraction = round((timestamp - seconds) * scale)
        out += struct.pack(order + "IIII", seconds, fraction, len(frame), len(frame)) + frame
    return out


def block(block_type: int, body: bytes, order: str = "<") -> bytes:
    body += b"\0" * (-len(body) % 4)
    length = 12 + len(body)
    return struct.pack(order + "II", block_type, length) + body + struct.pack(order + "I", length)


def section_header(order: str = "<") -> bytes:
    return block(0x0A0D0D0A, struct.pack(order + "IHHq", 0x1A2B3C4D, 1, 0, -1), order)


def option(code: int, value: bytes, order: str = "<") -> bytes:
    return struct.pack(order + "HH", code, len(value)) + value + b"\0" * (-len(value) % 4)


def interface(link: int, options: bytes = b"", order: str = "<") -> bytes:
    if options:
        options += struct.pack(order + "HH", 0, 0)
    return block(1, struct.pack(order + "HHI", link, 0, 65535) + options, order)


def enhanced(iface: int, ticks: int, frame: bytes, order: str = "<") -> bytes:
    head = struct.pack(order + "IIIII", iface, ticks >> 32, ticks & 0xFFFFFFFF, len(frame), len(frame))
    return block(6, head + frame, order)


def datagrams(data: bytes) -> list[UdpDatagram]:
    return list(iter_udp(io.BytesIO(data)))


HELLO = udp(5000, 1511, b"hello")


# ------------------------------------------------------------------------------------------------------------
# The real Motive session
# ------------------------------------------------------------------------------------------------------------


def test_real_session_datagrams() -> None:
    found = list(read_udp(PCAPNG))
    assert len(found) == 550
    first = found[0]
    assert first.src == ("192.168.0.100", 49465) and first.dst == ("192.168.0.255", 1510)
    assert natnet.split_packet(first.payload)[0] == natnet.MessageId.DISCOVERY
    assert first.timestamp == pytest.approx(1509244022.606067, abs=1e-6)
    times = [d.timestamp for d in found]
    assert times == sorted(times)
    frames = list(read_udp(PCAPNG, port=1511))
    assert len(frames) == 518
    assert {d.dst for d in frames} == {("239.255.42.99", 1511)}
    assert all(natnet.split_packet(d.payload)[0] == natnet.MessageId.FRAMEOFDATA for d in frames)
    gaps = [b.timestamp - a.timestamp for a, b in itertools.pairwise(frames)]
    assert statistics.median(gaps) == pytest.approx(8.34e-3, abs=0.01e-3)
    assert max(gaps) == pytest.approx(12.8e-3, abs=0.1e-3)


def test_real_decoded_frames_jsonl() -> None:
    recorded = list(read_frames_jsonl(JSONL))
    assert len(recorded) == 518
    receive_time, frame = recorded[0]
    assert receive_time == pytest.approx(1509244025.141882)
    assert frame.frame_number == 162734 and frame.n_labeled_markers == 6
    assert (frame.cam_mid_exposure, frame.data_received, frame.transmit) == (
        1416497730518,
        1416497745808,
        1416497748722,
    )
    (body,) = frame.rigid_bodies
    assert body.id == 2 and body.tracking_valid
    assert body.pos == pytest.approx((0.1744466, 1.4471314, -0.7343040), abs=1e-7)


def test_frame_records_round_trip(tmp_path: Path) -> None:
    recorded = list(read_frames_jsonl(JSONL))[:20]
    path = tmp_path / "frames.jsonl"
    path.write_text("".join(json.dumps(frame_to_record(f, t)) + "\n\n" for t, f in recorded))
    assert list(read_frames_jsonl(path)) == recorded


def test_bad_jsonl_lines_are_located(tmp_path: Path) -> None:
    good = JSONL.read_text().splitlines()[0]
    cases = {
        "not json": "not JSON",
        json.dumps({"pcap_t": 1.0}): "missing field 'frame'",
        good.replace('"pos": [', '"pos": [1.0, '): r"rigid_bodies\[0\].pos: expected a list of 3 numbers",
        good.replace(
            '"tracking_valid": true', '"tracking_valid": 1'
        ): "tracking_valid: expected true or false",
        "[1, 2]": "expected a JSON object",
    }
    for line, message in cases.items():
        path = tmp_path / "bad.jsonl"
        path.write_text(good + "\n" + line + "\n")
        with pytest.raises(CaptureError, match=rf"bad.jsonl:2: .*{message}"):
            list(read_frames_jsonl(path))


def test_recorded_frames_replay_through_the_encoder() -> None:
    # The emulator's path: a recorded frame, encoded as a 3.0 server would, decodes to the same bodies.
    receive_time, frame = next(read_frames_jsonl(JSONL))
    assert isinstance(receive_time, float)
    replayable = RecordedFrame(receive_time, frame).frame
    for version in (natnet.Version(3), natnet.Version(4, 1)):
        packet = natnet.encode_frame(
            natnet.Frame(
                replayable.frame_number,
                replayable.rigid_bodies,
                timestamp=replayable.timestamp,
                cam_mid_exposure=replayable.cam_mid_exposure,
            ),
            version,
        )
        decoded = natnet.decode_frame(natnet.split_packet(packet)[1], version)
        assert decoded.rigid_bodies[0].pos == pytest.approx(frame.rigid_bodies[0].pos, rel=1e-7)


# ------------------------------------------------------------------------------------------------------------
# Synthetic captures: link layers, byte orders, resolutions
# ------------------------------------------------------------------------------------------------------------


def test_pcap_ethernet_with_vlan_little_endian_micros() -> None:
    data = pcap([(1000.25, ethernet(ipv4("10.0.0.1", "10.0.0.2", HELLO), vlan=True))], link=1)
    assert datagrams(data) == [UdpDatagram(1000.25, ("10.0.0.1", 5000), ("10.0.0.2", 1511), b"hello")]


def test_pcap_raw_ip_big_endian_nanos() -> None:
    data = pcap([(7.000000123, ipv4("1.2.3.4", "5.6.7.8", HELLO))], link=101, order=">", nanos=True)
    (found,) = datagrams(data)
    assert found.timestamp == pytest.approx(7.000000123, abs=1e-9)
    assert found.src == ("1.2.3.4", 5000) and found.payload == b"hello"


@pytest.mark.parametrize(
    ("link", "prefix"),
    [
        (113, b"\0" * 14 + struct.pack(">H", 0x0800)),  # Linux cooked (SLL)
        (276, struct.pack(">H", 0x0800) + b"\0" * 18),  # Linux cooked v2 (SLL2)
        (0, struct.pack("<I", 2)),  # BSD loopback, little-endian family
        (0, struct.pack(">I", 2)),  # BSD loopback, big-endian family
        (228, b""),  # raw IPv4
    ],
)
def test_other_link_layers(link: int, prefix: bytes) -> None:
    data = pcap([(1.0, prefix + ipv4("127.0.0.1", "127.0.0.1", HELLO))], link=link)
    assert [d.payload for d in datagrams(data)] == [b"hello"]


def test_ipv6_udp() -> None:
    data = pcap([(2.0, ethernet(ipv6("fe80::1", "ff02::1", HELLO)))], link=1)
    (found,) = datagrams(data)
    assert found.src == ("fe80::1", 5000) and found.dst == ("ff02::1", 1511)


def test_non_udp_and_truncated_packets_are_skipped() -> None:
    full = ipv4("10.0.0.1", "10.0.0.2", HELLO)
    records = [
        (1.0, ethernet(ipv4("10.0.0.1", "10.0.0.2", b"\0" * 20, proto=6))),  # TCP
        (2.0, ethernet(b"\0" * 28, ethertype=0x0806)),  # ARP
        (3.0, ethernet(full)[:-3]),  # cut by the snap length
        (4.0, b"\x01\x02"),  # runt
        (5.0, ethernet(full)),
    ]
    assert [d.timestamp for d in datagrams(pcap(records, link=1))] == [5.0]


def test_ipv4_fragments_are_reassembled_out_of_order() -> None:
    payload = bytes(range(256)) * 12
    whole = udp(1510, 50000, payload)
    chunks = [(0, whole[:1480]), (1480, whole[1480:2960]), (2960, whole[2960:])]
    fragments = [
        ipv4("192.168.0.106", "192.168.0.100", chunk, ident=77, offset=offset, more=offset != 2960)
        for offset, chunk in chunks
    ]
    records = [(1.0, ethernet(fragments[1])), (1.1, ethernet(fragments[2])), (1.2, ethernet(fragments[0]))]
    (found,) = datagrams(pcap(records, link=1))
    assert found.payload == payload and found.timestamp == 1.2 and found.src == ("192.168.0.106", 1510)


def test_pcapng_resolution_offset_sections_and_simple_packets() -> None:
    frame = ethernet(ipv4("10.0.0.1", "10.0.0.2", HELLO))
    nanos = option(9, bytes([9])) + option(14, struct.pack("<q", 100))
    data = (
        section_header()
        + interface(1, nanos)
        + enhanced(0, 1_500_000_000, frame)
        + block(5, b"\0" * 8)  # interface statistics: ignored
        + section_header(">")
        + interface(1, option(9, bytes([0x80 | 10]), ">"), ">")  # 2^-10 s ticks
        + enhanced(0, 3 * 1024, frame, ">")
        + block(3, struct.pack(">I", len(frame)) + frame, ">")  # simple packet: no timestamp of its own
    )
    found = datagrams(data)
    assert [d.timestamp for d in found] == [pytest.approx(101.5), 3.0, 3.0]
    assert all(d.payload == b"hello" for d in found)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"garbage!", "not a pcap or pcapng capture"),
        (b"", "starts with nothing"),
        (pcap([(1.0, b"\0" * 40)], link=1)[:-10], "pcap record 0: file ends after 30 of 40 bytes"),
        (pcap([], link=1)[:10], "pcap file header"),
        (section_header() + struct.pack("<II", 1, 13), "pcapng block 1: bad block length 13"),
        (section_header() + enhanced(0, 1, b"x"), "packet names unknown interface 0"),
        (block(0x0A0D0D0A, b"\1\2\3\4" + b"\0" * 12), "bad byte-order magic"),
    ],
)
def test_malformed_captures_raise_capture_error(data: bytes, message: str) -> None:
    with pytest.raises(CaptureError, match=message):
        datagrams(data)


REAL_HEAD = PCAPNG.read_bytes()[:1500]


@settings(
    max_examples=400,
    deadline=timedelta(milliseconds=250),
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    data=st.one_of(
        st.binary(max_size=300),
        st.tuples(
            st.integers(0, len(REAL_HEAD) - 1), st.integers(0, 255), st.integers(0, len(REAL_HEAD))
        ).map(
            lambda t: REAL_HEAD[: t[0]] + bytes([REAL_HEAD[t[0]] ^ (t[1] or 1)]) + REAL_HEAD[t[0] + 1 : t[2]]
        ),
    )
)
def test_fuzz_captures_raise_only_capture_error(data: bytes) -> None:
    try:
        for datagram in datagrams(data):
            assert isinstance(datagram.payload, bytes)
    except CaptureError:
        pass
