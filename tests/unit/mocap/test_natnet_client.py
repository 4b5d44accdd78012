"""The NatNet client over real UDP sockets on loopback, against a small NatNet server run by the test.

:class:`FakeMotive` speaks the server side of NatNet with the codec's ``encode_*`` functions: it answers
CONNECT, REQUEST_MODELDEF and ECHO on its command socket and sends frames when the test says so, to the
multicast group or to the client's command socket (unicast). Tests also use it to inject what a real
network does to a client: garbage, truncated datagrams, frames before SERVERINFO, a restarted server, a
new NatNet version, silence.
"""

from __future__ import annotations

import itertools
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from arena_common.mocap import natnet
from arena_common.mocap.capture import read_frames_jsonl, read_udp
from arena_common.mocap.client import DEFAULT_GROUP, EchoClock, MocapError, NatNetClient, TimedFrame
from arena_common.mocap.natnet import (
    Frame,
    MessageId,
    ModelDefs,
    RigidBody,
    RigidBodyDef,
    ServerInfo,
    Version,
)
from tests.helpers import TESTS, free_port, wait_for

CAPTURE = TESTS / "data" / "natnet" / "motive-2.1-natnet-3.0"
LOOP = "127.0.0.1"


@dataclass
class Body:
    """A rigid body the fake server streams."""

    id: int
    name: str
    pos: tuple[float, float, float] = (0.0, 1.0, 0.0)
    quat: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    tracked: bool = True


@dataclass
class Received:
    when: float
    message_id: int
    addr: tuple[str, int]
    payload: bytes = b""


