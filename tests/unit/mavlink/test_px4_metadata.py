"""PX4's parameter metadata: file loading, the two messages pymavlink lacks, and MetadataClient against a
PX4-like responder (COMPONENT_METADATA / COMPONENT_INFORMATION, one-session MAVLink FTP with bursts,
the reply cache for resent requests) with faults injected: lost requests and replies, duplicates,
reordering, NAKs, a busy session, no burst support, a silent vehicle.  The same against PX4 itself is in
tests/px4/test_px4_metadata.py."""

from __future__ import annotations

import json
import lzma
import os
import queue
import random
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")

from arena_common.core.errors import ArenaError
from arena_common.mavlink import metadata as pm
from arena_common.mavlink.link import FrameSplitter, MavlinkLink, mavlink2
from tests.helpers import free_port

SYS = 21  # the vehicle (PX4 instance 20 would be 21)
GENERAL_PATH = "/etc/extras/component_general.json.xz"
PARAMS_PATH = "/etc/extras/parameters.json.xz"


# --- test data --------------------------------------------------------------------------------------
def make_parameters_doc(n: int = 400, seed: int = 7) -> dict[str, Any]:
    """A parameters.json shaped like PX4's: every third parameter reboot-required, noisy descriptions
    so that the xz file spans several bursts."""
    rng = random.Random(seed)
    params: list[dict[str, Any]] = []
    for i in range(n):
        p: dict[str, Any] = {
            "name": f"TST_P{i:04d}",
            "type": "Int32" if i % 2 else "Float",
            "default": i if i % 2 else i / 4,
            "group": "Test",
            "category": "Standard",
            "shortDesc": f"parameter {i}",
            "longDesc": "".join(rng.choice("abcdefghijklmnopqrstuvwxyz ") for _ in range(120)),
        }
        if i % 3 == 0:
            p["rebootRequired"] = True
        if i % 5 == 0:
            p["units"] = "m/s"
        params.append(p)
    params.append({"name": "EKF2_HGT_REF", "type": "Int32", "default": 1, "rebootRequired": True})
    params.append({"name": "ctl_bw", "type": "Int32", "default": 75, "units": "Hz"})  # a UAVCAN node's
    return {"version": 1, "parameters": params}


def xz(doc: dict[str, Any]) -> bytes:
    return lzma.compress(json.dumps(doc).encode(), format=lzma.FORMAT_XZ)


def general_doc(
    param_uri: str = "mftp://etc/extras/parameters.json.xz", crc: int | None = None
) -> dict[str, Any]:
    types: list[dict[str, Any]] = [
        {"type": 1, "uri": param_uri, "uriFallback": "https://example.invalid/parameters.json.xz"},
        {"type": 5, "uri": "mftp://etc/extras/actuators.json.xz", "fileCrc": 1},
    ]
    if crc is not None:
        types[0]["fileCrc"] = crc
    return {"version": 1, "metadataTypes": types}


@pytest.fixture(scope="module")
def params_doc() -> dict[str, Any]:
    return make_parameters_doc()


@pytest.fixture(scope="module")
def params_xz(params_doc: dict[str, Any]) -> bytes:
    data = xz(params_doc)
    assert len(data) > 20 * pm.FTP_DATA_MAX  # several bursts at the responder's chunk size
    return data


def vehicle_files(params_xz: bytes) -> dict[str, bytes]:
    general = json.dumps(general_doc(crc=pm.px4_crc32(params_xz))).encode()
    return {GENERAL_PATH: xz(json.loads(general)), PARAMS_PATH: params_xz}


