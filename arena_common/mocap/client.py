"""A NatNet client over UDP: handshake, model definitions, clock sync and reconnection, on one thread.

:class:`NatNetClient` talks to a Motive server (or anything speaking NatNet 2.x–4.x) the way the NatNet SDK
does, without threads of its own: call :meth:`NatNetClient.poll` in a loop and it returns each frame as a
:class:`TimedFrame`, having done the protocol work in between:

- **Handshake.** CONNECT goes to the command port; the server's SERVERINFO says its NatNet version, which
  decides how frames and model definitions are laid out. Nothing is decoded before that: frames that
  arrive first are counted (``before_serverinfo``) and dropped. REQUEST_MODELDEF then fetches the rigid
  bodies' names (frames carry only ids), again whenever a frame says the models changed.
- **Transport.** Multicast: a data socket bound to the group (``''`` where the system refuses that), with
  ``SO_REUSEADDR`` so several clients coexist, joined on the configured interface address. Unicast: Motive
  (NatNet 3.x and 4.x alike) sends each client's frames to the socket that sent CONNECT, from its data
  port, and nowhere else (docs/architecture.md, "NatNet unicast"), so the command socket is the only one; a
  KEEPALIVE goes every second to servers from NatNet 2.10 on, which drop a unicast client declaring 2.10 or
  later (this one declares 4.1) after 5–10 s without one.
- **Time.** ECHO round trips (NTP-like, :class:`EchoClock`) map the server's tick clock onto the local wall
  clock, so each frame's camera mid-exposure becomes its measurement time ``t`` (``tsrc="echo"``); until
  the clock is known, ``t`` is the arrival time minus the system latency the frame reports
  (``"latency"``), and before NatNet 3.0 simply the arrival time (``"arrival"``).
- **Robustness.** Garbage, truncated and oversized datagrams, unknown messages, undecodable frames, frames
  going back (a server restart), a NatNet version change and silence (no frame for ``loss_timeout``:
  the sockets are reopened and the handshake restarts, with back-off) are each counted under a reason and
  reported through ``on_reject``; the client keeps going. Every socket operation is non-blocking or
  bounded by ``poll``'s timeout.
"""

from __future__ import annotations

import collections
import errno
import ipaddress
import logging
import math
import select
import socket
import struct
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from arena_common.core.errors import ArenaError
from arena_common.mocap import natnet
from arena_common.mocap.natnet import MessageId, ModelDefs, NatNetError, RigidBody, ServerInfo, Version

__all__ = [
    "DEFAULT_GROUP",
    "EchoClock",
    "MocapError",
    "NatNetClient",
    "TimedFrame",
    "local_address_towards",
]

log = logging.getLogger("arena.natnet")

DEFAULT_GROUP = natnet.MULTICAST_GROUP
#: The NatNet version announced in CONNECT (the newest this client decodes).
CLIENT_NATNET_VERSION = Version(4, 1)
#: The first NatNet version whose servers take KEEPALIVE (and drop silent unicast clients without it).
KEEPALIVE_SINCE = Version(2, 10)
_HEADER = struct.Struct("<HH")
_RECV_SIZE = 65536  # larger than any IPv4 UDP payload
_RCVBUF = 1 << 20  # absorb bursts of frames while the process is descheduled
_NS = 1_000_000_000
_RESTART_BACKWARDS = 10  # a frame number this far behind the last one means a new session, not reordering
_MAX_DECODE_FAILURES = 10  # consecutive undecodable frames before the handshake is redone
_MAX_LATENCY_NS = 10 * _NS  # a reported system latency above this is nonsense


class MocapError(ArenaError):
    """A motion-capture source cannot be set up (bad address, interface, file…); the message says which."""


@dataclass(slots=True)
class TimedFrame:
    """One motion-capture frame with its timing, as every mocap source delivers it.

    ``bodies`` are in the source's frame (Motive's: metres, quaternion x, y, z, w). ``t`` is the measurement
    time on the local wall clock (ns) and ``tsrc`` how it was obtained (``echo``, ``latency``,
    ``arrival``); ``lat`` the system latency the server reported (ns, -1 unknown); ``mts`` the server's own
    timestamp (s); ``arrival`` when the datagram was read (ns). ``names`` maps body ids to names and
    ``models`` counts the model-definition updates behind it (0: no names known yet), so a consumer can
    cache its per-id lookups until ``models`` changes.
    """

    frame_number: int
    bodies: tuple[RigidBody, ...]
    t: int
    tsrc: str
    lat: int
    mts: float
    arrival: int
    names: Mapping[int, str]
    models: int
    params: int = 0


