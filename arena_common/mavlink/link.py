"""A MAVLink 2 link to one autopilot as the gateway needs it: raw frames, selective decoding, safe sending.

pymavlink decodes every message it reads (14–20 µs each) while a PX4 in onboard mode sends hundreds a
second, of which the gateway uses a few.  :class:`MavlinkLink` therefore splits the bytes into frames
itself (:class:`FrameSplitter`: header, length, CRC with the message's CRC_EXTRA, resynchronisation),
drops every frame whose system id is not the vehicle's, and decodes a frame only when asked
(:meth:`MavlinkLink.decode`).  Raw frames can be forwarded untouched (:class:`GcsForwarder`), the way
mavlink-router does.

Connection strings are pymavlink's:

- ``udpin:HOST:PORT`` (or ``udp:``) listens; replies go to the address the vehicle's own frames last
  came from, so another system sharing the port never receives anything from this link.  On a signed
  link only a frame whose signature verified moves that address (one let through unsigned, such as
  RADIO_STATUS, is data only); on an unsigned one any frame with the vehicle's system id does, so a
  host that can reach the port can divert the link.  ``peer="IP:PORT"`` (the vehicle's
  ``mavlink_peer``) pins it: replies go there from the start, and datagrams from any other address are
  dropped, counted in :attr:`MavlinkLink.wrong_source` and logged (at most every 10 s);
- ``udpout:HOST:PORT`` sends to that address first;
- ``tcp:HOST:PORT`` connects, ``tcpin:HOST:PORT`` accepts one client;
- ``serial:DEVICE[:BAUD]`` (``serial:/dev/ttyTHS1:921600``: a companion computer wired to the
  autopilot's TELEM2) opens a serial port raw, 8N1, no flow control, at BAUD (57600 by default), and
  reads and writes it without blocking;
- anything else (``/dev/ttyACM0``, ``/dev/ttyUSB0:921600`` for a baud rate, …) is opened by pymavlink
  and read and written as raw bytes (serial ports need ``pyserial``).

Sending is thread-safe: one lock covers sequence numbering and the write, so frames from the vision,
setpoint and command threads never interleave.

With a :class:`~arena_common.mavlink.signing.LinkSigning` (MAVLink 2 signing), every frame :meth:`MavlinkLink.send`
writes is signed, and :meth:`MavlinkLink.read` checks every frame of the vehicle (signature, replay) before
returning it: refused frames are counted per reason and handed to ``on_reject``, never decoded, never
forwarded.  Raw frames forwarded from a ground station are written as they are: the ground station must
sign them itself with the same key, or the vehicle drops them.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import select
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import all as mavlink2  # common + development + the rest: every CRC_EXTRA

from arena_common.mavlink.fastframe import FrameType
from arena_common.mavlink.signing import LinkSigning
from arena_common.mavlink.transports import MavlinkLinkError, _Transport, check_peer, open_transport

__all__ = [
    "MSG",
    "Frame",
    "FrameSplitter",
    "GcsForwarder",
    "MavlinkLink",
    "MavlinkLinkError",
    "mavlink2",
]

log = logging.getLogger("arena.mavlink.link")

MAGIC_V2 = 0xFD
MAGIC_V1 = 0xFE
_SIGNED = 0x01
_MAX_BUFFER = 1 << 16
_WRONG_SOURCE_EVERY = 10.0  # s between two log lines about datagrams from an address not pinned
_WRONG_SOURCE_ADDRESSES = 8  # distinct addresses named per log line (a flood may spoof many)
BUDGET_WINDOW_S = 0.1  # a link's budget is spent in windows this long (a flood waits at most this)

#: Message ids by name, for the messages the gateway handles or filters.
MSG: dict[str, int] = {
    name: getattr(mavlink2, f"MAVLINK_MSG_ID_{name}")
    for name in (
        "HEARTBEAT",
        "SYS_STATUS",
        "TIMESYNC",
        "PARAM_VALUE",
        "ATTITUDE_QUATERNION",
        "LOCAL_POSITION_NED",
        "MANUAL_CONTROL",
        "RC_CHANNELS_OVERRIDE",
        "COMMAND_ACK",
        "BATTERY_STATUS",
        "EXTENDED_SYS_STATE",
        "STATUSTEXT",
        "ODOMETRY",
        "GPS_GLOBAL_ORIGIN",
        "RADIO_STATUS",
        "ESTIMATOR_STATUS",
    )
}


@dataclass(frozen=True, slots=True)
class Frame:
    """One whole MAVLink frame as it travelled (header, payload, CRC, signature).

    ``checked`` is False for a datagram's frame of a message id unknown to the dialects: its CRC could
    not be checked, so it may be forwarded but never trusted (decoded, or used to learn the peer).
    """

    msgid: int
    sysid: int
    compid: int
    raw: bytes
    checked: bool = True


def _crc_ok(frame: bytes, header_len: int, payload_len: int, msgid: int) -> bool | None:
    """Whether the frame's CRC matches (None when the message is unknown to the dialect)."""
    spec = mavlink2.mavlink_map.get(msgid)
    if spec is None:
        return None
    end = header_len + payload_len
    crc = mavlink2.x25crc(bytearray(frame[1:end]) + bytes((spec.crc_extra,)))
    return bool(crc.crc == (frame[end] | (frame[end + 1] << 8)))


