"""Read recorded NatNet traffic: UDP datagrams from pcap/pcapng captures, and decoded-frame JSON lines.

:func:`read_udp` yields every UDP datagram of a capture with its capture time, so a Motive emulator can
replay a session at its original timing. Link layers understood: Ethernet (with VLAN tags), Linux cooked
(SLL and SLL2), raw IP and BSD loopback; IPv4 (fragments are reassembled) and IPv6 without extension
headers. Packets that are not UDP, or were cut short by the capture's snap length, are skipped.

:func:`read_frames_jsonl` reads ``traffic_frames_decoded.jsonl``-style files (one decoded frame per line)
back into :class:`~arena_common.mocap.natnet.Frame` objects; :func:`frame_to_record` writes that format.
"""

from __future__ import annotations

import json
import socket
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, NamedTuple

from arena_common.mocap.natnet import Frame, RigidBody

__all__ = [
    "CaptureError",
    "RecordedFrame",
    "UdpDatagram",
    "frame_to_record",
    "iter_udp",
    "read_frames_jsonl",
    "read_udp",
]


class CaptureError(ValueError):
    """A capture or JSON-lines file is malformed."""


class UdpDatagram(NamedTuple):
    """One UDP datagram of a capture: capture time (seconds since the epoch), source and destination
    ``(address, port)``, payload."""

    timestamp: float
    src: tuple[str, int]
    dst: tuple[str, int]
    payload: bytes


class RecordedFrame(NamedTuple):
    """A decoded frame and the time it was received (seconds since the epoch)."""

    receive_time: float
    frame: Frame


# Link-layer types (https://www.tcpdump.org/linktypes.html)
_LINK_NULL = 0
_LINK_ETHERNET = 1
_LINK_RAW = 101
_LINK_LINUX_SLL = 113
_LINK_IPV4 = 228
_LINK_IPV6 = 229
_LINK_LINUX_SLL2 = 276
_LINK_RAW_ALIASES = (12, 14)  # DLT_RAW on some BSDs

_PCAP_MAGICS = {
    b"\xd4\xc3\xb2\xa1": ("<", 1e-6),
    b"\xa1\xb2\xc3\xd4": (">", 1e-6),
    b"\x4d\x3c\xb2\xa1": ("<", 1e-9),
    b"\xa1\xb2\x3c\x4d": (">", 1e-9),
}
_PCAPNG_SHB = 0x0A0D0D0A
_PCAPNG_BYTE_ORDER_MAGIC = 0x1A2B3C4D
_MAX_BLOCK = 1 << 26  # refuse absurd block lengths rather than allocating them

_ETHERTYPE_IPV4 = 0x0800
_ETHERTYPE_IPV6 = 0x86DD
_ETHERTYPE_VLAN = (0x8100, 0x88A8, 0x9100)
_IPPROTO_UDP = 17


@dataclass(slots=True)
class _Interface:
    link_type: int
    resolution: float  # seconds per timestamp unit
    offset: float  # seconds added to every timestamp (pcapng if_tsoffset)


class _Reassembler:
    """IPv4 fragment reassembly keyed by (source, destination, protocol, identification)."""

    MAX_PENDING = 256  # datagrams with missing fragments kept at once; the oldest is dropped beyond

    def __init__(self) -> None:
        self._pending: dict[tuple[bytes, bytes, int, int], dict[int, bytes]] = {}
        self._total: dict[tuple[bytes, bytes, int, int], int] = {}

    def add(self, key: tuple[bytes, bytes, int, int], offset: int, more: bool, data: bytes) -> bytes | None:
        if key not in self._pending and len(self._pending) >= self.MAX_PENDING:
            oldest = next(iter(self._pending))
            del self._pending[oldest]
            self._total.pop(oldest, None)
        parts = self._pending.setdefault(key, {})
        parts[offset] = data
        if not more:
            self._total[key] = offset + len(data)
        total = self._total.get(key)
        if total is None:
            return None
        covered = 0
        for start in sorted(parts):
            if start > covered:
                return None
            covered = max(covered, start + len(parts[start]))
        if covered < total:
            return None
        whole = bytearray(total)
        for start, chunk in parts.items():
            whole[start : start + len(chunk)] = chunk
        del self._pending[key]
        del self._total[key]
        return bytes(whole[:total])