# --- a PX4-like responder ---------------------------------------------------------------------------
class FakePx4:
    """What PX4 v1.16 does with our requests, byte for byte on the wire (pymavlink encodes and decodes).

    ``answers`` the message ids it answers to MAV_CMD_REQUEST_MESSAGE; one FTP session; a request whose
    sequence number is the last small reply's minus one gets that reply again (PX4's reply cache);
    BurstReadFile streams ``burst_chunk`` bytes then sets burst_complete, or NAKs EOF at the end.
    Faults: ``drop_request(req, n)`` / ``drop_reply(reply, n)`` (n counts from 0), ``duplicate``,
    ``reorder`` (burst packets swapped pairwise), ``open_nak`` (code, errno), ``busy`` (a session held by
    someone else until ResetSessions), ``burst`` False (UnknownCommand), ``ftp`` False (FTP ignored).
    """

    def __init__(self, files: dict[str, bytes], **faults: Any) -> None:
        self.files = files
        self.answers: set[int] = set(faults.pop("answers", {pm.COMPONENT_METADATA, pm.COMPONENT_INFORMATION}))
        self.general_uri: str = faults.pop("general_uri", "mftp://etc/extras/component_general.json.xz")
        self.burst_chunk: int = faults.pop("burst_chunk", 4000)
        self.drop_request: Callable[[pm.FtpReply, int], bool] = faults.pop("drop_request", lambda r, n: False)
        self.drop_reply: Callable[[pm.FtpReply, int], bool] = faults.pop("drop_reply", lambda r, n: False)
        self.duplicate: bool = faults.pop("duplicate", False)
        self.reorder: bool = faults.pop("reorder", False)
        self.open_nak: tuple[int, int] | None = faults.pop("open_nak", None)
        self.busy: bool = faults.pop("busy", False)
        self.burst: bool = faults.pop("burst", True)
        self.ftp: bool = faults.pop("ftp", True)
        self.foreign: bool = faults.pop("foreign", False)
        assert not faults, f"unknown faults {faults}"
        self.mav = mavlink2.MAVLink(None, srcSystem=SYS, srcComponent=1)
        self._parser = mavlink2.MAVLink(None)
        self.session: tuple[str, bytes] | None = None
        self.cache: list[int] | None = None  # the last reply of <= 4 data bytes (its payload)
        self.requests: list[pm.FtpReply] = []
        self.replies = 0
        self.lock = threading.Lock()

    # input: the bytes of one frame from the client; output: frames to deliver
    def handle(self, frame: bytes) -> list[bytes]:
        msg = self._parser.decode(bytearray(frame))
        with self.lock:
            if msg.get_msgId() == mavlink2.MAVLINK_MSG_ID_COMMAND_LONG:
                return self._command(msg)
            if msg.get_msgId() == pm.FILE_TRANSFER_PROTOCOL and self.ftp:
                assert msg.target_system == SYS and msg.target_component == 1, "FTP must target the vehicle"
                req = pm.decode_ftp_payload(msg.payload)
                n = len(self.requests)
                self.requests.append(req)
                if self.drop_request(req, n):
                    return []
                return self._ftp(req, msg.get_srcSystem(), msg.get_srcComponent())
        return []

    def _pack(self, msg: Any) -> bytes:
        return bytes(msg.pack(self.mav))

    def _command(self, msg: Any) -> list[bytes]:
        assert msg.target_system == SYS, "never target system 0"
        out = [self._pack(self.mav.command_ack_encode(msg.command, 0, 0, 0, msg.get_srcSystem(), 0))]
        wanted = int(msg.param1)
        if msg.command == pm.MAV_CMD_REQUEST_MESSAGE and wanted in self.answers:
            uri = self.general_uri.encode()
            crc = pm.px4_crc32(lzma.decompress(self.files[GENERAL_PATH]))
            if wanted == pm.COMPONENT_METADATA:
                m: Any = pm.MAVLink_component_metadata_message(1234, crc, uri)
            else:
                m = pm.MAVLink_component_information_message(1234, crc, uri)
            out.insert(0, self._pack(m))
        return out

    def _reply_frame(self, payload: list[int], to: tuple[int, int]) -> bytes:
        return self._pack(self.mav.file_transfer_protocol_encode(0, to[0], to[1], payload))

    def _ftp(self, req: pm.FtpReply, src_sys: int, src_comp: int) -> list[bytes]:
        to = (src_sys, src_comp)
        if self.cache is not None and (req.seq + 1) & 0xFFFF == pm.decode_ftp_payload(self.cache).seq:
            return [self._reply_frame(self.cache, to)]  # a resent request: the same reply again
        seq = (req.seq + 1) & 0xFFFF
        op = req.opcode
        frames: list[bytes] = []
        if self.foreign:
            other = pm.encode_ftp_payload(seq, pm.OP_ACK, req_opcode=op, data=b"\x00\x00\x00\x00")
            frames.append(self._reply_frame(other, (200, 190)))  # a ground station's answer, not ours

        def ack(data: bytes = b"", **kw: Any) -> None:
            payload = pm.encode_ftp_payload(seq, pm.OP_ACK, req_opcode=op, data=data, **kw)
            self._emit(frames, payload, to)

        def nak(code: int, errno: int | None = None) -> None:
            data = bytes([code]) if errno is None else bytes([code, errno])
            self._emit(frames, pm.encode_ftp_payload(seq, pm.OP_NAK, req_opcode=op, data=data), to)

        if op == pm.OP_OPEN_FILE_RO:
            path = req.data.decode()
            if self.open_nak is not None:
                nak(*self.open_nak)
            elif self.busy or self.session is not None:
                nak(pm.ERR_NO_SESSIONS_AVAILABLE)
            elif path not in self.files:
                nak(pm.ERR_FILE_NOT_FOUND)
            else:
                self.session = (path, self.files[path])
                ack(len(self.files[path]).to_bytes(4, "little"))
        elif op == pm.OP_RESET_SESSIONS:
            self.session, self.busy = None, False
            ack()
        elif op == pm.OP_TERMINATE_SESSION:
            if self.session is None:
                nak(pm.ERR_INVALID_SESSION)
            else:
                self.session = None
                ack()
        elif op == pm.OP_READ_FILE:
            if self.session is None:
                nak(pm.ERR_INVALID_SESSION)
            elif req.offset >= len(self.session[1]):
                nak(pm.ERR_EOF)
            else:
                # PX4 v1.16 reads the size asked for (earlier versions always read 239 bytes)
                ack(self.session[1][req.offset : req.offset + req.size], offset=req.offset)
        elif op == pm.OP_BURST_READ_FILE:
            if not self.burst:
                nak(pm.ERR_UNKNOWN_COMMAND)
            elif self.session is None:
                nak(pm.ERR_INVALID_SESSION)
            else:
                frames += self._stream(req, to)
        else:
            nak(pm.ERR_UNKNOWN_COMMAND)
        return frames

    def _stream(self, req: pm.FtpReply, to: tuple[int, int]) -> list[bytes]:
        assert self.session is not None
        data = self.session[1]
        frames: list[bytes] = []
        seq, offset, sent = req.seq + 1, req.offset, 0
        while True:
            if offset >= len(data):
                payload = pm.encode_ftp_payload(
                    seq, pm.OP_NAK, req_opcode=pm.OP_BURST_READ_FILE, data=bytes([pm.ERR_EOF])
                )
                self._emit(frames, payload, to)
                break
            chunk = data[offset : offset + pm.FTP_DATA_MAX]
            sent += len(chunk)
            done = sent >= self.burst_chunk
            payload = pm.encode_ftp_payload(
                seq,
                pm.OP_ACK,
                req_opcode=pm.OP_BURST_READ_FILE,
                offset=offset,
                data=chunk,
                burst_complete=done,
            )
            self._emit(frames, payload, to)
            offset += len(chunk)
            seq += 1
            if done:
                break
        if self.reorder:
            for i in range(0, len(frames) - 1, 2):
                frames[i], frames[i + 1] = frames[i + 1], frames[i]
        return frames

    def _emit(self, frames: list[bytes], payload: list[int], to: tuple[int, int]) -> None:
        reply = pm.decode_ftp_payload(payload)
        if reply.size <= 4:
            self.cache = payload
        n = self.replies
        self.replies += 1
        if self.drop_reply(reply, n):
            return
        frames.append(self._reply_frame(payload, to))
        if self.duplicate:
            frames.append(self._reply_frame(payload, to))