class FrameSplitter:
    """Split bytes into MAVLink 1/2 frames, checking each CRC.

    ``stream=True`` (serial, TCP) keeps an incomplete tail for the next :meth:`feed` and resynchronises
    after garbage, a bad CRC or an unknown message id by skipping one byte; a datagram (UDP) is parsed on
    its own and may carry messages unknown to pymavlink's dialects (forwarded, never decoded).
    """

    def __init__(self, stream: bool = True) -> None:
        self.stream = stream
        self._buf = bytearray()
        self.bad_crc = 0
        self.garbage = 0

    def feed(self, data: bytes) -> list[Frame]:
        """Frames completed by ``data``."""
        if self.stream:
            self._buf += data
            buf: bytes | bytearray = self._buf
        else:
            buf = data
        out: list[Frame] = []
        i, n = 0, len(buf)
        while i < n:
            magic = buf[i]
            if magic == MAGIC_V2:
                if n - i < 10:
                    break
                plen = buf[i + 1]
                total = 12 + plen + (13 if buf[i + 2] & _SIGNED else 0)
                if n - i < total:
                    break
                sysid, compid = buf[i + 5], buf[i + 6]
                msgid = buf[i + 7] | (buf[i + 8] << 8) | (buf[i + 9] << 16)
                header = 10
            elif magic == MAGIC_V1:
                if n - i < 6:
                    break
                plen = buf[i + 1]
                total = 8 + plen
                if n - i < total:
                    break
                sysid, compid, msgid = buf[i + 3], buf[i + 4], buf[i + 5]
                header = 6
            else:
                j = _next_magic(buf, i + 1)
                self.garbage += j - i
                i = j
                continue
            raw = bytes(buf[i : i + total])
            crc = _crc_ok(raw, header, plen, msgid)
            # In a byte stream a message unknown to every dialect is most likely a false start.
            if crc is False or (crc is None and self.stream):
                self.bad_crc += 1
                i += 1
                continue
            out.append(Frame(msgid, sysid, compid, raw, checked=crc is True))
            i += total
        if self.stream:
            del self._buf[:i]
            if len(self._buf) > _MAX_BUFFER:
                self.garbage += len(self._buf)
                self._buf.clear()
        return out


def _next_magic(buf: bytes | bytearray, start: int) -> int:
    a, b = buf.find(MAGIC_V2, start), buf.find(MAGIC_V1, start)
    if a < 0 and b < 0:
        return len(buf)
    if a < 0:
        return b
    if b < 0:
        return a
    return min(a, b)