class EchoClock:
    """Maps a server's tick clock onto the local wall clock from ECHO round trips, like NTP.

    Each round trip gives an offset (local midpoint minus server time) whose error is at most half its round
    trip time; the estimate is the offset of the fastest round trip among the last ``window`` samples, which
    also follows slow drift between the clocks. A sample that disagrees with the estimate by more than
    ``jump_ns`` (plus both round trips) means the server's clock restarted: the window starts over.
    """

    def __init__(
        self, frequency: int, window: int = 16, max_rtt_ns: int = 200_000_000, jump_ns: int = 50_000_000
    ) -> None:
        if frequency <= 0:
            raise ValueError(f"clock frequency must be positive, got {frequency}")
        self.frequency = frequency
        self.max_rtt_ns = max_rtt_ns
        self.jump_ns = jump_ns
        self._samples: collections.deque[tuple[int, int]] = collections.deque(maxlen=window)
        self.offset_ns: int | None = None  # local wall clock minus server clock
        self.rtt_ns: int | None = None  # round trip of the sample the offset comes from
        self.resets = 0

    @property
    def ready(self) -> bool:
        """True once at least one usable round trip was made."""
        return self.offset_ns is not None

    @property
    def samples(self) -> int:
        """Round trips in the current window."""
        return len(self._samples)

    def ticks_to_ns(self, ticks: int) -> int:
        """Server ticks as nanoseconds of the server's clock (exact integer arithmetic)."""
        return ticks * _NS // self.frequency

    def add(self, sent_ns: int, server_ticks: int, received_ns: int) -> bool:
        """Add one round trip (local send and receive times, the server's ticks); False if unusable."""
        rtt = received_ns - sent_ns
        if rtt < 0 or rtt > self.max_rtt_ns:
            return False
        offset = (sent_ns + received_ns) // 2 - self.ticks_to_ns(server_ticks)
        if (
            self.offset_ns is not None
            and self.rtt_ns is not None
            and abs(offset - self.offset_ns) > self.jump_ns + rtt + self.rtt_ns
        ):
            self.reset()
        self._samples.append((rtt, offset))
        self.rtt_ns, self.offset_ns = min(self._samples)
        return True

    def to_local(self, ticks: int) -> int:
        """A server tick count as local wall-clock nanoseconds (the clock must be :attr:`ready`)."""
        assert self.offset_ns is not None
        return ticks * _NS // self.frequency + self.offset_ns

    def reset(self) -> None:
        """Forget every sample (the server restarted, or its clock jumped)."""
        self._samples.clear()
        self.offset_ns = self.rtt_ns = None
        self.resets += 1


def _ipv4(text: str, what: str) -> str:
    try:
        return str(ipaddress.IPv4Address(text))
    except ValueError:
        raise MocapError(f"{what} {text!r} is not an IPv4 address") from None


