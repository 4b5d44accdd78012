"""A NatNet server that behaves like OptiTrack Motive, and the frame sources that feed it.

* :class:`NatNetServer` — the UDP command socket (CONNECT/discovery → SERVERINFO, REQUEST_MODELDEF →
  MODELDEF, text requests, echo, keep-alive, disconnect) and the FRAMEOFDATA stream, by multicast or
  unicast, for any NatNet version the codec knows (the emulator offers 3.0, 3.1, 4.0 and 4.1).
* :class:`TickClock` — the high-resolution clock of the frames' tick stamps and of the echo replies
  (``time.perf_counter_ns`` counted at :data:`TICK_FREQUENCY`, 10 MHz like Windows' QPC).
* :func:`sleep_until` — the building block of drift-free, clock-driven frame schedules.
* :class:`SimScene` — simulated rigid bodies turned into Motive frames: true poses converted to Motive's
  frame, Gaussian noise, dropped frames, occlusions, camera and software latency.
* :class:`Recording` / :func:`load_recording` — a captured Motive session (pcap/pcapng, or decoded frames
  as JSON lines) to replay at its original timing.

Unicast follows the NatNet SDK: a client subscribes by sending CONNECT from its command socket and
receives the frames on that same socket (the SDK's unicast "data socket" is bound to an ephemeral port
the server never learns; its command thread decodes the frames and sends a KEEPALIVE after each
receive). A client is forgotten on DISCONNECT, or after ``client_timeout`` seconds of silence if it ever
sent a KEEPALIVE (clients that never do — NatNet 3.x, multicast clients — are kept). A KEEPALIVE from an
address that is not subscribed subscribes it again, so clients survive a server restart.
"""

from __future__ import annotations

import logging
import math
import random
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from fractions import Fraction
from pathlib import Path

from arena_common import natnet
from arena_common.capture import CaptureError, iter_udp, read_frames_jsonl
from arena_common.errors import ArenaError
from arena_common.frames import FrameTransform, quat_multiply
from arena_common.natnet import (
    Frame,
    MessageId,
    ModelDefs,
    RigidBody,
    RigidBodyDef,
    ServerInfo,
    Version,
)

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

#: Ticks per second of :class:`TickClock` (what SERVERINFO announces as the clock frequency).
TICK_FREQUENCY = 10_000_000
#: Frame params bit: the list of tracked models changed (clients re-request MODELDEF).
MODELS_CHANGED = 0x02
#: How many transmitted frames carry :data:`MODELS_CHANGED` after a model change (one could be lost).
MODELS_CHANGED_FRAMES = 3
#: Camera latency (mid-exposure → data received) and Motive's software latency (received → transmit),
#: the medians of the real Motive capture in tests/data/natnet.
CAMERA_LATENCY = 0.00457
SOFTWARE_LATENCY = 0.00081
#: A body whose last true pose is older than this (seconds) is streamed untracked.
TRUTH_TIMEOUT = 0.5
#: Attitude noise per metre of position noise: Motive's typical 0.05° for 0.3 mm.
ANGLE_NOISE_PER_M = math.radians(0.05) / 0.0003

_SUPPORTED = (Version(2, 0), Version(5, 0))  # what the codec can encode, [lo, hi)
_UNTRACKED_POSE: tuple[natnet.Vec3, natnet.Quat] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))


class NatNetServerError(ArenaError, ValueError):
    """Bad input to the NatNet server or its frame sources (version, socket, body, recording)."""


def motive_app_version(version: Version) -> Version:
    """The Motive release that streams NatNet ``version`` (what SERVERINFO announces as the app version)."""
    table = {(3, 0): Version(2, 1), (3, 1): Version(2, 2), (4, 0): Version(3, 0), (4, 1): Version(3, 1)}
    return table.get((version.major, version.minor), Version(version.major - 1, version.minor))


def _version(value: str | Version) -> Version:
    try:
        v = value if isinstance(value, Version) else Version.parse(str(value))
    except natnet.NatNetError as exc:
        raise NatNetServerError(str(exc)) from None
    if not _SUPPORTED[0] <= v < _SUPPORTED[1]:
        raise NatNetServerError(f"NatNet version {v} cannot be served (2.0 through 4.x can)")
    return v


# ------------------------------------------------------------------------------------------------------------
# Clock and schedule
# ------------------------------------------------------------------------------------------------------------