class MavlinkLink:
    """A MAVLink 2 link to the autopilot with system id ``system_id``; we speak as ``source_system``.

    :meth:`read` returns the frames of that system only (others are counted in :attr:`foreign` and
    dropped); :meth:`decode` turns a frame into a pymavlink message; :meth:`send` encodes and writes one.
    The link opens lazily and can be re-opened (:meth:`reopen`) after a loss.  With ``signing``, frames
    sent are signed and frames read are verified; ``on_reject(reason, frame)`` hears of each refused one
    (in the reading thread: keep it short).  ``peer`` (``"IP:PORT"``, ``udpin:`` links only) pins the
    autopilot's address: datagrams from elsewhere are dropped and counted in :attr:`wrong_source`.
    ``budget`` (datagrams per second, 0: none) caps what a datagram link reads, so that a flood on it
    costs its reader little: past it, within each :data:`BUDGET_WINDOW_S`, what was read is dropped
    unparsed (:attr:`over_budget`) and the rest waits in the socket, where the system drops what its
    buffer cannot hold (:meth:`kernel_drops`).
    """

    def __init__(
        self,
        url: str,
        system_id: int,
        *,
        source_system: int = 245,
        source_component: int = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER,
        signing: LinkSigning | None = None,
        on_reject: Callable[[str, Frame], None] | None = None,
        peer: str | None = None,
        budget: int = 0,
    ) -> None:
        if not 1 <= int(system_id) <= 250:
            raise MavlinkLinkError(f"vehicle system id must be within 1..250, got {system_id}")
        if not 1 <= int(source_system) <= 255 or int(source_system) == int(system_id):
            raise MavlinkLinkError(
                f"our system id must be within 1..255 and differ from the vehicle's, got {source_system}"
            )
        check_peer(url, peer)  # a wrong pin fails here, not at each (re-)opening
        self.url = url
        self.peer = peer
        self.system_id = int(system_id)
        self.mav = mavlink2.MAVLink(None, srcSystem=int(source_system), srcComponent=int(source_component))
        self.mav.robust_parsing = True
        self._decoder = mavlink2.MAVLink(
            None, srcSystem=int(source_system), srcComponent=int(source_component)
        )
        self._lock = threading.Lock()
        self._transport: _Transport | None = None
        self._splitter = FrameSplitter(stream=True)
        self.signing = signing
        self.on_reject = on_reject
        if signing is not None:
            signing.attach(self.mav)  # the decoder stays keyless: read() verifies before decoding
        self.frames_in = 0
        self.foreign = 0
        self.bad_crc = 0  # frames refused for their CRC (or unknown in a byte stream), over every opening
        self.garbage = 0  # bytes that were no frame, over every opening
        self.unchecked = 0  # frames of the vehicle whose CRC could not be checked (unknown message id)
        self.wrong_source = 0  # frames dropped for coming from an address other than the pinned peer
        self.last_wrong_source: Any = None  # the address the last of them came from
        self._wrong_pending: collections.Counter[str] = collections.Counter()
        self._wrong_report = 0.0
        self.pack_errors = 0
        self.last_pack_error = ""
        self.frames_out = 0
        self.send_errors = 0
        self.decode_errors = 0
        self.opened = 0
        self.budget = max(0, int(budget))
        self.datagrams_in = 0  # datagrams read, on a datagram link
        self.over_budget = 0  # datagrams read past the budget, dropped unparsed
        self._window_end = 0.0
        self._window_left = 0
        self._drops_closed = 0  # what the system dropped for the sockets of earlier openings

    # -- lifetime ------------------------------------------------------------------------------------
    def open(self) -> None:
        """Open the connection (no-op when open); :class:`MavlinkLinkError` when it cannot be."""
        with self._lock:
            if self._transport is None:
                self._transport = open_transport(self.url, self.peer)
                self._splitter = FrameSplitter(stream=self._transport.stream)
                self.opened += 1

    def close(self) -> None:
        """Close the connection (it can be opened again)."""
        with self._lock:
            transport, self._transport = self._transport, None
        if transport is not None:
            self._drops_closed += transport.kernel_drops() or 0
            with contextlib.suppress(OSError):
                transport.close()

    def kernel_drops(self) -> int:
        """Datagrams the system dropped before this link read them (its receive buffer full), over every
        opening; 0 where the system does not say."""
        t = self._transport
        return self._drops_closed + ((t.kernel_drops() or 0) if t is not None else 0)

    def reopen(self) -> bool:
        """Close and open again; False (and closed) when it cannot be opened right now."""
        self.close()
        try:
            self.open()
        except MavlinkLinkError:
            return False
        return True

    @property
    def is_open(self) -> bool:
        return self._transport is not None

    def can_send(self) -> bool:
        """Whether a frame would go anywhere (a listening UDP link knows its peer once it has heard it)."""
        t = self._transport
        return t is not None and t.can_send()

    # -- input ---------------------------------------------------------------------------------------
    def read(self, timeout: float) -> list[Frame]:
        """Wait up to ``timeout`` s for input; the vehicle's frames that arrived, possibly none."""
        t = self._transport
        if t is None:
            time.sleep(timeout)
            return []
        budgeted = self.budget > 0 and not t.stream
        if budgeted:
            now = time.monotonic()
            if now >= self._window_end:
                self._window_end = now + BUDGET_WINDOW_S
                self._window_left = max(1, round(self.budget * BUDGET_WINDOW_S))
            elif self._window_left <= 0:  # over budget: what comes meanwhile waits in the socket
                time.sleep(min(timeout, self._window_end - now))
                return []
        fd = t.fileno()
        try:
            if fd is None:
                time.sleep(min(timeout, 0.005))
            else:
                ready, _, _ = select.select([fd], [], [], timeout)
                if not ready:
                    return []
            chunks = t.read()
        except (OSError, ValueError):
            if self._transport is t:
                time.sleep(min(timeout, 0.05))  # closed under us or broken; the owner re-opens it
            return []
        if not t.stream:
            self.datagrams_in += len(chunks)
        if budgeted:
            kept = chunks[: self._window_left]
            self.over_budget += len(chunks) - len(kept)
            self._window_left -= len(kept)
            chunks = kept
        out: list[Frame] = []
        sid = self.system_id
        signing = self.signing
        splitter = self._splitter
        for data, addr in chunks:
            bad_crc, garbage = splitter.bad_crc, splitter.garbage
            frames = splitter.feed(data)
            self.bad_crc += splitter.bad_crc - bad_crc
            self.garbage += splitter.garbage - garbage
            if frames and not t.source_allowed(addr):
                self._wrong_source(addr, len(frames))
                continue
            mine = [f for f in frames if f.sysid == sid]
            self.foreign += len(frames) - len(mine)
            if not mine:
                continue
            # Only a frame that proves it is the vehicle's may tell where the vehicle is: on a signed link
            # one whose signature verified (RADIO_STATUS passes unsigned: anyone can send it), else one
            # whose CRC was checked (a corrupt datagram of an unknown message id proves nothing).
            if signing is not None:
                mine, trusted = self._verified(signing, mine)
            else:
                trusted = any(f.checked for f in mine)
            if trusted:
                t.accept_source(addr)
            self.unchecked += sum(1 for f in mine if not f.checked)
            out.extend(mine)
        self.frames_in += len(out)
        return out

    def _verified(self, signing: LinkSigning, frames: list[Frame]) -> tuple[list[Frame], bool]:
        """The frames that pass the signing check, and whether one of them was signed (and CRC-checked)."""
        kept: list[Frame] = []
        trusted = False
        for f in frames:
            reason, signed = signing.verify(f.raw, f.msgid, f.sysid, f.compid)
            if reason is None:
                kept.append(f)
                trusted = trusted or (signed and f.checked)
            elif self.on_reject is not None:
                self.on_reject(reason, f)
        return kept, trusted

    def _wrong_source(self, addr: Any, n: int) -> None:
        """``n`` frames came from ``addr``, which is not the pinned peer: count them, log now and then."""
        self.wrong_source += n
        self.last_wrong_source = addr
        name = f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) and len(addr) >= 2 else str(addr)
        pending = self._wrong_pending
        if name in pending or len(pending) < _WRONG_SOURCE_ADDRESSES:
            pending[name] += n
        else:
            pending["other addresses"] += n
        now = time.monotonic()
        if now < self._wrong_report:
            return
        self._wrong_report = now + _WRONG_SOURCE_EVERY
        detail = ", ".join(f"{a} ×{k}" for a, k in pending.most_common())
        pending.clear()
        log.warning(
            "%s: dropped frames from %s: not the pinned peer %s of system %d (mavlink_peer): another "
            "device is sending to this port, or the vehicle's address changed",
            self.url,
            detail,
            self.peer,
            self.system_id,
        )

    def decode(self, frame: Frame) -> Any:
        """The pymavlink message of a frame, or None when it cannot be decoded."""
        if not frame.checked:
            return None
        try:
            msg = self._decoder.decode(bytearray(frame.raw))
        except (mavlink2.MAVError, struct.error, IndexError, ValueError):
            self.decode_errors += 1
            return None
        if isinstance(msg, mavlink2.MAVLink_unknown):
            return None
        return msg

    # -- output --------------------------------------------------------------------------------------
    def send(self, msg: Any, fresh: Callable[[], bool] | None = None) -> bool:
        """Encode and write one message; False when the link is closed, has no peer yet, or failed.

        Never raises for the message: one that cannot be packed (a value beyond its field's type) is
        counted in :attr:`pack_errors` and not sent.  ``fresh``, when given, is asked once the frame is
        packed, just before it is written: False drops the frame (it became too old while waiting).
        """
        with self._lock:
            t = self._transport
            if t is None or not t.can_send():
                return False
            if self.signing is not None:
                self.signing.refresh()
            seq = self.mav.seq
            try:
                buf = msg.pack(self.mav)
            except Exception as exc:  # a value beyond its field's type: that message only, never the loop
                self.mav.seq = seq
                self._pack_failed(type(msg).__name__, exc)
                return False
            if fresh is not None and not fresh():
                return False
            self.mav.seq = (self.mav.seq + 1) % 256
            return self._write(t, buf)

    def send_packed(
        self,
        ftype: FrameType,
        payload: Callable[[], bytes],
        message: Callable[[], Any],
        fresh: Callable[[], bool] | None = None,
    ) -> bool:
        """As :meth:`send`, for a payload packed by ``payload()`` and framed here without a pymavlink object.

        A signed link needs pymavlink's signature: there ``message()`` builds the object instead.
        """
        if self.signing is not None:
            return self.send(message(), fresh)
        try:
            body = payload()
        except (struct.error, OverflowError) as exc:  # a value beyond its field's type
            self._pack_failed(ftype.name, exc)
            return False
        with self._lock:
            t = self._transport
            if t is None or not t.can_send():
                return False
            mav = self.mav
            buf = ftype.frame(body, mav.seq, mav.srcSystem, mav.srcComponent)
            if fresh is not None and not fresh():
                return False
            mav.seq = (mav.seq + 1) % 256
            return self._write(t, buf)

    def _pack_failed(self, what: str, exc: BaseException) -> None:
        self.pack_errors += 1
        self.last_pack_error = f"{what}: {exc}"

    def send_raw(self, data: bytes) -> bool:
        """Write already-encoded frames as they are (forwarding)."""
        with self._lock:
            t = self._transport
            if t is None or not t.can_send():
                return False
            return self._write(t, data)

    def _write(self, t: _Transport, buf: bytes) -> bool:
        try:
            t.write(buf)
        except OSError:
            self.send_errors += 1  # nobody listening yet, buffer full, peer gone: the next frame retries
            return False
        self.frames_out += 1
        return True