class FakeMotive:
    """A NatNet server on loopback: a command socket on a free port, frames sent when asked.

    The tick clock counts ``clock_frequency`` ticks per second from an arbitrary origin of the wall clock,
    so a frame's mid-exposure maps back to a known local time: ``send_frame`` stamps the transmit tick
    "now" and the mid-exposure ``latency_ns`` before it.
    """

    def __init__(
        self,
        version: str = "3.0",
        *,
        multicast: bool = True,
        bodies: list[Body] | None = None,
        clock_frequency: int = 10_000_000,
        latency_ns: int = 5_000_000,
        answer_connect: bool = True,
        answer_echo: bool = True,
        app_name: str = "Motive",
        command_port: int = 0,
        data_port: int | None = None,
    ) -> None:
        self.version = Version.parse(version)
        self.multicast = multicast
        self.bodies = bodies if bodies is not None else [Body(1, "d1"), Body(2, "d2")]
        self.clock_frequency = clock_frequency
        self.latency_ns = latency_ns
        self.answer_connect = answer_connect
        self.answer_echo = answer_echo
        self.app_name = app_name
        self.tick_origin_ns = time.time_ns() - 1234 * 1_000_000_000
        self.group = DEFAULT_GROUP
        self.data_port = data_port or free_port(socket.SOCK_DGRAM)
        self.received: list[Received] = []
        self.clients: list[tuple[str, int]] = []
        self.frame_number = 1000
        self.params = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.cmd.bind((LOOP, command_port))
        self.cmd.settimeout(0.05)
        self.command_port = self.cmd.getsockname()[1]
        self.out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(LOOP))
        self.out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        self.out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        self._thread = threading.Thread(target=self._serve, name="fake-motive", daemon=True)
        self._thread.start()

    # -- server side ------------------------------------------------------------------------------
    def ticks(self, wall_ns: int | None = None) -> int:
        wall = time.time_ns() if wall_ns is None else wall_ns
        return (wall - self.tick_origin_ns) * self.clock_frequency // 1_000_000_000

    def info(self) -> ServerInfo:
        if self.version.major < 3:
            return ServerInfo(self.app_name, Version(1, 9), self.version)
        return ServerInfo(
            self.app_name,
            Version(3, 1),
            self.version,
            self.clock_frequency,
            self.data_port,
            self.multicast,
            self.group,
        )

    def model_defs(self) -> ModelDefs:
        return ModelDefs(tuple(RigidBodyDef(b.name, b.id) for b in self.bodies))

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self.cmd.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                message_id, payload = natnet.split_packet(data)
            except natnet.NatNetError:
                continue
            with self._lock:
                self.received.append(Received(time.monotonic(), message_id, addr, payload))
            if message_id == MessageId.CONNECT and self.answer_connect:
                with self._lock:
                    if addr not in self.clients:
                        self.clients.append(addr)
                self._reply(natnet.encode_server_info(self.info()), addr)
            elif message_id == MessageId.REQUEST_MODELDEF and self.answer_connect:
                self._reply(natnet.encode_model_defs(self.model_defs(), self.version), addr)
            elif message_id == MessageId.ECHOREQUEST and self.answer_echo:
                stamp = natnet.decode_echo_request(payload)
                self._reply(natnet.encode_echo_response(stamp, self.ticks()), addr)
            elif message_id == MessageId.DISCONNECT:
                with self._lock:
                    if addr in self.clients:
                        self.clients.remove(addr)

    def _reply(self, datagram: bytes, addr: tuple[str, int]) -> None:
        try:
            self.cmd.sendto(datagram, addr)
        except OSError:
            pass

    def count(self, message_id: int) -> int:
        with self._lock:
            return sum(1 for r in self.received if r.message_id == message_id)

    def times(self, message_id: int) -> list[float]:
        with self._lock:
            return [r.when for r in self.received if r.message_id == message_id]

    # -- streaming --------------------------------------------------------------------------------
    def make_frame(self, frame_number: int | None = None, params: int | None = None) -> Frame:
        if frame_number is None:
            self.frame_number += 1
            frame_number = self.frame_number
        now = self.ticks()
        lat_ticks = self.latency_ns * self.clock_frequency // 1_000_000_000
        return Frame(
            frame_number=frame_number,
            rigid_bodies=tuple(
                RigidBody(b.id, b.pos, b.quat, 0.0002, b.tracked, 1 if b.tracked else 0) for b in self.bodies
            ),
            timestamp=frame_number / 180.0,
            cam_mid_exposure=now - lat_ticks,
            data_received=now - lat_ticks // 2,
            transmit=now,
            params=self.params if params is None else params,
        )

    def send_frame(self, frame_number: int | None = None, params: int | None = None) -> Frame:
        """Encode and send one frame (to the group, or to every connected client in unicast)."""
        frame = self.make_frame(frame_number, params)
        self.send_raw(natnet.encode_frame(frame, self.version))
        return frame

    def send_raw(self, datagram: bytes) -> None:
        if self.multicast:
            self.out.sendto(datagram, (self.group, self.data_port))
        else:
            with self._lock:
                clients = list(self.clients)
            for addr in clients:
                self.cmd.sendto(datagram, addr)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.cmd.close()
        self.out.close()


@pytest.fixture
def fake_motive() -> Iterator[Callable[..., FakeMotive]]:
    servers: list[FakeMotive] = []

    def make(*args: Any, **kwargs: Any) -> FakeMotive:
        server = FakeMotive(*args, **kwargs)
        servers.append(server)
        return server

    yield make
    for server in servers:
        server.close()


@dataclass
class Rejects:
    """Collects what a client reports through ``on_reject``."""

    items: list[tuple[str, str]] = field(default_factory=list)

    def __call__(self, reason: str, detail: str) -> None:
        self.items.append((reason, detail))

    def reasons(self) -> list[str]:
        return [r for r, _ in self.items]


def client_for(server: FakeMotive, **kwargs: Any) -> NatNetClient:
    options: dict[str, Any] = {
        "command_port": server.command_port,
        "interface": LOOP,
        "multicast": server.multicast,
        "loss_timeout": 1.0,
    }
    if server.multicast:
        options.update(group=server.group, data_port=server.data_port)
    options.update(kwargs)
    return NatNetClient(LOOP, **options)