class FakeLink:
    """The client's side: ``mav`` + ``send``; frames from the vehicle come back through a byte-stream
    splitter and a decoder, and a reader thread hands them to the client like the gateway's reader."""

    def __init__(self, vehicle: FakePx4) -> None:
        self.vehicle = vehicle
        self.mav = mavlink2.MAVLink(None, srcSystem=245, srcComponent=191)
        self.client: pm.MetadataClient | None = None
        self._splitter = FrameSplitter(stream=True)  # the strictest: unknown ids would be dropped
        self._decoder = mavlink2.MAVLink(None)
        self._q: queue.Queue[bytes | None] = queue.Queue()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()
        self.sent = 0

    def send(self, msg: Any) -> bool:
        data = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        self.sent += 1
        for frame in self.vehicle.handle(data):
            self._q.put(frame)
        return True

    def _read(self) -> None:
        while True:
            data = self._q.get()
            if data is None:
                return
            for frame in self._splitter.feed(data):
                assert frame.checked
                msg = self._decoder.decode(bytearray(frame.raw))
                if self.client is not None:
                    self.client.on_message(msg, time.monotonic())

    def close(self) -> None:
        self._q.put(None)
        self._thread.join(timeout=2)


@pytest.fixture
def rig(params_xz: bytes) -> Iterator[Callable[..., tuple[pm.MetadataClient, FakePx4]]]:
    links: list[FakeLink] = []

    def make(client_kw: dict[str, Any] | None = None, **faults: Any) -> tuple[pm.MetadataClient, FakePx4]:
        files = faults.pop("files", None) or vehicle_files(params_xz)
        vehicle = FakePx4(files, **faults)
        link = FakeLink(vehicle)
        kw: dict[str, Any] = {"timeout": 0.1, "request_timeout": 0.2}
        kw.update(client_kw or {})
        client = pm.MetadataClient(link, SYS, **kw)
        link.client = client
        links.append(link)
        return client, vehicle

    yield make
    for link in links:
        link.close()