class TickClock:
    """The high-resolution clock of the tick stamps: ``perf_counter_ns`` counted at ``frequency`` Hz.

    :meth:`align` re-bases it so that it reads ``tick`` at ``perf_ns`` and runs ``rate`` times as fast as
    real time: replay uses it to keep the echo replies in the recorded clock's domain. Integer arithmetic:
    two instants a whole number of ticks apart are stamped exactly that many ticks apart.
    """

    def __init__(self, frequency: int = TICK_FREQUENCY) -> None:
        if not isinstance(frequency, int) or frequency <= 0:
            raise NatNetServerError(f"clock frequency must be a positive integer, got {frequency!r}")
        self.frequency = frequency
        self._origin_tick = 0
        self._origin_ns = 0
        self._num, self._den = frequency, 1_000_000_000

    def align(self, tick: int, perf_ns: int, rate: float = 1.0) -> None:
        """Read ``tick`` at ``perf_ns`` (a ``time.perf_counter_ns`` value) and run at ``rate`` × real time."""
        if not rate > 0 or not math.isfinite(rate):
            raise NatNetServerError(f"clock rate must be positive, got {rate}")
        ratio = Fraction(rate).limit_denominator(1_000_000)
        self._origin_tick, self._origin_ns = int(tick), int(perf_ns)
        self._num, self._den = self.frequency * ratio.numerator, 1_000_000_000 * ratio.denominator

    def at(self, perf_ns: int) -> int:
        """The tick count at ``perf_ns`` (never negative)."""
        return max(0, self._origin_tick + (perf_ns - self._origin_ns) * self._num // self._den)

    def now(self) -> int:
        """The tick count now."""
        return self.at(time.perf_counter_ns())


def sleep_until(deadline_ns: int, stop: threading.Event | None = None) -> bool:
    """Sleep until ``time.perf_counter_ns()`` reaches ``deadline_ns``; ``False`` if ``stop`` was set first.

    A schedule built as ``start + k * period`` and this function does not drift: lateness of one wake-up
    does not delay the next deadline.
    """
    while True:
        left = deadline_ns - time.perf_counter_ns()
        if stop is not None and stop.is_set():
            return False
        if left <= 0:
            return True
        if stop is None:
            time.sleep(left / 1e9)
        elif stop.wait(left / 1e9):
            return False


# ------------------------------------------------------------------------------------------------------------
# The server
# ------------------------------------------------------------------------------------------------------------


@dataclass(slots=True)
class ClientInfo:
    """A client that sent CONNECT: where it is, what it said it is, when it was last heard."""

    address: tuple[str, int]
    app_name: str = ""
    natnet_version: Version | None = None
    connected: float = field(default_factory=time.monotonic)
    last_seen: float = field(default_factory=time.monotonic)
    keeps_alive: bool = False


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
        self._version = _version(version)
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
        self._clients: dict[tuple[str, int], ClientInfo] = {}
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
        v = _version(value)
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
        with self._lock:
            return [replace(c) for c in self._clients.values()]

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
            targets: list[tuple[str, int]] = [(self.group, self.data_port)]
            sock = self._data
        else:
            with self._lock:
                targets = list(self._clients)
            sock = self._cmd
        sent = 0
        for target in targets:
            try:
                assert sock is not None
                sock.sendto(datagram, target)
                sent += 1
            except OSError as exc:
                self.counters.send_errors += 1
                if self.counters.send_errors in (1, 10, 100) or self.counters.send_errors % 1000 == 0:
                    log.warning("frame not sent to %s:%d: %s", *target, exc)
        self.counters.frames += 1
        self.counters.datagrams += sent
        self.counters.bytes += sent * len(datagram)
        return sent

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
                    try:
                        sock.sendto(reply, addr)
                    except OSError as exc:
                        self.counters.send_errors += 1
                        log.debug("reply to %s:%d failed: %s", addr[0], addr[1], exc)
            if now - last_expiry >= 0.5:
                last_expiry = now
                self._expire(now)

    def _expire(self, now: float) -> None:
        if self.client_timeout is None:
            return
        with self._lock:
            for address, client in list(self._clients.items()):
                if client.keeps_alive and now - client.last_seen > self.client_timeout:
                    del self._clients[address]
                    log.info("client %s:%d timed out", *address)

    def _handle(self, data: bytes, addr: tuple[str, int], now: float) -> bytes | None:
        message_id, payload = natnet.split_packet(data)
        with self._lock:
            client = self._clients.get(addr)
            if client is not None:
                client.last_seen = now
        if message_id in (MessageId.CONNECT, MessageId.DISCOVERY):
            self.counters.requests += 1
            if message_id == MessageId.CONNECT:
                self._subscribe(addr, natnet.decode_connect(payload), now)
            return natnet.encode_server_info(self.server_info())
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
            with self._lock:
                client = self._clients.get(addr)
                if client is None:
                    self._clients[addr] = client = ClientInfo(addr)
                    self.counters.connects += 1
                    log.info("client %s:%d subscribed again by keep-alive", *addr)
                client.keeps_alive = True
            return None
        if message_id == MessageId.DISCONNECT:
            self.counters.requests += 1
            with self._lock:
                if self._clients.pop(addr, None) is not None:
                    self.counters.disconnects += 1
                    log.info("client %s:%d disconnected", *addr)
            return None
        if message_id == MessageId.REQUEST_FRAMEOFDATA:
            self.counters.requests += 1
            return self._last_frame
        self.counters.ignored += 1
        return None

    def _subscribe(self, addr: tuple[str, int], hello: natnet.ConnectRequest, now: float) -> None:
        with self._lock:
            known = addr in self._clients
            self._clients[addr] = ClientInfo(addr, hello.app_name, hello.natnet_version, now, now)
        if not known:
            self.counters.connects += 1
            log.info("client %s:%d connected (%s)", *addr, hello.app_name or "unnamed")

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


# ------------------------------------------------------------------------------------------------------------
# Simulated scene
# ------------------------------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Body:
    name: str
    id: int
    key: str
    # (perf_counter ns, Motive position, Motive quaternion x y z w, tracked)
    history: deque[tuple[int, natnet.Vec3, natnet.Quat, bool]] = field(
        default_factory=lambda: deque(maxlen=64)
    )
    occlusions: list[tuple[int, int]] = field(default_factory=list)


@dataclass(slots=True)
class SceneCounters:
    """What a :class:`SimScene` did: frames built and dropped, bodies occluded or without fresh truth."""

    frames: int = 0
    dropped: int = 0
    occluded: int = 0  # body-frames untracked because of an occlusion
    untracked: int = 0  # body-frames untracked for lack of a fresh, valid true pose
    updates: int = 0


class SimScene:
    """Simulated rigid bodies as Motive would stream them.

    Feed true poses (arena NED/FRD) with :meth:`update`; :meth:`frame` builds the frame transmitted at
    ``transmit_ns``: the camera mid-exposure is ``camera_latency + software_latency`` earlier and each body's
    pose is its latest true pose at that instant, converted to Motive's frame with
    ``transform.inverse_pose`` and blurred by ``noise_m`` (Gaussian per axis, and a proportional attitude
    noise, :data:`ANGLE_NOISE_PER_M`). A body is streamed untracked (bit 0 clear, zero pose) before its
    first true pose, when the true pose says ``ok=False``, when it is older than ``truth_timeout``, or while
    occluded. A whole frame is dropped with probability ``dropout``. Randomness comes from ``seed``.
    """

    def __init__(
        self,
        transform: FrameTransform | None = None,
        *,
        noise_m: float = 0.0,
        dropout: float = 0.0,
        seed: int = 0,
        camera_latency: float = CAMERA_LATENCY,
        software_latency: float = SOFTWARE_LATENCY,
        truth_timeout: float = TRUTH_TIMEOUT,
    ) -> None:
        if not (noise_m >= 0 and 0 <= dropout <= 1 and camera_latency >= 0 and software_latency >= 0):
            raise NatNetServerError(
                f"noise ({noise_m} m), dropout ({dropout}) and latencies ({camera_latency}, "
                f"{software_latency} s) must be non-negative, dropout at most 1"
            )
        if not truth_timeout > 0:
            raise NatNetServerError(f"truth timeout must be positive, got {truth_timeout}")
        self.transform = transform or FrameTransform()
        self.noise_m = float(noise_m)
        self.dropout = float(dropout)
        self.camera_latency_ns = round(camera_latency * 1e9)
        self.software_latency_ns = round(software_latency * 1e9)
        self.truth_timeout_ns = round(truth_timeout * 1e9)
        self.counters = SceneCounters()
        self._rng = random.Random(seed)
        self._bodies: dict[str, _Body] = {}
        self._lock = threading.Lock()

    # -- bodies ------------------------------------------------------------------------------------
    def add_body(self, name: str, body_id: int, *, key: str | None = None) -> None:
        """Add rigid body ``name`` with ``body_id``; its true poses come under ``key`` (default: name)."""
        key = key or name
        with self._lock:
            if key in self._bodies:
                raise NatNetServerError(f"rigid body source {key!r} is already in the scene")
            taken = {b.id: b.name for b in self._bodies.values()}
            if body_id in taken:
                raise NatNetServerError(
                    f"rigid body id {body_id} of {name!r} is already used by {taken[body_id]!r}"
                )
            if not name or "\0" in name:
                raise NatNetServerError(f"invalid rigid body name {name!r}")
            self._bodies[key] = _Body(name, int(body_id), key)

    def remove_body(self, key: str) -> None:
        """Remove the body whose true poses come under ``key``."""
        with self._lock:
            if self._bodies.pop(key, None) is None:
                raise NatNetServerError(
                    f"no rigid body {key!r} in the scene (known: {', '.join(self._bodies)})"
                )

    @property
    def keys(self) -> list[str]:
        """The sources of the bodies, in streaming order."""
        return list(self._bodies)

    def model_defs(self) -> ModelDefs:
        """The rigid-body definitions of the scene (no markers; offsets zero)."""
        with self._lock:
            return ModelDefs(tuple(RigidBodyDef(b.name, b.id) for b in self._bodies.values()))

    def occlude(self, key: str, duration: float, start_ns: int | None = None) -> None:
        """Hide body ``key`` from the cameras for ``duration`` seconds from ``start_ns`` (default: now)."""
        if not duration > 0:
            raise NatNetServerError(f"occlusion of {key!r}: duration must be positive, got {duration}")
        start = time.perf_counter_ns() if start_ns is None else int(start_ns)
        with self._lock:
            body = self._bodies.get(key)
            if body is None:
                raise NatNetServerError(
                    f"cannot occlude {key!r}: not in the scene (known: {', '.join(self._bodies)})"
                )
            body.occlusions.append((start, start + round(duration * 1e9)))

    # -- input -------------------------------------------------------------------------------------
    def update(
        self,
        key: str,
        p_ned: Sequence[float],
        q_frd: Sequence[float],
        ok: bool = True,
        t_ns: int | None = None,
    ) -> bool:
        """Record a true pose of body ``key`` seen at ``t_ns`` (``perf_counter_ns``; default now).

        Returns ``False`` for a key not in the scene. Raises :class:`~arena_common.frames.FrameError` for a
        non-finite position or a non-unit quaternion.
        """
        body = self._bodies.get(key)
        if body is None:
            return False
        p, (w, x, y, z) = self.transform.inverse_pose(p_ned, q_frd)
        t = time.perf_counter_ns() if t_ns is None else int(t_ns)
        with self._lock:
            body.history.append((t, p, (x, y, z, w), bool(ok)))
        self.counters.updates += 1
        return True

    # -- output ------------------------------------------------------------------------------------
    def frame(
        self, number: int, timestamp: float, transmit_ns: int, clock: TickClock, *, params: int = 0
    ) -> Frame | None:
        """The frame transmitted at ``transmit_ns`` (``perf_counter_ns``), or ``None`` if it is dropped."""
        self.counters.frames += 1
        if self.dropout and self._rng.random() < self.dropout:
            self.counters.dropped += 1
            return None
        received_ns = transmit_ns - self.software_latency_ns
        mid_ns = received_ns - self.camera_latency_ns
        bodies = []
        with self._lock:
            for body in self._bodies.values():
                bodies.append(self._body_at(body, mid_ns))
        wall = time.time()
        secs = int(wall)
        return Frame(
            frame_number=number,
            rigid_bodies=tuple(bodies),
            timestamp=timestamp,
            cam_mid_exposure=clock.at(mid_ns),
            data_received=clock.at(received_ns),
            transmit=clock.at(transmit_ns),
            precision_secs=secs,
            precision_fraction=min(int((wall - secs) * 2**32), 2**32 - 1),
            params=params,
        )

    def _body_at(self, body: _Body, mid_ns: int) -> RigidBody:
        occluded = False
        if body.occlusions:
            body.occlusions = [o for o in body.occlusions if o[1] > mid_ns]
            occluded = any(start <= mid_ns for start, _ in body.occlusions)
        sample = None
        for entry in reversed(body.history):
            sample = entry
            if entry[0] <= mid_ns:
                break
        fresh = sample is not None and sample[3] and mid_ns - sample[0] <= self.truth_timeout_ns
        if occluded or not fresh or sample is None:
            if occluded:
                self.counters.occluded += 1
            else:
                self.counters.untracked += 1
            return RigidBody(body.id, *_UNTRACKED_POSE, 0.0, False, 0)
        _, (px, py, pz), q, _ = sample
        if self.noise_m:
            gauss, sigma = self._rng.gauss, self.noise_m
            px, py, pz = px + gauss(0.0, sigma), py + gauss(0.0, sigma), pz + gauss(0.0, sigma)
            half = 0.5 * sigma * ANGLE_NOISE_PER_M
            dq = (1.0, gauss(0.0, half), gauss(0.0, half), gauss(0.0, half))
            qx, qy, qz, qw = q
            w, x, y, z = quat_multiply((qw, qx, qy, qz), dq)
            n = math.sqrt(w * w + x * x + y * y + z * z)
            q = (x / n, y / n, z / n, w / n)
        return RigidBody(body.id, (px, py, pz), q, self.noise_m, True, 1)


# ------------------------------------------------------------------------------------------------------------
# Recordings
# ------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recording:
    """A captured Motive session: its frames with their capture times, and what its server said.

    From a pcap/pcapng capture the frames are kept byte for byte (``raw``) and decoded in full, with the
    capture's SERVERINFO and MODELDEF. From JSON lines (decoded frames) only rigid bodies and timing exist;
    the clock frequency, which such files do not hold, is estimated from the tick stamps and capture times
    unless given.
    """

    path: str
    times: tuple[float, ...]
    frames: tuple[Frame, ...]
    version: Version | None = None
    raw: tuple[bytes, ...] = ()
    server_info: ServerInfo | None = None
    models: ModelDefs | None = None
    clock_frequency: int = TICK_FREQUENCY

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        return self.times[-1] - self.times[0] if self.times else 0.0

    @property
    def frame_rate(self) -> float:
        """The median frame rate (Hz), from frame numbers and capture times."""
        if len(self.times) < 2:
            return 0.0
        steps = sorted(
            (t1 - t0) / (f1.frame_number - f0.frame_number)
            for t0, t1, f0, f1 in zip(self.times, self.times[1:], self.frames, self.frames[1:], strict=False)
            if f1.frame_number > f0.frame_number and t1 > t0
        )
        return 1.0 / steps[len(steps) // 2] if steps else 0.0

    def datagram(self, index: int, version: Version) -> bytes:
        """Frame ``index`` as a datagram for ``version``: as captured when the version is the recorded one."""
        if self.raw and version == self.version:
            return self.raw[index]
        try:
            return natnet.encode_frame(self.frames[index], version)
        except natnet.NatNetError as exc:
            raise NatNetServerError(
                f"{self.path}: frame {index} cannot be sent as NatNet {version}: {exc}"
            ) from None


def load_recording(
    path: str | Path, *, version: str | Version | None = None, clock_frequency: int | None = None
) -> Recording:
    """Load a capture to replay: pcap/pcapng (recognised by content) or JSON lines of decoded frames.

    ``version`` decodes a capture whose SERVERINFO is missing; ``clock_frequency`` overrides the recorded
    (or estimated) tick frequency. Raises :class:`NatNetServerError` (no frames, undecodable frames) or
    :class:`~arena_common.capture.CaptureError` (malformed file).
    """
    p = Path(path)
    try:
        with open(p, "rb") as stream:
            head = stream.read(4)
    except OSError as exc:
        raise NatNetServerError(f"cannot read {p}: {exc.strerror or exc}") from None
    forced = _version(version) if version is not None else None
    # pcap (either byte order, µs or ns) and pcapng magics; anything else is read as JSON lines.
    is_capture = head in (b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d")
    rec = _load_pcap(p, forced) if is_capture or head == b"\x0a\x0d\x0d\x0a" else _load_jsonl(p, forced)
    if not rec.frames:
        raise NatNetServerError(f"{p}: no NatNet frames to replay")
    if clock_frequency is not None:
        if clock_frequency <= 0:
            raise NatNetServerError(f"clock frequency must be positive, got {clock_frequency}")
        rec = replace(rec, clock_frequency=int(clock_frequency))
    return rec


def _load_pcap(path: Path, forced: Version | None) -> Recording:
    info: ServerInfo | None = None
    server: str | None = None
    modeldef: bytes | None = None
    captured: list[tuple[float, str, bytes]] = []
    with open(path, "rb") as stream:
        for dg in iter_udp(stream):
            try:
                message_id, payload = natnet.split_packet(dg.payload)
            except natnet.NatNetError:
                continue
            if message_id == MessageId.SERVERINFO and info is None:
                try:
                    info = natnet.decode_server_info(payload)
                except natnet.NatNetError:
                    continue
                server = dg.src[0]
            elif message_id == MessageId.MODELDEF:
                modeldef = payload
            elif message_id == MessageId.FRAMEOFDATA:
                captured.append((dg.timestamp, dg.src[0], dg.payload))
    version = forced or (info.natnet_version if info else None)
    if version is None:
        raise NatNetServerError(
            f"{path}: the capture has no SERVERINFO; give the NatNet version to decode it"
        )
    times, frames, raw = [], [], []
    for t, src, datagram in captured:
        if server is not None and src != server:
            continue
        try:
            frames.append(natnet.decode_frame(natnet.split_packet(datagram)[1], version, full=True))
        except natnet.NatNetError as exc:
            raise NatNetServerError(f"{path}: frame at capture time {t:.6f}: {exc}") from None
        times.append(t)
        raw.append(datagram)
    models = None
    if modeldef is not None:
        try:
            models = natnet.decode_model_defs(modeldef, version)
        except natnet.NatNetError as exc:
            log.warning("%s: MODELDEF not decoded, serving none: %s", path, exc)
    clock = info.clock_frequency if info and info.clock_frequency else _estimate_clock(times, frames)
    return Recording(str(path), tuple(times), tuple(frames), version, tuple(raw), info, models, clock)


def _load_jsonl(path: Path, forced: Version | None) -> Recording:
    times, frames = [], []
    try:
        for recorded in read_frames_jsonl(path):
            # Only rigid bodies and timing are recorded: the other sections' counts cannot be re-encoded.
            frame = replace(
                recorded.frame,
                n_marker_sets=0,
                n_unlabeled_markers=0,
                n_skeletons=0,
                n_assets=0,
                n_labeled_markers=0,
                n_force_plates=0,
                n_devices=0,
            )
            times.append(recorded.receive_time)
            frames.append(frame)
    except CaptureError:
        raise
    except UnicodeDecodeError:
        raise CaptureError(f"{path}: neither a pcap/pcapng capture nor JSON lines") from None
    return Recording(
        str(path), tuple(times), tuple(frames), forced, (), None, None, _estimate_clock(times, frames)
    )


def _estimate_clock(times: Sequence[float], frames: Sequence[Frame]) -> int:
    """Ticks per second of a recording whose SERVERINFO is unknown.

    Motive's frame ``timestamp`` and the mid-exposure ticks both follow the camera clock, so their ratio
    is the tick frequency (within 0.01 % on the real capture); without timestamps, a least-squares fit of
    the transmit ticks against capture times (within 0.1 %).
    """
    stamped = [f for f in frames if f.timestamp is not None and f.cam_mid_exposure]
    if len(stamped) >= 2:
        first, last = stamped[0], stamped[-1]
        assert first.timestamp is not None and last.timestamp is not None
        span = last.timestamp - first.timestamp
        ticks = (last.cam_mid_exposure or 0) - (first.cam_mid_exposure or 0)
        if span >= 0.05 and ticks > 0:
            return round(ticks / span)
    pairs = [(t, f.transmit) for t, f in zip(times, frames, strict=True) if f.transmit]
    if len(pairs) < 2 or pairs[-1][0] - pairs[0][0] < 0.05:
        return TICK_FREQUENCY
    mt = sum(t for t, _ in pairs) / len(pairs)
    mk = sum(k for _, k in pairs) / len(pairs)
    var = sum((t - mt) ** 2 for t, _ in pairs)
    cov = sum((t - mt) * (k - mk) for t, k in pairs)
    slope = cov / var if var > 0 else 0.0
    return round(slope) if slope >= 1 else TICK_FREQUENCY


def iter_schedule(times: Sequence[float], start_ns: int, speed: float = 1.0) -> Iterator[tuple[int, int]]:
    """``(index, deadline_ns)`` for each capture time, relative to the first, at ``speed`` × real time."""
    if not speed > 0:
        raise NatNetServerError(f"replay speed must be positive, got {speed}")
    if not times:
        return
    t0 = times[0]
    for index, t in enumerate(times):
        yield index, start_ns + round((t - t0) / speed * 1e9)
