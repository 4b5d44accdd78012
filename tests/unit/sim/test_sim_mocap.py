"""The Motive emulator on real loopback sockets: NatNet clients (libmotioncapture and our own codec) receive
the simulated bodies by multicast and unicast, the command socket answers like Motive, recordings replay."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import math
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from arena_common.bus.session import Bus
from arena_common.core import keys, wire
from arena_common.core.config import ArenaConfig
from arena_common.core.errors import ConfigError
from arena_common.mocap import natnet
from arena_common.mocap.capture import read_frames_jsonl, read_udp
from arena_common.mocap.natnet import Frame, MessageId, ModelDefs, RigidBodyDef, Version
from arena_common.sim.natnet_scene import rigid_bodies
from arena_common.sim.natnet_server import (
    MODELS_CHANGED,
    TICK_FREQUENCY,
    NatNetServer,
    NatNetServerError,
    SimScene,
    TickClock,
    load_recording,
)
from services import sim_mocap
from tests.helpers import REPO, Proc, free_port, service_argv, wait_for

DATA = REPO / "tests" / "data" / "natnet" / "motive-2.1-natnet-3.0"
S = math.sqrt(0.5)
# Truth in the arena frame: 1 m north, 2 m east, 0.5 m up, heading east (yaw 90°).
TRUTH_P = (1.0, 2.0, -0.5)
TRUTH_Q = (S, 0.0, 0.0, S)
# The same pose in Motive's Y-up frame (N = x, E = z, D = -y): p = (1, 0.5, 2); the body turns about
# Motive's -y (down), so q = (x, y, z, w) = (0, -√½, 0, √½).
Y_UP_P = (1.0, 0.5, 2.0)
Y_UP_Q = (0.0, -S, 0.0, S)


# ------------------------------------------------------------------------------------------------------------
# Helpers: a NatNet client written from the protocol description, the service in a thread, truth publishers
# ------------------------------------------------------------------------------------------------------------


class Client:
    """A NatNet 4 SDK-like command-socket client on 127.0.0.1: its CONNECT declares NatNet 4.1; unicast frames
    arrive on this same socket, as from Motive for every client (tests/unit/mocap/test_natnet_clients.py).
    """

    def __init__(self, command_port: int) -> None:
        self.server = ("127.0.0.1", command_port)
        self.sock = stamped_socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.frames: list[tuple[float, bytes]] = []  # frames that arrived while waiting for replies

    def close(self) -> None:
        self.sock.close()

    def ask(self, datagram: bytes, expect: int, tries: int = 25) -> bytes:
        """Send ``datagram`` (again every 0.2 s) until a message ``expect`` comes back; its payload."""
        for _ in range(tries):
            self.sock.sendto(datagram, self.server)
            deadline = time.monotonic() + 0.2
            while time.monotonic() < deadline:
                try:
                    stamp, data = recv_stamped(self.sock)
                except TimeoutError:
                    break
                message_id, payload = natnet.split_packet(data)
                if message_id == expect:
                    return payload
                if message_id == MessageId.FRAMEOFDATA:
                    self.frames.append((stamp, data))
        raise AssertionError(f"no message {expect} from {self.server} after {tries} tries")

    def connect(self) -> natnet.ServerInfo:
        hello = natnet.encode_connect(natnet_version=Version(4, 1))
        return natnet.decode_server_info(self.ask(hello, MessageId.SERVERINFO))

    def recv_frames(self, count: int, timeout: float = 5.0) -> list[tuple[float, bytes]]:
        """``count`` frames received on the command socket (unicast)."""
        out = list(self.frames)
        self.frames.clear()
        deadline = time.monotonic() + timeout
        while len(out) < count:
            assert time.monotonic() < deadline, f"only {len(out)} of {count} unicast frames in {timeout} s"
            with contextlib.suppress(TimeoutError):
                stamp, data = recv_stamped(self.sock)
                if natnet.split_packet(data)[0] == MessageId.FRAMEOFDATA:
                    out.append((stamp, data))
        return out


# Linux: the kernel stamps each datagram on arrival (CLOCK_REALTIME), so arrival times do not depend on when
# the test thread gets to read them.
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
TIMESPEC = struct.Struct("@qq")


def stamped_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    return sock


def recv_stamped(sock: socket.socket) -> tuple[float, bytes]:
    """One datagram and its kernel arrival time (seconds since the epoch)."""
    data, ancillary, _, _ = sock.recvmsg(65535, 64)
    for level, kind, raw in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = TIMESPEC.unpack(raw[: TIMESPEC.size])
            return sec + nsec * 1e-9, data
    return time.time(), data


def multicast_receiver(port: int, group: str = natnet.MULTICAST_GROUP) -> socket.socket:
    """A data socket joined to ``group`` on the loopback interface (bound to the group port on '')."""
    sock = stamped_socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("", port))
    sock.setsockopt(
        socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(group) + socket.inet_aton("127.0.0.1")
    )
    sock.settimeout(0.2)
    return sock


def receive(sock: socket.socket, count: int, timeout: float = 5.0) -> list[tuple[float, bytes]]:
    """``count`` FRAMEOFDATA datagrams with their kernel arrival times."""
    out: list[tuple[float, bytes]] = []
    deadline = time.monotonic() + timeout
    while len(out) < count:
        assert time.monotonic() < deadline, f"only {len(out)} of {count} frames in {timeout} s"
        with contextlib.suppress(TimeoutError):
            stamp, data = recv_stamped(sock)
            if natnet.split_packet(data)[0] == MessageId.FRAMEOFDATA:
                out.append((stamp, data))
    return out


def decode(datagram: bytes, version: Version) -> Frame:
    message_id, payload = natnet.split_packet(datagram)
    assert message_id == MessageId.FRAMEOFDATA
    return natnet.decode_frame(payload, version)


def body(frame: Frame, body_id: int) -> natnet.RigidBody:
    return next(b for b in frame.rigid_bodies if b.id == body_id)


def close(a: tuple[float, ...], b: tuple[float, ...], tol: float = 1e-6) -> bool:
    return len(a) == len(b) and all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


@contextlib.contextmanager
def service(cfg: ArenaConfig, **kwargs: Any) -> Iterator[threading.Event]:
    """``sim_mocap.main`` in a thread; stopped (and its error re-raised) on exit."""
    stop = threading.Event()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            sim_mocap.main(cfg, host="test", stop=stop, **kwargs)
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=run, name="sim_mocap", daemon=True)
    thread.start()
    try:
        yield stop
    finally:
        stop.set()
        thread.join(timeout=10.0)
        assert not thread.is_alive(), "sim_mocap did not stop"
    if errors:
        raise errors[0]


@contextlib.contextmanager
def publish_truth(bus: Bus, poses: dict[str, wire.Pose], rate: float = 250.0) -> Iterator[None]:
    """Publish each vehicle's true pose at ``rate`` until the block ends."""
    pubs = {name: bus.stream_publisher(keys.truth(name), wire.Pose) for name in poses}
    stop = threading.Event()

    def run() -> None:
        while not stop.wait(1.0 / rate):
            for name, pose in poses.items():
                pubs[name].put(pose.replace(t=time.time_ns()))

    thread = threading.Thread(target=run, name="truth", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=5.0)