def deadline(seconds: float = 20.0) -> float:
    return time.monotonic() + seconds


# --- files, URIs, CRC -------------------------------------------------------------------------------
def test_load_parameters_json_plain_and_xz(tmp_path: Path, params_doc: dict[str, Any]) -> None:
    plain = tmp_path / "parameters.json"
    plain.write_text(json.dumps(params_doc))
    packed = tmp_path / "parameters.json.xz"
    packed.write_bytes(xz(params_doc))
    meta = pm.load_parameters_json(plain)
    assert meta == pm.load_parameters_json(packed) == pm.parse_parameters_json(params_doc)
    assert len(meta) == len(params_doc["parameters"])
    assert meta["EKF2_HGT_REF"] == {"type": "Int32", "rebootRequired": True, "default": 1, "units": ""}
    assert meta["TST_P0005"] == {"type": "Int32", "rebootRequired": False, "default": 5, "units": "m/s"}
    assert meta["TST_P0000"]["default"] == 0.0 and meta["TST_P0000"]["type"] == "Float"
    assert "ctl_bw" in meta  # names kept as PX4 spells them
    want = {p["name"] for p in params_doc["parameters"] if p.get("rebootRequired")}
    assert pm.reboot_required(meta) == frozenset(want)
    assert isinstance(pm.reboot_required(meta), frozenset)


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"not json", "not JSON"),
        (b'{"version": 1}', "no 'parameters' list"),
        (b'{"parameters": []}', "empty"),
        (b'{"parameters": [{"type": "Float"}]}', r"parameters\[0\] has no name"),
        (b'{"parameters": [{"name": "A"}]}', "parameter A has no type"),
        (b'{"parameters": [{"name": "A", "type": "Float", "rebootRequired": 1}]}', "rebootRequired"),
        (b'{"parameters": [{"name": "A", "type": "Float", "default": "x"}]}', "default"),
        (b"\xfd7zXZ\x00garbage", "not a valid xz file"),
        (lzma.compress(b'{"parameters": []}')[:-20], "xz"),
    ],
)
def test_bad_parameter_files_name_the_problem(tmp_path: Path, content: bytes, words: str) -> None:
    path = tmp_path / "parameters.json"
    path.write_bytes(content)
    with pytest.raises(pm.MetadataFormatError, match=words) as info:
        pm.load_parameters_json(path)
    assert str(path) in str(info.value)
    assert isinstance(info.value, ArenaError)


def test_missing_file_names_the_path(tmp_path: Path) -> None:
    with pytest.raises(pm.MetadataError, match=r"cannot read PX4 parameter metadata .*nowhere\.json"):
        pm.load_parameters_json(tmp_path / "nowhere.json")


@pytest.mark.parametrize(
    ("uri", "want"),
    [
        ("mftp://etc/extras/component_general.json.xz", (None, "/etc/extras/component_general.json.xz")),
        ("mftp:///fs/microsd/x.json", (None, "/fs/microsd/x.json")),
        ("mftp://[;comp=42]general.json", (42, "/general.json")),
        ("MFTP://[;comp=1]/etc/p.json.xz", (1, "/etc/p.json.xz")),
    ],
)
def test_parse_mftp_uri(uri: str, want: tuple[int | None, str]) -> None:
    assert pm.parse_mftp_uri(uri) == want