def _udp_from_ip(packet: bytes, timestamp: float, frags: _Reassembler) -> UdpDatagram | None:
    if not packet:
        return None
    version = packet[0] >> 4
    if version == 4:
        if len(packet) < 20:
            return None
        ihl = (packet[0] & 0x0F) * 4
        total_length, ident, flags_frag, _, proto = struct.unpack_from(">HHHBB", packet, 2)
        if proto != _IPPROTO_UDP or ihl < 20 or total_length < ihl or len(packet) < total_length:
            return None
        src, dst = packet[12:16], packet[16:20]
        body = packet[ihl:total_length]
        more = bool(flags_frag & 0x2000)
        frag_offset = (flags_frag & 0x1FFF) * 8
        if more or frag_offset:
            whole = frags.add((src, dst, proto, ident), frag_offset, more, body)
            if whole is None:
                return None
            body = whole
        src_text, dst_text = socket.inet_ntop(socket.AF_INET, src), socket.inet_ntop(socket.AF_INET, dst)
    elif version == 6:
        if len(packet) < 40:
            return None
        payload_length, next_header = struct.unpack_from(">HB", packet, 4)
        if next_header != _IPPROTO_UDP or len(packet) < 40 + payload_length:
            return None
        body = packet[40 : 40 + payload_length]
        src_text = socket.inet_ntop(socket.AF_INET6, packet[8:24])
        dst_text = socket.inet_ntop(socket.AF_INET6, packet[24:40])
    else:
        return None
    if len(body) < 8:
        return None
    sport, dport, udp_length = struct.unpack_from(">HHH", body, 0)
    if udp_length < 8 or udp_length > len(body):
        return None
    return UdpDatagram(timestamp, (src_text, sport), (dst_text, dport), bytes(body[8:udp_length]))


def _ip_from_link(link_type: int, frame: bytes) -> bytes | None:
    if link_type == _LINK_ETHERNET:
        if len(frame) < 14:
            return None
        offset = 12
        (ethertype,) = struct.unpack_from(">H", frame, offset)
        while ethertype in _ETHERTYPE_VLAN and len(frame) >= offset + 6:
            offset += 4
            (ethertype,) = struct.unpack_from(">H", frame, offset)
        if ethertype not in (_ETHERTYPE_IPV4, _ETHERTYPE_IPV6):
            return None
        return frame[offset + 2 :]
    if link_type == _LINK_LINUX_SLL:
        if len(frame) < 16 or struct.unpack_from(">H", frame, 14)[0] not in (
            _ETHERTYPE_IPV4,
            _ETHERTYPE_IPV6,
        ):
            return None
        return frame[16:]
    if link_type == _LINK_LINUX_SLL2:
        if len(frame) < 20 or struct.unpack_from(">H", frame, 0)[0] not in (_ETHERTYPE_IPV4, _ETHERTYPE_IPV6):
            return None
        return frame[20:]
    if link_type in (_LINK_RAW, _LINK_IPV4, _LINK_IPV6, *_LINK_RAW_ALIASES):
        return frame
    if link_type == _LINK_NULL:
        # The family is in the capturing host's byte order: accept either.
        if len(frame) < 4:
            return None
        families = (2, 24, 28, 30)  # AF_INET, and AF_INET6 on the BSDs and macOS
        little, big = struct.unpack_from("<I", frame, 0)[0], struct.unpack_from(">I", frame, 0)[0]
        return frame[4:] if little in families or big in families else None
    return None


def _read_exact(stream: IO[bytes], size: int, what: str) -> bytes:
    data = stream.read(size)
    if len(data) != size:
        raise CaptureError(f"{what}: file ends after {len(data)} of {size} bytes")
    return data


def _iter_pcap(stream: IO[bytes], magic: bytes) -> Iterator[tuple[int, float, bytes]]:
    order, resolution = _PCAP_MAGICS[magic]
    header = _read_exact(stream, 20, "pcap file header")
    link_type = struct.unpack_from(order + "I", header, 16)[0] & 0xFFFF
    record = struct.Struct(order + "IIII")
    index = 0
    while True:
        head = stream.read(16)
        if not head:
            return
        if len(head) != 16:
            raise CaptureError(f"pcap record {index}: header cut short ({len(head)} of 16 bytes)")
        seconds, fraction, captured, _ = record.unpack(head)
        if captured > _MAX_BLOCK:
            raise CaptureError(f"pcap record {index}: captured length {captured} is absurd")
        data = _read_exact(stream, captured, f"pcap record {index}")
        yield link_type, seconds + fraction * resolution, data
        index += 1