def truth(
    p: tuple[float, float, float] = TRUTH_P, q: tuple[float, ...] = TRUTH_Q, ok: bool = True
) -> wire.Pose:
    return wire.Pose(t=0, p=p, q=q, ok=ok)  # type: ignore[arg-type]


def counts(sub: Any) -> dict[str, int]:
    """The counters of the latest stats sample (empty when none arrived within 0.5 s)."""
    item = sub.get(0.5)
    return dict(item.payload.counts) if item is not None and item.payload is not None else {}


def with_mocap(cfg: ArenaConfig, **changes: Any) -> ArenaConfig:
    return cfg.replace(mocap=cfg.mocap.replace(**changes))


# ------------------------------------------------------------------------------------------------------------
# An independent client: libmotioncapture (PyPI motioncapture), in a subprocess because it blocks forever
# when nothing answers
# ------------------------------------------------------------------------------------------------------------

MOTIONCAPTURE = r"""
import json, sys, motioncapture
mc = motioncapture.connect("optitrack", {"hostname": "127.0.0.1", "port_command": sys.argv[1],
                                         "interface_ip": "127.0.0.1"})
seen = {}
for _ in range(2000):
    mc.waitForNextFrame()
    for name, b in mc.rigidBodies.items():
        r = b.rotation
        seen[name] = [[float(v) for v in b.position], [r.w, r.x, r.y, r.z]]
    if len(seen) >= int(sys.argv[2]):
        break
print("RESULT " + json.dumps(seen))
"""