@pytest.mark.parametrize(
    "uri", ["https://px4.io/parameters.json.xz", "mftp://", "mftp://[;comp=0]/a", "ftp://a"]
)
def test_parse_mftp_uri_refuses(uri: str) -> None:
    with pytest.raises(pm.MetadataError, match="metadata URI"):
        pm.parse_mftp_uri(uri)


def test_px4_crc32_is_crc32part_from_zero() -> None:
    def reference(data: bytes) -> int:  # bit by bit: reflected 0xEDB88320, initial 0, no final XOR
        crc = 0
        for byte in data:
            crc ^= byte
            for _ in range(8):
                crc = (crc >> 1) ^ 0xEDB88320 if crc & 1 else crc >> 1
        return crc

    for data in (b"", b"123456789", bytes(range(256)) * 3):
        assert pm.px4_crc32(data) == reference(data)


def test_general_metadata_parse() -> None:
    types = pm.parse_general_metadata(xz(general_doc(crc=99)))
    assert types[1].uri == "mftp://etc/extras/parameters.json.xz" and types[1].crc == 99
    assert types[1].uri_fallback.startswith("https://")
    assert types[5].crc == 1
    with pytest.raises(pm.MetadataFormatError, match="metadataTypes"):
        pm.parse_general_metadata(b'{"version": 1}')
    with pytest.raises(pm.MetadataFormatError, match=r"metadataTypes\[0\]"):
        pm.parse_general_metadata(b'{"metadataTypes": [{"type": "1"}]}')


# --- wire format ------------------------------------------------------------------------------------
@pytest.mark.parametrize("stream", [True, False])
def test_component_messages_cross_a_mavlink_link(stream: bool) -> None:
    """Both messages unknown to pymavlink are CRC-checked by the frame splitter and decoded by the link."""
    vehicle = mavlink2.MAVLink(None, srcSystem=SYS, srcComponent=1)
    uri = b"mftp://etc/extras/component_general.json.xz"
    raw = pm.MAVLink_component_metadata_message(5, 0xA51A860E, uri).pack(vehicle)
    raw += pm.MAVLink_component_information_message(6, 7, uri, 8, b"mftp://p.json").pack(vehicle)
    frames = FrameSplitter(stream=stream).feed(raw)
    assert [(f.msgid, f.checked) for f in frames] == [(397, True), (395, True)]
    link = MavlinkLink("udpin:127.0.0.1:1", SYS)  # never opened: decode needs no socket
    meta, info = (link.decode(f) for f in frames)
    assert (meta.get_type(), meta.time_boot_ms, meta.file_crc, meta.uri) == (
        "COMPONENT_METADATA",
        5,
        0xA51A860E,
        uri.decode(),
    )
    assert (info.general_metadata_file_crc, info.general_metadata_uri) == (7, uri.decode())
    assert (info.peripherals_metadata_file_crc, info.peripherals_metadata_uri) == (8, "mftp://p.json")
    corrupt = bytearray(frames[0].raw)
    corrupt[15] ^= 0xFF
    assert FrameSplitter(stream=stream).feed(bytes(corrupt)) == []


def test_component_metadata_as_px4_v1_16_sends_it() -> None:
    """The payload PX4 v1.16 SITL sent (captured), trailing zeros cut as MAVLink 2 does."""
    payload = bytes.fromhex("984f00000e861aa5") + b"mftp://etc/extras/component_general.json.xz"
    header = bytes([0xFD, len(payload), 0, 0, 0, SYS, 1]) + (397).to_bytes(3, "little")
    crc = mavlink2.x25crc(bytearray(header[1:] + payload) + bytes([182])).crc
    frames = FrameSplitter(stream=True).feed(header + payload + crc.to_bytes(2, "little"))
    msg = MavlinkLink("udpin:127.0.0.1:1", SYS).decode(frames[0])
    assert (msg.time_boot_ms, msg.file_crc, msg.uri) == (
        20376,
        0xA51A860E,
        "mftp://etc/extras/component_general.json.xz",
    )