def poll_until(
    client: NatNetClient, predicate: Callable[[], bool], timeout: float = 5.0, what: str = "condition"
) -> list[TimedFrame]:
    """Poll the client (keeping every frame) until ``predicate`` holds; fail after ``timeout``."""
    frames: list[TimedFrame] = []
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        frame = client.poll(0.02)
        if frame is not None:
            frames.append(frame)
    return frames


def stream_until(
    server: FakeMotive, client: NatNetClient, n: int, timeout: float = 5.0, **frame_kw: Any
) -> list[TimedFrame]:
    """Send frames one by one (each after the previous arrived or 50 ms) until ``n`` were received."""
    frames: list[TimedFrame] = []
    deadline = time.monotonic() + timeout
    while len(frames) < n:
        if time.monotonic() > deadline:
            raise AssertionError(f"{len(frames)} of {n} frames after {timeout} s; rejected {client.rejected}")
        server.send_frame(**frame_kw)
        end = time.monotonic() + 0.05
        while time.monotonic() < end:
            frame = client.poll(0.01)
            if frame is not None:
                frames.append(frame)
                break
    return frames


def connected(client: NatNetClient) -> Callable[[], bool]:
    return lambda: client.version is not None and client.models > 0


def assert_echo_stamped(frame: TimedFrame, client: NatNetClient, rtt_before_ns: int) -> None:
    """``frame.t`` is its exposure, ``frame.lat`` before the server sent it, within the echo clock's own error.

    The offset the frame was mapped with is off by at most half the round trip it came from; that round trip
    is the fastest of the window, so no slower than the one before the frames streamed (nor than the one
    after). A busy machine makes round trips slow, so the bound is the clock's, not a fixed margin.
    """
    assert frame.tsrc == "echo" and client.clock is not None and client.clock.rtt_ns is not None
    error_ns = max(rtt_before_ns, client.clock.rtt_ns) // 2 + 1_000  # + tick rounding
    sent_by_server = frame.t + frame.lat  # on the local clock, as the echo clock maps it
    assert sent_by_server <= frame.arrival + error_ns, (frame.t, frame.arrival, error_ns)
    assert sent_by_server > frame.arrival - error_ns - 1_000_000_000  # not mapped from a stale origin


# ------------------------------------------------------------------------------------------------------------
# Echo clock
# ------------------------------------------------------------------------------------------------------------


