"""Fetch PX4's parameter metadata from the vehicle: component metadata, then the files over MAVLink FTP."""

from __future__ import annotations

import random
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final, Protocol

from arena_common.mavlink.link import MavlinkLink
from arena_common.mavlink.metadata._errors import MetadataError, MetadataFormatError, MetadataTimeout
from arena_common.mavlink.metadata.ftp import (
    ERR_EOF,
    ERR_NO_SESSIONS_AVAILABLE,
    ERR_UNKNOWN_COMMAND,
    FTP_DATA_MAX,
    OP_ACK,
    OP_BURST_READ_FILE,
    OP_NAK,
    OP_OPEN_FILE_RO,
    OP_READ_FILE,
    OP_RESET_SESSIONS,
    OP_TERMINATE_SESSION,
    OPCODE_NAMES,
    FtpError,
    FtpNak,
    FtpReply,
    decode_ftp_payload,
    encode_ftp_payload,
)
from arena_common.mavlink.metadata.messages import (
    COMP_METADATA_TYPE_PARAMETER,
    COMPONENT_INFORMATION,
    COMPONENT_METADATA,
    FILE_TRANSFER_PROTOCOL,
    HANDLED_MESSAGES,
    MAV_CMD_REQUEST_MESSAGE,
)
from arena_common.mavlink.metadata.parameters import (
    ParamMeta,
    _CorruptFile,
    _unpack,
    parse_general_metadata,
    parse_mftp_uri,
    parse_parameters_json,
    reboot_required,
)


# --- the client -------------------------------------------------------------------------------------
class _Link(Protocol):
    """What the client needs of a link: a pymavlink encoder (``mav``, with ``srcSystem``) and ``send``."""

    mav: Any

    def send(self, msg: Any) -> bool: ...


@dataclass
class FetchInfo:
    """How the last :meth:`MetadataClient.fetch` went: what PX4 answered, sizes, CRCs, counts, times."""

    source_message: str = ""  # COMPONENT_METADATA or COMPONENT_INFORMATION
    general_uri: str = ""
    general_size: int = 0  # bytes transferred
    general_crc_ok: bool | None = None
    parameter_uri: str = ""
    parameter_size: int = 0
    parameter_json_size: int = 0
    parameter_crc_ok: bool | None = None
    parameters: int = 0
    reboot_required: int = 0
    requests: int = 0  # REQUEST_MESSAGE commands sent
    seconds: dict[str, float] = field(default_factory=dict)  # per phase: request, general, parameters, total
    ftp: dict[str, int] = field(default_factory=dict)  # counters, see MetadataClient.stats


_STAT_NAMES: Final = (
    "sent",
    "resent",
    "send_failed",
    "bursts",
    "burst_packets",
    "reads",
    "duplicates",
    "stale",
    "naks",
    "resets",
)