def test_ftp_payload_round_trip() -> None:
    payload = pm.encode_ftp_payload(
        65535, pm.OP_ACK, session=3, offset=70000, data=b"abc", req_opcode=15, burst_complete=True
    )
    assert len(payload) == 251
    r = pm.decode_ftp_payload(payload)
    assert (r.seq, r.session, r.opcode, r.size, r.req_opcode, r.burst_complete, r.offset, r.data) == (
        65535,
        3,
        pm.OP_ACK,
        3,
        15,
        True,
        70000,
        b"abc",
    )
    nak = pm.decode_ftp_payload(pm.encode_ftp_payload(1, pm.OP_NAK, data=bytes([pm.ERR_FAIL_ERRNO, 13])))
    assert nak.nak and nak.error == pm.ERR_FAIL_ERRNO and nak.errno == 13
    with pytest.raises(pm.FtpError, match="header"):
        pm.decode_ftp_payload(b"\x00" * 5)
    with pytest.raises(pm.FtpError):
        pm.encode_ftp_payload(0, pm.OP_ACK, data=bytes(240))


def test_target_system_zero_is_refused() -> None:
    link = FakeLink(FakePx4({}))
    try:
        with pytest.raises(pm.MetadataError, match="never 0"):
            pm.MetadataClient(link, 0)
    finally:
        link.close()


# --- fetching from the responder --------------------------------------------------------------------
def check(meta: dict[str, pm.ParamMeta], params_doc: dict[str, Any]) -> None:
    assert meta == pm.parse_parameters_json(params_doc)


def test_fetch(rig: Any, params_doc: dict[str, Any], params_xz: bytes) -> None:
    client, vehicle = rig()
    meta = client.fetch(deadline())
    check(meta, params_doc)
    info = client.info
    assert info.source_message == "COMPONENT_METADATA" and info.requests == 1
    assert info.general_uri == "mftp://etc/extras/component_general.json.xz"
    assert info.parameter_uri == "mftp://etc/extras/parameters.json.xz"
    assert info.parameter_size == len(params_xz) and info.parameter_json_size == len(json.dumps(params_doc))
    assert info.general_crc_ok is True and info.parameter_crc_ok is True
    assert info.parameters == len(meta) and info.reboot_required == len(pm.reboot_required(meta))
    assert info.ftp["bursts"] >= 2 + len(params_xz) // vehicle.burst_chunk  # burst_complete → next burst
    assert info.ftp["reads"] == 0 and info.ftp["resent"] == 0 and info.ftp["resets"] == 0
    assert vehicle.session is None  # terminated
    ops = [r.opcode for r in vehicle.requests]
    assert ops[0] == pm.OP_OPEN_FILE_RO and ops.count(pm.OP_TERMINATE_SESSION) == 2
    # the same client again: sequence numbers go on, the result is the same
    assert client.fetch(deadline()) == meta


def test_only_component_information(rig: Any, params_doc: dict[str, Any]) -> None:
    client, _ = rig(answers={pm.COMPONENT_INFORMATION})
    check(client.fetch(deadline()), params_doc)
    assert client.info.source_message == "COMPONENT_INFORMATION" and client.info.requests == 2


def test_request_messages_option(rig: Any, params_doc: dict[str, Any]) -> None:
    client, _ = rig({"request_messages": (pm.COMPONENT_INFORMATION,)})
    check(client.fetch(deadline()), params_doc)
    assert client.info.source_message == "COMPONENT_INFORMATION" and client.info.requests == 1
    with pytest.raises(pm.MetadataError, match="request_messages"):
        pm.MetadataClient(client.link, SYS, request_messages=(0,))


def test_silent_vehicle_times_out_naming_both_messages(rig: Any) -> None:
    client, _ = rig({"request_attempts": 4, "request_timeout": 0.05}, answers=set())
    words = r"COMPONENT_METADATA \(397\) or COMPONENT_INFORMATION \(395\) from system 21 component 1"
    with pytest.raises(pm.MetadataTimeout, match=words):
        client.fetch(deadline())
    assert client.info.requests == 4


def test_silent_ftp_server_times_out_naming_the_file(rig: Any) -> None:
    client, _ = rig({"attempts": 3, "timeout": 0.05}, ftp=False)
    words = r"OpenFileRO '/etc/extras/component_general\.json\.xz': no answer from system 21 .* 3 tries"
    with pytest.raises(pm.MetadataTimeout, match=words):
        client.fetch(deadline())
    assert client.stats["sent"] >= 3