def test_echo_clock_keeps_the_fastest_round_trip() -> None:
    clock = EchoClock(1_000_000, window=4)  # 1 tick = 1 µs
    assert not clock.ready
    offset = 5_000_000_000  # local = server + 5 s
    # Round trips of 10, 2 and 6 ms: the 2 ms one wins, its error is at most 1 ms.
    for rtt_ms, server_skew_ms in ((10, 4.0), (2, 0.5), (6, -2.0)):
        sent = 100_000_000_000 + rtt_ms * 1000
        server_ns = sent + rtt_ms * 500_000 - offset + int(server_skew_ms * 1e6)
        assert clock.add(sent, server_ns // 1000, sent + rtt_ms * 1_000_000)
    assert clock.rtt_ns == 2_000_000
    assert clock.offset_ns == offset - 500_000
    assert clock.to_local(7_000_000) == 7_000_000_000 + offset - 500_000
    assert not clock.add(10, 0, 5)  # negative round trip
    assert not clock.add(0, 0, 10**9)  # too slow to be useful
    assert clock.samples == 3


def test_echo_clock_window_forgets_old_samples_and_restarts_on_jumps() -> None:
    clock = EchoClock(1_000_000_000, window=2)
    clock.add(0, 1_000, 1_000)  # rtt 1 µs, offset -500
    clock.add(10_000, 11_000, 14_000)
    clock.add(20_000, 21_000, 24_000)  # the fast sample left the window
    assert clock.rtt_ns == 4_000
    before = clock.resets
    clock.add(30_000, 30_000 + 10**9, 32_000)  # the server clock jumped a second: start over
    assert clock.resets == before + 1 and clock.samples == 1
    assert clock.offset_ns == 31_000 - (30_000 + 10**9)
    with pytest.raises(ValueError, match="frequency"):
        EchoClock(0)


# ------------------------------------------------------------------------------------------------------------
# Handshake, transport and timing
# ------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("version", "multicast"),
    [("3.0", True), ("3.1", False), ("4.0", True), ("4.1", False), ("4.1", True), ("2.9", True)],
)
def test_handshake_names_and_frames(
    fake_motive: Callable[..., FakeMotive], version: str, multicast: bool
) -> None:
    bodies = [Body(1, "d1", (0.5, 1.2, -0.3), (0.0, 0.7071068, 0.0, 0.7071068)), Body(7, "other")]
    server = fake_motive(version, multicast=multicast, bodies=bodies, latency_ns=4_000_000)
    rejects = Rejects()
    with client_for(server, on_reject=rejects) as client:
        poll_until(client, connected(client), what="SERVERINFO and MODELDEF")
        assert client.version == Version.parse(version)
        assert client.info is not None and client.info.app_name == "Motive"
        assert client.names == {1: "d1", 7: "other"}
        if version >= "3":
            poll_until(client, lambda: client.clock is not None and client.clock.samples >= 3, what="echo")
        rtt_before = client.clock.rtt_ns if client.clock is not None else None
        sent_at = time.time_ns()
        frames = stream_until(server, client, 5)
        last = frames[-1]
        assert [b.id for b in last.bodies] == [1, 7]
        body = last.bodies[0]
        assert body.pos == pytest.approx((0.5, 1.2, -0.3))
        assert body.quat_xyzw == pytest.approx((0.0, 0.7071068, 0.0, 0.7071068))
        assert body.tracking_valid is (version >= "2.6")
        assert last.names[1] == "d1" and last.models == 1
        assert last.arrival >= sent_at
        if version >= "3":
            assert last.tsrc == "echo"
            assert last.lat == pytest.approx(4_000_000, abs=200)  # tick rounding
            # The server stamped transmit "now" and the exposure 4 ms before: t lands 4 ms before sending.
            assert rtt_before is not None
            assert_echo_stamped(last, client, rtt_before)
        else:
            assert last.tsrc == "arrival" and last.t == last.arrival and last.lat == -1
        if not multicast and Version.parse(version) >= Version(2, 10):  # Motive drops silent unicast clients
            poll_until(client, lambda: server.count(MessageId.KEEPALIVE) >= 1, what="a KEEPALIVE")
        else:
            assert server.count(MessageId.KEEPALIVE) == 0
    assert rejects.items == []
    wait_for(lambda: server.count(MessageId.DISCONNECT) == 1, what="DISCONNECT at close")