class MetadataClient:
    """PX4's parameter metadata from the vehicle: component metadata request, then MAVLink FTP.

    ``link`` is anything with a pymavlink encoder ``mav`` and ``send(msg)`` (a
    :class:`~arena_common.mavlink.link.MavlinkLink`); whoever reads the link hands every message of
    :data:`HANDLED_MESSAGES` to :meth:`on_message`; :meth:`fetch` blocks in another thread.

    Each FTP request waits ``timeout`` s for its answer and is sent up to ``attempts`` times; the
    component metadata request asks for ``request_messages`` in turn (COMPONENT_METADATA, then the
    older COMPONENT_INFORMATION), each attempt waiting ``request_timeout`` s.  A burst silent for
    ``timeout`` s is over; the holes it left are read with ReadFile (or a new burst from the first hole
    when there are more than ``max_hole_reads``; two bursts in a row that bring nothing, or a server
    without BurstReadFile, switch to ReadFile for the rest).  An open refused with NoSessionsAvailable
    (PX4 serves one FTP session per link, e.g. one left behind by an earlier client, or a ground
    station's through the gateway's forwarder) resets the link's sessions and opens again when
    ``reset_busy`` is true.  Never targets system 0.
    """

    def __init__(
        self,
        link: _Link,
        target_system: int,
        target_component: int = 1,
        *,
        timeout: float = 0.5,
        attempts: int = 6,
        request_timeout: float = 1.0,
        request_attempts: int = 6,
        request_messages: tuple[int, ...] = (COMPONENT_METADATA, COMPONENT_INFORMATION),
        burst: bool = True,
        max_hole_reads: int = 32,
        reset_busy: bool = True,
        max_file_size: int = 16 << 20,
        initial_seq: int | None = None,
    ) -> None:
        if not 1 <= int(target_system) <= 255:
            raise MetadataError(f"target system must be 1..255 (never 0, broadcast), got {target_system}")
        if not 1 <= int(target_component) <= 255:
            raise MetadataError(f"target component must be within 1..255, got {target_component}")
        self.link = link
        self.target_system = int(target_system)
        self.target_component = int(target_component)
        self.timeout = timeout
        self.attempts = max(1, attempts)
        self.request_timeout = request_timeout
        self.request_attempts = max(1, request_attempts)
        if not request_messages or not set(request_messages) <= {COMPONENT_METADATA, COMPONENT_INFORMATION}:
            raise MetadataError(
                f"request_messages must name COMPONENT_METADATA (397) and/or COMPONENT_INFORMATION (395), "
                f"got {request_messages!r}"
            )
        self.request_messages = tuple(request_messages)
        self.burst = burst
        self.max_hole_reads = max_hole_reads
        self.reset_busy = reset_busy
        self.max_file_size = max_file_size
        self._cond = threading.Condition()
        self._op = threading.Lock()  # one fetch / file read at a time
        self._inbox: deque[FtpReply] = deque(maxlen=4096)
        self._ftp_component: int | None = None  # the FTP server being talked to, while a read runs
        self._general: tuple[str, str, int, int] | None = None  # (message, uri, crc, serial)
        self._serial = 0
        # A random first sequence number: PX4 repeats its cached last reply to a request whose number
        # is that reply's minus one, which must never be an earlier client's reply.
        self._seq = random.randrange(0x10000) if initial_seq is None else initial_seq & 0xFFFF
        # Touched by the fetching thread only; the reader counts in _foreign (under _cond).
        self._stats: dict[str, int] = dict.fromkeys(_STAT_NAMES, 0)
        self._foreign = 0
        self.info = FetchInfo()

    @property
    def stats(self) -> dict[str, int]:
        """Counters over this client's life: FTP messages ``sent``, ``resent``, ``send_failed``; ``bursts``,
        ``burst_packets``, ``reads`` (ReadFile), ``duplicates``, ``stale`` (replies to no current request),
        ``naks``, ``resets`` (ResetSessions), ``foreign`` (FTP messages for someone else)."""
        with self._cond:
            return {**self._stats, "foreign": self._foreign}

    @property
    def _target(self) -> str:
        comp = self._ftp_component if self._ftp_component is not None else self.target_component
        return f"system {self.target_system} component {comp}"

    # -- reader side ---------------------------------------------------------------------------------
    def on_message(self, msg: Any, now: float) -> None:
        """Take one decoded message from the link's reader (any message; only ours are kept)."""
        mid = msg.get_msgId()
        if mid == FILE_TRANSFER_PROTOCOL:
            self._on_ftp(msg)
        elif mid in (COMPONENT_METADATA, COMPONENT_INFORMATION):
            self._on_component_metadata(msg)

    def _from_target(self, msg: Any, component: int) -> bool:
        return bool(msg.get_srcSystem() == self.target_system and msg.get_srcComponent() == component)

    def _addressed_to_us(self, msg: Any) -> bool:
        mav = self.link.mav
        return getattr(msg, "target_system", 0) in (0, mav.srcSystem) and getattr(
            msg, "target_component", 0
        ) in (0, mav.srcComponent)

    def _on_ftp(self, msg: Any) -> None:
        with self._cond:
            comp = self._ftp_component
            if comp is None:
                return  # no transfer running: nothing of it is wanted
            if not self._from_target(msg, comp) or not self._addressed_to_us(msg):
                self._foreign += 1  # e.g. a ground station's transfer through the same link
                return
            try:
                reply = decode_ftp_payload(msg.payload)
            except FtpError:
                self._foreign += 1
                return
            self._inbox.append(reply)
            self._cond.notify_all()

    def _on_component_metadata(self, msg: Any) -> None:
        if not self._from_target(msg, self.target_component):
            return  # another component (a camera, a gimbal) describing itself
        if msg.get_msgId() == COMPONENT_METADATA:
            entry = ("COMPONENT_METADATA", str(msg.uri), int(msg.file_crc))
        else:
            uri, crc = str(msg.general_metadata_uri), int(msg.general_metadata_file_crc)
            entry = ("COMPONENT_INFORMATION", uri, crc)
        if not entry[1]:
            return
        with self._cond:
            self._serial += 1
            self._general = (*entry, self._serial)
            self._cond.notify_all()

    # -- public API ----------------------------------------------------------------------------------
    def general_metadata_uri(self, deadline: float) -> tuple[str, str, int]:
        """``(message name, URI, CRC32)`` of the general metadata file, asked of the vehicle now.

        Sends MAV_CMD_REQUEST_MESSAGE for each of ``request_messages`` in turn until one answers
        (whatever COMMAND_ACK says: the reader may give ACKs to someone else).
        """
        with self._cond:
            start = self._serial
        asked = unsent = 0
        for attempt in range(self.request_attempts):
            if time.monotonic() >= deadline:
                break
            n = len(self.request_messages)
            wanted = self.request_messages[attempt % n]
            msg = self.link.mav.command_long_encode(
                self.target_system,
                self.target_component,
                MAV_CMD_REQUEST_MESSAGE,
                attempt // n,
                float(wanted),
                0,
                0,
                0,
                0,
                0,
                0,
            )
            if not self.link.send(msg):
                unsent += 1
            asked += 1
            self.info.requests += 1
            until = min(deadline, time.monotonic() + self.request_timeout)
            with self._cond:
                while True:
                    got = self._general
                    if got is not None and got[3] > start:
                        return got[0], got[1], got[2]
                    left = until - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
        raise MetadataTimeout(
            f"no COMPONENT_METADATA (397) or COMPONENT_INFORMATION (395) from system {self.target_system} "
            f"component {self.target_component} after {asked} MAV_CMD_REQUEST_MESSAGE"
            + (" (the link could not send)" if unsent == asked > 0 else "")
        )

    def fetch(self, deadline: float) -> dict[str, ParamMeta]:
        """PX4's parameter metadata, read from the vehicle before ``deadline`` (:func:`time.monotonic`).

        Raises :class:`MetadataTimeout`, :class:`FtpNak`, :class:`FtpError` or
        :class:`MetadataFormatError`; :attr:`info` tells how it went.
        """
        with self._op:
            info = self.info = FetchInfo()
            t0 = time.monotonic()
            stats0 = self.stats
            msg_name, uri, crc = self.general_metadata_uri(deadline)
            t1 = time.monotonic()
            info.source_message, info.general_uri = msg_name, uri
            comp, path = parse_mftp_uri(uri)
            raw = self._read_file(path, comp, deadline)
            info.general_size = len(raw)
            general_json, info.general_crc_ok = self._unpack(raw, crc, uri, "general_crc_ok")
            types = parse_general_metadata(general_json, uri)
            t2 = time.monotonic()
            entry = types.get(COMP_METADATA_TYPE_PARAMETER)
            if entry is None:
                raise MetadataFormatError(
                    f"{uri}: lists no parameter metadata (type {COMP_METADATA_TYPE_PARAMETER}); "
                    f"types {sorted(types)}"
                )
            info.parameter_uri = entry.uri
            pcomp, ppath = parse_mftp_uri(entry.uri)
            raw = self._read_file(ppath, pcomp if pcomp is not None else comp, deadline)
            info.parameter_size = len(raw)
            params_json, info.parameter_crc_ok = self._unpack(raw, entry.crc, entry.uri, "parameter_crc_ok")
            info.parameter_json_size = len(params_json)
            meta = parse_parameters_json(params_json, entry.uri)
            t3 = time.monotonic()
            info.parameters = len(meta)
            info.reboot_required = len(reboot_required(meta))
            info.seconds = {
                "request": t1 - t0,
                "general": t2 - t1,
                "parameters": t3 - t2,
                "total": t3 - t0,
            }
            info.ftp = {k: v - stats0[k] for k, v in self.stats.items()}
            return meta

    def _unpack(self, raw: bytes, crc: int | None, uri: str, crc_field: str) -> tuple[bytes, bool | None]:
        try:
            return _unpack(raw, crc, uri)
        except _CorruptFile:
            setattr(self.info, crc_field, False)
            raise

    def read_file(self, path: str, deadline: float, component: int | None = None) -> bytes:
        """One whole file from the vehicle's MAVLink FTP server (``component`` defaults to the target's)."""
        with self._op:
            return self._read_file(path, component, deadline)

    # -- FTP -----------------------------------------------------------------------------------------
    def _read_file(self, path: str, component: int | None, deadline: float) -> bytes:
        with self._cond:
            self._inbox.clear()
            self._ftp_component = component if component is not None else self.target_component
        try:
            session, size = self._open(path, deadline)
            try:
                return self._download(path, session, size, deadline)
            finally:
                self._terminate(path, session, deadline)
        finally:
            with self._cond:
                self._ftp_component = None
                self._inbox.clear()

    def _next_seq(self, skip: int = 1) -> int:
        seq = self._seq
        self._seq = (self._seq + skip) & 0xFFFF
        return seq

    def _send_ftp(self, payload: list[int]) -> bool:
        comp = self._ftp_component if self._ftp_component is not None else self.target_component
        msg = self.link.mav.file_transfer_protocol_encode(0, self.target_system, comp, payload)
        self._stats["sent"] += 1
        if self.link.send(msg):
            return True
        self._stats["send_failed"] += 1
        return False

    def _take(self, until: float) -> FtpReply | None:
        """The next reply received, waiting until ``until``; None when none came."""
        with self._cond:
            while not self._inbox:
                left = until - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._inbox.popleft()

    def _exchange(
        self,
        op: int,
        path: str,
        deadline: float,
        *,
        session: int = 0,
        offset: int = 0,
        data: bytes = b"",
        size: int | None = None,
        attempts: int | None = None,
    ) -> FtpReply:
        """Send one request (resent with the same sequence number) until its ACK or NAK comes back."""
        seq = self._next_seq()
        want = (seq + 1) & 0xFFFF
        payload = encode_ftp_payload(seq, op, session=session, offset=offset, data=data, size=size)
        sent = unsent = 0
        for _ in range(self.attempts if attempts is None else attempts):
            now = time.monotonic()
            if now >= deadline:
                break
            if not self._send_ftp(payload):
                unsent += 1
            if sent:
                self._stats["resent"] += 1
            sent += 1
            until = min(deadline, now + self.timeout)
            while True:
                reply = self._take(until)
                if reply is None:
                    break
                if reply.seq == want and reply.req_opcode == op and reply.opcode in (OP_ACK, OP_NAK):
                    if reply.nak:
                        self._stats["naks"] += 1
                    return reply
                self._stats["stale"] += 1  # an answer to an earlier request, a burst's tail
        what = f"MAVLink FTP {OPCODE_NAMES.get(op, op)} {path!r}: no answer from {self._target}"
        if not sent:
            raise MetadataTimeout(f"{what}: the deadline passed before it could be sent")
        why = " (the link could not send)" if unsent == sent else ""
        raise MetadataTimeout(f"{what} after {sent} tries of {self.timeout:g} s{why}")

    def _refused(self, reply: FtpReply, op: int, path: str) -> FtpNak:
        return FtpNak(op, reply.error, reply.errno, path, self._target)

    def _open(self, path: str, deadline: float) -> tuple[int, int]:
        name = path.encode()
        if len(name) >= FTP_DATA_MAX:
            raise FtpError(f"MAVLink FTP path {path!r} longer than {FTP_DATA_MAX - 1} bytes")
        reset = False
        while True:
            reply = self._exchange(OP_OPEN_FILE_RO, path, deadline, data=name)
            if reply.nak and reply.error == ERR_NO_SESSIONS_AVAILABLE and self.reset_busy and not reset:
                reset = True
                self._stats["resets"] += 1
                self._exchange(OP_RESET_SESSIONS, path, deadline)  # always ACKed
                continue
            if reply.nak:
                raise self._refused(reply, OP_OPEN_FILE_RO, path)
            if reply.size < 4:
                raise FtpError(f"MAVLink FTP OpenFileRO {path!r}: {self._target} sent no file size")
            size = int.from_bytes(reply.data[:4], "little")
            if size > self.max_file_size:
                raise FtpError(
                    f"MAVLink FTP {path!r} on {self._target}: {size} bytes, more than {self.max_file_size}"
                )
            return reply.session, size

    def _terminate(self, path: str, session: int, deadline: float) -> None:
        """Close the session; never raises (PX4 closes an idle session after 10 s anyway)."""
        try:
            self._exchange(
                OP_TERMINATE_SESSION,
                path,
                max(deadline, time.monotonic() + self.timeout),
                session=session,
                attempts=min(self.attempts, 2),
            )
        except MetadataError:
            pass

    def _download(self, path: str, session: int, size: int, deadline: float) -> bytes:
        buf = _Assembly(size, path, self._target)
        use_burst = self.burst
        useless = 0  # bursts in a row that brought nothing new (a lost request, or every packet lost)
        stalls = 0
        while True:
            gaps = buf.gaps()
            if not gaps:
                return bytes(buf.data)
            if time.monotonic() >= deadline:
                raise MetadataTimeout(
                    f"MAVLink FTP {path!r} from {self._target}: {buf.have} of {size} bytes by the deadline"
                )
            before = buf.have
            holes = [g for g in gaps if g[1] < size]  # missing ranges before the (missing) tail
            hole_reads = sum(-(-(e - s) // FTP_DATA_MAX) for s, e in holes)
            if use_burst and useless >= 2:
                use_burst = False  # bursting does not get through: read chunk by chunk
            if use_burst and (not holes or hole_reads > self.max_hole_reads):
                try:
                    self._burst(path, session, gaps[0][0], buf, deadline)
                except FtpNak as exc:
                    if exc.code != ERR_UNKNOWN_COMMAND:
                        raise
                    use_burst = False  # a server without BurstReadFile: read chunk by chunk
                else:
                    useless = 0 if buf.have > before else useless + 1
            else:
                for start, end in holes if use_burst else gaps:
                    self._read_range(path, session, start, end, buf, deadline)
            stalls = 0 if buf.have > before else stalls + 1
            if stalls >= self.attempts:
                raise MetadataTimeout(
                    f"MAVLink FTP {path!r} from {self._target}: no data for {stalls} tries "
                    f"({buf.have} of {size} bytes)"
                )

    def _read_range(
        self, path: str, session: int, start: int, end: int, buf: _Assembly, deadline: float
    ) -> None:
        offset = start
        while offset < end:
            # The request's size says how much to read (PX4 v1.16 reads exactly that: 0 gives nothing).
            n = min(FTP_DATA_MAX, end - offset)
            reply = self._exchange(OP_READ_FILE, path, deadline, session=session, offset=offset, size=n)
            self._stats["reads"] += 1
            if reply.nak:
                if reply.error == ERR_EOF:
                    raise FtpError(
                        f"MAVLink FTP {path!r} on {self._target}: EOF at {offset} of the {buf.size} bytes "
                        f"announced (the file changed?)"
                    )
                raise self._refused(reply, OP_READ_FILE, path)
            if not reply.data:
                raise FtpError(f"MAVLink FTP {path!r} on {self._target}: empty read at {offset}/{buf.size}")
            if not buf.put(offset, reply.data):
                self._stats["duplicates"] += 1
            offset += len(reply.data)

    def _burst(self, path: str, session: int, start: int, buf: _Assembly, deadline: float) -> None:
        """One BurstReadFile from ``start``: take its packets until burst complete, EOF or silence."""
        window = -(-(buf.size - start) // FTP_DATA_MAX) + 2  # packets (and sequence numbers) it may use
        seq = self._next_seq(skip=window + 1)  # the next request's number lies beyond this burst
        self._send_ftp(encode_ftp_payload(seq, OP_BURST_READ_FILE, session=session, offset=start))
        self._stats["bursts"] += 1
        while True:
            now = time.monotonic()
            if now >= deadline:
                return
            reply = self._take(min(deadline, now + self.timeout))
            if reply is None:
                return  # silence: the burst (or its request, or its last packet) is over or lost
            d = (reply.seq - seq) & 0xFFFF
            if reply.req_opcode != OP_BURST_READ_FILE or not 1 <= d <= window:
                self._stats["stale"] += 1
                continue
            if reply.nak:
                self._stats["naks"] += 1
                if reply.error == ERR_EOF:
                    return
                raise self._refused(reply, OP_BURST_READ_FILE, path)
            if reply.opcode != OP_ACK:
                self._stats["stale"] += 1
                continue
            self._stats["burst_packets"] += 1
            if not buf.put(reply.offset, reply.data):
                self._stats["duplicates"] += 1
            if reply.burst_complete:
                return


class _Assembly:
    """A file being put together from chunks at offsets, in any order, each byte checked once written."""

    def __init__(self, size: int, path: str, target: str) -> None:
        self.size = size
        self.path = path
        self.target = target
        self.data = bytearray(size)
        self._got = bytearray(size)  # 1 where a byte arrived
        self.have = 0

    def put(self, offset: int, chunk: bytes) -> bool:
        """Store a chunk; False when it brought nothing new (a duplicate).  Bytes past the end are dropped."""
        end = min(self.size, offset + len(chunk))
        if offset >= end:
            return False
        chunk = chunk[: end - offset]
        got = self._got[offset:end]
        known = got.count(1)
        if known:
            for i, flag in enumerate(got):
                if flag and self.data[offset + i] != chunk[i]:
                    raise FtpError(
                        f"MAVLink FTP {self.path!r} from {self.target}: two values at offset {offset + i}"
                    )
        if known == len(chunk):
            return False
        self.data[offset:end] = chunk
        self._got[offset:end] = b"\x01" * (end - offset)
        self.have += len(chunk) - known
        return True

    def gaps(self) -> list[tuple[int, int]]:
        """The missing ``[start, end)`` ranges, in order."""
        out: list[tuple[int, int]] = []
        pos = self._got.find(0)
        while pos >= 0:
            end = self._got.find(1, pos)
            end = self.size if end < 0 else end
            out.append((pos, end))
            pos = self._got.find(0, end)
        return out


def fetch_parameter_metadata(
    link: MavlinkLink,
    target_system: int,
    deadline: float,
    target_component: int = 1,
    *,
    client: MetadataClient | None = None,
    on_frame: Callable[[Any, float], None] | None = None,
) -> dict[str, ParamMeta]:
    """:meth:`MetadataClient.fetch` on an open link nobody else reads: a reader thread runs meanwhile.

    ``on_frame(frame, now)`` sees every frame read (e.g. to keep a heartbeat's bookkeeping).
    """
    client = client or MetadataClient(link, target_system, target_component)
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            for frame in link.read(0.05):
                now = time.monotonic()
                if on_frame is not None:
                    on_frame(frame, now)
                if frame.msgid in HANDLED_MESSAGES:
                    msg = link.decode(frame)
                    if msg is not None:
                        client.on_message(msg, now)

    thread = threading.Thread(target=reader, name="px4-metadata-reader", daemon=True)
    thread.start()
    try:
        return client.fetch(deadline)
    finally:
        stop.set()
        thread.join(timeout=1.0)
