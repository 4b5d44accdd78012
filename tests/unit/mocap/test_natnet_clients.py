"""The Motive emulator against independent NatNet clients, on real loopback sockets.

* libmotioncapture (PyPI ``motioncapture``, IMRCLab): it sends an empty CONNECT, reads SERVERINFO and MODELDEF
  as the next datagrams on its command socket (which it then closes), then listens on the data port
  SERVERINFO announces (on 0.0.0.0, joined to the group in multicast). In unicast Motive sends frames to the
  socket that sent CONNECT, not there, so libmotioncapture gets no frame in unicast, from Motive or from the
  emulator. It blocks forever when nothing comes, so it runs in a subprocess with a timeout.
* The NatNet SDK's Python client (PyPI ``natnetsdk``, NaturalPoint's PythonClient sample 4.1): a NatNet 4
  client. Its CONNECT is 271 bytes declaring NatNet 4.1; in unicast it reads frames on its command socket
  and sends a KEEPALIVE after each receive. Its threads never end (a blocking data socket), so it runs in a
  subprocess too, ended with ``os._exit``.

Each test has its own free ports. Also: SERVERINFO reaches every new unicast client before any frame; in
unicast, for NatNet 3.0, 3.1, 4.0 and 4.1 alike, frames go to the socket that sent CONNECT, from the data
port, and never to the data port of the client's address (docs/architecture.md, "NatNet unicast"); our
SERVERINFO and NatNet 3.0 frames decode in the independent clients like the real Motive 2.1 capture does.
"""

from __future__ import annotations

import contextlib
import io
import json
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from arena_common.mocap import natnet
from arena_common.mocap.natnet import Frame, MessageId, ModelDefs, RigidBody, RigidBodyDef, Version
from arena_common.sim.natnet_server import NatNetServer, TickClock
from tests.helpers import TESTS, free_port, wait_for

V3_DIR = TESTS / "data" / "natnet" / "motive-2.1-natnet-3.0"
GROUP = natnet.MULTICAST_GROUP
CHILD_TIMEOUT = 60.0  # a client that gets nothing blocks until killed

# Two bodies in Motive's frame: d1 level, d2 turned 120° about (1, 1, 1).
BODIES = (
    RigidBody(1, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 0.0002, True, 1),
    RigidBody(2, (-1.0, 0.5, 0.25), (0.5, 0.5, 0.5, 0.5), 0.0002, True, 1),
)
MODELS = ModelDefs((RigidBodyDef("d1", 1), RigidBodyDef("d2", 2)))
# What the clients report: libmotioncapture by name with (w, x, y, z), natnetsdk by id with (x, y, z, w).
EXPECT_BY_NAME = {"d1": [[1.0, 2.0, 3.0], [1.0, 0.0, 0.0, 0.0]], "d2": [[-1.0, 0.5, 0.25], [0.5] * 4]}
EXPECT_BY_ID = {"1": [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0]], "2": [[-1.0, 0.5, 0.25], [0.5] * 4]}


# ------------------------------------------------------------------------------------------------------------
# Helpers: a server streaming frames, the clients in subprocesses
# ------------------------------------------------------------------------------------------------------------


def make_server(*, multicast: bool, version: str = "4.1", **kwargs: Any) -> NatNetServer:
    """A server on 127.0.0.1 with its own free command and data ports."""
    return NatNetServer(
        command_port=free_port(socket.SOCK_DGRAM),
        data_port=free_port(socket.SOCK_DGRAM),
        multicast=multicast,
        version=version,
        models=kwargs.pop("models", MODELS),
        frame_rate=200.0,
        **kwargs,
    )


def body_frame(number: int) -> Frame:
    """Frame ``number`` of the two bodies, with tick stamps like Motive's."""
    ticks = 1_000_000 + number * 50_000
    return Frame(
        frame_number=number,
        rigid_bodies=BODIES,
        timestamp=number / 200.0,
        cam_mid_exposure=ticks,
        data_received=ticks + 45_700,
        transmit=ticks + 53_800,
        precision_secs=1_700_000_000,
        precision_fraction=0,
    )