def test_deadline_bounds_a_fetch(rig: Any) -> None:
    client, _ = rig({"attempts": 100, "timeout": 0.05}, ftp=False)
    with pytest.raises(pm.MetadataTimeout):
        client.fetch(time.monotonic() + 0.5)


@pytest.mark.parametrize(
    ("nak", "words"),
    [
        ((pm.ERR_FILE_NOT_FOUND, None), "NAK FileNotFound"),
        ((pm.ERR_FAIL_ERRNO, 13), r"NAK FailErrno \(errno 13: Permission denied\)"),
        ((pm.ERR_FAIL, None), "NAK Fail"),
    ],
)
def test_open_refused(rig: Any, nak: tuple[int, int | None], words: str) -> None:
    client, _ = rig(open_nak=nak)
    with pytest.raises(pm.FtpNak, match=words) as info:
        client.fetch(deadline())
    err = info.value
    assert (err.op_name, err.code, err.errno) == ("OpenFileRO", nak[0], nak[1])
    assert err.path == GENERAL_PATH and "system 21 component 1" in str(err)


def test_missing_parameter_file(rig: Any, params_xz: bytes) -> None:
    files = vehicle_files(params_xz)
    del files[PARAMS_PATH]
    client, _ = rig(files=files)
    with pytest.raises(pm.FtpNak, match=r"parameters\.json\.xz.*FileNotFound") as info:
        client.fetch(deadline())
    assert info.value.code_name == "FileNotFound"


def test_busy_session_is_reset(rig: Any, params_doc: dict[str, Any]) -> None:
    client, _ = rig(busy=True)
    check(client.fetch(deadline()), params_doc)
    assert client.info.ftp["resets"] == 1


def test_busy_session_left_alone(rig: Any) -> None:
    client, _ = rig({"reset_busy": False}, busy=True)
    with pytest.raises(pm.FtpNak, match="NoSessionsAvailable"):
        client.fetch(deadline())


def test_no_burst_support_reads_chunk_by_chunk(
    rig: Any, params_doc: dict[str, Any], params_xz: bytes
) -> None:
    client, _ = rig(burst=False)
    check(client.fetch(deadline()), params_doc)
    assert client.info.ftp["reads"] >= len(params_xz) // pm.FTP_DATA_MAX


def test_burst_disabled_by_option(rig: Any, params_doc: dict[str, Any]) -> None:
    client, vehicle = rig({"burst": False})
    check(client.fetch(deadline()), params_doc)
    assert pm.OP_BURST_READ_FILE not in {r.opcode for r in vehicle.requests}


def test_lost_burst_packets_are_read_again(rig: Any, params_doc: dict[str, Any]) -> None:
    def drop(reply: pm.FtpReply, n: int) -> bool:
        return reply.req_opcode == pm.OP_BURST_READ_FILE and n % 7 == 3

    client, _ = rig(drop_reply=drop)
    check(client.fetch(deadline()), params_doc)
    assert client.info.ftp["reads"] > 0  # the holes, with ReadFile


def test_many_holes_burst_again(rig: Any, params_doc: dict[str, Any]) -> None:
    def drop(reply: pm.FtpReply, n: int) -> bool:
        return reply.req_opcode == pm.OP_BURST_READ_FILE and n % 2 == 0

    client, _ = rig({"max_hole_reads": 2}, drop_reply=drop)
    check(client.fetch(deadline()), params_doc)