@pytest.mark.parametrize("version", ["3.0", "3.1", "4.0", "4.1"])
def test_motioncapture_receives_bodies_by_multicast(
    version: str, arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = arena_config(n_vehicles=2, noise_m=0.0)
    d2 = truth(p=(-1.0, 0.5, -1.25), q=(1.0, 0.0, 0.0, 0.0))
    with service(cfg, natnet_version=version), publish_truth(bus_factory(), {"d1": truth(), "d2": d2}):
        client = Client(cfg.mocap.command_port)
        try:
            info = client.connect()  # the emulator answers before libmotioncapture (which would block) asks
        finally:
            client.close()
        assert info.natnet_version == Version.parse(version) and info.is_multicast
        run = subprocess.run(
            [sys.executable, "-c", MOTIONCAPTURE, str(cfg.mocap.command_port), "2"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    line = next((x for x in run.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert run.returncode == 0 and line, run.stdout[-2000:] + run.stderr[-2000:]
    seen = json.loads(line[7:])
    assert set(seen) == {"d1", "d2"}
    (p1, q1), (p2, q2) = seen["d1"], seen["d2"]
    assert close(tuple(p1), Y_UP_P) and close(tuple(q1), (S, 0.0, -S, 0.0))  # w, x, y, z
    assert close(tuple(p2), (-1.0, 1.25, 0.5)) and close(tuple(q2), (1.0, 0.0, 0.0, 0.0))


# ------------------------------------------------------------------------------------------------------------
# Our own codec on plain sockets
# ------------------------------------------------------------------------------------------------------------


def test_multicast_stream_rate_ticks_echo_and_y_up_pose(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = arena_config(n_vehicles=2, noise_m=0.0, mocap_rate=180.0)
    version = Version(3, 1)
    data = multicast_receiver(cfg.mocap.data_port)
    client = Client(cfg.mocap.command_port)
    try:
        with service(cfg), publish_truth(bus_factory(), {"d1": truth()}):
            info = client.connect()
            assert (info.app_name, info.natnet_version, info.clock_frequency) == (
                "Motive",
                version,
                TICK_FREQUENCY,
            )
            assert (info.data_port, info.is_multicast, info.multicast_group) == (
                cfg.mocap.data_port,
                True,
                natnet.MULTICAST_GROUP,
            )
            models = natnet.decode_model_defs(
                client.ask(natnet.encode_request_model_defs(), MessageId.MODELDEF), version
            )
            assert models.rigid_body_names() == {1: "d1", 2: "d2"}
            rate = natnet.decode_response(client.ask(natnet.encode_request("FrameRate"), MessageId.RESPONSE))
            assert rate.float_value == 180.0

            wait_for(
                lambda: body(decode(receive(data, 1)[0][1], version), 1).tracking_valid,
                5.0,
                what="d1 tracked",
            )
            frames = receive(data, 200)
            echo_client, echo_ticks = natnet.decode_echo_response(
                client.ask(natnet.encode_echo_request(123456789), MessageId.ECHORESPONSE)
            )
            after = decode(receive(data, 1)[0][1], version)
    finally:
        data.close()
        client.close()

    decoded = [decode(raw, version) for _, raw in frames]
    numbers = [f.frame_number for f in decoded]
    # Frame numbers only increase (a busy machine may lose a datagram in the socket's buffer: counted, not
    # failed).  The rate by the frames' own stamps is exact (below); by the send and arrival times it is
    # 180 Hz ± 2 % on an idle machine. A busy one delays frames, in bursts the receiver drains at once, so
    # the arrival rate is only printed; asserted is that the emulator sends at 180 Hz by its own transmit
    # stamps and not at another of Motive's rates (120, 240, 360).
    assert all(b > a for a, b in itertools.pairwise(numbers)), "frame numbers increase"
    span = numbers[-1] - numbers[0]
    arrival_hz = span / (frames[-1][0] - frames[0][0])
    sent_hz = span * TICK_FREQUENCY / (decoded[-1].transmit - decoded[0].transmit)  # type: ignore[operator]
    print(
        f"\n{len(numbers)} of {span + 1} frames received; sent at {sent_hz:.2f} Hz, arrived at {arrival_hz:.2f} Hz"
    )
    assert 150.0 < sent_hz < 210.0, (sent_hz, arrival_hz)
    for f in decoded:
        assert f.timestamp == pytest.approx(f.frame_number / 180.0)
        mid, received, transmit = f.cam_mid_exposure, f.data_received, f.transmit
        assert mid is not None and received is not None and transmit is not None
        assert (received - mid) / TICK_FREQUENCY == pytest.approx(0.00457, abs=1e-6)
        assert 0.00081 <= (transmit - received) / TICK_FREQUENCY < 0.00081 + 0.002
        d1, d2 = body(f, 1), body(f, 2)
        assert d1.tracking_valid and close(d1.pos, Y_UP_P) and close(d1.quat_xyzw, Y_UP_Q)
        assert not d2.tracking_valid, "no truth for d2: streamed untracked"
    # The echo carries the server's tick clock: between the frames sent before and after it.
    assert echo_client == 123456789
    assert decoded[-1].transmit < echo_ticks < after.transmit  # type: ignore[operator]


def test_unicast_z_up_calibrated_pose_and_disconnect(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    calibration = "[calibration]\nyaw_deg = 90.0\noffset = [0.5, -0.25, 0.0]"
    cfg = with_mocap(arena_config(n_vehicles=1, extra=calibration, noise_m=0.0), up_axis="z", multicast=False)
    version = Version(4, 1)
    first, second = Client(cfg.mocap.command_port), Client(cfg.mocap.command_port)
    stats = bus_factory().subscribe(keys.stats("test", "sim-motive"), capacity=1)
    try:
        with service(cfg, natnet_version="4.1", rate=120.0), publish_truth(bus_factory(), {"d1": truth()}):
            info = first.connect()
            assert info.is_multicast is False and info.natnet_version == version
            second.connect()
            wait_for(
                lambda: body(decode(first.recv_frames(1)[0][1], version), 1).tracking_valid,
                5.0,
                what="tracked",
            )
            frames = [decode(raw, version) for _, raw in first.recv_frames(30)]
            assert len(second.recv_frames(30)) == 30, "every connected client gets the frames"
            wait_for(lambda: counts(stats).get("clients") == 2, 5.0, what="2 clients in the stats")
            first.sock.sendto(natnet.encode_disconnect(), first.server)
            # Frames already in flight may still arrive; then the socket stays silent while the second client
            # keeps receiving.
            quiet_since = time.monotonic()
            deadline = quiet_since + 3.0
            while time.monotonic() - quiet_since < 0.3:
                assert time.monotonic() < deadline, "frames still arrive after DISCONNECT"
                with contextlib.suppress(TimeoutError):
                    first.sock.recv(65535)
                    quiet_since = time.monotonic()
            assert len(second.recv_frames(10)) == 10
    finally:
        first.close()
        second.close()
    # Calibration inverse: Motive-NED = Rz(-90°)(p - offset) = (2.25, -0.5, -0.5); Z-up (x, -y, -z) gives
    # (2.25, 0.5, 0.5). The heading (90°) is the calibration's own rotation: the body is level and aligned.
    for f in frames:
        d1 = body(f, 1)
        assert (
            d1.tracking_valid
            and close(d1.pos, (2.25, 0.5, 0.5))
            and close(d1.quat_xyzw, (0.0, 0.0, 0.0, 1.0))
        )
        assert f.precision_secs is not None and abs(f.precision_secs - time.time()) < 30
        assert f.timestamp == pytest.approx(f.frame_number / 120.0)


def test_occlusion_dropout_and_stats(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus]
) -> None:
    cfg = arena_config(n_vehicles=2, noise_m=0.001, dropout=0.25, seed=7, mocap_rate=180.0)
    version = Version(3, 1)
    watcher = bus_factory()
    stats = watcher.subscribe(keys.stats("test", "sim-motive"), capacity=1)
    data = multicast_receiver(cfg.mocap.data_port)
    try:
        d2 = truth(p=(0.0, 0.0, -1.0), q=(1.0, 0.0, 0.0, 0.0))
        occlusion = sim_mocap.parse_occlusion("d1:0:0.6")
        with publish_truth(watcher, {"d1": truth(), "d2": d2}), service(cfg, occlusions=[occlusion]):
            frames = [decode(raw, version) for _, raw in receive(data, 240, timeout=10.0)]
            last = wait_for(lambda: (c := counts(stats)).get("frames", 0) > 200 and c, 5.0, what="stats")
    finally:
        data.close()
    numbers = [f.frame_number for f in frames]
    span = numbers[-1] - numbers[0] + 1
    assert 0.15 < 1.0 - len(frames) / span < 0.35, "about a quarter of the frames are dropped"
    # d1 is hidden for the first 0.6 s (108 frames at 180 Hz), then tracked with 1 mm noise.
    hidden = [f for f in frames if f.frame_number < 100]
    seen = [f for f in frames if f.frame_number > 130]
    assert hidden and seen
    assert not any(body(f, 1).tracking_valid for f in hidden)
    assert all(body(f, 1).tracking_valid for f in seen)
    assert all(body(f, 2).tracking_valid for f in seen)
    errors = [abs(a - b) for f in seen for a, b in zip(body(f, 1).pos, Y_UP_P, strict=True)]
    assert 0.0 < max(errors) < 0.006 and sum(errors) / len(errors) == pytest.approx(0.0008, rel=0.3)
    assert last["dropped"] > 0 and last["occluded"] > 0 and last["frames"] > 200


# ------------------------------------------------------------------------------------------------------------
# The server core: requests answered like Motive, model changes
# ------------------------------------------------------------------------------------------------------------


def test_server_requests_bitstream_echo_keepalive_and_models_changed() -> None:
    models = ModelDefs((RigidBodyDef("d1", 1),))
    server = NatNetServer(
        command_port=free_port(socket.SOCK_DGRAM),
        data_port=free_port(socket.SOCK_DGRAM),
        multicast=False,
        version="3.0",
        frame_rate=240.0,
        models=models,
    )
    client = Client(server.command_port)
    with server:
        assert (
            natnet.decode_server_info(
                client.ask(natnet.encode_discovery(), MessageId.SERVERINFO)
            ).is_multicast
            is False
        )
        assert server.clients == [], "discovery does not subscribe"
        info = client.connect()
        assert info.app_version == Version(2, 1) and info.natnet_version == Version(3, 0)
        assert [c.address for c in server.clients] == [client.sock.getsockname()]

        def answer(text: str) -> tuple[int, bytes]:
            for _ in range(25):
                client.sock.sendto(natnet.encode_request(text), client.server)
                with contextlib.suppress(TimeoutError):
                    message_id, payload = natnet.split_packet(client.sock.recv(65535))
                    if message_id != MessageId.FRAMEOFDATA:
                        return message_id, payload
            raise AssertionError(f"no answer to {text!r}")

        assert natnet.decode_response(answer("FrameRate")[1]).float_value == 240.0
        assert natnet.decode_response(answer("Bitstream")[1]).text == "3.0.0.0"
        assert natnet.decode_response(answer("AnalogSamplesPerMocapFrame")[1]).int_value == 0
        assert answer("TestRequest")[0] == MessageId.UNRECOGNIZED_REQUEST
        assert natnet.decode_response(answer("Bitstream,9.9")[1]).int_value == -1
        assert natnet.decode_response(answer("Bitstream,4.1")[1]).int_value == 0
        assert client.connect().natnet_version == Version(4, 1) and server.version == Version(4, 1)

        sent, ticks = natnet.decode_echo_response(
            client.ask(natnet.encode_echo_request(42), MessageId.ECHORESPONSE)
        )
        assert sent == 42 and abs(ticks - server.clock.now()) < TICK_FREQUENCY  # within a second

        frame = Frame(
            frame_number=7, rigid_bodies=(natnet.RigidBody(1, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)),)
        )
        assert server.send_frame(frame) == 1
        got = natnet.decode_frame(natnet.split_packet(client.recv_frames(1)[0][1])[1], Version(4, 1))
        assert got.frame_number == 7 and got.params & MODELS_CHANGED == 0
        polled = client.ask(natnet.encode_request_frame(), MessageId.FRAMEOFDATA)
        assert natnet.decode_frame(polled, Version(4, 1)).frame_number == 7

        # A model change: the next frames carry bit 0x02 and MODELDEF lists the new body.
        server.set_models(ModelDefs((RigidBodyDef("d1", 1), RigidBodyDef("d2", 2))))
        for n in range(8, 13):
            server.send_frame(dataclasses.replace(frame, frame_number=n))
        flags = [
            natnet.decode_frame(natnet.split_packet(raw)[1], Version(4, 1)).params & MODELS_CHANGED
            for _, raw in client.recv_frames(5)
        ]
        assert flags == [MODELS_CHANGED] * 3 + [0, 0]
        defs = natnet.decode_model_defs(
            client.ask(natnet.encode_request_model_defs(), MessageId.MODELDEF), Version(4, 1)
        )
        assert defs.rigid_body_names() == {1: "d1", 2: "d2"}

        # DISCONNECT unsubscribes; a KEEPALIVE from the same socket subscribes again (server restarts).
        client.sock.sendto(natnet.encode_disconnect(), client.server)
        wait_for(lambda: server.clients == [], 2.0, what="client gone")
        assert [c.address for c in server.clients_left] == [client.sock.getsockname()]
        client.sock.sendto(natnet.encode_keepalive(), client.server)
        wait_for(lambda: len(server.clients) == 1, 2.0, what="client back")
        assert server.counters.unrecognized == 1
    client.close()


def test_scene_latency_staleness_and_body_ids(arena_config: Callable[..., ArenaConfig]) -> None:
    scene = SimScene(camera_latency=0.004, software_latency=0.001, truth_timeout=0.5)
    scene.add_body("d1", 1)
    clock = TickClock()
    t = 10_000_000_000
    assert not body(scene.frame(1, 0.0, t, clock), 1).tracking_valid, "no truth yet"  # type: ignore[arg-type]
    # Two true poses: 6 ms and 2 ms before transmit. Mid-exposure is 5 ms before: the older one is imaged.
    scene.update("d1", (0.0, 0.0, -1.0), (1.0, 0.0, 0.0, 0.0), t_ns=t - 6_000_000)
    scene.update("d1", (5.0, 0.0, -1.0), (1.0, 0.0, 0.0, 0.0), t_ns=t - 2_000_000)
    frame = scene.frame(2, 0.0, t, clock)
    assert frame is not None and close(body(frame, 1).pos, (0.0, 1.0, 0.0))
    assert (
        frame.transmit is not None and frame.cam_mid_exposure is not None and frame.data_received is not None
    )
    assert (frame.transmit - frame.data_received, frame.data_received - frame.cam_mid_exposure) == (
        10_000,
        40_000,
    )
    late = scene.frame(3, 0.0, t + 600_000_000, clock)
    assert late is not None and not body(late, 1).tracking_valid, "a true pose older than 0.5 s"
    scene.update("d1", (5.0, 0.0, -1.0), (1.0, 0.0, 0.0, 0.0), ok=False, t_ns=t + 700_000_000)
    invalid = scene.frame(4, 0.0, t + 800_000_000, clock)
    assert invalid is not None and not body(invalid, 1).tracking_valid, "the truth itself says not ok"
    assert scene.counters.untracked == 3
    # Body ids: integer rigid bodies keep theirs (named after the vehicle), the others take index + 1 or
    # the next free id.
    cfg = arena_config(n_vehicles=3)
    vehicles = dict(cfg.vehicles)
    vehicles["d3"] = vehicles["d3"].replace(rigid_body=2)
    cfg = cfg.replace(vehicles=vehicles)
    assert rigid_bodies(cfg) == [("d1", "d1", 1), ("d2", "d2", 3), ("d3", "d3", 2)]
    assert rigid_bodies(cfg, ["d2"]) == [("d2", "d2", 3)]


def test_bad_input_raises_clear_errors(arena_config: Callable[..., ArenaConfig], tmp_path: Path) -> None:
    cfg = arena_config(n_vehicles=1)
    with pytest.raises(ConfigError, match="NatNet version must be one of"):
        sim_mocap.main(cfg, natnet_version="2.5")
    with pytest.raises(ConfigError, match="VEHICLE:START_S:DURATION_S"):
        sim_mocap.parse_occlusion("d1:soon")
    with pytest.raises(ConfigError, match="no vehicle 'd7'"):
        sim_mocap.main(cfg, occlusions=[("d7", 0.0, 1.0)])
    with pytest.raises(NatNetServerError, match="cannot be served"):
        NatNetServer(version="5.0")
    scene = SimScene()
    scene.add_body("d1", 1)
    with pytest.raises(NatNetServerError, match="already used by 'd1'"):
        scene.add_body("other", 1)
    with pytest.raises(NatNetServerError, match="cannot occlude 'd9'"):
        scene.occlude("d9", 1.0)
    empty = tmp_path / "empty.jsonl"
    empty.write_text("\n")
    with pytest.raises(NatNetServerError, match="no NatNet frames"):
        load_recording(empty)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        server = NatNetServer(command_port=taken.getsockname()[1])
        with pytest.raises(NatNetServerError, match="cannot bind the NatNet command socket"):
            server.start()


# ------------------------------------------------------------------------------------------------------------
# Replay
# ------------------------------------------------------------------------------------------------------------


def test_replay_jsonl_reproduces_frames_and_timing(arena_config: Callable[..., ArenaConfig]) -> None:
    cfg = arena_config(n_vehicles=2)
    path = DATA / "traffic_frames_decoded.jsonl"
    recorded = list(read_frames_jsonl(path))
    data = multicast_receiver(cfg.mocap.data_port)
    client = Client(cfg.mocap.command_port)
    try:
        with service(cfg, replay=path, natnet_version="3.0"):
            got = receive(data, 1)
            info = client.connect()
            models = client.ask(natnet.encode_request_model_defs(), MessageId.MODELDEF)
            got += receive(data, len(recorded) - 1, timeout=15.0)
    finally:
        data.close()
        client.close()
    assert info.natnet_version == Version(3, 0)
    assert info.clock_frequency == pytest.approx(3312787, rel=1e-4), "estimated from the ticks"
    assert natnet.decode_model_defs(models, Version(3, 0)).rigid_body_names() == {2: "d2"}, (
        "named by config id"
    )
    frames = [decode(raw, Version(3, 0)) for _, raw in got]
    for (_, want), have in zip(recorded, frames, strict=True):
        assert have.frame_number == want.frame_number and have.timestamp == want.timestamp
        assert (have.cam_mid_exposure, have.data_received, have.transmit) == (
            want.cam_mid_exposure,
            want.data_received,
            want.transmit,
        )
        assert have.rigid_bodies == tuple(dataclasses.replace(b, params=1) for b in want.rigid_bodies)
    # Timing: each frame leaves at its recorded offset from the first; a wake-up can only be late, so the
    # lateness is measured from the earliest frame relative to the schedule.
    offsets = [
        (t - got[0][0]) - (rec.receive_time - recorded[0].receive_time)
        for (t, _), rec in zip(got, recorded, strict=True)
    ]
    lateness = sorted(o - min(offsets) for o in offsets)
    median, p95 = lateness[len(lateness) // 2], lateness[int(len(lateness) * 0.95)]
    # Measured on an idle machine: median under 1.5 ms, p95 under 4 ms.  A busy machine delays wake-ups (the
    # tail above all, printed); the median stays within a bound that holds under load.
    print(f"\nreplay lateness: median {median * 1e3:.2f} ms, p95 {p95 * 1e3:.2f} ms")
    assert median < 0.02, f"lateness median {median * 1e3:.2f} ms, p95 {p95 * 1e3:.2f} ms"


@pytest.mark.parametrize("version", [None, "4.1"])
def test_replay_pcap_serves_recorded_server_and_frames(
    version: str | None, arena_config: Callable[..., ArenaConfig]
) -> None:
    cfg = arena_config(n_vehicles=1)
    path = DATA / "traffic.pcapng"
    captured = [
        d.payload for d in read_udp(path) if natnet.split_packet(d.payload)[0] == MessageId.FRAMEOFDATA
    ]
    data = multicast_receiver(cfg.mocap.data_port)
    client = Client(cfg.mocap.command_port)
    try:
        with service(cfg, replay=path, natnet_version=version, speed=4.0):
            got = receive(data, 1)
            info = client.connect()
            models = client.ask(natnet.encode_request_model_defs(), MessageId.MODELDEF)
            got += receive(data, len(captured) - 1, timeout=10.0)
    finally:
        data.close()
        client.close()
    served = Version.parse(version or "3.0")
    assert (info.app_name, info.app_version, info.natnet_version) == ("Motive", Version(2, 1), served)
    assert info.clock_frequency == 3312787 and info.data_port == cfg.mocap.data_port
    assert natnet.decode_model_defs(models, served).rigid_body_names() == {2: "RaceQuad"}
    if version is None:
        assert [raw for _, raw in got] == captured, "byte for byte"
    else:
        for raw, want in zip((raw for _, raw in got), captured, strict=True):
            have = natnet.decode_frame(natnet.split_packet(raw)[1], served, full=True)
            old = natnet.decode_frame(natnet.split_packet(want)[1], Version(3, 0), full=True)
            assert dataclasses.replace(have, precision_secs=None, precision_fraction=None) == old
    # Paced at 4x the recording's 4.31 s: never faster; a busy machine may only make it later.
    span = got[-1][0] - got[0][0]
    assert 4.3088 / 4.0 - 0.05 <= span < 3 * 4.3088 / 4.0, span


# ------------------------------------------------------------------------------------------------------------
# As a real process
# ------------------------------------------------------------------------------------------------------------


def test_runs_as_a_process_and_stops_on_sigterm(
    arena_config: Callable[..., ArenaConfig], bus_factory: Callable[[], Bus], processes: Callable[..., Proc]
) -> None:
    cfg = arena_config(n_vehicles=1, noise_m=0.0)
    data = multicast_receiver(cfg.mocap.data_port)
    argv = service_argv("sim_mocap", cfg.path, "--natnet-version", "4.0", "--occlude", "d1:0:0.2")
    proc = processes("sim_mocap", argv)
    try:
        with publish_truth(bus_factory(), {"d1": truth()}):

            def tracked() -> bool:
                frame = decode(receive(data, 1, timeout=20.0)[0][1], Version(4, 0))
                return body(frame, 1).tracking_valid and close(body(frame, 1).pos, Y_UP_P)

            wait_for(tracked, 30.0, what="the process streams d1 tracked")
        assert proc.stop(15.0, signal.SIGTERM) == 0, proc.tail()
    finally:
        data.close()