def test_timing_falls_back_to_latency_without_echo(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.0", answer_echo=False, latency_ns=7_000_000)
    with client_for(server) as client:
        poll_until(client, connected(client))
        frame = stream_until(server, client, 1)[0]
        assert frame.tsrc == "latency"
        assert frame.lat == pytest.approx(7_000_000, abs=200)
        assert frame.t == frame.arrival - frame.lat


def test_frames_before_serverinfo_are_counted_and_dropped(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("4.1", answer_connect=False)
    rejects = Rejects()
    with client_for(server, on_reject=rejects) as client:
        for _ in range(3):
            server.send_frame()
        poll_until(client, lambda: client.rejected.get("before_serverinfo", 0) == 3, what="3 early frames")
        assert client.frames == 0 and client.version is None
        server.answer_connect = True
        poll_until(client, connected(client), timeout=5.0, what="the handshake once the server answers")
        assert len(stream_until(server, client, 2)) == 2
    assert rejects.reasons().count("before_serverinfo") == 3


def test_garbage_truncated_oversized_and_unknown_datagrams(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.1")
    rejects = Rejects()
    with client_for(server, on_reject=rejects) as client:
        poll_until(client, connected(client))
        good = natnet.encode_frame(server.make_frame(), server.version)
        bad = [
            b"\x07",  # shorter than a header
            good[:-10],  # truncated: the length field says more
            good + b"\0" * 8,  # oversized: more than the length field says
            natnet.encode_packet(777, b"hello"),  # unknown message
            natnet.encode_packet(MessageId.FRAMEOFDATA, b"\xff" * 40),  # undecodable frame
            natnet.encode_packet(MessageId.FRAMEOFDATA, good[4:-1] + b"\0\0\0\0\0"),
        ]
        for datagram in bad:
            server.send_raw(datagram)
        expected = ["garbage", "truncated", "oversized", "unknown_message", "bad_frame", "bad_frame"]
        poll_until(client, lambda: len(rejects.items) >= len(expected), what="every bad datagram counted")
        assert sorted(rejects.reasons()) == sorted(expected)
        assert "FRAMEOFDATA (NatNet 3.1)" in dict(rejects.items)["bad_frame"]
        assert len(stream_until(server, client, 3)) == 3  # still streaming


def test_duplicates_and_reordering_are_dropped(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.0")
    rejects = Rejects()
    with client_for(server, on_reject=rejects) as client:
        poll_until(client, connected(client))
        stream_until(server, client, 1, frame_number=500)
        server.send_frame(500)
        server.send_frame(498)
        server.send_frame(501)
        frames = poll_until(client, lambda: client.last_frame_number == 501, what="frame 501")
        assert [f.frame_number for f in frames] == [501]
        assert rejects.reasons() == ["duplicate", "out_of_order"]


def test_models_changed_bit_requests_model_definitions_again(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("4.1")
    with client_for(server) as client:
        poll_until(client, connected(client))
        assert server.count(MessageId.REQUEST_MODELDEF) == 1
        server.bodies.append(Body(9, "late"))
        server.params = 0x02
        poll_until(client, lambda: client.models >= 2, what="new model definitions")
        server.params = 0
        assert client.names[9] == "late"
        frame = stream_until(server, client, 1)[0]
        assert frame.names[9] == "late" and frame.models == client.models


def test_server_restart_frame_numbers_going_back(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.0")
    rejects = Rejects()
    with client_for(server, on_reject=rejects) as client:
        poll_until(client, connected(client))
        poll_until(client, lambda: client.clock is not None and client.clock.samples >= 3, what="echo")
        stream_until(server, client, 3)
        connects = server.count(MessageId.CONNECT)
        # Motive restarts: frame numbers start over, its tick clock has a new origin.
        server.tick_origin_ns = time.time_ns() - 5 * 1_000_000_000
        server.frame_number = 10
        server.send_frame()
        poll_until(client, lambda: "server_restart" in rejects.reasons(), what="the restart noticed")
        poll_until(client, lambda: server.count(MessageId.CONNECT) > connects, what="a new CONNECT")
        poll_until(client, lambda: client.clock is not None and client.clock.ready, what="a new echo clock")
        assert client.clock is not None and client.clock.rtt_ns is not None
        rtt_before = client.clock.rtt_ns
        frames = stream_until(server, client, 3)
        assert frames[0].frame_number < 20
        assert_echo_stamped(frames[-1], client, rtt_before)


@pytest.mark.parametrize("version", ["2.9", "3.0", "3.1", "4.0", "4.1"])
def test_unicast_frames_on_the_command_socket_only(
    fake_motive: Callable[..., FakeMotive], version: str
) -> None:
    """Unicast as Motive does it (docs/architecture.md): frames come to the socket that sent CONNECT, so that
    is the only socket the client opens, even when given a data port (which another program may then bind
    alone), and it keeps alive from NatNet 2.10 on, whose servers drop silent unicast clients declaring 2.10
    or later."""
    server = fake_motive(version, multicast=False)
    rejects = Rejects()
    with client_for(server, on_reject=rejects, data_port=server.data_port) as client:
        poll_until(client, connected(client))
        assert client.data_address is None
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as alone:
            alone.bind((LOOP, server.data_port))  # no SO_REUSEADDR: fails if the client holds the port
        assert len(stream_until(server, client, 3)) == 3
        if Version.parse(version) >= Version(2, 10):
            poll_until(client, lambda: server.count(MessageId.KEEPALIVE) >= 1, what="a KEEPALIVE")
        else:
            assert server.count(MessageId.KEEPALIVE) == 0
    assert rejects.items == []


def test_natnet_version_change(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.1")
    rejects = Rejects()
    with client_for(server, on_reject=rejects) as client:
        poll_until(client, connected(client))
        stream_until(server, client, 2)
        server.version = Version(4, 1)  # restarted as a newer Motive, frame numbers going on
        for _ in range(12):
            server.send_frame()
        poll_until(client, lambda: client.version == Version(4, 1), what="the new SERVERINFO")
        assert "resync" in rejects.reasons() and "version_change" in rejects.reasons()
        assert 1 <= rejects.reasons().count("bad_frame") <= 12
        poll_until(client, lambda: client.models >= 2, what="model definitions in the new version")
        frames = stream_until(server, client, 3)
        assert frames[-1].bodies[0].tracking_valid and frames[-1].names[1] == "d1"


def test_lost_server_reconnects_with_back_off(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("4.1", multicast=False)
    rejects = Rejects()
    with client_for(server, on_reject=rejects, loss_timeout=0.3, retry=0.1, max_backoff=0.4) as client:
        poll_until(client, connected(client))
        stream_until(server, client, 2)
        server.answer_connect = False  # the server goes quiet
        lost_at = time.monotonic()
        poll_until(client, lambda: "no_data" in rejects.reasons(), what="the loss noticed")
        assert 0.3 <= time.monotonic() - lost_at < 3.0  # after loss_timeout, not long after (a busy machine)
        poll_until(
            client,
            lambda: len([t for t in server.times(MessageId.CONNECT) if t > lost_at]) >= 4,
            what="CONNECT retries",
        )
        retries = [t for t in server.times(MessageId.CONNECT) if t > lost_at]
        gaps = [b - a for a, b in itertools.pairwise(retries)]
        # The first retry after ``retry``, then doubling up to ``max_backoff``: each wait at least its back-off
        # (0.1, 0.2, 0.4, 0.4 s; a busy machine can only add to them), none far beyond the maximum.
        assert all(g >= want - 0.02 for g, want in zip(gaps, (0.1, 0.2, 0.4, 0.4), strict=False)), gaps
        assert max(gaps) < 0.4 + 1.0, gaps
        server.answer_connect = True
        poll_until(client, lambda: client.version is not None, what="the new session")
        assert len(stream_until(server, client, 2)) == 2


def test_nothing_answers_never_blocks(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.0", answer_connect=False)
    with client_for(server, retry=0.05, max_backoff=0.2) as client:
        start = time.monotonic()
        for _ in range(5):
            assert client.poll(0.1) is None
        assert time.monotonic() - start < 1.5
        assert client.version is None
        assert server.count(MessageId.CONNECT) >= 3


def test_configuration_errors_are_clear() -> None:
    with pytest.raises(MocapError, match="not an IPv4 address"):
        NatNetClient("motive.local")
    with pytest.raises(MocapError, match="not a multicast address"):
        NatNetClient(LOOP, group="10.0.0.1")
    with pytest.raises(MocapError, match="command port"):
        NatNetClient(LOOP, command_port=0)
    with pytest.raises(MocapError, match="is it an address of this computer"):
        NatNetClient(LOOP, interface="192.0.2.77").open()


def test_a_stream_configured_differently_is_reported(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.1")
    rejects = Rejects()
    other_port = free_port(socket.SOCK_DGRAM)
    with client_for(server, on_reject=rejects, data_port=other_port) as client:
        poll_until(client, connected(client))
    assert rejects.items == [
        (
            "config_mismatch",
            f"server streams to {DEFAULT_GROUP}:{server.data_port}, listening on "
            f"{DEFAULT_GROUP}:{other_port} (check mocap.group and mocap.data_port)",
        )
    ]
    rejects = Rejects()
    with client_for(server, on_reject=rejects, multicast=False) as client:
        poll_until(client, connected(client))
    assert rejects.reasons() == ["config_mismatch"]
    assert "server streams multicast, client expects unicast" in rejects.items[0][1]


def test_foreign_senders_on_the_command_socket_are_ignored(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.0")
    rejects = Rejects()
    with client_for(server, on_reject=rejects, multicast=False) as client:
        poll_until(client, connected(client))
        address = client.command_address
        assert address is not None
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as intruder:
            intruder.bind(("127.0.0.2", 0))
            intruder.sendto(natnet.encode_frame(server.make_frame(), server.version), address)
        poll_until(client, lambda: "foreign_sender" in rejects.reasons(), what="the intruder rejected")
        assert client.frames == 0


def test_several_clients_share_the_multicast_stream(fake_motive: Callable[..., FakeMotive]) -> None:
    server = fake_motive("3.1")
    with client_for(server) as first, client_for(server) as second:
        poll_until(first, connected(first))
        poll_until(second, connected(second))
        frame = server.send_frame()
        for client in (first, second):
            got = poll_until(client, lambda: client.frames >= 1)  # noqa: B023
            assert got[-1].frame_number == frame.frame_number


def test_replays_a_real_motive_session(fake_motive: Callable[..., FakeMotive]) -> None:
    """The captured Motive 2.1 session, replayed datagram by datagram, decodes as recorded."""
    expected = {
        r.frame.frame_number: r.frame for r in read_frames_jsonl(CAPTURE / "traffic_frames_decoded.jsonl")
    }
    server = fake_motive("3.0", answer_connect=False, answer_echo=False)
    replies: dict[int, bytes] = {MessageId.SERVERINFO: b"", MessageId.MODELDEF: b""}
    frames: list[bytes] = []
    for udp in read_udp(CAPTURE / "traffic.pcapng"):
        message_id = int.from_bytes(udp.payload[:2], "little")
        if message_id in replies:
            replies[message_id] = udp.payload
        elif message_id == MessageId.FRAMEOFDATA:
            frames.append(udp.payload)
    client = client_for(server, data_port=server.data_port)
    client.open()
    try:
        for message_id in (MessageId.SERVERINFO, MessageId.MODELDEF):
            server.cmd.sendto(replies[message_id], client.command_address)  # type: ignore[arg-type]
        poll_until(client, connected(client), what="the captured SERVERINFO and MODELDEF")
        assert client.info is not None and client.info.clock_frequency == 3_312_787
        assert client.names == {2: "RaceQuad"}
        got: list[TimedFrame] = []
        for datagram in frames[:100]:
            server.send_raw(datagram)
            want_frames = client.frames + 1
            got += poll_until(client, lambda: client.frames >= want_frames, what="a replayed frame")  # noqa: B023
        for frame in got:
            want = expected[frame.frame_number]
            assert frame.bodies[0].pos == pytest.approx(want.rigid_bodies[0].pos)
            assert frame.bodies[0].quat_xyzw == pytest.approx(want.rigid_bodies[0].quat_xyzw)
            assert frame.mts == pytest.approx(want.timestamp)
            assert want.transmit is not None and want.cam_mid_exposure is not None
            assert frame.lat == (want.transmit - want.cam_mid_exposure) * 10**9 // 3_312_787
            assert frame.tsrc == "latency"  # the capture's clock is not this server's: no echo mapping
        lats = sorted(f.lat for f in got)
        assert lats[len(lats) // 2] / 1e6 == pytest.approx(5.40, abs=0.3)
        assert [f.frame_number for f in got] == list(range(162734, 162834))
    finally:
        client.close()
    assert math.isfinite(got[-1].mts)