def local_address_towards(server: str, port: int = natnet.COMMAND_PORT) -> str:
    """The local address the system would use to reach ``server`` (no packet is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect((server, port))
            return str(probe.getsockname()[0])
        except OSError:
            return "0.0.0.0"


class NatNetClient:
    """A NatNet client: :meth:`open`, then :meth:`poll` in a loop; :meth:`close` (or use ``with``) at the end.

    ``server`` is the Motive computer's IPv4 address, ``interface`` this computer's address on the mocap
    network (the multicast group is joined there, the command socket bound there; ``""`` lets the system
    choose). ``group``/``data_port`` default to what the server's SERVERINFO says (NatNet 3.0+), else the
    NatNet defaults. ``on_reject(reason, detail)`` is called for every input or event counted as a problem,
    ``on_count(name, n)`` for normal protocol events (``serverinfo``, ``modeldef``, ``echo``…).
    """

    def __init__(
        self,
        server: str,
        *,
        command_port: int = natnet.COMMAND_PORT,
        interface: str = "",
        multicast: bool = True,
        group: str | None = None,
        data_port: int | None = None,
        loss_timeout: float = 1.0,
        retry: float = 0.25,
        max_backoff: float = 4.0,
        modeldef_retry: float = 1.0,
        echo_period: float = 0.5,
        keepalive_period: float = 1.0,
        app_name: str = "FlyingArena",
        on_reject: Callable[[str, str], None] | None = None,
        on_count: Callable[[str, int], None] | None = None,
    ) -> None:
        self.server = _ipv4(server, "mocap server")
        self.interface = "" if interface in ("", "0.0.0.0") else _ipv4(interface, "mocap interface")
        if not 1 <= command_port <= 65535:
            raise MocapError(f"command port {command_port} outside 1..65535")
        if data_port is not None and not 1 <= data_port <= 65535:
            raise MocapError(f"data port {data_port} outside 1..65535")
        if group is not None and not ipaddress.IPv4Address(_ipv4(group, "multicast group")).is_multicast:
            raise MocapError(f"multicast group {group!r} is not a multicast address (224.0.0.0/4)")
        self.command_port = command_port
        self.multicast = multicast
        self.group = group
        self.data_port = data_port
        self.loss_timeout = loss_timeout
        self.retry = retry
        self.max_backoff = max_backoff
        self.modeldef_retry = modeldef_retry
        self.echo_period = echo_period
        self.keepalive_period = keepalive_period
        self.app_name = app_name
        self.on_reject = on_reject
        self.on_count = on_count

        self.counts: dict[str, int] = {}
        self.rejected: dict[str, int] = {}
        self.info: ServerInfo | None = None  # the current session's SERVERINFO (None while handshaking)
        self.last_info: ServerInfo | None = None  # the last SERVERINFO ever received
        self.model_defs: ModelDefs | None = None
        self.names: dict[int, str] = {}
        self.models = 0  # model definitions received (generation of ``names``)
        self.clock: EchoClock | None = None
        self.frames = 0
        self.last_frame_number: int | None = None
        self.data_address: tuple[str, int] | None = None  # the group and port listened on (multicast only)

        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._socks: list[socket.socket] = []
        self._server_addr = (self.server, command_port)
        self._version: Version | None = None
        self._freq = 0
        self._backoff = retry
        self._next_connect = 0.0
        self._next_modeldef = math.inf
        self._next_echo = math.inf
        self._next_keepalive = math.inf
        self._echo_burst = 0
        self._echo_sent: collections.deque[int] = collections.deque(maxlen=32)
        self._last_frame = 0.0  # monotonic time of the last frame, or of the SERVERINFO starting a session
        self._decode_failures = 0

    # -- lifetime ---------------------------------------------------------------------------------
    def open(self) -> NatNetClient:
        """Create the sockets and send CONNECT; raise :class:`MocapError` if the sockets cannot be set up."""
        self._open_sockets()
        self._start_handshake(time.monotonic(), reset_backoff=True)
        return self

    def close(self) -> None:
        """Tell the server we leave (DISCONNECT) and close the sockets."""
        if self._cmd is not None and self.info is not None:
            self._send(natnet.encode_disconnect())
        self._close_sockets()
        self.info = None
        self._version = None

    def __enter__(self) -> NatNetClient:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def version(self) -> Version | None:
        """The server's NatNet version in the current session (None until SERVERINFO)."""
        return self._version

    @property
    def command_address(self) -> tuple[str, int] | None:
        """The local address of the command socket (where replies, and unicast frames, arrive)."""
        if self._cmd is None:
            return None
        host, port = self._cmd.getsockname()[:2]
        return str(host), int(port)

    # -- sockets ----------------------------------------------------------------------------------
    def _open_sockets(self) -> None:
        self._close_sockets()
        try:
            cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        except OSError as exc:
            raise MocapError(f"cannot create a UDP socket: {exc}") from None
        try:
            cmd.setblocking(False)
            cmd.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF)
            cmd.bind((self.interface, 0))
        except OSError as exc:
            cmd.close()
            raise MocapError(
                f"cannot bind the command socket to interface {self.interface or '0.0.0.0'}: "
                f"{exc.strerror or exc} (is it an address of this computer?)"
            ) from None
        self._cmd = cmd
        self._socks = [cmd]
        if self.multicast and (
            self.group is not None or self.data_port is not None or self.last_info is not None
        ):
            self._open_data_socket(self.last_info)

    def _open_data_socket(self, info: ServerInfo | None) -> None:
        """(Re)open the multicast data socket for the group and port configured, else those announced."""
        group = self.group or (info.multicast_group if info and info.multicast_group else DEFAULT_GROUP)
        port = self.data_port or (info.data_port if info and info.data_port else natnet.DATA_PORT)
        if not ipaddress.IPv4Address(group).is_multicast:
            group = DEFAULT_GROUP
        if self._data is not None:
            if self.data_address == (group, port):
                return
            self._socks.remove(self._data)
            self._data.close()
            self._data = None
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF)
            try:
                sock.bind((group, port))  # only this group's datagrams (Linux, macOS)
            except OSError:
                sock.bind(("", port))  # systems that refuse to bind a group address
            iface = socket.inet_aton(self.interface or "0.0.0.0")
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(group) + iface)
            self.data_address = (group, port)
        except OSError as exc:
            sock.close()
            raise MocapError(
                f"cannot join multicast group {group}:{port} on interface {self.interface or '0.0.0.0'}: "
                f"{exc.strerror or exc} (the interface must be this computer's address on the mocap network)"
            ) from None
        self._data = sock
        self._socks.append(sock)

    def _close_sockets(self) -> None:
        for sock in self._socks:
            try:
                sock.close()
            except OSError:
                pass
        self._socks = []
        self._cmd = self._data = None

    def _send(self, datagram: bytes) -> bool:
        if self._cmd is None:
            return False
        try:
            self._cmd.sendto(datagram, self._server_addr)
            return True
        except OSError as exc:
            self._reject("socket_error", f"send to {self.server}:{self.command_port}: {exc.strerror or exc}")
            return False

    # -- accounting -------------------------------------------------------------------------------
    def _reject(self, reason: str, detail: str) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        if self.on_reject is not None:
            self.on_reject(reason, detail)
        else:
            log.debug("%s: %s", reason, detail)

    def _count(self, name: str, n: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + n
        if self.on_count is not None:
            self.on_count(name, n)

    # -- protocol steps -----------------------------------------------------------------------------
    def _start_handshake(self, now: float, reset_backoff: bool = False) -> None:
        """Forget the session and send CONNECT; retries follow the back-off."""
        self.info = None
        self._version = None
        self.clock = None
        self._next_modeldef = self._next_echo = self._next_keepalive = math.inf
        if reset_backoff:
            self._backoff = self.retry
        self._connect(now)

    def _connect(self, now: float) -> None:
        self._count("connect")
        self._send(natnet.encode_connect(self.app_name, Version(1), CLIENT_NATNET_VERSION))
        self._next_connect = now + self._backoff
        self._backoff = min(self._backoff * 2, self.max_backoff)

    def _lost(self, now: float, why: str) -> None:
        """No data: reopen the sockets (a lost membership or interface comes back) and handshake again."""
        self._reject("no_data", why)
        self._count("reconnect")
        self.last_frame_number = None
        try:
            self._open_sockets()
        except MocapError as exc:
            self._reject("socket_error", str(exc))
        self._start_handshake(now)
        self._last_frame = now

    def _timers(self, now: float) -> float:
        """Run what is due; return when the next timer fires."""
        if self._version is None:
            if now >= self._next_connect:
                if self._cmd is None:
                    try:
                        self._open_sockets()
                    except MocapError as exc:
                        self._reject("socket_error", str(exc))
                self._connect(now)
            return self._next_connect
        if now - self._last_frame > self.loss_timeout:
            self._lost(now, f"no frame for {now - self._last_frame:.1f} s from {self.server}")
            return self._next_connect
        if now >= self._next_modeldef:
            self._count("request_modeldef")
            self._send(natnet.encode_request_model_defs())
            self._next_modeldef = now + self.modeldef_retry
        if now >= self._next_echo:
            stamp = time.time_ns()
            self._echo_sent.append(stamp)
            self._send(natnet.encode_echo_request(stamp))
            if self._echo_burst > 0:
                self._echo_burst -= 1
                self._next_echo = now + 0.02
            else:
                self._next_echo = now + self.echo_period
        if now >= self._next_keepalive:
            self._send(natnet.encode_keepalive())
            self._count("keepalive")
            self._next_keepalive = now + self.keepalive_period
        return min(
            self._next_modeldef, self._next_echo, self._next_keepalive, self._last_frame + self.loss_timeout
        )

    # -- receiving ----------------------------------------------------------------------------------
    def poll(self, timeout: float = 0.1) -> TimedFrame | None:
        """Do the protocol work due and return the next frame, or ``None`` after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            now = time.monotonic()
            wake = min(self._timers(now), deadline)
            socks = self._socks
            if not socks:
                wait = max(0.0, wake - now)
                if wait > 0:
                    time.sleep(wait)
                if time.monotonic() >= deadline:
                    return None
                continue
            try:
                ready, _, _ = select.select(socks, (), (), max(0.0, wake - now))
            except (OSError, ValueError):  # a socket closed under us: reopen at the next attempt
                self._close_sockets()
                continue
            for sock in ready:
                try:
                    data, addr = sock.recvfrom(_RECV_SIZE)
                except BlockingIOError:
                    continue
                except OSError as exc:
                    if exc.errno not in (errno.ECONNREFUSED, errno.EAGAIN):
                        self._reject("socket_error", f"receive: {exc.strerror or exc}")
                    continue
                arrival = time.time_ns()
                if sock is self._cmd and addr[0] != self.server:
                    self._reject("foreign_sender", f"datagram from {addr[0]}:{addr[1]}, not the server")
                    continue
                frame = self._handle(data, arrival)
                if frame is not None:
                    return frame
            if time.monotonic() >= deadline:
                return None

    def feed(self, datagram: bytes, arrival: int | None = None) -> TimedFrame | None:
        """Handle one datagram as if it had been received (replays, tests); returns the frame it held."""
        return self._handle(datagram, time.time_ns() if arrival is None else arrival)

    def _handle(self, data: bytes, arrival: int) -> TimedFrame | None:
        n = len(data)
        if n < 4:
            self._reject("garbage", f"{n}-byte datagram")
            return None
        message_id, length = _HEADER.unpack_from(data, 0)
        size = n - 4
        if length != size & 0xFFFF:
            name = _message_name(message_id)
            if length > size:
                self._reject("truncated", f"{name}: length field {length}, datagram holds {size} bytes")
            else:
                self._reject(
                    "oversized", f"{name}: {size} bytes in a datagram whose length field says {length}"
                )
            return None
        if message_id == MessageId.FRAMEOFDATA:
            return self._on_frame(data[4:], arrival)
        if message_id == MessageId.ECHORESPONSE:
            self._on_echo(data[4:], arrival)
        elif message_id == MessageId.SERVERINFO:
            self._on_server_info(data[4:])
        elif message_id == MessageId.MODELDEF:
            self._on_model_defs(data[4:])
        elif message_id in (MessageId.RESPONSE, MessageId.UNRECOGNIZED_REQUEST):
            self._count("response")
        elif message_id == MessageId.MESSAGESTRING:
            self._count("message")
            log.info("server says: %s", natnet.decode_message_string(data[4:]))
        elif message_id in _CLIENT_MESSAGES:
            self._count("client_message")  # another client's request seen on a shared port
        else:
            self._reject("unknown_message", f"message id {message_id}, {size} bytes")
        return None

    def _on_server_info(self, payload: bytes) -> None:
        try:
            info = natnet.decode_server_info(payload)
        except NatNetError as exc:
            self._reject("bad_serverinfo", str(exc))
            return
        now = time.monotonic()
        self._count("serverinfo")
        previous = self.last_info
        if previous is not None and previous.natnet_version != info.natnet_version:
            self._reject("version_change", f"server NatNet {previous.natnet_version} → {info.natnet_version}")
        if not 2 <= info.natnet_version.major <= 4:
            self._reject(
                "unsupported_version", f"server speaks NatNet {info.natnet_version} (2.0–4.x understood)"
            )
            return
        if self._version is not None and info == self.info:
            return  # a repeated answer to a retried CONNECT
        self.info = self.last_info = info
        self._version = info.natnet_version
        self._freq = info.clock_frequency or 0
        self._decode_failures = 0
        self._last_frame = now
        self._backoff = self.retry
        if self.multicast and (self._data is None or (self.group is None and self.data_port is None)):
            try:
                self._open_data_socket(info)
            except MocapError as exc:
                self._reject("socket_error", str(exc))
        if self.multicast and info.is_multicast and self.data_address is not None:
            announced = (info.multicast_group, info.data_port)
            if announced != self.data_address:
                self._reject(
                    "config_mismatch",
                    f"server streams to {announced[0]}:{announced[1]}, listening on "
                    f"{self.data_address[0]}:{self.data_address[1]} (check mocap.group and mocap.data_port)",
                )
        if info.is_multicast is not None and info.is_multicast != self.multicast:
            self._reject(
                "config_mismatch",
                f"server streams {'multicast' if info.is_multicast else 'unicast'}, client expects "
                f"{'multicast' if self.multicast else 'unicast'}",
            )
        if previous != info:
            log.info(
                "server %s %s, NatNet %s%s",
                info.app_name,
                info.app_version,
                info.natnet_version,
                f", clock {info.clock_frequency} Hz" if info.clock_frequency else "",
            )
        self.clock = EchoClock(self._freq) if self._freq > 0 and info.natnet_version.major >= 3 else None
        self._next_modeldef = now
        self._next_echo = now if self.clock is not None else math.inf
        self._echo_burst = 4
        self._next_keepalive = (
            now if (not self.multicast and info.natnet_version >= KEEPALIVE_SINCE) else math.inf
        )

    def _on_model_defs(self, payload: bytes) -> None:
        if self._version is None:
            self._reject("before_serverinfo", "MODELDEF before SERVERINFO")
            return
        try:
            defs = natnet.decode_model_defs(payload, self._version)
        except NatNetError as exc:
            self._reject("bad_modeldef", str(exc))
            return
        self._count("modeldef")
        self.model_defs = defs
        self.names = defs.rigid_body_names()
        self.models += 1
        self._next_modeldef = math.inf

    def _on_echo(self, payload: bytes, arrival: int) -> None:
        try:
            sent, ticks = natnet.decode_echo_response(payload)
        except NatNetError as exc:
            self._reject("bad_echo", str(exc))
            return
        if self.clock is None or sent not in self._echo_sent:
            self._reject("bad_echo", f"ECHORESPONSE to an unknown request {sent}")
            return
        self._echo_sent.remove(sent)
        if self.clock.add(sent, ticks, arrival):
            self._count("echo")

    def _on_frame(self, payload: bytes, arrival: int) -> TimedFrame | None:
        version = self._version
        if version is None:
            self._reject("before_serverinfo", "frame before the server's NatNet version is known")
            return None
        try:
            frame = natnet.decode_frame(payload, version)
        except NatNetError as exc:
            self._reject("bad_frame", str(exc))
            self._decode_failures += 1
            if self._decode_failures >= _MAX_DECODE_FAILURES:
                self._reject(
                    "resync", f"{self._decode_failures} undecodable frames in a row: handshake again"
                )
                self._start_handshake(time.monotonic(), reset_backoff=True)
            return None
        self._decode_failures = 0
        fn = frame.frame_number
        last = self.last_frame_number
        if last is not None and fn <= last:
            if fn == last:
                self._reject("duplicate", f"frame {fn} again")
                return None
            if last - fn < _RESTART_BACKWARDS:
                self._reject("out_of_order", f"frame {fn} after {last}")
                return None
            # A new session (Motive restarted, or a take looped): its clock and maybe its version changed.
            self._reject("server_restart", f"frame number went back from {last} to {fn}: handshake again")
            self.last_frame_number = None
            self._start_handshake(time.monotonic(), reset_backoff=True)
            return None
        self.last_frame_number = fn
        self._last_frame = time.monotonic()
        self.frames += 1
        if frame.params & 0x02 and self._next_modeldef == math.inf:
            self._count("models_changed")
            self._next_modeldef = self._last_frame

        lat = -1
        tsrc = "arrival"
        t = arrival
        mid = frame.cam_mid_exposure
        freq = self._freq
        if freq > 0 and mid is not None and frame.transmit is not None:
            ticks = frame.transmit - mid
            if ticks >= 0:
                lat = ticks * _NS // freq
                if lat > _MAX_LATENCY_NS:
                    lat = -1
            clock = self.clock
            if clock is not None and clock.offset_ns is not None:
                t_echo = mid * _NS // freq + clock.offset_ns
                # The camera exposed before we read the datagram, and not long before.
                slack = 2_000_000 + (clock.rtt_ns or 0)
                if arrival - _NS < t_echo <= arrival + slack:
                    t, tsrc = t_echo, "echo"
                else:
                    self._reject(
                        "clock_reset",
                        f"echo clock maps the exposure {(t_echo - arrival) / 1e6:+.1f} ms from arrival",
                    )
                    clock.reset()
            if tsrc == "arrival" and lat >= 0:
                t, tsrc = arrival - lat, "latency"
        return TimedFrame(
            fn,
            frame.rigid_bodies,
            t,
            tsrc,
            lat,
            frame.timestamp or 0.0,
            arrival,
            self.names,
            self.models,
            frame.params,
        )


_CLIENT_MESSAGES = frozenset(
    {
        MessageId.CONNECT,
        MessageId.REQUEST,
        MessageId.REQUEST_MODELDEF,
        MessageId.REQUEST_FRAMEOFDATA,
        MessageId.DISCONNECT,
        MessageId.KEEPALIVE,
        MessageId.ECHOREQUEST,
        MessageId.DISCOVERY,
    }
)


def _message_name(message_id: int) -> str:
    try:
        return MessageId(message_id).name
    except ValueError:
        return f"message {message_id}"