@contextlib.contextmanager
def streaming(
    server: NatNetServer, frame: Callable[[int], Frame | bytes] = body_frame, period: float = 0.005
) -> Iterator[None]:
    """Send ``frame(n)`` for n = 1, 2, … every ``period`` seconds until the block ends."""
    stop = threading.Event()

    def run() -> None:
        number = 0
        while not stop.wait(period):
            number += 1
            item = frame(number)
            if isinstance(item, bytes):
                server.send_datagram(item)
            else:
                server.send_frame(item)

    thread = threading.Thread(target=run, name="frames", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=5.0)


def run_child(code: str, *args: object, timeout: float = CHILD_TIMEOUT) -> Any:
    """Run ``code`` in a Python subprocess and return the JSON after its ``RESULT`` line."""
    try:
        run = subprocess.run(
            [sys.executable, "-c", code, *map(str, args)],
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else exc.stdout or ""
        raise AssertionError(f"the client got nothing in {timeout} s; its output: {out[-1000:]}") from None
    line = next((x for x in run.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert run.returncode == 0 and line, run.stdout[-2000:] + run.stderr[-2000:]
    return json.loads(line[7:])


# libmotioncapture: argv = server address, command port, frames to read.
MOTIONCAPTURE = r"""
import json, sys, motioncapture
mc = motioncapture.connect("optitrack", {"hostname": sys.argv[1], "port_command": sys.argv[2],
                                         "interface_ip": "127.0.0.1"})
seen = {}
for _ in range(int(sys.argv[3])):
    mc.waitForNextFrame()
    for name, b in mc.rigidBodies.items():
        r = b.rotation
        seen[name] = [[float(v) for v in b.position], [r.w, r.x, r.y, r.z]]
print("RESULT " + json.dumps(seen))
"""

# natnetsdk: argv = local address, command port, data port, "multicast"/"unicast", frames to collect once the
# client knows the server's version. Each frame is listed with its bodies and whether the client knew
# the version when it finished decoding it (natnetsdk decodes multicast frames before SERVERINFO says
# their layout).
NATNETSDK = r"""
import json, os, sys, time
out = os.fdopen(os.dup(1), "w")
sys.stdout = open(os.devnull, "w")  # the client prints every frame
from natnetsdk.NatNetClient import NatNetClient
client = NatNetClient()
client.set_client_address(sys.argv[1])
client.set_server_address("127.0.0.1")
client.command_port, client.data_port = int(sys.argv[2]), int(sys.argv[3])
client.set_use_multicast(sys.argv[4] == "multicast")
frames, bodies = [], {}
def on_body(i, p, q):
    bodies[str(i)] = [list(p), list(q)]
def on_frame(d):
    frames.append([d["frame_number"], dict(bodies), client.get_application_name() != "Not Set"])
    bodies.clear()
client.rigid_body_listener, client.new_frame_listener = on_body, on_frame
started = client.run()
while started and sum(known for _, _, known in list(frames)) < int(sys.argv[5]):
    time.sleep(0.01)
result = {"frames": frames[:200], "app": client.get_application_name(),
          "app_version": client.get_server_version(), "natnet": client.get_nat_net_version_server()}
out.write("RESULT " + json.dumps(result) + "\n")
out.flush()
os._exit(0)
"""


def close(a: list[list[float]], b: list[list[float]], tol: float = 1e-6) -> bool:
    return all(abs(x - y) <= tol for u, v in zip(a, b, strict=True) for x, y in zip(u, v, strict=True))


@contextlib.contextmanager
def loopback_membership(group: str) -> Iterator[None]:
    """The group joined on the loopback interface while the block runs (see the natnetsdk test)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(
            socket.IPPROTO_IP,
            socket.IP_ADD_MEMBERSHIP,
            socket.inet_aton(group) + socket.inet_aton("127.0.0.1"),
        )
        yield
    finally:
        sock.close()


def default_interface_can_join(group: str) -> bool:
    """Whether a multicast join on INADDR_ANY works here (it needs a route for the group)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.setsockopt(
                socket.IPPROTO_IP,
                socket.IP_ADD_MEMBERSHIP,
                socket.inet_aton(group) + socket.inet_aton("0.0.0.0"),
            )
        except OSError:
            return False
    return True


# ------------------------------------------------------------------------------------------------------------
# SERVERINFO first, and each generation's frames where it reads them
# ------------------------------------------------------------------------------------------------------------


def test_serverinfo_precedes_every_frame_to_a_new_unicast_client() -> None:
    """300 new clients while frames stream at 2 kHz: the first datagram each receives is SERVERINFO.

    A third subscribe with the real NatNet 3.0 library's CONNECT (captured), a third with a NatNet 4.1 one,
    a third with a KEEPALIVE from an unknown address (a client that outlived a server restart). Each then
    receives frames on that same socket, and leaves with DISCONNECT.
    """
    server = make_server(multicast=False)
    connects = 300
    firsts: list[int] = []
    hellos = (
        (V3_DIR / "connect_packet_v3.bin").read_bytes(),
        natnet.encode_connect(natnet_version=Version(4, 1)),
        natnet.encode_keepalive(),
    )
    with server, streaming(server, period=0.0005):
        for i in range(connects):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
                sock.bind(("127.0.0.1", 0))
                sock.settimeout(5.0)
                hello = hellos[i % 3]
                sock.sendto(hello, server.command_address)
                firsts.append(natnet.split_packet(sock.recv(65535))[0])
                while natnet.split_packet(sock.recv(65535))[0] != MessageId.FRAMEOFDATA:
                    pass  # then frames come (a timeout here fails the test)
                sock.sendto(natnet.encode_disconnect(), server.command_address)
        # Each left with DISCONNECT, or was forgotten first when the kernel reported its closed port.
        left = server.counters
        wait_for(lambda: left.disconnects + left.gone == connects, 5.0, what="every client gone")
    assert firsts == [MessageId.SERVERINFO] * connects
    assert server.counters.connects == connects and server.clients == []


# What the clients that subscribe send: the real NatNet 3.0 library's CONNECT (captured from Motive 2.1's
# traffic), the same declaring NatNet 3.1, libmotioncapture's empty one, and a NatNet 4.1 one.
HELLOS = {
    "natnetlib-3.0": (V3_DIR / "connect_packet_v3.bin").read_bytes(),
    "natnetlib-3.1": natnet.encode_connect(natnet_version=Version(3, 1)),
    "empty": natnet.encode_packet(MessageId.CONNECT, b""),
    "natnet-4.1": natnet.encode_connect(natnet_version=Version(4, 1)),
}


@pytest.mark.parametrize("version", ["3.0", "3.1", "4.0", "4.1"])
def test_unicast_frames_go_to_the_socket_that_sent_connect(version: str) -> None:
    """Motive (2.x: NatNet 3.0, 3.1; 3.x: NatNet 4.0, 4.1) sends unicast frames to the address the CONNECT came
    from, from its data port, and nowhere else (docs/architecture.md): every client, whatever its CONNECT, gets them on
    the socket that sent it, and a listener on the data port of the clients' address (where libmotioncapture
    waits) gets none. The frames decode as the served version.
    """
    server = make_server(multicast=False, version=version)
    clients = {name: socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for name in HELLOS}
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    got: dict[str, list[tuple[bytes, tuple[str, int]]]] = {name: [] for name in HELLOS}
    try:
        for sock in clients.values():
            sock.bind(("127.0.0.1", 0))
            sock.settimeout(5.0)
        addresses = [sock.getsockname() for sock in clients.values()]
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("0.0.0.0", server.data_port))
        with server, streaming(server):
            for name, sock in clients.items():
                sock.sendto(HELLOS[name], server.command_address)
            for name, sock in clients.items():
                while len(got[name]) < 5:  # a timeout here: no frame where the client reads them
                    data, source = sock.recvfrom(65535)
                    got[name].append((data, source))
            routes = {c.address: c.frames_to for c in server.clients}
            listener.settimeout(0.3)  # 60 more frames meanwhile
            with pytest.raises(TimeoutError):
                listener.recvfrom(65535)
    finally:
        for sock in (*clients.values(), listener):
            sock.close()
    assert routes == {address: address for address in addresses}
    served = Version.parse(version)
    for name, datagrams in got.items():
        (first, _), *rest = datagrams
        assert natnet.split_packet(first)[0] == MessageId.SERVERINFO, name
        assert natnet.decode_server_info(natnet.split_packet(first)[1]).natnet_version == served
        for data, source in rest:
            message_id, payload = natnet.split_packet(data)
            assert message_id == MessageId.FRAMEOFDATA, name
            assert source == ("127.0.0.1", server.data_port), "frames come from the data port"
            bodies = natnet.decode_frame(payload, served).rigid_bodies
            assert [(b.id, b.pos, b.quat_xyzw) for b in bodies] == [
                (b.id, b.pos, b.quat_xyzw) for b in BODIES
            ]


def test_unicast_replies_on_the_command_socket_and_closed_clients_forgotten() -> None:
    """Replies (SERVERINFO, MODELDEF) come from the command port, frames from the data port, both to the
    socket that sent CONNECT; a client whose port closes without DISCONNECT is forgotten."""
    server = make_server(multicast=False, version="3.1")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for s in (sock, other):
            s.bind(("127.0.0.1", 0))
            s.settimeout(5.0)
        with server, streaming(server):
            for s in (sock, other):
                s.sendto(HELLOS["natnetlib-3.0"], server.command_address)
                assert natnet.split_packet(s.recv(65535))[0] == MessageId.SERVERINFO
            sock.sendto(natnet.encode_request_model_defs(), server.command_address)
            sources: dict[int, tuple[str, int]] = {}
            while not {MessageId.MODELDEF, MessageId.FRAMEOFDATA} <= sources.keys():
                data, source = sock.recvfrom(65535)
                sources[natnet.split_packet(data)[0]] = source
            assert sources[MessageId.MODELDEF] == server.command_address
            assert sources[MessageId.FRAMEOFDATA] == ("127.0.0.1", server.data_port)
            gone = sock.getsockname()
            sock.close()  # no DISCONNECT: the kernel reports the closed port, the server forgets the client
            wait_for(lambda: server.counters.gone == 1, 5.0, what="the closed client forgotten")
            assert [c.address for c in server.clients] == [other.getsockname()]
            assert [(c.address, c.app_name) for c in server.clients_left] == [(gone, "NatNetLib")]
            assert natnet.split_packet(other.recv(65535))[0] == MessageId.FRAMEOFDATA
    finally:
        sock.close()
        other.close()


# ------------------------------------------------------------------------------------------------------------
# libmotioncapture
# ------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("version", ["3.0", "4.1"])
def test_libmotioncapture_receives_the_bodies(version: str) -> None:
    pytest.importorskip("motioncapture")
    server = make_server(multicast=True, version=version)
    with server, streaming(server):
        seen = run_child(MOTIONCAPTURE, "127.0.0.1", server.command_port, 40)
        clients = server.clients
    assert seen.keys() == EXPECT_BY_NAME.keys()
    assert all(close(seen[name], EXPECT_BY_NAME[name]) for name in seen)
    assert [(c.app_name, c.natnet_version) for c in clients] == [("", None)], "an empty CONNECT"


@pytest.mark.parametrize("version", ["3.0", "4.1"])
def test_libmotioncapture_gets_no_frame_in_unicast(version: str) -> None:
    """As from Motive: libmotioncapture connects (SERVERINFO, MODELDEF on its command socket), but the frames
    go to that command socket, which it has closed, and it waits on the data port, where none come."""
    pytest.importorskip("motioncapture")
    server = make_server(multicast=False, version=version)
    with server, streaming(server), pytest.raises(AssertionError, match="got nothing"):
        run_child(MOTIONCAPTURE, "127.0.0.1", server.command_port, 1, timeout=3.0)
    requests = server.counters
    assert (requests.connects, requests.gone) == (1, 1), "frames sent to its closed command socket"


# ------------------------------------------------------------------------------------------------------------
# The NatNet SDK's Python client
# ------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("version", ["3.0", "4.1"])
@pytest.mark.parametrize("mode", ["multicast", "unicast"])
def test_natnetsdk_receives_the_bodies(mode: str, version: str) -> None:
    """In unicast every frame the client decodes is right: SERVERINFO, which gives the layout, comes first on
    the socket it reads everything on. In multicast it decodes frames before it knows the server's version
    (garbage then); once it knows, every frame is right.

    In multicast the client must be given 0.0.0.0 on Linux: it binds its data socket to its local address,
    and a socket bound to 127.0.0.1 never receives group datagrams. It then joins the group on the default
    interface, so the test joins it on the loopback interface, where the emulator sends."""
    pytest.importorskip("natnetsdk")
    multicast = mode == "multicast"
    if multicast and not default_interface_can_join(GROUP):
        pytest.skip("no route for multicast: the NatNet SDK client cannot join the group on INADDR_ANY")
    server = make_server(multicast=multicast, version=version)
    local = "0.0.0.0" if multicast else "127.0.0.1"
    membership = loopback_membership(GROUP) if multicast else contextlib.nullcontext()
    with server, streaming(server), membership:
        got = run_child(NATNETSDK, local, server.command_port, server.data_port, mode, 20)
        # Once the child has exited, a frame to its closed port makes the server forget it (unicast).
        clients = server.clients_left + server.clients
    assert (got["app"], got["app_version"][:2], got["natnet"][:2]) == (
        "Motive",
        list(server.server_info().app_version.to_bytes()[:2]),
        [int(x) for x in version.split(".")],
    )
    numbers = [number for number, _, _ in got["frames"]]
    assert numbers == sorted(numbers)
    known = [bodies for _, bodies, knew_version in got["frames"] if knew_version]
    assert len(known) >= 20
    if multicast:
        # Frames decoded before SERVERINFO are garbage; one whose decoding began before may end after it.
        known = known[1:]
    else:
        assert all(knew_version for _, _, knew_version in got["frames"]), "SERVERINFO came first"
        assert clients[0].frames_to == clients[0].address and clients[0].keeps_alive
    for bodies in known:
        assert bodies.keys() == EXPECT_BY_ID.keys()
        assert all(close(bodies[i], EXPECT_BY_ID[i]) for i in bodies)
    assert [c.natnet_version for c in clients] == [Version(4, 1)]


# ------------------------------------------------------------------------------------------------------------
# The emulator against the real Motive 2.1 capture (NatNet 3.0)
# ------------------------------------------------------------------------------------------------------------

CAPTURE_BODY = ([0.1744466, 1.4471314, -0.7343040], [-0.05459423, 0.5099482, 0.04370357, -0.8573577])


def capture_server(*, multicast: bool) -> NatNetServer:
    """The emulator configured as the captured Motive: 2.1, NatNet 3.0, its clock, its model definitions."""
    _, modeldef = natnet.split_packet((V3_DIR / "modeldef_packet_v3.bin").read_bytes())
    return make_server(
        multicast=multicast,
        version="3.0",
        app_version=Version(2, 1),
        clock=TickClock(3_312_787),
        models=natnet.decode_model_defs(modeldef, Version(3)),
    )


def emulated_frame(real: bytes) -> bytes:
    """The capture's frame as the emulator builds frames: its rigid body and timing, nothing else."""
    f = natnet.decode_frame(natnet.split_packet(real)[1], Version(3))
    ours = Frame(
        frame_number=f.frame_number,
        rigid_bodies=f.rigid_bodies,
        timestamp=f.timestamp,
        cam_mid_exposure=f.cam_mid_exposure,
        data_received=f.data_received,
        transmit=f.transmit,
        params=f.params,
    )
    return natnet.encode_frame(ours, Version(3))


def natnetsdk_decode(*datagrams: bytes) -> tuple[tuple[object, ...], list[Any], str]:
    """What the NatNet SDK's Python client makes of ``datagrams`` (server info, listener calls, its print)."""
    module = pytest.importorskip("natnetsdk.NatNetClient")
    client = module.NatNetClient()
    calls: list[Any] = []
    client.rigid_body_listener = lambda i, p, q: calls.append(("body", i, list(p), list(q)))
    client.new_frame_listener = lambda d: calls.append(("frame", dict(d)))
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        for datagram in datagrams:
            client._NatNetClient__process_message(datagram, print_level=1)
    info = (client.get_application_name(), client.get_server_version(), client.get_nat_net_version_server())
    return info, calls, printed.getvalue()


def test_capture_and_emulator_decode_alike_in_natnetsdk() -> None:
    """The capture's SERVERINFO and frame, and the emulator's, through the NatNet SDK's own decoder."""
    real_info = (V3_DIR / "serverinfo_packet_v3.bin").read_bytes()
    real_frame = (V3_DIR / "mocapframe_packet_v3.bin").read_bytes()
    our_info = natnet.encode_server_info(capture_server(multicast=True).server_info())
    assert our_info != real_info, "the capture has garbage after the name's NUL"
    real = natnetsdk_decode(real_info, real_frame)
    ours = natnetsdk_decode(our_info, emulated_frame(real_frame))
    assert real[0] == ours[0] == ("Motive", [2, 1, 0, 0], [3, 0, 0, 0])
    bodies = [c for c in real[1] if c[0] == "body"]
    assert bodies == [c for c in ours[1] if c[0] == "body"]
    assert len(bodies) == 1 and bodies[0][1] == 2 and close(list(bodies[0][2:]), list(CAPTURE_BODY), 1e-7)
    (real_frame_call,) = [c[1] for c in real[1] if c[0] == "frame"]
    (our_frame_call,) = [c[1] for c in ours[1] if c[0] == "frame"]
    markers = (
        "marker_set_count",
        "unlabeled_markers_count",
        "labeled_marker_count",
    )  # the emulator sends none
    assert {k: v for k, v in real_frame_call.items() if k not in markers} == {
        k: v for k, v in our_frame_call.items() if k not in markers
    }
    assert real_frame_call["frame_number"] == 162734 and real_frame_call["rigid_body_count"] == 1
    assert real_frame_call["timestamp"] == pytest.approx(1356.1167, abs=1e-4)
    # The whole printed decode (rigid body, tracking, error, the three tick stamps) but the labeled markers.
    assert without_labeled_markers(real[2]) == without_labeled_markers(ours[2])
    assert "Tracking Valid: True" in ours[2] and "Transmit timestamp             : 1416497748722" in ours[2]


def without_labeled_markers(printed: str) -> str:
    """natnetsdk's printed frame without its labeled-marker section."""
    head, _, rest = printed.partition("  Labeled Marker Count:")
    return head + rest[rest.index("  Force Plate Count:") :]


@pytest.mark.parametrize("source", ["capture", "emulator"])
def test_capture_and_emulator_decode_alike_in_libmotioncapture(source: str) -> None:
    """The emulator serving the capture's Motive (its SERVERINFO fields and MODELDEF, multicast like the
    capture), with the captured frame as recorded or as the emulator builds it: libmotioncapture reads
    RaceQuad the same."""
    pytest.importorskip("motioncapture")
    real = (V3_DIR / "mocapframe_packet_v3.bin").read_bytes()
    datagram = real if source == "capture" else emulated_frame(real)
    server = capture_server(multicast=True)
    with server, streaming(server, lambda _: datagram):
        seen = run_child(MOTIONCAPTURE, "127.0.0.1", server.command_port, 20)
    position, (qx, qy, qz, qw) = CAPTURE_BODY
    assert list(seen) == ["RaceQuad"]
    assert close(seen["RaceQuad"], [position, [qw, qx, qy, qz]], 1e-6)