def _pcapng_resolution(options: bytes, order: str) -> tuple[float, float]:
    resolution, offset = 1e-6, 0.0
    pos = 0
    while pos + 4 <= len(options):
        code, length = struct.unpack_from(order + "HH", options, pos)
        value = options[pos + 4 : pos + 4 + length]
        if code == 0:
            break
        if code == 9 and len(value) >= 1:  # if_tsresol
            exponent = value[0] & 0x7F
            resolution = 2.0**-exponent if value[0] & 0x80 else 10.0**-exponent
        elif code == 14 and len(value) >= 8:  # if_tsoffset
            offset = float(struct.unpack_from(order + "q", value, 0)[0])
        pos += 4 + ((length + 3) & ~3)
    return resolution, offset


def _iter_pcapng(stream: IO[bytes], first: bytes) -> Iterator[tuple[int, float, bytes]]:
    order = "<"
    interfaces: list[_Interface] = []
    last_time = 0.0
    index = 0
    pending = first  # the start of the first block, already read to recognise the format
    while True:
        head = pending + stream.read(8 - len(pending))
        pending = b""
        if not head:
            return
        if len(head) != 8:
            raise CaptureError(f"pcapng block {index}: header cut short ({len(head)} of 8 bytes)")
        block_type = struct.unpack_from("<I", head, 0)[0]
        if block_type == _PCAPNG_SHB:
            magic = _read_exact(stream, 4, f"pcapng block {index} byte-order magic")
            if struct.unpack("<I", magic)[0] == _PCAPNG_BYTE_ORDER_MAGIC:
                order = "<"
            elif struct.unpack(">I", magic)[0] == _PCAPNG_BYTE_ORDER_MAGIC:
                order = ">"
            else:
                raise CaptureError(f"pcapng block {index}: bad byte-order magic {magic.hex()}")
            interfaces = []
            length = struct.unpack_from(order + "I", head, 4)[0]
            if length < 28 or length % 4 or length > _MAX_BLOCK:
                raise CaptureError(f"pcapng block {index}: bad section header length {length}")
            _read_exact(stream, length - 12, f"pcapng block {index}")
            index += 1
            continue
        block_type, length = struct.unpack_from(order + "II", head, 0)
        if length < 12 or length % 4 or length > _MAX_BLOCK:
            raise CaptureError(f"pcapng block {index}: bad block length {length}")
        body = _read_exact(stream, length - 8, f"pcapng block {index}")[:-4]
        if block_type == 1:  # interface description
            if len(body) < 8:
                raise CaptureError(f"pcapng block {index}: interface description cut short")
            link_type = struct.unpack_from(order + "H", body, 0)[0]
            resolution, offset = _pcapng_resolution(body[8:], order)
            interfaces.append(_Interface(link_type, resolution, offset))
        elif block_type in (6, 2):  # enhanced packet, obsolete packet
            if len(body) < 20:
                raise CaptureError(f"pcapng block {index}: packet block cut short")
            if block_type == 6:
                iface, high, low, captured = struct.unpack_from(order + "IIII", body, 0)
            else:
                iface, _, high, low, captured = struct.unpack_from(order + "HHIII", body, 0)
            if iface >= len(interfaces):
                raise CaptureError(f"pcapng block {index}: packet names unknown interface {iface}")
            if captured > len(body) - 20:
                raise CaptureError(f"pcapng block {index}: captured length {captured} exceeds its block")
            info = interfaces[iface]
            last_time = ((high << 32) | low) * info.resolution + info.offset
            yield info.link_type, last_time, body[20 : 20 + captured]
        elif block_type == 3:  # simple packet: no timestamp, keep the previous one
            if not interfaces or len(body) < 4:
                raise CaptureError(f"pcapng block {index}: simple packet without interface or length")
            original = struct.unpack_from(order + "I", body, 0)[0]
            yield interfaces[0].link_type, last_time, body[4 : 4 + original]
        index += 1


def iter_udp(stream: IO[bytes]) -> Iterator[UdpDatagram]:
    """Yield the UDP datagrams of a pcap or pcapng capture read from a binary stream, in file order."""
    magic = stream.read(4)
    if magic in _PCAP_MAGICS:
        records = _iter_pcap(stream, magic)
    elif len(magic) == 4 and struct.unpack("<I", magic)[0] == _PCAPNG_SHB:
        records = _iter_pcapng(stream, magic)
    else:
        raise CaptureError(f"not a pcap or pcapng capture (starts with {magic.hex() or 'nothing'})")
    frags = _Reassembler()
    for link_type, timestamp, frame in records:
        packet = _ip_from_link(link_type, frame)
        if packet is None:
            continue
        datagram = _udp_from_ip(packet, timestamp, frags)
        if datagram is not None:
            yield datagram


