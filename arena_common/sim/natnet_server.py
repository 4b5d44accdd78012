"""A NatNet server that behaves like OptiTrack Motive: the Motive emulator.

:class:`NatNetServer` — the UDP command socket (CONNECT/discovery → SERVERINFO, REQUEST_MODELDEF → MODELDEF,
text requests, echo, keep-alive, disconnect) and the FRAMEOFDATA stream, by multicast or unicast, for any
NatNet version the codec knows (the emulator offers 3.0, 3.1, 4.0 and 4.1). Its parts, re-exported here:

* :mod:`arena_common.sim.natnet_motive` — :class:`TickClock`, the high-resolution clock of the frames' tick
  stamps and of the echo replies (``time.perf_counter_ns`` counted at :data:`TICK_FREQUENCY`, 10 MHz like
  Windows' QPC), and :func:`sleep_until`, the building block of drift-free, clock-driven frame schedules.
* :mod:`arena_common.sim.natnet_scene` — :class:`SimScene`, simulated rigid bodies turned into Motive frames:
  true poses converted to Motive's frame, Gaussian noise, dropped frames, occlusions, camera and software
  latency.
* :mod:`arena_common.sim.natnet_replay` — :class:`Recording` / :func:`load_recording`, a captured Motive session
  (pcap/pcapng, or decoded frames as JSON lines) to replay at its original timing.
* :mod:`arena_common.sim.natnet_sessions` — the unicast clients.

Unicast as Motive does it, for NatNet 3.0, 3.1, 4.0 and 4.1 alike: every client's frames go to the address
its CONNECT came from (the socket that sent it), from the data port, and nowhere else — not to the data port
of the client's address (:mod:`arena_common.sim.natnet_sessions`; the evidence is in docs/architecture.md).
SERVERINFO always reaches a new client before its first frame. A client is forgotten on DISCONNECT, after
``client_timeout`` seconds of silence if it ever sent a KEEPALIVE (clients that never do — multicast clients,
libmotioncapture — are kept), or when its port is closed. A KEEPALIVE from an address that is not subscribed
subscribes it again (after a SERVERINFO), so clients survive a server restart.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

from arena_common.mocap import natnet
from arena_common.mocap.natnet import ConnectRequest, Frame, MessageId, ModelDefs, ServerInfo, Version
from arena_common.sim.natnet_motive import (
    TICK_FREQUENCY,
    NatNetServerError,
    TickClock,
    motive_app_version,
    served_version,
    sleep_until,
)
from arena_common.sim.natnet_replay import Recording, iter_schedule, load_recording
from arena_common.sim.natnet_scene import (
    ANGLE_NOISE_PER_M,
    CAMERA_LATENCY,
    SOFTWARE_LATENCY,
    TRUTH_TIMEOUT,
    SceneCounters,
    SimScene,
)
from arena_common.sim.natnet_sessions import ClientInfo, Subscriptions

__all__ = [
    "ANGLE_NOISE_PER_M",
    "CAMERA_LATENCY",
    "MODELS_CHANGED",
    "MODELS_CHANGED_FRAMES",
    "SOFTWARE_LATENCY",
    "TICK_FREQUENCY",
    "TRUTH_TIMEOUT",
    "ClientInfo",
    "NatNetServer",
    "NatNetServerError",
    "Recording",
    "SceneCounters",
    "ServerCounters",
    "SimScene",
    "TickClock",
    "iter_schedule",
    "load_recording",
    "motive_app_version",
    "sleep_until",
]

log = logging.getLogger("arena.natnet_server")

#: Frame params bit: the list of tracked models changed (clients re-request MODELDEF).
MODELS_CHANGED = 0x02
#: How many transmitted frames carry :data:`MODELS_CHANGED` after a model change (one could be lost).
MODELS_CHANGED_FRAMES = 3


# ------------------------------------------------------------------------------------------------------------
# The server
# ------------------------------------------------------------------------------------------------------------


@dataclass(slots=True)
class ServerCounters:
    """What a :class:`NatNetServer` did since it started."""

    frames: int = 0  # FRAMEOFDATA sent (once per frame, whatever the number of unicast clients)
    datagrams: int = 0  # FRAMEOFDATA datagrams (one per unicast client, one per multicast frame)
    bytes: int = 0
    send_errors: int = 0
    requests: int = 0  # command-socket messages answered or accepted
    unrecognized: int = 0  # text requests answered with UNRECOGNIZED_REQUEST
    ignored: int = 0  # malformed, or message ids a server does not accept
    connects: int = 0
    disconnects: int = 0
    gone: int = 0  # unicast clients forgotten because their port was closed


# Text requests Motive acknowledges with an integer 0 (no effect in an emulator).
_ACCEPTED_COMMANDS = frozenset(
    s.lower()
    for s in (
        "StartRecording",
        "StopRecording",
        "LiveMode",
        "EditMode",
        "TimelinePlay",
        "TimelineStop",
        "SetPlaybackTakeName",
        "SetRecordTakeName",
        "SetCurrentSession",
        "SetPlaybackStartFrame",
        "SetPlaybackStopFrame",
        "SetPlaybackLooping",
        "SetPlaybackCurrentFrame",
        "SubscribeToData",
        "SubscribeByID",
    )
)

RequestHandler = Callable[[str, tuple[str, int]], "str | bytes | int | float | None"]


class NatNetServer:
    """A Motive-like NatNet server on real UDP sockets.

    The command socket is bound to ``host:command_port``. Frames go to ``group:data_port`` from a socket
    bound to ``interface`` (``IP_MULTICAST_IF`` = ``interface``, loopback on, TTL 1) when ``multicast``,
    else to every subscribed client (see the module docstring). Feed it with :meth:`send_frame` (encoded
    for the current version, models-changed bit added when due) or :meth:`send_datagram` (sent as is).

    Text requests: ``FrameRate`` (f32), ``Bitstream`` (the version as text) and ``Bitstream,X.Y`` (switch
    the stream's version: i32 0, or -1 when refused), ``AnalogSamplesPerMocapFrame`` (i32 0),
    ``UnitsToMillimeters`` (f32 1000), ``CurrentMode`` (i32 0, live), recording/timeline/subscription
    commands (i32 0, no effect); ``request_handler(text, address)`` is asked first and may answer
    anything else; the rest gets UNRECOGNIZED_REQUEST.
    """

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        command_port: int = natnet.COMMAND_PORT,
        data_port: int = natnet.DATA_PORT,
        multicast: bool = True,
        group: str = natnet.MULTICAST_GROUP,
        interface: str = "127.0.0.1",
        version: str | Version = "3.1",
        app_name: str = "Motive",
        app_version: Version | None = None,
        clock: TickClock | None = None,
        frame_rate: float = 180.0,
        models: ModelDefs | None = None,
        request_handler: RequestHandler | None = None,
        client_timeout: float | None = 10.0,
        allow_bitstream_change: bool = True,
    ) -> None:
        self.host, self.command_port, self.data_port = host, int(command_port), int(data_port)
        self.multicast, self.group, self.interface = bool(multicast), group, interface
        self._version = served_version(version)
        self.app_name = app_name
        self.app_version = app_version
        self.clock = clock or TickClock()
        self.frame_rate = float(frame_rate)
        self.request_handler = request_handler
        self.client_timeout = client_timeout
        self.allow_bitstream_change = allow_bitstream_change
        self.counters = ServerCounters()
        self._models = models or ModelDefs()
        self._models_changed = 0
        self._sessions = Subscriptions(
            host=host, data_port=self.data_port, unicast=not self.multicast, client_timeout=client_timeout
        )
        self._last_frame: bytes | None = None
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._thread: threading.Thread | None = None
        try:
            socket.inet_aton(group)
            socket.inet_aton(interface)
        except OSError:
            raise NatNetServerError(
                f"multicast group {group!r} and interface {interface!r} must be IPv4"
            ) from None
        if not 0 < self.command_port < 65536 or not 0 < self.data_port < 65536:
            raise NatNetServerError(f"ports must be in 1..65535, got {command_port} and {data_port}")

    # -- life cycle --------------------------------------------------------------------------------
    def start(self) -> NatNetServer:
        """Bind the sockets and start answering commands."""
        if self._cmd is not None:
            return self
        cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            cmd.bind((self.host, self.command_port))
        except OSError as exc:
            cmd.close()
            where = f"{self.host}:{self.command_port}"
            raise NatNetServerError(
                f"cannot bind the NatNet command socket to {where}: {exc.strerror or exc}"
            ) from None
        cmd.settimeout(0.1)
        data: socket.socket | None = None
        if self.multicast:
            data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(self.interface))
                data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
                data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
                data.bind((self.interface, 0))
            except OSError as exc:
                data.close()
                cmd.close()
                raise NatNetServerError(
                    f"cannot send multicast from interface {self.interface}: {exc.strerror or exc}"
                ) from None
        try:
            self._sessions.open()
        except OSError as exc:
            for sock in (cmd, data):
                if sock is not None:
                    sock.close()
            raise NatNetServerError(
                f"cannot open the unicast frame socket on {self.host}: {exc.strerror or exc}"
            ) from None
        self._cmd, self._data = cmd, data
        self._thread = threading.Thread(target=self._serve, name="natnet-command", daemon=True)
        self._thread.start()
        log.info(
            "NatNet %s server on %s:%d, frames %s",
            self.version,
            self.host,
            self.command_port,
            f"to {self.group}:{self.data_port} via {self.interface}" if self.multicast else "by unicast",
        )
        return self

    def close(self) -> None:
        """Stop answering and close the sockets."""
        self._closed.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for sock in (self._cmd, self._data):
            if sock is not None:
                sock.close()
        self._sessions.close()

    def __enter__(self) -> NatNetServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- state -------------------------------------------------------------------------------------
    @property
    def version(self) -> Version:
        """The NatNet version frames, SERVERINFO and MODELDEF are encoded for."""
        return self._version

    @version.setter
    def version(self, value: str | Version) -> None:
        v = served_version(value)
        with self._lock:
            self._version = v

    @property
    def command_address(self) -> tuple[str, int]:
        """The address the command socket is bound to."""
        if self._cmd is None:
            return (self.host, self.command_port)
        host, port = self._cmd.getsockname()[:2]
        return (str(host), int(port))

    @property
    def models(self) -> ModelDefs:
        """The model definitions served to REQUEST_MODELDEF."""
        return self._models

    def set_models(self, models: ModelDefs) -> None:
        """Replace the model definitions; the next frames carry the models-changed bit."""
        with self._lock:
            changed = models != self._models
            self._models = models
            if changed:
                self._models_changed = MODELS_CHANGED_FRAMES

    @property
    def clients(self) -> list[ClientInfo]:
        """The clients that connected and have not left."""
        return self._sessions.clients()

    @property
    def clients_left(self) -> list[ClientInfo]:
        """The clients that left, timed out or were found gone (their port closed), oldest first."""
        return self._sessions.left()

    def server_info(self) -> ServerInfo:
        """The SERVERINFO this server sends."""
        return ServerInfo(
            app_name=self.app_name,
            app_version=self.app_version or motive_app_version(self.version),
            natnet_version=self.version,
            clock_frequency=self.clock.frequency,
            data_port=self.data_port,
            is_multicast=self.multicast,
            multicast_group=self.group,
        )

    # -- streaming ---------------------------------------------------------------------------------
    def send_frame(self, frame: Frame) -> int:
        """Encode ``frame`` for the current version and stream it; returns the datagrams sent.

        While a model change is being announced, the frame's params get :data:`MODELS_CHANGED`.
        """
        with self._lock:
            version = self._version
            if self._models_changed:
                self._models_changed -= 1
                frame = replace(frame, params=frame.params | MODELS_CHANGED)
        return self.send_datagram(natnet.encode_frame(frame, version))

    def send_datagram(self, datagram: bytes) -> int:
        """Stream one FRAMEOFDATA datagram as it is; returns the datagrams sent."""
        self._last_frame = datagram
        if self._cmd is None:
            raise NatNetServerError("the server is not started")
        if self.multicast:
            assert self._data is not None
            try:
                self._data.sendto(datagram, (self.group, self.data_port))
                sent = 1
            except OSError as exc:
                sent = 0
                self._send_failed((self.group, self.data_port), exc)
        else:
            result = self._sessions.send(datagram)
            sent = result.sent
            for target, error in result.failures:
                self._send_failed(target, error)
            for address in result.gone:
                self.counters.gone += 1
                log.info("client %s:%d gone (its port is closed)", *address)
        self.counters.frames += 1
        self.counters.datagrams += sent
        self.counters.bytes += sent * len(datagram)
        return sent

    def _send_failed(self, target: tuple[str, int], exc: OSError) -> None:
        self.counters.send_errors += 1
        if self.counters.send_errors in (1, 10, 100) or self.counters.send_errors % 1000 == 0:
            log.warning("frame not sent to %s:%d: %s", *target, exc)

    # -- command socket ----------------------------------------------------------------------------
    def _serve(self) -> None:
        assert self._cmd is not None
        sock = self._cmd
        last_expiry = time.monotonic()
        while not self._closed.is_set():
            try:
                data, addr = sock.recvfrom(65535)
            except TimeoutError:
                data = b""
            except OSError as exc:
                if self._closed.is_set():
                    break
                log.debug("command socket: %s", exc)  # e.g. ICMP port unreachable reported late
                continue
            now = time.monotonic()
            if data:
                try:
                    reply = self._handle(data, (str(addr[0]), int(addr[1])), now)
                except natnet.NatNetError as exc:
                    self.counters.ignored += 1
                    log.debug("bad command from %s:%d: %s", addr[0], addr[1], exc)
                    reply = None
                except Exception:  # a request handler's bug must not end the command socket
                    self.counters.ignored += 1
                    log.exception("command from %s:%d not handled", addr[0], addr[1])
                    reply = None
                if reply is not None:
                    self._reply(reply, (str(addr[0]), int(addr[1])))
            if now - last_expiry >= 0.5:
                last_expiry = now
                self._expire(now)

    def _reply(self, datagram: bytes, addr: tuple[str, int]) -> None:
        """Send ``datagram`` from the command socket to ``addr``."""
        try:
            assert self._cmd is not None
            self._cmd.sendto(datagram, addr)
        except OSError as exc:
            self.counters.send_errors += 1
            log.debug("reply to %s:%d failed: %s", addr[0], addr[1], exc)

    def _expire(self, now: float) -> None:
        for address in self._sessions.expire(now):
            log.info("client %s:%d timed out", *address)

    def _handle(self, data: bytes, addr: tuple[str, int], now: float) -> bytes | None:
        message_id, payload = natnet.split_packet(data)
        self._sessions.seen(addr, now)
        if message_id in (MessageId.CONNECT, MessageId.DISCOVERY):
            self.counters.requests += 1
            info = natnet.encode_server_info(self.server_info())
            if message_id == MessageId.DISCOVERY:
                return info
            self._subscribe(addr, natnet.decode_connect(payload), info, now)
            return None
        if message_id == MessageId.REQUEST_MODELDEF:
            self.counters.requests += 1
            with self._lock:
                models, version = self._models, self._version
            return natnet.encode_model_defs(models, version)
        if message_id == MessageId.REQUEST:
            self.counters.requests += 1
            return self._answer(natnet.decode_request_text(payload), addr)
        if message_id == MessageId.ECHOREQUEST:
            self.counters.requests += 1
            return natnet.encode_echo_response(natnet.decode_echo_request(payload), self.clock.now())
        if message_id == MessageId.KEEPALIVE:
            self.counters.requests += 1
            info = natnet.encode_server_info(self.server_info())
            if self._sessions.keepalive(addr, now, lambda: self._reply(info, addr)):
                self.counters.connects += 1
                log.info("client %s:%d subscribed again by keep-alive", *addr)
            return None
        if message_id == MessageId.DISCONNECT:
            self.counters.requests += 1
            if self._sessions.disconnect(addr):
                self.counters.disconnects += 1
                log.info("client %s:%d disconnected", *addr)
            return None
        if message_id == MessageId.REQUEST_FRAMEOFDATA:
            self.counters.requests += 1
            return self._last_frame
        self.counters.ignored += 1
        return None

    def _subscribe(self, addr: tuple[str, int], hello: ConnectRequest, info: bytes, now: float) -> None:
        """Answer a CONNECT with SERVERINFO, then send the client frames (never the other way round)."""
        if self._sessions.connect(addr, hello, now, lambda: self._reply(info, addr)):
            self.counters.connects += 1
            log.info(
                "client %s:%d connected (%s, NatNet %s)%s",
                *addr,
                hello.app_name or "unnamed",
                hello.natnet_version or "not said",
                "" if self.multicast else ": frames to this address, from the data port",
            )

    def _answer(self, text: str, addr: tuple[str, int]) -> bytes:
        if self.request_handler is not None:
            answer = self.request_handler(text, addr)
            if answer is not None:
                return natnet.encode_response(answer)
        command, _, argument = text.partition(",")
        key = command.strip().lower()
        if key == "framerate":
            return natnet.encode_response(float(self.frame_rate))
        if key == "bitstream":
            if not argument.strip():
                return natnet.encode_response(str(self.version))
            if not self.allow_bitstream_change:
                return natnet.encode_response(-1)
            try:
                self.version = argument.strip()
            except NatNetServerError as exc:
                log.info("refused %r from %s:%d: %s", text, *addr, exc)
                return natnet.encode_response(-1)
            log.info("bitstream switched to NatNet %s by %s:%d", self.version, *addr)
            return natnet.encode_response(0)
        if key == "analogsamplespermocapframe":
            return natnet.encode_response(0)
        if key == "unitstomillimeters":
            return natnet.encode_response(1000.0)
        if key == "currentmode":
            return natnet.encode_response(0)
        if key in _ACCEPTED_COMMANDS:
            return natnet.encode_response(0)
        self.counters.unrecognized += 1
        return natnet.encode_unrecognized()