def test_lost_requests_and_replies_are_resent(rig: Any, params_doc: dict[str, Any]) -> None:
    """The first try of every Open, Terminate and Burst request is lost, and so is the answer to the
    second Open: the client resends with the same sequence number (the responder answers the third
    Open from its reply cache, as PX4 does), and bursts again after a silent one."""
    seen: set[tuple[int, int]] = set()
    first_burst = [False]

    def drop_req(req: pm.FtpReply, n: int) -> bool:
        if req.opcode == pm.OP_OPEN_FILE_RO:
            first_burst[0] = True
        if req.opcode == pm.OP_BURST_READ_FILE:
            lost, first_burst[0] = first_burst[0], False
            return lost
        key = (req.seq, req.opcode)
        if req.opcode not in (pm.OP_OPEN_FILE_RO, pm.OP_TERMINATE_SESSION) or key in seen:
            return False
        seen.add(key)
        return True

    lost: set[int] = set()

    def drop_rep(reply: pm.FtpReply, n: int) -> bool:
        if reply.req_opcode == pm.OP_OPEN_FILE_RO and reply.seq not in lost:
            lost.add(reply.seq)
            return True
        return False

    client, vehicle = rig({"attempts": 4}, drop_request=drop_req, drop_reply=drop_rep)
    check(client.fetch(deadline()), params_doc)
    assert client.info.ftp["resent"] >= 6
    assert client.info.ftp["reads"] == 0  # the bursts got through in the end
    opens = [r for r in vehicle.requests if r.opcode == pm.OP_OPEN_FILE_RO]
    assert len({r.seq for r in opens}) == 2 and len(opens) == 6  # 3 tries per file, one number each
    assert vehicle.session is None


def test_duplicated_and_reordered_replies(rig: Any, params_doc: dict[str, Any]) -> None:
    client, _ = rig(duplicate=True, reorder=True)
    check(client.fetch(deadline()), params_doc)
    assert client.info.ftp["duplicates"] > 0
    assert client.info.ftp["stale"] > 0  # the second copy of each small reply answers nothing current


def test_foreign_ftp_messages_are_ignored(rig: Any, params_doc: dict[str, Any]) -> None:
    client, _ = rig(foreign=True)
    check(client.fetch(deadline()), params_doc)
    assert client.info.ftp["foreign"] > 0


def test_corrupt_parameter_file(rig: Any, params_xz: bytes) -> None:
    files = vehicle_files(params_xz)
    files[PARAMS_PATH] = params_xz[:100] + bytes(100) + params_xz[200:]
    client, _ = rig(files=files)
    with pytest.raises(pm.MetadataFormatError, match=r"parameters\.json\.xz: not a valid xz file.*CRC32"):
        client.fetch(deadline())
    assert client.info.parameter_crc_ok is False


def test_general_file_without_parameters(rig: Any, params_xz: bytes) -> None:
    files = vehicle_files(params_xz)
    files[GENERAL_PATH] = xz({"version": 1, "metadataTypes": [{"type": 5, "uri": "mftp://a.json"}]})
    client, _ = rig(files=files)
    with pytest.raises(pm.MetadataFormatError, match=r"no parameter metadata \(type 1\); types \[5\]"):
        client.fetch(deadline())


def test_parameter_metadata_on_the_internet_only(rig: Any, params_xz: bytes) -> None:
    files = vehicle_files(params_xz)
    files[GENERAL_PATH] = xz(general_doc(param_uri="https://example.invalid/parameters.json.xz"))
    client, _ = rig(files=files)
    with pytest.raises(pm.MetadataError, match="not on the vehicle"):
        client.fetch(deadline())


def test_read_file_api(rig: Any, params_xz: bytes) -> None:
    client, _ = rig()
    assert client.read_file(PARAMS_PATH, deadline()) == params_xz


# --- over a real MavlinkLink (UDP) with the responder behind a socket --------------------------------
def test_fetch_parameter_metadata_over_udp(params_doc: dict[str, Any], params_xz: bytes) -> None:
    vehicle = FakePx4(vehicle_files(params_xz), burst_chunk=35000)
    port = free_port(socket.SOCK_DGRAM)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.05)
    stop = threading.Event()

    def serve() -> None:
        splitter = FrameSplitter(stream=False)
        while not stop.is_set():
            try:
                data, addr = sock.recvfrom(65535)
            except TimeoutError:
                continue
            for frame in splitter.feed(data):
                for out in vehicle.handle(frame.raw):
                    sock.sendto(out, addr)
                    time.sleep(0)  # let the client's reader keep up, as a real link paces its output

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    link = MavlinkLink(f"udpout:127.0.0.1:{port}", SYS)
    link.open()
    try:
        seen: list[int] = []
        meta = pm.fetch_parameter_metadata(
            link, SYS, deadline(), on_frame=lambda frame, now: seen.append(frame.msgid)
        )
        check(meta, params_doc)
        assert pm.COMPONENT_METADATA in seen and pm.FILE_TRANSFER_PROTOCOL in seen
    finally:
        stop.set()
        server.join(timeout=2)
        link.close()
        sock.close()