def read_udp(path: str | Path, *, port: int | None = None) -> Iterator[UdpDatagram]:
    """Yield the UDP datagrams of the pcap/pcapng file at ``path`` (those from or to ``port`` if given)."""
    with open(path, "rb") as stream:
        for datagram in iter_udp(stream):
            if port is None or port in (datagram.src[1], datagram.dst[1]):
                yield datagram


# ------------------------------------------------------------------------------------------------------------
# Decoded frames as JSON lines
# ------------------------------------------------------------------------------------------------------------


def _floats(value: Any, size: int, where: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != size:
        raise CaptureError(f"{where}: expected a list of {size} numbers, got {value!r}")
    try:
        return tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise CaptureError(f"{where}: expected numbers, got {value!r}") from None


def _record_to_frame(record: Any, where: str) -> RecordedFrame:
    if not isinstance(record, dict):
        raise CaptureError(f"{where}: expected a JSON object")
    try:
        bodies = []
        for i, rb in enumerate(record.get("rigid_bodies", [])):
            body_where = f"{where}: rigid_bodies[{i}]"
            x, y, z = _floats(rb["pos"], 3, body_where + ".pos")
            qx, qy, qz, qw = _floats(rb["quat_xyzw"], 4, body_where + ".quat_xyzw")
            mean_error = rb.get("mean_error")
            valid = rb.get("tracking_valid", True)
            if not isinstance(valid, bool):
                raise CaptureError(f"{body_where}.tracking_valid: expected true or false")
            bodies.append(
                RigidBody(
                    int(rb["id"]),
                    (x, y, z),
                    (qx, qy, qz, qw),
                    None if mean_error is None else float(mean_error),
                    valid,
                    rb.get("params"),
                )
            )

        def optional_int(key: str) -> int | None:
            value = record.get(key)
            return None if value is None else int(value)

        timestamp = record.get("timestamp")
        frame = Frame(
            frame_number=int(record["frame"]),
            rigid_bodies=tuple(bodies),
            timecode=int(record.get("timecode", 0)),
            subframe=int(record.get("subframe", 0)),
            timestamp=None if timestamp is None else float(timestamp),
            cam_mid_exposure=optional_int("cam_mid_exposure"),
            data_received=optional_int("cam_data_received"),
            transmit=optional_int("transmit"),
            precision_secs=optional_int("precision_secs"),
            precision_fraction=optional_int("precision_fraction"),
            params=int(record.get("params", 0)),
            n_labeled_markers=int(record.get("n_labeled_markers", 0)),
        )
        return RecordedFrame(float(record.get("pcap_t", 0.0)), frame)
    except KeyError as exc:
        raise CaptureError(f"{where}: missing field {exc}") from None
    except (TypeError, ValueError) as exc:
        if isinstance(exc, CaptureError):
            raise
        raise CaptureError(f"{where}: {exc}") from None


def read_frames_jsonl(path: str | Path) -> Iterator[RecordedFrame]:
    """Yield the frames of a ``traffic_frames_decoded.jsonl``-style file: one JSON object per line with
    ``pcap_t`` (receive time), ``frame``, ``timestamp``, ``cam_mid_exposure``, ``cam_data_received``,
    ``transmit``, ``rigid_bodies`` (``id``, ``pos``, ``quat_xyzw``, ``mean_error``, ``tracking_valid``) and
    ``n_labeled_markers``. Blank lines are skipped."""
    with open(path, encoding="utf-8") as stream:
        for number, line in enumerate(stream, start=1):
            if not line.strip():
                continue
            where = f"{path}:{number}"
            try:
                record = json.loads(line)
            except json.JSONDecodeError as exc:
                raise CaptureError(f"{where}: not JSON: {exc}") from None
            yield _record_to_frame(record, where)


def frame_to_record(frame: Frame, receive_time: float) -> dict[str, Any]:
    """The JSON-lines record of a frame (the inverse of what :func:`read_frames_jsonl` reads)."""
    return {
        "pcap_t": receive_time,
        "frame": frame.frame_number,
        "timestamp": frame.timestamp,
        "cam_mid_exposure": frame.cam_mid_exposure,
        "cam_data_received": frame.data_received,
        "transmit": frame.transmit,
        "rigid_bodies": [
            {
                "id": rb.id,
                "pos": list(rb.pos),
                "quat_xyzw": list(rb.quat_xyzw),
                "mean_error": rb.mean_error,
                "tracking_valid": rb.tracking_valid,
            }
            for rb in frame.rigid_bodies
        ],
        "n_labeled_markers": frame.n_labeled_markers,
    }