class GcsForwarder:
    """Raw MAVLink forwarding between the vehicle link and a ground station, like mavlink-router.

    Every frame of the vehicle goes to the GCS unchanged; every frame from the GCS goes to the vehicle
    unchanged, except RC_CHANNELS_OVERRIDE and MANUAL_CONTROL, which are blocked unless
    ``allow_manual`` (users must never fly the arena's vehicles with sticks over the network; a pilot's
    RC transmitter talks to the vehicle directly and is not affected).
    """

    BLOCKED = frozenset({MSG["RC_CHANNELS_OVERRIDE"], MSG["MANUAL_CONTROL"]})

    def __init__(self, url: str, vehicle: MavlinkLink, *, allow_manual: bool = False) -> None:
        self.url = url
        self.vehicle = vehicle
        self.allow_manual = allow_manual
        self._transport: _Transport | None = None
        self._splitter = FrameSplitter(stream=True)
        self._lock = threading.Lock()
        self.to_gcs = 0
        self.to_vehicle = 0
        self.blocked = 0

    def open(self) -> None:
        """Open the GCS side (raises :class:`MavlinkLinkError`)."""
        self._transport = open_transport(self.url)
        self._splitter = FrameSplitter(stream=self._transport.stream)

    def close(self) -> None:
        t, self._transport = self._transport, None
        if t is not None:
            with contextlib.suppress(OSError):
                t.close()

    def forward_to_gcs(self, frames: list[Frame]) -> None:
        """Send the vehicle's frames to the GCS as they are."""
        t = self._transport
        if t is None or not frames or not t.can_send():
            return
        with self._lock:
            try:
                t.write(b"".join(f.raw for f in frames))
            except OSError:
                return
        self.to_gcs += len(frames)

    def pump(self, timeout: float) -> int:
        """Wait up to ``timeout`` s for GCS input and forward it; the number of frames forwarded."""
        t = self._transport
        if t is None:
            time.sleep(timeout)
            return 0
        fd = t.fileno()
        try:
            if fd is None:
                time.sleep(min(timeout, 0.005))
            elif not select.select([fd], [], [], timeout)[0]:
                return 0
            chunks = t.read()
        except (OSError, ValueError):
            time.sleep(min(timeout, 0.05))
            return 0
        sent = 0
        for data, addr in chunks:
            frames = self._splitter.feed(data)
            if any(f.checked for f in frames):
                t.accept_source(addr)
            keep = [f for f in frames if self.allow_manual or f.msgid not in self.BLOCKED]
            self.blocked += len(frames) - len(keep)
            if keep and self.vehicle.send_raw(b"".join(f.raw for f in keep)):
                sent += len(keep)
        self.to_vehicle += sent
        return sent
